//! Radial distortion from the tracks, after the mapper: each camera group's SIMPLE_RADIAL
//! coefficient refined by a bundle adjustment on the photos' own pixels
//! ([`crate::bundle::adjust_lens`]), as COLMAP's and GLOMAP's bundle adjustments refine it.
//!
//! The calibration before the mapper ([`crate::distortion_calibration`]) sees pairs only, and a
//! pair's fundamental matrix absorbs most of a distortion that both views share: where the
//! verified matches lie in the middle of the photos it measures nothing. A track seen by many
//! cameras of one group cannot absorb it. The coefficient is kept only when it lowers the
//! robust reprojection cost by `min_improvement`, so a pinhole set stays pinhole; the caller
//! then undistorts the matches with it and maps again.

use crate::bundle::{BundleOptions, LensAdjustment, Point, Radial, adjust_lens};
use crate::camera::CameraPose;
use crate::error::Result;
use crate::intrinsics::ImageIntrinsics;

/// The lens model refined: COLMAP's SIMPLE_RADIAL (`k`, its default) or RADIAL (`k₁, k₂`).
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default)]
#[cfg_attr(
    feature = "serde",
    derive(serde::Serialize, serde::Deserialize),
    serde(rename_all = "snake_case")
)]
pub enum LensModel {
    /// One coefficient.
    #[default]
    SimpleRadial,
    /// Two coefficients.
    Radial,
}

impl LensModel {
    /// The coefficients it refines.
    pub fn coefficients(self) -> usize {
        match self {
            Self::SimpleRadial => 1,
            Self::Radial => 2,
        }
    }
}

/// Settings of [`refine_lens`]; chosen on the shared sets and their wide-angle copies
/// (`posediff variant --radial=-0.12:0.02`, docs/BENCHMARKS.md, "Real cameras: the lens in the
/// bundle adjustment").
#[derive(Debug, Clone, Copy, PartialEq)]
#[cfg_attr(
    feature = "serde",
    derive(serde::Serialize, serde::Deserialize),
    serde(default, deny_unknown_fields)
)]
pub struct LensRefinementOptions {
    /// The model: `simple_radial` (COLMAP's default; one coefficient) or `radial` (`k₁, k₂`:
    /// a strong wide-angle lens, the copies' OpenCV `k1 = −0.12, k2 = 0.02`, which one
    /// coefficient fits as −0.112 on the fountain).
    pub model: LensModel,
    /// Points adjusted at most, evenly spaced over the mapper's (a few thousand determine one
    /// coefficient per camera; the poses are adjusted again by the second mapping).
    pub max_points: usize,
    /// Relative decrease of the robust reprojection cost needed to keep the coefficients when
    /// the start is pinhole (no distortion measured before the mapper). 0.1: on the apple's
    /// wide-angle copy the cost falls by 27 % (kept: mAA(30) 0.402 → 0.474); on the temple's
    /// by 1.5 % and on the original temple by 2.4 %, towards `k ≈ −0.4…−0.5` that its central
    /// points cannot determine (kept, the original's mAA(30) falls 0.966 → 0.725). A start
    /// that is already a measured lens is refined whenever the cost falls at all.
    pub min_improvement: f64,
    /// Largest `|k|` kept (COLMAP's coefficient on `x_c / z_c`; a strong wide-angle lens is
    /// about −0.3): beyond it the adjustment has gone astray and the lens is left as it was.
    pub max_k: f64,
    /// Fewest estimated images of a camera for its coefficient to be refined (the others keep
    /// theirs). On a few photos of a small object the coefficient trades off against the
    /// structure: on the temple's 5-image subsets the reprojection cost fell by 21–31 % towards
    /// `k` = −0.23…−0.87 from a pinhole set (bench-real's temple N = 5: mAA(30) 0.061 →
    /// 0.053); the sets whose lens it finds have 11–20 (fountain, apple, synthetic).
    pub min_images: usize,
}

impl Default for LensRefinementOptions {
    fn default() -> Self {
        Self {
            model: LensModel::SimpleRadial,
            max_points: 20_000,
            min_improvement: 0.1,
            max_k: 1.0,
            min_images: 8,
        }
    }
}

/// What [`refine_lens`] found.
#[derive(Debug, Clone, PartialEq, Default)]
pub struct LensRefinement {
    /// Per camera group, the refined coefficients `[k₁, k₂]` (`k₂ = 0` with SIMPLE_RADIAL; the
    /// start's where the group was not refined).
    pub k: Vec<Radial>,
    /// Whether the coefficients are kept (they lowered the cost enough and stayed in range).
    pub kept: bool,
    /// Why they are not kept (`None` when kept).
    pub reason: Option<&'static str>,
    /// The adjustment.
    pub adjustment: LensAdjustment,
}

/// Each group's radial coefficients (`options.model`) from `points` (observations in the photos' pixels) seen by
/// `cameras` with focal `intrinsics.focal(1.0, i)` (the estimated focal in `scale`), starting
/// from `k` (per group). The cameras and points given are not changed.
///
/// # Errors
/// As [`adjust_lens`]: inputs of the wrong length, no reference camera, a reduced system that
/// is not positive definite at any damping.
pub fn refine_lens(
    points: &[Point],
    intrinsics: &ImageIntrinsics,
    cameras: &[Option<CameraPose>],
    k: &[Radial],
    bundle: &BundleOptions,
    options: &LensRefinementOptions,
) -> Result<LensRefinement> {
    let pinhole = k.iter().all(|k| *k == [0.0, 0.0]);
    let mut ks = k.to_vec();
    let Some(reference) = cameras.iter().position(Option::is_some) else {
        return Ok(LensRefinement {
            k: ks,
            kept: false,
            reason: Some("no camera estimated"),
            adjustment: LensAdjustment::default(),
        });
    };
    // The cameras with too few estimated images keep their coefficient: their images' points
    // are adjusted with it fixed.
    let mut estimated = vec![0usize; ks.len()];
    for (i, c) in cameras.iter().enumerate() {
        if c.is_some()
            && let Some(n) = intrinsics.group.get(i).and_then(|g| estimated.get_mut(*g))
        {
            *n += 1;
        }
    }
    let free: Vec<usize> = estimated
        .iter()
        .map(|&n| {
            if n >= options.min_images {
                options.model.coefficients()
            } else {
                0
            }
        })
        .collect();
    if free.iter().all(|f| *f == 0) {
        return Ok(LensRefinement {
            k: ks,
            kept: false,
            reason: Some("no camera has min_images estimated images"),
            adjustment: LensAdjustment::default(),
        });
    }
    let step = points.len().div_ceil(options.max_points.max(1)).max(1);
    let subset: Vec<Point> = points.iter().step_by(step).cloned().collect();
    let mut cameras = cameras.to_vec();
    let mut factors = vec![1.0; intrinsics.groups()];
    let (_, adjustment) = adjust_lens(
        subset,
        intrinsics,
        &mut cameras,
        (&mut factors, &mut ks, &free),
        reference,
        bundle,
    )?;
    let reason = if adjustment.observations == 0 {
        Some("no observation")
    } else if !(adjustment.cost_before.is_finite() && adjustment.cost_after.is_finite()) {
        Some("a reprojection cost that is not finite")
    } else if !ks
        .iter()
        .flatten()
        .all(|k| k.is_finite() && k.abs() <= options.max_k)
    {
        Some("a coefficient beyond max_k")
    } else if adjustment.cost_after > adjustment.cost_before {
        Some("the reprojection cost did not fall")
    } else if pinhole
        && adjustment.cost_after >= (1.0 - options.min_improvement) * adjustment.cost_before
    {
        Some("the reprojection cost fell by less than min_improvement from a pinhole start")
    } else {
        None
    };
    Ok(LensRefinement {
        k: ks,
        kept: reason.is_none(),
        reason,
        adjustment,
    })
}
