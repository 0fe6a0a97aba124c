//! The pipeline end to end: the official end-to-end result on the reference images with the
//! tiny model and the official noise, and the `posediff estimate` command on the 20 apple
//! frames writing all four formats, read back.

// Test helpers outside #[test] functions unwrap too: a failure is the test failing.
#![allow(clippy::unwrap_used)]

use std::process::Command;

use candle_core::{DType, Device, IndexOp};
use posediff::io::export::{
    Pytorch3dRecord, read_cameras_json, read_colmap_cameras, read_nerfstudio,
};
use posediff::{EstimateConfig, EstimateInput, Estimator, SamplingInput, Silent, StageTimes};
use posediff_diffusion::{PoseDiffusionModel, ReplayNoise};
use posediff_fixtures::tensors::{tensor, values};
use posediff_fixtures::{SafetensorsFixture, assert_close, shared_path};
use posediff_geometry::PoseEncoding;

#[test]
fn pipeline_reproduces_the_official_end_to_end_sample() {
    let model = PoseDiffusionModel::load(
        &shared_path("reference/tiny/model_tiny.safetensors"),
        DType::F64,
        &Device::Cpu,
    )
    .unwrap();
    let io = SafetensorsFixture::open(&shared_path("reference/tiny/denoiser_io_tiny.safetensors"));
    let run = SafetensorsFixture::open(&shared_path("reference/tiny/sampling_io_tiny.safetensors"));
    let estimator = Estimator::from_model(model, Device::Cpu, EstimateConfig::default());
    let noise = tensor(&run, "step_noise");
    let draws: Vec<Vec<f64>> = std::iter::once(values(&tensor(&run, "x_T")))
        .chain((0..99).map(|k| values(&noise.i(k).unwrap())))
        .collect();
    let mut times = StageTimes::default();
    let x = estimator
        .sample_encodings(
            SamplingInput::new(&tensor(&io, "images")),
            &mut ReplayNoise::new(draws),
            &mut times,
            &mut Silent,
        )
        .unwrap();
    let cams: Vec<_> = values(&x)
        .chunks(9)
        .map(|e| {
            PoseEncoding(<[f64; 9]>::try_from(e).unwrap())
                .decode()
                .unwrap()
        })
        .collect();
    let r: Vec<f64> = cams
        .iter()
        .flat_map(|c| c.r.transpose().as_slice().to_vec())
        .collect();
    let t: Vec<f64> = cams.iter().flat_map(|c| c.t.as_slice().to_vec()).collect();
    let f: Vec<f64> = cams
        .iter()
        .flat_map(|c| c.intrinsics.focal.as_slice().to_vec())
        .collect();
    // Free-running tolerances of the tiny README: 2e-2 on R, 0.3 abs on T and on the encoding
    // (so log-focal within 0.3: focal within a factor e^0.3).
    assert_close("e2e_R", &r, &run.tensor("e2e_R").data, 2e-2, 0.0);
    assert_close("e2e_T", &t, &run.tensor("e2e_T").data, 0.3, 0.0);
    assert_close(
        "e2e_focal_length",
        &f,
        &run.tensor("e2e_focal_length").data,
        0.0,
        0.3f64.exp() - 1.0,
    );
}

fn posediff() -> Command {
    Command::new(env!("CARGO_BIN_EXE_posediff"))
}

#[test]
fn estimate_on_the_apple_frames_writes_four_formats_that_read_back_alike() {
    let out = std::env::temp_dir().join(format!("posediff-e2e-{}", std::process::id()));
    let status = posediff()
        .arg("estimate")
        .arg(shared_path("data/co3d_apple_posediffusion/images"))
        .arg("--weights")
        .arg(shared_path("reference/tiny/model_tiny.safetensors"))
        .arg("--out")
        .arg(&out)
        .args(["--quiet", "--samples", "2"])
        .status()
        .unwrap();
    assert!(status.success());
    let json = read_cameras_json(&out.join("cameras.json")).unwrap();
    assert_eq!(json.len(), 20);
    assert_eq!(json[0].image, "frame000007.jpg");
    assert_eq!(
        (
            json[0].camera.image_size.width(),
            json[0].camera.image_size.height()
        ),
        (576, 1024)
    );
    // The principal point sits at the centre of the crop (the 576-px square at top 224).
    assert!((json[0].camera.intrinsics.cx() - 288.0).abs() < 1e-9);
    assert!((json[0].camera.intrinsics.cy() - (224.0 + 288.0)).abs() < 1e-9);
    for other in [
        read_colmap_cameras(&out.join("sparse/0")).unwrap(),
        read_nerfstudio(&out.join("transforms.json")).unwrap(),
    ] {
        assert_eq!(other.len(), json.len());
        for (a, b) in json.iter().zip(&other) {
            assert_eq!(a.image, b.image.trim_start_matches("images/"));
            assert!(
                (a.camera.cam_from_world.rotation - b.camera.cam_from_world.rotation).norm() < 1e-9
            );
            assert!(
                (a.camera.cam_from_world.translation - b.camera.cam_from_world.translation).norm()
                    < 1e-9 * (1.0 + a.camera.cam_from_world.translation.norm())
            );
            assert!(
                (a.camera.intrinsics.matrix() - b.camera.intrinsics.matrix()).norm()
                    < 1e-9 * a.camera.intrinsics.fx()
            );
        }
    }
    let p3d: Vec<Pytorch3dRecord> =
        serde_json::from_str(&std::fs::read_to_string(out.join("pytorch3d.json")).unwrap())
            .unwrap();
    assert_eq!(p3d.len(), 20);
    // The model's principal point is the crop centre: NDC (0, 0).
    assert!(
        p3d.iter().all(|r| r.camera.principal_point[0].abs() < 1e-9
            && r.camera.principal_point[1].abs() < 1e-9)
    );
    let run: serde_json::Value =
        serde_json::from_str(&std::fs::read_to_string(out.join("run.json")).unwrap()).unwrap();
    assert_eq!(run["matches_per_pair"].as_array().unwrap().len(), 190);
    // GGS's matches are the checkpoint path's own (`EstimateConfig`: hloc's 4096 keypoints),
    // not the checkpoint-free tree's (8192, contrast 0.03), which run.json also carries.
    let frames =
        posediff::io::loader::image_files(&shared_path("data/co3d_apple_posediffusion/images"))
            .unwrap();
    let (_, own) =
        posediff_matching::match_images(&frames[..2], None, &EstimateConfig::default().matching)
            .unwrap();
    let first = &run["matches_per_pair"][0];
    assert_eq!(
        (first["first"].as_u64(), first["second"].as_u64()),
        (Some(0), Some(1))
    );
    assert_eq!(first["matches"].as_u64(), Some(own[0].len() as u64));
    assert_eq!(
        run["options"]["matching"]["features"]["max_keypoints"],
        8192
    );
    // Two samples: a spread per camera, finite, and not all zero (the samples differ).
    let spread = run["sample_spread"].as_array().unwrap();
    assert_eq!(spread.len(), 20);
    let rot: Vec<f64> = spread
        .iter()
        .map(|s| s["rotation_deg_max"].as_f64().unwrap())
        .collect();
    assert!(
        rot.iter()
            .all(|r| r.is_finite() && *r >= 0.0 && *r <= 180.0)
    );
    assert!(rot.iter().any(|r| *r > 0.0));
    std::fs::remove_dir_all(&out).unwrap();
}

#[test]
fn bad_invocations_fail_with_a_message() {
    let one = shared_path("data/strecha_fountainP11/images/0000.jpg");
    let weights = shared_path("reference/tiny/model_tiny.safetensors");
    let out = std::env::temp_dir().join(format!("posediff-bad-{}", std::process::id()));
    // An output "folder" that is a file cannot be created.
    let blocker =
        std::env::temp_dir().join(format!("posediff-out-is-a-file-{}", std::process::id()));
    std::fs::write(&blocker, "x").unwrap();
    let two = [
        one.clone(),
        shared_path("data/strecha_fountainP11/images/0001.jpg"),
    ];
    let o = posediff()
        .arg("estimate")
        .args(&two)
        .args(["--no-ggs", "--quiet", "--weights"])
        .arg(&weights)
        .arg("--out")
        .arg(&blocker)
        .output()
        .unwrap();
    assert!(!o.status.success());
    assert!(String::from_utf8_lossy(&o.stderr).contains("posediff-out-is-a-file"));
    std::fs::remove_file(&blocker).unwrap();
    let cases: [(Vec<std::ffi::OsString>, &str); 3] = [
        (
            vec![
                "estimate".into(),
                one.clone().into(),
                "--weights".into(),
                weights.clone().into(),
                "--out".into(),
                out.clone().into(),
            ],
            "at least 2 images",
        ),
        (
            vec![
                "estimate".into(),
                one.clone().into(),
                one.clone().into(),
                "--weights".into(),
                "missing.pth".into(),
                "--out".into(),
                out.clone().into(),
            ],
            "missing.pth",
        ),
        (
            vec![
                "estimate".into(),
                std::env::temp_dir().join("posediff-no-such-folder").into(),
                one.clone().into(),
                "--weights".into(),
                weights.into(),
                "--out".into(),
                out.into(),
            ],
            "posediff-no-such-folder",
        ),
    ];
    for (args, needle) in cases {
        let o = posediff().args(&args).output().unwrap();
        assert!(!o.status.success(), "{args:?} succeeded");
        let err = String::from_utf8_lossy(&o.stderr);
        assert!(err.contains(needle), "{args:?}: {err}");
    }
}

/// Records what the pipeline reports.
#[derive(Default)]
struct Recorder {
    stages: Vec<(String, u64)>,
    advances: u64,
    finished: usize,
}

impl posediff::Progress for Recorder {
    fn start(&mut self, stage: &str, total: u64) {
        self.stages.push((stage.to_owned(), total));
    }
    fn advance(&mut self) {
        self.advances += 1;
    }
    fn finish(&mut self) {
        self.finished += 1;
    }
}

#[test]
fn progress_reports_every_stage_and_every_sampling_step() {
    let estimator = Estimator::load(
        &shared_path("reference/tiny/model_tiny.safetensors"),
        Device::Cpu,
        EstimateConfig::default(),
    )
    .unwrap();
    let images = [
        shared_path("data/strecha_fountainP11/images/0000.jpg"),
        shared_path("data/strecha_fountainP11/images/0001.jpg"),
    ];
    let mut rec = Recorder::default();
    let estimate = estimator
        .estimate(EstimateInput::new(&images), &mut rec)
        .unwrap();
    let names: Vec<&str> = rec.stages.iter().map(|s| s.0.as_str()).collect();
    assert_eq!(names, ["images", "matching", "features", "sampling"]);
    assert_eq!(rec.stages[3].1, 100);
    assert_eq!(rec.advances, 100);
    assert_eq!(rec.finished, 4);
    assert_eq!(estimate.samples[0][1].image, "0001.jpg");
    // The fountain pair has verified matches, so GGS ran (with random weights its phases stop at
    // once, but the hook was called).
    assert!(estimate.matches_per_pair[0].2 >= 20);
}

/// `--weights` on distorted photos (issue 40): the fountain's wide-angle copy (OpenCV
/// k1 = −0.12, k2 = 0.02) has its distortion measured from GGS's matches, which are undistorted
/// before they are mapped into the crops; every camera comes out SIMPLE_RADIAL around the
/// lens's centre with one focal, and its pixel displacement at the corner is the true lens's
/// (whatever focal the random weights give, `k` is at that focal). The original photos:
/// nothing measured, pinhole cameras.
#[test]
fn the_network_path_undistorts_the_matches_of_a_wide_angle_copy() {
    let dir = posediff_fixtures::temp_dir("e2e-network-radial");
    let set = dir.join("set");
    let status = posediff()
        .arg("variant")
        .arg(shared_path("data/strecha_fountainP11"))
        .arg("--radial=-0.12:0.02")
        .arg("--out")
        .arg(&set)
        .status()
        .unwrap();
    assert!(status.success());
    let weights = shared_path("reference/tiny/model_tiny.safetensors");
    let run = |images: &std::path::Path, out: &std::path::Path| {
        let status = posediff()
            .arg("estimate")
            .arg(images)
            .arg("--weights")
            .arg(&weights)
            .arg("--out")
            .arg(out)
            .args(["--no-view", "--quiet"])
            .status()
            .unwrap();
        assert!(status.success());
        let report: serde_json::Value =
            serde_json::from_str(&std::fs::read_to_string(out.join("run.json")).unwrap()).unwrap();
        let cameras: serde_json::Value =
            serde_json::from_str(&std::fs::read_to_string(out.join("cameras.json")).unwrap())
                .unwrap();
        (report["distortion"].clone(), cameras)
    };
    let (distortion, cameras) = run(&set.join("images"), &dir.join("wide"));
    assert_eq!(distortion["measured"], true, "{distortion}");
    let truth: serde_json::Value =
        serde_json::from_str(&std::fs::read_to_string(set.join("cameras.json")).unwrap()).unwrap();
    let cameras = cameras.as_array().unwrap();
    assert_eq!(cameras.len(), 11);
    for (i, (c, t)) in cameras.iter().zip(truth.as_array().unwrap()).enumerate() {
        assert_eq!(c["model"], "SIMPLE_RADIAL", "{c}");
        let p: Vec<f64> = c["params"]
            .as_array()
            .unwrap()
            .iter()
            .map(|v| v.as_f64().unwrap())
            .collect();
        let (f, cx, cy, k) = (p[0], p[1], p[2], p[3]);
        assert_eq!((cx, cy), (511.5, 341.0), "{c}");
        assert_eq!(
            c["K"][0][0].as_f64().unwrap(),
            c["K"][1][1].as_f64().unwrap()
        );
        assert_eq!(distortion["k1"][i].as_f64().unwrap(), k);
        // The displacement at the corner, ours and the truth's (OPENCV at its own focal).
        let r = cx.hypot(cy);
        let ours = k * r.powi(3) / (f * f);
        let rn = r / t["params"][0].as_f64().unwrap();
        let theirs = r * (-0.12 * rn.powi(2) + 0.02 * rn.powi(4));
        assert!(
            theirs < -20.0 && (ours / theirs - 1.0).abs() < 0.2,
            "image {i}: {ours} px against {theirs} px"
        );
    }
    let (distortion, cameras) = run(
        &shared_path("data/strecha_fountainP11/images"),
        &dir.join("original"),
    );
    assert_eq!(distortion["measured"], false, "{distortion}");
    for c in cameras.as_array().unwrap() {
        assert!(c.get("model").is_none_or(|m| m.is_null()), "{c}");
    }
}
