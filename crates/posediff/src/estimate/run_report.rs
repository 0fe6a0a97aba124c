//! `run.json`: one typed record of a run, whichever path estimated the cameras.

use std::path::PathBuf;

use serde::Serialize;

use crate::estimate::geometric_report::GeometricReport;
pub use posediff_pipeline::report::Warning;

/// What was written, for the summary line and run.json.
#[derive(Debug, Clone, Default, PartialEq, serde::Serialize)]
pub struct Written {
    /// Files and folders written, relative to the output folder.
    pub files: Vec<String>,
    /// Points in the model.
    pub points: usize,
    /// Their mean reprojection error, px.
    pub mean_reprojection_error_px: Option<f64>,
    /// Mean track length.
    pub mean_track_length: f64,
}

/// The version of run.json's layout; raised when a field changes meaning or goes.
pub const RUN_REPORT_SCHEMA: u32 = 3;

/// How the cameras were estimated, with what that path reports.
#[derive(Debug, Clone, Serialize)]
#[serde(tag = "method", rename_all = "snake_case")]
pub enum MethodReport {
    /// Without a checkpoint: the mapper of `posediff-sfm`.
    Geometric {
        /// `--refine`.
        refine: crate::estimate::options::RefineMode,
        /// What each stage did.
        report: Box<GeometricReport>,
    },
    /// PoseDiffusion with `--weights`.
    Posediffusion(Box<NetworkReport>),
}

/// What the network path reports.
#[derive(Debug, Clone, Serialize)]
pub struct NetworkReport {
    /// The checkpoint.
    pub weights: PathBuf,
    /// The diffusion step the initial cameras were noised to, with `--init`.
    pub start_step: Option<usize>,
    /// The sampler's seed.
    pub seed: u64,
    /// Samples drawn.
    pub samples: usize,
    /// Whether GGS ran.
    pub ggs: bool,
    /// The photos' distortion measured from GGS's matches before they were mapped into the
    /// crops (`cameras.distortion`, as the checkpoint-free path's; its `k1` per image, at the
    /// image's focal); `null` without GGS.
    pub distortion: Option<posediff_pipeline::report::DistortionOutcome>,
    /// The hybrid bundle adjustment's report (`--refine bundle`).
    pub bundle: Option<crate::estimate::geometric_report::BundleRefinement>,
    /// `cpu` or `cuda`.
    pub device: &'static str,
    /// Seconds per stage.
    pub seconds: NetworkSeconds,
    /// Per image, how far the samples spread.
    pub sample_spread: Vec<SampleSpread>,
}

/// Seconds per stage of the network path.
#[derive(Debug, Clone, Copy, Serialize)]
pub struct NetworkSeconds {
    /// Reading the checkpoint.
    pub load_weights: f64,
    /// Loading the images.
    pub load_images: f64,
    /// Features and matches for GGS.
    pub matching: f64,
    /// DINO features.
    pub features: f64,
    /// The reverse diffusion.
    pub sampling: f64,
    /// GGS inside it.
    pub ggs: f64,
}

/// How far the samples of one image spread.
#[derive(Debug, Clone, Serialize)]
pub struct SampleSpread {
    /// The image.
    pub image: String,
    /// Largest rotation between two samples, degrees.
    pub rotation_deg_max: f64,
    /// Largest distance between two samples' centres.
    pub center_distance_max: f64,
}

/// Verified matches of one pair.
#[derive(Debug, Clone, Copy, Serialize)]
pub struct PairCount {
    /// First image index.
    pub first: usize,
    /// Second image index.
    pub second: usize,
    /// Verified matches.
    pub matches: usize,
}

/// `path` as text, invalid UTF-8 replaced by U+FFFD.
fn lossy_path<S: serde::Serializer>(path: &std::path::Path, s: S) -> Result<S::Ok, S::Error> {
    s.serialize_str(&path.to_string_lossy())
}

/// An input image left out (`--skip-bad-images`).
#[derive(Debug, Clone, Serialize)]
pub struct SkippedImage {
    /// The file (a path that is not UTF-8 written lossily: JSON cannot carry it).
    #[serde(serialize_with = "lossy_path")]
    pub image: PathBuf,
    /// Why.
    pub reason: String,
}

/// The points of the exports.
#[derive(Debug, Clone, Copy, Serialize)]
pub struct PointsSummary {
    /// Tracks built from the matches.
    pub tracks: usize,
    /// Tracks dropped for seeing an image twice.
    pub inconsistent_tracks: usize,
    /// Points kept.
    pub points: usize,
    /// Their observations.
    pub observations: usize,
    /// Observations dropped beyond the threshold.
    pub dropped_observations: usize,
    /// Tracks without two estimated images.
    pub tracks_without_two_estimated_images: usize,
    /// Tracks no point fits.
    pub rejected_tracks: usize,
    /// Mean reprojection error, px.
    pub mean_reprojection_error_px: f64,
    /// The threshold, px.
    pub max_reprojection_px: f64,
    /// The smallest triangulation angle kept, degrees.
    pub min_triangulation_angle_deg: f64,
}

impl PointsSummary {
    /// From the triangulation's report and options.
    pub fn new(
        r: &posediff_sfm::points::PointsReport,
        o: &posediff_sfm::points::PointOptions,
    ) -> Self {
        Self {
            tracks: r.tracks.tracks,
            inconsistent_tracks: r.tracks.inconsistent,
            points: r.points,
            observations: r.observations,
            dropped_observations: r.dropped_observations,
            tracks_without_two_estimated_images: r.unseen,
            rejected_tracks: r.rejected,
            mean_reprojection_error_px: r.mean_error_px,
            max_reprojection_px: o.max_reprojection_px,
            min_triangulation_angle_deg: o.min_angle_deg,
        }
    }
}

/// run.json.
#[derive(Debug, Clone, Serialize)]
pub struct RunReport {
    /// [`RUN_REPORT_SCHEMA`].
    pub schema: u32,
    /// The version of posediff.
    pub posediff: &'static str,
    /// The images used, in order.
    pub images: Vec<PathBuf>,
    /// Images left out.
    pub skipped_images: Vec<SkippedImage>,
    /// `--init` as given.
    pub init: Option<String>,
    /// The matcher of the correspondences (`None` when none were needed: `--no-ggs`).
    pub matcher: Option<&'static str>,
    /// How the cameras were estimated.
    #[serde(flatten)]
    pub method: MethodReport,
    /// The options tree of the run: every threshold of the checkpoint-free path. With a
    /// checkpoint its stages make the `--init geometric` cameras; GGS's matches keep the
    /// checkpoint path's own matching settings (`posediff::EstimateConfig`, hloc's 4096
    /// keypoints), of which only the detector follows `--matcher`.
    pub options: Option<crate::estimate::options::PipelineOptions>,
    /// Verified matches per pair.
    pub matches_per_pair: Vec<PairCount>,
    /// The points of the exports (filled when they are triangulated).
    pub points: Option<PointsSummary>,
    /// Things the user should know.
    pub warnings: Vec<Warning>,
    /// `--masks`: the folder, how many images it masks, those it has no mask for.
    #[serde(skip_serializing_if = "Option::is_none")]
    pub masks: Option<MasksReport>,
    /// Video input: each video's container, codec, frames decoded and skipped by reason, and
    /// the keyframes with their frame index, timestamp, sharpness and displacement.
    #[serde(skip_serializing_if = "Option::is_none")]
    pub video: Option<crate::io::video::Capture>,
    /// The command's wall time and peak memory (filled by the CLI before writing).
    #[serde(skip_serializing_if = "Option::is_none")]
    pub resources: Option<Resources>,
    /// What was written (filled by [`crate::io::outputs::write_outputs`]).
    pub outputs: Option<Written>,
}

/// run.json's `resources`: what the run cost.
#[derive(Debug, Clone, Copy, Serialize)]
pub struct Resources {
    /// Seconds from the command's start to its results written (all but the final renames).
    pub seconds: f64,
    /// The process's peak resident memory, MiB (Linux's `VmHWM`; `None` elsewhere).
    pub peak_rss_mib: Option<f64>,
}

impl Resources {
    /// The resources of this process since `start`.
    pub fn since(start: std::time::Instant) -> Self {
        Self {
            seconds: start.elapsed().as_secs_f64(),
            peak_rss_mib: peak_rss_mib(),
        }
    }
}

/// The process's peak resident memory in MiB, from `/proc/self/status` (`VmHWM`).
pub fn peak_rss_mib() -> Option<f64> {
    let status = std::fs::read_to_string("/proc/self/status").ok()?;
    let line = status.lines().find(|l| l.starts_with("VmHWM:"))?;
    let kib: f64 = line.split_whitespace().nth(1)?.parse().ok()?;
    Some(kib / 1024.0)
}

/// run.json's `masks`.
#[derive(Debug, Clone, Serialize)]
pub struct MasksReport {
    /// The mask folder.
    #[serde(serialize_with = "lossy_path")]
    pub folder: PathBuf,
    /// Images with a mask.
    pub masked: usize,
    /// Images without one (as COLMAP: used whole).
    pub missing: Vec<String>,
}

impl RunReport {
    /// A report of this version of posediff.
    pub fn new(images: Vec<PathBuf>, method: MethodReport) -> Self {
        Self {
            schema: RUN_REPORT_SCHEMA,
            posediff: env!("CARGO_PKG_VERSION"),
            images,
            skipped_images: Vec::new(),
            init: None,
            matcher: None,
            method,
            options: None,
            matches_per_pair: Vec::new(),
            points: None,
            warnings: Vec::new(),
            masks: None,
            video: None,
            resources: None,
            outputs: None,
        }
    }
}
