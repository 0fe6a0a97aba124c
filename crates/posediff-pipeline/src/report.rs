//! What the checkpoint-free path reports: run.json's `method` for it.

use posediff_sfm::MapperReport;
use posediff_sfm::sampson_refine::SampsonRefineReport;
use serde::Serialize;

/// Wall-clock seconds per stage.
#[derive(Debug, Clone, Copy, Default, PartialEq, serde::Serialize)]
pub struct GeometricTimes {
    /// Feature extraction.
    pub extraction: f64,
    /// Pair selection (retrieval when used).
    pub pair_selection: f64,
    /// Matching and verification of the selected pairs.
    pub matching_pairs: f64,
    /// Extraction, selection and matching together.
    pub matching: f64,
    /// The lens distortion calibration and the undistortion of the keypoints.
    pub distortion: f64,
    /// Homography tests, least-squares F and relative poses (all focal starts).
    pub two_view: f64,
    /// Rotation and translation averaging (all starts).
    pub averaging: f64,
    /// Every focal start: two-view geometry, averaging and the Sampson refinement.
    pub initialisation: f64,
    /// Tracks, bridge resection and bundle adjustment of the chosen start (or the official GGS
    /// schedule).
    pub refinement: f64,
    /// Of that, the resection of the cameras on view-graph bridges.
    pub resection: f64,
    /// The cameras split by the bundle adjustment (cameras from the data): its adjustments
    /// and the maps made again with the split cameras.
    pub camera_split: f64,
}

impl GeometricTimes {
    /// Adds the mapping stages of an earlier run (the first pass before [`Densify`](crate::geometric::Densify)).
    pub(crate) fn add_mapping(&mut self, earlier: &Self) {
        self.two_view += earlier.two_view;
        self.averaging += earlier.averaging;
        self.initialisation += earlier.initialisation;
        self.refinement += earlier.refinement;
        self.resection += earlier.resection;
        self.camera_split += earlier.camera_split;
    }
}

/// An image not estimated (run.json).
#[derive(Debug, Clone, PartialEq, serde::Serialize)]
pub struct NotEstimatedImage {
    /// Image index.
    pub image: usize,
    /// Why.
    pub reason: String,
}

/// What the estimate did, for run.json: the pipeline's own record (pairs, turned images,
/// cameras, times) and the outcome, with the mapper's report as the mapper wrote it.
#[derive(Debug, Clone, Default, PartialEq, serde::Serialize)]
pub struct GeometricReport {
    /// The pair selection used (e.g. `exhaustive`, `sequential:10,retrieval:20`).
    pub pair_selection: String,
    /// Pairs matched (both passes).
    pub pairs_matched: usize,
    /// Of those, pairs of the second pass ([`Densify`](crate::geometric::Densify)).
    pub pairs_densified: usize,
    /// Images a learned matcher matched turned by 180°: the groups the orientation check found
    /// turned against the largest (before the map), and the images the map left out that matched
    /// the estimated ones better turned (the retry, [`TURN_PARTNERS`](crate::geometric::TURN_PARTNERS)). Their features are the
    /// turned image's; keypoints and cameras are in the image as given.
    pub turned_images: Vec<usize>,
    /// Pairs with verified matches.
    pub pairs_with_matches: usize,
    /// The images estimated.
    pub estimated: Vec<usize>,
    /// The others and why.
    pub not_estimated: Vec<NotEstimatedImage>,
    /// Where the focal came from.
    pub focal_source: FocalOrigin,
    /// `φ = f / max(W, H)` before refinement.
    pub focal_factor_initial: f64,
    /// `φ` after refinement.
    pub focal_factor: f64,
    /// The cameras: which images share one, each one's focal, and how that was decided.
    pub cameras: CamerasOutcome,
    /// The mapper's report of the map kept, stage by stage, as `posediff_sfm` writes it
    /// ([`MapperReport`]: pairs with a pose and those the checks dropped, the averaging,
    /// the Sampson refinement, tracks, bridge resection, the bundle adjustment, every focal
    /// start); `null` when given cameras were refined without the mapper (`--init`).
    pub mapper: Option<MapperReport>,
    /// The Sampson refinement of given cameras (`--init` with `--refine converge`); `null`
    /// otherwise (the mapper's own is in `mapper.sampson`).
    pub given_refinement: Option<SampsonRefineReport>,
    /// Stage timings.
    pub times: GeometricTimes,
}

impl GeometricReport {
    /// The Sampson refinement that ran: the mapper's, or that of the given cameras.
    pub fn sampson(&self) -> Option<&SampsonRefineReport> {
        self.mapper
            .as_ref()
            .and_then(|m| m.sampson.as_ref())
            .or(self.given_refinement.as_ref())
    }

    /// The mapper's bundle adjustment, where it ran and was kept.
    pub fn bundle(&self) -> Option<&posediff_sfm::bundle::BundleReport> {
        self.mapper
            .as_ref()
            .filter(|m| !m.bundle_undone)
            .and_then(|m| m.bundle.as_ref())
    }

    /// Takes the mapper's report.
    pub(crate) fn record_cameras(
        &mut self,
        mode: crate::options::CameraMode,
        decided_by: &str,
        image_prior: &[Option<String>],
        intrinsics: &posediff_sfm::ImageIntrinsics,
        phi: f64,
        (calibration, split): (
            Option<&posediff_sfm::report::CameraCalibrationReport>,
            &[posediff_sfm::report::CameraSplitRound],
        ),
    ) {
        let count = intrinsics.groups();
        let mut focal_px = vec![0.0; count];
        let mut prior = vec![None; count];
        for (i, &g) in intrinsics.group.iter().enumerate().rev() {
            focal_px[g] = intrinsics.focal(phi, i);
            prior[g] = image_prior.get(i).cloned().flatten();
        }
        // The calibration's shared φ was the first start; per image: ratio · φ_initial · s_i
        // with s_i before folding (the longer side).
        let image_focal_calibrated = calibration
            .filter(|c| c.from_data)
            .map(|c| {
                c.image_ratio
                    .iter()
                    .zip(&c.image_determined)
                    .enumerate()
                    .map(|(i, (r, d))| {
                        d.then(|| r * c.phi * c.image_scale.get(i).copied().unwrap_or(f64::NAN))
                    })
                    .collect()
            })
            .unwrap_or_default();
        self.cameras = CamerasOutcome {
            mode: mode.as_str().into(),
            decided_by: decided_by.into(),
            prior: prior
                .into_iter()
                .map(|p| p.unwrap_or_else(|| "none (self-calibrated)".into()))
                .collect(),
            count,
            image_camera: intrinsics.group.clone(),
            focal_px,
            image_focal_calibrated,
            distortion: DistortionOutcome::default(),
            split: split.to_vec(),
        };
    }

    /// Takes the mapper's report: the outcome and the report itself.
    pub(crate) fn record_mapper(&mut self, m: &MapperReport) {
        self.pairs_with_matches = m.pairs_with_matches;
        self.estimated = m.estimated.clone();
        self.not_estimated = m
            .not_estimated
            .iter()
            .map(|(image, reason)| NotEstimatedImage {
                image: *image,
                reason: reason.as_str().into(),
            })
            .collect();
        self.focal_source = m.focal_source.into();
        self.focal_factor_initial = m.focal_factor_initial;
        self.focal_factor = m.focal_factor;
        let s = &m.times;
        self.times.two_view = s.pair_geometry + s.two_view;
        self.times.averaging = s.averaging;
        self.times.initialisation =
            s.pair_geometry + s.focal + s.two_view + s.averaging + s.refinement;
        self.times.refinement = s.resection + s.bundle;
        self.times.resection = s.resection;
        self.times.camera_split = s.camera_split;
        self.mapper = Some(m.clone());
    }
}

/// The cameras of an estimate (run.json's `cameras`).
#[derive(Debug, Clone, PartialEq, Default, Serialize)]
pub struct CamerasOutcome {
    /// The camera mode asked for (`cameras.mode`).
    pub mode: String,
    /// How the cameras were decided: `given` (known intrinsics), `single`, `per-folder`,
    /// `per-image`, `exif` (auto with EXIF) or `from the data` (auto without).
    pub decided_by: String,
    /// Each camera's focal prior: `given`, how its EXIF gave one (`exif 35 mm equivalent`, …),
    /// or `none (self-calibrated)`.
    pub prior: Vec<String>,
    /// Number of cameras.
    pub count: usize,
    /// Each image's camera (index into `focal_px`).
    pub image_camera: Vec<usize>,
    /// Each camera's focal in pixels, at its first image's size (estimated cameras only have
    /// meaning; images not estimated keep their camera's value).
    pub focal_px: Vec<f64>,
    /// Auto: each image's own focal from the view-graph calibration before grouping, pixels
    /// (`null` where its pairs did not determine it: it joined the main camera).
    pub image_focal_calibrated: Vec<Option<f64>>,
    /// The lens distortion calibrated before the mapper (`cameras.distortion`).
    pub distortion: DistortionOutcome,
    /// From the data: the cameras split by a focal per image in the bundle adjustment after
    /// the mapper, round by round (`mapper.camera_split`; empty: not run).
    pub split: Vec<posediff_sfm::report::CameraSplitRound>,
}

/// run.json's `cameras.distortion`.
#[derive(Debug, Clone, PartialEq, Default, Serialize)]
pub struct DistortionOutcome {
    /// Whether the calibration ran (off: `cameras.distortion = null` or given intrinsics).
    pub calibrated: bool,
    /// Whether it measured a distortion (else the cameras are pinhole: none the pairs show).
    pub measured: bool,
    /// Pairs it used.
    pub pairs: usize,
    /// Robust cost of those pairs' fundamental-matrix fits without distortion (pixels²).
    pub cost_pinhole: f64,
    /// The same with the best distortion found, kept or not (kept when it lowers the cost by
    /// `cameras.distortion.min_improvement`).
    pub cost: f64,
    /// Per camera, COLMAP's SIMPLE_RADIAL `k` at its estimated focal (`null`: none of its
    /// images estimated); empty when none measured.
    pub k1: Vec<Option<f64>>,
    /// Per camera, RADIAL's or OPENCV's `k₂` at its estimated focal; empty unless the lens is
    /// one of them (`cameras.lens_refinement.model = "radial"` or `"opencv"`).
    pub k2: Vec<Option<f64>>,
    /// Per camera, OPENCV's tangential `p₁` at its estimated focal; empty unless the lens is
    /// OPENCV.
    pub p1: Vec<Option<f64>>,
    /// See `p1`.
    pub p2: Vec<Option<f64>>,
    /// Per camera, OPENCV_FISHEYE's `k₃` (its `k₁, k₂` are `k1`, `k2`: coefficients of the
    /// angle `θ`, not of `r`); empty unless the lens is OPENCV_FISHEYE.
    pub k3: Vec<Option<f64>>,
    /// See `k3`.
    pub k4: Vec<Option<f64>>,
    /// The lens refined by the bundle adjustment after the mapper (`cameras.lens_refinement`);
    /// `null` when it did not run (off, given intrinsics, no points).
    pub refinement: Option<LensRefinementOutcome>,
}

/// run.json's `cameras.distortion.refinement`.
#[derive(Debug, Clone, PartialEq, Default, Serialize)]
pub struct LensRefinementOutcome {
    /// Whether the refined lens was kept (and the matches mapped again with it).
    pub kept: bool,
    /// Why it was not kept (`null` when kept).
    pub reason: Option<String>,
    /// The adjustment (points and observations, the robust cost and the RMS error in the
    /// photos' pixels before and after, its steps and why it stopped), its fields inline.
    #[serde(flatten)]
    pub adjustment: posediff_sfm::bundle::LensAdjustment,
    /// Per camera, the refined `[k₁, k₂, p₁, p₂]` at the focal of that adjustment, kept or not
    /// (the coefficients the model lacks 0).
    pub k: Vec<posediff_sfm::bundle::LensCoefficients>,
}

impl DistortionOutcome {
    /// Not calibrated.
    pub fn off() -> Self {
        Self::default()
    }
}

/// Where the focal of a geometric estimate came from (run.json's `focal_source`).
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default, serde::Serialize)]
#[serde(rename_all = "kebab-case")]
pub enum FocalOrigin {
    /// Known intrinsics were given.
    #[default]
    Given,
    /// Self-calibration from pairwise fundamental matrices.
    SelfCalibration,
    /// Rotation homographies (no pair with parallax).
    Homographies,
    /// The mean focal of the initial cameras (`--init cameras.json`).
    #[serde(rename = "initial cameras")]
    InitialCameras,
}

impl From<posediff_sfm::report::FocalSource> for FocalOrigin {
    fn from(s: posediff_sfm::report::FocalSource) -> Self {
        use posediff_sfm::report::FocalSource;
        match s {
            FocalSource::Given => Self::Given,
            FocalSource::SelfCalibration => Self::SelfCalibration,
            FocalSource::Homographies => Self::Homographies,
        }
    }
}

pub use posediff_sfm::bundle_refine::BundleRefinement;

/// Something a run did that the user should know of (written to run.json and the log as its
/// message).
#[derive(Debug, Clone, PartialEq, Eq)]
#[non_exhaustive]
pub enum Warning {
    /// No pair has parallax: every camera centre is the same.
    NoParallax,
    /// Images outside the largest group of images that share matches.
    NotEstimated {
        /// How many.
        count: usize,
        /// Of how many images.
        of: usize,
    },
    /// GGS did not run: no pair has verified matches.
    GgsSkipped,
    /// No verified matches at all (matching off or none found): no points.
    NoVerifiedMatches,
    /// An `--init` file and the images do not pair up completely (the mismatch, listed).
    InitMismatch(String),
    /// Images the initial estimate has no camera for (the diffusion starts them at the first
    /// estimated camera).
    NoInitialCamera(Vec<String>),
}

impl std::fmt::Display for Warning {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        match self {
            Self::NoParallax => f.write_str(
                "no pair has measurable parallax (pure rotation or identical images): all camera \
                 centres coincide",
            ),
            Self::NotEstimated { count, of } => write!(
                f,
                "{count} of {of} images share no usable matches with the largest group and are \
                 not estimated"
            ),
            Self::GgsSkipped => f.write_str("GGS skipped: no image pair has verified matches"),
            Self::NoVerifiedMatches => f.write_str(
                "no verified matches (none were found, or GGS was off, which skips matching): the \
                 COLMAP model has no points",
            ),
            Self::InitMismatch(m) => write!(
                f,
                "{m} (images without an initial camera start uninitialised)"
            ),
            Self::NoInitialCamera(images) => write!(
                f,
                "no initial camera for {}: the diffusion starts them at the first estimated camera",
                images.join(", ")
            ),
        }
    }
}

impl Serialize for Warning {
    fn serialize<S: serde::Serializer>(&self, s: S) -> std::result::Result<S::Ok, S::Error> {
        s.collect_str(self)
    }
}
