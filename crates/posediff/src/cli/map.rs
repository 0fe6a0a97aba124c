//! `posediff map`: cameras and points from the features and verified matches a COLMAP
//! database holds (ours from `posediff features` / `posediff match`, or COLMAP's, pycolmap's,
//! hloc's), as COLMAP's and GLOMAP's mappers map `database.db`: nothing is extracted or
//! matched.

use std::path::PathBuf;
use std::time::Instant;

use posediff::estimate::run::{Inputs, RunOptions, run};
use posediff::estimate::run_report::Resources;
use posediff::io::outputs::{OutputOptions, prepare_output_dir, thumbnail_side};
use posediff::{Progress, Silent};

use super::Bars;
use super::estimate::pipeline_options;

/// The arguments of `posediff map`.
#[derive(clap::Args)]
pub struct Args {
    /// COLMAP's database.db (read only).
    #[arg(long, value_name = "FILE")]
    database: PathBuf,
    /// The folder the database's image names are relative to (colours, out/images).
    #[arg(long)]
    images: PathBuf,
    /// Output folder (created).
    #[arg(long)]
    out: PathBuf,
    /// Which photos share a camera (as `posediff estimate --camera-mode`).
    #[arg(long, value_name = "MODE")]
    camera_mode: Option<posediff_pipeline::options::CameraMode>,
    /// The lens model (as `posediff estimate --camera-model`).
    #[arg(long, value_name = "MODEL")]
    camera_model: Option<String>,
    /// The pipeline's options from a TOML or JSON file (as `posediff estimate --config`).
    #[arg(long, value_name = "FILE")]
    config: Option<PathBuf>,
    /// One option of the tree, `key.path=value` (as `posediff estimate --set`).
    #[arg(long = "set", value_name = "KEY=VALUE")]
    set: Vec<String>,
    /// Do not write view.html.
    #[arg(long)]
    no_view: bool,
    /// Print nothing but errors.
    #[arg(long)]
    quiet: bool,
}

impl Args {
    /// Runs the command.
    pub fn run(self) -> anyhow::Result<()> {
        let start = Instant::now();
        let pipeline = pipeline_options(
            self.config.as_deref(),
            None,
            (self.camera_mode, self.camera_model.as_deref()),
            &self.set,
        )?;
        let inputs = Inputs::resolve(std::slice::from_ref(&self.images), false)?;
        let options = RunOptions {
            pipeline,
            database: Some(self.database.clone()),
            map_database: true,
            thumbnail_side: (!self.no_view).then(|| thumbnail_side(inputs.names.len())),
            ..RunOptions::default()
        };
        options.check()?;
        if !self.database.is_file() {
            anyhow::bail!("--database {}: no such file", self.database.display());
        }
        let output_options = OutputOptions {
            view: !self.no_view,
            ..OutputOptions::default()
        };
        prepare_output_dir(&self.out, &inputs.images, output_options.images)?;
        let mut bars = Bars::default();
        let progress: &mut dyn Progress = if self.quiet { &mut Silent } else { &mut bars };
        let mut result = run(&inputs, &options, None, progress)?;
        result.report.resources = Some(Resources::since(start));
        let written = result.write(&self.out, &output_options)?;
        if !self.quiet {
            println!(
                "{} of {} images estimated, {} points; wrote {} to {}",
                result
                    .reconstruction
                    .images
                    .iter()
                    .filter(|e| e.camera.camera.is_some())
                    .count(),
                result.reconstruction.images.len(),
                written.points,
                written.files.join(", "),
                self.out.display()
            );
        }
        Ok(())
    }
}
