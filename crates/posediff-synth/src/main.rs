//! `synth`: render synthetic CO3D-style sequences (`cargo xtask synth --out D ...`).
#![allow(clippy::print_stdout)]

use std::path::PathBuf;
use std::time::Instant;

use anyhow::Context;
use clap::Parser;
use posediff_synth::{DatasetSpec, parse_size, write_dataset};

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
    Ok(())
}
