//! Accuracy benchmarks with the official protocol's metrics.
//!
//! - [`bench_real`]: the sets of `../shared/data` (cameras.json layout) over the subsets of
//!   `subsets.json` (N = 3, 5, 10, all); a camera a method did not estimate fails all its pairs;
//!   per set and N, the mean over subsets.
//! - [`bench_co3d`]: CO3Dv2 annotation files, categories sorted, sequences in file order, the
//!   frames `test.py` draws (numpy's stream, seed 0 once), pairs pooled per category, the
//!   unweighted mean over categories.
//!
//! A [`Method`] turns image files into cameras (or `None` per image it could not estimate).

use std::collections::BTreeMap;
use std::path::{Path, PathBuf};
use std::time::Instant;

use posediff_geometry::{Camera, Pose};
use posediff_metrics::numpy_rng::LegacyRandomState;
use posediff_metrics::{
    CategoryPool, PoseAccuracy, camera_center_accuracy, relative_pose_errors_with_failures,
};
use serde::{Deserialize, Serialize};

use crate::error::{PosediffError, Result};
use crate::io::co3d::{load_annotations, official_frame_ids, usable_sequences};
use crate::io::export::read_cameras_json;

/// Something that estimates cameras for image files.
pub trait Method {
    /// A short name for reports.
    fn name(&self) -> String;
    /// Cameras (OpenCV, cam from world) for `images`, `None` where none was estimated.
    ///
    /// # Errors
    /// Whatever stops the method as a whole (a failure on one set is reported, not fatal, by
    /// the callers).
    fn estimate(&self, images: &[PathBuf], ground_truth: &[Pose]) -> Result<Vec<Option<Pose>>>;
}

/// The ceiling check: the ground truth scored as a prediction.
#[derive(Debug, Clone, Copy, Default)]
pub struct GroundTruth;

impl Method for GroundTruth {
    fn name(&self) -> String {
        "ground-truth".into()
    }
    fn estimate(&self, _images: &[PathBuf], ground_truth: &[Pose]) -> Result<Vec<Option<Pose>>> {
        Ok(ground_truth.iter().copied().map(Some).collect())
    }
}

/// PoseDiffusion through the pipeline.
pub struct Posediffusion {
    /// The estimator.
    pub estimator: crate::Estimator,
    /// Report name.
    pub label: String,
}

impl Method for Posediffusion {
    fn name(&self) -> String {
        self.label.clone()
    }
    fn estimate(&self, images: &[PathBuf], _ground_truth: &[Pose]) -> Result<Vec<Option<Pose>>> {
        let e = self
            .estimator
            .estimate(crate::EstimateInput::new(images), &mut crate::Silent)?;
        Ok(e.samples[0]
            .iter()
            .map(|c| Some(c.camera.cam_from_world))
            .collect())
    }
}

/// Cameras without a checkpoint ([`crate::estimate::geometric`]).
#[derive(Debug, Clone, Default)]
pub struct Geometric {
    /// Settings.
    pub config: crate::estimate::geometric::GeometricConfig,
    /// The name in reports (default: "posediff geometric (no checkpoint)").
    pub label: Option<String>,
}

impl Method for Geometric {
    fn name(&self) -> String {
        self.label
            .clone()
            .unwrap_or_else(|| "posediff geometric (no checkpoint)".into())
    }
    fn estimate(&self, images: &[PathBuf], _ground_truth: &[Pose]) -> Result<Vec<Option<Pose>>> {
        match crate::estimate::geometric::estimate_geometric(images, &self.config) {
            Ok(e) => Ok(e
                .cameras
                .iter()
                .map(|c| c.map(|c| c.cam_from_world))
                .collect()),
            // No overlap at all: every camera failed, which the scores count.
            Err(crate::PosediffError::NoMatches { .. }) => Ok(vec![None; images.len()]),
            Err(e) => Err(e),
        }
    }
}

/// Metrics of one scored set of images.
#[derive(Debug, Clone, Copy, PartialEq, Serialize)]
pub struct Scores {
    /// RRA at 5/15/30°.
    pub rra: [f64; 3],
    /// RTA at 5/15/30°.
    pub rta: [f64; 3],
    /// mAA(30) (test.py).
    pub maa_30: f64,
    /// Fraction of cameras estimated.
    pub registered: f64,
}

fn mean_scores(all: &[Scores]) -> Option<Scores> {
    if all.is_empty() {
        return None;
    }
    let n = all.len() as f64;
    let avg3 = |f: fn(&Scores) -> [f64; 3]| {
        [0, 1, 2].map(|k| all.iter().map(|s| f(s)[k]).sum::<f64>() / n)
    };
    Some(Scores {
        rra: avg3(|s| s.rra),
        rta: avg3(|s| s.rta),
        maa_30: all.iter().map(|s| s.maa_30).sum::<f64>() / n,
        registered: all.iter().map(|s| s.registered).sum::<f64>() / n,
    })
}

#[derive(Deserialize)]
struct SubsetFile {
    datasets: BTreeMap<String, SubsetSet>,
}

#[derive(Deserialize)]
struct SubsetSet {
    subsets: Vec<Subset>,
}

#[derive(Deserialize)]
struct Subset {
    id: String,
    images: Vec<String>,
}

/// One scored subset: scores, camera-centre accuracy, seconds.
type SubsetRun = (Scores, f64, f64);

/// One row of the real-data report: a set, a subset size, the mean over its subsets.
#[derive(Debug, Clone, PartialEq, Serialize)]
pub struct RealRow {
    /// Data set.
    pub set: String,
    /// Subset size label ("3", "5", "10", "all").
    pub n: String,
    /// Subsets scored.
    pub subsets: usize,
    /// Mean scores.
    pub scores: Scores,
    /// Mean camera-centre accuracy at 10 % of the scene scale.
    pub cc_10: f64,
    /// Mean seconds per subset.
    pub seconds: f64,
}

fn read_err(path: &Path, e: impl std::fmt::Display) -> PosediffError {
    PosediffError::invalid(path, e)
}

/// The official test.py scores of predicted cameras (`None`: not estimated, failed in all its
/// pairs) against the ground truth, and the RelPose++ camera-centre accuracy at 10 %.
///
/// # Errors
/// Different counts, fewer than two cameras, degenerate ground truth.
pub fn score_set(
    gt: &[Camera],
    pred: &[Option<Pose>],
) -> std::result::Result<(Scores, f64), posediff_metrics::MetricsError> {
    let gt_poses: Vec<Pose> = gt.iter().map(|c| c.cam_from_world).collect();
    let pairs = relative_pose_errors_with_failures(&gt_poses, pred)?;
    let acc = PoseAccuracy::from_pairs(&pairs)?;
    let pred_cams: Vec<Option<Camera>> = pred
        .iter()
        .zip(gt)
        .map(|(p, g)| {
            p.map(|p| Camera {
                cam_from_world: p,
                ..*g
            })
        })
        .collect();
    let cc = camera_center_accuracy(gt, &pred_cams, posediff_metrics::RELPOSE_CENTER_THRESHOLD)?;
    let registered = pred.iter().filter(|p| p.is_some()).count() as f64 / pred.len().max(1) as f64;
    Ok((
        Scores {
            rra: acc.rra,
            rta: acc.rta,
            maa_30: acc.maa_30,
            registered,
        },
        cc,
    ))
}

/// An estimate's cameras.json scored against a ground truth's, matched by file name.
#[derive(Debug, Clone, Copy, PartialEq, Serialize)]
pub struct FileScores {
    /// The official test.py scores (an image missing from the estimate, marked not estimated or
    /// with an invalid camera fails in all its pairs).
    pub scores: Scores,
    /// The RelPose++ camera-centre accuracy at 10 % of the scene scale.
    pub cc_10: f64,
    /// The median relative focal error `|fx / fx_truth - 1|` over the estimated images
    /// (`None` when none was).
    pub focal_error: Option<f64>,
}

/// Scores the cameras.json at `estimate` (ours or `pycolmap_run.py`'s; records matched to
/// the truth's by file name, so any order and any missing image is fine) against the ground
/// truth cameras.json at `truth`.
///
/// # Errors
/// Unreadable or unparsable files, a ground truth that is not a camera list, fewer than two
/// ground-truth cameras.
pub fn score_cameras_files(estimate: &Path, truth: &Path) -> Result<FileScores> {
    use posediff_geometry::camera_json::CameraRecord;
    fn records(path: &Path) -> Result<Vec<serde_json::Value>> {
        serde_json::from_str(&crate::error::read_text(path)?).map_err(|e| read_err(path, e))
    }
    fn file_name(image: &str) -> &str {
        image.rsplit('/').next().unwrap_or(image)
    }
    let gt: Vec<CameraRecord> = serde_json::from_value(serde_json::Value::Array(records(truth)?))
        .map_err(|e| read_err(truth, e))?;
    let est = records(estimate)?;
    let mut pred = Vec::with_capacity(gt.len());
    let mut focal_errors = Vec::new();
    let mut gt_cams = Vec::with_capacity(gt.len());
    for g in &gt {
        let gc = g.to_camera().map_err(|e| read_err(truth, e))?;
        let camera = est
            .iter()
            .find(|e| {
                e.get("image")
                    .and_then(|v| v.as_str())
                    .is_some_and(|n| file_name(n) == file_name(&g.image))
            })
            .filter(|e| e.get("estimated") != Some(&serde_json::Value::Bool(false)))
            .and_then(|e| serde_json::from_value::<CameraRecord>(e.clone()).ok())
            .and_then(|r| r.to_camera().ok());
        if let Some(c) = &camera {
            focal_errors.push((c.intrinsics.fx() / gc.intrinsics.fx() - 1.0).abs());
        }
        pred.push(camera.map(|c| c.cam_from_world));
        gt_cams.push(gc);
    }
    let (scores, cc_10) = score_set(&gt_cams, &pred).map_err(|e| read_err(truth, e))?;
    focal_errors.sort_by(f64::total_cmp);
    Ok(FileScores {
        scores,
        cc_10,
        focal_error: (!focal_errors.is_empty()).then(|| focal_errors[focal_errors.len() / 2]),
    })
}

/// Scores `method` on the sets of `data` over the subsets of `subsets_json`.
///
/// # Errors
/// Unreadable files; a method error on a subset counts all its cameras as failed instead.
pub fn bench_real(data: &Path, subsets_json: &Path, method: &dyn Method) -> Result<Vec<RealRow>> {
    bench_real_sets(data, subsets_json, method, None)
}

/// As [`bench_real`], on the sets named in `sets` only (all when `None`).
///
/// # Errors
/// As [`bench_real`]; a named set that subsets.json does not have.
pub fn bench_real_sets(
    data: &Path,
    subsets_json: &Path,
    method: &dyn Method,
    sets: Option<&[String]>,
) -> Result<Vec<RealRow>> {
    let text = crate::error::read_text(subsets_json)?;
    let file: SubsetFile = serde_json::from_str(&text).map_err(|e| read_err(subsets_json, e))?;
    if let Some(unknown) = sets
        .unwrap_or_default()
        .iter()
        .find(|s| !file.datasets.contains_key(s.as_str()))
    {
        return Err(read_err(subsets_json, format!("no set {unknown}")));
    }
    let mut rows = Vec::new();
    for (set, spec) in &file.datasets {
        if sets.is_some_and(|list| !list.iter().any(|s| s == set)) {
            continue;
        }
        let dir = data.join(set);
        let cams = read_cameras_json(&dir.join("cameras.json"))?;
        let by_name: BTreeMap<&str, &Camera> =
            cams.iter().map(|c| (c.image.as_str(), &c.camera)).collect();
        // Keyed by (size, label) so that 3 < 5 < 10 < all; per subset (scores, CC, seconds).
        let mut groups: BTreeMap<(usize, String), Vec<SubsetRun>> = BTreeMap::new();
        for subset in &spec.subsets {
            let gt: Vec<Camera> = subset
                .images
                .iter()
                .map(|i| {
                    by_name
                        .get(i.as_str())
                        .map(|c| **c)
                        .ok_or_else(|| read_err(subsets_json, format!("{set}: unknown image {i}")))
                })
                .collect::<Result<_>>()?;
            let paths: Vec<PathBuf> = subset.images.iter().map(|i| dir.join(i)).collect();
            let gt_poses: Vec<Pose> = gt.iter().map(|c| c.cam_from_world).collect();
            let start = Instant::now();
            let pred = method.estimate(&paths, &gt_poses).unwrap_or_else(|e| {
                log::warn!(
                    "{set} {}: {e}; its {} cameras count as failed",
                    subset.id,
                    gt.len()
                );
                vec![None; gt.len()]
            });
            let seconds = start.elapsed().as_secs_f64();
            let (scores, cc) = score_set(&gt, &pred).map_err(|e| read_err(subsets_json, e))?;
            let n = subset
                .id
                .split('_')
                .next()
                .unwrap_or("")
                .trim_start_matches('N')
                .to_owned();
            let size = n.parse::<usize>().unwrap_or(usize::MAX);
            groups
                .entry((size, n))
                .or_default()
                .push((scores, cc, seconds));
        }
        for ((_, n), runs) in groups {
            let scores: Vec<Scores> = runs.iter().map(|r| r.0).collect();
            let k = runs.len() as f64;
            if let Some(mean) = mean_scores(&scores) {
                rows.push(RealRow {
                    set: set.clone(),
                    n,
                    subsets: runs.len(),
                    scores: mean,
                    cc_10: runs.iter().map(|r| r.1).sum::<f64>() / k,
                    seconds: runs.iter().map(|r| r.2).sum::<f64>() / k,
                });
            }
        }
    }
    Ok(rows)
}

/// One sequence of the CO3D report.
#[derive(Debug, Clone, PartialEq, Serialize)]
pub struct Co3dSequenceRun {
    /// Category.
    pub category: String,
    /// Sequence name.
    pub sequence: String,
    /// The frame indices drawn (annotation order), sorted by file name.
    pub frame_ids: Vec<usize>,
    /// Seconds the method took.
    pub seconds: f64,
}

/// The CO3D report.
#[derive(Debug, Clone, PartialEq, Serialize)]
pub struct Co3dReport {
    /// Per category (sorted) its pooled scores.
    pub per_category: BTreeMap<String, PoseAccuracyRow>,
    /// Unweighted mean over categories.
    pub mean: PoseAccuracyRow,
    /// Every sequence run.
    pub sequences: Vec<Co3dSequenceRun>,
}

/// [`PoseAccuracy`] for reports.
#[derive(Debug, Clone, Copy, PartialEq, Serialize)]
pub struct PoseAccuracyRow {
    /// RRA at 5/15/30°.
    pub rra: [f64; 3],
    /// RTA at 5/15/30°.
    pub rta: [f64; 3],
    /// mAA(30).
    pub maa_30: f64,
    /// Pairs pooled.
    pub pairs: usize,
}

impl From<PoseAccuracy> for PoseAccuracyRow {
    fn from(a: PoseAccuracy) -> Self {
        Self {
            rra: a.rra,
            rta: a.rta,
            maa_30: a.maa_30,
            pairs: a.pairs,
        }
    }
}

/// The official CO3D test protocol on `categories` (sorted here), annotation files
/// `{annotation_dir}/{category}_test.jgz`, images under `co3d_dir`.
///
/// # Errors
/// Unreadable annotations; no usable sequence at all.
pub fn bench_co3d(
    co3d_dir: &Path,
    annotation_dir: &Path,
    categories: &[String],
    min_frames: usize,
    num_frames: usize,
    seed: u32,
    method: &dyn Method,
) -> Result<Co3dReport> {
    let mut categories = categories.to_vec();
    categories.sort();
    let mut rng = LegacyRandomState::new(seed);
    let mut pool = CategoryPool::new();
    let mut runs = Vec::new();
    for category in &categories {
        let path = annotation_dir.join(format!("{category}_test.jgz"));
        let sequences = load_annotations(&path)?;
        let usable = usable_sequences(&sequences, min_frames);
        let ids = official_frame_ids(&usable, num_frames, &mut rng)?;
        for (seq, ids) in usable.iter().zip(ids) {
            if ids.is_empty() {
                continue;
            }
            let frames: Vec<_> = ids.iter().map(|&i| &seq.frames[i]).collect();
            let gt: Vec<Pose> = frames.iter().map(|f| f.cam_from_world()).collect();
            let paths: Vec<PathBuf> = frames.iter().map(|f| co3d_dir.join(&f.filepath)).collect();
            let start = Instant::now();
            let pred = method
                .estimate(&paths, &gt)
                .unwrap_or_else(|_| vec![None; gt.len()]);
            let seconds = start.elapsed().as_secs_f64();
            let pairs =
                relative_pose_errors_with_failures(&gt, &pred).map_err(|e| read_err(&path, e))?;
            pool.add(category, &pairs);
            runs.push(Co3dSequenceRun {
                category: category.clone(),
                sequence: seq.name.clone(),
                frame_ids: ids,
                seconds,
            });
        }
    }
    let report = pool
        .report()
        .map_err(|e| read_err(annotation_dir, format!("no usable sequence: {e}")))?;
    Ok(Co3dReport {
        per_category: report
            .per_category
            .into_iter()
            .map(|(k, v)| (k, v.into()))
            .collect(),
        mean: report.mean.into(),
        sequences: runs,
    })
}

/// The real-data table in Markdown.
pub fn real_markdown(method: &str, rows: &[RealRow]) -> String {
    let mut md = format!(
        "Method: {method}\n\n| set | N | subsets | RRA@15 | RTA@15 | mAA(30) | reg. | CC@0.1 | s / subset |\n|---|---|---:|---:|---:|---:|---:|---:|---:|\n"
    );
    for r in rows {
        md.push_str(&format!(
            "| {} | {} | {} | {:.3} | {:.3} | {:.3} | {:.3} | {:.3} | {:.2} |\n",
            r.set,
            r.n,
            r.subsets,
            r.scores.rra[1],
            r.scores.rta[1],
            r.scores.maa_30,
            r.scores.registered,
            r.cc_10,
            r.seconds
        ));
    }
    md
}

/// The CO3D table in Markdown.
pub fn co3d_markdown(method: &str, report: &Co3dReport) -> String {
    let mut md = format!(
        "Method: {method}\n\n| category | pairs | RRA@5 | RRA@15 | RRA@30 | RTA@5 | RTA@15 | RTA@30 | mAA(30) |\n|---|---:|---:|---:|---:|---:|---:|---:|---:|\n"
    );
    let row = |name: &str, a: &PoseAccuracyRow| {
        format!(
            "| {name} | {} | {:.3} | {:.3} | {:.3} | {:.3} | {:.3} | {:.3} | {:.3} |\n",
            a.pairs, a.rra[0], a.rra[1], a.rra[2], a.rta[0], a.rta[1], a.rta[2], a.maa_30
        )
    };
    for (c, a) in &report.per_category {
        md.push_str(&row(c, a));
    }
    md.push_str(&row("**mean**", &report.mean));
    md
}
