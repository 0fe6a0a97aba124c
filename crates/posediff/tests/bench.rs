//! The benchmarks end to end on the shared data: the ground truth scored as a prediction reaches
//! the metric ceiling on every set/subset and CO3D category, and the tiny-weight model runs
//! through the CO3D protocol with the report's structure intact.

// Test helpers outside #[test] functions unwrap too: a failure is the test failing.
#![allow(clippy::unwrap_used)]

use candle_core::Device;
use posediff::bench::{GroundTruth, Posediffusion, bench_co3d, bench_real};
use posediff::{EstimateConfig, Estimator};
use posediff_fixtures::shared_path;

/// The tiny random-weight reference model through the pipeline (a smoke test, not accuracy).
fn tiny_model() -> Posediffusion {
    Posediffusion {
        estimator: Estimator::load(
            &shared_path("reference/tiny/model_tiny.safetensors"),
            Device::Cpu,
            EstimateConfig::default(),
        )
        .unwrap(),
        label: "tiny random weights (smoke test)".into(),
    }
}

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

    let method = tiny_model();
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

#[test]
fn the_commands_write_json_and_markdown_reports() {
    let out = std::env::temp_dir().join(format!("posediff-bench-{}", std::process::id()));
    let bin = env!("CARGO_BIN_EXE_posediff");
    let real = out.join("real.json");
    let status = std::process::Command::new(bin)
        .arg("bench-real")
        .arg("--data")
        .arg(shared_path("data"))
        .arg("--subsets")
        .arg(shared_path("data/subsets.json"))
        .args(["--method", "ground-truth"])
        .arg("--out")
        .arg(&real)
        .output()
        .unwrap();
    assert!(
        status.status.success(),
        "{}",
        String::from_utf8_lossy(&status.stderr)
    );
    let json: serde_json::Value =
        serde_json::from_str(&std::fs::read_to_string(&real).unwrap()).unwrap();
    assert_eq!(json["method"], "ground-truth");
    assert!(json["command"].as_str().unwrap().contains("bench-real"));
    assert_eq!(json["rows"].as_array().unwrap().len(), 12);
    assert!(
        std::fs::read_to_string(real.with_extension("md"))
            .unwrap()
            .contains("| strecha_fountainP11 | all |")
    );

    let co3d = out.join("co3d.json");
    let status = std::process::Command::new(bin)
        .arg("bench-co3d")
        .arg("--co3d-dir")
        .arg(shared_path("data"))
        .arg("--annotation-dir")
        .arg(shared_path("data/co3d_mini_annotations"))
        .args([
            "--categories",
            "fountain,apple",
            "--min-frames",
            "10",
            "--method",
            "ground-truth",
            "--out",
        ])
        .arg(&co3d)
        .output()
        .unwrap();
    assert!(
        status.status.success(),
        "{}",
        String::from_utf8_lossy(&status.stderr)
    );
    let json: serde_json::Value =
        serde_json::from_str(&std::fs::read_to_string(&co3d).unwrap()).unwrap();
    let seqs = json["report"]["sequences"].as_array().unwrap();
    assert_eq!(seqs.len(), 2);
    assert_eq!(seqs[0]["category"], "apple");
    assert_eq!(seqs[0]["frame_ids"].as_array().unwrap().len(), 10);
    assert_eq!(json["report"]["mean"]["rra"][1], 1.0);
    assert!(
        std::fs::read_to_string(co3d.with_extension("md"))
            .unwrap()
            .contains("**mean**")
    );
    std::fs::remove_dir_all(&out).unwrap();
}

#[test]
fn bench_real_runs_the_tiny_model_on_a_few_subsets() {
    let full: serde_json::Value =
        serde_json::from_str(&std::fs::read_to_string(shared_path("data/subsets.json")).unwrap())
            .unwrap();
    let mut small = serde_json::json!({"datasets": {}});
    for set in ["co3d_apple_posediffusion", "strecha_fountainP11"] {
        let first = full["datasets"][set]["subsets"][0].clone();
        small["datasets"][set] = serde_json::json!({"subsets": [first]});
    }
    let path = std::env::temp_dir().join(format!("posediff-subsets-{}.json", std::process::id()));
    std::fs::write(&path, small.to_string()).unwrap();
    let method = tiny_model();
    let rows = bench_real(&shared_path("data"), &path, &method).unwrap();
    std::fs::remove_file(&path).unwrap();
    assert_eq!(rows.len(), 2);
    for r in &rows {
        assert_eq!(r.subsets, 1);
        assert_eq!(r.scores.registered, 1.0);
        assert!(
            r.scores
                .rra
                .iter()
                .chain(&r.scores.rta)
                .all(|v| (0.0..=1.0).contains(v))
        );
        assert!((0.0..=1.0).contains(&r.cc_10) && r.seconds > 0.0);
    }
}
