//! `posediff bench-video`: the capture benchmark. A `posediff-synth` orbit with a moving
//! distractor (a figure walking around the objects; then a checkered companion that keeps its
//! place in the camera's view; then that companion nearer, covering 60–70 % of every frame),
//! rendered at 30 fps and encoded as phones do (H.264 in MP4 where the system's
//! FFmpeg has the encoder, else Motion JPEG), estimated from the video with and without its
//! masks (keyframes' cameras against the exact ones: mAA(30), RRA@5, RTA@5); and the streaming
//! cost at 1280×720: wall time, peak memory, seconds per decoded frame and per keyframe.
//! Each estimate runs as its own `posediff estimate` process, so run.json's `resources` are
//! that run's alone.

use std::path::{Path, PathBuf};
use std::process::Command;

use anyhow::{Context, bail};
use posediff::io::synthetic_video::write_video;
use posediff_geometry::ImageSize;
use posediff_geometry::camera_json::CameraRecord;
use posediff_synth::video::{Distractor, VideoSpec};
use serde::Serialize;

/// The capture benchmark (JSON + Markdown).
#[derive(clap::Args)]
pub struct Args {
    /// Output folder: videos, estimates, results.json, results.md.
    #[arg(long)]
    out: PathBuf,
    /// Length of each video, seconds.
    #[arg(long, default_value_t = 20.0)]
    seconds: f64,
    /// Skip the 1280×720 streaming run.
    #[arg(long)]
    no_streaming: bool,
}

/// One estimate from a video.
#[derive(Debug, Clone, Serialize)]
struct Row {
    video: String,
    codec: String,
    masks: bool,
    frames: usize,
    keyframes: usize,
    estimated: usize,
    maa_30: f64,
    rra_5: f64,
    rta_5: f64,
    seconds: f64,
    peak_rss_mib: Option<f64>,
    /// Decoding, scoring, tracking and writing the keyframes.
    video_seconds: f64,
    ms_per_decoded_frame: f64,
    seconds_per_keyframe: f64,
}

fn video(
    out: &Path,
    name: &str,
    (size, distractor): (ImageSize, Distractor),
    seconds: f64,
) -> anyhow::Result<(PathBuf, String)> {
    let dir = out.join(name);
    let spec = VideoSpec {
        seed: 3,
        size,
        fps: 30.0,
        seconds,
        distractor: Some(distractor),
    };
    let summary =
        write_video(&dir, &spec, false).with_context(|| format!("rendering {}", dir.display()))?;
    Ok((dir, summary.codec))
}

fn estimate(exe: &Path, dir: &Path, codec: &str, masks: bool, out: &Path) -> anyhow::Result<Row> {
    let file = std::fs::read_dir(dir)?
        .filter_map(|e| e.ok().map(|e| e.path()))
        .find(|p| p.file_stem().is_some_and(|s| s == "capture"))
        .with_context(|| format!("no capture video in {}", dir.display()))?;
    let mut cmd = Command::new(exe);
    cmd.arg("estimate")
        .arg(&file)
        .arg("--out")
        .arg(out)
        .arg("--quiet");
    if masks {
        cmd.arg("--masks").arg(dir.join("masks"));
    }
    let status = cmd.status()?;
    if !status.success() {
        bail!("posediff estimate {} failed", file.display());
    }
    let run: serde_json::Value =
        serde_json::from_str(&std::fs::read_to_string(out.join("run.json"))?)?;
    let truth: Vec<CameraRecord> =
        serde_json::from_str(&std::fs::read_to_string(dir.join("cameras.json"))?)?;
    let estimate: Vec<CameraRecord> =
        serde_json::from_str(&std::fs::read_to_string(out.join("cameras.json"))?)?;
    let keyframes = run["video"]["keyframes"]
        .as_array()
        .context("run.json has no video.keyframes")?;
    let mut gt = Vec::new();
    let mut pred = Vec::new();
    for (k, e) in keyframes.iter().zip(&estimate) {
        let frame = k["frame"].as_u64().context("keyframe without frame")? as usize;
        if k["image"].as_str() != Some(e.image.as_str()) {
            bail!("cameras.json and run.json list the keyframes differently");
        }
        gt.push(truth[frame].to_camera()?);
        pred.push(e.to_camera().ok().map(|c| c.cam_from_world));
    }
    let (scores, _) = posediff::bench::score_set(&gt, &pred)?;
    let v = &run["video"]["videos"][0];
    let video_seconds = v["seconds"].as_f64().unwrap_or(0.0);
    let frames = v["frames_decoded"].as_u64().unwrap_or(0) as usize;
    Ok(Row {
        video: dir
            .file_name()
            .map(|n| n.to_string_lossy().into_owned())
            .unwrap_or_default(),
        codec: codec.to_owned(),
        masks,
        frames,
        keyframes: keyframes.len(),
        estimated: pred.iter().flatten().count(),
        maa_30: scores.maa_30,
        rra_5: scores.rra[0],
        rta_5: scores.rta[0],
        seconds: run["resources"]["seconds"].as_f64().unwrap_or(f64::NAN),
        peak_rss_mib: run["resources"]["peak_rss_mib"].as_f64(),
        video_seconds,
        ms_per_decoded_frame: 1000.0 * video_seconds / frames.max(1) as f64,
        seconds_per_keyframe: run["resources"]["seconds"].as_f64().unwrap_or(f64::NAN)
            / keyframes.len().max(1) as f64,
    })
}

impl Args {
    /// Runs the command.
    pub fn run(self) -> anyhow::Result<()> {
        std::fs::create_dir_all(&self.out)?;
        let exe = std::env::current_exe()?;
        let mut rows = Vec::new();
        let vga = ImageSize::new(640, 480)?;
        for (name, distractor) in [
            ("orbit-640x480", Distractor::Walking),
            ("orbit-640x480-companion", Distractor::Companion),
            ("orbit-640x480-cover", Distractor::Cover),
        ] {
            let (dir, codec) = video(&self.out, name, (vga, distractor), self.seconds)?;
            for masks in [true, false] {
                let out = self.out.join(format!(
                    "estimate-{name}-{}",
                    if masks { "masks" } else { "no-masks" }
                ));
                rows.push(estimate(&exe, &dir, &codec, masks, &out)?);
            }
        }
        if !self.no_streaming {
            let (dir, codec) = video(
                &self.out,
                "orbit-1280x720",
                (ImageSize::new(1280, 720)?, Distractor::Walking),
                self.seconds,
            )?;
            let out = self.out.join("estimate-1280x720");
            rows.push(estimate(&exe, &dir, &codec, false, &out)?);
        }
        std::fs::write(
            self.out.join("results.json"),
            serde_json::to_string_pretty(&rows)?,
        )?;
        let md = markdown(&rows);
        std::fs::write(self.out.join("results.md"), &md)?;
        println!("{md}");
        Ok(())
    }
}

fn markdown(rows: &[Row]) -> String {
    let mut s = String::from(
        "| video | codec | masks | frames | keyframes | estimated | mAA(30) | RRA@5 | RTA@5 | seconds | peak RSS MiB | video s | ms / decoded frame | s / keyframe (whole run) |\n|---|---|---|---|---|---|---|---|---|---|---|---|---|---|\n",
    );
    for r in rows {
        s.push_str(&format!(
            "| {} | {} | {} | {} | {} | {} | {:.3} | {:.3} | {:.3} | {:.1} | {} | {:.1} | {:.1} | {:.2} |\n",
            r.video,
            r.codec,
            if r.masks { "yes" } else { "no" },
            r.frames,
            r.keyframes,
            r.estimated,
            r.maa_30,
            r.rra_5,
            r.rta_5,
            r.seconds,
            r.peak_rss_mib.map_or("—".into(), |m| format!("{m:.0}")),
            r.video_seconds,
            r.ms_per_decoded_frame,
            r.seconds_per_keyframe,
        ));
    }
    s
}
