//! The hybrid of the paper's future work (`posediff estimate --weights W --refine bundle`):
//! cameras from elsewhere (PoseDiffusion after GGS) refined by this crate's Sampson refinement
//! and bundle adjustment, with tracks built from the matches.

use posediff_geometry::{Camera, Intrinsics, PairMatches, Pose};

use crate::bundle::{BundleOptions, bundle_adjust};
use crate::error::{Result, SfmError};
use crate::sampson_refine::{SampsonRefineOptions, refine_sampson};
use crate::tracks::build_tracks;
use crate::{CameraPose, ImageIntrinsics};

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
        ..SampsonRefineOptions::default()
    };
    let first = refine_sampson(&refs, &layout, &mut poses, &mut phi, 0, &sampson)?;
    let (tracks, track_report) = build_tracks(cameras.len(), pairs)?;
    let options = BundleOptions {
        refine_focal: !known_intrinsics,
        ..BundleOptions::default()
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
