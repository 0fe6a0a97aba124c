//! `posediff features` and `posediff match`: the checkpoint-free path's extraction and first
//! matching pass into COLMAP's database, resumable (images and pairs already stored are
//! skipped), as COLMAP's `feature_extractor` and matchers fill `database.db` before its mapper.

use std::path::PathBuf;

use posediff::estimate::run::{Inputs, RunOptions, Shard, StopAfter, run_stages};
use posediff::{Progress, Silent};

use super::estimate::pipeline_options;
use super::{Bars, Matcher};

/// The arguments of `posediff features` and `posediff match`.
#[derive(clap::Args)]
pub struct Args {
    /// A folder (its .png/.jpg/.jpeg files, sorted) or image files (in the order given).
    #[arg(required = true)]
    inputs: Vec<PathBuf>,
    /// COLMAP 4.2's database.db (created if absent); what it holds is not done again.
    #[arg(long, value_name = "FILE")]
    database: PathBuf,
    /// Keypoints and matches (a database keeps one matcher's features).
    #[arg(long, value_enum, default_value = "sift")]
    matcher: Matcher,
    /// Folder of the learned matcher's weights.
    #[arg(long)]
    weights_dir: Option<PathBuf>,
    /// Which pairs are matched (`posediff match`; as `posediff estimate --pairs`).
    #[arg(long)]
    pairs: Option<posediff_matching::PairSelection>,
    /// Which photos share a camera in the database (`posediff features`; the options tree's
    /// `cameras.mode`): `auto` (the default: one per EXIF camera and size, else one per image),
    /// `single` (one per image size), `per-folder` (one per folder and size) or `per-image`
    /// (COLMAP's default). Images already stored keep theirs.
    #[arg(long, value_name = "MODE")]
    camera_mode: Option<posediff_pipeline::options::CameraMode>,
    /// The pipeline's options from a TOML or JSON file (as `posediff estimate --config`).
    #[arg(long, value_name = "FILE")]
    config: Option<PathBuf>,
    /// One option of the tree, `key.path=value` (as `posediff estimate --set`).
    #[arg(long = "set", value_name = "KEY=VALUE")]
    set: Vec<String>,
    /// A folder of masks named as COLMAP's (`<image name>.png`, zero = ignore).
    #[arg(long)]
    masks: Option<PathBuf>,
    /// Go on without images that are corrupt, truncated or unreadable.
    #[arg(long)]
    skip_bad_images: bool,
    /// `posediff match`: store the pair selection and stop, matching nothing (a driver does
    /// this once; its `--shard` workers, given the database with --from, match that selection
    /// instead of each making it again).
    #[arg(long)]
    select_only: bool,
    /// Do only the K-th of N parts (`K/N`, from 0): a contiguous run of the images'
    /// extraction, or every N-th selected pair (the selection needs every image's features:
    /// give them with --from). A driver merges the parts' databases with --from.
    #[arg(long, value_name = "K/N")]
    shard: Option<String>,
    /// Databases of the same matcher and settings (workers' shards) whose features and pairs
    /// --database lacks: imported before any work, so only what none of them did is done
    /// (repeatable).
    #[arg(long = "from", value_name = "DB")]
    import_from: Vec<PathBuf>,
    /// Print nothing but errors.
    #[arg(long)]
    quiet: bool,
}

impl Args {
    /// Runs the command up to `stop`.
    pub fn run(self, stop: StopAfter) -> anyhow::Result<()> {
        let pipeline = pipeline_options(
            self.config.as_deref(),
            self.pairs.as_ref(),
            (self.camera_mode, None),
            &self.set,
        )?;
        let options = RunOptions {
            pipeline,
            matcher: self.matcher.into(),
            weights_dir: self.weights_dir.clone(),
            masks: self.masks.clone(),
            database: Some(self.database.clone()),
            shard: self.shard.as_deref().map(Shard::parse).transpose()?,
            import_from: self.import_from.clone(),
            ..RunOptions::default()
        };
        options.check()?;
        let inputs = Inputs::resolve(&self.inputs, self.skip_bad_images)?;
        let mut bars = Bars::default();
        let progress: &mut dyn Progress = if self.quiet { &mut Silent } else { &mut bars };
        let stop = match (stop, self.select_only) {
            (StopAfter::Matching, true) => StopAfter::Selection,
            (_, true) => anyhow::bail!("--select-only is a `posediff match` option"),
            (stop, false) => stop,
        };
        let summary = run_stages(&inputs, &options, stop, progress)?;
        if !self.quiet {
            if summary.imported != (0, 0) {
                println!(
                    "imported {} images' features and {} pairs from {} database(s)",
                    summary.imported.0,
                    summary.imported.1,
                    self.import_from.len()
                );
            }
            match stop {
                StopAfter::Import => {}
                StopAfter::Selection => println!(
                    "{} pairs ({}) selected, stored in {}",
                    summary.pairs,
                    summary.selection,
                    self.database.display()
                ),
                StopAfter::Features => println!(
                    "{} images with features in {}",
                    summary.images,
                    self.database.display()
                ),
                StopAfter::Matching => println!(
                    "{} pairs ({}) matched, {} verified, in {}",
                    summary.pairs,
                    summary.selection,
                    summary.verified,
                    self.database.display()
                ),
            }
        }
        Ok(())
    }
}
