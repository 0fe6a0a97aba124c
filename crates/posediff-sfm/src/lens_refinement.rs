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

use crate::bundle::{
    BundleOptions, LensAdjustment, LensCoefficients, LensKind, Point, adjust_lens,
};
use crate::camera::CameraPose;
use crate::error::Result;
use crate::intrinsics::ImageIntrinsics;

/// The lens model refined: COLMAP's SIMPLE_RADIAL (`k`, its default), RADIAL (`k₁, k₂`) or
/// OPENCV (`k₁, k₂, p₁, p₂`, with one focal: nerfstudio's default for COLMAP).
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
    /// Two radial and two tangential coefficients.
    Opencv,
    /// OpenCV's fisheye: four coefficients of the angle `θ = atan r`.
    OpencvFisheye,
}

impl LensModel {
    /// The coefficients it refines.
    pub fn coefficients(self) -> usize {
        match self {
            Self::SimpleRadial => 1,
            Self::Radial => 2,
            Self::Opencv | Self::OpencvFisheye => 4,
        }
    }

    /// The distortion model of its coefficients.
    pub fn kind(self) -> LensKind {
        match self {
            Self::OpencvFisheye => LensKind::Fisheye,
            _ => LensKind::Brown,
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
    /// coefficient fits as −0.112 on the fountain) or `opencv` (`k₁, k₂, p₁, p₂`: a lens
    /// whose centre is off its optical axis).
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
    /// OPENCV_FISHEYE: `k₁, k₂` only, and the lens must not fold inside the image; its `k₃,
    /// k₄` are weakly determined over a narrow field (the fountain's fisheye copy, `posediff
    /// variant --fisheye=0.05:-0.02:0.01:0`, corners 31° off the axis: (0.04, 0.18, −1.14,
    /// 2.56), within 0.5 px of the truth's displacement to 28°; docs/BENCHMARKS.md, "A fisheye
    /// copy").
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
    pub k: Vec<LensCoefficients>,
    /// Whether the coefficients are kept (they lowered the cost enough and stayed in range).
    pub kept: bool,
    /// Why they are not kept (`None` when kept).
    pub reason: Option<&'static str>,
    /// Per camera group, the factor the adjustment moved its focal by (1 where not refined):
    /// a fisheye lens is defined at its focal, so its camera keeps that focal.
    pub factors: Vec<f64>,
    /// The adjustment.
    pub adjustment: LensAdjustment,
}

/// Whether the fisheye `k`'s distorted radius `r_d(θ) = θ (1 + k₁θ² + k₂θ⁴ + k₃θ⁶ + k₄θ⁸)`
/// grows with the ray's angle `θ` until it reaches `corner` (the image corner's radius over the
/// focal, where the photo ends; or up to 90°): one pixel per direction, no fold. Walked in
/// steps of 0.45°.
fn fisheye_unfolded(k: LensCoefficients, corner: f64) -> bool {
    let radius = |t: f64| {
        let t2 = t * t;
        t * (1.0 + t2 * (k[0] + t2 * (k[1] + t2 * (k[2] + t2 * k[3]))))
    };
    for s in 0..=200 {
        let t = std::f64::consts::FRAC_PI_2 * f64::from(s) / 200.0;
        let t2 = t * t;
        let slope =
            1.0 + t2 * (3.0 * k[0] + t2 * (5.0 * k[1] + t2 * (7.0 * k[2] + t2 * 9.0 * k[3])));
        if slope <= 0.0 {
            return false;
        }
        if radius(t) >= corner {
            return true;
        }
    }
    true
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
    k: &[LensCoefficients],
    bundle: &BundleOptions,
    options: &LensRefinementOptions,
) -> Result<LensRefinement> {
    let pinhole = k.iter().all(|k| *k == options.model.kind().pinhole());
    let mut ks = k.to_vec();
    let Some(reference) = cameras.iter().position(Option::is_some) else {
        return Ok(LensRefinement {
            k: ks,
            kept: false,
            reason: Some("no camera estimated"),
            factors: vec![1.0; k.len()],
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
    // Each group's farthest image corner from the axis over the focal (the principal point
    // at the centre): how far a fisheye's radius must grow without folding.
    let mut widest = vec![0.0f64; ks.len()];
    for (i, &g) in intrinsics.group.iter().enumerate() {
        if let Some(w) = widest.get_mut(g) {
            let [cx, cy] = intrinsics.principal[i];
            *w = w.max((cx + 0.5).hypot(cy + 0.5) / intrinsics.focal(1.0, i));
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
            factors: vec![1.0; k.len()],
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
        options.model.kind(),
        reference,
        bundle,
    )?;
    let reason = if adjustment.observations == 0 {
        Some("no observation")
    } else if !(adjustment.cost_before.is_finite() && adjustment.cost_after.is_finite()) {
        Some("a reprojection cost that is not finite")
    } else if !ks.iter().all(|k| {
        // A fisheye's k₃, k₄ (of θ⁷, θ⁹) are weakly determined over a narrow field and may
        // be large there without harm: its first two are bounded.
        let bounded = match options.model {
            LensModel::OpencvFisheye => &k[..2],
            _ => &k[..],
        };
        k.iter().all(|v| v.is_finite()) && bounded.iter().all(|v| v.abs() <= options.max_k)
    }) {
        Some("a coefficient beyond max_k")
    } else if options.model == LensModel::OpencvFisheye
        && !ks
            .iter()
            .zip(&widest)
            .all(|(k, &corner)| fisheye_unfolded(*k, corner))
    {
        Some("the fisheye folds inside the image")
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
        factors,
        adjustment,
    })
}

#[cfg(test)]
mod tests {
    #![allow(clippy::unwrap_used)]
    use super::*;
    use crate::bundle::{LensCoefficients, LensKind, PINHOLE, adjust_lens};
    use nalgebra::Vector3;

    /// A fisheye whose radius turns back before the image's corner is refused, one whose
    /// corner comes first is not; the pinhole's series and the fountain copy's refined lens
    /// (large `k₃, k₄`) do not fold.
    #[test]
    fn a_fisheye_folding_inside_the_image_is_found() {
        // r_d = θ − 0.5 θ³ turns back at θ = 0.816 (r_d 0.544).
        let folding = [-0.5, 0.0, 0.0, 0.0];
        assert!(fisheye_unfolded(folding, 0.3));
        assert!(!fisheye_unfolded(folding, 0.6));
        assert!(fisheye_unfolded(LensKind::Fisheye.pinhole(), 1.5));
        assert!(fisheye_unfolded([0.038, 0.177, -1.143, 2.559], 0.6));
    }

    /// A ring of cameras around a cloud of points, seen through a SIMPLE_RADIAL lens with
    /// coefficient `k`: the points with their exact observations (photo pixels).
    fn ring(k: LensCoefficients) -> (Vec<Option<CameraPose>>, ImageIntrinsics, Vec<Point>) {
        ring_with((LensKind::Brown, k))
    }

    /// [`ring`] through a lens of either kind.
    fn ring_with(
        lens: (LensKind, LensCoefficients),
    ) -> (Vec<Option<CameraPose>>, ImageIntrinsics, Vec<Point>) {
        let ring = crate::test_scenes::Ring {
            cameras: 8,
            step: 0.35,
            lift: 0.4,
            points: 300,
            extent: [1.5, 1.2, 1.5],
            seed: 12345,
        };
        let (cameras, points) = ring.scene(&|_| 500.0, [320.0, 240.0], lens);
        let intrinsics = ImageIntrinsics::new(vec![[320.0, 240.0]; 8], vec![500.0; 8]);
        (cameras, intrinsics, points)
    }

    /// From a pinhole start and a focal 3 % off, the lens, the focal and the cameras come back
    /// exactly; the pinhole start's error is pixels.
    #[test]
    fn the_radial_coefficient_is_recovered_with_the_focal() {
        let (truth, intrinsics, points) = ring([-0.1, 0.0, 0.0, 0.0]);
        let mut cameras = truth.clone();
        for c in cameras.iter_mut().skip(1).flatten() {
            c.center += Vector3::new(0.01, -0.02, 0.01);
        }
        let (mut factors, mut ks) = (vec![1.03], vec![PINHOLE]);
        let options = BundleOptions {
            max_error_px: 1e3,
            tolerance: 1e-12,
            ..BundleOptions::default()
        };
        let (kept, report) = adjust_lens(
            points,
            &intrinsics,
            &mut cameras,
            (&mut factors, &mut ks, &[1]),
            LensKind::Brown,
            0,
            &options,
        )
        .unwrap();
        assert!(report.rms_before_px > 1.0, "{report:?}");
        assert!(report.rms_after_px < 1e-3, "{report:?}");
        assert!(report.cost_after < 1e-3 * report.cost_before, "{report:?}");
        assert!(
            (ks[0][0] + 0.1).abs() < 1e-4 && ks[0][1] == 0.0,
            "k {:?}",
            ks[0]
        );
        assert!(
            (factors[0] - 1.0).abs() < 1e-4,
            "focal factor {}",
            factors[0]
        );
        assert_eq!(kept.len(), 300);
        // Up to the gauge (unit mean distance from the reference): rotations exact.
        for (c, t) in cameras.iter().zip(&truth) {
            let (c, t) = (c.unwrap(), t.unwrap());
            let angle = (c.rotation.matrix() - t.rotation.matrix()).norm();
            assert!(angle < 1e-5, "{angle} {report:?}");
        }
    }

    /// The pinhole adjustment is the lens adjustment at `k = 0` held fixed: on pinhole data
    /// the coefficient stays at zero and nothing is gained.
    #[test]
    fn a_pinhole_scene_keeps_a_zero_coefficient() {
        let (truth, intrinsics, points) = ring(PINHOLE);
        let mut cameras = truth.clone();
        let (mut factors, mut ks) = (vec![1.0], vec![PINHOLE]);
        let (_, report) = adjust_lens(
            points,
            &intrinsics,
            &mut cameras,
            (&mut factors, &mut ks, &[4]),
            LensKind::Brown,
            0,
            &BundleOptions::default(),
        )
        .unwrap();
        assert!(ks[0].iter().all(|k| k.abs() < 1e-6), "k {:?}", ks[0]);
        assert!(report.rms_before_px < 1e-6 && report.rms_after_px < 1e-6);
        let wrong = adjust_lens(
            Vec::new(),
            &intrinsics,
            &mut cameras,
            (&mut factors, &mut [PINHOLE; 2], &[1, 1]),
            LensKind::Brown,
            0,
            &BundleOptions::default(),
        );
        assert!(wrong.is_err());
    }

    /// [`refine_lens`] of a scene from `start` (one camera group).
    fn refine(
        (cameras, intrinsics, points): &(Vec<Option<CameraPose>>, ImageIntrinsics, Vec<Point>),
        start: LensCoefficients,
        bundle: &BundleOptions,
        options: &LensRefinementOptions,
    ) -> LensRefinement {
        refine_lens(points, intrinsics, cameras, &[start], bundle, options).unwrap()
    }

    /// The refinement's verdicts: the ring's lens is found and kept from a pinhole start; a
    /// camera with fewer than `min_images` estimated images keeps its coefficient (held fixed
    /// in the adjustment), and a pinhole scene stays pinhole (the cost cannot fall).
    #[test]
    fn the_refinement_keeps_a_lens_only_where_the_images_determine_it() {
        let scene = ring([-0.1, 0.0, 0.0, 0.0]);
        let options = LensRefinementOptions::default();
        let bundle = BundleOptions::default();
        let found = refine(&scene, PINHOLE, &bundle, &options);
        assert!(found.kept, "{found:?}");
        assert!((found.k[0][0] + 0.1).abs() < 1e-4, "{found:?}");
        let too_few = LensRefinementOptions {
            min_images: 9,
            ..options
        };
        let held = refine(&scene, [-0.05, 0.0, 0.0, 0.0], &bundle, &too_few);
        assert!(!held.kept && held.k == [[-0.05, 0.0, 0.0, 0.0]], "{held:?}");
        let scene = ring(PINHOLE);
        let pinhole = refine(&scene, PINHOLE, &bundle, &options);
        assert!(!pinhole.kept && pinhole.reason.is_some(), "{pinhole:?}");
    }

    /// RADIAL: a lens with `k₂` (OpenCV's `k1 = −0.12, k2 = 0.02`, the wide-angle copies')
    /// comes back with both coefficients, where SIMPLE_RADIAL's one coefficient cannot fit it.
    #[test]
    fn a_second_coefficient_is_recovered_with_the_radial_model() {
        let scene = ring([-0.12, 0.02, 0.0, 0.0]);
        let bundle = BundleOptions {
            tolerance: 1e-12,
            ..BundleOptions::default()
        };
        let radial = LensRefinementOptions {
            model: LensModel::Radial,
            ..LensRefinementOptions::default()
        };
        let two = refine(&scene, PINHOLE, &bundle, &radial);
        assert!(two.kept, "{two:?}");
        let [k1, k2, p1, p2] = two.k[0];
        assert_eq!((p1, p2), (0.0, 0.0));
        assert!(
            (k1 + 0.12).abs() < 1e-3 && (k2 - 0.02).abs() < 1e-3,
            "{two:?}"
        );
        assert!(two.adjustment.rms_after_px < 1e-3, "{two:?}");
        let one = refine(&scene, PINHOLE, &bundle, &LensRefinementOptions::default());
        assert_eq!(one.k[0][1], 0.0);
        assert!(
            one.adjustment.rms_after_px > 10.0 * two.adjustment.rms_after_px,
            "{one:?}"
        );
    }

    /// OPENCV: a lens with tangential terms (a centre off the optical axis) comes back with
    /// all four coefficients; RADIAL's two leave the tangential part as error.
    #[test]
    fn tangential_coefficients_are_recovered_with_the_opencv_model() {
        let truth = [-0.1, 0.015, 0.002, -0.0015];
        let scene = ring(truth);
        let bundle = BundleOptions {
            tolerance: 1e-12,
            ..BundleOptions::default()
        };
        let opencv = LensRefinementOptions {
            model: LensModel::Opencv,
            ..LensRefinementOptions::default()
        };
        let four = refine(&scene, PINHOLE, &bundle, &opencv);
        assert!(four.kept, "{four:?}");
        for (k, t) in four.k[0].iter().zip(truth) {
            assert!((k - t).abs() < 1e-4, "{four:?}");
        }
        assert!(four.adjustment.rms_after_px < 1e-3, "{four:?}");
        let radial = LensRefinementOptions {
            model: LensModel::Radial,
            ..opencv
        };
        let two = refine(&scene, PINHOLE, &bundle, &radial);
        assert_eq!((two.k[0][2], two.k[0][3]), (0.0, 0.0));
        assert!(
            two.adjustment.rms_after_px > 10.0 * four.adjustment.rms_after_px,
            "{two:?}"
        );
    }

    /// OPENCV_FISHEYE: from the start that stands for a pinhole, a fisheye lens comes back
    /// moving every pixel as the truth does (coefficients of `θ⁶, θ⁸` are weakly determined at
    /// these angles, so the lens is compared, not the coefficients), and is kept.
    #[test]
    fn a_fisheye_lens_is_recovered() {
        let truth = [0.25, 0.05, 0.0, 0.0];
        let scene = ring_with((LensKind::Fisheye, truth));
        let bundle = BundleOptions {
            tolerance: 1e-14,
            max_iterations: 300,
            ..BundleOptions::default()
        };
        let fisheye = LensRefinementOptions {
            model: LensModel::OpencvFisheye,
            ..LensRefinementOptions::default()
        };
        let start = LensKind::Fisheye.pinhole();
        let found = refine(&scene, start, &bundle, &fisheye);
        assert!(found.kept, "{found:?}");
        assert!(found.adjustment.rms_before_px > 1.0, "{found:?}");
        assert!(found.adjustment.rms_after_px < 1e-3, "{found:?}");
        for step in 0..=30 {
            let r = f64::from(step).to_radians().tan();
            let a = posediff_geometry::lens::distort_fisheye(found.k[0], r, 0.0)
                .0
                .x;
            let b = posediff_geometry::lens::distort_fisheye(truth, r, 0.0).0.x;
            assert!(
                (500.0 * (a - b)).abs() < 0.01,
                "{step}°: {} px",
                500.0 * (a - b)
            );
        }
    }
}
