//! Times GGS on a synthetic ring problem: `cargo run --release -p posediff-guidance --example
//! ggs_timing -- [FRAMES (20)] [MATCHES_PER_PAIR (500)] [CALLS (10)]`. Ten calls are one
//! sample's worth of GGS (diffusion steps t = 9…0).
#![allow(clippy::print_stdout)]

use std::time::Instant;

use posediff_guidance::synthetic::ring_problem;
use posediff_guidance::{GgsConfig, GgsSolver};

fn main() -> anyhow::Result<()> {
    let mut args = std::env::args().skip(1).map(|a| a.parse::<usize>());
    let frames = args.next().transpose()?.unwrap_or(20);
    let per_pair = args.next().transpose()?.unwrap_or(500);
    let calls = args.next().transpose()?.unwrap_or(10);
    let problem = ring_problem(frames, per_pair, 0.5, 7)?;
    let mut mean = problem.initial.clone();
    let mut solver = GgsSolver::new(&problem.matches, GgsConfig::default())?;
    let before = solver.objective().evaluate(&mean)?;
    let start = Instant::now();
    for _ in 0..calls {
        solver.run(&mut mean, None)?;
    }
    let secs = start.elapsed().as_secs_f64();
    let after = solver.objective().evaluate(&mean)?;
    let evals = (calls * 700 * problem.matches.len()) as f64;
    println!(
        "{frames} frames, {per_pair} matches/pair ({} matches): {calls} GGS calls in {secs:.3} s \
         ({:.1} ns per match evaluation); loss {:.4} -> {:.4} px², valid {} -> {}",
        problem.matches.len(),
        secs / evals * 1e9,
        before.loss,
        after.loss,
        before.n_valid,
        after.n_valid
    );
    Ok(())
}
