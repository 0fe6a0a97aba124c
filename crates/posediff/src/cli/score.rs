//! `posediff score`: the official metrics against a ground truth.

use std::path::{Path, PathBuf};

use anyhow::Context;
use posediff::io::export::read_cameras_json_partial;

use super::truth_for;

/// Score cameras against a ground truth with the official test.py metrics (every pair,
/// images not estimated failed in all their pairs).
#[derive(clap::Args)]
pub struct Args {
    /// A cameras.json (images not estimated allowed).
    cameras: PathBuf,
    /// Ground-truth cameras.json (matched by image name, any order).
    #[arg(long)]
    gt: PathBuf,
    /// Also write the scores as JSON here.
    #[arg(long)]
    out: Option<PathBuf>,
}

impl Args {
    /// Runs the command.
    pub fn run(self) -> anyhow::Result<()> {
        score(&self.cameras, &self.gt, self.out.as_deref())
    }
}

fn score(cameras: &Path, gt: &Path, out: Option<&Path>) -> anyhow::Result<()> {
    let est = read_cameras_json_partial(cameras)
        .with_context(|| format!("reading {}", cameras.display()))?;
    let gt_cams = truth_for(cameras, &est, gt)?;
    let pred: Vec<_> = est
        .iter()
        .map(|e| e.camera.map(|c| c.cam_from_world))
        .collect();
    let (s, cc) = posediff::bench::score_set(&gt_cams, &pred)?;
    println!(
        "{} cameras ({} estimated): RRA@15 {:.3}  RTA@15 {:.3}  mAA(30) {:.3}  CC@0.1 {:.3}",
        est.len(),
        pred.iter().filter(|p| p.is_some()).count(),
        s.rra[1],
        s.rta[1],
        s.maa_30,
        cc
    );
    if let Some(out) = out {
        let record = ScoreRecord {
            cameras,
            gt,
            scores: &s,
            cc_10: cc,
        };
        std::fs::write(out, serde_json::to_string_pretty(&record)?)
            .with_context(|| format!("writing {}", out.display()))?;
    }
    Ok(())
}

/// The scores file `--out` writes.
#[derive(serde::Serialize)]
struct ScoreRecord<'a, S: serde::Serialize> {
    /// The cameras scored.
    cameras: &'a Path,
    /// The ground truth.
    gt: &'a Path,
    /// The official metrics.
    scores: &'a S,
    /// RelPose++'s camera-centre accuracy at 10 % of the scene scale.
    cc_10: f64,
}
