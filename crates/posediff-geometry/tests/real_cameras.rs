//! The ground-truth cameras of the real data sets in `../shared/data` through the geometry
//! crate: they parse, the PyTorch3D copies stored beside them convert to the same OpenCV
//! cameras, and hand-checkable correspondences (projections of points the cameras look at) have
//! sub-pixel Sampson errors while a 1-px shift across the epipolar line does not.

// Test helpers outside #[test] functions unwrap too: a failure is the test failing.
#![allow(clippy::unwrap_used)]

use nalgebra::{Point2, Vector2, Vector3};
use posediff_fixtures::shared_path;
use posediff_geometry::camera_json::CameraRecord;
use posediff_geometry::normalize::optical_axis_intersection;
use posediff_geometry::pytorch3d::NdcIntrinsics;
use posediff_geometry::{
    Camera, Pytorch3dCamera, fundamental_from_cameras, sampson_error,
    symmetric_epipolar_distance_sq,
};

const DATASETS: [&str; 3] = [
    "co3d_apple_posediffusion",
    "middlebury_templeSR",
    "strecha_fountainP11",
];

fn load(dataset: &str) -> (Vec<CameraRecord>, serde_json::Value) {
    let path = shared_path(&format!("data/{dataset}/cameras.json"));
    let text = std::fs::read_to_string(&path).unwrap();
    (
        serde_json::from_str(&text).unwrap(),
        serde_json::from_str(&text).unwrap(),
    )
}

#[test]
fn ground_truth_cameras_parse_and_round_trip() {
    for dataset in DATASETS {
        let (records, _) = load(dataset);
        assert!(records.len() >= 10, "{dataset}");
        for r in &records {
            let cam = r
                .to_camera()
                .unwrap_or_else(|e| panic!("{dataset} {}: {e}", r.image));
            let again = CameraRecord::from_camera(r.image.clone(), &cam);
            assert_eq!(&again, r);
        }
    }
}

#[test]
fn stored_pytorch3d_cameras_convert_to_the_opencv_ones() {
    // The apple set stores its PyTorch3D (row-vector, +X left, +Y up) cameras beside the
    // OpenCV ones: an independent check of the transpose and the sign flips on real data.
    let (records, raw) = load("co3d_apple_posediffusion");
    for (r, value) in records.iter().zip(raw.as_array().unwrap()) {
        let p3d = &value["pytorch3d"];
        let m = |v: &serde_json::Value| -> Vec<f64> {
            v.as_array()
                .unwrap()
                .iter()
                .flat_map(|row| row.as_array().unwrap().iter().map(|x| x.as_f64().unwrap()))
                .collect()
        };
        let t: Vec<f64> = p3d["T"]
            .as_array()
            .unwrap()
            .iter()
            .map(|x| x.as_f64().unwrap())
            .collect();
        let cam = r.to_camera().unwrap();
        let converted = Pytorch3dCamera {
            r: nalgebra::Matrix3::from_row_slice(&m(&p3d["R"])),
            t: Vector3::from_row_slice(&t),
            intrinsics: NdcIntrinsics {
                focal: Vector2::new(1.0, 1.0),
                principal_point: Vector2::zeros(),
            },
        }
        .opencv_pose();
        // Stored in float32: agreement to ~1e-6.
        assert!(
            (converted.rotation - cam.cam_from_world.rotation).norm() < 1e-6,
            "{}",
            r.image
        );
        assert!(
            (converted.translation - cam.cam_from_world.translation).norm() < 1e-5,
            "{}",
            r.image
        );
    }
}

/// Distance from `p` to the line `l = (a, b, c)`, `a x + b y + c = 0`.
fn point_line_distance(l: &Vector3<f64>, p: &Point2<f64>) -> f64 {
    (l.x * p.x + l.y * p.y + l.z).abs() / (l.x * l.x + l.y * l.y).sqrt()
}

#[test]
fn ground_truth_cameras_give_sub_pixel_sampson_errors() {
    for dataset in DATASETS {
        let (records, _) = load(dataset);
        let cams: Vec<Camera> = records.iter().map(|r| r.to_camera().unwrap()).collect();
        let target = optical_axis_intersection(&cams).unwrap().point;
        let last = cams.len() - 1;
        for (i, j) in [(0, 1), (0, last), (1, 2)] {
            let (c1, c2) = (&cams[i], &cams[j]);
            let f = fundamental_from_cameras(c1, c2);
            let radius = 0.05 * (c1.center() - target).norm();
            let mut checked = 0;
            for o in [
                [0.0, 0.0, 0.0],
                [1.0, 0.0, 0.0],
                [0.0, -1.0, 0.0],
                [0.0, 0.0, 1.0],
                [-0.6, 0.6, -0.5],
            ] {
                let x = target + Vector3::new(o[0], o[1], o[2]) * radius;
                let (Some(p1), Some(p2)) = (c1.project(&x), c2.project(&x)) else {
                    continue;
                };
                let s = sampson_error(&f, &p1, &p2).unwrap();
                assert!(s < 1e-12, "{dataset} ({i},{j}): Sampson {s}");
                // One pixel across the epipolar line in image 2.
                let l2 = f * p1.to_homogeneous();
                let n = Vector2::new(l2.x, l2.y).normalize();
                let moved = p2 + n;
                assert!((point_line_distance(&l2, &moved) - 1.0).abs() < 1e-9);
                let s = sampson_error(&f, &p1, &moved).unwrap();
                assert!(
                    s > 0.05 && s <= 1.0 + 1e-9,
                    "{dataset} ({i},{j}): moved Sampson {s}"
                );
                let d = symmetric_epipolar_distance_sq(&f, &p1, &moved).unwrap();
                assert!(d >= 1.0 - 1e-9, "{dataset} ({i},{j}): symmetric {d}");
                checked += 1;
            }
            assert!(
                checked >= 4,
                "{dataset} ({i},{j}): only {checked} points in front of both cameras"
            );
        }
    }
}
