//! `posediff synth-video`: a synthetic capture video with exact cameras
//! ([`posediff::io::synthetic_video`]).

use std::path::PathBuf;

use anyhow::Context;
use posediff::io::synthetic_video::write_video;
use posediff_synth::parse_size;
use posediff_synth::video::{Distractor, VideoSpec};

/// The arguments of `posediff synth-video`.
#[derive(clap::Args)]
pub struct Args {
    /// Output folder: capture.mp4 (or .avi), cameras.json, masks/, video.json.
    #[arg(long)]
    out: PathBuf,
    /// Frame size `WxH`.
    #[arg(long, default_value = "640x480")]
    size: String,
    /// Frames per second.
    #[arg(long, default_value_t = 30.0)]
    fps: f64,
    /// Length, seconds.
    #[arg(long, default_value_t = 20.0)]
    seconds: f64,
    /// Scene and camera path seed.
    #[arg(long, default_value_t = 3)]
    seed: u64,
    /// A distractor and its masks in out/masks: `walking` (a textured figure walking around
    /// the objects; the default of a bare `--distractor`) or `companion` (one that keeps its
    /// place in the camera's view, as a person walking beside the camera) or `cover` (the
    /// companion nearer and in the middle, about half of every frame).
    #[arg(long, value_enum, num_args = 0..=1, default_missing_value = "walking")]
    distractor: Option<DistractorArg>,
    /// Motion JPEG (AVI) even where H.264 can be encoded.
    #[arg(long)]
    mjpeg: bool,
}

/// `--distractor`'s values.
#[derive(Debug, Clone, Copy, clap::ValueEnum)]
enum DistractorArg {
    Walking,
    Companion,
    Cover,
}

impl Args {
    /// Runs the command.
    pub fn run(self) -> anyhow::Result<()> {
        let spec = VideoSpec {
            seed: self.seed,
            size: parse_size(&self.size)?,
            fps: self.fps,
            seconds: self.seconds,
            distractor: self.distractor.map(|d| match d {
                DistractorArg::Walking => Distractor::Walking,
                DistractorArg::Companion => Distractor::Companion,
                DistractorArg::Cover => Distractor::Cover,
            }),
        };
        let start = std::time::Instant::now();
        let summary = write_video(&self.out, &spec, self.mjpeg)
            .with_context(|| format!("writing {}", self.out.display()))?;
        println!(
            "{} frames ({}) in {:.1} s: {}",
            summary.frames,
            summary.codec,
            start.elapsed().as_secs_f64(),
            summary.video.display()
        );
        Ok(())
    }
}
