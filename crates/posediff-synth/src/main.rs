//! `synth`: render synthetic CO3D-style sequences (`cargo xtask synth --out D ...`).
#![allow(clippy::print_stdout)]

use std::path::PathBuf;
use std::time::Instant;

use anyhow::Context;
use clap::Parser;
use posediff_synth::scene::PathKind;
use posediff_synth::{DatasetSpec, LensSpec, parse_size, write_dataset};

/// Render synthetic object-centric sequences with exact cameras.
#[derive(Parser)]
#[command(name = "synth", version)]
struct Cli {
    /// Output folder (the CO3D root: annotations at the top, sequences below).
    #[arg(long)]
    out: PathBuf,
    /// Number of sequences.
    #[arg(long, default_value_t = 10)]
    sequences: usize,
    /// Frames per sequence.
    #[arg(long, default_value_t = 20)]
    frames: usize,
    /// Master seed.
    #[arg(long, default_value_t = 0)]
    seed: u64,
    /// Image sizes `WxH`, comma-separated, used in turn by the sequences.
    #[arg(long, default_value = "320x240")]
    size: String,
    /// Every N-th sequence goes to the test split (0: none).
    #[arg(long, default_value_t = 5)]
    test_every: usize,
    /// Force the camera path of every sequence: `orbit` or `forward` (default: drawn per
    /// sequence, forward with probability 1/4).
    #[arg(long, value_parser = parse_path)]
    path: Option<PathKind>,
    /// Zoom every N-th frame (a focal of its own, drawn from --zoom; 0: none).
    #[arg(long, default_value_t = 0)]
    zoom_every: usize,
    /// Zoom factors `LO:HI`.
    #[arg(long, default_value = "1.3:1.6")]
    zoom: String,
    /// SIMPLE_RADIAL distortion `k` of every frame (cameras.json then carries the model; no
    /// CO3D annotations are written).
    #[arg(long, default_value_t = 0.0, allow_hyphen_values = true)]
    radial: f64,
    /// Also write a PNG grid of the first, middle and last frame of up to four sequences.
    #[arg(long)]
    contact_sheet: Option<PathBuf>,
}

fn parse_path(s: &str) -> Result<PathKind, String> {
    match s {
        "orbit" => Ok(PathKind::Orbit),
        "forward" => Ok(PathKind::Forward),
        _ => Err(format!("`{s}`: use orbit or forward")),
    }
}

fn main() -> anyhow::Result<()> {
    let cli = Cli::parse();
    let sizes = cli
        .size
        .split(',')
        .map(parse_size)
        .collect::<Result<Vec<_>, _>>()?;
    let spec = DatasetSpec {
        sequences: cli.sequences,
        frames: cli.frames,
        seed: cli.seed,
        sizes,
        test_every: cli.test_every,
        path: cli.path,
        lens: LensSpec {
            zoom_every: cli.zoom_every,
            zoom: cli
                .zoom
                .split_once(':')
                .and_then(|(a, b)| Some((a.parse().ok()?, b.parse().ok()?)))
                .with_context(|| format!("--zoom {}: expected LO:HI", cli.zoom))?,
            radial_k: cli.radial,
        },
    };
    let start = Instant::now();
    let summary =
        write_dataset(&cli.out, &spec).with_context(|| format!("writing {}", cli.out.display()))?;
    let seconds = start.elapsed().as_secs_f64();
    println!(
        "{} sequences x {} frames ({} frames) in {seconds:.1} s: {} ({})",
        cli.sequences,
        cli.frames,
        summary.frames,
        cli.out.display(),
        summary.annotations.join(", ")
    );
    if let Some(sheet) = &cli.contact_sheet {
        contact_sheet(&cli.out, &summary.sequences, cli.frames, sheet)?;
        println!("wrote {}", sheet.display());
    }
    Ok(())
}

/// Rows of sequences, columns of frames (first, middle, last), each cell 240×180 (letterboxed).
fn contact_sheet(
    out: &std::path::Path,
    sequences: &[String],
    frames: usize,
    path: &std::path::Path,
) -> anyhow::Result<()> {
    let (cw, ch) = (240u32, 180u32);
    let rows = sequences.len().min(4) as u32;
    let picks = [0, frames / 2, frames.saturating_sub(1)];
    let mut sheet = image::RgbImage::from_pixel(cw * 3, ch * rows, image::Rgb([255, 255, 255]));
    for (r, seq) in sequences.iter().take(4).enumerate() {
        for (c, f) in picks.iter().enumerate() {
            let file = out.join(seq).join(format!("images/frame{f:06}.png"));
            let img = image::open(&file)
                .with_context(|| format!("reading {}", file.display()))?
                .to_rgb8();
            let scale = f64::min(
                f64::from(cw) / f64::from(img.width()),
                f64::from(ch) / f64::from(img.height()),
            );
            let (w, h) = (
                (f64::from(img.width()) * scale) as u32,
                (f64::from(img.height()) * scale) as u32,
            );
            let small = image::imageops::resize(&img, w, h, image::imageops::FilterType::Triangle);
            image::imageops::overlay(
                &mut sheet,
                &small,
                i64::from(c as u32 * cw + (cw - w) / 2),
                i64::from(r as u32 * ch + (ch - h) / 2),
            );
        }
    }
    sheet
        .save(path)
        .with_context(|| format!("writing {}", path.display()))?;
    Ok(())
}
