//! `scripts/device_check.sh` in its CPU mode (issue 21): staged as for the GPU machine (the
//! tiny fixtures and the apple frames copied beside the binary), then run with `--device cpu
//! --quick`: `posediff device-check` (F32 parity, timings, a training iteration), `posediff
//! estimate` with the official-size random model it wrote, `posediff score`, and the merged
//! report. What runs on the GPU is the same script with `--device cuda`.

#![allow(clippy::unwrap_used)]

use std::path::Path;
use std::process::Command;

use posediff_fixtures::{read_json, shared_dir, temp_dir, workspace_root};

fn script() -> std::path::PathBuf {
    workspace_root().join("scripts/device_check.sh")
}

#[test]
fn the_device_script_runs_every_check_on_the_cpu() {
    let tmp = temp_dir("device_check");
    let stage = tmp.join("stage");
    let out = tmp.join("out");
    let status = Command::new("bash")
        .arg(script())
        .args(["stage", "--binary", env!("CARGO_BIN_EXE_posediff")])
        .arg("--shared")
        .arg(shared_dir())
        .arg("--dir")
        .arg(&stage)
        .status()
        .unwrap();
    assert!(status.success(), "stage failed");
    // The binary travels compressed; the tiny model travels in the tree (fixtures/torch).
    assert!(stage.join("posediff.xz").is_file());
    assert!(
        stage
            .join("reference/tiny/denoiser_io_tiny.safetensors")
            .is_file()
    );
    assert!(!stage.join("reference/tiny/model_tiny.safetensors").exists());
    assert_eq!(
        std::fs::read_dir(stage.join("data/co3d_apple_posediffusion/images"))
            .unwrap()
            .count(),
        20
    );
    let run = Command::new("bash")
        .arg(script())
        .args(["run", "--device", "cpu", "--quick", "--no-pytorch"])
        .arg("--dir")
        .arg(&stage)
        .arg("--out")
        .arg(&out)
        .output()
        .unwrap();
    assert!(
        run.status.success(),
        "run failed:\n{}",
        String::from_utf8_lossy(&run.stderr)
    );
    let report = read_json(&out.join("report.json"));
    let network = &report["network"];
    assert_eq!(network["device"], "cpu");
    assert_eq!(network["parity_passed"], true);
    let checks = network["parity"].as_array().unwrap();
    // Backbone, three denoiser steps, two teacher-forced sampling checks, on the tiny set.
    assert_eq!(checks.len(), 6, "{checks:?}");
    for c in checks {
        let (worst, bound) = (
            c["worst_abs"].as_f64().unwrap(),
            c["bound"].as_f64().unwrap(),
        );
        assert!(worst.is_finite() && worst <= bound && bound <= 1e-5, "{c}");
    }
    let rows = network["network"].as_array().unwrap();
    let frames: Vec<u64> = rows.iter().map(|r| r["frames"].as_u64().unwrap()).collect();
    assert_eq!(frames, [1, 2]);
    for r in rows {
        for key in ["features_s", "denoiser_step_s", "sampling_100_s"] {
            assert!(r[key].as_f64().unwrap() > 0.0, "{r}");
        }
    }
    let training = network["training"].as_array().unwrap();
    assert_eq!(training[0]["preset"], "tiny");
    assert!(training[0]["seconds_per_iteration"].as_f64().unwrap() > 0.0);
    assert!(training[0]["loss"].as_f64().unwrap().is_finite());
    assert_eq!(training[1]["skipped"], "--skip-official-training");
    // The estimate ran the network path on the device, on the five quick frames.
    let estimate = &report["estimate"];
    assert_eq!(estimate["run"]["device"], "cpu");
    assert_eq!(estimate["run"]["method"], "posediffusion");
    assert_eq!(estimate["run"]["images"].as_array().unwrap().len(), 5);
    assert!(estimate["run"]["seconds"]["sampling"].as_f64().unwrap() > 0.0);
    assert_eq!(estimate["score"]["scores"]["registered"], 1.0);
    let md = std::fs::read_to_string(out.join("report.md")).unwrap();
    assert!(
        md.contains("F32 parity") && md.contains("posediff estimate"),
        "{md}"
    );
}

#[test]
fn device_check_names_a_missing_fixture_folder() {
    let tmp = temp_dir("device_check_missing");
    let out = Command::new(env!("CARGO_BIN_EXE_posediff"))
        .args(["device-check", "--reference"])
        .arg(tmp.join("nowhere"))
        .arg("--out")
        .arg(tmp.join("out"))
        .output()
        .unwrap();
    assert!(!out.status.success());
    let err = String::from_utf8_lossy(&out.stderr);
    assert!(
        err.contains("nowhere/tiny/model_tiny.safetensors") && err.contains("../shared/reference"),
        "{err}"
    );
    assert!(!Path::new(&tmp.join("out/report.json")).exists());
}

#[test]
fn the_device_script_refuses_a_missing_binary() {
    let tmp = temp_dir("device_check_nobinary");
    let out = Command::new("bash")
        .arg(script())
        .args(["stage", "--binary"])
        .arg(tmp.join("posediff"))
        .arg("--dir")
        .arg(tmp.join("stage"))
        .output()
        .unwrap();
    assert!(!out.status.success());
    let err = String::from_utf8_lossy(&out.stderr);
    assert!(err.contains("cargo xtask cuda-build"), "{err}");
}
