//! `posediff variant`: a harder copy of a set with its ground truth transformed.

use std::path::PathBuf;

use anyhow::Context;
use posediff::io::variants::{ZoomVariant, zoom_copy};

/// Write a zoomed copy of a set (`images/` + `cameras.json`): every `--every`-th photo is a
/// centred crop resized back to full size, so its focal is the zoom times the original's; the
/// copy's cameras.json holds the transformed ground truth.
#[derive(clap::Args)]
pub struct Args {
    /// The set: a folder with `images/` and `cameras.json`.
    set: PathBuf,
    /// Zoom every N-th photo.
    #[arg(long, default_value_t = 2)]
    every: usize,
    /// Zoom factors, drawn uniformly: `LO:HI`.
    #[arg(long, default_value = "1.3:1.6")]
    zoom: String,
    /// Seed of the draw.
    #[arg(long, default_value_t = 0)]
    seed: u64,
    /// Write EXIF into every copy (make, model, focal length, rounded 35 mm equivalent of
    /// its true focal), as a phone's photos carry.
    #[arg(long)]
    exif: bool,
    /// Output folder (created).
    #[arg(long)]
    out: PathBuf,
}

impl Args {
    /// Runs the command.
    pub fn run(self) -> anyhow::Result<()> {
        let (lo, hi) = self
            .zoom
            .split_once(':')
            .and_then(|(a, b)| Some((a.parse().ok()?, b.parse().ok()?)))
            .with_context(|| format!("--zoom {}: expected LO:HI, e.g. 1.3:1.6", self.zoom))?;
        let variant = ZoomVariant {
            every: self.every,
            range: (lo, hi),
            seed: self.seed,
            exif: self.exif,
        };
        let factors = zoom_copy(&self.set, &self.out, &variant)?;
        let zoomed = factors.iter().filter(|f| **f > 1.0).count();
        println!(
            "{} photos, {zoomed} zoomed ({}), written to {}",
            factors.len(),
            factors
                .iter()
                .map(|f| format!("{f:.3}"))
                .collect::<Vec<_>>()
                .join(" "),
            self.out.display()
        );
        Ok(())
    }
}
