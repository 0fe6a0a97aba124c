//! The hybrid of the paper's future work (`posediff estimate --weights W --refine bundle`):
//! cameras from elsewhere (PoseDiffusion after GGS) refined by this crate's Sampson refinement
//! and bundle adjustment, with tracks built from the matches.

use posediff_geometry::{Camera, Intrinsics, PairMatches, Pose};

use crate::bundle::{BundleOptions, bundle_adjust};
use crate::error::{Result, SfmError};
use crate::sampson_refine::{SampsonRefineOptions, refine_sampson};
use crate::tracks::build_tracks;
use crate::{CameraPose, ImageIntrinsics};

/// The focal factor of cameras given from elsewhere in `layout`'s terms: the mean over the
/// given cameras of `(f_x + f_y) / 2 / s_i` (`NaN` when none is given).
pub fn given_focal_factor(cameras: &[Option<Camera>], layout: &ImageIntrinsics) -> f64 {
    let given: Vec<f64> = cameras
        .iter()
        .zip(&layout.scale)
        .filter_map(|(c, s)| c.map(|c| 0.5 * (c.intrinsics.fx() + c.intrinsics.fy()) / s))
        .collect();
    given.iter().sum::<f64>() / given.len() as f64
}

/// Cameras given from elsewhere (`posediff estimate --init cameras.json`) refined on the
/// matches by the Sampson refinement alone, to convergence: the poses in place (images
/// without a camera stay `None`), the shared focal factor `phi` with them unless
/// `options.refine_focal` is off, camera `reference` holding the gauge. Each refined camera's
/// intrinsics become `layout`'s at the refined `phi`, or `known[i]` where the intrinsics are
/// known per image.
///
/// # Errors
/// As [`refine_sampson`]; a focal that makes no valid intrinsics.
pub fn sampson_refine_cameras(
    cameras: &mut [Option<Camera>],
    pairs: &[PairMatches],
    (layout, phi, known): (&ImageIntrinsics, &mut f64, Option<&[Intrinsics]>),
    reference: usize,
    options: &SampsonRefineOptions,
) -> Result<crate::sampson_refine::SampsonRefineReport> {
    let mut poses: Vec<Option<CameraPose>> = cameras
        .iter()
        .map(|c| c.as_ref().map(CameraPose::of_camera))
        .collect();
    let refs: Vec<&PairMatches> = pairs.iter().collect();
    let report = refine_sampson(&refs, layout, &mut poses, phi, reference, options)?;
    for (i, (camera, pose)) in cameras.iter_mut().zip(&poses).enumerate() {
        if let (Some(camera), Some(pose)) = (camera.as_mut(), pose) {
            camera.cam_from_world = Pose::new(*pose.rotation.matrix(), pose.translation());
            camera.intrinsics = match known {
                Some(k) => k[i],
                None => layout.intrinsics(*phi, i)?,
            };
        }
    }
    Ok(report)
}

/// What [`bundle_refine_cameras`] did (run.json).
#[derive(Debug, Clone, PartialEq)]
#[cfg_attr(feature = "serde", derive(serde::Serialize))]
pub struct BundleRefinement {
    /// Tracks built from the matches.
    pub tracks: usize,
    /// Points adjusted.
    pub points: usize,
    /// Their observations.
    pub observations: usize,
    /// RMS reprojection error at the end, px.
    pub rms_px: f64,
    /// Accepted steps.
    pub iterations: usize,
    /// Why it stopped.
    pub termination: String,
    /// Accepted steps of the Sampson refinement before.
    pub sampson_iterations: usize,
    /// Why it stopped.
    pub sampson_termination: String,
    /// The factor applied to every focal (1 when the intrinsics are known).
    pub focal_factor: f64,
}

/// The hybrid of the paper's future work: cameras from elsewhere (PoseDiffusion after GGS)
/// refined by the mapper: the Sampson refinement to convergence, then the bundle adjustment
/// with tracks built from `pairs`. Camera 0 is
/// held fixed and the scene keeps its scale (mean distance of the centres from camera 0);
/// unless `known_intrinsics`, one factor on every camera's focal is refined with them.
///
/// Non-square pixels are adjusted by their mean focal (the factor applies to both).
///
/// # Errors
/// Fewer than two cameras (`InvalidInput`), malformed pairs, a degenerate adjustment.
pub fn bundle_refine_cameras(
    cameras: &mut [Camera],
    pairs: &[PairMatches],
    known_intrinsics: bool,
    (sampson, bundle): (&SampsonRefineOptions, &BundleOptions),
) -> Result<BundleRefinement> {
    if cameras.len() < 2 {
        return Err(SfmError::InvalidInput(format!(
            "the bundle refinement needs at least 2 cameras, got {}",
            cameras.len()
        )));
    }
    let layout =
        ImageIntrinsics::from_known(&cameras.iter().map(|c| c.intrinsics).collect::<Vec<_>>());
    let mut poses: Vec<Option<CameraPose>> = cameras
        .iter()
        .map(|c| Some(CameraPose::of_camera(c)))
        .collect();
    let spread = |p: &[Option<CameraPose>]| -> f64 {
        let origin = p[0].map_or(nalgebra::Vector3::zeros(), |c| c.center);
        p.iter()
            .flatten()
            .map(|c| (c.center - origin).norm())
            .sum::<f64>()
            / p.len() as f64
    };
    let scale_before = spread(&poses);
    // The Sampson refinement first (its basin is wide: a few degrees off is fine), then the
    // bundle adjustment, whose points are triangulated from the refined cameras.
    let mut phi = 1.0;
    let refs: Vec<&PairMatches> = pairs.iter().filter(|p| !p.is_empty()).collect();
    let sampson = SampsonRefineOptions {
        refine_focal: !known_intrinsics,
        ..*sampson
    };
    let first = refine_sampson(&refs, &layout, &mut poses, &mut phi, 0, &sampson)?;
    let (tracks, track_report) = build_tracks(cameras.len(), pairs)?;
    let options = BundleOptions {
        refine_focal: !known_intrinsics,
        ..*bundle
    };
    let (_, report) = bundle_adjust(
        &tracks,
        &layout,
        &mut poses,
        std::slice::from_mut(&mut phi),
        0,
        &options,
    )?;
    let scale_after = spread(&poses);
    let rescale = if scale_after > 0.0 && scale_before > 0.0 {
        scale_before / scale_after
    } else {
        1.0
    };
    let origin = poses[0].map_or(nalgebra::Vector3::zeros(), |c| c.center);
    for (c, p) in cameras.iter_mut().zip(&poses) {
        let Some(p) = p else { continue };
        let center = origin + (p.center - origin) * rescale;
        let r = *p.rotation.matrix();
        c.cam_from_world = Pose::from_rotation_centre(r, center);
        if !known_intrinsics {
            let k = c.intrinsics;
            c.intrinsics = Intrinsics::new(k.fx() * phi, k.fy() * phi, k.cx(), k.cy())?;
        }
    }
    Ok(BundleRefinement {
        tracks: track_report.tracks,
        points: report.points,
        observations: report.observations,
        rms_px: report.rms_px,
        iterations: report.iterations,
        termination: report.termination.as_str().into(),
        sampson_iterations: first.iterations,
        sampson_termination: first.termination.as_str().into(),
        focal_factor: phi,
    })
}

#[cfg(test)]
mod tests {
    #![allow(clippy::unwrap_used)]
    use posediff_geometry::ImageSize;

    use super::*;
    use crate::bundle::{LensKind, PINHOLE};
    use crate::test_scenes::Ring;

    const FOCAL: f64 = 500.0;
    const PRINCIPAL: [f64; 2] = [320.0, 240.0];

    /// Six cameras on a ring, exact matches of every pair, and the cameras as given.
    fn scene() -> (Vec<Camera>, Vec<PairMatches>) {
        let ring = Ring {
            cameras: 6,
            step: 0.25,
            lift: 0.6,
            points: 300,
            extent: [1.0, 1.0, 1.0],
            seed: 5,
        };
        let (poses, points) = ring.scene(&|_| FOCAL, PRINCIPAL, (LensKind::Brown, PINHOLE));
        let k = Intrinsics::new(FOCAL, FOCAL, PRINCIPAL[0], PRINCIPAL[1]).unwrap();
        let size = ImageSize::new(640, 480).unwrap();
        let cameras = poses
            .iter()
            .map(|p| {
                let p = p.unwrap();
                Camera::new(k, Pose::new(*p.rotation.matrix(), p.translation()), size)
            })
            .collect();
        let mut pairs = Vec::new();
        for a in 0..6 {
            for b in a + 1..6 {
                let mut m = PairMatches::placeholder(a, b, 0);
                for (id, point) in points.iter().enumerate() {
                    let seen = |i| point.observations.iter().find(|o| o.image == i);
                    if let (Some(oa), Some(ob)) = (seen(a), seen(b)) {
                        m.kp1.push(oa.xy);
                        m.kp2.push(ob.xy);
                        m.idx1.push(id as u32);
                        m.idx2.push(id as u32);
                    }
                }
                pairs.push(m);
            }
        }
        (cameras, pairs)
    }

    /// The largest angle between two cameras' relative rotations, estimated and true, degrees.
    fn worst_relative_rotation(est: &[Option<Camera>], truth: &[Camera]) -> f64 {
        let mut worst = 0f64;
        for a in 0..truth.len() {
            for b in a + 1..truth.len() {
                let (Some(ea), Some(eb)) = (est[a], est[b]) else {
                    continue;
                };
                let rel = |x: &Camera, y: &Camera| {
                    y.cam_from_world.rotation * x.cam_from_world.rotation.transpose()
                };
                let d = rel(&ea, &eb) * rel(&truth[a], &truth[b]).transpose();
                let angle = ((d.trace() - 1.0) / 2.0).clamp(-1.0, 1.0).acos();
                worst = worst.max(angle.to_degrees());
            }
        }
        worst
    }

    #[test]
    fn given_cameras_are_refined_to_the_exact_scene() {
        let (truth, pairs) = scene();
        // Turned about 0.5–2.5° each (camera 0 too), the focal 4 % long, camera 4 not given.
        let mut given: Vec<Option<Camera>> = truth
            .iter()
            .enumerate()
            .map(|(i, c)| {
                let mut c = *c;
                let turn = nalgebra::Rotation3::from_euler_angles(0.01 * i as f64, 0.008, -0.005);
                c.cam_from_world.rotation = turn.matrix() * c.cam_from_world.rotation;
                c.intrinsics = Intrinsics::new(1.04 * FOCAL, 1.04 * FOCAL, 320.0, 240.0).unwrap();
                (i != 4).then_some(c)
            })
            .collect();
        let layout = ImageIntrinsics::new(vec![PRINCIPAL; 6], vec![640.0; 6]);
        let mut phi = given_focal_factor(&given, &layout);
        assert!((phi - 1.04 * FOCAL / 640.0).abs() < 1e-12, "{phi}");
        let before = worst_relative_rotation(&given, &truth);
        let options = SampsonRefineOptions::default();
        let report =
            sampson_refine_cameras(&mut given, &pairs, (&layout, &mut phi, None), 0, &options)
                .unwrap();
        assert!(report.iterations > 0 && report.final_cost < report.initial_cost);
        assert!(given[4].is_none(), "a camera not given stays not given");
        let after = worst_relative_rotation(&given, &truth);
        assert!(before > 1.0 && after < 1e-3, "{before}° → {after}°");
        assert!((phi * 640.0 / FOCAL - 1.0).abs() < 1e-4, "{phi}");
        for c in given.iter().flatten() {
            assert_eq!(c.intrinsics, layout.intrinsics(phi, 0).unwrap());
        }

        // Known intrinsics per image are written back as given, the focal held.
        let known: Vec<Intrinsics> = truth.iter().map(|c| c.intrinsics).collect();
        let mut fixed = truth.iter().map(|c| Some(*c)).collect::<Vec<_>>();
        let mut phi = FOCAL / 640.0;
        let options = SampsonRefineOptions {
            refine_focal: false,
            ..SampsonRefineOptions::default()
        };
        sampson_refine_cameras(
            &mut fixed,
            &pairs,
            (&layout, &mut phi, Some(&known)),
            0,
            &options,
        )
        .unwrap();
        assert_eq!(phi, FOCAL / 640.0);
        for (c, k) in fixed.iter().zip(&known) {
            assert_eq!(c.unwrap().intrinsics, *k);
        }
        assert!(worst_relative_rotation(&fixed, &truth) < 1e-4);
    }
}
