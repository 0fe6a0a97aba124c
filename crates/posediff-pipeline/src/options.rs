//! The options of a run: [`PipelineOptions`], every threshold of the checkpoint-free pipeline
//! in one tree, and what is known of the intrinsics and how the cameras are refined.

use std::path::Path;

use posediff_geometry::{ImageSize, Intrinsics};
use posediff_matching::pairs::AutoPairs;
use posediff_matching::{MatchConfig, PairRule, PairSelection, TwoViewConfig};
use posediff_sfm::MapperOptions;
use posediff_sfm::intrinsics::image_centre;
use posediff_sfm::points::PointOptions;
use serde::{Deserialize, Serialize};

use crate::error::{PosediffError, Result};

/// How the cameras are refined (`--refine`).
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default, Serialize)]
#[serde(rename_all = "snake_case")]
pub enum RefineMode {
    /// Levenberg–Marquardt on the Sampson distances until the cost stops falling, then the
    /// bundle adjustment with tracks.
    #[default]
    Converge,
    /// With a checkpoint: PoseDiffusion's cameras (after GGS) refined by the mapper's bundle
    /// adjustment; without, as `Converge`.
    Bundle,
    /// The official five-phase GGS schedule (7000 SGD iterations) in the 224 crops.
    Official,
    /// The averaged cameras as they are.
    None,
}

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

/// Every threshold of the checkpoint-free pipeline, one tree: each stage's options struct with
/// its documented defaults and the measurements that chose them. run.json carries it whole
/// (`options`), `posediff estimate --config FILE` (TOML or JSON, any subset of the tree) and
/// `--set key.path=value` change it, and so do the Python module's `config=` and
/// `options={"key.path": value}`. Unknown keys are errors that name the key and where it came
/// from.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(default, deny_unknown_fields)]
pub struct PipelineOptions {
    /// Which pairs are matched.
    pub pairs: PairOptions,
    /// Features and matching (OpenCV's; `features.detector` follows `--matcher`).
    pub matching: MatchConfig,
    /// Two-view geometry (its `homography_fraction` is also the mapper's).
    pub two_view: TwoViewConfig,
    /// A learned matcher's orientation check before the map.
    pub orientation: OrientationOptions,
    /// A learned matcher's turned retry of the images the map left out.
    pub retry: RetryOptions,
    /// The second matching pass after a first map.
    pub densify: DensifyOptions,
    /// The support check of learned pairs (off by default).
    pub support: SupportOptions,
    /// Which photos share a camera.
    pub cameras: CameraOptions,
    /// The mapper's stages (`posediff_sfm::MapperOptions`; its `sampson` is the refinement
    /// `--refine converge|bundle` runs, and with a learned matcher `score_dropped_as_missing`
    /// is on whatever it says here).
    pub mapper: MapperOptions,
    /// Video input: which frames are decoded and kept as keyframes.
    pub video: VideoOptions,
    /// `--database`: how often features and matches are committed to it.
    pub database: DatabaseOptions,
    /// The learned matcher's arithmetic (`--matcher aliked-lightglue|disk-lightglue`).
    pub learned: LearnedOptions,
    /// The sparse points of the exports (COLMAP model, PLY, viewer), triangulated from the
    /// verified matches with the final cameras whichever path made them
    /// (`posediff_sfm::points::PointOptions`): an observation further than
    /// `max_reprojection_px` = 4 px from its point's projection is dropped (COLMAP's
    /// `filter_max_reproj_error`, 4), a point whose widest ray angle is below `min_angle_deg` =
    /// 1.5° is not kept (COLMAP's `filter_min_tri_angle`, 1.5), `iterations` = 10 Gauss–Newton
    /// steps per point (converged well before on the shared sets).
    pub points: PointOptions,
}

impl Default for PipelineOptions {
    fn default() -> Self {
        let mut matching = MatchConfig::default();
        matching.features.contrast_threshold = GEOMETRIC_CONTRAST_THRESHOLD;
        matching.features.max_keypoints = GEOMETRIC_MAX_KEYPOINTS;
        Self {
            pairs: PairOptions::default(),
            matching,
            two_view: TwoViewConfig::default(),
            orientation: OrientationOptions::default(),
            retry: RetryOptions::default(),
            densify: DensifyOptions::default(),
            support: SupportOptions::default(),
            cameras: CameraOptions::default(),
            mapper: MapperOptions::default(),
            video: VideoOptions::default(),
            database: DatabaseOptions::default(),
            learned: LearnedOptions::default(),
            points: PointOptions::default(),
        }
    }
}

/// Long side the learned matcher resizes every image to (the reference pipeline's setting,
/// `LearnedOptions::image_side`).
pub const LEARNED_IMAGE_SIDE: u32 = 1024;
/// ALIKED's or DISK's keypoints per image (`LearnedOptions::max_keypoints`).
pub const LEARNED_MAX_KEYPOINTS: usize = 2048;

/// The learned matcher (ALIKED/DISK + LightGlue): image size, keypoints, arithmetic.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize)]
#[serde(default, deny_unknown_fields)]
pub struct LearnedOptions {
    /// Long side each image is resized to before extraction (OpenCV INTER_AREA; keypoints are
    /// mapped back to the original pixels): 1024, the reference pipeline's.
    pub image_side: u32,
    /// Keypoints per image, the strongest after NMS with no detection threshold (so weak
    /// texture still gets keypoints): 2048, the reference setting; at 2048 the apple's 20
    /// frames gain mAA(30) over SIFT at every subset size (docs/BENCHMARKS.md, "Learned
    /// matching").
    pub max_keypoints: usize,
    /// The precision of LightGlue's large products (its input projection, attention and
    /// feed-forward layers). `highest` (the default): F32, the reference's arithmetic, the
    /// same matches on every CPU. `high`: PyTorch's "high", each F32 operand as the sum of two
    /// BF16 values on AMX tiles where the CPU has them (F32 elsewhere), LightGlue about 1.3×
    /// faster there. Opt-in because it does not give the same matches on every shared set:
    /// with it, two of the apple's 80 pairs keep other verified matches (534 and 335 against
    /// F32's 527 and 333) and its cameras move by up to 0.02°, mAA(30) unchanged
    /// (docs/BENCHMARKS.md, "AMX tiles on or off: the shared sets").
    pub precision: LearnedPrecision,
}

impl Default for LearnedOptions {
    fn default() -> Self {
        Self {
            image_side: LEARNED_IMAGE_SIDE,
            max_keypoints: LEARNED_MAX_KEYPOINTS,
            precision: LearnedPrecision::default(),
        }
    }
}

/// [`LearnedOptions::precision`].
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default, Serialize, Deserialize)]
#[serde(rename_all = "kebab-case")]
pub enum LearnedPrecision {
    /// F32 products.
    #[default]
    Highest,
    /// Two BF16 terms per operand on AMX tiles where available.
    High,
}

impl LearnedPrecision {
    /// The network crate's precision.
    pub fn matmul(self) -> posediff_diffusion::MatmulPrecision {
        match self {
            Self::Highest => posediff_diffusion::MatmulPrecision::Highest,
            Self::High => posediff_diffusion::MatmulPrecision::High,
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

/// How a run writes `--database` (`crate::store::Stored`): what it extracts and matches is
/// committed in chunks, so that a run killed mid-way loses at most one chunk of work and the
/// next run resumes from the rest. One commit costs a few milliseconds (SQLite's journal and
/// sync): at 32 images and 256 pairs the commits are under 1 % of the extraction and matching
/// time of the 300-frame synthetic orbit, and a lost chunk is a few seconds of work.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize)]
#[serde(default, deny_unknown_fields)]
pub struct DatabaseOptions {
    /// Images extracted per commit.
    pub images_per_commit: usize,
    /// Pairs matched per commit.
    pub pairs_per_commit: usize,
}

impl Default for DatabaseOptions {
    fn default() -> Self {
        Self {
            images_per_commit: 32,
            pairs_per_commit: 256,
        }
    }
}

/// Which pairs are matched.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(default, deny_unknown_fields)]
pub struct PairOptions {
    /// The selection (`--pairs`): `auto`, `exhaustive`, `sequential:K`, `retrieval:K` or a
    /// comma-separated union.
    pub selection: PairSelection,
    /// What `auto` means with OpenCV's matchers.
    pub auto: AutoPairs,
    /// With a learned matcher, `auto` matches sets of up to this many images exhaustively;
    /// larger ones on `learned_first_pass` and then the second pass (`densify`). LightGlue
    /// costs about 0.9 s a pair on two AVX-512 cores at 2048 keypoints (1.3–1.4 s on AVX2):
    /// exhaustive pairs grow as n².
    pub learned_exhaustive_up_to: usize,
    /// The first pass of a learned matcher's `auto` above `learned_exhaustive_up_to`: each
    /// image with the next 3 and its 3 most similar (measured against `retrieval:3..8`,
    /// `sequential:3..5` and the descriptor screen as ranking on the shared sets).
    pub learned_first_pass: PairSelection,
}

impl Default for PairOptions {
    fn default() -> Self {
        Self {
            selection: PairSelection::Auto,
            auto: AutoPairs::default(),
            learned_exhaustive_up_to: 12,
            learned_first_pass: PairSelection::Rules(vec![
                PairRule::Sequential(3),
                PairRule::Retrieval(3),
            ]),
        }
    }
}

/// A learned matcher's orientation check before the map (`geometric::turn_components`).
/// ALIKED and DISK are not invariant to in-plane rotation: images upside down relative to the
/// others match within their orientation and poorly across, so the strong pairs fall into
/// groups by orientation; each smaller group is tested by one image extracted turned by 180°.
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
#[serde(default, deny_unknown_fields)]
pub struct OrientationOptions {
    /// Whether the check runs (learned matchers without the support check only).
    pub enabled: bool,
    /// Fewest verified matches of a pair that joins two images into one group. Every good
    /// ALIKED + LightGlue pair of the shared sets has at least 96 and no unrelated pair more
    /// than 74 (docs/BENCHMARKS.md, "Pairs").
    pub strong_pair: usize,
    /// Most groups besides the largest that are tested, each by one image extracted turned:
    /// the check's cost is bounded however many frames a run has.
    pub tests: usize,
    /// Partners of a tested or turned image: its most similar images of other groups by the
    /// bag of words.
    pub partners: usize,
    /// The evidence between two groups is decisive when one way (upright or turned) verifies
    /// at least this many matches by the descriptor screen ...
    pub min_matches: usize,
    /// ... and at least this many times the other way's (temple: the turned group verifies
    /// hundreds turned against a handful upright; docs/BENCHMARKS.md, "Groups turned").
    pub ratio: f64,
}

impl Default for OrientationOptions {
    fn default() -> Self {
        Self {
            enabled: true,
            strong_pair: 80,
            tests: 8,
            partners: 8,
            min_matches: 5,
            ratio: 2.0,
        }
    }
}

impl OrientationOptions {
    /// How two groups lie to each other by the verified matches of one group's representative
    /// with the other group's images, upright (`same`) and turned by 180° (`opposite`):
    /// `Some(true)` when turned wins clearly (at least [`Self::min_matches`] and
    /// [`Self::ratio`] times the other way's), `Some(false)` when upright does, `None` when
    /// neither.
    pub fn evidence(&self, same: usize, opposite: usize) -> Option<bool> {
        let (high, low) = (same.max(opposite), same.min(opposite));
        (high >= self.min_matches && high as f64 >= self.ratio * low as f64)
            .then_some(opposite > same)
    }
}

/// A learned matcher's retry of the images its map left out (`geometric::turn_left_out`):
/// each is extracted again turned by 180° and matched with the estimated images among its
/// most similar; kept turned when those pairs verify more matches than upright.
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
#[serde(default, deny_unknown_fields)]
pub struct RetryOptions {
    /// Whether the retry runs (learned matchers without the support check only).
    pub enabled: bool,
    /// Partners of a retried image: the estimated images among its this many most similar by
    /// the bag of words (temple's turned five found their partners at 8; docs/BENCHMARKS.md).
    pub partners: usize,
}

impl Default for RetryOptions {
    fn default() -> Self {
        Self {
            enabled: true,
            partners: 8,
        }
    }
}

/// Which photos share a camera (COLMAP's camera per image or per device).
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default, Serialize, Deserialize)]
#[serde(rename_all = "kebab-case")]
pub enum CameraMode {
    /// With EXIF: a camera per distinct EXIF camera (make, model, focal length) and image size,
    /// as COLMAP groups; the images without EXIF share one more. Without EXIF, decided from the
    /// data: a focal calibrated per image from the view graph (`mapper.calibration`), and the
    /// images whose focals agree within `mapper.calibration.group_tolerance` share one camera;
    /// every other image is a camera of its own. A set taken with one lens stays one camera.
    #[default]
    Auto,
    /// One camera for all images (one focal factor for the set; the mapper before cameras).
    Single,
    /// A camera per folder of the input (COLMAP's `single_camera_per_folder`).
    PerFolder,
    /// A camera per image (COLMAP's default): a focal each, refined in the bundle adjustment.
    PerImage,
}

/// What the caller knows of one image's camera before any estimate: its folder and what its
/// EXIF says. [`crate::geometric::GeometricConfig::hints`] holds one per image (or none).
#[derive(Debug, Clone, PartialEq, Default)]
pub struct CameraHint {
    /// The image's folder relative to the input (`per-folder` groups by it).
    pub folder: String,
    /// The camera its EXIF names (make, model, focal length); `None` without EXIF.
    pub device: Option<String>,
    /// The focal its EXIF gives.
    pub focal: ExifFocal,
}

/// An image's EXIF focal tags, converted to a focal in pixels as COLMAP 4.2 does
/// (`Bitmap::ExifFocalLength`, [`Self::prior`]).
#[derive(Debug, Clone, Copy, PartialEq, Default)]
pub struct ExifFocal {
    /// `FocalLength`, mm.
    pub focal_mm: Option<f64>,
    /// `FocalLengthIn35mmFilm`, mm.
    pub focal_35mm: Option<f64>,
    /// `FocalPlaneXResolution` in pixels per mm.
    pub focal_plane_px_per_mm: Option<f64>,
    /// `PixelXDimension` (the width the focal-plane resolution refers to).
    pub pixel_width: Option<u32>,
}

impl ExifFocal {
    /// The focal in pixels of an image `width × height` and how it was read:
    /// 1. `FocalLengthIn35mmFilm`: `f_px = f_35 / 35 · max(W, H)` (COLMAP's rule);
    /// 2. else `FocalLength` with `FocalPlaneXResolution`, rescaled when `PixelXDimension` is
    ///    not the file's width (a resized copy).
    ///
    /// COLMAP's third source, a sensor-width table per camera model, is not carried: a focal in
    /// mm alone gives no prior.
    pub fn prior(&self, width: u32, height: u32) -> Option<(f64, &'static str)> {
        let max_side = f64::from(width.max(height));
        let usable = |v: &f64| v.is_finite() && *v > 0.0;
        if let Some(f35) = self.focal_35mm.filter(usable) {
            return Some((f35 / 35.0 * max_side, "exif 35 mm equivalent"));
        }
        let (f, per_mm) = (
            self.focal_mm.filter(usable)?,
            self.focal_plane_px_per_mm.filter(usable)?,
        );
        let rescale = self
            .pixel_width
            .filter(|w| *w > 0)
            .map_or(1.0, |w| f64::from(width) / f64::from(w));
        Some((
            f * per_mm * rescale,
            "exif focal length and focal plane resolution",
        ))
    }
}

impl CameraMode {
    /// The name in options and run.json.
    pub fn as_str(self) -> &'static str {
        match self {
            Self::Auto => "auto",
            Self::Single => "single",
            Self::PerFolder => "per-folder",
            Self::PerImage => "per-image",
        }
    }
}

impl std::str::FromStr for CameraMode {
    type Err = PosediffError;

    fn from_str(s: &str) -> Result<Self> {
        match s {
            "auto" => Ok(Self::Auto),
            "single" => Ok(Self::Single),
            "per-folder" => Ok(Self::PerFolder),
            "per-image" => Ok(Self::PerImage),
            other => Err(PosediffError::InvalidArgument(format!(
                "camera mode {other:?}: expected auto, single, per-folder or per-image"
            ))),
        }
    }
}

/// The cameras of an estimate without known intrinsics.
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
#[serde(default, deny_unknown_fields)]
pub struct CameraOptions {
    /// Which photos share a camera (`--camera-mode`).
    pub mode: CameraMode,
    /// The radial distortion of each camera, calibrated from the first pass's verified matches
    /// before the mapper ([`posediff_sfm::distortion_calibration`]); every keypoint is then
    /// undistorted once and the cameras are SIMPLE_RADIAL in the exports. `null`: pinhole
    /// cameras, no calibration.
    pub distortion: Option<posediff_sfm::distortion_calibration::DistortionCalibrationOptions>,
    /// The radial distortion of each camera refined after the mapper by a bundle adjustment on
    /// the photos' own pixels ([`posediff_sfm::lens_refinement`]); when it is kept, the matches
    /// are undistorted with it and mapped again. `null`: the lens stays as calibrated before
    /// the mapper.
    pub lens_refinement: Option<posediff_sfm::lens_refinement::LensRefinementOptions>,
}

impl CameraOptions {
    /// COLMAP's `--ImageReader.camera_model` (`--camera-model`) as settings of this tree:
    /// `SIMPLE_PINHOLE` and `PINHOLE` turn the lens calibration and refinement off (one focal
    /// per camera, the principal point at the centre, no distortion), `SIMPLE_RADIAL` is the
    /// default (a coefficient where the data show one), `RADIAL` refines `k₁, k₂`, `OPENCV`
    /// `k₁, k₂, p₁, p₂` (with one focal, `fx = fy`), `OPENCV_FISHEYE` `k₁…k₄` of the angle
    /// (the focal then held at the adjusted one when the set is mapped again). Names as COLMAP
    /// spells them, in any case.
    ///
    /// # Errors
    /// An unknown name.
    pub fn set_model(&mut self, name: &str) -> Result<()> {
        use posediff_sfm::lens_refinement::{LensModel, LensRefinementOptions};
        let model = posediff_geometry::lens::CameraModel::from_name(&name.to_ascii_uppercase())
            .map_err(|e| PosediffError::InvalidArgument(format!("camera model {name:?}: {e}")))?;
        match model {
            posediff_geometry::lens::CameraModel::SimplePinhole
            | posediff_geometry::lens::CameraModel::Pinhole => {
                self.distortion = None;
                self.lens_refinement = None;
            }
            posediff_geometry::lens::CameraModel::SimpleRadial
            | posediff_geometry::lens::CameraModel::Radial
            | posediff_geometry::lens::CameraModel::OpenCv
            | posediff_geometry::lens::CameraModel::OpenCvFisheye => {
                self.distortion.get_or_insert_with(Default::default);
                let refinement = self
                    .lens_refinement
                    .get_or_insert_with(LensRefinementOptions::default);
                refinement.model = match model {
                    posediff_geometry::lens::CameraModel::Radial => LensModel::Radial,
                    posediff_geometry::lens::CameraModel::OpenCv => LensModel::Opencv,
                    posediff_geometry::lens::CameraModel::OpenCvFisheye => LensModel::OpencvFisheye,
                    _ => LensModel::SimpleRadial,
                };
            }
        }
        Ok(())
    }
}

impl Default for CameraOptions {
    fn default() -> Self {
        Self {
            mode: CameraMode::default(),
            distortion: Some(Default::default()),
            lens_refinement: Some(Default::default()),
        }
    }
}

/// Video input (`posediff estimate capture.mp4`): which decoded frames become keyframes, and
/// how the keyframes are paired.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(default, deny_unknown_fields)]
pub struct VideoOptions {
    /// Frames looked at per second of video (`--fps`); `null`: every decoded frame. Frames in
    /// between are decoded (a video decodes in order) but neither scored nor tracked.
    pub fps: Option<f64>,
    /// At most this many keyframes per video (`--max-frames`); more are thinned evenly (and
    /// run.json says the overlap bound no longer holds). `null`: no cap.
    pub max_frames: Option<usize>,
    /// The keyframe selection's thresholds.
    pub keyframes: posediff_matching::keyframes::KeyframeOptions,
    /// The pairs matched when the input is a video and `pairs.selection` is `auto`: sequential
    /// neighbours (consecutive keyframes overlap by construction) plus retrieval for loop
    /// closure. 8 neighbours span 8 × `keyframes.max_displacement` of motion at most.
    pub pairs: PairSelection,
    /// JPEG quality of the keyframes written to `out/images` (OpenCV's 0-100).
    pub jpeg_quality: u8,
}

impl Default for VideoOptions {
    fn default() -> Self {
        Self {
            fps: None,
            max_frames: None,
            keyframes: posediff_matching::keyframes::KeyframeOptions::default(),
            pairs: PairSelection::Rules(vec![PairRule::Sequential(8), PairRule::Retrieval(8)]),
            jpeg_quality: 95,
        }
    }
}

/// When the second matching pass runs.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default, Serialize, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum DensifyWhen {
    /// Where `auto` chooses it: a learned matcher with `pairs.selection = "auto"` on more than
    /// `pairs.learned_exhaustive_up_to` images.
    #[default]
    Auto,
    /// After every first map.
    Always,
    /// Never.
    Never,
}

/// The second matching pass (`geometric::densify_pairs`): after mapping the first pairs, each
/// estimated image is matched with up to `per_image` others that were not matched yet and
/// whose estimated rotations are within `max_angle_deg` of its own (nearest first; COLMAP's
/// spatial matcher on estimated poses), and the mapper runs again on all pairs. It recovers the
/// wide bridges a sparse first selection misses (apple, 20 frames, ALIKED + LightGlue:
/// `sequential:3,retrieval:3` alone 0.824 mAA(30), with this pass 0.888 on 80 pairs,
/// exhaustive 0.883 on 190; docs/BENCHMARKS.md). 45°: the same accuracy as 60° (96 pairs) and
/// 30° (68 pairs) on apple.
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
#[serde(default, deny_unknown_fields)]
pub struct DensifyOptions {
    /// When it runs.
    pub when: DensifyWhen,
    /// Largest rotation between the two estimated cameras, degrees.
    pub max_angle_deg: f64,
    /// New pairs per image at most.
    pub per_image: usize,
}

impl Default for DensifyOptions {
    fn default() -> Self {
        Self {
            when: DensifyWhen::Auto,
            max_angle_deg: 45.0,
            per_image: 5,
        }
    }
}

/// The support check of learned pairs: a pair is supported when its extractor's descriptors
/// alone verify at least `min_verified` matches (`correspondences::descriptor_support`), and
/// the mapper keeps an unsupported pair only when a triangle of kept pairs confirms it.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default, Serialize, Deserialize)]
#[serde(default, deny_unknown_fields)]
pub struct SupportOptions {
    /// `None` (the default): every pair is kept as matched. Measured on the shared sets, as
    /// many wrong pairs reach the averaging with the check as without, and small subsets lose
    /// good pairs (docs/BENCHMARKS.md); 5 is the screen's measured bound where it is used:
    /// every wrong ALIKED + LightGlue pair of apple (19) and temple (20) scores below it.
    pub min_verified: Option<usize>,
}

fn unknown_key(
    key: &str,
    known: &serde_json::Map<String, serde_json::Value>,
    from: &str,
) -> String {
    let names: Vec<&str> = known.keys().map(String::as_str).collect();
    format!(
        "unknown option `{key}` in {from}; the keys there are: {}",
        names.join(", ")
    )
}

/// Merges `patch` into `base` key by key; every key of `patch` must exist in `base`.
fn merge(
    base: &mut serde_json::Value,
    patch: serde_json::Value,
    prefix: &str,
    from: &str,
) -> std::result::Result<(), String> {
    match (base, patch) {
        (serde_json::Value::Object(b), serde_json::Value::Object(p)) => {
            for (k, v) in p {
                let key = if prefix.is_empty() {
                    k.clone()
                } else {
                    format!("{prefix}.{k}")
                };
                let Some(slot) = b.get_mut(&k) else {
                    return Err(unknown_key(&key, b, from));
                };
                // A table replaces a null (an optional stage turned on) whole.
                if slot.is_null() || !v.is_object() {
                    *slot = v;
                } else {
                    merge(slot, v, &key, from)?;
                }
            }
            Ok(())
        }
        (b, p) => {
            *b = p;
            Ok(())
        }
    }
}

impl PipelineOptions {
    /// This tree with `patch` (a JSON object with any subset of its keys, nested) applied.
    ///
    /// # Errors
    /// An unknown key or a value of the wrong type, naming the key and `from`.
    pub fn patched(&self, patch: serde_json::Value, from: &str) -> Result<Self> {
        let mut tree = serde_json::to_value(self)?;
        merge(&mut tree, patch, "", from).map_err(PosediffError::InvalidArgument)?;
        serde_json::from_value(tree)
            .map_err(|e| PosediffError::InvalidArgument(format!("{from}: {e}")))
    }

    /// This tree with the options of a TOML (`.toml`) or JSON file applied.
    ///
    /// # Errors
    /// An unreadable or malformed file, unknown keys, wrong types: each naming the file.
    pub fn with_file(&self, path: &Path) -> Result<Self> {
        let text = crate::error::read_text(path)?;
        let is_toml = path
            .extension()
            .is_some_and(|e| e.eq_ignore_ascii_case("toml"));
        let patch: serde_json::Value = if is_toml {
            toml::from_str(&text).map_err(|e| PosediffError::invalid(path, e.to_string()))?
        } else {
            serde_json::from_str(&text).map_err(|e| PosediffError::invalid(path, e.to_string()))?
        };
        if !patch.is_object() {
            return Err(PosediffError::invalid(
                path,
                "the options file must hold a table of options",
            ));
        }
        self.patched(patch, &path.display().to_string())
            .map_err(|e| match e {
                PosediffError::InvalidArgument(m) => PosediffError::invalid(path, m),
                other => other,
            })
    }

    /// This tree with one field set: `key` a dotted path (`orientation.strong_pair`), `value`
    /// JSON (`100`, `true`, `null`, `"sequential:5"`) or, when it does not parse as JSON, a
    /// string (`sequential:5`).
    ///
    /// # Errors
    /// An unknown key or a value of the wrong type, naming the key.
    pub fn with_field(&self, key: &str, value: &str) -> Result<Self> {
        let value: serde_json::Value = serde_json::from_str(value)
            .unwrap_or_else(|_| serde_json::Value::String(value.to_owned()));
        let mut patch = value;
        for part in key.rsplit('.') {
            if part.is_empty() {
                return Err(PosediffError::InvalidArgument(format!(
                    "--set {key}: an empty key part"
                )));
            }
            let mut map = serde_json::Map::new();
            map.insert(part.to_owned(), patch);
            patch = serde_json::Value::Object(map);
        }
        self.patched(patch, &format!("--set {key}"))
    }

    /// [`Self::with_field`] for `key=value`.
    ///
    /// # Errors
    /// No `=`, and as [`Self::with_field`].
    pub fn with_assignment(&self, assignment: &str) -> Result<Self> {
        let (key, value) = assignment.split_once('=').ok_or_else(|| {
            PosediffError::InvalidArgument(format!(
                "--set {assignment}: expected key.path=value (e.g. orientation.strong_pair=100)"
            ))
        })?;
        self.with_field(key.trim(), value.trim())
    }

    /// The checks that need no image: numbers in range.
    ///
    /// # Errors
    /// An option out of range, naming it.
    pub fn check(&self) -> Result<()> {
        let bad = |what: &str| Err(PosediffError::InvalidArgument(what.to_owned()));
        if self.orientation.ratio.is_nan() || self.orientation.ratio < 1.0 {
            return bad("orientation.ratio must be at least 1");
        }
        if !(self.densify.max_angle_deg.is_finite() && self.densify.max_angle_deg > 0.0) {
            return bad("densify.max_angle_deg must be a positive number of degrees");
        }
        if self.pairs.learned_first_pass == PairSelection::Auto {
            return bad("pairs.learned_first_pass must name rules, not auto");
        }
        if !(0.0..=1.0).contains(&self.two_view.homography_fraction) {
            return bad("two_view.homography_fraction must be within 0-1");
        }
        if !(self.two_view.homography_min_fraction > 0.0
            && self.two_view.homography_min_fraction <= self.two_view.homography_fraction)
        {
            return bad(
                "two_view.homography_min_fraction must be above 0 and at most two_view.homography_fraction",
            );
        }
        if !(self.two_view.cheirality_distance.is_finite()
            && self.two_view.cheirality_distance > 0.0)
        {
            return bad("two_view.cheirality_distance must be a positive number of baselines");
        }
        if let Some(fps) = self.video.fps
            && !(fps.is_finite() && fps > 0.0)
        {
            return bad("video.fps (--fps) must be a positive number of frames per second");
        }
        if self.video.max_frames.is_some_and(|n| n < 2) {
            return bad("video.max_frames (--max-frames) must be at least 2");
        }
        if self.video.pairs == PairSelection::Auto {
            return bad("video.pairs must name rules, not auto");
        }
        if self.database.images_per_commit == 0 || self.database.pairs_per_commit == 0 {
            return bad(
                "database.images_per_commit and database.pairs_per_commit must be at least 1",
            );
        }
        if self.video.jpeg_quality > 100 {
            return bad("video.jpeg_quality must be within 0-100");
        }
        self.video
            .keyframes
            .check()
            .map_err(|e| PosediffError::InvalidArgument(e.to_string()))?;
        if !(64..=8192).contains(&self.learned.image_side) {
            return bad("learned.image_side must be within 64-8192 pixels");
        }
        if self.learned.max_keypoints < 8 {
            return bad("learned.max_keypoints must be at least 8");
        }
        if !(self.points.max_reprojection_px.is_finite() && self.points.max_reprojection_px > 0.0) {
            return bad("points.max_reprojection_px must be a positive number of pixels");
        }
        if !(self.points.min_angle_deg.is_finite()
            && (0.0..90.0).contains(&self.points.min_angle_deg))
        {
            return bad("points.min_angle_deg must be within 0-90 degrees");
        }
        Ok(())
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn the_exif_35mm_equivalent_wins_then_the_focal_plane() {
        let focal = ExifFocal {
            focal_mm: Some(4.25),
            focal_35mm: Some(26.0),
            focal_plane_px_per_mm: Some(735.5),
            pixel_width: Some(4032),
        };
        let (f, how) = focal.prior(4032, 3024).unwrap_or_default();
        assert!((f - 26.0 / 35.0 * 4032.0).abs() < 1e-9);
        assert_eq!(how, "exif 35 mm equivalent");
        let plane = ExifFocal {
            focal_35mm: None,
            ..focal
        };
        // A half-size copy of the photo: the pixels per mm halve with it.
        let (f, how) = plane.prior(2016, 1512).unwrap_or_default();
        assert!((f - 4.25 * 735.5 * 0.5).abs() < 1e-9, "{f}");
        assert!(how.contains("focal plane"));
        let bare = ExifFocal {
            focal_plane_px_per_mm: None,
            ..plane
        };
        assert!(bare.prior(4032, 3024).is_none(), "mm alone is no prior");
    }

    /// Evidence decides only when one way has the screen's minimum and twice the other's.
    #[test]
    fn orientation_evidence_needs_a_clear_winner() {
        let o = OrientationOptions::default();
        let min = o.min_matches;
        assert_eq!(o.evidence(0, min), Some(true));
        assert_eq!(o.evidence(min, 0), Some(false));
        assert_eq!(o.evidence(0, min - 1), None);
        assert_eq!(o.evidence(30, 59), None);
        assert_eq!(o.evidence(30, 60), Some(true));
        assert_eq!(o.evidence(60, 30), Some(false));
        assert_eq!(o.evidence(0, 0), None);
        // The thresholds are the options' own.
        let strict = OrientationOptions {
            min_matches: 50,
            ratio: 4.0,
            ..o
        };
        assert_eq!(strict.evidence(0, 40), None);
        assert_eq!(strict.evidence(20, 79), None);
        assert_eq!(strict.evidence(20, 80), Some(true));
    }

    /// `--camera-model` in COLMAP's names, any case: the pinhole models turn the lens off, the
    /// radial ones choose the refined model; others are refused by name.
    #[test]
    fn camera_models_set_the_lens_options() {
        use posediff_sfm::lens_refinement::LensModel;
        let mut c = CameraOptions::default();
        c.set_model("RADIAL").unwrap();
        assert_eq!(c.lens_refinement.unwrap().model, LensModel::Radial);
        assert!(c.distortion.is_some());
        c.set_model("simple_pinhole").unwrap();
        assert!(c.distortion.is_none() && c.lens_refinement.is_none());
        c.set_model("opencv").unwrap();
        assert_eq!(c.lens_refinement.unwrap().model, LensModel::Opencv);
        c.set_model("simple_radial").unwrap();
        assert_eq!(c.lens_refinement.unwrap().model, LensModel::SimpleRadial);
        assert!(c.distortion.is_some());
        c.set_model("opencv_fisheye").unwrap();
        assert_eq!(c.lens_refinement.unwrap().model, LensModel::OpencvFisheye);
        let e = c.set_model("fisheye62").unwrap_err().to_string();
        assert!(
            e.contains("fisheye62") && e.contains("SIMPLE_RADIAL"),
            "{e}"
        );
    }
}
