//! The benchmarks end to end on the shared data: the ground truth scored as a prediction reaches
//! the metric ceiling on every set/subset and CO3D category, and the tiny-weight model runs
//! through the CO3D protocol with the report's structure intact.

// Test helpers outside #[test] functions unwrap too: a failure is the test failing.
#![allow(clippy::unwrap_used)]

use candle_core::Device;
use posediff::bench::{GroundTruth, Posediffusion, bench_co3d, bench_real};
use posediff::{EstimateConfig, Estimator};
use posediff_fixtures::shared_path;

#[test]
fn ground_truth_reaches_the_ceiling_on_the_real_sets() {
    let rows = bench_real(
        &shared_path("data"),
        &shared_path("data/subsets.json"),
        &GroundTruth,
    )
    .unwrap();
    // 3 sets × (3, 5, 10, all), fountain has no N = 10 draws beyond "all"? All four where drawn.
    assert!(rows.len() >= 10, "{rows:?}");
    for r in &rows {
        assert_eq!(r.scores.rra, [1.0, 1.0, 1.0], "{r:?}");
        assert_eq!(r.scores.rta, [1.0, 1.0, 1.0], "{r:?}");
        assert_eq!(r.scores.maa_30, 1.0, "{r:?}");
        assert_eq!((r.scores.registered, r.cc_10), (1.0, 1.0), "{r:?}");
    }
}

#[test]
fn co3d_protocol_runs_on_the_mini_annotations() {
    let categories: Vec<String> = ["temple", "apple", "fountain"].map(String::from).to_vec();
    let data = shared_path("data");
    let annotations = shared_path("data/co3d_mini_annotations");
    let gt = bench_co3d(&data, &annotations, &categories, 10, 10, 0, &GroundTruth).unwrap();
    assert_eq!(
        gt.per_category.keys().collect::<Vec<_>>(),
        ["apple", "fountain", "temple"]
    );
    assert_eq!(gt.mean.rra, [1.0, 1.0, 1.0]);
    assert_eq!(gt.mean.maa_30, 1.0);
    assert_eq!(gt.sequences.len(), 3);
    assert!(gt.sequences.iter().all(|s| s.frame_ids.len() == 10));

    let estimator = Estimator::load(
        &shared_path("reference/tiny/model_tiny.safetensors"),
        Device::Cpu,
        EstimateConfig::default(),
    )
    .unwrap();
    let method = Posediffusion {
        estimator,
        label: "tiny random weights (smoke test)".into(),
    };
    let run = bench_co3d(&data, &annotations, &categories, 10, 10, 0, &method).unwrap();
    // Same frames as the ceiling run: the draw does not depend on the method.
    let ids = |r: &posediff::bench::Co3dReport| {
        r.sequences
            .iter()
            .map(|s| s.frame_ids.clone())
            .collect::<Vec<_>>()
    };
    assert_eq!(ids(&run), ids(&gt));
    assert_eq!(run.mean.pairs, 3 * 45);
    assert!(run.mean.rra.iter().all(|v| (0.0..=1.0).contains(v)));
}
