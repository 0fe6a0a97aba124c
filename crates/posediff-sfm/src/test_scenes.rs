//! Exact scenes for the adjustments' unit tests: cameras on a ring around a cloud of points,
//! each point with its exact observations through a lens.

use nalgebra::{Rotation3, Vector3};

use crate::bundle::{LensCoefficients, LensKind, Point, project_lens};
use crate::camera::CameraPose;
use crate::tracks::Observation;

/// A ring: `cameras` looking at the origin from `4` units, `step` radians apart, their height
/// `lift · cos a`; `points` drawn uniformly in the box `±extent` (a fixed LCG from `seed`).
pub(crate) struct Ring {
    pub cameras: usize,
    pub step: f64,
    pub lift: f64,
    pub points: usize,
    pub extent: [f64; 3],
    pub seed: u64,
}

impl Ring {
    /// The cameras and the points, image `i` seen with focal `focal(i)`, principal point
    /// `principal` and `lens`.
    pub fn scene(
        &self,
        focal: &dyn Fn(usize) -> f64,
        principal: [f64; 2],
        lens: (LensKind, LensCoefficients),
    ) -> (Vec<Option<CameraPose>>, Vec<Point>) {
        let cameras: Vec<Option<CameraPose>> = (0..self.cameras)
            .map(|i| {
                let a = i as f64 * self.step;
                let center = Vector3::new(4.0 * a.sin(), self.lift * a.cos(), -4.0 * a.cos());
                Some(CameraPose {
                    rotation: Rotation3::look_at_lh(&(-center), &Vector3::y()),
                    center,
                })
            })
            .collect();
        let mut state = self.seed;
        let mut next = || {
            state = state
                .wrapping_mul(6364136223846793005)
                .wrapping_add(1442695040888963407);
            (state >> 11) as f64 / (1u64 << 53) as f64 * 2.0 - 1.0
        };
        let [ex, ey, ez] = self.extent;
        let points = (0..self.points)
            .map(|_| {
                let xyz = Vector3::new(ex * next(), ey * next(), ez * next());
                let observations = cameras
                    .iter()
                    .enumerate()
                    .filter_map(|(image, c)| {
                        let (uv, _) =
                            project_lens(c.as_ref()?, focal(image), principal, lens, &xyz)?;
                        Some(Observation {
                            image,
                            keypoint: 0,
                            xy: uv,
                        })
                    })
                    .collect();
                Point {
                    xyz,
                    observations,
                    alone: Vec::new(),
                }
            })
            .collect();
        (cameras, points)
    }
}

#[cfg(test)]
mod tests {
    #![allow(clippy::unwrap_used)]
    use super::*;
    use crate::bundle::{BundleOptions, IterativeSchurOptions, LensKind, PINHOLE, adjust_lens};
    use crate::intrinsics::ImageIntrinsics;

    /// The iterative solver of the reduced system against the sparse Cholesky, on a ring of 12
    /// cameras in two groups with a focal and two radial coefficients each (every kind of
    /// block): the first step and the converged adjustment agree, and both reach the truth.
    #[test]
    fn the_iterative_reduced_solver_agrees_with_the_cholesky() {
        let ring = Ring {
            cameras: 12,
            step: 0.25,
            lift: 0.5,
            points: 300,
            extent: [1.2, 1.0, 1.2],
            seed: 5,
        };
        let focal = |i: usize| if i.is_multiple_of(2) { 600.0 } else { 780.0 };
        let truth_k = [-0.08, 0.02, 0.0, 0.0];
        let (truth, points) = ring.scene(&focal, [319.5, 239.5], (LensKind::Brown, truth_k));
        let mut intrinsics = ImageIntrinsics::new(vec![[319.5, 239.5]; 12], vec![640.0; 12]);
        intrinsics.group = (0..12).map(|i| i % 2).collect();
        // Cameras moved off the truth (not the reference, image 0).
        let start: Vec<Option<CameraPose>> = truth
            .iter()
            .enumerate()
            .map(|(i, c)| {
                let c = c.unwrap();
                let s = if i == 0 { 0.0 } else { 1.0 };
                let d = [0.01, -0.008, 0.006, 0.02, -0.03, 0.01].map(|v| v * s * (i % 3) as f64);
                Some(c.moved(&d))
            })
            .collect();
        let run = |iterative: Option<IterativeSchurOptions>, max_iterations: usize| {
            let options = BundleOptions {
                max_error_px: 1e3,
                tolerance: 1e-14,
                max_iterations,
                iterative,
                ..BundleOptions::default()
            };
            let mut cameras = start.clone();
            let (mut factors, mut ks) = (vec![0.9, 1.1], vec![PINHOLE; 2]);
            let (points, report) = adjust_lens(
                points.clone(),
                &intrinsics,
                &mut cameras,
                (&mut factors, &mut ks, &[2, 2]),
                LensKind::Brown,
                0,
                &options,
            )
            .unwrap();
            (cameras, factors, ks, points, report)
        };
        let iterative = IterativeSchurOptions {
            min_cameras: 0,
            tolerance: 1e-12,
            max_iterations: 1000,
        };
        for max_iterations in [1, 100] {
            let (ca, fa, ka, pa, ra) = run(None, max_iterations);
            let (cb, fb, kb, pb, rb) = run(Some(iterative), max_iterations);
            assert_eq!(ra.iterations, rb.iterations, "{ra:?} {rb:?}");
            for (a, b) in ca.iter().zip(&cb) {
                let (a, b) = (a.unwrap(), b.unwrap());
                assert!((a.center - b.center).norm() < 1e-8, "{a:?} {b:?}");
                // (Not `angle_to`: its acos is only good to ~1e-8 near zero.)
                let turn = (a.rotation.matrix() - b.rotation.matrix()).norm();
                assert!(turn < 1e-8, "{a:?} {b:?}");
            }
            for (a, b) in fa.iter().zip(&fb) {
                assert!((a / b - 1.0).abs() < 1e-9, "{fa:?} {fb:?}");
            }
            for (a, b) in ka.iter().zip(&kb) {
                assert!((a[0] - b[0]).abs() < 1e-9 && (a[1] - b[1]).abs() < 1e-9);
            }
            for (a, b) in pa.iter().zip(&pb) {
                assert!((a.xyz - b.xyz).norm() < 1e-8);
            }
            if max_iterations == 1 {
                // One step from a wrong start: far from the truth still.
                assert!(ra.rms_after_px > 1e-3, "{ra:?}");
            } else {
                assert!(rb.rms_before_px > 10.0 && rb.rms_after_px < 1e-6, "{rb:?}");
                for (g, k) in kb.iter().enumerate() {
                    assert!((k[0] - truth_k[0]).abs() < 1e-6, "group {g}: {k:?}");
                }
            }
        }
    }
}
