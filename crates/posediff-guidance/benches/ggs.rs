//! GGS speed: one full official GGS call (700 iterations) for N = 10, 20, 50, 100 frames with
//! 200 and 1000 matches per pair (all pairs i < j), and the whole 10-step GGS of one sample for
//! 20 frames with 500 matches per pair (the target: under 1 s on the 2-core machine).
//!
//! `cargo bench -p posediff-guidance --bench ggs`

use criterion::{BenchmarkId, Criterion, criterion_group, criterion_main};
use posediff_guidance::synthetic::ring_problem;
use posediff_guidance::{GgsConfig, GgsSolver};

fn one_call(c: &mut Criterion) {
    let mut group = c.benchmark_group("ggs_call_700_iterations");
    group.sample_size(10);
    for per_pair in [200, 1000] {
        for frames in [10, 20, 50, 100] {
            let Ok(problem) = ring_problem(frames, per_pair, 0.5, 1) else {
                panic!("synthetic problem {frames}x{per_pair}");
            };
            let Ok(mut solver) = GgsSolver::new(&problem.matches, GgsConfig::default()) else {
                panic!("solver");
            };
            let id = BenchmarkId::new(format!("{per_pair}_per_pair"), frames);
            group.bench_function(id, |b| {
                b.iter(|| {
                    let mut mean = problem.initial.clone();
                    if solver.run(&mut mean, None).is_err() {
                        panic!("GGS failed");
                    }
                    mean
                });
            });
        }
    }
    group.finish();
}

fn ten_steps(c: &mut Criterion) {
    let mut group = c.benchmark_group("ggs_10_steps");
    group.sample_size(10);
    let Ok(problem) = ring_problem(20, 500, 0.5, 1) else {
        panic!("synthetic problem");
    };
    let Ok(mut solver) = GgsSolver::new(&problem.matches, GgsConfig::default()) else {
        panic!("solver");
    };
    group.bench_function("20_frames_500_per_pair", |b| {
        b.iter(|| {
            let mut mean = problem.initial.clone();
            for _ in 0..10 {
                if solver.run(&mut mean, None).is_err() {
                    panic!("GGS failed");
                }
            }
            mean
        });
    });
    group.finish();
}

// criterion_group! generates an undocumented public function.
#[allow(missing_docs)]
mod group {
    use super::*;
    criterion_group!(benches, ten_steps, one_call);
}
use group::benches;
criterion_main!(benches);
