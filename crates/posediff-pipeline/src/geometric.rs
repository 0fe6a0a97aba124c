//! Cameras without a checkpoint: the wiring from images to the mapper of `posediff-sfm`.
//!
//! images → features (`posediff-matching`) → pair selection (exhaustive, sequential,
//! retrieval) → verified matches with keypoint ids → [`posediff_sfm::GlobalMapper`] (two-view
//! geometry through OpenCV behind its [`posediff_sfm::mapper::GeometrySolver`] trait, focal, rotation and translation
//! averaging, Sampson refinement, tracks, bundle adjustment) → OpenCV cameras in original
//! pixels. Principal points are the image centres (`((W−1)/2, (H−1)/2)`) unless given.

use std::collections::{HashMap, HashSet};
use std::path::PathBuf;
use std::time::Instant;

use nalgebra::Matrix3;
use posediff_geometry::lens::{CameraModel, LensCamera};
use posediff_geometry::{Camera, ImageSize, Intrinsics, Pose};
use posediff_guidance::GgsConfig;
use posediff_matching::pairs::{BagOfWords, RetrievalOptions, select_pairs_with};
use posediff_matching::{ImageFeatures, PairMatches, PairRule, PairSelection};
use posediff_sfm::bundle::{LensCoefficients, Point};
use posediff_sfm::bundle_refine::{given_focal_factor, sampson_refine_cameras};
use posediff_sfm::sampson_refine::SampsonRefineOptions;
use posediff_sfm::{CameraPose, GlobalMapper, ImageIntrinsics, MapperOptions, SfmError};

pub use crate::bundle_refine::{BundleRefinement, bundle_refine_cameras};
use crate::correspondences::{
    Adjusted, Correspondences, NoCounter, SharedLearned, StepCounter, descriptor_support,
};
use crate::error::{PosediffError, Result};
pub use crate::ggs::{model_frame_matches, official_ggs};
pub use crate::orientation::{STRONG_PAIR, TURN_PARTNERS, TURN_TESTS};
use crate::orientation::{turn_components, turn_left_out};
use crate::report::{DistortionOutcome, LensRefinementOutcome, Warning};
use crate::store::{Shard, SharedStore, Stored};
use crate::two_view::{OpenCvTwoView, TwoViewCache};

pub use posediff_sfm::intrinsics::{focal_scale, image_centre};

use crate::options::{CameraHint, CameraMode, DensifyWhen, PipelineOptions};
pub use crate::options::{
    GEOMETRIC_CONTRAST_THRESHOLD, GEOMETRIC_MAX_KEYPOINTS, KnownIntrinsics, resolve_intrinsics,
};

/// How the cameras are refined after the initialisation.
#[derive(Debug, Clone, Copy, PartialEq)]
pub enum Refinement {
    /// None: the averaged cameras.
    None,
    /// The Sampson objective to convergence (Levenberg–Marquardt), then the bundle adjustment.
    Converge(SampsonRefineOptions),
    /// The official GGS schedule (five SGD phases, 7000 iterations by default) on the cameras
    /// in their 224 crops, as the released code runs it inside the diffusion.
    Official(GgsConfig),
}

/// Settings of the geometric estimate: the options tree and what the run knows.
#[derive(Debug, Clone, PartialEq)]
pub struct GeometricConfig {
    /// Every threshold of the pipeline ([`PipelineOptions`]).
    pub options: PipelineOptions,
    /// Known intrinsics.
    pub intrinsics: KnownIntrinsics,
    /// Refinement.
    pub refinement: Refinement,
    /// The learned matcher, when the run uses it instead of OpenCV's.
    pub learned: Option<SharedLearned>,
    /// What the files say of each image's camera (EXIF, folder), one per image; empty when
    /// nothing is known. They decide the camera groups and focal priors of `cameras.mode`.
    pub hints: Vec<CameraHint>,
    /// Each masked image's mask file (COLMAP's: zero = ignore), by the image's path: its
    /// keypoints on masked pixels are dropped after every extraction, before any matching.
    pub masks: HashMap<PathBuf, PathBuf>,
    /// `--database`: where features and verified matches are read first and written as they
    /// are made ([`crate::store`]).
    pub store: Option<SharedStore>,
}

/// The second matching pass as it runs ([`crate::options::DensifyOptions`] has
/// the why): each estimated image matched with up to `per_image` unmatched images within
/// `max_angle_deg` of its rotation. At most `per_image · n` more pairs.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Densify {
    /// Largest rotation between the two estimated cameras, degrees.
    pub max_angle_deg: f64,
    /// New pairs per image at most.
    pub per_image: usize,
}

impl Default for Densify {
    fn default() -> Self {
        let d = crate::options::DensifyOptions::default();
        Self {
            max_angle_deg: d.max_angle_deg,
            per_image: d.per_image,
        }
    }
}

impl Default for GeometricConfig {
    fn default() -> Self {
        let options = PipelineOptions::default();
        Self {
            refinement: Refinement::Converge(options.mapper.sampson.unwrap_or_default()),
            options,
            intrinsics: KnownIntrinsics::Unknown,
            learned: None,
            hints: Vec::new(),
            masks: HashMap::new(),
            store: None,
        }
    }
}

/// The default of `pairs.learned_exhaustive_up_to` ([`crate::options::PairOptions`]).
pub const LEARNED_EXHAUSTIVE_UP_TO: usize = 12;

/// The default of `pairs.learned_first_pass` ([`crate::options::PairOptions`]).
pub const LEARNED_FIRST_PASS: [PairRule; 2] = [PairRule::Sequential(3), PairRule::Retrieval(3)];

impl GeometricConfig {
    /// The pair selection (its rules resolved for `n` images) and the second pass used for
    /// `n` images: `auto` is `pairs.auto` with OpenCV's matchers; with a learned matcher,
    /// exhaustive up to `pairs.learned_exhaustive_up_to` images and above it
    /// `pairs.learned_first_pass` plus the second pass. `densify.when` forces the second pass
    /// on or off.
    pub fn plan(&self, n: usize) -> (PairSelection, Option<Densify>) {
        let o = &self.options;
        let d = Densify {
            max_angle_deg: o.densify.max_angle_deg,
            per_image: o.densify.per_image,
        };
        let auto = o.pairs.selection == PairSelection::Auto;
        let learned_auto = auto && self.learned.is_some() && n > o.pairs.learned_exhaustive_up_to;
        let selection = if learned_auto {
            PairSelection::Rules(o.pairs.learned_first_pass.rules(n))
        } else if auto && self.learned.is_some() {
            PairSelection::Rules(vec![PairRule::Exhaustive])
        } else {
            PairSelection::Rules(o.pairs.selection.rules_with(n, &o.pairs.auto))
        };
        let densify = match o.densify.when {
            DensifyWhen::Auto => learned_auto.then_some(d),
            DensifyWhen::Always => Some(d),
            DensifyWhen::Never => None,
        };
        (selection, densify)
    }

    /// The matcher the options ask for ([`crate::correspondences::correspondences`]).
    pub fn correspondences(&self) -> Box<dyn Correspondences + '_> {
        let mut matcher =
            crate::correspondences::correspondences(&self.options.matching, self.learned.as_ref());
        if !self.masks.is_empty() {
            matcher = Box::new(crate::correspondences::Adjusted {
                inner: matcher,
                adjust: Box::new(|path, features| match self.masks.get(path) {
                    Some(mask) => {
                        Ok(posediff_matching::mask::apply_mask(features, mask).map(|_| ())?)
                    }
                    None => Ok(()),
                }),
            });
        }
        // The store holds the masked features: the ones its matches index.
        match &self.store {
            Some(store) => Box::new(Stored {
                inner: matcher,
                store: store.0.as_ref(),
                images_per_commit: self.options.database.images_per_commit,
                pairs_per_commit: self.options.database.pairs_per_commit,
            }),
            None => matcher,
        }
    }

    /// The mapper's options for this refinement.
    fn mapper_options(&self) -> MapperOptions {
        let mut o = self.options.mapper.clone();
        o.homography_fraction = self.options.two_view.homography_fraction;
        // A learned matcher's wrong pairs must not decide the focal (MapperOptions' doc).
        o.score_dropped_as_missing |= self.learned.is_some();
        // EXIF, where any image has it, decides auto's groups instead of the data.
        o.cameras_from_data = self.options.cameras.mode == CameraMode::Auto
            && !self.hints.iter().any(|h| h.device.is_some());
        match self.refinement {
            Refinement::Converge(r) => o.sampson = Some(r),
            Refinement::None | Refinement::Official(_) => {
                o.sampson = None;
                o.bundle = None;
            }
        }
        o
    }
}

pub use crate::report::{FocalOrigin, GeometricReport, GeometricTimes, NotEstimatedImage};

/// The cameras of a geometric estimate: `None` for images that were not estimated.
#[derive(Debug, Clone, PartialEq)]
pub struct GeometricEstimate {
    /// One per image, in input order.
    pub cameras: Vec<Option<Camera>>,
    /// Image sizes.
    pub sizes: Vec<ImageSize>,
    /// Matches of every matched pair (original pixels, keypoint ids).
    pub pairs: Vec<PairMatches>,
    /// The bundle adjustment's points (empty without it).
    pub points: Vec<Point>,
    /// Statistics.
    pub report: GeometricReport,
    /// Things the user should know.
    pub warnings: Vec<Warning>,
    /// The lens distortion calibrated before the mapper (`cameras.distortion`), when one was
    /// measured: `pairs` and `points` are then in undistorted pixels, the cameras pinhole on
    /// them, and each image's lens ([`RadialLens::lens_camera`]) maps back to the photos'
    /// pixels.
    pub lens: Option<RadialLens>,
}

/// Each image's radial distortion as calibrated before the mapper
/// ([`posediff_sfm::distortion_calibration`]).
#[derive(Debug, Clone, PartialEq)]
pub struct RadialLens {
    /// Per image, its SIMPLE_RADIAL lens `[s, cx, cy, k]` around the focal guess `s` the
    /// calibration normalised by, at the image's principal point.
    pub lenses: Vec<LensCamera>,
}

impl RadialLens {
    /// The undistorted pixel of image `i`'s pixel `p`; `None` beyond the model's fold.
    pub fn undistort_pixel(&self, i: usize, p: [f64; 2]) -> Option<[f64; 2]> {
        self.lenses[i]
            .undistort_pixel(&nalgebra::Vector2::from(p))
            .ok()
            .map(Into::into)
    }

    /// COLMAP's OPENCV `[k₁, k₂, p₁, p₂]` of image `i` at its estimated focal `focal` (pixels;
    /// the coefficients its model lacks 0): a coefficient of `r^{2n}` scales as `(f / s)^{2n}`,
    /// a tangential one as `f / s`.
    pub fn coefficients(&self, i: usize, focal: f64) -> LensCoefficients {
        let lens = &self.lenses[i];
        let d = lens.distortion();
        if lens.model() == CameraModel::OpenCvFisheye {
            // Defined at its own focal, which the camera keeps (see `lens_camera`).
            return [d[0], d[1], d[2], d[3]];
        }
        let ratio = focal / lens.focal().0;
        let k1 = posediff_sfm::distortion_calibration::coefficient_at(d[0], 1.0, ratio);
        let k2 = d.get(1).map_or(0.0, |k2| k2 * ratio.powi(4));
        let p1 = d.get(2).map_or(0.0, |p| p * ratio);
        let p2 = d.get(3).map_or(0.0, |p| p * ratio);
        [k1, k2, p1, p2]
    }

    /// Image `i`'s lens around its estimated pinhole intrinsics `k`: its model (SIMPLE_RADIAL,
    /// RADIAL, OPENCV with `fx = fy`, OPENCV_FISHEYE) with the coefficients at that focal.
    ///
    /// # Errors
    /// A fisheye lens at another focal than its own; two focals, or a principal point other
    /// than the lens's (the model would then not be the lens calibrated).
    pub fn lens_camera(&self, i: usize, k: &Intrinsics) -> Result<LensCamera> {
        let (cx, cy) = self.lenses[i].principal();
        let off = (k.cx() - cx).hypot(k.cy() - cy);
        let fisheye = self.lenses[i].model() == CameraModel::OpenCvFisheye;
        if fisheye && (k.fx() / self.lenses[i].focal().0 - 1.0).abs() > 1e-9 {
            return Err(PosediffError::InvalidArgument(format!(
                "image {i}: focal {} is not its fisheye lens's {}: the equidistant model holds \
                 at that focal only",
                k.fx(),
                self.lenses[i].focal().0
            )));
        }
        if off > 1e-6 * k.fx() || k.fx() != k.fy() {
            return Err(PosediffError::InvalidArgument(format!(
                "image {i}: focal ({}, {}) and principal point ({}, {}) are not the distortion's \
                 one focal and centre ({cx}, {cy}); its SIMPLE_RADIAL model would not be exact",
                k.fx(),
                k.fy(),
                k.cx(),
                k.cy()
            )));
        }
        let model = self.lenses[i].model();
        let [k1, k2, p1, p2] = self.coefficients(i, k.fx());
        let params = match model {
            CameraModel::Radial => vec![k.fx(), k.cx(), k.cy(), k1, k2],
            CameraModel::OpenCv | CameraModel::OpenCvFisheye => {
                vec![k.fx(), k.fx(), k.cx(), k.cy(), k1, k2, p1, p2]
            }
            _ => vec![k.fx(), k.cx(), k.cy(), k1],
        };
        Ok(LensCamera::new(model, params)?)
    }

    /// Undistorts every keypoint of `features` (in place; once: the caller's invariant).
    fn undistort_features(&self, features: &mut [ImageFeatures]) {
        for (i, f) in features.iter_mut().enumerate() {
            for p in &mut f.keypoints {
                // Inside the image the model never folds (the calibration's range keeps the
                // fold beyond the corners), so every keypoint has its undistorted pixel.
                if let Some(u) = self.undistort_pixel(i, *p) {
                    *p = u;
                }
            }
        }
    }

    /// Undistorts every keypoint of `pairs` (in place; once: the caller's invariant).
    pub fn undistort_pairs(&self, pairs: &mut [PairMatches]) {
        for p in pairs {
            for x in &mut p.kp1 {
                if let Some(u) = self.undistort_pixel(p.first, *x) {
                    *x = u;
                }
            }
            for x in &mut p.kp2 {
                if let Some(u) = self.undistort_pixel(p.second, *x) {
                    *x = u;
                }
            }
        }
    }
}

/// The camera layout of unknown intrinsics and each image's focal guess `s` (the prior), the
/// frame a [`RadialLens`] is calibrated in.
fn lens_frame(
    sizes: &[ImageSize],
    config: &GeometricConfig,
) -> Result<(ImageIntrinsics, Vec<f64>)> {
    let layout = camera_layout(
        sizes,
        &config.intrinsics,
        config.options.cameras.mode,
        &config.hints,
        config.options.mapper.focal_prior,
    )?
    .intrinsics;
    let scale: Vec<f64> = layout
        .scale
        .iter()
        .map(|s| s * config.options.mapper.focal_prior)
        .collect();
    Ok((layout, scale))
}

/// The lens calibration before the mapper (and before GGS on the network path): with unknown
/// intrinsics and `cameras.distortion` on, each camera group's radial coefficient from the
/// verified matches; `None` when off, given intrinsics, or no distortion measured (then the
/// report says which).
///
/// # Errors
/// An invalid camera layout (hints of another count than the images, bad known intrinsics).
pub fn calibrate_lens(
    sizes: &[ImageSize],
    pairs: &[PairMatches],
    config: &GeometricConfig,
) -> Result<(Option<RadialLens>, DistortionOutcome)> {
    let Some(options) = &config.options.cameras.distortion else {
        return Ok((None, DistortionOutcome::off()));
    };
    if !matches!(config.intrinsics, KnownIntrinsics::Unknown) {
        return Ok((None, DistortionOutcome::off()));
    }
    let (layout, scale) = lens_frame(sizes, config)?;
    let corner: Vec<f64> = sizes
        .iter()
        .zip(&layout.principal)
        .zip(&scale)
        .map(|((size, c), s)| {
            let (w, h) = (f64::from(size.width()), f64::from(size.height()));
            let dx = c[0].max(w - c[0]);
            let dy = c[1].max(h - c[1]);
            dx.hypot(dy) / s
        })
        .collect();
    let calibration = posediff_sfm::distortion_calibration::calibrate_distortion(
        pairs,
        &layout.group,
        &layout.principal,
        &scale,
        &corner,
        options,
    );
    let outcome = DistortionOutcome {
        calibrated: true,
        measured: calibration.determined.iter().any(|d| *d),
        pairs: calibration.pairs,
        cost_pinhole: calibration.cost_pinhole,
        cost: calibration.cost,
        refinement: None,
        ..DistortionOutcome::default()
    };
    if !outcome.measured {
        return Ok((None, outcome));
    }
    let lenses = layout
        .group
        .iter()
        .zip(&layout.principal)
        .zip(&scale)
        .map(|((g, c), s)| {
            LensCamera::new(
                CameraModel::SimpleRadial,
                vec![*s, c[0], c[1], calibration.k[*g]],
            )
        })
        .collect::<std::result::Result<_, _>>()?;
    Ok((Some(RadialLens { lenses }), outcome))
}

/// The index of `path` among `images`.
fn image_index(images: &[PathBuf], path: &std::path::Path) -> Result<usize> {
    images
        .iter()
        .position(|p| p.as_path() == path)
        .ok_or_else(|| {
            PosediffError::InvalidArgument(format!(
                "{} is not an image of this estimate",
                path.display()
            ))
        })
}

/// The lens refined after the mapper (`cameras.lens_refinement`): each camera's coefficients
/// (SIMPLE_RADIAL, RADIAL, OPENCV or OPENCV_FISHEYE) by a bundle adjustment of the estimate's points on the photos' pixels
/// ([`posediff_sfm::lens_refinement`]), starting from `lens` (pinhole without one). Returns the
/// refined lens of every image when it is kept, and what the refinement did.
fn refine_lens_after_mapping(
    sizes: &[ImageSize],
    estimate: &GeometricEstimate,
    lens: Option<&RadialLens>,
    config: &GeometricConfig,
    options: &posediff_sfm::lens_refinement::LensRefinementOptions,
) -> Result<(Option<RadialLens>, LensRefinementOutcome)> {
    let (frame, scale) = lens_frame(sizes, config)?;
    let group = &estimate.report.cameras.image_camera;
    let n = sizes.len();
    if group.len() != n {
        return Err(PosediffError::InvalidArgument(format!(
            "lens refinement: {} camera assignments for {n} images",
            group.len()
        )));
    }
    let groups = group.iter().max().map_or(0, |g| g + 1);
    // Each image's focal (the estimated one; else its group's ratio to the frame's guess).
    let mut ratio = vec![None; groups];
    for (i, c) in estimate.cameras.iter().enumerate() {
        if let (None, Some(c)) = (ratio[group[i]], c) {
            ratio[group[i]] = Some(c.intrinsics.fx() / scale[i]);
        }
    }
    let focal: Vec<f64> = (0..n)
        .map(|i| match &estimate.cameras[i] {
            Some(c) => c.intrinsics.fx(),
            None => scale[i] * ratio[group[i]].unwrap_or(1.0),
        })
        .collect();
    let intrinsics = ImageIntrinsics {
        principal: frame.principal.clone(),
        scale: focal.clone(),
        group: group.clone(),
    };
    let cameras: Vec<Option<CameraPose>> = estimate
        .cameras
        .iter()
        .map(|c| c.as_ref().map(CameraPose::of_camera))
        .collect();
    // The start: each camera's coefficients at its focal (0 without a lens).
    let kind = options.model.kind();
    let mut start = vec![kind.pinhole(); groups];
    if let Some(lens) = lens {
        let mut seen = vec![false; groups];
        for (i, c) in estimate.cameras.iter().enumerate() {
            if let (false, Some(c)) = (seen[group[i]], c) {
                seen[group[i]] = true;
                let k = lens.coefficients(i, c.intrinsics.fx());
                start[group[i]] = match kind {
                    posediff_sfm::bundle::LensKind::Brown => k,
                    // A radial lens `1 + k r²` is a fisheye `θ (1 + (1/3 + k) θ² + …)` to the
                    // third order: the start.
                    posediff_sfm::bundle::LensKind::Fisheye => {
                        let mut f = kind.pinhole();
                        f[0] += k[0];
                        f
                    }
                };
            }
        }
    }
    // The points adjusted (evenly spaced, `max_points` at most: only those are copied), their
    // observations back in the photos' pixels.
    let step = estimate
        .points
        .len()
        .div_ceil(options.max_points.max(1))
        .max(1);
    let points: Vec<Point> = estimate
        .points
        .iter()
        .step_by(step)
        .map(|p| {
            let mut p = p.clone();
            if let Some(lens) = lens {
                for o in &mut p.observations {
                    let x = lens.lenses[o.image].distort_pixel(&nalgebra::Vector2::from(o.xy));
                    o.xy = [x.x, x.y];
                }
            }
            p
        })
        .collect();
    let bundle = config.options.mapper.bundle.unwrap_or_default();
    let refined = posediff_sfm::lens_refinement::refine_lens(
        &points,
        &intrinsics,
        &cameras,
        &start,
        &bundle,
        options,
    )?;
    let mut outcome = LensRefinementOutcome {
        kept: refined.kept,
        reason: refined.reason.map(Into::into),
        adjustment: refined.adjustment,
        k: refined.k.clone(),
    };
    if !refined.kept {
        return Ok((None, outcome));
    }
    // Each image's lens in its frame: Brown's coefficients at the focal f rescaled to s (a
    // coefficient of r^{2n} by (s / f)^{2n}, a tangential one by s / f; the inverse of
    // `RadialLens::coefficients`).
    let mut lenses = Vec::with_capacity(n);
    for i in 0..n {
        let (s, c) = (scale[i], frame.principal[i]);
        let [k1, k2, p1, p2] = refined.k[group[i]];
        let ratio = s / focal[i];
        let (k1, k2, p1, p2) = (
            k1 * ratio.powi(2),
            k2 * ratio.powi(4),
            p1 * ratio,
            p2 * ratio,
        );
        let (model, params) = match options.model {
            posediff_sfm::lens_refinement::LensModel::SimpleRadial => {
                (CameraModel::SimpleRadial, vec![s, c[0], c[1], k1])
            }
            posediff_sfm::lens_refinement::LensModel::Radial => {
                (CameraModel::Radial, vec![s, c[0], c[1], k1, k2])
            }
            posediff_sfm::lens_refinement::LensModel::Opencv => {
                (CameraModel::OpenCv, vec![s, s, c[0], c[1], k1, k2, p1, p2])
            }
            // Not covariant under a change of focal: at the adjusted focal itself, which the
            // mapping again keeps fixed (`fixed_focals`).
            posediff_sfm::lens_refinement::LensModel::OpencvFisheye => {
                let f = focal[i] * refined.factors[group[i]];
                let k = refined.k[group[i]];
                (
                    CameraModel::OpenCvFisheye,
                    vec![f, f, c[0], c[1], k[0], k[1], k[2], k[3]],
                )
            }
        };
        let camera = LensCamera::new(model, params)?;
        // The lens must be invertible over the whole photo: a coefficient that folds inside
        // it is no lens of this camera.
        let (w, h) = (f64::from(sizes[i].width()), f64::from(sizes[i].height()));
        let folds = [[0.0, 0.0], [w, 0.0], [0.0, h], [w, h]].iter().any(|p| {
            camera
                .undistort_pixel(&nalgebra::Vector2::from(*p))
                .is_err()
        });
        if folds {
            outcome.kept = false;
            outcome.reason = Some(format!(
                "the refined lens folds inside image {i} (k = {:?})",
                refined.k[group[i]]
            ));
            return Ok((None, outcome));
        }
        lenses.push(camera);
    }
    Ok((Some(RadialLens { lenses }), outcome))
}

impl RadialLens {
    /// Image `i`'s undistorted pixel `x` back in the photo's pixels through `this` (pinhole:
    /// unchanged).
    fn photo_pixel(this: Option<&Self>, i: usize, x: &[f64; 2]) -> [f64; 2] {
        match this {
            Some(l) => {
                let p = l.lenses[i].distort_pixel(&nalgebra::Vector2::from(*x));
                [p.x, p.y]
            }
            None => *x,
        }
    }

    /// `pairs` undistorted by `this` moved to `other`'s undistortion: each match back to its
    /// photo pixel through `this` (pinhole when `None`) and undistorted by `other`.
    fn moved_pairs(this: Option<&Self>, other: &Self, pairs: &[PairMatches]) -> Vec<PairMatches> {
        let mv = |i: usize, x: &[f64; 2]| {
            let photo = Self::photo_pixel(this, i, x);
            other.undistort_pixel(i, photo).unwrap_or(photo)
        };
        pairs
            .iter()
            .map(|p| PairMatches {
                kp1: p.kp1.iter().map(|x| mv(p.first, x)).collect(),
                kp2: p.kp2.iter().map(|x| mv(p.second, x)).collect(),
                ..p.clone()
            })
            .collect()
    }
}

impl From<SfmError> for PosediffError {
    fn from(e: SfmError) -> Self {
        match e {
            SfmError::NoUsablePairs { images } => PosediffError::NoMatches { images },
            other => PosediffError::Mapper(other),
        }
    }
}

/// Estimates cameras of `images` without a checkpoint.
///
/// # Errors
/// Fewer than two images, unreadable images, matching errors, no pair with enough matches.
pub fn estimate_geometric(
    images: &[PathBuf],
    config: &GeometricConfig,
) -> Result<GeometricEstimate> {
    estimate_geometric_counted(images, config, &NoCounter)
}

/// [`estimate_geometric`], reporting its stages on `counter`: "features" and "matching" (the
/// learned matcher's images and pairs counted), "mapping", and with a second pass "second
/// pass" and "mapping" again.
///
/// # Errors
/// As [`estimate_geometric`].
pub fn estimate_geometric_counted(
    images: &[PathBuf],
    config: &GeometricConfig,
    counter: &dyn StepCounter,
) -> Result<GeometricEstimate> {
    let Matched {
        mut features,
        mut pairs,
        mut support,
        mut times,
        selection,
        words,
    } = match_all(images, config, None, counter)?;
    let matcher = config.correspondences();
    let sizes: Vec<ImageSize> = features.iter().map(|f| f.image_size).collect();
    let (_, densify) = config.plan(images.len());
    // A learned matcher's orientation check and turned retry (not with the support check,
    // whose screen saw the upright features).
    let learned_checks = config.learned.is_some() && support.is_none();
    let retry = learned_checks && config.options.retry.enabled;
    let orient = learned_checks && config.options.orientation.enabled;
    let mut turned_images = Vec::new();
    if orient {
        let clock = Instant::now();
        if let Some((flipped, new_pairs)) = turn_components(
            images,
            &mut features,
            &pairs,
            words.as_ref(),
            (
                matcher.as_ref(),
                &config.options.orientation,
                &config.options.matching,
            ),
            counter,
        )? {
            pairs = new_pairs;
            turned_images = flipped;
        }
        times[2] += clock.elapsed().as_secs_f64();
    }
    // The lens: with a distortion measured, every keypoint is undistorted here, once (the
    // features for the later passes, the pairs made so far), and the turned retry's new
    // features through `Adjusted`.
    let clock = Instant::now();
    let (lens, distortion) = calibrate_lens(&sizes, &pairs, config)?;
    if let Some(lens) = &lens {
        lens.undistort_features(&mut features);
        lens.undistort_pairs(&mut pairs);
    }
    let distortion_seconds = clock.elapsed().as_secs_f64();
    // Features extracted from here on (the turned retry's) come undistorted: their image's
    // lens, found by its path.
    let undistorting = lens.as_ref().map(|lens| Adjusted {
        inner: Box::new(matcher.as_ref()),
        adjust: Box::new(move |path, features| {
            let i = image_index(images, path)?;
            for p in &mut features.keypoints {
                if let Some(u) = lens.undistort_pixel(i, *p) {
                    *p = u;
                }
            }
            Ok(())
        }),
    });
    let matcher: &dyn Correspondences = match &undistorting {
        Some(u) => u,
        None => matcher.as_ref(),
    };
    // The features are only needed again by the second pass and the turned retry (SIFT's of
    // a thousand images are gigabytes): dropped before the mapper otherwise.
    let mut features = (densify.is_some() || retry).then_some(features);
    // The first pass's matches are kept for the second (a copy) only when it runs.
    counter.stage("mapping", 0);
    let cache = TwoViewCache::default();
    let mut estimate = if features.is_some() {
        map_supported_matches(
            &sizes,
            pairs.clone(),
            support.clone(),
            config,
            (&cache, None),
        )?
    } else {
        map_supported_matches(
            &sizes,
            std::mem::take(&mut pairs),
            support.take(),
            config,
            (&cache, None),
        )?
    };
    let mut densified = 0;
    if let (Some(d), Some(features)) = (densify, &features) {
        let matched: HashSet<(usize, usize)> = pairs.iter().map(|p| (p.first, p.second)).collect();
        let extra = densify_pairs(&estimate.cameras, &matched, &d);
        if !extra.is_empty() {
            let clock = Instant::now();
            pairs.extend(matcher.match_pairs(features, &extra, (counter, "second pass"))?);
            if let (Some(flags), Some(minimum)) =
                (&mut support, config.options.support.min_verified)
            {
                flags.extend(
                    descriptor_support(features, &extra, &config.options.matching)?
                        .into_iter()
                        .map(|count| count >= minimum),
                );
            }
            times[2] += clock.elapsed().as_secs_f64();
            densified = extra.len();
            let first = estimate.report.times;
            counter.stage("mapping", 0);
            estimate =
                map_supported_matches(&sizes, pairs.clone(), support, config, (&cache, None))?;
            estimate.report.times.add_mapping(&first);
        }
    }
    if let (true, Some(features)) = (retry, features.as_mut()) {
        let clock = Instant::now();
        if let Some((kept, turned_pairs)) = turn_left_out(
            images,
            features,
            &pairs,
            &estimate.cameras,
            matcher,
            &config.options.retry,
            counter,
        )? {
            times[2] += clock.elapsed().as_secs_f64();
            let earlier = estimate.report.times;
            counter.stage("mapping", 0);
            // The turned images' features changed: the two-view results of their pairs are
            // new, so a new cache.
            estimate = map_supported_matches(
                &sizes,
                turned_pairs,
                None,
                config,
                (&TwoViewCache::default(), None),
            )?;
            estimate.report.times.add_mapping(&earlier);
            turned_images.extend(kept);
            turned_images.sort_unstable();
        } else {
            times[2] += clock.elapsed().as_secs_f64();
        }
    }
    // The matching is over: the lens is the estimate's now.
    drop(undistorting);
    let mut lens = lens;
    let mut distortion = distortion;
    let mut distortion_seconds = distortion_seconds;
    if let Some(options) = &config.options.cameras.lens_refinement
        && matches!(config.intrinsics, KnownIntrinsics::Unknown)
        && !estimate.points.is_empty()
    {
        let clock = Instant::now();
        let (refined, mut outcome) =
            refine_lens_after_mapping(&sizes, &estimate, lens.as_ref(), config, options)?;
        distortion_seconds += clock.elapsed().as_secs_f64();
        if let Some(refined) = refined {
            let earlier = estimate.report.times;
            // The matches undistorted with the refined lens and mapped again (new two-view
            // results: the coordinates moved). The mapping with the lens before is kept when
            // this one fails or estimates fewer images.
            let pairs = RadialLens::moved_pairs(lens.as_ref(), &refined, &estimate.pairs);
            counter.stage("mapping", 0);
            let estimated = estimate.cameras.iter().flatten().count();
            let fixed: Option<Vec<f64>> = (options.model.kind()
                == posediff_sfm::bundle::LensKind::Fisheye)
                .then(|| refined.lenses.iter().map(|l| l.focal().0).collect());
            let cache = TwoViewCache::default();
            match map_supported_matches(&sizes, pairs, None, config, (&cache, fixed.as_deref())) {
                Ok(mut again) if again.cameras.iter().flatten().count() >= estimated => {
                    again.report.times.add_mapping(&earlier);
                    estimate = again;
                    lens = Some(refined);
                }
                Ok(again) => {
                    estimate.report.times.add_mapping(&again.report.times);
                    outcome.kept = false;
                    outcome.reason = Some(format!(
                        "mapped again with it, {} of {estimated} images were estimated",
                        again.cameras.iter().flatten().count()
                    ));
                }
                Err(e) => {
                    outcome.kept = false;
                    outcome.reason = Some(format!("mapping again with it failed: {e}"));
                }
            }
        }
        distortion.refinement = Some(outcome);
    }
    estimate.report.turned_images = turned_images;
    if let Some(lens) = &lens {
        // Each camera's COLMAP k at its focal, from its first estimated image.
        let mut k = vec![None; estimate.report.cameras.count];
        for (i, &g) in estimate.report.cameras.image_camera.iter().enumerate() {
            if let (None, Some(c)) = (k[g], estimate.cameras[i]) {
                k[g] = Some(lens.coefficients(i, c.intrinsics.fx()));
            }
        }
        distortion.k1 = k.iter().map(|k| k.map(|k| k[0])).collect();
        let model = |m: CameraModel| lens.lenses.iter().any(|l| l.model() == m);
        let column = |c: usize| k.iter().map(|k| k.map(|k| k[c])).collect();
        if model(CameraModel::Radial)
            || model(CameraModel::OpenCv)
            || model(CameraModel::OpenCvFisheye)
        {
            distortion.k2 = column(1);
        }
        if model(CameraModel::OpenCv) {
            distortion.p1 = column(2);
            distortion.p2 = column(3);
        }
        if model(CameraModel::OpenCvFisheye) {
            distortion.k3 = column(2);
            distortion.k4 = column(3);
        }
    }
    estimate.report.cameras.distortion = distortion;
    estimate.report.times.distortion = distortion_seconds;
    estimate.lens = lens;
    estimate.report.pair_selection = selection;
    estimate.report.pairs_matched = estimate.pairs.len();
    estimate.report.pairs_densified = densified;
    let t = &mut estimate.report.times;
    (t.extraction, t.pair_selection, t.matching_pairs) = (times[0], times[1], times[2]);
    t.matching = times.iter().sum();
    Ok(estimate)
}

/// The pairs of [`Densify`]'s second pass: for each estimated image, its nearest estimated
/// images by the rotation between them, within `max_angle_deg`, that are not in `matched`,
/// `per_image` at most; sorted `(i, j)` with `i < j`, without repeats. `O(n²)` rotation
/// comparisons, which are nothing beside one LightGlue pair
/// ([`posediff_matching::pairs::spatial_pairs`], the spatial pair plan).
pub fn densify_pairs(
    cameras: &[Option<Camera>],
    matched: &HashSet<(usize, usize)>,
    densify: &Densify,
) -> Vec<(usize, usize)> {
    let rotations: Vec<Option<Matrix3<f64>>> = cameras
        .iter()
        .map(|c| c.as_ref().map(|c| c.cam_from_world.rotation))
        .collect();
    posediff_matching::pairs::spatial_pairs(
        &rotations,
        matched,
        densify.max_angle_deg,
        densify.per_image,
    )
}

/// The first pass as `posediff match` runs it alone: extraction, the pair plan's first
/// selection and matching (with a store, from it and into it); the selected pairs' matches
/// (empty where a pair verified too few) and the selection's rules.
///
/// # Errors
/// As [`estimate_geometric`].
pub fn extract_and_match(
    images: &[PathBuf],
    config: &GeometricConfig,
    counter: &dyn StepCounter,
) -> Result<(Vec<PairMatches>, String)> {
    let m = match_all(images, config, None, counter)?;
    Ok((m.pairs, m.selection))
}

/// [`extract_and_match`] restricted to `shard`'s part of the selected pairs (every image's
/// features are read or extracted: the selection needs them all, and stores them).
///
/// # Errors
/// As [`extract_and_match`].
pub fn extract_and_match_shard(
    images: &[PathBuf],
    config: &GeometricConfig,
    shard: Shard,
    counter: &dyn StepCounter,
) -> Result<(Vec<PairMatches>, String)> {
    let m = match_all(images, config, Some(shard), counter)?;
    Ok((m.pairs, m.selection))
}

/// What [`match_all`] gives.
struct Matched {
    /// The features of every image.
    features: Vec<ImageFeatures>,
    /// The matches of the selected pairs.
    pairs: Vec<PairMatches>,
    /// Their support flags (learned matchers with the support check).
    support: Option<Vec<bool>>,
    /// The seconds of extraction, selection and matching.
    times: [f64; 3],
    /// The selection's rules.
    selection: String,
    /// The bag of words of the features, when a retrieval rule built it for a learned matcher
    /// (the orientation check uses it again).
    words: Option<BagOfWords>,
}

/// Extraction, pair selection, matching and (for a learned matcher) the support screen.
fn match_all(
    images: &[PathBuf],
    config: &GeometricConfig,
    shard: Option<Shard>,
    counter: &dyn StepCounter,
) -> Result<Matched> {
    if images.len() < 2 {
        return Err(PosediffError::TooFewImages {
            needed: 2,
            got: images.len(),
        });
    }
    let clock = Instant::now();
    let matcher = config.correspondences();
    let features = matcher.extract(images, counter)?;
    let extraction = clock.elapsed().as_secs_f64();
    let clock = Instant::now();
    let Selected {
        pairs: pair_list,
        mut rules,
        words,
    } = selected_pairs(config, &features)?;
    let pair_list = match shard {
        Some(s) => {
            rules.push(format!("shard:{s}"));
            s.pairs(&pair_list)
        }
        None => pair_list,
    };
    let selection = clock.elapsed().as_secs_f64();
    let clock = Instant::now();
    let pairs = matcher.match_pairs(&features, &pair_list, (counter, "matching"))?;
    let support = match (config.learned.as_ref(), config.options.support.min_verified) {
        (Some(_), Some(minimum)) => Some(
            descriptor_support(&features, &pair_list, &config.options.matching)?
                .into_iter()
                .map(|count| count >= minimum)
                .collect(),
        ),
        _ => None,
    };
    Ok(Matched {
        features,
        pairs,
        support,
        times: [extraction, selection, clock.elapsed().as_secs_f64()],
        selection: rules.join(","),
        words,
    })
}

/// The first pass's pairs of `features`' images: the store's fixed pairs (`posediff map`), a
/// selection the store holds for these images under the same rules (a distributed run's
/// driver made it once), or the selection made now (and stored); with the rules as run.json
/// names them and the bag of words when the orientation check needs one.
fn selected_pairs(config: &GeometricConfig, features: &[ImageFeatures]) -> Result<Selected> {
    let n = features.len();
    let (selection, densify) = config.plan(n);
    // The bag of words once, for a retrieval rule and the orientation check.
    let words = (config.learned.is_some()
        && config.options.support.min_verified.is_none()
        && selection
            .rules(n)
            .iter()
            .any(|r| matches!(r, PairRule::Retrieval(_))))
    .then(|| BagOfWords::build(features, &RetrievalOptions::default()))
    .flatten();
    let store = config.store.as_ref().map(|s| &s.0);
    let fixed = match store {
        Some(store) => store.fixed_pairs()?,
        None => None,
    };
    let (pair_list, mut rules) = match fixed {
        Some(list) => (list, vec!["database".to_owned()]),
        None => {
            let rules: Vec<String> = selection.rules(n).iter().map(ToString::to_string).collect();
            let key = rules.join(",");
            let stored = match store {
                Some(store) => store.selection(&key)?,
                None => None,
            };
            let list = match stored {
                Some(list) => {
                    log::info!("selection: {} pairs ({key}) from the database", list.len());
                    list
                }
                None => {
                    let list = select_pairs_with(n, &selection, Some(features), words.as_ref())?;
                    if let Some(store) = store {
                        store.put_selection(&key, &list)?;
                    }
                    list
                }
            };
            (list, rules)
        }
    };
    if let Some(d) = densify {
        rules.push(format!("densify:{}deg,{}", d.max_angle_deg, d.per_image));
    }
    Ok(Selected {
        pairs: pair_list,
        rules,
        words,
    })
}

/// What [`selected_pairs`] gives: the pairs, the rules as run.json names them, the bag of words.
struct Selected {
    pairs: Vec<(usize, usize)>,
    rules: Vec<String>,
    words: Option<BagOfWords>,
}

/// Features of every image (read from the store or extracted into it) and the first pass's
/// pair selection, stored for the workers that match it (`posediff.distributed`'s driver).
/// Returns how many pairs and the selection's rules.
///
/// # Errors
/// Fewer than two images; as [`extract_and_match`].
pub fn extract_and_select(
    images: &[PathBuf],
    config: &GeometricConfig,
    counter: &dyn StepCounter,
) -> Result<(usize, String)> {
    if images.len() < 2 {
        return Err(PosediffError::TooFewImages {
            needed: 2,
            got: images.len(),
        });
    }
    let features = config.correspondences().extract(images, counter)?;
    let selected = selected_pairs(config, &features)?;
    Ok((selected.pairs.len(), selected.rules.join(",")))
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
    refine_given_cameras_counted(images, init, config, &NoCounter)
}

/// [`refine_given_cameras`], reporting its matching stages on `counter` as
/// [`estimate_geometric_counted`] does.
///
/// # Errors
/// As [`refine_given_cameras`].
pub fn refine_given_cameras_counted(
    images: &[PathBuf],
    init: &[Option<Camera>],
    config: &GeometricConfig,
    counter: &dyn StepCounter,
) -> Result<GeometricEstimate> {
    if init.len() != images.len() {
        return Err(PosediffError::InvalidArgument(format!(
            "{} initial cameras for {} images",
            init.len(),
            images.len()
        )));
    }
    let Some(reference) = init.iter().position(Option::is_some) else {
        return Err(PosediffError::InvalidArgument(
            "no initial camera is estimated".into(),
        ));
    };
    let Matched {
        features,
        mut pairs,
        mut times,
        selection,
        ..
    } = match_all(images, config, None, counter)?;
    let matcher = config.correspondences();
    let sizes: Vec<ImageSize> = features.iter().map(|f| f.image_size).collect();
    // The second pass needs no first map here: the given cameras say which images overlap.
    let mut densified = 0;
    if let (_, Some(d)) = config.plan(images.len()) {
        let matched: HashSet<(usize, usize)> = pairs.iter().map(|p| (p.first, p.second)).collect();
        let extra = densify_pairs(init, &matched, &d);
        let clock = Instant::now();
        pairs.extend(matcher.match_pairs(&features, &extra, (counter, "second pass"))?);
        times[2] += clock.elapsed().as_secs_f64();
        densified = extra.len();
    }
    counter.stage("refining", 0);
    let CameraLayout {
        intrinsics: layout,
        known_phi,
        ..
    } = camera_layout(
        &sizes,
        &config.intrinsics,
        CameraMode::Single,
        &[],
        config.options.mapper.focal_prior,
    )?;
    let mut phi = known_phi.unwrap_or(given_focal_factor(init, &layout));
    let mut report = GeometricReport {
        pair_selection: selection,
        pairs_matched: pairs.len(),
        pairs_densified: densified,
        pairs_with_matches: pairs.iter().filter(|p| !p.is_empty()).count(),
        focal_source: if known_phi.is_some() {
            FocalOrigin::Given
        } else {
            FocalOrigin::InitialCameras
        },
        focal_factor_initial: phi,
        ..GeometricReport::default()
    };
    (
        report.times.extraction,
        report.times.pair_selection,
        report.times.matching_pairs,
    ) = (times[0], times[1], times[2]);
    report.times.matching = times.iter().sum();
    let start = Instant::now();
    let mut out: Vec<Option<Camera>> = init.to_vec();
    if let Refinement::Converge(mut refine) = config.refinement {
        refine.refine_focal &= known_phi.is_none();
        let known = match &config.intrinsics {
            KnownIntrinsics::PerImage(k) => Some(&k[..]),
            _ => None,
        };
        let r = sampson_refine_cameras(
            &mut out,
            &pairs,
            (&layout, &mut phi, known),
            reference,
            &refine,
        )?;
        report.given_refinement = Some(r);
    }
    if let Refinement::Official(ggs) = config.refinement {
        let mut ggs = ggs;
        ggs.fix_focal |= known_phi.is_some();
        official_ggs(&mut out, &pairs, &ggs)?;
    }
    report.focal_factor = phi;
    report.estimated = (0..images.len()).filter(|&i| out[i].is_some()).collect();
    report.times.refinement = start.elapsed().as_secs_f64();
    Ok(GeometricEstimate {
        cameras: out,
        sizes,
        pairs,
        points: Vec::new(),
        report,
        warnings: Vec::new(),
        lens: None,
    })
}

/// The cameras of an estimate as laid out before the mapper: each image's principal point,
/// focal scale and camera group, `φ` when the focal is known, and each image's focal prior.
struct CameraLayout {
    intrinsics: ImageIntrinsics,
    known_phi: Option<f64>,
    decided_by: &'static str,
    /// Per image: how its prior was read (`None`: no prior, the focal self-calibrated).
    prior: Vec<Option<String>>,
}

/// The camera layout of `mode` with the files' `hints` (none, or one per image).
///
/// Groups: `single` one; `per-image` one each; `per-folder` one per folder; `auto` one per
/// EXIF camera and image size (the images without EXIF one more), or one split later by the
/// mapper from the data when no image has EXIF. A group whose images all have an EXIF focal
/// starts from it: `s_i = f_exif / focal_prior`, so that `φ = mapper.focal_prior` (the
/// mapper's fixed start) is the EXIF focal and self-calibration still moves it.
fn camera_layout(
    sizes: &[ImageSize],
    known: &KnownIntrinsics,
    mode: CameraMode,
    hints: &[CameraHint],
    focal_prior: f64,
) -> Result<CameraLayout> {
    let n = sizes.len();
    if !hints.is_empty() && hints.len() != n {
        return Err(PosediffError::InvalidArgument(format!(
            "{} camera hints for {n} images",
            hints.len()
        )));
    }
    if let Some(k) = resolve_intrinsics(known, sizes)? {
        return Ok(CameraLayout {
            intrinsics: ImageIntrinsics::from_known(&k),
            known_phi: Some(1.0),
            decided_by: "given",
            prior: vec![Some("given".into()); n],
        });
    }
    let hint = |i: usize| hints.get(i);
    let exif = hints.iter().any(|h| h.device.is_some());
    let keys: Option<Vec<String>> = match mode {
        CameraMode::Single => None,
        CameraMode::PerImage => Some((0..n).map(|i| i.to_string()).collect()),
        CameraMode::PerFolder => Some(
            (0..n)
                .map(|i| hint(i).map(|h| h.folder.clone()).unwrap_or_default())
                .collect(),
        ),
        CameraMode::Auto if exif => Some(
            (0..n)
                .map(|i| match hint(i).and_then(|h| h.device.as_deref()) {
                    Some(d) => format!("{d} {}x{}", sizes[i].width(), sizes[i].height()),
                    None => String::new(),
                })
                .collect(),
        ),
        CameraMode::Auto => None,
    };
    let mut intrinsics = ImageIntrinsics::from_sizes(sizes);
    if let Some(keys) = keys {
        let mut index: HashMap<&str, usize> = HashMap::new();
        for (i, key) in keys.iter().enumerate() {
            let next = index.len();
            intrinsics.group[i] = *index.entry(key.as_str()).or_insert(next);
        }
    }
    let focal = |i: usize| hint(i).and_then(|h| h.focal.prior(sizes[i].width(), sizes[i].height()));
    let mut whole = vec![true; intrinsics.groups()];
    for (i, &g) in intrinsics.group.iter().enumerate() {
        whole[g] &= focal(i).is_some_and(|(f, _)| f.is_finite() && f > 0.0);
    }
    let mut prior = vec![None; n];
    for i in 0..n {
        if let (true, Some((f, how))) = (whole[intrinsics.group[i]], focal(i)) {
            intrinsics.scale[i] = f / focal_prior;
            prior[i] = Some(how.to_owned());
        }
    }
    let decided_by = match mode {
        CameraMode::Auto if exif => "exif",
        CameraMode::Auto => "from the data",
        m => m.as_str(),
    };
    Ok(CameraLayout {
        intrinsics,
        known_phi: None,
        decided_by,
        prior,
    })
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
    estimate_from_supported_matches(sizes, pairs, None, config)
}

/// [`estimate_from_matches`] with support flags, one per pair (`true`: evidence beyond the
/// matcher's own; see [`crate::options::SupportOptions`]): the mapper keeps an
/// unsupported pair only when a triangle of kept pairs confirms it.
///
/// # Errors
/// As [`estimate_from_matches`]; support flags of another count than the pairs.
pub fn estimate_from_supported_matches(
    sizes: &[ImageSize],
    pairs: Vec<PairMatches>,
    support: Option<Vec<bool>>,
    config: &GeometricConfig,
) -> Result<GeometricEstimate> {
    map_supported_matches(
        sizes,
        pairs,
        support,
        config,
        (&TwoViewCache::default(), None),
    )
}

/// [`estimate_from_supported_matches`] with the two-view results of the estimate's earlier
/// mapper runs.
fn map_supported_matches(
    sizes: &[ImageSize],
    pairs: Vec<PairMatches>,
    support: Option<Vec<bool>>,
    config: &GeometricConfig,
    (cache, fixed_focals): (&TwoViewCache, Option<&[f64]>),
) -> Result<GeometricEstimate> {
    let n = sizes.len();
    if n < 2 {
        return Err(PosediffError::TooFewImages { needed: 2, got: n });
    }
    let cameras = camera_layout(
        sizes,
        &config.intrinsics,
        config.options.cameras.mode,
        &config.hints,
        config.options.mapper.focal_prior,
    )?;
    let (mut layout, mut known_phi) = (cameras.intrinsics.clone(), cameras.known_phi);
    if let Some(focals) = fixed_focals {
        // Each image's focal held (a fisheye lens is defined at it), the cameras as decided.
        layout.scale = focals.to_vec();
        known_phi = Some(1.0);
    }
    let mapper = GlobalMapper::new(config.mapper_options());
    let solver = OpenCvTwoView {
        config: &config.options.two_view,
        cache: Some(cache),
    };
    let reconstruction = match &support {
        Some(flags) => {
            mapper.run_with_support(&pairs, flags, layout, known_phi.is_some(), &solver)?
        }
        None => mapper.run(&pairs, layout, known_phi.is_some(), &solver)?,
    };
    let mut report = GeometricReport::default();
    report.record_mapper(&reconstruction.report);
    report.record_cameras(
        config.options.cameras.mode,
        cameras.decided_by,
        &cameras.prior,
        &reconstruction.intrinsics,
        reconstruction.phi,
        (
            reconstruction.report.cameras.as_ref(),
            &reconstruction.report.camera_split,
        ),
    );
    let mut pairs = pairs;
    if let Some(s) = &reconstruction.report.support {
        // The rejected pairs keep their record without matches: nothing downstream (GGS,
        // points, exports) may use them.
        let rejected: std::collections::HashSet<[usize; 2]> =
            s.rejected_pairs.iter().copied().collect();
        for p in &mut pairs {
            if rejected.contains(&[p.first, p.second]) {
                *p = PairMatches {
                    first: p.first,
                    second: p.second,
                    kp1: Vec::new(),
                    kp2: Vec::new(),
                    idx1: Vec::new(),
                    idx2: Vec::new(),
                };
            }
        }
    }
    let mut warnings = Vec::new();
    if reconstruction.report.no_parallax {
        warnings.push(Warning::NoParallax);
    }
    let not_estimated = reconstruction.report.not_estimated.len();
    if not_estimated > 0 {
        warnings.push(Warning::NotEstimated {
            count: not_estimated,
            of: n,
        });
    }
    let mut cameras = reconstruction
        .cameras
        .iter()
        .enumerate()
        .map(|(i, c)| {
            let Some(c) = c else { return Ok(None) };
            let intrinsics = match &config.intrinsics {
                KnownIntrinsics::PerImage(given) => given[i],
                _ => reconstruction
                    .intrinsics
                    .intrinsics(reconstruction.phi, i)?,
            };
            Ok(Some(Camera::new(
                intrinsics,
                Pose::new(*c.rotation.matrix(), c.translation()),
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
        points: reconstruction.points,
        report,
        warnings,
        lens: None,
    })
}

#[cfg(test)]
mod tests {
    #![allow(clippy::unwrap_used, clippy::expect_used)]
    use super::*;
    use nalgebra::{Rotation3, Vector3};
    use posediff_sfm::resection::{Evidence, ResectionOptions, resect_bridged_sides};
    use posediff_sfm::tracks::build_tracks;

    const N: usize = 6;

    fn hint(folder: &str, device: Option<&str>, f35: Option<f64>) -> CameraHint {
        CameraHint {
            folder: folder.into(),
            device: device.map(Into::into),
            focal: crate::options::ExifFocal {
                focal_35mm: f35,
                ..Default::default()
            },
        }
    }

    /// Groups per mode, EXIF priors only where a whole group has one, each at its image's
    /// size, and a count of hints that is not the images' an error.
    #[test]
    fn camera_layouts_follow_the_mode_and_the_exif() {
        let big = ImageSize::new(700, 350).unwrap();
        let small = ImageSize::new(350, 175).unwrap();
        let sizes = [big, big, small, big, big];
        let hints = [
            hint("a", Some("Acme 4.00 mm"), Some(35.0)),
            hint("a", Some("Acme 6.00 mm"), Some(52.5)),
            hint("b", Some("Acme 4.00 mm"), Some(35.0)),
            hint("b", None, None),
            hint("b", Some("Acme 4.00 mm"), Some(35.0)),
        ];
        let layout = |mode, hints: &[CameraHint]| {
            camera_layout(&sizes, &KnownIntrinsics::Unknown, mode, hints, 1.2).unwrap()
        };
        // Auto with EXIF: device and size; the image without EXIF in a group of its own.
        let auto = layout(CameraMode::Auto, &hints);
        assert_eq!(auto.decided_by, "exif");
        assert_eq!(auto.intrinsics.group, vec![0, 1, 2, 3, 0]);
        // f_35 = 35 mm: the focal is the longer side; the scale puts it at φ = 1.2.
        assert!((auto.intrinsics.focal(1.2, 0) - 700.0).abs() < 1e-9);
        assert!((auto.intrinsics.focal(1.2, 1) - 1050.0).abs() < 1e-9);
        assert!((auto.intrinsics.focal(1.2, 2) - 350.0).abs() < 1e-9);
        assert_eq!(auto.prior[3], None);
        assert_eq!(auto.prior[0].as_deref(), Some("exif 35 mm equivalent"));
        // Per folder: folder b holds the image without EXIF, so b keeps no prior.
        let folder = layout(CameraMode::PerFolder, &hints);
        assert_eq!(folder.intrinsics.group, vec![0, 0, 1, 1, 1]);
        assert!(folder.prior[0].is_some() && folder.prior[2].is_none());
        assert_eq!(
            folder.intrinsics.scale[2],
            ImageIntrinsics::from_sizes(&sizes).scale[2]
        );
        assert_eq!(
            layout(CameraMode::PerImage, &hints).intrinsics.group,
            vec![0, 1, 2, 3, 4]
        );
        assert_eq!(layout(CameraMode::Single, &hints).intrinsics.groups(), 1);
        // No EXIF at all: auto leaves the split to the data.
        let bare: Vec<CameraHint> = (0..5).map(|_| hint("", None, None)).collect();
        let auto = layout(CameraMode::Auto, &bare);
        assert_eq!(
            (auto.decided_by, auto.intrinsics.groups()),
            ("from the data", 1)
        );
        assert!(
            camera_layout(
                &sizes,
                &KnownIntrinsics::Unknown,
                CameraMode::Auto,
                &hints[..2],
                1.2
            )
            .is_err()
        );
        let given = camera_layout(
            &sizes,
            &KnownIntrinsics::FocalPx(500.0),
            CameraMode::Auto,
            &hints,
            1.2,
        )
        .unwrap();
        assert_eq!((given.decided_by, given.known_phi), ("given", Some(1.0)));
    }

    fn as_cameras(poses: &[Option<CameraPose>]) -> Vec<Option<Camera>> {
        let k = posediff_geometry::Intrinsics::new(500.0, 500.0, 320.0, 240.0).unwrap();
        let size = ImageSize::new(640, 480).unwrap();
        poses
            .iter()
            .map(|p| {
                p.map(|p| Camera::new(k, Pose::new(*p.rotation.matrix(), p.translation()), size))
            })
            .collect()
    }

    /// The second pass's pairs: within the angle, nearest first, at most `per_image` per
    /// image, never a matched pair or an image without a camera.
    #[test]
    fn densify_pairs_are_the_nearest_unmatched_within_the_angle() {
        let mut cams = as_cameras(&cameras());
        cams[5] = None;
        let angle = |i: usize, j: usize| {
            let (a, b) = (cams[i].unwrap(), cams[j].unwrap());
            posediff_geometry::epipolar::rotation_angle_between_deg(
                &a.cam_from_world.rotation,
                &b.cam_from_world.rotation,
            )
        };
        let matched: HashSet<(usize, usize)> = [(0, 1), (1, 2)].into_iter().collect();
        let d = Densify {
            max_angle_deg: 45.0,
            per_image: 1,
        };
        let pairs = densify_pairs(&cams, &matched, &d);
        assert!(!pairs.is_empty());
        for &(i, j) in &pairs {
            assert!(i < j && j != 5 && !matched.contains(&(i, j)));
            assert!(angle(i, j) <= 45.0);
        }
        // Each image contributed its nearest unmatched neighbour, so every pair is the
        // nearest unmatched one of one of its images.
        for &(i, j) in &pairs {
            let nearest = |a: usize| {
                (0..5)
                    .filter(|&b| b != a && !matched.contains(&(a.min(b), a.max(b))))
                    .min_by(|&x, &y| angle(a, x).total_cmp(&angle(a, y)))
                    .unwrap()
            };
            assert!(nearest(i) == j || nearest(j) == i, "({i}, {j})");
        }
        assert!(pairs.len() <= 5);
        // A wide angle and a large budget give every unmatched pair of estimated images.
        let all = densify_pairs(
            &cams,
            &matched,
            &Densify {
                max_angle_deg: 180.0,
                per_image: 10,
            },
        );
        assert_eq!(all.len(), 5 * 4 / 2 - matched.len());
        // A tight angle gives none.
        let none = Densify {
            max_angle_deg: 1.0,
            per_image: 10,
        };
        assert!(densify_pairs(&cams, &matched, &none).is_empty());
    }

    /// Without a learned matcher `auto` is `pairs.auto` resolved for the set's size, and the
    /// second pass only runs when configured.
    #[test]
    fn the_plan_without_a_learned_matcher_is_the_configuration() {
        let mut config = GeometricConfig::default();
        let rules = |r: &[PairRule]| PairSelection::Rules(r.to_vec());
        let big = rules(&[PairRule::Sequential(10), PairRule::Retrieval(20)]);
        assert_eq!(config.plan(200), (big, None));
        assert_eq!(config.plan(60), (rules(&[PairRule::Exhaustive]), None));
        config.options.pairs.auto.exhaustive_up_to = 4;
        config.options.pairs.auto.sequential = 2;
        assert_eq!(
            config.plan(5).0,
            rules(&[PairRule::Sequential(2), PairRule::Retrieval(20)])
        );
        config.options.densify.when = crate::options::DensifyWhen::Always;
        assert_eq!(config.plan(5).1, Some(Densify::default()));
    }

    /// Six cameras on an arc 2.5 above a table (`z = 0`), looking at its centre.
    fn cameras() -> Vec<Option<CameraPose>> {
        (0..N)
            .map(|i| {
                let a = 0.35 * i as f64;
                let center = Vector3::new(3.0 * a.cos(), 3.0 * a.sin(), 2.5);
                let forward = (-center).normalize();
                let right = forward.cross(&Vector3::z()).normalize();
                let down = forward.cross(&right);
                let rotation = Rotation3::from_matrix(&Matrix3::from_rows(&[
                    right.transpose(),
                    down.transpose(),
                    forward.transpose(),
                ]));
                Some(CameraPose { rotation, center })
            })
            .collect()
    }

    fn intrinsics() -> ImageIntrinsics {
        ImageIntrinsics::new(vec![[320.0, 240.0]; N], vec![640.0; N])
    }

    /// Table points (and `object` points above it), numbered from `first`.
    fn points(first: usize, count: usize, object: bool) -> Vec<(u32, Vector3<f64>)> {
        let mut s: u64 = 0x5eed + first as u64;
        let mut rnd = || {
            s = s
                .wrapping_mul(6_364_136_223_846_793_005)
                .wrapping_add(1_442_695_040_888_963_407);
            ((s >> 33) as f64) / f64::from(1u32 << 31) - 0.5
        };
        (0..count)
            .map(|k| {
                let z = if object && k % 3 == 0 {
                    0.4 + 0.4 * rnd()
                } else {
                    0.0
                };
                (
                    (first + k) as u32,
                    Vector3::new(2.0 * rnd(), 2.0 * rnd(), z),
                )
            })
            .collect()
    }

    /// The exact matches of `points` between cameras `a` and `b` (keypoint id = point id).
    fn pair(a: usize, b: usize, pts: &[(u32, Vector3<f64>)]) -> PairMatches {
        pair_seen_by(a, b, pts, cameras()[b].unwrap())
    }

    /// Matches of `points` whose pixels in `b` are where camera `seen_by` sees them.
    fn pair_seen_by(
        a: usize,
        b: usize,
        pts: &[(u32, Vector3<f64>)],
        seen_by: CameraPose,
    ) -> PairMatches {
        let (cams, k) = (cameras(), intrinsics());
        let project = |c: CameraPose, i: usize, x: &Vector3<f64>| {
            let p = k.k(1.0, i) * (c.rotation * (x - c.center));
            [p.x / p.z, p.y / p.z]
        };
        PairMatches {
            first: a,
            second: b,
            kp1: pts
                .iter()
                .map(|(_, x)| project(cams[a].unwrap(), a, x))
                .collect(),
            kp2: pts.iter().map(|(_, x)| project(seen_by, b, x)).collect(),
            idx1: pts.iter().map(|(id, _)| *id).collect(),
            idx2: pts.iter().map(|(id, _)| *id).collect(),
        }
    }

    /// Side {3, 4, 5} turned by 25° about camera 3 and scaled by `scale`: a wrong bridge pose.
    fn misplaced(scale: f64) -> Vec<Option<CameraPose>> {
        let truth = cameras();
        let pivot = truth[3].unwrap();
        let turn = Rotation3::from_axis_angle(&Vector3::y_axis(), 25f64.to_radians());
        truth
            .iter()
            .enumerate()
            .map(|(i, c)| {
                let c = c.unwrap();
                Some(if i < 3 {
                    c
                } else {
                    CameraPose {
                        rotation: c.rotation * turn.inverse(),
                        center: pivot.center + scale * (turn * (c.center - pivot.center)),
                    }
                })
            })
            .collect()
    }

    fn worst_error(cameras: &[Option<CameraPose>]) -> (f64, f64) {
        let truth = self::cameras();
        cameras
            .iter()
            .zip(&truth)
            .fold((0.0, 0.0), |(r, c), (a, b)| {
                let (a, b) = (a.unwrap(), b.unwrap());
                (
                    r.max((a.rotation * b.rotation.inverse()).angle().to_degrees()),
                    c.max((a.center - b.center).norm()),
                )
            })
    }

    fn run(
        pairs: &[PairMatches],
        cameras: &mut [Option<CameraPose>],
    ) -> posediff_sfm::resection::ResectionReport {
        let edges: Vec<(usize, usize)> = pairs.iter().map(|p| (p.first, p.second)).collect();
        run_with(pairs, &edges, cameras, &ResectionOptions::default())
    }

    fn run_with(
        pairs: &[PairMatches],
        edges: &[(usize, usize)],
        cameras: &mut [Option<CameraPose>],
        options: &ResectionOptions,
    ) -> posediff_sfm::resection::ResectionReport {
        let (tracks, _) = build_tracks(N, pairs).unwrap();
        let config = posediff_matching::TwoViewConfig::default();
        resect_bridged_sides(
            &tracks,
            pairs,
            &intrinsics(),
            1.0,
            cameras,
            edges,
            &OpenCvTwoView::new(&config),
            options,
        )
        .unwrap()
    }

    #[test]
    fn a_side_on_a_wrong_bridge_is_resected_from_the_tracks_through_it() {
        // Triangles {0, 1, 2} and {3, 4, 5} joined by the bridge 2–3; one set of points seen by
        // all, so tracks run through the bridge.
        let pts = points(0, 80, true);
        let links = [(0, 1), (1, 2), (0, 2), (2, 3), (3, 4), (4, 5), (3, 5)];
        let pairs: Vec<PairMatches> = links.iter().map(|&(a, b)| pair(a, b, &pts)).collect();
        let mut cams = misplaced(1.7);
        assert!(worst_error(&cams).0 > 20.0);
        let report = run(&pairs, &mut cams);
        assert_eq!(report.bridges, 1);
        assert_eq!(report.moved.len(), 1, "{report:?}");
        let moved = report.moved[0];
        assert_eq!(
            (moved.first, moved.second, moved.evidence),
            (2, 3, Evidence::Tracks)
        );
        assert_eq!(moved.images, 3);
        let scale = moved.scale.expect("the shared points observe the scale");
        assert!((scale - 1.0 / 1.7).abs() < 1e-3, "{scale}");
        let (rotation, centre) = worst_error(&cams);
        assert!(rotation < 0.01 && centre < 1e-3, "{rotation}° {centre}");
        // Where the cameras are right, nothing moves.
        let report = run(&pairs, &mut cams);
        assert!(report.moved.is_empty(), "{report:?}");
    }

    #[test]
    fn a_planar_bridge_without_tracks_is_resected_on_the_anchor_s_plane() {
        // The bridge 2–3 matches table points that no other pair of the anchor sees, so no
        // track through it has two anchor observations: only the plane can place camera 3.
        let anchor = points(0, 80, true);
        let bridge = points(1000, 40, false);
        let side = points(2000, 60, true);
        let mut pairs: Vec<PairMatches> = [(0, 1), (1, 2), (0, 2)]
            .iter()
            .map(|&(a, b)| pair(a, b, &anchor))
            .collect();
        pairs.push(pair(2, 3, &bridge));
        let with_bridge: Vec<(u32, Vector3<f64>)> = side.iter().chain(&bridge).copied().collect();
        for (a, b) in [(3, 4), (4, 5), (3, 5)] {
            pairs.push(pair(a, b, &with_bridge));
        }
        let mut cams = misplaced(0.6);
        let report = run(&pairs, &mut cams);
        assert_eq!(report.moved.len(), 1, "{report:?}");
        let moved = report.moved[0];
        assert_eq!((moved.image, moved.evidence), (3, Evidence::Plane));
        assert!(moved.inliers_after >= 38, "{moved:?}");
        let scale = moved.scale.expect("the side's points meet the plane");
        assert!((scale - 1.0 / 0.6).abs() < 1e-3, "{scale}");
        let (rotation, centre) = worst_error(&cams);
        assert!(rotation < 0.01 && centre < 1e-3, "{rotation}° {centre}");
        let report = run(&pairs, &mut cams);
        assert!(report.moved.is_empty(), "{report:?}");
    }

    #[test]
    fn tracks_of_wrong_matches_do_not_move_a_side_against_its_bridge() {
        // As the first test with the cameras right, plus a pair 2–4 (left out of the pose graph,
        // as the rotation check drops it, but in the tracks) whose pixels in 4 are where a
        // camera turned by 40° would see the points: repeated structure matched wrongly, more
        // of it than the right matches. A PnP of 4 on the anchor's points (0 and 2 see them
        // right) fits that camera with 200 inliers against 80 for the right pose.
        let pts = points(0, 80, true);
        let links = [(0, 1), (1, 2), (0, 2), (2, 3), (3, 4), (4, 5), (3, 5)];
        let mut pairs: Vec<PairMatches> = links.iter().map(|&(a, b)| pair(a, b, &pts)).collect();
        let edges: Vec<(usize, usize)> = links.to_vec();
        let truth = cameras()[4].unwrap();
        let turn = Rotation3::from_axis_angle(&Vector3::z_axis(), 40f64.to_radians());
        let wrong = CameraPose {
            rotation: truth.rotation * turn.inverse(),
            center: turn * truth.center,
        };
        let mirrored = points(5000, 200, true);
        pairs.push(pair(0, 2, &mirrored));
        pairs.push(pair_seen_by(2, 4, &mirrored, wrong));
        let mut cams = cameras();
        let report = run_with(&pairs, &edges, &mut cams, &ResectionOptions::default());
        assert!(report.moved.is_empty(), "{report:?}");
        assert_eq!(cams, cameras());
        // Without the bridge's epipolar check the tracks would have moved the side.
        let unchecked = ResectionOptions {
            min_relative_inliers: 0.0,
            ..ResectionOptions::default()
        };
        let report = run_with(&pairs, &edges, &mut cams, &unchecked);
        assert_eq!(report.moved.len(), 1, "{report:?}");
        assert_eq!(
            (report.moved[0].image, report.moved[0].evidence),
            (4, Evidence::Tracks)
        );
    }
}
