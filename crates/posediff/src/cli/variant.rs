//! `posediff variant`: a harder copy of a set with its ground truth transformed.

use std::path::PathBuf;

use anyhow::Context;
use posediff::io::variants::{RadialVariant, ZoomVariant, radial_copy, zoom_copy};

/// Write a harder copy of a set (`images/` + `cameras.json`) with its ground truth transformed:
/// zoomed (every `--every`-th photo a centred crop resized back to full size, so its focal is
/// the zoom times the original's) or, with `--radial`, every photo seen through a radial lens
/// distortion (cameras.json then carries an OPENCV model with `k1 k2`).
#[derive(clap::Args)]
pub struct Args {
    /// The set: a folder with `images/` and `cameras.json`.
    set: PathBuf,
    /// Distort instead of zooming: `K1:K2` of OpenCV's radial model (issue 40's wide-angle
    /// copies use `-0.12:0.02`).
    #[arg(
        long,
        value_name = "K1:K2",
        allow_hyphen_values = true,
        conflicts_with = "fisheye"
    )]
    radial: Option<String>,
    /// Distort through OpenCV's fisheye model instead: `K1:K2:K3:K4` of the angle (the copy's
    /// cameras.json then carries OPENCV_FISHEYE), e.g. `0.05:-0.02:0.01:0` (`0:0:0:0` is the
    /// equidistant lens).
    #[arg(long, value_name = "K1:K2:K3:K4", allow_hyphen_values = true)]
    fisheye: Option<String>,
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
        if let Some(fisheye) = &self.fisheye {
            let k: Vec<f64> = fisheye
                .split(':')
                .map(str::parse)
                .collect::<Result<_, _>>()
                .ok()
                .filter(|k: &Vec<f64>| k.len() == 4)
                .with_context(|| {
                    format!("--fisheye {fisheye}: expected K1:K2:K3:K4, e.g. 0.05:-0.02:0.01:0")
                })?;
            let variant = RadialVariant {
                k1: k[0],
                k2: k[1],
                fisheye: Some([k[2], k[3]]),
            };
            radial_copy(&self.set, &self.out, &variant)?;
            println!("fisheye copy (k {k:?}) written to {}", self.out.display());
            return Ok(());
        }
        if let Some(radial) = &self.radial {
            let (k1, k2) = radial
                .split_once(':')
                .and_then(|(a, b)| Some((a.parse().ok()?, b.parse().ok()?)))
                .with_context(|| format!("--radial {radial}: expected K1:K2, e.g. -0.12:0.02"))?;
            let variant = RadialVariant {
                k1,
                k2,
                fisheye: None,
            };
            radial_copy(&self.set, &self.out, &variant)?;
            println!(
                "distorted copy (k1 {k1}, k2 {k2}) written to {}",
                self.out.display()
            );
            return Ok(());
        }
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
