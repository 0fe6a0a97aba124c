//! What the mapper did, stage by stage (the umbrella writes it into run.json).

use crate::bundle::BundleReport;
use crate::resection::ResectionReport;
use crate::rotation_averaging::RotationAveragingReport;
use crate::sampson_refine::SampsonRefineReport;
use crate::tracks::TrackReport;
use crate::translation_averaging::TranslationAveragingReport;

/// Where the focal came from.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default)]
pub enum FocalSource {
    /// Known intrinsics were given.
    #[default]
    Given,
    /// Self-calibration from pairwise fundamental matrices.
    SelfCalibration,
    /// Rotation homographies (no pair with parallax).
    Homographies,
}

impl FocalSource {
    /// The name written to run.json.
    pub fn as_str(self) -> &'static str {
        match self {
            Self::Given => "given",
            Self::SelfCalibration => "self-calibration",
            Self::Homographies => "homographies",
        }
    }
}

/// Why an image was not estimated.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum NotEstimated {
    /// No pair of the image has a relative pose with the largest group.
    OutsideLargestComponent,
    /// Its rotation is known but no direction edge connects its centre to the others.
    NoCentre,
}

impl NotEstimated {
    /// A sentence for run.json.
    pub fn as_str(self) -> &'static str {
        match self {
            Self::OutsideLargestComponent => {
                "shares no usable two-view geometry with the largest group of images"
            }
            Self::NoCentre => "its centre is not constrained by any pair with parallax",
        }
    }
}

#[cfg(feature = "serde")]
serialize_as_str!(FocalSource, NotEstimated);

/// One round of the cameras split by the bundle adjustment ([`crate::camera_split`]).
#[derive(Debug, Clone, PartialEq, Default)]
#[cfg_attr(feature = "serde", derive(serde::Serialize))]
pub struct CameraSplitRound {
    /// Per image, its focal from the adjustment with a focal per image (pixels; `null`: not
    /// estimated or too few observations).
    pub image_focal: Vec<Option<f64>>,
    /// Per image, the camera those focals give.
    pub image_camera: Vec<usize>,
    /// Whether they differ from the map's cameras (then the mapper ran again with them).
    pub mapped_again: bool,
    /// The robust cost over all matches of the map before (lower is better; the mapper's
    /// score of a focal start); `null` when no new map was made.
    pub score_before: Option<f64>,
    /// The same of the new map (`null` when none was made).
    pub score_after: Option<f64>,
    /// Images estimated before and by the new map.
    pub images_before: usize,
    /// See `images_before`.
    pub images_after: Option<usize>,
    /// Whether the new map was kept.
    pub kept: bool,
    /// The adjustment with a focal per image.
    #[cfg_attr(feature = "serde", serde(flatten))]
    pub adjustment: crate::bundle::LensAdjustment,
}

/// The cameras the view-graph calibration found ([`crate::view_graph_calibration`]).
#[derive(Debug, Clone, PartialEq, Default)]
#[cfg_attr(feature = "serde", derive(serde::Serialize))]
pub struct CameraCalibrationReport {
    /// Whether the cameras were decided from the data (otherwise given).
    pub from_data: bool,
    /// Cameras (groups) in the end.
    pub cameras: usize,
    /// Each camera's focal ratio to the first's at calibration (folded into the scales).
    pub ratio: Vec<f64>,
    /// From data: each image's own calibrated ratio to the shared focal (1 where undetermined).
    pub image_ratio: Vec<f64>,
    /// From data: whether each image's pairs determined its focal.
    pub image_determined: Vec<bool>,
    /// The shared focal factor the ratios are relative to.
    pub phi: f64,
    /// The first camera's calibrated focal factor (a start of the mapper with the cameras).
    pub start: f64,
    /// Whether the cameras were kept: the map with them explained the matches better than
    /// the map with one shared focal (otherwise one camera, and the ratios are only reported).
    pub kept: bool,
    /// Each image's focal scale before the ratios were folded in (`f_i = ratio · phi · scale`).
    pub image_scale: Vec<f64>,
}

/// One focal start of the multi-start.
#[derive(Debug, Clone, Copy, PartialEq, Default)]
#[cfg_attr(feature = "serde", derive(serde::Serialize))]
pub struct FocalStart {
    /// `φ` it started from.
    pub start: f64,
    /// `φ` it ended at.
    pub phi: f64,
    /// Whether the focal was free.
    pub free: bool,
    /// Images estimated.
    pub images: usize,
    /// Robust cost over all matches (lower wins).
    pub score: f64,
    /// Dropped because a free focal left the search range.
    pub out_of_range: bool,
}

/// The bundle adjustment's second opinion on the focal ([`crate::mapper::FocalRival`]).
#[derive(Debug, Clone, Copy, PartialEq, Default)]
#[cfg_attr(feature = "serde", derive(serde::Serialize))]
pub struct FocalRivalReport {
    /// `φ` of the lowest start cost.
    pub winner_phi: f64,
    /// `φ` of the rival.
    pub rival_phi: f64,
    /// RMS reprojection error of the winner's map after the bundle adjustment, px.
    pub winner_rms_px: f64,
    /// The same of the rival's.
    pub rival_rms_px: f64,
    /// Whether the rival's map was kept.
    pub switched: bool,
}

/// Seconds per stage, summed over the focal starts.
#[derive(Debug, Clone, Copy, PartialEq, Default)]
#[cfg_attr(feature = "serde", derive(serde::Serialize))]
pub struct StageTimes {
    /// Homography tests and least-squares fundamental matrices (per pair, once).
    pub pair_geometry: f64,
    /// Focal initialisation (self-calibration or homographies).
    pub focal: f64,
    /// Relative poses at each start.
    pub two_view: f64,
    /// Rotation and translation averaging.
    pub averaging: f64,
    /// Sampson refinement and scoring.
    pub refinement: f64,
    /// Resection of the cameras on bridges.
    pub resection: f64,
    /// Tracks and bundle adjustment of the chosen start.
    pub bundle: f64,
    /// The cameras split by the bundle adjustment: its adjustments and the maps made again
    /// (whose own stages are not in the other fields).
    pub camera_split: f64,
}

/// The support check: which unsupported pairs were confirmed by triangles of kept pairs.
#[derive(Debug, Clone, PartialEq, Default)]
#[cfg_attr(feature = "serde", derive(serde::Serialize))]
pub struct SupportReport {
    /// Pairs with matches that the caller marked supported.
    pub supported: usize,
    /// Unsupported pairs that a triangle of two kept pairs confirmed.
    pub confirmed: usize,
    /// Unsupported pairs dropped (no relative pose, or no confirming triangle).
    pub rejected: usize,
    /// Those pairs, `[first, second]` as given.
    pub rejected_pairs: Vec<[usize; 2]>,
}

/// What the mapper did.
#[derive(Debug, Clone, PartialEq, Default)]
#[cfg_attr(feature = "serde", derive(serde::Serialize))]
pub struct MapperReport {
    /// Pairs with matches.
    pub pairs_with_matches: usize,
    /// Pairs with a relative pose at the chosen start.
    pub pairs_with_pose: usize,
    /// Of those, rotation-only pairs.
    pub rotation_only_pairs: usize,
    /// Pairs dropped by the rotation-consistency check.
    pub inconsistent_pairs: usize,
    /// Pairs dropped by the cycle check before rotation averaging (every triangle through
    /// them contradicts them).
    pub cycle_rejected_pairs: usize,
    /// The support check's outcome, when the caller gave support flags
    /// ([`crate::mapper::GlobalMapper::run_with_support`]).
    pub support: Option<SupportReport>,
    /// The pairs whose relative poses the averaging used at the chosen start (after the
    /// consistency checks), both of whose cameras are estimated.
    pub averaged_pairs: Vec<[usize; 2]>,
    /// No pair has parallax: all centres coincide.
    pub no_parallax: bool,
    /// The images estimated.
    pub estimated: Vec<usize>,
    /// The others, with the reason.
    pub not_estimated: Vec<(usize, NotEstimated)>,
    /// Where the focal came from.
    pub focal_source: FocalSource,
    /// `φ` before refinement.
    pub focal_factor_initial: f64,
    /// `φ` at the end.
    pub focal_factor: f64,
    /// Whether the chosen start's focal was free (refined; otherwise fixed at its start).
    pub focal_free: bool,
    /// The cameras' view-graph calibration (`None`: one camera, or known intrinsics).
    pub cameras: Option<CameraCalibrationReport>,
    /// The cameras split by the bundle adjustment after the mapper, round by round (empty:
    /// not run).
    pub camera_split: Vec<CameraSplitRound>,
    /// Every focal start tried.
    pub starts: Vec<FocalStart>,
    /// The bundle adjustment's second opinion on the focal ([`crate::mapper::FocalRival`];
    /// `null`: off, or no rival).
    pub focal_rival: Option<FocalRivalReport>,
    /// Rotation averaging of the chosen start.
    pub rotation_averaging: RotationAveragingReport,
    /// Translation averaging of the chosen start.
    pub translation_averaging: TranslationAveragingReport,
    /// Sampson refinement of the chosen start.
    pub sampson: Option<SampsonRefineReport>,
    /// Tracks.
    pub tracks: Option<TrackReport>,
    /// Resection of the cameras on bridges.
    pub resection: Option<ResectionReport>,
    /// Bundle adjustment.
    pub bundle: Option<BundleReport>,
    /// The bundle adjustment drove a free focal out of range and was undone.
    pub bundle_undone: bool,
    /// Stage timings.
    pub times: StageTimes,
}
