//! The global mapper: matches → pair types → a shared focal → (per focal start) relative poses
//! → rotation averaging → translation averaging → Sampson refinement → the best start → tracks
//! → resection of the cameras on view-graph bridges
//! → bundle adjustment.
//!
//! The focal is multi-started: the self-calibrated value, a log grid and the prior (fixed),
//! because the Sampson cost is flat in the focal for narrow fields of view and
//! self-calibration can be far off. A free focal that leaves the search range is unobservable
//! (optical axes meeting at one point, as in object-centric captures of two or three views):
//! such solutions are dropped. The start with the lowest robust cost over all matches wins.
//!
//! Only the largest connected component of the view graph is estimated; every other image is
//! reported with its reason ([`NotEstimated`]).

use crate::report::FocalRivalReport;
use std::collections::HashSet;
use std::time::Instant;

use nalgebra::{Matrix3, Rotation3};
use posediff_geometry::PairMatches;
use rayon::prelude::*;

use crate::bundle::{BundleOptions, Point, bundle_adjust};
use crate::camera::CameraPose;
use crate::camera_split::{CameraSplitOptions, split_cameras};
use crate::error::{Result, SfmError};
use crate::focal::{FocalSearch, PairFundamental, focal_from_homographies, self_calibrate};
use crate::intrinsics::ImageIntrinsics;
use crate::report::{
    CameraCalibrationReport, CameraSplitRound, FocalSource, FocalStart, MapperReport, NotEstimated,
    SupportReport,
};
use crate::resection::{ResectionOptions, resect_bridged_sides};
use crate::rotation_averaging::{
    RelativeRotation, RotationAveragingOptions, RotationAveragingReport, average_rotations,
    confirmed_by_trusted_triangles, keep_bridges, rotation_residuals_deg, unconfirmed_by_cycles,
};
use crate::sampson_refine::{
    SampsonRefineOptions, SampsonRefineReport, refine_sampson, robust_cost,
};
use crate::tracks::build_tracks;
use crate::translation_averaging::{
    CenterDirection, TranslationAveragingOptions, TranslationAveragingReport, average_translations,
};
use crate::view_graph::largest_component;
use crate::view_graph_calibration::{
    ImagePair, ViewGraphCalibrationOptions, calibrate_groups, group_by_focal,
};

pub use crate::solver::{GeometrySolver, Homography, RelativePose};

/// Settings of the mapper, one struct per stage.
#[derive(Debug, Clone, PartialEq)]
#[cfg_attr(
    feature = "serde",
    derive(serde::Serialize, serde::Deserialize),
    serde(default, deny_unknown_fields)
)]
pub struct MapperOptions {
    /// Self-calibration search range (`φ = f / s`).
    pub focal_search: FocalSearch,
    /// Focal factors tried besides the self-calibrated one.
    pub focal_starts: Vec<f64>,
    /// The focal factor used (fixed) when the data cannot determine it: COLMAP's `1.2`.
    pub focal_prior: f64,
    /// A pair whose homography explains at least this fraction of its matches has no parallax.
    /// (Not in the serialised options: the umbrella sets it from its two-view settings.)
    #[cfg_attr(feature = "serde", serde(skip))]
    pub homography_fraction: f64,
    /// Rotation averaging.
    pub rotation_averaging: RotationAveragingOptions,
    /// Pairs whose relative rotation disagrees with the averaged rotations by more than this
    /// (degrees) are dropped before translation averaging.
    pub max_rotation_residual_deg: f64,
    /// The cycle check before rotation averaging: a pair is dropped when it closes at least
    /// `min_triangles` triangles of the view graph and none within `threshold_deg`
    /// ([`crate::rotation_averaging::unconfirmed_by_cycles`]); `None` (the default): no
    /// check. Measured on the shared sets (docs/BENCHMARKS.md, `examples/mapper_replay.rs`): it
    /// lifts ALIKED + LightGlue on all of temple from 0.104 to 0.457 mAA(30) but costs SIFT on
    /// all apple frames 0.957 → 0.697, so it stays off.
    pub cycle_check: Option<CycleCheck>,
    /// With support flags ([`GlobalMapper::run_with_support`]): an unsupported pair is kept
    /// when a triangle of two kept pairs closes within this angle (degrees) at the start's
    /// focal ([`crate::rotation_averaging::confirmed_by_trusted_triangles`]). Looser than the
    /// cycle check because a start's focal is not yet refined; the wrong pairs it is for are
    /// off by tens of degrees (5° and 3° measured worse, docs/BENCHMARKS.md).
    pub support_triangle_deg: f64,
    /// When the focal starts are compared, a pair that the start's consistency checks dropped
    /// (rotation residual, cycle check) costs the missing penalty per match instead of its
    /// residuals under the start's cameras. Without it, a start that keeps a learned matcher's
    /// wrong pairs at a wrong focal can win by fitting them: on templeSR (all frames, ALIKED +
    /// LightGlue) the prior 1.2 beat the true 2.35 and mAA(30) was 0.104; with it, 0.473, the
    /// other shared-set cells unchanged within 0.002. Off by default because SIFT's temple
    /// "all" loses with it (0.978 → 0.765: its few dropped pairs are right, and scoring them
    /// as missing moves the choice); the umbrella turns it on with a learned matcher.
    pub score_dropped_as_missing: bool,
    /// Translation averaging.
    pub translation_averaging: TranslationAveragingOptions,
    /// The Sampson refinement (`None`: the averaged cameras).
    pub sampson: Option<SampsonRefineOptions>,
    /// Resection of the cameras that hang on a bridge of the view graph, from the other side's
    /// tracks, before the bundle adjustment (`None`: skipped).
    pub resection: Option<ResectionOptions>,
    /// The bundle adjustment with tracks (`None`: skipped).
    pub bundle: Option<BundleOptions>,
    /// When starts are compared, a match whose pair is not estimated costs as much as one this
    /// far (px) from its epipolar line.
    pub missing_penalty_px: f64,
    /// The view-graph calibration of each camera group's focal before the multi-start
    /// ([`crate::view_graph_calibration`]; `None`: every group starts from the shared focal).
    pub calibration: Option<ViewGraphCalibrationOptions>,
    /// Decide the cameras from the data: given one group, calibrate a focal per image and
    /// group the images whose focals agree ([`crate::view_graph_calibration::group_by_focal`]).
    /// (Not in the serialised options: the umbrella sets it from its camera mode.)
    #[cfg_attr(feature = "serde", serde(skip))]
    pub cameras_from_data: bool,
    /// With the cameras decided from the data, the cameras split by a focal per image in the
    /// bundle adjustment after the mapper, and the map made again with them when they differ
    /// ([`crate::camera_split`]; `None`: not split). On the zoomed copies without EXIF
    /// (docs/BENCHMARKS.md, "Cameras split by the bundle adjustment") it lifts the temple's
    /// mAA(30) from 0.518 to 0.748 and the synthetic orbit's from 0.210 to 0.470.
    pub camera_split: Option<CameraSplitOptions>,
    /// With more images than this, the focal starts are compared on a connected subset of this
    /// many images (grown breadth-first from the best-matched image along the strongest
    /// pairs), and the whole set is solved once, from the winner's refined focal. The
    /// multi-start then costs the same at 1000 images as at this many.
    pub focal_selection_images: usize,
    /// A second opinion on the focal from the bundle adjustment (`None`: the lowest start
    /// cost wins alone). See [`FocalRival`].
    pub focal_rival: Option<FocalRival>,
}

/// When another focal start's cost is within `max_cost_ratio` of the winner's at a focal at
/// least `min_focal_ratio` apart, both maps are bundle-adjusted with the tracks and the rival
/// wins if its RMS reprojection error is below `max_rms_ratio` of the winner's. The start
/// cost (robust Sampson distances) cannot always tell a long focal from a short one on a
/// narrow ring: on the temple with LightGlue's AMX matches a start at φ 1.128 cost 8853
/// against 9274 at the true φ 2.37, while the bundle adjustment gave 0.696 against 0.398 px
/// (docs/BENCHMARKS.md, "AMX tiles on or off: the shared sets"). Only where the starts are
/// compared on the whole set (at most `focal_selection_images` images).
#[derive(Debug, Clone, Copy, PartialEq)]
#[cfg_attr(
    feature = "serde",
    derive(serde::Serialize, serde::Deserialize),
    serde(default, deny_unknown_fields)
)]
pub struct FocalRival {
    /// A rival's start cost at most this multiple of the winner's.
    pub max_cost_ratio: f64,
    /// Its focal at least this factor from the winner's (either way).
    pub min_focal_ratio: f64,
    /// It wins if its RMS error after the bundle adjustment is below this multiple of the
    /// winner's.
    pub max_rms_ratio: f64,
}

impl Default for FocalRival {
    fn default() -> Self {
        Self {
            max_cost_ratio: 1.06,
            min_focal_ratio: 1.3,
            max_rms_ratio: 0.8,
        }
    }
}

impl Default for MapperOptions {
    fn default() -> Self {
        Self {
            focal_search: FocalSearch::default(),
            focal_starts: vec![0.4, 0.6, 0.9, 1.35, 2.0, 3.0],
            focal_prior: 1.2,
            homography_fraction: 0.9,
            rotation_averaging: RotationAveragingOptions::default(),
            max_rotation_residual_deg: 10.0,
            cycle_check: None,
            support_triangle_deg: 10.0,
            score_dropped_as_missing: false,
            translation_averaging: TranslationAveragingOptions::default(),
            sampson: Some(SampsonRefineOptions::default()),
            resection: Some(ResectionOptions::default()),
            bundle: Some(BundleOptions::default()),
            missing_penalty_px: 10.0,
            focal_selection_images: 60,
            calibration: Some(ViewGraphCalibrationOptions::default()),
            cameras_from_data: false,
            camera_split: Some(CameraSplitOptions::default()),
            focal_rival: None,
        }
    }
}

/// Settings of the cycle check on the view graph's triangles.
#[derive(Debug, Clone, Copy, PartialEq)]
#[cfg_attr(
    feature = "serde",
    derive(serde::Serialize, serde::Deserialize),
    serde(default, deny_unknown_fields)
)]
pub struct CycleCheck {
    /// A triangle confirms its edges when its rotations compose to within this angle.
    pub threshold_deg: f64,
    /// Edges in fewer triangles are never dropped (bridges and thinly connected images).
    pub min_triangles: usize,
}

impl Default for CycleCheck {
    fn default() -> Self {
        Self {
            threshold_deg: 5.0,
            min_triangles: 2,
        }
    }
}

/// The mapper's result.
#[derive(Debug, Clone, PartialEq)]
pub struct Reconstruction {
    /// One per image; `None` for images not estimated.
    pub cameras: Vec<Option<CameraPose>>,
    /// The shared focal factor: image `i`'s focal is `intrinsics.focal(phi, i)`.
    pub phi: f64,
    /// Principal points and focal scales.
    pub intrinsics: ImageIntrinsics,
    /// The bundle adjustment's points (empty without it).
    pub points: Vec<Point>,
    /// What happened.
    pub report: MapperReport,
}

/// The pairs with a fundamental matrix, with their images' intrinsics.
fn image_pairs(
    matched: &[&PairMatches],
    fundamentals: &[Option<Matrix3<f64>>],
    intrinsics: &ImageIntrinsics,
) -> Vec<ImagePair> {
    matched
        .iter()
        .zip(fundamentals)
        .filter_map(|(p, f)| {
            f.map(|f| ImagePair {
                a: p.first,
                b: p.second,
                fundamental: PairFundamental {
                    f,
                    principal_a: intrinsics.principal[p.first],
                    principal_b: intrinsics.principal[p.second],
                    scale_a: intrinsics.scale[p.first],
                    scale_b: intrinsics.scale[p.second],
                    weight: (p.len() as f64).sqrt(),
                },
            })
        })
        .collect()
}

/// Calibrates each camera group's focal ratio to the shared `phi` (with `split`, first one
/// group per image, then grouped where the focals agree) and folds the ratios to the first
/// group's into the scales; the report's `start` is the first group's calibrated factor.
fn calibrate_cameras(
    intrinsics: &mut ImageIntrinsics,
    pairs: &[ImagePair],
    phi: f64,
    split: bool,
    options: &ViewGraphCalibrationOptions,
) -> CameraCalibrationReport {
    let n = intrinsics.len();
    let image_scale = intrinsics.scale.clone();
    let (group, ratio, base, per_image) = if split {
        let each: Vec<usize> = (0..n).collect();
        let c = calibrate_groups(pairs, &each, n, phi, options);
        let (group, ratio, base) = group_by_focal(&c.ratio, &c.determined, options.group_tolerance);
        (group, ratio, base, Some(c))
    } else {
        let c = calibrate_groups(pairs, &intrinsics.group, intrinsics.groups(), phi, options);
        let base = c.ratio[0];
        let ratio = c.ratio.iter().map(|r| r / base).collect();
        (intrinsics.group.clone(), ratio, base, None)
    };
    for (s, g) in intrinsics.scale.iter_mut().zip(&group) {
        *s *= ratio[*g];
    }
    intrinsics.group = group;
    CameraCalibrationReport {
        from_data: split,
        cameras: ratio.len(),
        ratio,
        image_ratio: per_image
            .as_ref()
            .map(|c| c.ratio.clone())
            .unwrap_or_default(),
        image_determined: per_image.map(|c| c.determined).unwrap_or_default(),
        phi,
        start: phi * base,
        kept: false,
        image_scale,
    }
}

/// `size` images connected through `matched`, grown breadth-first from the image with the most
/// matches, each image's neighbours taken strongest pair first (deterministic).
fn selection_subset(n: usize, matched: &[&PairMatches], size: usize) -> Vec<bool> {
    let mut adjacency: Vec<Vec<(usize, usize)>> = vec![Vec::new(); n];
    let mut total = vec![0usize; n];
    for p in matched {
        adjacency[p.first].push((p.len(), p.second));
        adjacency[p.second].push((p.len(), p.first));
        total[p.first] += p.len();
        total[p.second] += p.len();
    }
    for a in &mut adjacency {
        a.sort_by(|x, y| y.0.cmp(&x.0).then(x.1.cmp(&y.1)));
    }
    let mut keep = vec![false; n];
    let Some(start) = (0..n).max_by(|&a, &b| total[a].cmp(&total[b]).then(b.cmp(&a))) else {
        return keep;
    };
    let mut queue = std::collections::VecDeque::from([start]);
    keep[start] = true;
    let mut count = 1;
    while let Some(v) = queue.pop_front() {
        for &(_, w) in &adjacency[v] {
            if count >= size {
                return keep;
            }
            if !keep[w] {
                keep[w] = true;
                count += 1;
                queue.push_back(w);
            }
        }
    }
    keep
}

/// The checkpoint-free global mapper.
#[derive(Debug, Clone, PartialEq, Default)]
pub struct GlobalMapper {
    /// Its settings.
    pub options: MapperOptions,
}

/// Cameras initialised and refined from one starting focal.
#[derive(Clone)]
struct Solution {
    cameras: Vec<Option<CameraPose>>,
    members: Vec<usize>,
    /// The pairs whose relative pose the averaging used.
    edges: Vec<(usize, usize)>,
    phi: f64,
    pairs_with_pose: usize,
    rotation_only_pairs: usize,
    inconsistent_pairs: usize,
    cycle_rejected_pairs: usize,
    /// Unsupported pairs the support check dropped.
    support_rejected: Vec<(usize, usize)>,
    no_parallax: bool,
    rotations: RotationAveragingReport,
    translations: TranslationAveragingReport,
    sampson: Option<SampsonRefineReport>,
    score: f64,
    free_focal: bool,
}

impl GlobalMapper {
    /// A mapper with `options`.
    pub fn new(options: MapperOptions) -> Self {
        Self { options }
    }

    /// Cameras of `intrinsics.len()` images from the matches of `pairs`. With `known_focal`
    /// the intrinsics are exact (`φ = 1`, never refined); otherwise one focal factor is
    /// estimated.
    ///
    /// # Errors
    /// Fewer than two images, no pair with matches or a relative pose, pairs naming images
    /// out of range, invalid options, the two-view solver's failures, degenerate normal
    /// equations.
    pub fn run(
        &self,
        pairs: &[PairMatches],
        intrinsics: ImageIntrinsics,
        known_focal: bool,
        solver: &dyn GeometrySolver,
    ) -> Result<Reconstruction> {
        self.run_checked(pairs, &HashSet::new(), intrinsics, known_focal, solver)
    }

    /// [`Self::run`] with the pairs that lack support (empty: no support check): one map, then
    /// the cameras split by the bundle adjustment ([`MapperOptions::camera_split`]).
    fn run_checked(
        &self,
        pairs: &[PairMatches],
        unsupported: &HashSet<(usize, usize)>,
        intrinsics: ImageIntrinsics,
        known_focal: bool,
        solver: &dyn GeometrySolver,
    ) -> Result<Reconstruction> {
        let o = &self.options;
        let base = intrinsics.scale.clone();
        let mut best = self.map_once(pairs, unsupported, intrinsics, known_focal, solver)?;
        let (Some(split), Some(bundle)) = (&o.camera_split, &o.bundle) else {
            return Ok(best);
        };
        if known_focal
            || !o.cameras_from_data
            || !best.report.focal_free
            || best.report.bundle_undone
            || best.points.is_empty()
        {
            return Ok(best);
        }
        let clock = Instant::now();
        let matched: Vec<&PairMatches> = pairs.iter().filter(|p| !p.is_empty()).collect();
        let cauchy = o
            .sampson
            .map_or(SampsonRefineOptions::default().cauchy_px, |s| s.cauchy_px);
        let score = |r: &Reconstruction| {
            robust_cost(
                &matched,
                &r.intrinsics,
                &r.cameras,
                r.phi,
                cauchy,
                o.missing_penalty_px,
            )
        };
        // Maps again with given cameras: no calibration, no split.
        let again = GlobalMapper::new(MapperOptions {
            calibration: None,
            cameras_from_data: false,
            camera_split: None,
            ..o.clone()
        });
        let mut rounds = Vec::new();
        // The score of the map so far, computed when a new map is to be compared with it.
        let mut current: Option<f64> = None;
        for _ in 0..split.rounds {
            let s = split_cameras(
                &best.points,
                (&best.intrinsics, best.phi, &base),
                &best.cameras,
                bundle,
                split,
            )?;
            let mut round = CameraSplitRound {
                image_focal: s.image_focal.clone(),
                image_camera: s.group.clone(),
                images_before: best.report.estimated.len(),
                adjustment: s.adjustment,
                ..CameraSplitRound::default()
            };
            if s.same_cameras(&best.intrinsics.group) {
                rounds.push(round);
                break;
            }
            round.mapped_again = true;
            let before = match current {
                Some(s) => s,
                None => score(&best)?,
            };
            round.score_before = Some(before);
            let intrinsics = ImageIntrinsics {
                principal: best.intrinsics.principal.clone(),
                scale: s.scale,
                group: s.group,
            };
            // A map that fails is not kept (the one before stands).
            if let Ok(r) = again.map_once(pairs, unsupported, intrinsics, false, solver) {
                let after = score(&r)?;
                round.score_after = Some(after);
                round.images_after = Some(r.report.estimated.len());
                if after < before {
                    round.kept = true;
                    current = Some(after);
                    let calibration = best.report.cameras.take().map(|mut c| {
                        c.cameras = r.intrinsics.groups();
                        c
                    });
                    best = Reconstruction {
                        report: MapperReport {
                            cameras: calibration,
                            ..r.report
                        },
                        ..r
                    };
                }
            }
            let kept = round.kept;
            rounds.push(round);
            if !kept {
                break;
            }
        }
        best.report.camera_split = rounds;
        best.report.times.camera_split = clock.elapsed().as_secs_f64();
        Ok(best)
    }

    /// One map of [`Self::run_checked`].
    fn map_once(
        &self,
        pairs: &[PairMatches],
        unsupported: &HashSet<(usize, usize)>,
        intrinsics: ImageIntrinsics,
        known_focal: bool,
        solver: &dyn GeometrySolver,
    ) -> Result<Reconstruction> {
        let o = &self.options;
        let n = intrinsics.len();
        if n < 2 {
            return Err(SfmError::InvalidInput(format!(
                "need at least 2 images, got {n}"
            )));
        }
        intrinsics.check(n)?;
        if let Some(p) = pairs
            .iter()
            .find(|p| p.first >= n || p.second >= n || p.first == p.second || !p.is_consistent())
        {
            return Err(SfmError::InvalidInput(format!(
                "pair ({}, {}) of {n} images with {} matches is malformed",
                p.first,
                p.second,
                p.len()
            )));
        }
        let mut report = MapperReport::default();
        let matched: Vec<&PairMatches> = pairs.iter().filter(|p| !p.is_empty()).collect();
        report.pairs_with_matches = matched.len();
        if matched.is_empty() {
            return Err(SfmError::NoUsablePairs { images: n });
        }

        // Pair types (no intrinsics needed) and, for self-calibration, least-squares F.
        let clock = Instant::now();
        let homography: Vec<Option<(Matrix3<f64>, f64)>> = matched
            .par_iter()
            .map(|p| solver.homography(p))
            .collect::<Result<_>>()?;
        let parallax: Vec<bool> = homography
            .iter()
            .map(|h| h.is_none_or(|(_, fraction)| fraction < o.homography_fraction))
            .collect();
        let fundamentals: Vec<Option<Matrix3<f64>>> = if known_focal {
            Vec::new()
        } else {
            matched
                .par_iter()
                .zip(&parallax)
                .map(|(p, par)| {
                    if *par {
                        solver.fundamental(p)
                    } else {
                        Ok(None)
                    }
                })
                .collect::<Result<_>>()?
        };
        report.times.pair_geometry = clock.elapsed().as_secs_f64();

        let clock = Instant::now();
        let mut intrinsics = intrinsics;
        let mut cameras: Option<(ImageIntrinsics, CameraCalibrationReport)> = None;
        let phi = if known_focal {
            report.focal_source = FocalSource::Given;
            1.0
        } else {
            let image_pairs = image_pairs(&matched, &fundamentals, &intrinsics);
            let pf: Vec<PairFundamental> = image_pairs.iter().map(|p| p.fundamental).collect();
            let calibrated = self_calibrate(&pf, &o.focal_search);
            // Cameras of their own, calibrated from the view graph at the self-calibrated
            // scale; tried after the multi-start of one shared focal.
            let split = o.cameras_from_data && intrinsics.groups() == 1;
            if let (Some(phi), Some(cal), true) =
                (calibrated, &o.calibration, split || intrinsics.groups() > 1)
            {
                let mut grouped = intrinsics.clone();
                let report = calibrate_cameras(&mut grouped, &image_pairs, phi, split, cal);
                cameras = Some((grouped, report));
            }
            if let Some(phi) = calibrated {
                report.focal_source = FocalSource::SelfCalibration;
                phi
            } else {
                let rotation_pairs: Vec<(usize, usize, Matrix3<f64>)> = matched
                    .iter()
                    .zip(&homography)
                    .filter_map(|(p, h)| h.map(|(h, _)| (p.first, p.second, h)))
                    .collect();
                report.focal_source = FocalSource::Homographies;
                focal_from_homographies(&rotation_pairs, &intrinsics, &o.focal_search)
                    .ok_or(SfmError::NoUsablePairs { images: n })?
            }
        };
        report.times.focal = clock.elapsed().as_secs_f64();

        let any_parallax = parallax.iter().any(|p| *p);
        let candidates: Vec<(f64, bool)> = if known_focal || !any_parallax {
            // Without parallax the focal comes from the rotation homographies alone: any other
            // start would treat the pairs as general and fit meaningless epipolar geometry.
            vec![(phi, false)]
        } else {
            std::iter::once(phi)
                .chain(o.focal_starts.iter().copied())
                .map(|p| (p, true))
                .chain(std::iter::once((o.focal_prior, false)))
                .collect()
        };
        let active = {
            let mut seen = vec![false; n];
            for p in &matched {
                seen[p.first] = true;
                seen[p.second] = true;
            }
            seen.iter().filter(|s| **s).count()
        };
        let subset = (candidates.len() > 1 && active > o.focal_selection_images)
            .then(|| selection_subset(n, &matched, o.focal_selection_images));
        let all_refs: Vec<&PairMatches> = pairs.iter().collect();
        type Trial<'p> = (Vec<&'p PairMatches>, Vec<Homography>);
        let ((trial_matched, trial_h), trial_all): (Trial<'_>, Vec<&PairMatches>) = match &subset {
            Some(keep) => (
                matched
                    .iter()
                    .zip(&homography)
                    .filter(|(p, _)| keep[p.first] && keep[p.second])
                    .map(|(p, h)| (*p, *h))
                    .unzip(),
                all_refs
                    .iter()
                    .copied()
                    .filter(|p| keep[p.first] && keep[p.second])
                    .collect(),
            ),
            None => ((matched.clone(), homography.clone()), all_refs.clone()),
        };
        // One start: solved, recorded, and kept unless a free focal left the search range.
        let attempt = |start: f64,
                       free: bool,
                       set: (&[&PairMatches], &[Homography]),
                       scored: &[&PairMatches],
                       intrinsics: &ImageIntrinsics,
                       report: &mut MapperReport|
         -> Result<Option<Solution>> {
            let s = self.solve_at_focal(
                start,
                set,
                scored,
                unsupported,
                intrinsics,
                free,
                solver,
                report,
            )?;
            let out_of_range = free && !(o.focal_search.min..=o.focal_search.max).contains(&s.phi);
            report.starts.push(FocalStart {
                start,
                phi: s.phi,
                free,
                images: s.members.len(),
                score: s.score,
                out_of_range,
            });
            Ok((!out_of_range).then_some(s))
        };
        let mut best: Option<Solution> = None;
        let mut tried: Vec<Solution> = Vec::new();
        for &(start, free) in &candidates {
            let s = attempt(
                start,
                free,
                (&trial_matched, &trial_h),
                &trial_all,
                &intrinsics,
                &mut report,
            )?;
            if let Some(s) = s {
                if o.focal_rival.is_some() && subset.is_none() {
                    tried.push(s.clone());
                }
                if best.as_ref().is_none_or(|b| s.score < b.score) {
                    best = Some(s);
                }
            }
        }
        if let (Some(rival_options), Some(bundle), Some(winner)) =
            (o.focal_rival, o.bundle, best.as_ref())
        {
            let rival = tried
                .iter()
                .filter(|s| {
                    let ratio = s.phi / winner.phi;
                    ratio.max(1.0 / ratio) >= rival_options.min_focal_ratio
                        && s.score <= winner.score * rival_options.max_cost_ratio
                })
                .min_by(|a, b| a.score.total_cmp(&b.score));
            if let Some(rival) = rival {
                let (tracks, _) = build_tracks(n, pairs)?;
                let rms = |s: &Solution| -> Result<f64> {
                    let mut cameras = s.cameras.clone();
                    let Some(reference) = cameras.iter().position(Option::is_some) else {
                        return Ok(f64::INFINITY);
                    };
                    let mut factors = vec![s.phi; intrinsics.groups()];
                    let mut options = bundle;
                    options.refine_focal &= s.free_focal;
                    let (_, r) = bundle_adjust(
                        &tracks,
                        &intrinsics,
                        &mut cameras,
                        &mut factors,
                        reference,
                        &options,
                    )?;
                    Ok(r.rms_px)
                };
                let (winner_rms, rival_rms) = (rms(winner)?, rms(rival)?);
                let switched = rival_rms < rival_options.max_rms_ratio * winner_rms;
                report.focal_rival = Some(FocalRivalReport {
                    winner_phi: winner.phi,
                    rival_phi: rival.phi,
                    winner_rms_px: winner_rms,
                    rival_rms_px: rival_rms,
                    switched,
                });
                if switched {
                    best = Some(rival.clone());
                }
            }
        }
        if let (Some(_), Some(chosen)) = (&subset, &best) {
            // The whole set once, from the subset winner's refined focal.
            let (start, free) = (chosen.phi, chosen.free_focal);
            best = attempt(
                start,
                free,
                (&matched, &homography),
                &all_refs,
                &intrinsics,
                &mut report,
            )?;
        }
        let Some(mut best) = best else {
            return Err(SfmError::NoUsablePairs { images: n });
        };
        // The cameras of their own: the whole set solved from their calibrated factor and
        // from the shared winner's, with the groups' ratios; kept when that explains the
        // matches better than one shared focal (the calibration's common scale can be off
        // where self-calibration is).
        if let Some((grouped, mut calibration)) = cameras.take() {
            let changed = grouped != intrinsics;
            if changed && any_parallax {
                for start in [calibration.start, best.phi] {
                    if let Some(s) = attempt(
                        start,
                        true,
                        (&matched, &homography),
                        &all_refs,
                        &grouped,
                        &mut report,
                    )? && s.score < best.score
                    {
                        best = s;
                        calibration.kept = true;
                    }
                }
            }
            if calibration.kept {
                intrinsics = grouped;
            } else {
                // From the data: one camera. Given groups stay, each from the shared focal.
                calibration.cameras = intrinsics.groups();
            }
            report.cameras = Some(calibration);
        }
        report.focal_factor_initial = phi;
        report.pairs_with_pose = best.pairs_with_pose;
        report.rotation_only_pairs = best.rotation_only_pairs;
        report.inconsistent_pairs = best.inconsistent_pairs;
        report.cycle_rejected_pairs = best.cycle_rejected_pairs;
        report.averaged_pairs = best.edges.iter().map(|&(a, b)| [a, b]).collect();
        report.no_parallax = best.no_parallax;
        report.rotation_averaging = best.rotations;
        report.translation_averaging = best.translations;
        report.sampson = best.sampson;
        let mut cameras = best.cameras;
        let mut phi_refined = best.phi;
        let mut points = Vec::new();

        let clock = Instant::now();
        let reference = (0..n).find(|&i| cameras[i].is_some());
        // The support check's rejected pairs take no part in the tracks.
        let filtered: Vec<PairMatches>;
        let pairs = if best.support_rejected.is_empty() {
            pairs
        } else {
            let rejected: HashSet<(usize, usize)> = best.support_rejected.iter().copied().collect();
            filtered = pairs
                .iter()
                .filter(|p| !rejected.contains(&(p.first, p.second)))
                .cloned()
                .collect();
            &filtered
        };
        if !unsupported.is_empty() {
            let rejected = best.support_rejected.len();
            report.support = Some(SupportReport {
                supported: matched.len().saturating_sub(unsupported.len()),
                confirmed: unsupported.len().saturating_sub(rejected),
                rejected,
                rejected_pairs: best.support_rejected.iter().map(|&(a, b)| [a, b]).collect(),
            });
        }
        let tracks = if o.bundle.is_some() || o.resection.is_some() {
            let (tracks, track_report) = build_tracks(n, pairs)?;
            report.tracks = Some(track_report);
            tracks
        } else {
            Vec::new()
        };
        if let Some(options) = &o.resection {
            report.resection = Some(resect_bridged_sides(
                &tracks,
                pairs,
                &intrinsics,
                phi_refined,
                &mut cameras,
                &best.edges,
                solver,
                options,
            )?);
        }
        report.times.resection = clock.elapsed().as_secs_f64();
        let clock = Instant::now();
        if let (Some(options), Some(reference)) = (o.bundle, reference) {
            let mut options = options;
            options.refine_focal &= best.free_focal;
            let (before, phi_before) = (cameras.clone(), phi_refined);
            // One focal factor per camera group, each starting from the shared one (the
            // groups' ratios are folded into the scales).
            let mut factors = vec![phi_refined; intrinsics.groups()];
            let (adjusted, r) = bundle_adjust(
                &tracks,
                &intrinsics,
                &mut cameras,
                &mut factors,
                reference,
                &options,
            )?;
            let range = o.focal_search.min..=o.focal_search.max;
            if options.refine_focal && !factors.iter().all(|f| range.contains(f)) {
                // The points drove a focal out of range: keep the pairwise solution.
                cameras = before;
                phi_refined = phi_before;
                report.bundle_undone = true;
            } else {
                phi_refined = intrinsics.fold_factors(&factors);
                points = adjusted;
            }
            report.bundle = Some(r);
        }
        report.times.bundle = clock.elapsed().as_secs_f64();
        report.focal_factor = phi_refined;
        report.focal_free = best.free_focal;
        report.estimated = (0..n).filter(|&i| cameras[i].is_some()).collect();
        report.not_estimated = (0..n)
            .filter(|&i| cameras[i].is_none())
            .map(|i| {
                let reason = if best.members.binary_search(&i).is_ok() {
                    NotEstimated::NoCentre
                } else {
                    NotEstimated::OutsideLargestComponent
                };
                (i, reason)
            })
            .collect();
        Ok(Reconstruction {
            cameras,
            phi: phi_refined,
            intrinsics,
            points,
            report,
        })
    }

    /// [`Self::run`] with a support check: `support[k]` says whether `pairs[k]` has evidence
    /// independent of its matches (for a learned matcher: its extractor's own descriptors
    /// matched without the network). At every focal start, before rotation averaging,
    /// supported pairs are kept; an unsupported pair is kept when a triangle of two kept pairs
    /// confirms its relative rotation ([`MapperOptions::support_triangle_deg`],
    /// [`crate::rotation_averaging::confirmed_by_trusted_triangles`]) or when it is the only
    /// link between two groups of kept pairs (a bridge, strongest first: nothing could confirm
    /// or contradict it). The chosen start's rejected pairs are left out of the tracks, the
    /// resection and the bundle adjustment too. Counts in [`MapperReport::support`].
    ///
    /// # Errors
    /// As [`Self::run`]; a support list of another length than `pairs`.
    pub fn run_with_support(
        &self,
        pairs: &[PairMatches],
        support: &[bool],
        intrinsics: ImageIntrinsics,
        known_focal: bool,
        solver: &dyn GeometrySolver,
    ) -> Result<Reconstruction> {
        if support.len() != pairs.len() {
            return Err(SfmError::InvalidInput(format!(
                "{} support flags for {} pairs",
                support.len(),
                pairs.len()
            )));
        }
        let unsupported: HashSet<(usize, usize)> = pairs
            .iter()
            .zip(support)
            .filter(|(p, s)| !p.is_empty() && !**s)
            .map(|(p, _)| (p.first, p.second))
            .collect();
        let mut r = self.run_checked(pairs, &unsupported, intrinsics, known_focal, solver)?;
        // Every pair supported: nothing was checked.
        r.report.support.get_or_insert(SupportReport {
            supported: r.report.pairs_with_matches,
            ..SupportReport::default()
        });
        Ok(r)
    }

    #[allow(clippy::too_many_arguments)]
    fn solve_at_focal(
        &self,
        phi: f64,
        (matched, homographies): (&[&PairMatches], &[Homography]),
        all_pairs: &[&PairMatches],
        unsupported: &HashSet<(usize, usize)>,
        intrinsics: &ImageIntrinsics,
        refine_focal: bool,
        solver: &dyn GeometrySolver,
        report: &mut MapperReport,
    ) -> Result<Solution> {
        let o = &self.options;
        let n = intrinsics.len();
        let clock = Instant::now();
        let poses: Vec<Option<RelativePose>> = matched
            .par_iter()
            .zip(homographies)
            .map(|(p, h)| {
                solver.relative_pose(
                    p,
                    *h,
                    &intrinsics.k(phi, p.first),
                    &intrinsics.k(phi, p.second),
                )
            })
            .collect::<Result<_>>()?;
        report.times.two_view += clock.elapsed().as_secs_f64();
        let clock = Instant::now();
        let mut rotations = Vec::new();
        let mut directions_local = Vec::new();
        for (p, pose) in matched.iter().zip(poses) {
            let Some(pose) = pose else { continue };
            let (rotation, translation, inliers) = match pose {
                RelativePose::General {
                    rotation,
                    translation,
                    inliers,
                } => (rotation, Some(translation), inliers),
                RelativePose::RotationOnly { rotation, inliers } => (rotation, None, inliers),
            };
            rotations.push(RelativeRotation {
                first: p.first,
                second: p.second,
                rotation: Rotation3::from_matrix(&rotation),
                weight: inliers as f64,
            });
            directions_local.push(translation);
        }
        let pairs_with_pose = rotations.len();
        // The rotation-only pairs (no direction), left out of the Sampson refinement below.
        let tied: HashSet<(usize, usize)> = rotations
            .iter()
            .zip(&directions_local)
            .filter(|(_, t)| t.is_none())
            .map(|(r, _)| (r.first, r.second))
            .collect();
        let rotation_only_pairs = tied.len();

        // Pairs that every triangle through them contradicts are dropped first; then rotation
        // averaging on the largest component, inconsistent pairs dropped, once.
        let mut keep = match o.cycle_check {
            Some(c) => unconfirmed_by_cycles(&rotations, c.threshold_deg, c.min_triangles)
                .iter()
                .map(|dropped| !dropped)
                .collect(),
            None => vec![true; rotations.len()],
        };
        let cycle_rejected_pairs = keep.iter().filter(|k| !**k).count();
        let mut support_rejected = Vec::new();
        if !unsupported.is_empty() {
            let trusted: Vec<bool> = rotations
                .iter()
                .map(|r| !unsupported.contains(&(r.first, r.second)))
                .collect();
            let mut confirmed =
                confirmed_by_trusted_triangles(&rotations, &trusted, o.support_triangle_deg);
            keep_bridges(n, &rotations, &mut confirmed);
            // The bridges are trusted now: what their triangles confirm joins them.
            confirmed =
                confirmed_by_trusted_triangles(&rotations, &confirmed, o.support_triangle_deg);
            for ((k, c), r) in keep.iter_mut().zip(&confirmed).zip(&rotations) {
                if !c {
                    *k = false;
                    support_rejected.push((r.first, r.second));
                }
            }
            // Unsupported pairs without a relative pose are rejected too.
            let posed: HashSet<(usize, usize)> =
                rotations.iter().map(|r| (r.first, r.second)).collect();
            support_rejected.extend(
                matched
                    .iter()
                    .map(|p| (p.first, p.second))
                    .filter(|q| unsupported.contains(q) && !posed.contains(q)),
            );
        }
        let mut members = Vec::new();
        let mut absolute = vec![None; n];
        let mut inconsistent_pairs = 0;
        let mut rotation_report = RotationAveragingReport::default();
        for round in 0..2 {
            let edges: Vec<RelativeRotation> = rotations
                .iter()
                .zip(&keep)
                .filter(|(_, k)| **k)
                .map(|(r, _)| *r)
                .collect();
            let graph: Vec<(usize, usize, f64)> = edges
                .iter()
                .map(|e| (e.first, e.second, e.weight))
                .collect();
            members = largest_component(n, &graph);
            let Some(&reference) = members.first() else {
                break;
            };
            (absolute, rotation_report) =
                average_rotations(n, &edges, reference, &o.rotation_averaging)?;
            if round == 1 {
                break;
            }
            let residuals = rotation_residuals_deg(&rotations, &absolute);
            let mut dropped = 0;
            for (k, r) in keep.iter_mut().zip(&residuals) {
                if *k && r.is_some_and(|r| r > o.max_rotation_residual_deg) {
                    *k = false;
                    dropped += 1;
                }
            }
            inconsistent_pairs = dropped;
            if dropped == 0 {
                break;
            }
        }
        let empty = |members: Vec<usize>| Solution {
            cameras: vec![None; n],
            members,
            edges: Vec::new(),
            phi,
            pairs_with_pose,
            rotation_only_pairs,
            inconsistent_pairs,
            cycle_rejected_pairs,
            support_rejected: support_rejected.clone(),
            no_parallax: false,
            rotations: rotation_report,
            translations: TranslationAveragingReport::default(),
            sampson: None,
            score: f64::INFINITY,
            free_focal: refine_focal,
        };
        let Some(&reference) = members.first() else {
            report.times.averaging += clock.elapsed().as_secs_f64();
            return Ok(empty(members));
        };
        let directions: Vec<CenterDirection> = rotations
            .iter()
            .zip(&directions_local)
            .zip(&keep)
            .filter(|(_, k)| **k)
            .filter_map(|((r, t), _)| {
                let rb = absolute[r.second]?;
                Some(CenterDirection {
                    first: r.first,
                    second: r.second,
                    direction: t.map(|t| rb.inverse() * t),
                    weight: r.weight,
                })
            })
            .collect();
        let no_parallax = directions.iter().all(|d| d.direction.is_none());
        let (centres, translation_report) = average_translations(
            n,
            &members,
            &directions,
            reference,
            &o.translation_averaging,
        )?;
        report.times.averaging += clock.elapsed().as_secs_f64();
        let clock = Instant::now();
        let mut cameras: Vec<Option<CameraPose>> = (0..n)
            .map(|i| match (absolute[i], centres[i]) {
                (Some(rotation), Some(center)) if members.binary_search(&i).is_ok() => {
                    Some(CameraPose { rotation, center })
                }
                _ => None,
            })
            .collect();
        let mut phi = phi;
        let mut sampson = None;
        let rejected: HashSet<(usize, usize)> = support_rejected.iter().copied().collect();
        let score_rejected: HashSet<(usize, usize)> = if o.score_dropped_as_missing {
            rotations
                .iter()
                .zip(&keep)
                .filter(|(_, k)| !**k)
                .map(|(r, _)| (r.first, r.second))
                .chain(rejected.iter().copied())
                .collect()
        } else {
            rejected.clone()
        };
        let cauchy = match o.sampson {
            Some(mut options) => {
                options.refine_focal &= refine_focal;
                // Rotation-only pairs (zero baseline) have no epipolar geometry: left out, also
                // where translation averaging gave them distinct centres (a tie group spanned by
                // direction pairs): with them in, a 300-frame forward walk's initialisation took
                // 139 s instead of 73 s fitting noise. So are the pairs the support check dropped.
                let lm_pairs: Vec<&PairMatches> = matched
                    .iter()
                    .filter(|p| !rejected.contains(&(p.first, p.second)))
                    .filter(|p| !tied.contains(&(p.first, p.second)))
                    .filter(|p| match (cameras[p.first], cameras[p.second]) {
                        (Some(a), Some(b)) => (a.center - b.center).norm() > 0.0,
                        _ => false,
                    })
                    .copied()
                    .collect();
                sampson = Some(refine_sampson(
                    &lm_pairs,
                    intrinsics,
                    &mut cameras,
                    &mut phi,
                    reference,
                    &options,
                )?);
                options.cauchy_px
            }
            None => SampsonRefineOptions::default().cauchy_px,
        };
        // A pair the support check (and with `score_dropped_as_missing` any check) dropped
        // costs what a pair without cameras costs (the missing penalty per match), whatever
        // the cameras predict for it: a start is not rewarded for fitting pairs it did not use.
        let (dropped, scored): (Vec<&PairMatches>, Vec<&PairMatches>) = all_pairs
            .iter()
            .partition(|p| score_rejected.contains(&(p.first, p.second)));
        let score = robust_cost(
            &scored,
            intrinsics,
            &cameras,
            phi,
            cauchy,
            o.missing_penalty_px,
        )? + robust_cost(
            &dropped,
            intrinsics,
            &vec![None; n],
            phi,
            cauchy,
            o.missing_penalty_px,
        )?;
        report.times.refinement += clock.elapsed().as_secs_f64();
        let edges = rotations
            .iter()
            .zip(&keep)
            .filter(|(r, k)| **k && cameras[r.first].is_some() && cameras[r.second].is_some())
            .map(|(r, _)| (r.first, r.second))
            .collect();
        Ok(Solution {
            cameras,
            members,
            edges,
            phi,
            pairs_with_pose,
            rotation_only_pairs,
            inconsistent_pairs,
            cycle_rejected_pairs,
            support_rejected,
            no_parallax,
            rotations: rotation_report,
            translations: translation_report,
            sampson,
            score,
            free_focal: refine_focal,
        })
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn pair(first: usize, second: usize, n: usize) -> PairMatches {
        PairMatches::placeholder(first, second, n)
    }

    #[test]
    fn the_focal_subset_grows_from_the_best_matched_image_along_strong_pairs() {
        // A chain 0–1–2–3–4–5 and a weak shortcut 3–0; image 3 has the most matches.
        let pairs = [
            pair(0, 1, 50),
            pair(1, 2, 60),
            pair(2, 3, 90),
            pair(3, 4, 80),
            pair(4, 5, 70),
            pair(3, 0, 21),
        ];
        let refs: Vec<&PairMatches> = pairs.iter().collect();
        let keep = selection_subset(6, &refs, 3);
        assert_eq!(keep, vec![false, false, true, true, true, false]);
        let keep = selection_subset(6, &refs, 4);
        assert_eq!(keep.iter().filter(|k| **k).count(), 4);
        assert!(keep[0], "the weak shortcut is the next neighbour of 3");
        assert!(selection_subset(6, &refs, 10).iter().all(|k| *k));
    }
}
