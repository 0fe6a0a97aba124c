//! The `posediff` commands, one module each (the layout of cargo's `src/bin/cargo/commands/`):
//! an `Args` struct per command with `fn run(self) -> anyhow::Result<()>`, and what they share
//! (progress bars, the device argument, the ground truth matched by name).

pub mod bench;
pub mod bench_cameras;
pub mod bench_video;
pub mod device_check;
pub mod estimate;
pub mod import_colmap;
pub mod map;
pub mod plot;
pub mod score;
pub mod stages;
pub mod synth_video;
pub mod train;
pub mod variant;
pub mod view;

use std::path::Path;

use anyhow::Context;
use clap::{Subcommand, ValueEnum};
use posediff::Progress;
use posediff::correspondences::StepCounter;
use posediff::io::export::ImageCamera;

/// Every command.
#[derive(Subcommand)]
pub enum Command {
    /// Estimate the cameras of a folder of images (or a list of image files).
    Estimate(estimate::Args),
    /// Extract the features of images into COLMAP's database (`--database`), skipping the
    /// images it already holds.
    Features(stages::Args),
    /// Extract what is missing, then match the selected pairs (`--pairs`) into COLMAP's
    /// database, skipping the pairs it already holds.
    Match(stages::Args),
    /// Cameras and points from the features and verified pairs of a COLMAP database (ours or
    /// COLMAP's, pycolmap's, hloc's), as COLMAP's mappers map it: nothing is matched.
    Map(map::Args),
    /// Score a method on the real sets of `--data` over `--subsets` (JSON + Markdown report).
    BenchReal(bench::RealArgs),
    /// The real-cameras benchmark: each set and its zoomed copy, camera modes single and auto,
    /// and COLMAP 4.2's mappers side by side with `--colmap-python` (JSON + Markdown report).
    BenchCameras(bench_cameras::Args),
    /// The capture benchmark: a synthetic orbit video with a moving distractor, estimated with
    /// and without its masks against the exact cameras, and the streaming cost at 1280×720
    /// (JSON + Markdown report).
    BenchVideo(bench_video::Args),
    /// Write a synthetic capture video with exact cameras (an orbit, H.264 or Motion JPEG,
    /// optionally a moving distractor and its masks).
    SynthVideo(synth_video::Args),
    /// The official CO3Dv2 test protocol (JSON + Markdown report).
    BenchCo3d(bench::Co3dArgs),
    /// Train on CO3D-layout data (e.g. `cargo xtask synth` output): the official recipe with a
    /// frozen backbone whose features are computed once.
    Train(train::Args),
    /// Convert a COLMAP model (text or binary) to cameras.json, e.g. for
    /// `estimate --init`: with --images, one entry per image of that folder in its order
    /// (images COLMAP did not register are marked not estimated).
    ImportColmap(import_colmap::Args),
    /// Score cameras against a ground truth with the official test.py metrics (every pair,
    /// images not estimated failed in all their pairs).
    Score(score::Args),
    /// Write view.html (cameras with thumbnails, points, the aligned ground truth) for an
    /// output folder of `estimate`.
    View(view::Args),
    /// Plot cameras (frusta from above and from the side), optionally against the ground truth.
    Plot(plot::Args),
    /// Check the network on a device (`--device cuda`) against the official outputs of the
    /// parity fixtures and time it: backbone, denoiser step, sampling, training iteration.
    DeviceCheck(device_check::Args),
    /// Write a harder copy of a set with its ground truth transformed (every N-th photo
    /// zoomed: several cameras).
    Variant(variant::Args),
}

impl Command {
    /// Runs the command.
    pub fn run(self) -> anyhow::Result<()> {
        match self {
            Self::Estimate(a) => a.run(),
            Self::Map(a) => a.run(),
            Self::Features(a) => a.run(posediff::estimate::run::StopAfter::Features),
            Self::Match(a) => a.run(posediff::estimate::run::StopAfter::Matching),
            Self::BenchReal(a) => a.run(),
            Self::BenchCameras(a) => a.run(),
            Self::BenchVideo(a) => a.run(),
            Self::SynthVideo(a) => a.run(),
            Self::BenchCo3d(a) => a.run(),
            Self::Train(a) => a.run(),
            Self::ImportColmap(a) => a.run(),
            Self::Score(a) => a.run(),
            Self::View(a) => a.run(),
            Self::Plot(a) => a.run(),
            Self::DeviceCheck(a) => a.run(),
            Self::Variant(a) => a.run(),
        }
    }
}

/// A set of CO3D categories: `seen`, `unseen` (the official lists) or a comma-separated list.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct Categories(pub Vec<String>);

impl std::str::FromStr for Categories {
    type Err = String;

    fn from_str(s: &str) -> Result<Self, Self::Err> {
        let list: Vec<String> = match s {
            "seen" => posediff::io::co3d::SEEN_CATEGORIES
                .iter()
                .map(|c| (*c).to_owned())
                .collect(),
            "unseen" => posediff::io::co3d::UNSEEN_CATEGORIES
                .iter()
                .map(|c| (*c).to_owned())
                .collect(),
            other => other
                .split(',')
                .map(|c| c.trim().to_owned())
                .filter(|c| !c.is_empty())
                .collect(),
        };
        if list.is_empty() {
            return Err("no category: give `seen`, `unseen` or a comma-separated list".into());
        }
        Ok(Self(list))
    }
}

/// Where the network runs.
/// `--matcher`.
#[derive(Clone, Copy, ValueEnum)]
pub enum Matcher {
    /// OpenCV SIFT, mutual nearest neighbours with Lowe's ratio.
    Sift,
    /// OpenCV ORB (binary descriptors).
    Orb,
    /// ALIKED keypoints matched by LightGlue (released weights: `cargo xtask weights`).
    #[value(name = "aliked-lightglue")]
    AlikedLightglue,
    /// The rotation-robust ALIKED (`aliked-n16rot`) matched by the same LightGlue.
    #[value(name = "aliked-n16rot-lightglue")]
    AlikedN16rotLightglue,
    /// DISK keypoints matched by the LightGlue trained on DISK (released weights).
    #[value(name = "disk-lightglue")]
    DiskLightglue,
}

impl From<Matcher> for posediff::correspondences::MatcherChoice {
    fn from(m: Matcher) -> Self {
        match m {
            Matcher::Sift => Self::Sift,
            Matcher::Orb => Self::Orb,
            Matcher::AlikedLightglue => Self::AlikedLightGlue,
            Matcher::AlikedN16rotLightglue => Self::AlikedN16RotLightGlue,
            Matcher::DiskLightglue => Self::DiskLightGlue,
        }
    }
}

#[derive(Clone, Copy, ValueEnum)]
pub enum DeviceArg {
    Cpu,
    Cuda,
}

impl DeviceArg {
    /// The candle device.
    ///
    /// # Errors
    /// CUDA without a CUDA build or a GPU.
    pub fn device(self) -> anyhow::Result<candle_core::Device> {
        match self {
            Self::Cpu => Ok(candle_core::Device::Cpu),
            Self::Cuda if cfg!(feature = "cuda") => candle_core::Device::new_cuda(0).context(
                "--device cuda: no usable NVIDIA GPU (is the driver's libcuda.so.1 the real \
                 one, and does nvidia-smi see a GPU?)",
            ),
            Self::Cuda => candle_core::Device::new_cuda(0).context(
                "--device cuda needs a CUDA build (`cargo xtask cuda-build`, feature `cuda`) \
                 and a GPU",
            ),
        }
    }

    /// Its name in run.json.
    pub fn name(self) -> &'static str {
        match self {
            Self::Cpu => "cpu",
            Self::Cuda => "cuda",
        }
    }
}

/// Progress bars on stderr (drawn only on a terminal). Steps may finish on any thread
/// ([`StepCounter`]): the bar sits behind a lock.
#[derive(Default)]
pub struct Bars {
    bar: std::sync::Mutex<Option<indicatif::ProgressBar>>,
}

impl Bars {
    fn bar(stage: &str, total: u64) -> indicatif::ProgressBar {
        let bar = if total > 0 {
            let b = indicatif::ProgressBar::new(total);
            if let Ok(style) = indicatif::ProgressStyle::with_template(
                "{msg:>11} [{bar:40}] {pos}/{len} {elapsed}",
            ) {
                b.set_style(style.progress_chars("=> "));
            }
            b
        } else {
            let b = indicatif::ProgressBar::new_spinner();
            b.enable_steady_tick(std::time::Duration::from_millis(120));
            b
        };
        bar.set_message(stage.to_owned());
        bar
    }

    /// Replaces the current bar (cleared) by `next`.
    fn replace(&self, next: Option<indicatif::ProgressBar>) {
        if let Ok(mut current) = self.bar.lock() {
            if let Some(b) = current.take() {
                b.finish_and_clear();
            }
            *current = next;
        }
    }
}

impl StepCounter for Bars {
    fn stage(&self, name: &str, total: u64) {
        self.replace(Some(Self::bar(name, total)));
    }

    fn step(&self) {
        if let Ok(current) = self.bar.lock()
            && let Some(b) = current.as_ref()
        {
            b.inc(1);
        }
    }
}

impl Progress for Bars {
    fn start(&mut self, stage: &str, total: u64) {
        StepCounter::stage(self, stage, total);
    }

    fn advance(&mut self) {
        self.step();
    }

    fn finish(&mut self) {
        self.replace(None);
    }

    fn counter(&self) -> &dyn StepCounter {
        self
    }
}

/// The ground truth's cameras for the entries of `cameras`, matched by name: every entry
/// must have one and every ground-truth camera an entry.
fn truth_for(
    cameras: &Path,
    est: &[ImageCamera],
    gt: &Path,
) -> anyhow::Result<Vec<posediff_geometry::Camera>> {
    let names: Vec<String> = est.iter().map(|e| e.image.clone()).collect();
    Ok(posediff::io::records::ground_truth_for(
        &names,
        gt,
        &cameras.display().to_string(),
    )?)
}

/// The command line, for reports.
pub fn command_line() -> String {
    std::env::args().collect::<Vec<_>>().join(" ")
}
