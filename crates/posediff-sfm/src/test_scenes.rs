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
                Point { xyz, observations }
            })
            .collect();
        (cameras, points)
    }
}
