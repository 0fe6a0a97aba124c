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

/// A stage that iterates: how it ended.
#[derive(Debug, Clone, Default, PartialEq, serde::Serialize)]
pub struct StageOutcome {
    /// Iterations (accepted steps for refinements, rounds for averaging).
    pub iterations: usize,
    /// Stopped at a minimum / fixed point (not at the iteration limit).
    pub converged: bool,
    /// Why it stopped, where the stage says.
    pub termination: String,
}

/// An image that was not estimated, with the reason.
#[derive(Debug, Clone, PartialEq, serde::Serialize)]
pub struct NotEstimatedImage {
    /// Image index.
    pub image: usize,
    /// Why.
    pub reason: String,
}

/// What the estimate did, for run.json.
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
    /// Pairs with a relative pose (general or rotation-only).
    pub pairs_with_pose: usize,
    /// Of those, rotation-only pairs.
    pub rotation_only_pairs: usize,
    /// Pairs dropped by the rotation-consistency check.
    pub inconsistent_pairs: usize,
    /// Pairs dropped by the cycle check (every triangle of the view graph through them
    /// contradicts their relative rotation).
    pub cycle_rejected_pairs: usize,
    /// The support check of a learned matcher's pairs (`null` when not run).
    pub support: Option<SupportOutcome>,
    /// The pairs whose relative poses the averaging used (image indices).
    pub averaged_pairs: Vec<[usize; 2]>,
    /// The images estimated (the largest view-graph component).
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
    /// Rotation averaging.
    pub rotation_averaging: StageOutcome,
    /// Translation averaging.
    pub translation_averaging: StageOutcome,
    /// Refinement: accepted steps.
    pub refine_iterations: usize,
    /// Refinement converged (not stopped by the iteration limit).
    pub refine_converged: bool,
    /// Why the refinement stopped.
    pub refine_termination: String,
    /// Matches within 3 px of their epipolar geometry after refinement / used.
    pub refine_inliers: usize,
    /// Matches used by the refinement.
    pub refine_matches: usize,
    /// Each pair's matches thinned to at most this many for the refinement
    /// (`mapper.sampson.max_matches_per_pair`, the set above `thin_above_matches`); `None`:
    /// all used.
    pub refine_per_pair_cap: Option<usize>,
    /// The refinement's convergence tolerance (`mapper.sampson.tolerance`, or
    /// `large_set_tolerance` where the set is above `thin_above_matches`).
    pub refine_tolerance: f64,
    /// The refinement's step tolerance (`mapper.sampson.large_set_step_tolerance` where the
    /// set is above `thin_above_matches`, else 0: none); `refine_termination` says
    /// `small step` where it stopped the refinement.
    pub refine_step_tolerance: f64,
    /// RMS Sampson distance of those inliers, px.
    pub refine_inlier_rms_px: f64,
    /// Bridges of the view graph: pairs that no cycle confirms (0: resection not run).
    pub bridges: usize,
    /// The smaller sides of bridges moved to where the other side's tracks or plane resect
    /// them.
    pub resected_sides: Vec<ResectedSide>,
    /// Bridges the resection could not check (the solver failed): `[first, second]` and why.
    pub unchecked_bridges: Vec<([usize; 2], String)>,
    /// Tracks built from the matches (0: not run).
    pub tracks: usize,
    /// Tracks dropped because they see an image twice.
    pub inconsistent_tracks: usize,
    /// Points triangulated and adjusted by the bundle adjustment (0: not run).
    pub bundle_points: usize,
    /// Their observations.
    pub bundle_observations: usize,
    /// RMS reprojection error after the bundle adjustment, px.
    pub bundle_rms_px: f64,
    /// Conjugate-gradient iterations of the bundle adjustment's iterative reduced solver, and
    /// its solves stopped at their limit (`mapper.bundle.iterative`; 0 and 0: the sparse
    /// Cholesky solved every step).
    pub bundle_linear_iterations: [usize; 2],
    /// The keyframe adjustment (`mapper.bundle.keyframes`; absent: every camera was adjusted
    /// jointly): `keyframes` adjusted with the points (`promoted` of them for too few points
    /// or as their camera's only one), `refined_alone` others refined alone against the
    /// points, `unrefined` left where they were (fewer than
    /// `mapper.bundle.keyframes.min_inliers` points within `mapper.bundle.max_error_px`).
    pub bundle_keyframes: Option<posediff_sfm::bundle::KeyframeReport>,
    /// How the bundle adjustment ended.
    pub bundle: StageOutcome,
    /// Stage timings.
    pub times: GeometricTimes,
}

/// The support check of a learned matcher's pairs (run.json).
#[derive(Debug, Clone, Copy, Default, PartialEq, serde::Serialize)]
pub struct SupportOutcome {
    /// Pairs with matches that the extractor's descriptors support.
    pub supported: usize,
    /// Unsupported pairs confirmed by a triangle of kept pairs.
    pub confirmed: usize,
    /// Unsupported pairs dropped before the mapper used them.
    pub rejected: usize,
}

/// One side of a view-graph bridge moved by resection (run.json).
#[derive(Debug, Clone, PartialEq, serde::Serialize)]
pub struct ResectedSide {
    /// The bridge pair (image indices).
    pub bridge: [usize; 2],
    /// The camera placed by the evidence.
    pub image: usize,
    /// Cameras moved (the side).
    pub images: usize,
    /// What placed it: `tracks` (PnP) or `plane` (the bridge's homography and the plane).
    pub evidence: &'static str,
    /// The correspondences weighed: 2D–3D (tracks) or the bridge pair's matches (plane).
    pub correspondences: usize,
    /// Inliers among them with the pose before.
    pub inliers_before: usize,
    /// Inliers among them with the new pose.
    pub inliers_after: usize,
    /// The side's scale change; `null` when unobserved (kept).
    pub scale: Option<f64>,
}

impl GeometricReport {
    /// Takes the refinement's statistics.
    pub(crate) fn record_refine(&mut self, r: &SampsonRefineReport) {
        self.refine_iterations = r.iterations;
        self.refine_converged = r.converged;
        self.refine_termination = r.termination.as_str().into();
        self.refine_inliers = r.inliers;
        self.refine_matches = r.matches;
        self.refine_per_pair_cap = r.per_pair_cap;
        self.refine_tolerance = r.tolerance;
        self.refine_step_tolerance = r.step_tolerance;
        self.refine_inlier_rms_px = r.inlier_rms_px;
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

    pub(crate) fn record_mapper(&mut self, m: &MapperReport) {
        self.pairs_with_matches = m.pairs_with_matches;
        self.pairs_with_pose = m.pairs_with_pose;
        self.rotation_only_pairs = m.rotation_only_pairs;
        self.inconsistent_pairs = m.inconsistent_pairs;
        self.averaged_pairs = m.averaged_pairs.clone();
        self.cycle_rejected_pairs = m.cycle_rejected_pairs;
        self.support = m.support.as_ref().map(|s| SupportOutcome {
            supported: s.supported,
            confirmed: s.confirmed,
            rejected: s.rejected,
        });
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
        let r = &m.rotation_averaging;
        self.rotation_averaging = StageOutcome {
            iterations: r.iterations,
            converged: r.converged,
            termination: format!("median residual {:.3}°", r.median_residual_deg),
        };
        let t = &m.translation_averaging;
        self.translation_averaging = StageOutcome {
            iterations: t.iterations,
            converged: t.converged,
            termination: format!(
                "{} centres, {} edges, {} scales at the bound, {} unreachable, \
                 {} tie groups split, {} attached to a tied partner",
                t.centres,
                t.edges,
                t.scales_at_bound,
                t.unreachable,
                t.split_tie_groups,
                t.attached
            ),
        };
        if let Some(r) = &m.sampson {
            self.record_refine(r);
        }
        if let Some(r) = &m.resection {
            self.bridges = r.bridges;
            self.resected_sides = r
                .moved
                .iter()
                .map(|s| ResectedSide {
                    bridge: [s.first, s.second],
                    image: s.image,
                    images: s.images,
                    evidence: s.evidence.as_str(),
                    correspondences: s.correspondences,
                    inliers_before: s.inliers_before,
                    inliers_after: s.inliers_after,
                    scale: s.scale,
                })
                .collect();
            self.unchecked_bridges = r
                .unchecked
                .iter()
                .map(|(a, b, why)| ([*a, *b], why.clone()))
                .collect();
        }
        if let Some(t) = &m.tracks {
            self.tracks = t.tracks;
            self.inconsistent_tracks = t.inconsistent;
        }
        if let (Some(b), false) = (&m.bundle, m.bundle_undone) {
            self.bundle_points = b.points;
            self.bundle_observations = b.observations;
            self.bundle_rms_px = b.rms_px;
            self.bundle_linear_iterations = [b.linear_iterations, b.linear_unconverged];
            self.bundle_keyframes = b.keyframes;
            self.bundle = StageOutcome {
                iterations: b.iterations,
                converged: b.converged,
                termination: b.termination.as_str().into(),
            };
        } else if m.bundle_undone {
            self.bundle.termination =
                "undone: the points drove the focal out of the search range".into();
        }
        let s = &m.times;
        self.times.two_view = s.pair_geometry + s.two_view;
        self.times.averaging = s.averaging;
        self.times.initialisation =
            s.pair_geometry + s.focal + s.two_view + s.averaging + s.refinement;
        self.times.refinement = s.resection + s.bundle;
        self.times.resection = s.resection;
        self.times.camera_split = s.camera_split;
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
