//! `posediff plot`: a PNG of the right size with something drawn, and per-camera errors that
//! vanish for an estimate that is the ground truth up to a similarity.

// Test helpers outside #[test] functions unwrap too: a failure is the test failing.
#![allow(clippy::unwrap_used)]

use nalgebra::Vector3;
use opencv::prelude::*;
use posediff::io::export::{NamedCamera, read_cameras_json, write_cameras_json};
use posediff::plot::plot_cameras;
use posediff_fixtures::shared_path;
use posediff_geometry::{Quaternion, Sim3};

#[test]
fn plots_against_the_ground_truth_with_zero_errors_for_a_similar_estimate() {
    let gt = read_cameras_json(&shared_path("data/middlebury_templeSR/cameras.json")).unwrap();
    let sim = Sim3 {
        rotation: Quaternion::new(0.8, 0.2, -0.3, 0.4)
            .to_rotation_matrix()
            .unwrap(),
        translation: Vector3::new(1.0, -2.0, 0.5),
        scale: 3.0,
    };
    let est: Vec<NamedCamera> = gt
        .iter()
        .map(|c| NamedCamera {
            image: c.image.clone(),
            camera: sim.transform_camera(&c.camera),
        })
        .collect();
    let dir = std::env::temp_dir().join(format!("posediff-plot-{}", std::process::id()));
    std::fs::create_dir_all(&dir).unwrap();
    let png = dir.join("cameras.png");
    let errors = plot_cameras(&png, &est, Some(&gt)).unwrap();
    assert_eq!(errors.len(), gt.len());
    for e in &errors {
        assert!(e.rotation_deg < 1e-3 && e.center_rel < 1e-6, "{e:?}");
    }
    let img = opencv::imgcodecs::imread(png.to_str().unwrap(), opencv::imgcodecs::IMREAD_GRAYSCALE)
        .unwrap();
    assert_eq!((img.cols(), img.rows()), (1600, 700));
    let dark = img
        .data_bytes()
        .unwrap()
        .iter()
        .filter(|v| **v < 128)
        .count();
    assert!(dark > 1000, "only {dark} dark pixels");

    // Through the command, without ground truth.
    write_cameras_json(&dir.join("est.json"), &est).unwrap();
    let status = std::process::Command::new(env!("CARGO_BIN_EXE_posediff"))
        .arg("plot")
        .arg(dir.join("est.json"))
        .arg("-o")
        .arg(dir.join("plain.png"))
        .output()
        .unwrap();
    assert!(
        status.status.success(),
        "{}",
        String::from_utf8_lossy(&status.stderr)
    );
    assert!(dir.join("plain.png").is_file());
    std::fs::remove_dir_all(&dir).unwrap();
}
