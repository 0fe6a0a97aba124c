//! `posediff bench-real` and `posediff bench-co3d`: the accuracy benchmarks.

use std::path::{Path, PathBuf};

use anyhow::{Context, bail};
use candle_core::Device;
use clap::ValueEnum;
use posediff::{EstimateConfig, Estimator};

use posediff::correspondences::MatcherChoice;

use super::{Categories, Matcher, command_line};

/// What a benchmark scores.
#[derive(Clone, Copy, ValueEnum)]
pub enum BenchMethod {
    /// The ground truth itself (the ceiling check of the scoring).
    GroundTruth,
    /// Cameras without a checkpoint (two-view geometry, averaging, refinement).
    Geometric,
    /// PoseDiffusion with `--weights`.
    Posediffusion,
}

/// Score a method on the real sets of `--data` over `--subsets` (JSON + Markdown report).
#[derive(clap::Args)]
pub struct RealArgs {
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
    /// Correspondences of the geometric method.
    #[arg(long, value_enum, default_value = "sift")]
    matcher: Matcher,
    /// Folder of the learned matcher's weights (default: $POSEDIFF_WEIGHTS_DIR, else
    /// ~/.cache/posediff/weights).
    #[arg(long)]
    weights_dir: Option<PathBuf>,
    /// Only these sets of subsets.json (comma-separated; default all).
    #[arg(long, value_delimiter = ',')]
    sets: Option<Vec<String>>,
    /// Report path (JSON; the Markdown table is written beside it).
    #[arg(long)]
    out: PathBuf,
    /// The geometric method's options from a TOML or JSON file (as `posediff estimate
    /// --config`), to measure a setting against the defaults on the same sets.
    #[arg(long, value_name = "FILE")]
    config: Option<PathBuf>,
    /// One option of the geometric method's tree, `key.path=value` (as `posediff estimate
    /// --set`; repeatable).
    #[arg(long = "set", value_name = "KEY=VALUE")]
    set: Vec<String>,
}

impl RealArgs {
    /// Runs the command.
    pub fn run(self) -> anyhow::Result<()> {
        let RealArgs {
            data,
            subsets,
            weights,
            method,
            matcher,
            weights_dir,
            sets,
            out,
            config,
            set,
        } = self;
        let options = (config.is_some() || !set.is_empty())
            .then(|| super::estimate::pipeline_options(config.as_deref(), None, (None, None), &set))
            .transpose()?;
        let method = with_matcher(
            bench_method(method, weights.as_deref(), false)?,
            (matcher, options),
            weights_dir,
        )?;
        let rows =
            posediff::bench::bench_real_sets(&data, &subsets, method.as_ref(), sets.as_deref())?;
        let md = posediff::bench::real_markdown(&method.name(), &rows);
        write_report(
            &out,
            serde_json::json!({"command": command_line(), "method": method.name(), "rows": rows}),
            &md,
        )
    }
}

/// The official CO3Dv2 test protocol (JSON + Markdown report).
#[derive(clap::Args)]
pub struct Co3dArgs {
    /// CO3D root (image file paths of the annotations are relative to it).
    #[arg(long)]
    co3d_dir: PathBuf,
    /// Folder of `{category}_test.jgz`.
    #[arg(long)]
    annotation_dir: PathBuf,
    /// `seen`, `unseen` or a comma-separated list.
    #[arg(long, default_value = "seen")]
    categories: Categories,
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
    /// Correspondences of the geometric method.
    #[arg(long, value_enum, default_value = "sift")]
    matcher: Matcher,
    /// Folder of the learned matcher's weights (default: $POSEDIFF_WEIGHTS_DIR, else
    /// ~/.cache/posediff/weights).
    #[arg(long)]
    weights_dir: Option<PathBuf>,
    /// Report path (JSON; the Markdown table is written beside it).
    #[arg(long)]
    out: PathBuf,
}

impl Co3dArgs {
    /// Runs the command.
    pub fn run(self) -> anyhow::Result<()> {
        let Co3dArgs {
            co3d_dir,
            annotation_dir,
            categories,
            num_frames,
            min_frames,
            seed,
            weights,
            method,
            no_ggs,
            matcher,
            weights_dir,
            out,
        } = self;
        let list = categories.0;
        let method = with_matcher(
            bench_method(method, weights.as_deref(), no_ggs)?,
            (matcher, None),
            weights_dir,
        )?;
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
        write_report(
            &out,
            serde_json::json!({"command": command_line(), "method": method.name(), "report": report}),
            &md,
        )
    }
}

/// The geometric method with `matcher` instead of SIFT and with `options` instead of the
/// defaults (other methods, and SIFT with the defaults, unchanged).
fn with_matcher(
    method: Box<dyn posediff::bench::Method>,
    (matcher, options): (Matcher, Option<posediff_pipeline::options::PipelineOptions>),
    weights_dir: Option<PathBuf>,
) -> anyhow::Result<Box<dyn posediff::bench::Method>> {
    let choice: MatcherChoice = matcher.into();
    if choice == MatcherChoice::Sift && options.is_none() {
        return Ok(method);
    }
    if !method.name().starts_with("posediff geometric") {
        bail!("--matcher {choice}, --config and --set apply to --method geometric");
    }
    let custom = options.is_some();
    let run = posediff::estimate::run::RunOptions {
        matcher: choice,
        weights_dir,
        ..posediff::estimate::run::RunOptions::default()
    };
    let mut config = posediff::estimate::geometric::GeometricConfig {
        learned: run.load_learned()?,
        options: options.unwrap_or_default(),
        ..Default::default()
    };
    config.options.matching.features.detector = choice.detector();
    Ok(Box::new(posediff::bench::Geometric {
        config,
        label: Some(format!(
            "posediff geometric ({choice}{})",
            if custom { ", options changed" } else { "" }
        )),
    }))
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
