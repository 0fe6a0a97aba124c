//! Every writer read back (round trips on real cameras), plus hand-checked values that would
//! catch a transpose, a sign flip, camera-to-world vs world-to-camera, or the half-pixel shift of
//! COLMAP/nerfstudio pixel centres.

// Test helpers outside #[test] functions unwrap too: a failure is the test failing.
#![allow(clippy::unwrap_used)]

use nalgebra::{Matrix3, Point3, Vector3};
use posediff::export::{
    NamedCamera, NerfstudioTransforms, Pytorch3dRecord, read_cameras_json, read_colmap_text,
    read_nerfstudio, write_cameras_json, write_colmap_text, write_nerfstudio, write_pytorch3d,
};
use posediff_fixtures::shared_path;
use posediff_geometry::{Camera, CenterCrop, ImageSize, Intrinsics, Pose, Quaternion};

fn temp_dir(tag: &str) -> std::path::PathBuf {
    let d = std::env::temp_dir().join(format!("posediff-export-{tag}-{}", std::process::id()));
    std::fs::create_dir_all(&d).unwrap();
    d
}

fn apple() -> (Vec<NamedCamera>, serde_json::Value) {
    let path = shared_path("data/co3d_apple_posediffusion/cameras.json");
    let raw: serde_json::Value =
        serde_json::from_str(&std::fs::read_to_string(&path).unwrap()).unwrap();
    (read_cameras_json(&path).unwrap(), raw)
}

fn assert_same(a: &[NamedCamera], b: &[NamedCamera]) {
    assert_eq!(a.len(), b.len());
    for (x, y) in a.iter().zip(b) {
        assert_eq!(x.image, y.image);
        assert_eq!(x.camera.image_size, y.camera.image_size);
        assert!(
            (x.camera.intrinsics.matrix() - y.camera.intrinsics.matrix()).norm() < 1e-9,
            "{}",
            x.image
        );
        assert!(
            (x.camera.cam_from_world.rotation - y.camera.cam_from_world.rotation).norm() < 1e-9,
            "{}",
            x.image
        );
        assert!(
            (x.camera.cam_from_world.translation - y.camera.cam_from_world.translation).norm()
                < 1e-9,
            "{}",
            x.image
        );
    }
}

#[test]
fn every_format_round_trips_real_cameras() {
    let (cams, _) = apple();
    let dir = temp_dir("roundtrip");
    write_cameras_json(&dir.join("cameras.json"), &cams).unwrap();
    assert_same(
        &cams,
        &read_cameras_json(&dir.join("cameras.json")).unwrap(),
    );
    write_colmap_text(&dir, &cams).unwrap();
    assert_same(&cams, &read_colmap_text(&dir).unwrap());
    write_nerfstudio(&dir.join("transforms.json"), &cams).unwrap();
    assert_same(
        &cams,
        &read_nerfstudio(&dir.join("transforms.json")).unwrap(),
    );
    std::fs::remove_dir_all(&dir).unwrap();
}

#[test]
fn hand_checked_colmap_and_nerfstudio_values() {
    // A camera at C = (1, 2, −5), turned about world y so that it looks along world +x,
    // principal point at the geometric centre of a 640×480 image in OpenCV pixels.
    let h = std::f64::consts::FRAC_1_SQRT_2;
    let r = Quaternion::new(h, 0.0, h, 0.0)
        .to_rotation_matrix()
        .unwrap()
        .transpose();
    let c = Vector3::new(1.0, 2.0, -5.0);
    let cam = Camera::new(
        Intrinsics::new(500.0, 510.0, 319.5, 239.5).unwrap(),
        Pose::new(r, -(r * c)),
        ImageSize::new(640, 480).unwrap(),
    );
    let axis = cam.optical_axis();
    assert!(
        (axis - Vector3::new(1.0, 0.0, 0.0)).norm() < 1e-12,
        "{axis}"
    );
    let named = [NamedCamera {
        image: "images/a b.jpg".into(),
        camera: cam,
    }];
    let dir = temp_dir("hand");
    write_colmap_text(&dir, &named).unwrap();
    let cams_txt = std::fs::read_to_string(dir.join("cameras.txt")).unwrap();
    assert!(
        cams_txt
            .lines()
            .any(|l| l == "1 PINHOLE 640 480 500 510 320 240"),
        "{cams_txt}"
    );
    let imgs_txt = std::fs::read_to_string(dir.join("images.txt")).unwrap();
    let line = imgs_txt.lines().find(|l| l.starts_with("1 ")).unwrap();
    let v: Vec<f64> = line
        .split_whitespace()
        .skip(1)
        .take(7)
        .map(|x| x.parse().unwrap())
        .collect();
    // World-to-camera: the quaternion of R (= a −90° turn about y), t = −R C.
    let q = Quaternion::new(v[0], v[1], v[2], v[3])
        .to_rotation_matrix()
        .unwrap();
    assert!((q - r).norm() < 1e-12);
    assert!(v[2] < 0.0 && v[0] > 0.0, "qvec {v:?}");
    assert!((Vector3::new(v[4], v[5], v[6]) - (-(r * c))).norm() < 1e-12);
    assert!(line.ends_with(" 1 images/a b.jpg"));

    write_nerfstudio(&dir.join("transforms.json"), &named).unwrap();
    let t: NerfstudioTransforms =
        serde_json::from_str(&std::fs::read_to_string(dir.join("transforms.json")).unwrap())
            .unwrap();
    let f = &t.frames[0];
    let m = f.transform_matrix;
    // Camera-to-world: the last column is the camera centre; OpenGL looks along −z.
    assert!((Vector3::new(m[0][3], m[1][3], m[2][3]) - c).norm() < 1e-12);
    let back = Vector3::new(m[0][2], m[1][2], m[2][2]);
    assert!(
        (back + axis).norm() < 1e-12,
        "−z column must be the optical axis"
    );
    let up = Vector3::new(m[0][1], m[1][1], m[2][1]);
    assert!(
        (up + r.row(1).transpose()).norm() < 1e-12,
        "y is up: minus OpenCV's down axis"
    );
    assert_eq!(
        (f.cx, f.cy, f.fl_x, f.fl_y, f.w, f.h),
        (320.0, 240.0, 500.0, 510.0, 640, 480)
    );
    // A world point projects to the same pixel through the parsed nerfstudio camera.
    let x = Point3::new(4.0, 2.5, -4.5);
    let parsed = read_nerfstudio(&dir.join("transforms.json")).unwrap();
    assert!((parsed[0].camera.project(&x).unwrap() - cam.project(&x).unwrap()).norm() < 1e-9);
    std::fs::remove_dir_all(&dir).unwrap();
}

#[test]
fn pytorch3d_json_matches_the_official_conventions() {
    // The apple set stores each camera's PyTorch3D R, T and NDC focal (of the original image,
    // whose NDC unit, half the shorter side, is the crop's too).
    let (cams, raw) = apple();
    let dir = temp_dir("p3d");
    let with_crops: Vec<(NamedCamera, CenterCrop)> = cams
        .iter()
        .map(|c| (c.clone(), CenterCrop::official(c.camera.image_size, 224)))
        .collect();
    write_pytorch3d(&dir.join("pytorch3d.json"), &with_crops).unwrap();
    let records: Vec<Pytorch3dRecord> =
        serde_json::from_str(&std::fs::read_to_string(dir.join("pytorch3d.json")).unwrap())
            .unwrap();
    for (rec, stored) in records.iter().zip(raw.as_array().unwrap()) {
        let p = &stored["pytorch3d"];
        let r_expected = Matrix3::from_fn(|i, j| p["R"][i][j].as_f64().unwrap());
        let r = Matrix3::from_fn(|i, j| rec.r[i][j]);
        assert!((r - r_expected).norm() < 1e-6, "{}", rec.image);
        let t_expected = Vector3::from_fn(|i, _| p["T"][i].as_f64().unwrap());
        assert!(
            (Vector3::from(rec.t) - t_expected).norm() < 1e-5,
            "{}",
            rec.image
        );
        // fx in NDC of the short side; the stored value is fx's (the set has fx ≠ fy slightly).
        assert!(
            (rec.focal_length[0] - p["focal_ndc"][0].as_f64().unwrap()).abs() < 1e-5,
            "{}",
            rec.image
        );
        assert!(rec.principal_point[0].abs() < 0.01 && rec.principal_point[1].abs() < 0.01);
    }
    std::fs::remove_dir_all(&dir).unwrap();
}
