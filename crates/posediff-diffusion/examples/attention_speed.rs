//! LightGlue's attention kernels alone, at its shape (4 heads of 64 over 2048 × 2048 points), on
//! the calling threads: self-attention (`attend_heads_with`) and the bidirectional
//! cross-attention (`cross_attend_heads_with`), at both matmul precisions. On hosts without AMX
//! tiles `High` runs the F32 kernels.
//!
//! `cargo run --profile ci -p posediff-diffusion --example attention_speed [points] [reps] [high|highest]`

use std::time::Instant;

use posediff_diffusion::attention::{attend_heads_with, cross_attend_heads_with};
use posediff_diffusion::tiles::MatmulPrecision;
use rand::{Rng, SeedableRng};

/// Seconds per call of `f`, the best of `reps` after one warm-up call.
fn best_of(
    reps: usize,
    mut f: impl FnMut() -> posediff_diffusion::Result<()>,
) -> anyhow::Result<f64> {
    f()?;
    let mut best = f64::INFINITY;
    for _ in 0..reps {
        let start = Instant::now();
        f()?;
        best = best.min(start.elapsed().as_secs_f64());
    }
    Ok(best)
}

fn main() -> anyhow::Result<()> {
    let mut args = std::env::args().skip(1);
    let n: usize = args.next().map_or(Ok(2048), |a| a.parse())?;
    let reps: usize = args.next().map_or(Ok(5), |a| a.parse())?;
    // `high` or `highest` alone (for a profile of one path); both by default.
    let only = args.next();
    let (h, d) = (4usize, 64usize);
    let mut rng = rand::rngs::StdRng::seed_from_u64(7);
    // Scores of the size LightGlue's trained descriptors give (a few units), scaled by 1/√d.
    let mut random = |len: usize| -> Vec<f32> {
        (0..len)
            .map(|_| rng.random_range(-1.0f32..1.0) * 0.5)
            .collect()
    };
    let (q, k, v) = (random(h * n * d), random(h * n * d), random(h * n * d));
    let (a, b, va, vb) = (
        random(h * n * d),
        random(h * n * d),
        random(h * n * d),
        random(h * n * d),
    );
    let mut out = vec![0f32; h * n * d];
    let mut cross = vec![0f32; h * 2 * n * d];
    eprintln!(
        "{h} heads × {d}, {n} × {n} points, {} threads, AMX {}",
        posediff_diffusion::threads(),
        posediff_amx::available()
    );
    eprintln!("| precision | self-attention | cross-attention (both directions) |");
    eprintln!("|---|---:|---:|");
    for precision in [MatmulPrecision::Highest, MatmulPrecision::High] {
        if only
            .as_deref()
            .is_some_and(|o| !format!("{precision:?}").eq_ignore_ascii_case(o))
        {
            continue;
        }
        let own = best_of(reps, || {
            attend_heads_with(&q, &k, &v, &mut out, (h, n, n, d), precision)
        })?;
        let both = best_of(reps, || {
            cross_attend_heads_with((&a, &b), (&va, &vb), &mut cross, (h, n, n, d), precision)
        })?;
        eprintln!(
            "| {precision:?} | {:.1} ms | {:.1} ms |",
            own * 1e3,
            both * 1e3
        );
    }
    Ok(())
}
