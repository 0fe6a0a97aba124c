//! `posediff train`: the official recipe on CO3D-layout data.

use std::path::PathBuf;

use clap::ValueEnum;

use anyhow::bail;
use posediff::train::{Split, Start, TrainData, TrainMode, Trainer, load_training_data};

use super::{Categories, DeviceArg};

/// Training settings.
#[derive(Clone, Copy, ValueEnum)]
pub enum Preset {
    /// A CPU-sized run.
    Tiny,
    /// The official `cfgs/default_train.yaml`.
    Official,
}

/// Train on CO3D-layout data (e.g. `cargo xtask synth` output): the official recipe with a
/// frozen backbone whose features are computed once.
#[derive(clap::Args)]
pub struct Args {
    /// CO3D root (image paths of the annotations are relative to it).
    #[arg(long)]
    co3d_dir: PathBuf,
    /// Folder of `{category}_{split}.jgz`.
    #[arg(long)]
    annotation_dir: PathBuf,
    /// `seen`, `unseen` or a comma-separated list of categories.
    #[arg(long)]
    categories: Categories,
    /// Checkpoint folder (model.safetensors, optimizer.safetensors, trainer.json, loss.csv,
    /// loss.png).
    #[arg(long)]
    out: PathBuf,
    /// Settings.
    #[arg(long, value_enum, default_value = "tiny")]
    config: Preset,
    /// Initial weights in the official layout (e.g. the official checkpoint to fine-tune, or
    /// ../shared/reference/tiny/model_tiny.safetensors); without it a fresh model of the
    /// preset's depths (PyTorch's default initialisation; DINO's for the ViT, so a frozen
    /// fresh backbone gives random features: fine-tune from pretrained weights instead).
    #[arg(long)]
    init: Option<PathBuf>,
    /// Keep the backbone fixed and cache its features (no augmentation; the practical mode
    /// on a CPU). Without it every batch is read, augmented as the official dataset does
    /// and the backbone is trained too.
    #[arg(long)]
    freeze_backbone: bool,
    /// Continue the run saved in --out.
    #[arg(long)]
    resume: bool,
    /// Override the iteration count of the preset.
    #[arg(long)]
    iterations: Option<u64>,
    /// Stop after this many iterations of this invocation (the schedule still spans
    /// --iterations; --resume continues).
    #[arg(long)]
    stop_after: Option<u64>,
    /// Annotation split (`{category}_{split}.jgz`).
    #[arg(long, value_enum, default_value = "train")]
    split: Split,
    /// Where the network runs.
    #[arg(long, value_enum, default_value = "cpu")]
    device: DeviceArg,
    /// No progress bar.
    #[arg(long)]
    quiet: bool,
}

impl Args {
    /// Runs the command.
    pub fn run(self) -> anyhow::Result<()> {
        let Args {
            co3d_dir,
            annotation_dir,
            categories,
            out,
            config,
            init,
            freeze_backbone,
            resume,
            iterations,
            stop_after,
            split,
            device,
            quiet,
        } = self;
        let mut cfg = match config {
            Preset::Tiny => posediff::train::TrainConfig::tiny(),
            Preset::Official => posediff::train::TrainConfig::official(),
        };
        if let Some(k) = iterations {
            cfg.iterations = k;
            cfg.period = cfg.period.min(k.max(1));
        }
        let device = device.device()?;
        let mode = if freeze_backbone {
            TrainMode::FrozenBackbone
        } else {
            TrainMode::Full
        };
        let start = if resume {
            Start::Resume
        } else {
            Start::New {
                init,
                config: cfg,
                mode,
            }
        };
        let mut trainer = Trainer::open(&out, start, &device)?;
        if trainer.state.mode != mode {
            bail!(
                "{} was trained with {}: give the same --freeze-backbone to resume it",
                out.display(),
                match trainer.state.mode {
                    TrainMode::FrozenBackbone => "a frozen backbone (--freeze-backbone)",
                    TrainMode::Full => "every parameter (no --freeze-backbone)",
                }
            );
        }
        if let (true, Some(k)) = (resume, iterations) {
            // A resumed run keeps its schedule; only its length changes.
            trainer.state.config.iterations = k;
        }
        let list = categories.0;
        let bar = if quiet {
            indicatif::ProgressBar::hidden()
        } else {
            indicatif::ProgressBar::new(0)
        };
        if let Ok(style) =
            indicatif::ProgressStyle::with_template("{msg:>12} [{bar:40}] {pos}/{len} {elapsed}")
        {
            bar.set_style(style.progress_chars("=> "));
        }
        bar.set_message("features");
        let data = load_training_data(
            &TrainData {
                co3d_dir: &co3d_dir,
                annotation_dir: &annotation_dir,
                categories: &list,
                split,
                min_frames: trainer.state.config.min_frames,
            },
            trainer.frame_input(),
            &device,
            |done, total| {
                bar.set_length(total as u64);
                bar.set_position(done as u64);
            },
        )?;
        bar.set_length(trainer.state.config.iterations);
        bar.set_position(trainer.state.iteration);
        bar.set_message("training");
        trainer.run(&data, stop_after, |row, images_per_s| {
            bar.set_position(row.iteration + 1);
            bar.set_message(format!(
                "loss {:.4} lr {:.1e} {:.0} img/s",
                row.loss, row.lr, images_per_s
            ));
        })?;
        bar.finish_and_clear();
        if !quiet {
            println!(
                "{} sequences; iteration {} of {}; checkpoint in {}",
                data.len(),
                trainer.state.iteration,
                trainer.state.config.iterations,
                out.display()
            );
        }
        Ok(())
    }
}
