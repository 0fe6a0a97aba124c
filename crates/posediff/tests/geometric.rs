//! Cameras without a checkpoint on real images: accuracy against the ground truth, the CLI's
//! outputs, and the bad cases (no matches, disconnected groups, pure rotation, identical
//! images, known focal, refining given cameras).

// Test helpers outside #[test] functions unwrap too: a failure is the test failing.
#![allow(clippy::unwrap_used)]

use posediff::estimate::run_report::Warning;
use std::ffi::OsString;
use std::path::{Path, PathBuf};
use std::process::Command;

use nalgebra::{Matrix3, Rotation3};
use opencv::core::{Mat, Size};
use opencv::prelude::*;
use posediff::PosediffError;
use posediff::estimate::geometric::{
    GeometricConfig, GeometricEstimate, KnownIntrinsics, estimate_geometric, refine_given_cameras,
};
use posediff::io::export::{read_cameras_json, read_cameras_json_partial};
use posediff_fixtures::shared_path;
use posediff_geometry::epipolar::relative_pose;
use posediff_geometry::lens::CameraModel;
use posediff_geometry::{Camera, Pose};

/// Worst relative rotation and translation-direction errors over all pairs (degrees).
fn worst_pair_errors(est: &[Camera], gt: &[Camera]) -> (f64, f64) {
    let (mut rot, mut trans) = (0.0f64, 0.0f64);
    for i in 0..est.len() {
        for j in i + 1..est.len() {
            let e = relative_pose(&est[i].cam_from_world, &est[j].cam_from_world);
            let g = relative_pose(&gt[i].cam_from_world, &gt[j].cam_from_world);
            rot = rot.max(posediff_geometry::rotation_angle_between_deg(
                &g.rotation,
                &e.rotation,
            ));
            let c = e
                .translation
                .normalize()
                .dot(&g.translation.normalize())
                .clamp(-1.0, 1.0);
            trans = trans.max(c.acos().to_degrees());
        }
    }
    (rot, trans)
}

fn set(name: &str) -> (Vec<PathBuf>, Vec<Camera>) {
    let dir = shared_path(&format!("data/{name}"));
    let gt = read_cameras_json(&dir.join("cameras.json")).unwrap();
    (
        gt.iter().map(|c| dir.join(&c.image)).collect(),
        gt.iter().map(|c| c.camera).collect(),
    )
}

/// Runs the `posediff` command; with `ok`, asserts success (showing stderr otherwise).
fn posediff<const N: usize>(args: [OsString; N], ok: bool) -> std::process::Output {
    let run = Command::new(env!("CARGO_BIN_EXE_posediff"))
        .args(args)
        .output()
        .unwrap();
    if ok {
        assert!(
            run.status.success(),
            "{}",
            String::from_utf8_lossy(&run.stderr)
        );
    }
    run
}

#[test]
fn fountain_cameras_and_focal_match_the_ground_truth() {
    let (images, gt) = set("strecha_fountainP11");
    let e = estimate_geometric(&images, &GeometricConfig::default()).unwrap();
    let est: Vec<Camera> = e.cameras.iter().map(|c| c.unwrap()).collect();
    let (rot, trans) = worst_pair_errors(&est, &gt);
    assert!(rot < 1.0 && trans < 1.0, "worst pair: {rot}° / {trans}°");
    let focal = est[0].intrinsics.fx();
    let truth = gt[0].intrinsics.fx();
    assert!(
        (focal / truth - 1.0).abs() < 0.01,
        "focal {focal} vs {truth}"
    );
    let sampson = e
        .report
        .sampson()
        .expect("the mapper ran its Sampson refinement");
    assert!(sampson.converged);
    assert!(sampson.inlier_rms_px < 1.0);
}

/// The zoomed copy of a shared set (every second photo zoomed 1.3–1.6×, its ground truth
/// transformed) estimated with the default options: the zooms, the truth and the estimate,
/// checked for what every such copy must give: cameras from the data, no zoomed photo in the
/// unzoomed photos' camera, every focal within 1 % of the truth.
fn zoomed_copy_estimated(set: &str) -> (Vec<f64>, Vec<Camera>, GeometricEstimate) {
    let dir = posediff_fixtures::temp_dir(&format!("geometric-zoomed-{set}"));
    let zooms = posediff::io::variants::zoom_copy(
        &shared_path(&format!("data/{set}")),
        &dir,
        &posediff::io::variants::ZoomVariant::default(),
    )
    .unwrap();
    let gt = read_cameras_json(&dir.join("cameras.json")).unwrap();
    let images: Vec<PathBuf> = gt.iter().map(|c| dir.join(&c.image)).collect();
    let gt: Vec<Camera> = gt.iter().map(|c| c.camera).collect();
    let e = estimate_geometric(&images, &GeometricConfig::default()).unwrap();
    let cameras = &e.report.cameras;
    assert_eq!(cameras.decided_by, "from the data");
    for (i, z) in zooms.iter().enumerate() {
        // A zoomed photo never shares the unzoomed photos' camera.
        assert_eq!(*z > 1.0, cameras.image_camera[i] != 0, "{cameras:?}");
    }
    for (i, (c, g)) in e.cameras.iter().zip(&gt).enumerate() {
        let error = c.unwrap().intrinsics.fx() / g.intrinsics.fx() - 1.0;
        assert!(
            error.abs() < 0.01,
            "{set} image {i}: focal off by {:.2} %",
            100.0 * error
        );
    }
    std::fs::remove_dir_all(&dir).unwrap();
    (zooms, gt, e)
}

/// Every second photo of fountain zoomed 1.3–1.6× (a copy with its ground truth transformed):
/// the default camera mode gives the zoomed photos cameras of their own, each focal within
/// 1 % of the truth and the poses as good as on the original set.
#[test]
fn zoomed_photos_get_cameras_of_their_own() {
    let (zooms, gt, e) = zoomed_copy_estimated("strecha_fountainP11");
    assert_eq!(zooms.iter().filter(|z| **z > 1.29).count(), 5, "{zooms:?}");
    let est: Vec<Camera> = e.cameras.iter().map(|c| c.unwrap()).collect();
    assert!(e.report.cameras.count >= 2, "{:?}", e.report.cameras);
    let (rot, trans) = worst_pair_errors(&est, &gt);
    assert!(rot < 1.0 && trans < 2.0, "worst pair: {rot}° / {trans}°");
}

/// The temple's zoomed copy, where the view-graph calibration's per-image focals are three
/// times too short and put three zoomed photos into the unzoomed photos' camera (every optical
/// axis of the ring passes near the temple): the focal per image in the bundle adjustment
/// splits them off, the map made again with those cameras is kept, and every focal comes out
/// within 1 % (0.7 % measured), every pair's rotation within 15° (before the split: 67 % of the
/// pairs).
#[test]
fn the_bundle_adjustment_splits_zoomed_photos_the_calibration_mixed_up() {
    let (_, gt, e) = zoomed_copy_estimated("middlebury_templeSR");
    let first = &e.report.cameras.split[0];
    assert!(first.mapped_again && first.kept, "{first:?}");
    let est: Vec<Camera> = e.cameras.iter().map(|c| c.unwrap()).collect();
    let (rot, _) = worst_pair_errors(&est, &gt);
    assert!(rot < 15.0, "worst pair: {rot}°");
}

/// With EXIF as a phone writes it (a zoom lens's photos name another focal length), `auto`
/// groups by it and starts each camera from its 35 mm equivalent: the zoomed fountain comes
/// out with every focal within 1.5 % (two zooms that round to one 35 mm focal share a camera,
/// and their true focals differ by up to 0.9 %).
#[test]
fn exif_names_the_cameras_and_gives_their_focal_priors() {
    let dir = posediff_fixtures::temp_dir("geometric-zoomed-exif");
    let zooms = posediff::io::variants::zoom_copy(
        &shared_path("data/strecha_fountainP11"),
        &dir,
        &posediff::io::variants::ZoomVariant {
            exif: true,
            ..Default::default()
        },
    )
    .unwrap();
    let gt = read_cameras_json(&dir.join("cameras.json")).unwrap();
    let images: Vec<PathBuf> = gt.iter().map(|c| dir.join(&c.image)).collect();
    let names: Vec<String> = gt.iter().map(|c| c.image.clone()).collect();
    let gt: Vec<Camera> = gt.iter().map(|c| c.camera).collect();
    let config = GeometricConfig {
        hints: posediff::estimate::run::camera_hints(&images, &names).unwrap(),
        ..GeometricConfig::default()
    };
    assert!(config.hints.iter().all(|h| h.device.is_some()));
    let e = estimate_geometric(&images, &config).unwrap();
    let cameras = &e.report.cameras;
    assert_eq!(cameras.decided_by, "exif");
    assert!(
        cameras.prior.iter().all(|p| p == "exif 35 mm equivalent"),
        "{cameras:?}"
    );
    for (i, z) in zooms.iter().enumerate() {
        assert_eq!(*z > 1.0, cameras.image_camera[i] != 0, "{cameras:?}");
    }
    let est: Vec<Camera> = e.cameras.iter().map(|c| c.unwrap()).collect();
    for (i, (c, g)) in est.iter().zip(&gt).enumerate() {
        let error = c.intrinsics.fx() / g.intrinsics.fx() - 1.0;
        assert!(
            error.abs() < 0.015,
            "image {i}: focal off by {:.2} %",
            100.0 * error
        );
    }
    // The shared focal of two zooms costs the worst pair's direction a little: 2.1° measured
    // (the data's own split, a focal each, keeps it under 2°).
    let (rot, trans) = worst_pair_errors(&est, &gt);
    assert!(rot < 1.0 && trans < 3.0, "worst pair: {rot}° / {trans}°");
}

#[test]
fn a_known_focal_is_kept_and_used() {
    let (images, gt) = set("strecha_fountainP11");
    let truth = gt[0].intrinsics.fx();
    let config = GeometricConfig {
        intrinsics: KnownIntrinsics::FocalPx(truth),
        ..GeometricConfig::default()
    };
    let e = estimate_geometric(&images[..4], &config).unwrap();
    assert_eq!(
        e.report.focal_source,
        posediff::estimate::geometric::FocalOrigin::Given
    );
    let est: Vec<Camera> = e.cameras.iter().map(|c| c.unwrap()).collect();
    for c in &est {
        assert_eq!(c.intrinsics.fx(), truth);
        assert_eq!(c.intrinsics.fy(), truth);
    }
    let (rot, trans) = worst_pair_errors(&est, &gt[..4]);
    assert!(rot < 1.0 && trans < 2.0, "worst pair: {rot}° / {trans}°");
}

#[test]
fn given_cameras_are_refined_towards_the_truth() {
    let (images, gt) = set("strecha_fountainP11");
    let (images, gt) = (&images[..5], &gt[..5]);
    // Perturb: 2° about a tilted axis per camera, centres moved, focal 5 % off.
    let init: Vec<Option<Camera>> = gt
        .iter()
        .enumerate()
        .map(|(i, c)| {
            let mut c = *c;
            let extra = Rotation3::from_euler_angles(0.02 * i as f64, -0.03, 0.01);
            let centre = c.center().coords + nalgebra::Vector3::new(0.05, -0.04, 0.03) * i as f64;
            let r = extra.matrix() * c.cam_from_world.rotation;
            c.cam_from_world = Pose::from_rotation_centre(r, centre);
            c.intrinsics = posediff_geometry::Intrinsics::new(
                c.intrinsics.fx() * 1.05,
                c.intrinsics.fy() * 1.05,
                c.intrinsics.cx(),
                c.intrinsics.cy(),
            )
            .unwrap();
            Some(c)
        })
        .collect();
    let before: Vec<Camera> = init.iter().map(|c| c.unwrap()).collect();
    let (rot0, _) = worst_pair_errors(&before, gt);
    let e = refine_given_cameras(images, &init, &GeometricConfig::default()).unwrap();
    let after: Vec<Camera> = e.cameras.iter().map(|c| c.unwrap()).collect();
    let (rot, trans) = worst_pair_errors(&after, gt);
    assert!(rot0 > 3.0, "the perturbation is visible: {rot0}°");
    assert!(rot < 1.0 && trans < 2.0, "worst pair: {rot}° / {trans}°");
    // Refined without the mapper: its report says so, the refinement's is its own.
    assert!(e.report.mapper.is_none());
    let refined = e
        .report
        .given_refinement
        .expect("the given cameras were refined");
    assert_eq!(e.report.sampson(), Some(&refined));
    assert!(refined.iterations > 0 && refined.final_cost < refined.initial_cost);
}

#[test]
fn images_without_any_match_are_an_error() {
    let (fountain, _) = set("strecha_fountainP11");
    let (temple, _) = set("middlebury_templeSR");
    let err = estimate_geometric(
        &[fountain[0].clone(), temple[0].clone()],
        &GeometricConfig::default(),
    )
    .unwrap_err();
    assert!(
        matches!(err, PosediffError::NoMatches { images: 2 }),
        "{err}"
    );

    // The command says so and fails.
    let out = posediff_fixtures::temp_dir("geometric-nomatch");
    let run = posediff(
        [
            OsString::from("estimate"),
            OsString::from(&fountain[0]),
            OsString::from(&temple[0]),
            OsString::from("--out"),
            OsString::from(&out),
            OsString::from("--quiet"),
        ],
        false,
    );
    assert!(!run.status.success());
    let stderr = String::from_utf8_lossy(&run.stderr);
    assert!(stderr.contains("share enough verified matches"), "{stderr}");
}

#[test]
fn a_second_group_is_reported_not_estimated() {
    let (fountain, fountain_gt) = set("strecha_fountainP11");
    let (temple, _) = set("middlebury_templeSR");
    // Three fountain views and two overlapping temple views (0 and 1 share ~120 matches).
    let images = vec![
        fountain[2].clone(),
        temple[0].clone(),
        fountain[3].clone(),
        temple[1].clone(),
        fountain[4].clone(),
    ];
    let e = estimate_geometric(&images, &GeometricConfig::default()).unwrap();
    assert_eq!(e.report.estimated, vec![0, 2, 4]);
    assert!(e.cameras[1].is_none() && e.cameras[3].is_none());
    assert!(
        e.warnings
            .contains(&Warning::NotEstimated { count: 2, of: 5 }),
        "{:?}",
        e.warnings
    );
    assert!(
        e.warnings
            .iter()
            .any(|w| w.to_string().contains("not estimated"))
    );
    let est: Vec<Camera> = [0, 2, 4].iter().map(|&i| e.cameras[i].unwrap()).collect();
    let (rot, trans) = worst_pair_errors(&est, &fountain_gt[2..5]);
    assert!(rot < 2.0 && trans < 3.0, "worst pair: {rot}° / {trans}°");

    // cameras.json keeps every image, marking the temple views; the other formats omit them.
    let dir = posediff_fixtures::temp_dir("geometric-groups");
    for (k, img) in images.iter().enumerate() {
        std::fs::copy(
            img,
            dir.join(format!(
                "{k:02}.{}",
                img.extension().unwrap().to_str().unwrap()
            )),
        )
        .unwrap();
    }
    let out = dir.join("out");
    posediff(
        [
            OsString::from("estimate"),
            OsString::from(&dir),
            OsString::from("--out"),
            OsString::from(&out),
            OsString::from("--quiet"),
        ],
        true,
    );
    let entries = read_cameras_json_partial(&out.join("cameras.json")).unwrap();
    let estimated: Vec<bool> = entries.iter().map(|e| e.camera.is_some()).collect();
    assert_eq!(estimated, vec![true, false, true, false, true]);
    let raw = std::fs::read_to_string(out.join("cameras.json")).unwrap();
    assert_eq!(raw.matches("\"estimated\": false").count(), 2);
    assert!(read_cameras_json(&out.join("cameras.json")).is_err());
    let images_txt = std::fs::read_to_string(out.join("sparse/0/images.txt")).unwrap();
    assert_eq!(
        images_txt.lines().filter(|l| l.ends_with(".png")).count(),
        0
    );
    assert_eq!(
        images_txt.lines().filter(|l| l.ends_with(".jpg")).count(),
        3
    );
    let run_json: serde_json::Value =
        serde_json::from_str(&std::fs::read_to_string(out.join("run.json")).unwrap()).unwrap();
    assert_eq!(
        run_json["report"]["estimated"],
        serde_json::json!([0, 2, 4])
    );
    // The mapper's own report, stage by stage, as posediff-sfm derives it (schema 3).
    assert_eq!(run_json["schema"], 3);
    let mapper = &run_json["report"]["mapper"];
    assert_eq!(mapper["estimated"], serde_json::json!([0, 2, 4]));
    assert_eq!(mapper["not_estimated"].as_array().unwrap().len(), 2);
    assert_eq!(
        mapper["not_estimated"][0][1],
        "shares no usable two-view geometry with the largest group of images"
    );
    assert_eq!(mapper["focal_source"], run_json["report"]["focal_source"]);
    assert!(mapper["rotation_averaging"]["iterations"].as_u64().unwrap() > 0);
    assert!(mapper["sampson"]["termination"].is_string());
    assert!(mapper["bundle"]["points"].as_u64().unwrap() > 0);
    assert!(!mapper["starts"].as_array().unwrap().is_empty());
    assert!(run_json["report"]["given_refinement"].is_null());
}

/// Writes `image` seen by a camera rotated by `r` about its own centre: `x' = K R K⁻¹ x`.
fn write_rotated(image: &Path, k: &Matrix3<f64>, r: &Matrix3<f64>, out: &Path) {
    let src = opencv::imgcodecs::imread(image.to_str().unwrap(), opencv::imgcodecs::IMREAD_COLOR)
        .unwrap();
    let h = k * r * k.try_inverse().unwrap();
    let rows: Vec<[f64; 3]> = (0..3).map(|i| [h[(i, 0)], h[(i, 1)], h[(i, 2)]]).collect();
    let hm = Mat::from_slice_2d(&rows).unwrap();
    let mut dst = Mat::default();
    opencv::imgproc::warp_perspective(
        &src,
        &mut dst,
        &hm,
        Size::new(src.cols(), src.rows()),
        opencv::imgproc::INTER_LINEAR,
        opencv::core::BORDER_REFLECT,
        opencv::core::Scalar::default(),
    )
    .unwrap();
    opencv::imgcodecs::imwrite(out.to_str().unwrap(), &dst, &opencv::core::Vector::new()).unwrap();
}

#[test]
fn pure_rotation_gives_one_centre_and_the_rotations() {
    let (images, gt) = set("strecha_fountainP11");
    let k = gt[5].intrinsics.matrix();
    let dir = posediff_fixtures::temp_dir("geometric-rotation");
    let rotations: Vec<Matrix3<f64>> = [(0.0, 0.0, 0.0), (0.02, 0.05, 0.0), (-0.03, 0.09, 0.01)]
        .iter()
        .map(|&(a, b, c)| *Rotation3::from_euler_angles(a, b, c).matrix())
        .collect();
    let files: Vec<PathBuf> = rotations
        .iter()
        .enumerate()
        .map(|(i, r)| {
            let f = dir.join(format!("{i}.png"));
            write_rotated(&images[5], &k, r, &f);
            f
        })
        .collect();
    let e = estimate_geometric(&files, &GeometricConfig::default()).unwrap();
    assert!(
        e.warnings.contains(&Warning::NoParallax)
            && e.warnings
                .iter()
                .any(|w| w.to_string().contains("pure rotation")),
        "{:?}",
        e.warnings
    );
    let cams: Vec<Camera> = e.cameras.iter().map(|c| c.unwrap()).collect();
    for c in &cams {
        assert!(c.center().coords.norm() < 1e-9, "centre {}", c.center());
    }
    // The image of camera i is the original seen through R_i: x_i = K R_i K⁻¹ x_0, so camera i
    // is rotated by R_i relative to camera 0.
    for i in 1..3 {
        let rel = cams[i].cam_from_world.rotation * cams[0].cam_from_world.rotation.transpose();
        let err = posediff_geometry::rotation_angle_between_deg(&rotations[i], &rel);
        assert!(err < 0.2, "camera {i}: {err}°");
    }
    let focal = cams[0].intrinsics.fx();
    assert!((focal / k[(0, 0)] - 1.0).abs() < 0.05, "focal {focal}");
}

#[test]
fn identical_images_get_the_same_camera() {
    let (images, _) = set("strecha_fountainP11");
    let dir = posediff_fixtures::temp_dir("geometric-twins");
    let files: Vec<PathBuf> = [0, 1, 2, 0]
        .iter()
        .enumerate()
        .map(|(k, &i)| {
            let f = dir.join(format!("{k}.jpg"));
            std::fs::copy(&images[i], &f).unwrap();
            f
        })
        .collect();
    let e = estimate_geometric(&files, &GeometricConfig::default()).unwrap();
    let cams: Vec<Camera> = e.cameras.iter().map(|c| c.unwrap()).collect();
    let scale = (cams[1].center() - cams[0].center()).norm();
    assert!((cams[3].center() - cams[0].center()).norm() < 1e-3 * scale);
    let rel = cams[3].cam_from_world.rotation * cams[0].cam_from_world.rotation.transpose();
    assert!(posediff_geometry::rotation_angle_between_deg(&Matrix3::identity(), &rel) < 0.05);
    assert!(e.report.mapper.as_ref().unwrap().rotation_only_pairs >= 1);
}

#[test]
fn a_repeated_viewpoint_shares_its_centre_and_keeps_the_ring() {
    // templeSR0011 was taken from templeSR0001's viewpoint (a different photo, not a copy).
    let (images, gt) = set("middlebury_templeSR");
    let e = estimate_geometric(&images, &GeometricConfig::default()).unwrap();
    let est: Vec<Camera> = e.cameras.iter().map(|c| c.unwrap()).collect();
    // Tied in the averaging; refined apart only by noise (centres at unit mean distance).
    let gap = (est[0].center() - est[10].center()).norm();
    assert!(gap < 0.02, "gap {gap}");
    let mut worst_t: f64 = 0.0;
    for i in 0..est.len() {
        for j in i + 1..est.len() {
            if (i, j) == (0, 10) {
                continue; // no baseline to measure a direction of
            }
            let (a, b) = (
                relative_pose(&est[i].cam_from_world, &est[j].cam_from_world),
                relative_pose(&gt[i].cam_from_world, &gt[j].cam_from_world),
            );
            let c = a.translation.normalize().dot(&b.translation.normalize());
            worst_t = worst_t.max(c.clamp(-1.0, 1.0).acos().to_degrees());
        }
    }
    let (rot, _) = worst_pair_errors(&est, &gt);
    assert!(
        rot < 3.0 && worst_t < 5.0,
        "worst pair: {rot}° / {worst_t}°"
    );
}

#[test]
fn a_colmap_model_imports_and_initialises_the_refinement() {
    let (images, gt) = set("strecha_fountainP11");
    let dir = posediff_fixtures::temp_dir("geometric-colmap");
    let folder = dir.join("images");
    std::fs::create_dir_all(&folder).unwrap();
    for image in &images[..3] {
        std::fs::copy(image, folder.join(image.file_name().unwrap())).unwrap();
    }
    // COLMAP's own layout: a SIMPLE_RADIAL camera, two lines per image (the second with 2-D
    // points), image 0002 not registered, names with the folder prefix.
    let model = dir.join("sparse");
    std::fs::create_dir_all(&model).unwrap();
    let k = gt[0].intrinsics;
    std::fs::write(
        model.join("cameras.txt"),
        format!(
            "# Camera list\n1 SIMPLE_RADIAL 1024 683 {} {} {} -0.01\n",
            k.fx(),
            k.cx() + 0.5,
            k.cy() + 0.5
        ),
    )
    .unwrap();
    let mut lines = String::from("# Image list\n");
    for (id, i) in [0usize, 1].iter().enumerate() {
        let q = posediff_geometry::Quaternion::from_rotation_matrix(
            &gt[*i].cam_from_world.rotation,
            posediff_geometry::QuaternionSign::NonNegativeReal,
        )
        .unwrap();
        let t = gt[*i].cam_from_world.translation;
        lines.push_str(&format!(
            "{} {} {} {} {} {} {} {} 1 images/{:04}.jpg\n10.5 20.5 -1 30.0 40.0 7\n",
            id + 1,
            q.w,
            q.x,
            q.y,
            q.z,
            t.x,
            t.y,
            t.z,
            i
        ));
    }
    std::fs::write(model.join("images.txt"), lines).unwrap();
    std::fs::write(model.join("points3D.txt"), "").unwrap();
    let out = dir.join("init.json");
    posediff(
        [
            OsString::from("import-colmap"),
            OsString::from(&model),
            OsString::from("--images"),
            OsString::from(&folder),
            OsString::from("--out"),
            OsString::from(&out),
        ],
        true,
    );
    let entries = read_cameras_json_partial(&out).unwrap();
    assert_eq!(entries.len(), 3);
    assert!(entries[2].camera.is_none());
    assert_eq!(
        (entries[2].size.width(), entries[2].size.height()),
        (1024, 683)
    );
    for i in 0..2 {
        let c = entries[i].camera.unwrap();
        assert!((c.cam_from_world.rotation - gt[i].cam_from_world.rotation).norm() < 1e-9);
        assert!(
            (c.intrinsics.cx() - k.cx()).abs() < 1e-9,
            "COLMAP's half-pixel offset undone"
        );
    }

    // The imported estimate initialises the refinement; the unregistered image stays so.
    let refined = dir.join("refined");
    posediff(
        [
            OsString::from("estimate"),
            OsString::from(&folder),
            OsString::from("--init"),
            OsString::from(&out),
            OsString::from("--out"),
            OsString::from(&refined),
            OsString::from("--quiet"),
        ],
        true,
    );
    let entries = read_cameras_json_partial(&refined.join("cameras.json")).unwrap();
    assert!(entries[0].camera.is_some() && entries[1].camera.is_some());
    assert!(entries[2].camera.is_none());
    let est = [entries[0].camera.unwrap(), entries[1].camera.unwrap()];
    let (rot, trans) = worst_pair_errors(&est, &gt[..2]);
    assert!(rot < 1.0 && trans < 1.0, "{rot}° / {trans}°");
}

#[test]
fn the_official_ggs_schedule_is_an_option() {
    let (images, gt) = set("strecha_fountainP11");
    let config = GeometricConfig {
        refinement: posediff::estimate::geometric::Refinement::Official(
            posediff_guidance::GgsConfig {
                iter_num: 20,
                ..posediff_guidance::GgsConfig::default()
            },
        ),
        ..GeometricConfig::default()
    };
    let e = estimate_geometric(&images[..4], &config).unwrap();
    let est: Vec<Camera> = e.cameras.iter().map(|c| c.unwrap()).collect();
    // The averaged cameras refined by the official SGD in the 224 crops: still close.
    let (rot, trans) = worst_pair_errors(&est, &gt[..4]);
    assert!(rot < 3.0 && trans < 5.0, "worst pair: {rot}° / {trans}°");
    assert!(e.report.times.refinement > 0.0);
}

#[test]
fn known_intrinsics_from_a_file_are_returned_exactly() {
    let dir = shared_path("data/strecha_fountainP11");
    let out = posediff_fixtures::temp_dir("geometric-intrinsics");
    posediff(
        [
            OsString::from("estimate"),
            OsString::from(dir.join("images")),
            OsString::from("--intrinsics"),
            OsString::from(dir.join("cameras.json")),
            OsString::from("--out"),
            OsString::from(&out),
            OsString::from("--quiet"),
        ],
        true,
    );
    let est = read_cameras_json(&out.join("cameras.json")).unwrap();
    let gt = read_cameras_json(&dir.join("cameras.json")).unwrap();
    for (e, g) in est.iter().zip(&gt) {
        assert_eq!(e.camera.intrinsics, g.camera.intrinsics);
    }
    let run_json: serde_json::Value =
        serde_json::from_str(&std::fs::read_to_string(out.join("run.json")).unwrap()).unwrap();
    assert_eq!(run_json["report"]["focal_source"], "given");
    let est: Vec<Camera> = est.iter().map(|c| c.camera).collect();
    let gt: Vec<Camera> = gt.iter().map(|c| c.camera).collect();
    let (rot, trans) = worst_pair_errors(&est, &gt);
    assert!(rot < 1.0 && trans < 1.0, "worst pair: {rot}° / {trans}°");

    // A file for other images is refused.
    let bad = posediff(
        [
            OsString::from("estimate"),
            OsString::from(dir.join("images/0000.jpg")),
            OsString::from(dir.join("images/0001.jpg")),
            OsString::from("--intrinsics"),
            OsString::from(dir.join("cameras.json")),
            OsString::from("--out"),
            OsString::from(out.join("bad")),
        ],
        false,
    );
    assert!(!bad.status.success());
    let stderr = String::from_utf8_lossy(&bad.stderr);
    assert!(
        stderr.contains("9 entr(y/ies) name no input image"),
        "{stderr}"
    );
}

/// The hybrid refinement (`--weights W --refine bundle`): cameras from elsewhere, here the
/// ground truth perturbed by about a degree and 4 % in focal, are pulled back by the bundle
/// adjustment with tracks from real matches; the scene keeps its scale.
#[test]
fn the_bundle_refinement_pulls_given_cameras_to_the_truth() {
    let (images, gt) = set("strecha_fountainP11");
    let (images, gt) = (&images[..5], &gt[..5]);
    let config = GeometricConfig::default();
    let (_, pairs) =
        posediff_matching::match_images(images, None, &config.options.matching).unwrap();
    assert!(
        pairs.iter().all(|p| p.idx1.len() == p.len()),
        "keypoint ids travel with the matches"
    );
    let mut cams: Vec<Camera> = gt
        .iter()
        .enumerate()
        .map(|(i, c)| {
            let mut c = *c;
            if i > 0 {
                let extra = Rotation3::from_euler_angles(0.01, -0.012 * i as f64, 0.008);
                let centre =
                    c.center().coords + nalgebra::Vector3::new(0.02, -0.01, 0.015) * i as f64;
                let r = extra.matrix() * c.cam_from_world.rotation;
                c.cam_from_world = Pose::from_rotation_centre(r, centre);
            }
            c.intrinsics = posediff_geometry::Intrinsics::new(
                c.intrinsics.fx() * 1.04,
                c.intrinsics.fy() * 1.04,
                c.intrinsics.cx(),
                c.intrinsics.cy(),
            )
            .unwrap();
            c
        })
        .collect();
    let (rot0, _) = worst_pair_errors(&cams, gt);
    let spread = |c: &[Camera]| -> f64 {
        c.iter()
            .map(|x| (x.center() - c[0].center()).norm())
            .sum::<f64>()
            / c.len() as f64
    };
    let scale0 = spread(&cams);
    let defaults = (
        posediff_sfm::sampson_refine::SampsonRefineOptions::default(),
        posediff_sfm::bundle::BundleOptions::default(),
    );
    let r = posediff::estimate::geometric::bundle_refine_cameras(
        &mut cams,
        &pairs,
        false,
        (&defaults.0, &defaults.1),
    )
    .unwrap();
    let (rot, trans) = worst_pair_errors(&cams, gt);
    assert!(rot0 > 1.0, "the perturbation is visible: {rot0}°");
    assert!(
        rot < 0.2 && trans < 0.5,
        "worst pair after: {rot}° / {trans}° ({r:?})"
    );
    assert!(r.points > 1000 && r.rms_px < 1.0, "{r:?}");
    let f_err = cams[0].intrinsics.fx() / gt[0].intrinsics.fx() - 1.0;
    assert!(f_err.abs() < 0.01, "focal {f_err}");
    assert!(
        (spread(&cams) / scale0 - 1.0).abs() < 1e-9,
        "the scale is kept"
    );
}

#[test]
fn the_support_check_drops_a_wrong_pair_and_keeps_confirmed_bridges() {
    use posediff::estimate::geometric::estimate_from_supported_matches;
    // Six fountain frames, SIFT matches. Supported: the neighbours (i, i+1); every other pair
    // is unsupported but right, and must be confirmed through triangles. One wrong pair is
    // planted: (0, 5) carries the matches of (2, 3) (real matches of two other views, as a
    // learned matcher's pair on the other side of a symmetric object), a relative rotation
    // tens of degrees from the truth.
    let (images, gt) = set("strecha_fountainP11");
    let (images, gt) = (&images[..6], &gt[..6]);
    let config = GeometricConfig::default();
    let (features, mut pairs) =
        posediff_matching::match_images(images, None, &config.options.matching).unwrap();
    let sizes: Vec<_> = features.iter().map(|f| f.image_size).collect();
    let donor = pairs
        .iter()
        .find(|p| (p.first, p.second) == (2, 3))
        .unwrap()
        .clone();
    let planted = pairs
        .iter_mut()
        .find(|p| (p.first, p.second) == (0, 5))
        .unwrap();
    *planted = posediff_geometry::PairMatches {
        first: 0,
        second: 5,
        ..donor.clone()
    };
    let truth = relative_pose(&gt[0].cam_from_world, &gt[5].cam_from_world).rotation;
    let fake = relative_pose(&gt[2].cam_from_world, &gt[3].cam_from_world).rotation;
    let apart = posediff_geometry::rotation_angle_between_deg(&truth, &fake);
    assert!(apart > 20.0, "the planted pair is only {apart}° off");
    assert!(pairs.iter().all(|p| p.len() >= 20), "every pair is matched");
    let support: Vec<bool> = pairs.iter().map(|p| p.second == p.first + 1).collect();

    let e = estimate_from_supported_matches(&sizes, pairs.clone(), Some(support), &config).unwrap();
    let mapper = e.report.mapper.as_ref().unwrap();
    let s = mapper.support.as_ref().unwrap();
    assert_eq!(s.supported, 5);
    assert_eq!((s.confirmed, s.rejected), (9, 1), "{s:?}");
    let rejected = e
        .pairs
        .iter()
        .find(|p| (p.first, p.second) == (0, 5))
        .unwrap();
    assert!(
        rejected.is_empty(),
        "a rejected pair keeps no matches downstream"
    );
    assert!(!mapper.averaged_pairs.contains(&[0, 5]));
    let est: Vec<Camera> = e.cameras.iter().map(|c| c.unwrap()).collect();
    let (rot, trans) = worst_pair_errors(&est, gt);
    assert!(rot < 1.0 && trans < 2.0, "worst pair: {rot}° / {trans}°");

    // Flags of another count are an error, not a silent mismatch.
    let err = estimate_from_supported_matches(&sizes, pairs, Some(vec![true; 3]), &config);
    assert!(err.is_err());
}

/// The second matching pass on the first map's cameras: fountain matched on each image's next
/// neighbour only (a chain), then densified — the new pairs are those the first map puts
/// within the angle, matched and mapped, and the cameras stay within a degree.
#[test]
fn the_second_pass_matches_the_pairs_the_first_map_puts_close() {
    use posediff::estimate::options::{DensifyOptions, DensifyWhen};
    let (images, gt) = set("strecha_fountainP11");
    let mut config = GeometricConfig::default();
    config.options.pairs.selection = "sequential:1".parse().unwrap();
    config.options.densify = DensifyOptions {
        when: DensifyWhen::Always,
        max_angle_deg: 30.0,
        per_image: 3,
    };
    let e = estimate_geometric(&images, &config).unwrap();
    assert!(e.report.pair_selection.contains("densify:30deg,3"));
    let added = e.report.pairs_densified;
    assert!(
        added > 0 && added <= 3 * images.len(),
        "{added} pairs added"
    );
    assert_eq!(e.report.pairs_matched, images.len() - 1 + added);
    // Every new pair is within the angle by the ground truth too (the first map is right to
    // a degree), and is no chain pair.
    for p in &e.pairs[images.len() - 1..] {
        assert!(
            p.second > p.first + 1,
            "({}, {}) is a chain pair",
            p.first,
            p.second
        );
        let angle = posediff_geometry::rotation_angle_between_deg(
            &gt[p.first].cam_from_world.rotation,
            &gt[p.second].cam_from_world.rotation,
        );
        assert!(
            angle < 31.0,
            "({}, {}) is {angle}° apart",
            p.first,
            p.second
        );
    }
    let est: Vec<Camera> = e.cameras.iter().map(|c| c.unwrap()).collect();
    let (rot, trans) = worst_pair_errors(&est, &gt);
    assert!(rot < 1.0 && trans < 1.0, "worst pair: {rot}° / {trans}°");
}

/// The options tree from the CLI: a `--config` file changes the pair plan (`pairs.auto` with a
/// bound of 2 images makes four fountain views sequential + retrieval), run.json carries the
/// tree as used, `--set` overrides the file field by field, and a misspelt key or a wrong type
/// is an error naming it and the file before any work.
#[test]
fn the_options_tree_is_read_from_a_file_and_overridden_per_field() {
    let (images, _) = set("strecha_fountainP11");
    let dir = posediff_fixtures::temp_dir("geometric-options-tree");
    let imgs = dir.join("images");
    std::fs::create_dir_all(&imgs).unwrap();
    for img in &images[..4] {
        std::fs::copy(img, imgs.join(img.file_name().unwrap())).unwrap();
    }
    let config = dir.join("opts.toml");
    std::fs::write(
        &config,
        "[pairs.auto]\nexhaustive_up_to = 2\nsequential = 1\nretrieval = 1\n\n[orientation]\nstrong_pair = 120\n",
    )
    .unwrap();
    let run = |out: &str, extra: &[&str], ok: bool| {
        let out = dir.join(out);
        let mut args = vec![
            OsString::from("estimate"),
            OsString::from(&imgs),
            OsString::from("--out"),
            OsString::from(&out),
            OsString::from("--quiet"),
            OsString::from("--no-view"),
            OsString::from("--config"),
            OsString::from(&config),
        ];
        args.extend(extra.iter().map(OsString::from));
        let r = Command::new(env!("CARGO_BIN_EXE_posediff"))
            .args(&args)
            .output()
            .unwrap();
        assert_eq!(
            r.status.success(),
            ok,
            "{}",
            String::from_utf8_lossy(&r.stderr)
        );
        (out, String::from_utf8_lossy(&r.stderr).into_owned())
    };
    let report = |out: &Path| -> serde_json::Value {
        serde_json::from_str(&std::fs::read_to_string(out.join("run.json")).unwrap()).unwrap()
    };

    let (out, _) = run("from-file", &[], true);
    let r = report(&out);
    assert_eq!(r["report"]["pair_selection"], "sequential:1,retrieval:1");
    assert_eq!(r["options"]["pairs"]["auto"]["exhaustive_up_to"], 2);
    assert_eq!(r["options"]["orientation"]["strong_pair"], 120);
    // Fields the file did not name keep their defaults.
    assert_eq!(r["options"]["orientation"]["tests"], 8);
    assert_eq!(r["options"]["pairs"]["selection"], "auto");

    let (out, _) = run(
        "overridden",
        &[
            "--set",
            "pairs.auto.exhaustive_up_to=60",
            "--set",
            "mapper.focal_prior=1.5",
            "--set",
            "points.max_reprojection_px=2",
        ],
        true,
    );
    let r = report(&out);
    assert_eq!(r["report"]["pair_selection"], "exhaustive");
    assert_eq!(r["options"]["pairs"]["auto"]["exhaustive_up_to"], 60);
    assert_eq!(r["options"]["mapper"]["focal_prior"], 1.5);
    // The exports' points are triangulated with the tree's threshold.
    assert_eq!(r["points"]["max_reprojection_px"], 2.0);
    // `--pairs` is `pairs.selection`.
    let (out, _) = run("flag", &["--pairs", "sequential:2"], true);
    assert_eq!(report(&out)["report"]["pair_selection"], "sequential:2");

    // Errors: an unknown key names the key, the keys there and the file; a wrong type names
    // the key; no work starts.
    std::fs::write(&config, "[orientation]\nstrong_pairs = 120\n").unwrap();
    let (out, err) = run("misspelt", &[], false);
    assert!(
        err.contains("orientation.strong_pairs")
            && err.contains("strong_pair,")
            && err.contains("opts.toml"),
        "{err}"
    );
    assert!(!out.join("cameras.json").exists());
    std::fs::write(&config, "").unwrap();
    let (_, err) = run("wrong-type", &["--set", "orientation.tests=many"], false);
    assert!(err.contains("--set orientation.tests"), "{err}");
    let (_, err) = run("no-equals", &["--set", "orientation.tests"], false);
    assert!(err.contains("key.path=value"), "{err}");
    let (_, err) = run("bad-angle", &["--set", "points.min_angle_deg=-1"], false);
    assert!(err.contains("points.min_angle_deg"), "{err}");
}

/// A synthetic orbit rendered through an exact SIMPLE_RADIAL lens (`k = −0.1`, posediff-synth):
/// the one model the calibration fits is the truth's, so its coefficient comes back within 0.01
/// (−0.098 measured, after the bundle adjustment's refinement), every focal within 1 % and
/// every pair's direction within 2°. With the calibration before the mapper off, the bundle
/// adjustment's refinement alone finds the lens (−0.0945) from a pinhole start. RADIAL and
/// OPENCV fit the lens as the truth moves pixels (OPENCV's tangential terms near 0). The
/// pinhole rendering of the same orbit is left pinhole by both.
#[test]
fn a_synthetic_wide_angle_lens_is_recovered() {
    use posediff_synth::{DatasetSpec, LensSpec, scene::PathKind, write_dataset};
    let dir = posediff_fixtures::temp_dir("geometric-synthetic-radial");
    let truth = -0.1;
    use posediff_sfm::lens_refinement::LensModel;
    for (radial_k, calibrate, lens_model) in [
        (truth, true, LensModel::SimpleRadial),
        (truth, false, LensModel::SimpleRadial),
        (truth, true, LensModel::Radial),
        (truth, true, LensModel::Opencv),
        (0.0, true, LensModel::SimpleRadial),
    ] {
        let radial_model = lens_model != LensModel::SimpleRadial;
        let root = dir.join(format!("k{radial_k}-{calibrate}-{lens_model:?}"));
        write_dataset(
            &root,
            &DatasetSpec {
                sequences: 1,
                frames: 20,
                seed: 3,
                sizes: vec![posediff_geometry::ImageSize::new(640, 480).unwrap()],
                test_every: 0,
                path: Some(PathKind::Orbit),
                lens: LensSpec {
                    radial_k,
                    ..LensSpec::default()
                },
            },
        )
        .unwrap();
        let seq = root.join("synthetic/synthetic_0000");
        let gt = read_cameras_json(&seq.join("cameras.json")).unwrap();
        let images: Vec<PathBuf> = gt.iter().map(|c| seq.join(&c.image)).collect();
        let gt: Vec<Camera> = gt.iter().map(|c| c.camera).collect();
        let mut config = GeometricConfig::default();
        if !calibrate {
            config.options.cameras.distortion = None;
        }
        let refinement = config.options.cameras.lens_refinement.as_mut().unwrap();
        refinement.model = lens_model;
        let e = estimate_geometric(&images, &config).unwrap();
        let distortion = &e.report.cameras.distortion;
        assert_eq!(
            distortion.measured,
            radial_k != 0.0 && calibrate,
            "{distortion:?}"
        );
        let refinement = distortion.refinement.as_ref().unwrap();
        assert_eq!(refinement.kept, radial_k != 0.0, "{refinement:?}");
        assert_eq!(e.lens.is_some(), radial_k != 0.0);
        if radial_k != 0.0 {
            let k = distortion.k1[0].unwrap();
            if !radial_model {
                assert!((k - truth).abs() < 0.01, "k {k} against {truth}");
            }
            assert!(refinement.adjustment.rms_after_px < refinement.adjustment.rms_before_px);
            // RADIAL: a second coefficient near the truth's 0, and the lens written as RADIAL.
            assert_eq!(distortion.k2.is_empty(), !radial_model, "{distortion:?}");
            let c = e.cameras[0].unwrap();
            let lens = e
                .lens
                .as_ref()
                .unwrap()
                .lens_camera(0, &c.intrinsics)
                .unwrap();
            let model = match lens_model {
                LensModel::SimpleRadial => CameraModel::SimpleRadial,
                LensModel::Radial => CameraModel::Radial,
                LensModel::Opencv => CameraModel::OpenCv,
                LensModel::OpencvFisheye => CameraModel::OpenCvFisheye,
            };
            assert_eq!(lens.model(), model);
            // OPENCV: tangential terms near the truth's 0 (a pixel's worth at the corner is
            // 1e-3), in run.json.
            assert_eq!(
                distortion.p1.is_empty(),
                lens_model != LensModel::Opencv,
                "{distortion:?}"
            );
            if lens_model == LensModel::Opencv {
                let (p1, p2) = (distortion.p1[0].unwrap(), distortion.p2[0].unwrap());
                assert!(p1.abs() < 1e-3 && p2.abs() < 1e-3, "{distortion:?}");
                assert_eq!(lens.distortion()[2], p1);
            }
            if radial_model {
                // Two coefficients trade off where the points thin out (0.56 px off at the
                // corners): inside the circle inscribed in the photo the lens they make moves
                // every pixel as the truth's does, within half a pixel.
                let k2 = distortion.k2[0].unwrap();
                let f = c.intrinsics.fx();
                let inscribed = 240.0 / f;
                for step in 0..=20 {
                    let r = inscribed * f64::from(step) / 20.0;
                    let off = f * r * ((k * r * r + k2 * r.powi(4)) - truth * r * r);
                    assert!(off.abs() < 0.5, "k {k}, k2 {k2}: {off} px at r {r}");
                }
            }
        }
        let est: Vec<Camera> = e.cameras.iter().map(|c| c.unwrap()).collect();
        for (i, (c, g)) in est.iter().zip(&gt).enumerate() {
            let error = c.intrinsics.fx() / g.intrinsics.fx() - 1.0;
            assert!(
                error.abs() < 0.01,
                "image {i}: focal off by {:.2} %",
                100.0 * error
            );
        }
        let (rot, trans) = worst_pair_errors(&est, &gt);
        // OPENCV's tangential terms (fitted at 6e-4, about 0.2 px at the corners, where the
        // truth has none) trade off against the translations: its worst pair is 2.7° (mAA(30)
        // 0.998 against RADIAL's 1.000).
        let max_trans = if lens_model == LensModel::Opencv {
            3.0
        } else {
            2.0
        };
        assert!(
            rot < 1.0 && trans < max_trans,
            "{lens_model:?}, calibrated {calibrate}: worst pair {rot}° / {trans}°"
        );
    }
    std::fs::remove_dir_all(&dir).unwrap();
}

/// `--masks` (COLMAP's naming, zero = ignore), with SIFT and ORB: no keypoint of a masked image
/// lies on its masked left third (COLMAP's 2-D points: every keypoint in a verified match),
/// where without masks there are many; the image without a mask is listed in run.json; a mask
/// of the wrong size is an error that names it before any work.
#[test]
fn masked_pixels_give_no_keypoints() {
    let dir = posediff_fixtures::temp_dir("geometric-masks");
    let (images, _) = set("co3d_apple_posediffusion");
    let input = dir.join("in");
    let masks = dir.join("masks");
    std::fs::create_dir_all(&input).unwrap();
    std::fs::create_dir_all(&masks).unwrap();
    let mut width = 0;
    for (k, image) in images.iter().take(8).enumerate() {
        let name = image.file_name().unwrap().to_string_lossy().into_owned();
        std::fs::copy(image, input.join(&name)).unwrap();
        let img =
            opencv::imgcodecs::imread(image.to_str().unwrap(), opencv::imgcodecs::IMREAD_GRAYSCALE)
                .unwrap();
        width = img.cols();
        if k == 7 {
            continue; // no mask: used whole
        }
        let mut mask = Mat::new_rows_cols_with_default(
            img.rows(),
            img.cols(),
            opencv::core::CV_8UC1,
            opencv::core::Scalar::all(255.0),
        )
        .unwrap();
        let third = opencv::core::Rect::new(0, 0, img.cols() / 3, img.rows());
        Mat::roi_mut(&mut mask, third)
            .unwrap()
            .set_to_def(&opencv::core::Scalar::all(0.0))
            .unwrap();
        let path = masks.join(format!("{name}.png"));
        opencv::imgcodecs::imwrite_def(path.to_str().unwrap(), &mask).unwrap();
    }
    let edge = f64::from(width / 3) - 0.5;
    let unmasked = images[7]
        .file_name()
        .unwrap()
        .to_string_lossy()
        .into_owned();
    // Keypoints on the left third of the images that get masks, per run.
    let left_of_masked = |out: &Path| -> Vec<usize> {
        let model = posediff::io::colmap::ColmapModel::read(&out.join("sparse/0")).unwrap();
        model
            .images
            .iter()
            .filter(|im| im.name != unmasked)
            .map(|im| {
                im.points2d
                    .iter()
                    .filter(|(xy, _)| xy[0] - 0.5 < edge)
                    .count()
            })
            .collect()
    };
    for matcher in ["sift", "orb"] {
        let out = dir.join(format!("out-{matcher}"));
        let args = |masked: bool, out: &Path| -> Vec<OsString> {
            let mut a: Vec<OsString> = vec![
                "estimate".into(),
                input.clone().into(),
                "--matcher".into(),
                matcher.into(),
                "--no-view".into(),
                "--quiet".into(),
                "--out".into(),
                out.into(),
            ];
            if masked {
                a.extend(["--masks".into(), masks.clone().into()]);
            }
            a
        };
        let plain = dir.join(format!("plain-{matcher}"));
        let r = Command::new(env!("CARGO_BIN_EXE_posediff"))
            .args(args(false, &plain))
            .output()
            .unwrap();
        assert!(r.status.success(), "{}", String::from_utf8_lossy(&r.stderr));
        let without: usize = left_of_masked(&plain).iter().sum();
        assert!(
            without > 50,
            "{matcher}: only {without} keypoints there without masks"
        );
        let r = Command::new(env!("CARGO_BIN_EXE_posediff"))
            .args(args(true, &out))
            .output()
            .unwrap();
        assert!(r.status.success(), "{}", String::from_utf8_lossy(&r.stderr));
        let run: serde_json::Value =
            serde_json::from_str(&std::fs::read_to_string(out.join("run.json")).unwrap()).unwrap();
        assert_eq!(run["masks"]["masked"], 7, "{matcher}");
        assert_eq!(run["masks"]["missing"], serde_json::json!([unmasked]));
        let with: Vec<usize> = left_of_masked(&out);
        assert!(
            with.iter().all(|n| *n == 0),
            "{matcher}: masked keypoints {with:?}"
        );
    }
    // A mask of another size: named before any work.
    let small = Mat::new_rows_cols_with_default(
        10,
        10,
        opencv::core::CV_8UC1,
        opencv::core::Scalar::all(255.0),
    )
    .unwrap();
    let name = images[7]
        .file_name()
        .unwrap()
        .to_string_lossy()
        .into_owned();
    let wrong = masks.join(format!("{name}.png"));
    opencv::imgcodecs::imwrite_def(wrong.to_str().unwrap(), &small).unwrap();
    let run = posediff(
        [
            "estimate".into(),
            input.into(),
            "--masks".into(),
            masks.into(),
            "--out".into(),
            dir.join("out-wrong").into(),
        ],
        false,
    );
    let stderr = String::from_utf8_lossy(&run.stderr);
    assert!(!run.status.success());
    assert!(
        stderr.contains("the mask is 10x10") && stderr.contains(&name),
        "{stderr}"
    );
    assert!(!dir.join("out-wrong/cameras.json").exists());
    std::fs::remove_dir_all(&dir).unwrap();
}

/// A fisheye copy of the fountain (`posediff variant --fisheye`: OpenCV's fisheye model, nearly
/// equidistant, far from a pinhole's tan) estimated with `--camera-model OPENCV_FISHEYE`: the
/// lens is kept, every camera is OPENCV_FISHEYE with one focal within 1 % of the truth's, and
/// its radius moves every angle out to the image's corners as the truth's does (within a pixel,
/// two at the corners: the coefficients of `θ⁷, θ⁹` are weakly determined over 31°, so the lens is compared, not
/// the coefficients); the cameras are right.
#[test]
fn a_fisheye_copy_is_calibrated_with_its_model() {
    let dir = posediff_fixtures::temp_dir("geometric-fisheye");
    let set = dir.join("set");
    posediff(
        [
            "variant".into(),
            shared_path("data/strecha_fountainP11").into(),
            "--fisheye=0.05:-0.02:0.01:0".into(),
            "--out".into(),
            set.clone().into(),
        ],
        true,
    );
    let out = dir.join("out");
    posediff(
        [
            "estimate".into(),
            set.join("images").into(),
            "--camera-model".into(),
            "OPENCV_FISHEYE".into(),
            "--out".into(),
            out.clone().into(),
            "--no-view".into(),
            "--quiet".into(),
        ],
        true,
    );
    let truth = read_cameras_json_partial(&set.join("cameras.json")).unwrap();
    let found = read_cameras_json_partial(&out.join("cameras.json")).unwrap();
    assert_eq!(truth.len(), found.len());
    let radius = |params: &[f64], theta: f64| {
        let t2 = theta * theta;
        let k = &params[4..8];
        params[0] * theta * (1.0 + t2 * (k[0] + t2 * (k[1] + t2 * (k[2] + t2 * k[3]))))
    };
    for (t, f) in truth.iter().zip(&found) {
        let (tl, fl) = (t.lens.as_ref().unwrap(), f.lens.as_ref().unwrap());
        assert_eq!(fl.model(), CameraModel::OpenCvFisheye, "{:?}", fl.params());
        let (tp, fp) = (tl.params(), fl.params());
        assert_eq!(fp[0], fp[1]);
        assert!((fp[0] / tp[0] - 1.0).abs() < 0.01, "{fp:?} vs {tp:?}");
        // Out to the corner (the image is 1024 × 683).
        let corner = (512.0f64.hypot(341.5) / tp[0]).atan();
        for s in 0..=20 {
            let theta = corner * f64::from(s) / 20.0;
            let (a, b) = (radius(fp, theta), radius(tp, theta));
            // Within a pixel over the image's inner 80 %, two at the corners (fewest points).
            let bound = if s <= 16 { 1.0 } else { 2.0 };
            assert!(
                (a - b).abs() < bound,
                "θ {theta}: {a} px vs {b} px ({fp:?})"
            );
        }
    }
    let est: Vec<Camera> = found.iter().map(|c| c.camera.unwrap()).collect();
    let gt: Vec<Camera> = truth.iter().map(|c| c.camera.unwrap()).collect();
    let (rot, _) = worst_pair_errors(&est, &gt);
    assert!(rot < 1.0, "worst pair rotation error {rot}°");
}

/// The bundle adjustment's second opinion on the focal (`mapper.focal_rival`, off by default):
/// with every other start let in as a rival, the fountain's right focal keeps its map (the
/// rival's error is not lower); told to take any rival, the map takes it and says so.
#[test]
fn a_focal_rival_is_weighed_by_the_bundle_adjustment() {
    let (images, gt) = set("strecha_fountainP11");
    let dir = posediff_fixtures::temp_dir("geometric-focal-rival");
    let images_dir = images[0].parent().unwrap().to_path_buf();
    let run = |name: &str, rival: &str| -> (serde_json::Value, Vec<Camera>) {
        let out = dir.join(name);
        posediff(
            [
                OsString::from("estimate"),
                OsString::from(&images_dir),
                OsString::from("--out"),
                OsString::from(&out),
                OsString::from("--quiet"),
                OsString::from("--no-view"),
                OsString::from("--set"),
                OsString::from(format!("mapper.focal_rival={rival}")),
            ],
            true,
        );
        let run: serde_json::Value =
            serde_json::from_str(&std::fs::read_to_string(out.join("run.json")).unwrap()).unwrap();
        let cameras = read_cameras_json(&out.join("cameras.json")).unwrap();
        (run, cameras.into_iter().map(|c| c.camera).collect())
    };
    let truth = gt[0].intrinsics.fx();
    let (kept, cameras) = run(
        "kept",
        r#"{"max_cost_ratio": 10, "min_focal_ratio": 1.01, "max_rms_ratio": 0.8}"#,
    );
    let r = &kept["report"]["mapper"]["focal_rival"];
    assert_eq!(r["switched"], false, "{r}");
    let (winner, rival) = (
        r["winner_rms_px"].as_f64().unwrap(),
        r["rival_rms_px"].as_f64().unwrap(),
    );
    assert!(winner < 1.0 && rival >= 0.8 * winner, "{r}");
    let focal = cameras[0].intrinsics.fx();
    assert!((focal / truth - 1.0).abs() < 0.01, "{focal} vs {truth}");
    let (taken, _) = run(
        "taken",
        r#"{"max_cost_ratio": 10, "min_focal_ratio": 1.01, "max_rms_ratio": 1000}"#,
    );
    let r = &taken["report"]["mapper"]["focal_rival"];
    assert_eq!(r["switched"], true, "{r}");
    let phi = taken["report"]["mapper"]["focal_factor_initial"]
        .as_f64()
        .unwrap();
    assert!(phi.is_finite());
    std::fs::remove_dir_all(&dir).unwrap();
}
