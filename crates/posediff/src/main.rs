//! The `posediff` command: `posediff estimate <folder or images> --weights <ckpt> --out <dir>`.
// The command prints its summary table on stdout.
#![allow(clippy::print_stdout)]

use std::path::{Path, PathBuf};
use std::process::ExitCode;

use anyhow::{Context, bail};
use candle_core::Device;
use clap::{Parser, Subcommand, ValueEnum};
use posediff::export::{write_cameras_json, write_colmap_text, write_nerfstudio, write_pytorch3d};
use posediff::loader::image_files;
use posediff::{EstimateConfig, Estimator, Progress, Silent};
use posediff_matching::Detector;

#[derive(Parser)]
#[command(
    name = "posediff",
    version,
    about = "Camera poses from a handful of photos (PoseDiffusion in Rust)"
)]
struct Cli {
    #[command(subcommand)]
    command: Command,
}

#[derive(Clone, Copy, ValueEnum)]
enum Matcher {
    Sift,
    Orb,
}

/// What a benchmark scores.
#[derive(Clone, Copy, ValueEnum)]
enum BenchMethod {
    /// The ground truth itself (the ceiling check of the scoring).
    GroundTruth,
    /// Cameras without a checkpoint (two-view geometry, averaging, refinement).
    Geometric,
    /// PoseDiffusion with `--weights`.
    Posediffusion,
}

#[derive(Clone, Copy, ValueEnum)]
enum DeviceArg {
    Cpu,
    Cuda,
}

#[derive(Subcommand)]
enum Command {
    /// Estimate the cameras of a folder of images (or a list of image files).
    Estimate {
        /// A folder (its .png/.jpg/.jpeg files, sorted) or image files (in the order given).
        #[arg(required = true)]
        inputs: Vec<PathBuf>,
        /// Official PoseDiffusion checkpoint (.pth or safetensors).
        #[arg(long)]
        weights: PathBuf,
        /// Output folder (created).
        #[arg(long)]
        out: PathBuf,
        /// Seed of the sampler.
        #[arg(long, default_value_t = 0)]
        seed: u64,
        /// Samples per image set (spread reported in run.json).
        #[arg(long, default_value_t = 1)]
        samples: usize,
        /// Skip geometry-guided sampling (and matching).
        #[arg(long)]
        no_ggs: bool,
        /// Keypoint detector for GGS matches.
        #[arg(long, value_enum, default_value = "sift")]
        matcher: Matcher,
        /// Where the network runs.
        #[arg(long, value_enum, default_value = "cpu")]
        device: DeviceArg,
        /// Print nothing but errors.
        #[arg(long)]
        quiet: bool,
    },
    /// Score a method on the real sets of `--data` over `--subsets` (JSON + Markdown report).
    BenchReal {
        /// Folder of sets in the cameras.json layout.
        #[arg(long)]
        data: PathBuf,
        /// subsets.json.
        #[arg(long)]
        subsets: PathBuf,
        /// Checkpoint for PoseDiffusion.
        #[arg(long)]
        weights: Option<PathBuf>,
        /// What to score (default: posediffusion with --weights, else geometric).
        #[arg(long, value_enum)]
        method: Option<BenchMethod>,
        /// Report path (JSON; the Markdown table is written beside it).
        #[arg(long)]
        out: PathBuf,
    },
    /// The official CO3Dv2 test protocol (JSON + Markdown report).
    BenchCo3d {
        /// CO3D root (image file paths of the annotations are relative to it).
        #[arg(long)]
        co3d_dir: PathBuf,
        /// Folder of `{category}_test.jgz`.
        #[arg(long)]
        annotation_dir: PathBuf,
        /// `seen`, `unseen` or a comma-separated list.
        #[arg(long, default_value = "seen")]
        categories: String,
        /// Frames drawn per sequence.
        #[arg(long, default_value_t = 10)]
        num_frames: usize,
        /// Minimum frames of a usable sequence (official 50).
        #[arg(long, default_value_t = 50)]
        min_frames: usize,
        /// numpy seed (official 0).
        #[arg(long, default_value_t = 0)]
        seed: u32,
        /// Checkpoint for PoseDiffusion.
        #[arg(long)]
        weights: Option<PathBuf>,
        /// What to score (default: posediffusion with --weights, else geometric).
        #[arg(long, value_enum)]
        method: Option<BenchMethod>,
        /// Skip GGS.
        #[arg(long)]
        no_ggs: bool,
        /// Report path (JSON; the Markdown table is written beside it).
        #[arg(long)]
        out: PathBuf,
    },
    /// Plot cameras (frusta from above and from the side), optionally against the ground truth.
    Plot {
        /// A cameras.json.
        cameras: PathBuf,
        /// Ground-truth cameras.json (same images, same order).
        #[arg(long)]
        gt: Option<PathBuf>,
        /// Output PNG.
        #[arg(short = 'o', long = "out")]
        out: PathBuf,
    },
}

/// Progress bars on stderr (drawn only on a terminal).
#[derive(Default)]
struct Bars {
    bar: Option<indicatif::ProgressBar>,
}

impl Progress for Bars {
    fn start(&mut self, stage: &str, total: u64) {
        let bar = if total > 0 {
            let b = indicatif::ProgressBar::new(total);
            if let Ok(style) = indicatif::ProgressStyle::with_template(
                "{msg:>10} [{bar:40}] {pos}/{len} {elapsed}",
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
        self.bar = Some(bar);
    }

    fn advance(&mut self) {
        if let Some(b) = &self.bar {
            b.inc(1);
        }
    }

    fn finish(&mut self) {
        if let Some(b) = self.bar.take() {
            b.finish_and_clear();
        }
    }
}

fn main() -> ExitCode {
    // Logs go to stderr; `RUST_LOG=info` shows the stages, warnings are on by default.
    env_logger::Builder::from_env(env_logger::Env::default().default_filter_or("warn")).init();
    match run(Cli::parse()) {
        Ok(()) => ExitCode::SUCCESS,
        Err(e) => {
            eprintln!("error: {e:#}");
            ExitCode::FAILURE
        }
    }
}

fn run(cli: Cli) -> anyhow::Result<()> {
    let (inputs, weights, out, seed, samples, no_ggs, matcher, device, quiet) = match cli.command {
        Command::Estimate {
            inputs,
            weights,
            out,
            seed,
            samples,
            no_ggs,
            matcher,
            device,
            quiet,
        } => (
            inputs, weights, out, seed, samples, no_ggs, matcher, device, quiet,
        ),
        Command::Plot { cameras, gt, out } => return plot(&cameras, gt.as_deref(), &out),
        Command::BenchReal {
            data,
            subsets,
            weights,
            method,
            out,
        } => {
            let method = bench_method(method, weights.as_deref(), false)?;
            let rows = posediff::bench::bench_real(&data, &subsets, method.as_ref())?;
            let md = posediff::bench::real_markdown(&method.name(), &rows);
            return write_report(
                &out,
                serde_json::json!({"command": command_line(), "method": method.name(), "rows": rows}),
                &md,
            );
        }
        Command::BenchCo3d {
            co3d_dir,
            annotation_dir,
            categories,
            num_frames,
            min_frames,
            seed,
            weights,
            method,
            no_ggs,
            out,
        } => {
            let list: Vec<String> = match categories.as_str() {
                "seen" => posediff::co3d::SEEN_CATEGORIES
                    .iter()
                    .map(|c| c.to_string())
                    .collect(),
                "unseen" => posediff::co3d::UNSEEN_CATEGORIES
                    .iter()
                    .map(|c| c.to_string())
                    .collect(),
                other => other
                    .split(',')
                    .map(|c| c.trim().to_owned())
                    .filter(|c| !c.is_empty())
                    .collect(),
            };
            let method = bench_method(method, weights.as_deref(), no_ggs)?;
            let report = posediff::bench::bench_co3d(
                &co3d_dir,
                &annotation_dir,
                &list,
                min_frames,
                num_frames,
                seed,
                method.as_ref(),
            )?;
            let md = posediff::bench::co3d_markdown(&method.name(), &report);
            return write_report(
                &out,
                serde_json::json!({"command": command_line(), "method": method.name(), "report": report}),
                &md,
            );
        }
    };
    if samples == 0 {
        bail!("--samples must be at least 1");
    }
    let (images, root) = match inputs.as_slice() {
        [one] if one.is_dir() => (image_files(one)?, Some(one.clone())),
        files => (
            files.to_vec(),
            files
                .first()
                .and_then(|f| f.parent())
                .map(Path::to_path_buf),
        ),
    };
    let device_name = match device {
        DeviceArg::Cpu => "cpu",
        DeviceArg::Cuda => "cuda",
    };
    let device = match device {
        DeviceArg::Cpu => Device::Cpu,
        DeviceArg::Cuda => Device::new_cuda(0)
            .context("--device cuda needs a CUDA build (feature `cuda`) and a GPU")?,
    };
    let mut config = EstimateConfig {
        seed,
        samples,
        ggs: !no_ggs,
        ..EstimateConfig::default()
    };
    config.matching.features.detector = match matcher {
        Matcher::Sift => Detector::Sift,
        Matcher::Orb => Detector::Orb,
    };
    let load_start = std::time::Instant::now();
    let estimator = Estimator::load(&weights, device, config.clone())
        .with_context(|| format!("loading weights {}", weights.display()))?;
    let load_weights = load_start.elapsed().as_secs_f64();
    let mut bars = Bars::default();
    let progress: &mut dyn Progress = if quiet { &mut Silent } else { &mut bars };
    let estimate = estimator.estimate_with(&images, root.as_deref(), progress)?;
    std::fs::create_dir_all(&out).with_context(|| format!("creating {}", out.display()))?;
    let export_start = std::time::Instant::now();
    let first = &estimate.samples[0];
    write_cameras_json(&out.join("cameras.json"), first)?;
    write_colmap_text(&out, first)?;
    write_nerfstudio(&out.join("transforms.json"), first)?;
    let with_crops: Vec<_> = first
        .iter()
        .cloned()
        .zip(estimate.crops.iter().copied())
        .collect();
    write_pytorch3d(&out.join("pytorch3d.json"), &with_crops)?;
    let export = export_start.elapsed().as_secs_f64();
    let run = serde_json::json!({
        "posediff": env!("CARGO_PKG_VERSION"),
        "weights": weights,
        "images": images,
        "seed": seed,
        "samples": samples,
        "ggs": !no_ggs,
        "device": device_name,
        "seconds": {"load_weights": load_weights, "load_images": estimate.times.load, "matching": estimate.times.matching,
                    "features": estimate.times.features, "sampling": estimate.times.sampling, "ggs": estimate.times.ggs, "export": export},
        "matches_per_pair": estimate.matches_per_pair.iter().map(|(a, b, n)| serde_json::json!({"first": a, "second": b, "matches": n})).collect::<Vec<_>>(),
        "sample_spread": first.iter().zip(estimate.spread()?).map(|(c, s)| serde_json::json!({
            "image": c.image, "rotation_deg_max": s.rotation_deg_max, "center_distance_max": s.center_distance_max,
        })).collect::<Vec<_>>(),
        "warnings": estimate.warnings,
    });
    std::fs::write(out.join("run.json"), serde_json::to_string_pretty(&run)?)
        .with_context(|| format!("writing {}", out.join("run.json").display()))?;
    if !quiet {
        println!(
            "{:<32} {:>9} {:>9} {:>28}",
            "image", "fx px", "fy px", "centre (world)"
        );
        for c in first {
            let k = &c.camera.intrinsics;
            let p = c.camera.center();
            println!(
                "{:<32} {:>9.1} {:>9.1} {:>9.3} {:>9.3} {:>9.3}",
                c.image,
                k.fx(),
                k.fy(),
                p.x,
                p.y,
                p.z
            );
        }
        println!(
            "wrote cameras.json, cameras.txt/images.txt/points3D.txt, transforms.json, pytorch3d.json, run.json to {}",
            out.display()
        );
    }
    Ok(())
}

fn plot(cameras: &Path, gt: Option<&Path>, out: &Path) -> anyhow::Result<()> {
    let est = posediff::export::read_cameras_json(cameras)
        .with_context(|| format!("reading {}", cameras.display()))?;
    let truth = gt
        .map(|g| {
            posediff::export::read_cameras_json(g)
                .with_context(|| format!("reading {}", g.display()))
        })
        .transpose()?;
    if let Some(t) = truth.as_ref().filter(|t| t.len() != est.len()) {
        bail!(
            "{} has {} cameras, the ground truth {}",
            cameras.display(),
            est.len(),
            t.len()
        );
    }
    let errors = posediff::plot::plot_cameras(out, &est, truth.as_deref())?;
    for e in &errors {
        println!(
            "{:<32} {:>8.2} deg {:>8.4} centre",
            e.image, e.rotation_deg, e.center_rel
        );
    }
    println!("wrote {}", out.display());
    Ok(())
}

fn command_line() -> String {
    std::env::args().collect::<Vec<_>>().join(" ")
}

fn bench_method(
    method: Option<BenchMethod>,
    weights: Option<&Path>,
    no_ggs: bool,
) -> anyhow::Result<Box<dyn posediff::bench::Method>> {
    let method = method.unwrap_or(if weights.is_some() {
        BenchMethod::Posediffusion
    } else {
        BenchMethod::Geometric
    });
    Ok(match (method, weights) {
        (BenchMethod::GroundTruth, _) => Box::new(posediff::bench::GroundTruth),
        (BenchMethod::Geometric, _) => Box::new(posediff::bench::Geometric::default()),
        (BenchMethod::Posediffusion, None) => bail!("--method posediffusion needs --weights"),
        (BenchMethod::Posediffusion, Some(w)) => {
            let config = EstimateConfig {
                ggs: !no_ggs,
                ..EstimateConfig::default()
            };
            let estimator = Estimator::load(w, Device::Cpu, config)
                .with_context(|| format!("loading weights {}", w.display()))?;
            Box::new(posediff::bench::Posediffusion {
                estimator,
                label: format!(
                    "posediff ({}{})",
                    w.display(),
                    if no_ggs { ", no GGS" } else { "" }
                ),
            })
        }
    })
}

fn write_report(out: &Path, json: serde_json::Value, md: &str) -> anyhow::Result<()> {
    if let Some(dir) = out.parent().filter(|d| !d.as_os_str().is_empty()) {
        std::fs::create_dir_all(dir).with_context(|| format!("creating {}", dir.display()))?;
    }
    std::fs::write(out, serde_json::to_string_pretty(&json)?)
        .with_context(|| format!("writing {}", out.display()))?;
    std::fs::write(out.with_extension("md"), md)
        .with_context(|| format!("writing {}", out.with_extension("md").display()))?;
    println!("{md}");
    Ok(())
}
