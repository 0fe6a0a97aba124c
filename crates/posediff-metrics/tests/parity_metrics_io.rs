//! Parity with `reference/full/metrics_io.json`, produced by the official `util/metric.py`
//! (`camera_to_rel_deg`, `calculate_auc_np`, `calculate_auc`, `compute_ARE`) and pytorch3d
//! 0.7.4's `corresponding_cameras_alignment`.
//!
//! Tolerance: the README's "compare angles to ~1e-3 degrees (float32 acos near 0)"; the
//! accuracies and mAA are compared exactly (they count pairs).

// Test helpers outside #[test] functions unwrap too: a failure is the test failing.
#![allow(clippy::unwrap_used)]

use nalgebra::{Matrix3, Vector2, Vector3};
use posediff_fixtures::serde_json;
use posediff_fixtures::{assert_close, fixture_path, json_f64s, read_json};
use posediff_geometry::pytorch3d::NdcIntrinsics;
use posediff_geometry::{Camera, ImageSize, Pose, Pytorch3dCamera};
use posediff_metrics::{
    PairError, PoseAccuracy, absolute_rotation_errors_deg, maa_test_py, maa_train_py,
    relative_pose_errors, relative_pose_errors_with_failures, rotation_angle_deg,
    translation_angle_deg,
};

/// The README's angle tolerance.
const ANGLE_TOL_DEG: f64 = 1e-3;

struct Fixture {
    json: serde_json::Value,
    gt: Vec<Pytorch3dCamera>,
    pred: Vec<Pytorch3dCamera>,
}

fn cameras(json: &serde_json::Value, r: &str, t: &str) -> Vec<Pytorch3dCamera> {
    let r = json_f64s(&json[r]);
    let t = json_f64s(&json[t]);
    let f = json_f64s(&json["focal_length"]);
    (0..t.len() / 3)
        .map(|i| Pytorch3dCamera {
            r: Matrix3::from_row_slice(&r[9 * i..9 * i + 9]),
            t: Vector3::from_row_slice(&t[3 * i..3 * i + 3]),
            intrinsics: NdcIntrinsics {
                focal: Vector2::new(f[2 * i], f[2 * i + 1]),
                principal_point: Vector2::zeros(),
            },
        })
        .collect()
}

fn fixture() -> Fixture {
    let json = read_json(&fixture_path("reference/full/metrics_io.json"));
    let gt = cameras(&json, "gt_R", "gt_T");
    let pred = cameras(&json, "pred_R", "pred_T");
    assert_eq!(gt.len(), 10);
    Fixture { json, gt, pred }
}

fn poses(cams: &[Pytorch3dCamera]) -> Vec<Pose> {
    cams.iter().map(Pytorch3dCamera::opencv_pose).collect()
}

fn pairs(fx: &Fixture) -> Vec<PairError> {
    relative_pose_errors(&poses(&fx.gt), &poses(&fx.pred)).unwrap()
}

#[test]
fn relative_errors_match_camera_to_rel_deg() {
    let fx = fixture();
    let p = pairs(&fx);
    let i1: Vec<f64> = p.iter().map(|e| e.i as f64).collect();
    let i2: Vec<f64> = p.iter().map(|e| e.j as f64).collect();
    assert_eq!(i1, json_f64s(&fx.json["pair_i1"]));
    assert_eq!(i2, json_f64s(&fx.json["pair_i2"]));
    let rot: Vec<f64> = p.iter().map(|e| e.rotation_deg).collect();
    let trans: Vec<f64> = p.iter().map(|e| e.translation_deg).collect();
    assert_close(
        "rel_rotation_error_deg",
        &rot,
        &json_f64s(&fx.json["rel_rotation_error_deg"]),
        ANGLE_TOL_DEG,
        0.0,
    );
    assert_close(
        "rel_translation_angle_deg",
        &trans,
        &json_f64s(&fx.json["rel_translation_angle_deg"]),
        ANGLE_TOL_DEG,
        0.0,
    );
}

#[test]
fn accuracies_and_maa_match_test_py_and_train_py() {
    let fx = fixture();
    let p = pairs(&fx);
    let acc = PoseAccuracy::from_pairs(&p).unwrap();
    let expect = |k: &str| fx.json[k].as_f64().unwrap();
    assert_eq!(
        acc.rra,
        [expect("RRA@5"), expect("RRA@15"), expect("RRA@30")]
    );
    assert_eq!(
        acc.rta,
        [expect("RTA@5"), expect("RTA@15"), expect("RTA@30")]
    );
    assert_close(
        "mAA30 (test.py)",
        &[acc.maa_30],
        &[expect("mAA30_calculate_auc_np_test_py")],
        1e-12,
        0.0,
    );
    assert_close(
        "mAA30 (train.py, torch.histc)",
        &[maa_train_py(&p, 30).unwrap()],
        &[expect("mAA30_calculate_auc_torch_histc_train_py")],
        1e-7,
        0.0,
    );
    assert_ne!(maa_test_py(&p, 30).unwrap(), maa_train_py(&p, 30).unwrap());
}

#[test]
fn pytorch3d_and_opencv_inputs_give_the_same_errors() {
    // The official code works on PyTorch3D row-vector matrices: R_ij = R_iᵀ R_j,
    // T_ij = T_j − T_i R_iᵀ R_j. Computing that way must agree with our OpenCV-based pairs.
    let fx = fixture();
    for e in pairs(&fx) {
        let rel = |c: &[Pytorch3dCamera]| {
            let (a, b) = (&c[e.i], &c[e.j]);
            let r = a.r.transpose() * b.r;
            let t = b.t - (a.t.transpose() * a.r.transpose() * b.r).transpose();
            (r, t)
        };
        let (rg, tg) = rel(&fx.gt);
        let (rp, tp) = rel(&fx.pred);
        assert!((rotation_angle_deg(&rg, &rp).unwrap() - e.rotation_deg).abs() < 1e-9);
        assert!((translation_angle_deg(&tg, &tp).unwrap() - e.translation_deg).abs() < 1e-9);
    }
}

#[test]
fn edge_cases_match_the_raw_functions() {
    let fx = fixture();
    let id = json_f64s(&fx.json["edge_rotation_angle_identity_deg"]);
    let ours = rotation_angle_deg(&Matrix3::identity(), &Matrix3::identity()).unwrap();
    assert_close("identity rotation angle", &[ours, ours], &id, 1e-6, 0.0);
    let t = json_f64s(
        &fx.json["edge_translation_angle_deg_for_[[1,0,0]vs[-2,0,0]],[[0,1,0]vs[0,1,1]]"],
    );
    let a = translation_angle_deg(&Vector3::x(), &Vector3::new(-2.0, 0.0, 0.0)).unwrap();
    let b = translation_angle_deg(&Vector3::y(), &Vector3::new(0.0, 1.0, 1.0)).unwrap();
    assert_close("edge translation angles", &[a, b], &t, ANGLE_TOL_DEG, 0.0);
}

#[test]
fn demo_absolute_rotation_errors_match_compute_are_after_alignment() {
    let fx = fixture();
    let size = ImageSize::new(224, 224).unwrap();
    let to_cv = |c: &[Pytorch3dCamera]| -> Vec<Camera> {
        c.iter().map(|c| c.to_opencv(size).unwrap()).collect()
    };
    let are = absolute_rotation_errors_deg(&to_cv(&fx.gt), &to_cv(&fx.pred)).unwrap();
    assert_close(
        "demo_ARE_after_umeyama_alignment_deg",
        &are,
        &json_f64s(&fx.json["demo_ARE_after_umeyama_alignment_deg"]),
        ANGLE_TOL_DEG,
        0.0,
    );
    let mean = are.iter().sum::<f64>() / are.len() as f64;
    assert_close(
        "demo_ARE_mean_deg",
        &[mean],
        &[fx.json["demo_ARE_mean_deg"].as_f64().unwrap()],
        ANGLE_TOL_DEG,
        0.0,
    );
}

#[test]
fn failed_cameras_lower_every_metric() {
    let fx = fixture();
    let gt = poses(&fx.gt);
    let mut pred: Vec<Option<Pose>> = poses(&fx.pred).into_iter().map(Some).collect();
    let full =
        PoseAccuracy::from_pairs(&relative_pose_errors_with_failures(&gt, &pred).unwrap()).unwrap();
    pred[0] = None;
    let failed =
        PoseAccuracy::from_pairs(&relative_pose_errors_with_failures(&gt, &pred).unwrap()).unwrap();
    // Camera 0 is in 9 of the 45 pairs; its pairs were the most accurate ones.
    assert!(
        failed.rra[2] <= full.rra[2] - 9.0 / 45.0 + 1e-12,
        "{failed:?} vs {full:?}"
    );
    assert!(failed.maa_30 < full.maa_30);
}
