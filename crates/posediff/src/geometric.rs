//! Cameras without a checkpoint: matches → pairwise two-view geometry → a shared focal by
//! self-calibration → rotation averaging → translation averaging → the GGS objective refined to
//! convergence.
//!
//! | stage | method | crate |
//! |---|---|---|
//! | matches | SIFT, mutual NN + ratio, MAGSAC-verified (≥ 20 per pair) | `posediff-matching` |
//! | pair type | homography RANSAC: ≥ 90 % of the matches within 1 px = no parallax measured | `posediff-matching::two_view` |
//! | focal | Mendonça–Cipolla over the least-squares `F` of the parallax pairs (`f = φ·max(W, H)`) | `posediff-guidance::selfcal` |
//! | relative poses | OpenCV five-point RANSAC + cheirality on normalised matches; rotation-only pairs from the homography | `posediff-matching::two_view` |
//! | rotations | maximum spanning tree + Cauchy IRLS in the Lie algebra; edges off by > 10° dropped | `posediff-guidance::averaging` |
//! | centres | LUD (`s ≥ 1`) by IRLS with an active set; rotation-only pairs tie centres | `posediff-guidance::averaging` |
//! | refinement | Levenberg–Marquardt on Cauchy-robust Sampson distances, all cameras + focal | `posediff-guidance::refine` |
//! | bundle adjustment | tracks by union-find, linear triangulation, LM with Schur complement on reprojection errors | `posediff-guidance::bundle` |
//!
//! Only the largest connected component of the view graph is estimated; every other image is
//! reported as not estimated. Principal points are the image centres (`((W−1)/2, (H−1)/2)`).

use std::path::PathBuf;
use std::time::Instant;

use nalgebra::{Matrix3, Rotation3};
use posediff_geometry::{
    Camera, CenterCrop, ImageSize, Intrinsics, MODEL_INPUT_SIDE, Pose, PoseEncoding, QuaternionSign,
};
use posediff_guidance::averaging::{
    CenterDirection, RelativeRotation, RotationAveragingConfig, TranslationAveragingConfig,
    average_rotations, average_translations, largest_component, rotation_residuals_deg,
};
use posediff_guidance::bundle::{BundleConfig, build_tracks, bundle_adjust};
use posediff_guidance::refine::robust_cost;
use posediff_guidance::selfcal::{FocalSearch, PairFundamental, self_calibrate};
use posediff_guidance::{
    GgsConfig, GgsSolver, ImageIntrinsics, MatchSet, RefineCamera, RefineConfig, RefineReport,
    refine_cameras,
};
use posediff_matching::two_view::{
    fundamental_least_squares, homography_fit, homography_rotation, relative_pose,
};
use posediff_matching::{MatchConfig, PairMatches, RelativePose, TwoViewConfig, match_images};

use crate::error::{PosediffError, Result};

/// What is known of the intrinsics.
#[derive(Debug, Clone, PartialEq)]
pub enum KnownIntrinsics {
    /// Nothing: a shared focal is estimated.
    Unknown,
    /// One focal length in pixels for every image (principal points at the centres).
    FocalPx(f64),
    /// Full intrinsics per image (fixed; the focal is not refined).
    PerImage(Vec<Intrinsics>),
}

/// How the cameras are refined after the initialisation.
#[derive(Debug, Clone, Copy, PartialEq)]
pub enum Refinement {
    /// None: the averaged cameras.
    None,
    /// The Sampson objective to convergence (Levenberg–Marquardt).
    Converge(RefineConfig),
    /// The official GGS schedule (five SGD phases, 7000 iterations by default) on the cameras
    /// in their 224 crops, as the released code runs it inside the diffusion.
    Official(GgsConfig),
}

/// Settings of the geometric estimate.
#[derive(Debug, Clone, PartialEq)]
pub struct GeometricConfig {
    /// Matching.
    pub matching: MatchConfig,
    /// Two-view geometry.
    pub two_view: TwoViewConfig,
    /// Known intrinsics.
    pub intrinsics: KnownIntrinsics,
    /// Focal search range (`φ = f / max(W, H)`).
    pub focal_search: FocalSearch,
    /// Rotation averaging.
    pub rotations: RotationAveragingConfig,
    /// Translation averaging.
    pub translations: TranslationAveragingConfig,
    /// Pairs whose relative rotation disagrees with the averaged rotations by more than this
    /// (degrees) are dropped before translation averaging.
    pub max_rotation_residual_deg: f64,
    /// Refinement.
    pub refinement: Refinement,
    /// Focal factors `φ` tried besides the self-calibrated one (multi-start); unused when the
    /// focal is known.
    pub focal_starts: Vec<f64>,
    /// The focal factor used (fixed) when the data cannot determine it: COLMAP's default
    /// `1.2 · max(W, H)`.
    pub focal_prior: f64,
    /// Bundle adjustment with tracks after the refinement (with [`Refinement::Converge`]).
    pub bundle: Option<BundleConfig>,
}

impl Default for GeometricConfig {
    fn default() -> Self {
        let mut matching = MatchConfig::default();
        matching.features.contrast_threshold = GEOMETRIC_CONTRAST_THRESHOLD;
        matching.features.max_keypoints = GEOMETRIC_MAX_KEYPOINTS;
        Self {
            matching,
            two_view: TwoViewConfig::default(),
            intrinsics: KnownIntrinsics::Unknown,
            focal_search: FocalSearch::default(),
            rotations: RotationAveragingConfig::default(),
            translations: TranslationAveragingConfig::default(),
            max_rotation_residual_deg: 10.0,
            refinement: Refinement::Converge(RefineConfig::default()),
            focal_starts: vec![0.4, 0.6, 0.9, 1.35, 2.0, 3.0],
            focal_prior: 1.2,
            bundle: Some(BundleConfig::default()),
        }
    }
}

/// SIFT contrast threshold of the checkpoint-free path: below OpenCV's 0.04, for the weakly
/// textured objects of object-centric captures (measured on the shared sets; see
/// docs/BENCHMARKS.md).
pub const GEOMETRIC_CONTRAST_THRESHOLD: f64 = 0.03;

/// Keypoints per image of the checkpoint-free path (COLMAP's default; the official GGS
/// matching keeps hloc's 4096).
pub const GEOMETRIC_MAX_KEYPOINTS: usize = 8192;

/// Wall-clock seconds per stage.
#[derive(Debug, Clone, Copy, Default, PartialEq, serde::Serialize)]
pub struct GeometricTimes {
    /// Features and matching.
    pub matching: f64,
    /// Every focal start: two-view geometry, averaging and the Sampson refinement.
    pub initialisation: f64,
    /// The bundle adjustment of the chosen start (or the official GGS schedule).
    pub refinement: f64,
}

/// What the estimate did, for run.json.
#[derive(Debug, Clone, Default, PartialEq, serde::Serialize)]
pub struct GeometricReport {
    /// Pairs with verified matches.
    pub pairs_with_matches: usize,
    /// Pairs with a relative pose (general or rotation-only).
    pub pairs_with_pose: usize,
    /// Of those, rotation-only pairs.
    pub rotation_only_pairs: usize,
    /// Pairs dropped by the rotation-consistency check.
    pub inconsistent_pairs: usize,
    /// The images estimated (the largest view-graph component).
    pub estimated: Vec<usize>,
    /// Where the focal came from: "self-calibration", "homographies", "given".
    pub focal_source: String,
    /// `φ = f / max(W, H)` before refinement.
    pub focal_factor_initial: f64,
    /// `φ` after refinement.
    pub focal_factor: f64,
    /// Refinement: accepted steps.
    pub refine_iterations: usize,
    /// Refinement converged (not stopped by the iteration limit).
    pub refine_converged: bool,
    /// Matches within 3 px of their epipolar geometry after refinement / used.
    pub refine_inliers: usize,
    /// Matches used by the refinement.
    pub refine_matches: usize,
    /// RMS Sampson distance of those inliers, px.
    pub refine_inlier_rms_px: f64,
    /// Points triangulated and adjusted by the bundle adjustment (0: not run).
    pub bundle_points: usize,
    /// Their observations.
    pub bundle_observations: usize,
    /// RMS reprojection error after the bundle adjustment, px.
    pub bundle_rms_px: f64,
    /// Stage timings.
    pub times: GeometricTimes,
}

impl GeometricReport {
    /// Takes the refinement's statistics.
    fn record_refine(&mut self, r: &RefineReport) {
        self.refine_iterations = r.iterations;
        self.refine_converged = r.converged;
        self.refine_inliers = r.inliers;
        self.refine_matches = r.matches;
        self.refine_inlier_rms_px = r.inlier_rms_px;
    }
}

/// The cameras of a geometric estimate: `None` for images that were not estimated.
#[derive(Debug, Clone, PartialEq)]
pub struct GeometricEstimate {
    /// One per image, in input order.
    pub cameras: Vec<Option<Camera>>,
    /// Image sizes.
    pub sizes: Vec<ImageSize>,
    /// Matches of every pair (original pixels).
    pub pairs: Vec<PairMatches>,
    /// Statistics.
    pub report: GeometricReport,
    /// Things the user should know.
    pub warnings: Vec<String>,
}

/// The image centre in OpenCV pixels (pixel centres at integers).
pub fn image_centre(size: ImageSize) -> [f64; 2] {
    [
        (f64::from(size.width()) - 1.0) / 2.0,
        (f64::from(size.height()) - 1.0) / 2.0,
    ]
}

/// The focal scale `s` of `f = φ·s`: the longer side.
pub fn focal_scale(size: ImageSize) -> f64 {
    f64::from(size.width().max(size.height()))
}

/// Estimates cameras of `images` without a checkpoint.
///
/// # Errors
/// Fewer than two images, unreadable images, matching errors, no pair with enough matches.
pub fn estimate_geometric(
    images: &[PathBuf],
    config: &GeometricConfig,
) -> Result<GeometricEstimate> {
    let (sizes, pairs, matching) = match_all(images, &config.matching)?;
    let mut estimate = estimate_from_matches(&sizes, pairs, config)?;
    estimate.report.times.matching = matching;
    Ok(estimate)
}

/// Image sizes and the matches of every pair, with the seconds it took.
fn match_all(
    images: &[PathBuf],
    config: &MatchConfig,
) -> Result<(Vec<ImageSize>, Vec<PairMatches>, f64)> {
    if images.len() < 2 {
        return Err(PosediffError::TooFewImages {
            needed: 2,
            got: images.len(),
        });
    }
    let start = Instant::now();
    let (features, pairs) = match_images(images, None, config)?;
    let sizes = features.iter().map(|f| f.image_size).collect();
    Ok((sizes, pairs, start.elapsed().as_secs_f64()))
}

/// Refines cameras from elsewhere (e.g. COLMAP's, converted to cameras.json) on the matches of
/// `images` instead of initialising them; `None` entries stay not estimated. The focal is
/// refined as one shared factor (started from the mean of the given focals) unless
/// `config.intrinsics` fixes it. With [`Refinement::None`] the cameras come back unchanged.
///
/// # Errors
/// As [`estimate_geometric`]; a count of cameras that does not match the images; fewer than
/// one given camera.
pub fn refine_given_cameras(
    images: &[PathBuf],
    init: &[Option<Camera>],
    config: &GeometricConfig,
) -> Result<GeometricEstimate> {
    if init.len() != images.len() {
        return Err(PosediffError::InvalidArgument(format!(
            "{} initial cameras for {} images",
            init.len(),
            images.len()
        )));
    }
    let (sizes, pairs, matching) = match_all(images, &config.matching)?;
    let n = sizes.len();
    let (layout, known_phi) = intrinsics_layout(&sizes, &config.intrinsics)?;
    let given: Vec<f64> = init
        .iter()
        .zip(&layout.scale)
        .filter_map(|(c, s)| c.map(|c| 0.5 * (c.intrinsics.fx() + c.intrinsics.fy()) / s))
        .collect();
    let Some(reference) = init.iter().position(Option::is_some) else {
        return Err(PosediffError::InvalidArgument(
            "no initial camera is estimated".into(),
        ));
    };
    let mut phi = known_phi.unwrap_or(given.iter().sum::<f64>() / given.len() as f64);
    let mut cameras: Vec<Option<RefineCamera>> = init
        .iter()
        .map(|c| {
            c.map(|c| RefineCamera {
                rotation: Rotation3::from_matrix(&c.cam_from_world.rotation),
                center: c.center().coords,
            })
        })
        .collect();
    let mut report = GeometricReport {
        pairs_with_matches: pairs.iter().filter(|p| !p.is_empty()).count(),
        focal_source: if known_phi.is_some() {
            "given"
        } else {
            "initial cameras"
        }
        .into(),
        focal_factor_initial: phi,
        ..GeometricReport::default()
    };
    report.times.matching = matching;
    let start = Instant::now();
    let mut out: Vec<Option<Camera>> = init.to_vec();
    if let Refinement::Converge(mut refine) = config.refinement {
        refine.refine_focal &= known_phi.is_none();
        let set = pixel_match_set(n, &pairs)?;
        let r = refine_cameras(&set, &layout, &mut cameras, &mut phi, reference, &refine)?;
        report.record_refine(&r);
        for (i, (o, c)) in out.iter_mut().zip(&cameras).enumerate() {
            if let (Some(o), Some(c)) = (o.as_mut(), c) {
                let r = *c.rotation.matrix();
                o.cam_from_world = Pose::new(r, -(r * c.center));
                o.intrinsics = match &config.intrinsics {
                    KnownIntrinsics::PerImage(k) => k[i],
                    _ => Intrinsics::from_matrix(&k_of(&layout, phi, i))?,
                };
            }
        }
    }
    if let Refinement::Official(ggs) = config.refinement {
        let mut ggs = ggs;
        ggs.fix_focal |= known_phi.is_some();
        official_ggs(&mut out, &pairs, &ggs)?;
    }
    report.focal_factor = phi;
    report.estimated = (0..n).filter(|&i| out[i].is_some()).collect();
    report.times.refinement = start.elapsed().as_secs_f64();
    Ok(GeometricEstimate {
        cameras: out,
        sizes,
        pairs,
        report,
        warnings: Vec::new(),
    })
}

/// Per image, the known intrinsics in original pixels (`None` when unknown); a focal alone puts
/// the principal point at the image centre.
///
/// # Errors
/// A count that does not match the images, a non-positive focal.
pub fn resolve_intrinsics(
    known: &KnownIntrinsics,
    sizes: &[ImageSize],
) -> Result<Option<Vec<Intrinsics>>> {
    match known {
        KnownIntrinsics::Unknown => Ok(None),
        KnownIntrinsics::FocalPx(f) => sizes
            .iter()
            .map(|s| {
                let c = image_centre(*s);
                Intrinsics::new(*f, *f, c[0], c[1]).map_err(|_| {
                    PosediffError::InvalidArgument(format!(
                        "focal length must be positive, got {f}"
                    ))
                })
            })
            .collect::<Result<Vec<_>>>()
            .map(Some),
        KnownIntrinsics::PerImage(k) if k.len() == sizes.len() => Ok(Some(k.clone())),
        KnownIntrinsics::PerImage(k) => Err(PosediffError::InvalidArgument(format!(
            "{} intrinsics for {} images",
            k.len(),
            sizes.len()
        ))),
    }
}

/// The per-image principal points and focal scales, and `φ` when the focal is known.
fn intrinsics_layout(
    sizes: &[ImageSize],
    known: &KnownIntrinsics,
) -> Result<(ImageIntrinsics, Option<f64>)> {
    Ok(match resolve_intrinsics(known, sizes)? {
        None => (
            ImageIntrinsics {
                principal: sizes.iter().map(|s| image_centre(*s)).collect(),
                scale: sizes.iter().map(|s| focal_scale(*s)).collect(),
            },
            None,
        ),
        // Square pixels are assumed by the refinement: the mean of fx and fy.
        Some(k) => (
            ImageIntrinsics {
                principal: k.iter().map(|k| [k.cx(), k.cy()]).collect(),
                scale: k.iter().map(|k| 0.5 * (k.fx() + k.fy())).collect(),
            },
            Some(1.0),
        ),
    })
}

fn k_of(layout: &ImageIntrinsics, phi: f64, i: usize) -> Matrix3<f64> {
    let f = phi * layout.scale[i];
    let c = layout.principal[i];
    Matrix3::new(f, 0.0, c[0], 0.0, f, c[1], 0.0, 0.0, 1.0)
}

/// The matches of the pairs as a match set in original pixels.
///
/// # Errors
/// Invalid pairs.
pub fn pixel_match_set<'p>(
    n_images: usize,
    pairs: impl IntoIterator<Item = &'p PairMatches>,
) -> Result<MatchSet> {
    let (mut kp1, mut kp2, mut frames) = (Vec::new(), Vec::new(), Vec::new());
    for p in pairs {
        kp1.extend_from_slice(&p.kp1);
        kp2.extend_from_slice(&p.kp2);
        frames.extend(std::iter::repeat_n((p.first, p.second), p.len()));
    }
    Ok(MatchSet::new(n_images, &kp1, &kp2, &frames)?)
}

/// [`estimate_geometric`] from matches already made.
///
/// # Errors
/// Fewer than two images, no pair with enough matches, invalid known intrinsics.
pub fn estimate_from_matches(
    sizes: &[ImageSize],
    pairs: Vec<PairMatches>,
    config: &GeometricConfig,
) -> Result<GeometricEstimate> {
    let n = sizes.len();
    if n < 2 {
        return Err(PosediffError::TooFewImages { needed: 2, got: n });
    }
    let start = Instant::now();
    let mut report = GeometricReport::default();
    let mut warnings = Vec::new();
    let matched: Vec<&PairMatches> = pairs.iter().filter(|p| !p.is_empty()).collect();
    report.pairs_with_matches = matched.len();
    if matched.is_empty() {
        return Err(PosediffError::NoMatches { images: n });
    }
    let (layout, known_phi) = intrinsics_layout(sizes, &config.intrinsics)?;

    // Homography test (no intrinsics needed): pairs without measurable parallax.
    let homography: Vec<Option<(Matrix3<f64>, f64)>> = matched
        .iter()
        .map(|p| homography_fit(&p.kp1, &p.kp2, &config.two_view))
        .collect::<std::result::Result<_, _>>()?;
    let parallax: Vec<bool> = homography
        .iter()
        .map(|h| h.is_none_or(|(_, fraction)| fraction < config.two_view.homography_fraction))
        .collect();

    let phi = match known_phi {
        Some(phi) => {
            report.focal_source = "given".into();
            phi
        }
        None => {
            let mut fundamentals = Vec::new();
            for (p, _) in matched.iter().zip(&parallax).filter(|(_, par)| **par) {
                if let Some(f) = fundamental_least_squares(&p.kp1, &p.kp2)? {
                    fundamentals.push(PairFundamental {
                        f,
                        principal_a: layout.principal[p.first],
                        principal_b: layout.principal[p.second],
                        scale_a: layout.scale[p.first],
                        scale_b: layout.scale[p.second],
                        weight: (p.len() as f64).sqrt(),
                    });
                }
            }
            if let Some(phi) = self_calibrate(&fundamentals, &config.focal_search) {
                report.focal_source = "self-calibration".into();
                phi
            } else {
                let rotation_pairs: Vec<(usize, usize, Matrix3<f64>)> = matched
                    .iter()
                    .zip(&homography)
                    .filter_map(|(p, h)| h.map(|(h, _)| (p.first, p.second, h)))
                    .collect();
                report.focal_source = "homographies".into();
                focal_from_homographies(&rotation_pairs, &layout, &config.focal_search)
                    .ok_or(PosediffError::NoMatches { images: n })?
            }
        }
    };
    // Multi-start over the focal: the self-calibrated value and a log grid (the Sampson cost is
    // flat in the focal for narrow fields of view, and self-calibration can be far off); the
    // solution with the lowest robust cost over all matches wins. A free focal that leaves the
    // search range is unobservable (optical axes meeting at one point, as in object-centric
    // captures, make it so for two or three views): such solutions are dropped, and the prior
    // focal (fixed) is always a candidate.
    let any_parallax = parallax.iter().any(|p| *p);
    let candidates: Vec<(f64, bool)> = match known_phi {
        Some(phi) => vec![(phi, false)],
        // Without parallax the focal comes from the rotation homographies alone: any other
        // start would treat the pairs as general and fit meaningless epipolar geometry.
        None if !any_parallax => vec![(phi, false)],
        None => std::iter::once(phi)
            .chain(config.focal_starts.iter().copied())
            .map(|p| (p, true))
            .chain(std::iter::once((config.focal_prior, false)))
            .collect(),
    };
    let set = pixel_match_set(n, &pairs)?;
    let mut best: Option<Solution> = None;
    for &(start_phi, free) in &candidates {
        let solution = solve_at_focal(start_phi, &matched, &layout, &set, free, config)?;
        if free && !(config.focal_search.min..=config.focal_search.max).contains(&solution.phi) {
            log::debug!(
                "focal start {start_phi:.3}: phi {:.4} out of range",
                solution.phi
            );
            continue;
        }
        log::debug!(
            "focal start {start_phi:.3}: phi {:.4}, {} images, score {:.2}",
            solution.phi,
            solution.members.len(),
            solution.score
        );
        if best.as_ref().is_none_or(|b| solution.score < b.score) {
            best = Some(solution);
        }
    }
    let Some(best) = best else {
        return Err(PosediffError::NoMatches { images: n });
    };
    report.times.initialisation = start.elapsed().as_secs_f64();
    let start = Instant::now();
    let Solution {
        mut cameras,
        members,
        phi: mut phi_refined,
        stats,
        refine,
        free_focal,
        ..
    } = best;
    if let (Refinement::Converge(_), Some(bundle), Some(&reference)) =
        (config.refinement, config.bundle, members.first())
    {
        let tracks = build_tracks(
            n,
            pairs
                .iter()
                .map(|p| (p.first, p.second, &p.kp1[..], &p.kp2[..])),
        );
        let mut bundle = bundle;
        bundle.refine_focal &= free_focal;
        let (before, phi_before) = (cameras.clone(), phi_refined);
        let r = bundle_adjust(
            &tracks,
            &layout,
            &mut cameras,
            &mut phi_refined,
            reference,
            &bundle,
        )?;
        if bundle.refine_focal
            && !(config.focal_search.min..=config.focal_search.max).contains(&phi_refined)
        {
            // The points drove the focal out of range: keep the pairwise solution.
            cameras = before;
            phi_refined = phi_before;
        } else {
            report.bundle_points = r.points;
            report.bundle_observations = r.observations;
            report.bundle_rms_px = r.rms_px;
        }
    }
    report.focal_factor_initial = phi;
    report.pairs_with_pose = stats.pairs_with_pose;
    report.rotation_only_pairs = stats.rotation_only_pairs;
    report.inconsistent_pairs = stats.inconsistent_pairs;
    if stats.no_parallax {
        warnings.push(
            "no pair has measurable parallax (pure rotation or identical images): all camera \
             centres coincide"
                .into(),
        );
    }
    if let Some(r) = &refine {
        report.record_refine(r);
    }
    report.focal_factor = phi_refined;
    report.times.refinement = start.elapsed().as_secs_f64();
    report.estimated = members.clone();
    let not_estimated = n - members.len();
    if not_estimated > 0 {
        warnings.push(format!(
            "{not_estimated} of {n} images share no usable matches with the largest group and are \
             not estimated"
        ));
    }
    let mut cameras = cameras
        .iter()
        .enumerate()
        .map(|(i, c)| {
            let Some(c) = c else { return Ok(None) };
            let r = *c.rotation.matrix();
            let k = k_of(&layout, phi_refined, i);
            let intrinsics = match &config.intrinsics {
                KnownIntrinsics::PerImage(given) => given[i],
                _ => Intrinsics::from_matrix(&k)?,
            };
            Ok(Some(Camera::new(
                intrinsics,
                Pose::new(r, -(r * c.center)),
                sizes[i],
            )))
        })
        .collect::<Result<Vec<_>>>()?;
    if let Refinement::Official(ggs) = config.refinement {
        let start = Instant::now();
        let mut ggs = ggs;
        ggs.fix_focal |= known_phi.is_some();
        official_ggs(&mut cameras, &pairs, &ggs)?;
        report.times.refinement += start.elapsed().as_secs_f64();
    }
    Ok(GeometricEstimate {
        cameras,
        sizes: sizes.to_vec(),
        pairs,
        report,
        warnings,
    })
}

/// Pair statistics of one solve.
#[derive(Debug, Clone, Copy, Default)]
struct SolveStats {
    pairs_with_pose: usize,
    rotation_only_pairs: usize,
    inconsistent_pairs: usize,
    no_parallax: bool,
}

/// Cameras initialised and refined from one starting focal.
struct Solution {
    cameras: Vec<Option<RefineCamera>>,
    members: Vec<usize>,
    phi: f64,
    stats: SolveStats,
    refine: Option<RefineReport>,
    /// Robust cost over all matches, unestimated pairs at the penalty.
    score: f64,
    /// Whether the focal was refined (not held at a given value or the prior).
    free_focal: bool,
}

fn solve_at_focal(
    phi: f64,
    matched: &[&PairMatches],
    layout: &ImageIntrinsics,
    set: &MatchSet,
    refine_focal: bool,
    config: &GeometricConfig,
) -> Result<Solution> {
    let n = layout.scale.len();
    let mut stats = SolveStats::default();
    let mut rotations = Vec::new();
    let mut directions_local = Vec::new();
    for p in matched {
        let (ka, kb) = (k_of(layout, phi, p.first), k_of(layout, phi, p.second));
        let Some(pose) = relative_pose(&p.kp1, &p.kp2, &ka, &kb, &config.two_view)? else {
            continue;
        };
        let (rotation, translation, inliers) = match pose {
            RelativePose::General {
                rotation,
                translation,
                inliers,
            } => (rotation, Some(translation), inliers),
            RelativePose::RotationOnly { rotation, inliers } => {
                stats.rotation_only_pairs += 1;
                (rotation, None, inliers)
            }
        };
        rotations.push(RelativeRotation {
            first: p.first,
            second: p.second,
            rotation: Rotation3::from_matrix(&rotation),
            weight: inliers as f64,
        });
        directions_local.push(translation);
    }
    stats.pairs_with_pose = rotations.len();

    // Rotation averaging on the largest component, inconsistent pairs dropped, repeated once.
    let mut keep = vec![true; rotations.len()];
    let mut members = Vec::new();
    let mut absolute = vec![None; n];
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
        absolute = average_rotations(n, &edges, reference, &config.rotations);
        if round == 1 {
            break;
        }
        let residuals = rotation_residuals_deg(&rotations, &absolute);
        let mut dropped = 0;
        for (k, r) in keep.iter_mut().zip(&residuals) {
            if r.is_some_and(|r| r > config.max_rotation_residual_deg) {
                *k = false;
                dropped += 1;
            }
        }
        stats.inconsistent_pairs = dropped;
        if dropped == 0 {
            break;
        }
    }
    let Some(&reference) = members.first() else {
        return Ok(Solution {
            cameras: vec![None; n],
            members,
            phi,
            stats,
            refine: None,
            score: f64::INFINITY,
            free_focal: refine_focal,
        });
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
    stats.no_parallax = directions.iter().all(|d| d.direction.is_none());
    let centres = average_translations(n, &members, &directions, reference, &config.translations);
    let mut cameras: Vec<Option<RefineCamera>> = (0..n)
        .map(|i| match (absolute[i], centres[i]) {
            (Some(rotation), Some(center)) if members.binary_search(&i).is_ok() => {
                Some(RefineCamera { rotation, center })
            }
            _ => None,
        })
        .collect();
    let mut phi = phi;
    let mut refine_report = None;
    let cauchy = match config.refinement {
        Refinement::Converge(mut refine) => {
            refine.refine_focal &= refine_focal;
            // Tied pairs (zero baseline) have no epipolar geometry: left out.
            let baseline = |p: &&&PairMatches| match (cameras[p.first], cameras[p.second]) {
                (Some(a), Some(b)) => (a.center - b.center).norm() > 0.0,
                _ => false,
            };
            let lm_set = pixel_match_set(n, matched.iter().filter(baseline).copied())?;
            refine_report = Some(refine_cameras(
                &lm_set,
                layout,
                &mut cameras,
                &mut phi,
                reference,
                &refine,
            )?);
            refine.cauchy_px
        }
        Refinement::None | Refinement::Official(_) => RefineConfig::default().cauchy_px,
    };
    let score = robust_cost(set, layout, &cameras, phi, cauchy, MISSING_PENALTY_PX)?;
    Ok(Solution {
        cameras,
        members,
        phi,
        stats,
        refine: refine_report,
        score,
        free_focal: refine_focal,
    })
}

/// A match whose pair has no estimated geometry costs as much as one this far (px) from its
/// epipolar line when solutions are compared.
const MISSING_PENALTY_PX: f64 = 10.0;

/// The official GGS schedule on the estimated cameras, in place: each camera into its 224 crop
/// and encoded, the matches of the estimated images mapped into the crops, the five phases, and
/// back to original pixels.
///
/// # Errors
/// Cameras that cannot be encoded; invalid GGS settings.
pub fn official_ggs(
    cameras: &mut [Option<Camera>],
    pairs: &[PairMatches],
    config: &GgsConfig,
) -> Result<()> {
    let members: Vec<usize> = (0..cameras.len())
        .filter(|&i| cameras[i].is_some())
        .collect();
    if members.len() < 2 {
        return Ok(());
    }
    let local = |i: usize| members.binary_search(&i).ok();
    let crops: Vec<Option<CenterCrop>> = cameras
        .iter()
        .map(|c| c.map(|c| CenterCrop::official(c.image_size, MODEL_INPUT_SIDE)))
        .collect();
    let (mut kp1, mut kp2, mut frames) = (Vec::new(), Vec::new(), Vec::new());
    for p in pairs {
        let (Some(a), Some(b), Some(ca), Some(cb)) = (
            local(p.first),
            local(p.second),
            crops[p.first],
            crops[p.second],
        ) else {
            continue;
        };
        for (x, y) in p.kp1.iter().zip(&p.kp2) {
            kp1.push(ca.to_model(*x));
            kp2.push(cb.to_model(*y));
            frames.push((a, b));
        }
    }
    let set = MatchSet::new(members.len(), &kp1, &kp2, &frames)?;
    let mut encodings = members
        .iter()
        .map(|&i| match (cameras[i], crops[i]) {
            (Some(c), Some(crop)) => Ok(PoseEncoding::from_camera(
                &crop.camera_to_model(&c)?,
                QuaternionSign::default(),
            )?),
            _ => Err(PosediffError::InvalidArgument("missing camera".into())),
        })
        .collect::<Result<Vec<_>>>()?;
    GgsSolver::new(&set, *config)?.run(&mut encodings, None)?;
    let model = ImageSize::new(MODEL_INPUT_SIDE, MODEL_INPUT_SIDE)?;
    for (&i, e) in members.iter().zip(&encodings) {
        if let (Some(c), Some(crop)) = (cameras[i].as_mut(), crops[i]) {
            let mut refined = crop.camera_from_model(&e.to_camera(model)?, c.image_size)?;
            if config.fix_focal {
                refined.intrinsics = c.intrinsics;
            }
            *c = refined;
        }
    }
    Ok(())
}

/// `φ` from rotation-only homographies: `K_b⁻¹ H K_a` is a rotation at the right focal.
fn focal_from_homographies(
    pairs: &[(usize, usize, Matrix3<f64>)],
    layout: &ImageIntrinsics,
    search: &FocalSearch,
) -> Option<f64> {
    if pairs.is_empty() {
        return None;
    }
    let cost = |phi: f64| -> f64 {
        pairs
            .iter()
            .map(|(a, b, h)| {
                let ka = k_of(layout, phi, *a);
                let kb_inv = k_of(layout, phi, *b)
                    .try_inverse()
                    .unwrap_or_else(Matrix3::zeros);
                homography_rotation(h, &ka, &kb_inv).map_or(1.0, |(_, ratio)| ratio - 1.0)
            })
            .sum()
    };
    let steps = search.steps.max(2);
    let (lo, hi) = (search.min.ln(), search.max.ln());
    (0..steps)
        .map(|k| (lo + (hi - lo) * k as f64 / (steps - 1) as f64).exp())
        .map(|phi| (phi, cost(phi)))
        .min_by(|a, b| a.1.total_cmp(&b.1))
        .map(|(phi, _)| phi)
}
