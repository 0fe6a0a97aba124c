//! Every writer read back (round trips on real cameras), plus hand-checked values that would
//! catch a transpose, a sign flip, camera-to-world vs world-to-camera, or the half-pixel shift of
//! COLMAP/nerfstudio pixel centres.

// Test helpers outside #[test] functions unwrap too: a failure is the test failing.
#![allow(clippy::unwrap_used)]

use nalgebra::{Matrix3, Point3, Vector3};
use posediff::io::colmap::{ColmapFormat, ColmapModel};
use posediff::io::export::{
    ImageCamera, NamedCamera, NerfstudioCamera, NerfstudioTransforms, Pytorch3dRecord,
    nerfstudio_applied_transform, read_cameras_json, read_cameras_json_partial,
    read_colmap_cameras, read_nerfstudio, read_ply, write_cameras_json, write_cameras_json_partial,
    write_colmap, write_nerfstudio, write_ply, write_pytorch3d,
};
use posediff::reconstruction::Reconstruction;
use posediff_fixtures::shared_path;
use posediff_geometry::lens::{CameraModel, LensCamera};
use posediff_geometry::{Camera, ImageSize, Intrinsics, Pose, Quaternion};
use posediff_sfm::points::PointOptions;

fn apple() -> (Vec<NamedCamera>, serde_json::Value) {
    let path = shared_path("data/co3d_apple_posediffusion/cameras.json");
    let raw: serde_json::Value =
        serde_json::from_str(&std::fs::read_to_string(&path).unwrap()).unwrap();
    (read_cameras_json(&path).unwrap(), raw)
}

fn image_cameras(cams: &[NamedCamera]) -> Vec<ImageCamera> {
    cams.iter()
        .map(|c| ImageCamera {
            image: c.image.clone(),
            size: c.camera.image_size,
            camera: Some(c.camera),
            lens: None,
        })
        .collect()
}

fn reconstruction_of(cams: &[NamedCamera]) -> Reconstruction {
    Reconstruction::from_cameras(image_cameras(cams))
}

fn nerf_cameras(cams: &[NamedCamera]) -> Vec<NerfstudioCamera> {
    cams.iter()
        .enumerate()
        .map(|(i, c)| NerfstudioCamera {
            camera: c.camera,
            lens: None,
            file_path: c.image.clone(),
            colmap_id: Some(i as u32 + 1),
        })
        .collect()
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
    let dir = posediff_fixtures::temp_dir("export-roundtrip");
    write_cameras_json(&dir.join("cameras.json"), &cams).unwrap();
    assert_same(
        &cams,
        &read_cameras_json(&dir.join("cameras.json")).unwrap(),
    );
    for (format, sub) in [(ColmapFormat::Text, "text"), (ColmapFormat::Binary, "bin")] {
        write_colmap(&dir.join(sub), &reconstruction_of(&cams), format).unwrap();
        assert_same(&cams, &read_colmap_cameras(&dir.join(sub)).unwrap());
    }
    write_nerfstudio(&dir.join("transforms.json"), &nerf_cameras(&cams), None).unwrap();
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
        Pose::from_rotation_centre(r, c),
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
    let dir = posediff_fixtures::temp_dir("export-hand");
    write_colmap(&dir, &reconstruction_of(&named), ColmapFormat::Text).unwrap();
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

    write_nerfstudio(
        &dir.join("transforms.json"),
        &nerf_cameras(&named),
        Some("sparse_pc.ply"),
    )
    .unwrap();
    let t: NerfstudioTransforms =
        serde_json::from_str(&std::fs::read_to_string(dir.join("transforms.json")).unwrap())
            .unwrap();
    let f = &t.frames[0];
    let m = f.transform_matrix;
    // nerfstudio's world is COLMAP's with y ← z, z ← −y (its converter's applied_transform).
    let world = |v: Vector3<f64>| Vector3::new(v.x, v.z, -v.y);
    assert_eq!(
        t.applied_transform,
        [
            [1.0, 0.0, 0.0, 0.0],
            [0.0, 0.0, 1.0, 0.0],
            [0.0, -1.0, 0.0, 0.0]
        ]
    );
    // Camera-to-world: the last column is the camera centre; OpenGL looks along −z.
    assert!((Vector3::new(m[0][3], m[1][3], m[2][3]) - world(c)).norm() < 1e-12);
    let back = Vector3::new(m[0][2], m[1][2], m[2][2]);
    assert!(
        (back + world(axis)).norm() < 1e-12,
        "−z column must be the optical axis"
    );
    let up = Vector3::new(m[0][1], m[1][1], m[2][1]);
    assert!(
        (up + world(r.row(1).transpose())).norm() < 1e-12,
        "y is up: minus OpenCV's down axis"
    );
    // One camera: its intrinsics are shared, at the top level.
    let k = t.intrinsics.unwrap();
    assert!(f.intrinsics.is_none());
    assert_eq!(
        (k.cx, k.cy, k.fl_x, k.fl_y, k.w, k.h),
        (320.0, 240.0, 500.0, 510.0, 640, 480)
    );
    assert_eq!(t.ply_file_path.as_deref(), Some("sparse_pc.ply"));
    assert_eq!(f.colmap_im_id, Some(1));
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
    let dir = posediff_fixtures::temp_dir("export-p3d");
    write_pytorch3d(&dir.join("pytorch3d.json"), &image_cameras(&cams)).unwrap();
    let records: Vec<Pytorch3dRecord> =
        serde_json::from_str(&std::fs::read_to_string(dir.join("pytorch3d.json")).unwrap())
            .unwrap();
    for (rec, stored) in records.iter().zip(raw.as_array().unwrap()) {
        let p = &stored["pytorch3d"];
        let r_expected = Matrix3::from_fn(|i, j| p["R"][i][j].as_f64().unwrap());
        let r = Matrix3::from_fn(|i, j| rec.camera.r[i][j]);
        assert!((r - r_expected).norm() < 1e-6, "{}", rec.image);
        let t_expected = Vector3::from_fn(|i, _| p["T"][i].as_f64().unwrap());
        assert!(
            (Vector3::from(rec.camera.t) - t_expected).norm() < 1e-5,
            "{}",
            rec.image
        );
        // fx in NDC of the short side; the stored value is fx's (the set has fx ≠ fy slightly).
        assert!(
            (rec.camera.focal_length[0] - p["focal_ndc"][0].as_f64().unwrap()).abs() < 1e-5,
            "{}",
            rec.image
        );
        assert!(
            rec.camera.principal_point[0].abs() < 0.01
                && rec.camera.principal_point[1].abs() < 0.01
        );
    }
    std::fs::remove_dir_all(&dir).unwrap();
}

/// Apple's cameras and points on a sphere inside them, seen by every camera: matches between
/// consecutive frames with keypoint ids = point ids.
fn apple_scene() -> (
    Vec<NamedCamera>,
    Vec<Point3<f64>>,
    Vec<posediff_geometry::PairMatches>,
) {
    let (cams, _) = apple();
    let centre = cams
        .iter()
        .map(|c| c.camera.center().coords)
        .sum::<Vector3<f64>>()
        / cams.len() as f64;
    let radius = cams
        .iter()
        .map(|c| (c.camera.center().coords - centre).norm())
        .fold(0.0, f64::max);
    let points: Vec<Point3<f64>> = (0..200)
        .map(|k| {
            let (a, b) = (k as f64 * 2.4, (k as f64 / 200.0) * 2.0 - 1.0);
            let s = (1.0 - b * b).sqrt();
            Point3::from(centre + 0.1 * radius * Vector3::new(s * a.cos(), s * a.sin(), b))
        })
        .collect();
    let pairs = (0..cams.len() - 1)
        .map(|i| {
            let project = |j: usize| -> Vec<[f64; 2]> {
                points
                    .iter()
                    .map(|p| {
                        let q = cams[j].camera.project(p).unwrap();
                        [q.x, q.y]
                    })
                    .collect()
            };
            posediff_geometry::PairMatches {
                first: i,
                second: i + 1,
                kp1: project(i),
                kp2: project(i + 1),
                idx1: (0..points.len() as u32).collect(),
                idx2: (0..points.len() as u32).collect(),
            }
        })
        .collect();
    (cams, points, pairs)
}

#[test]
fn colmap_models_with_points_round_trip_in_text_and_binary() {
    let (cams, truth, pairs) = apple_scene();
    let images = image_cameras(&cams);
    let (recon, report) =
        Reconstruction::triangulate(images, None, &pairs, &PointOptions::default()).unwrap();
    assert_eq!(report.points, truth.len());
    assert_eq!(recon.points.len(), truth.len());
    for (p, t) in recon.points.iter().zip(&truth) {
        assert!((p.xyz - t.coords).norm() < 1e-6 * (1.0 + t.coords.norm()));
        assert_eq!(p.track.len(), cams.len());
    }
    let model = ColmapModel::from_reconstruction(&recon).unwrap();
    // Every keypoint of every image observes its point.
    for im in &model.images {
        assert_eq!(im.points2d.len(), truth.len());
        assert!(im.points2d.iter().all(|p| p.1.is_some()));
    }
    let distinct: std::collections::HashSet<String> = cams
        .iter()
        .map(|c| format!("{:?} {:?}", c.camera.intrinsics, c.camera.image_size))
        .collect();
    assert_eq!(model.cameras.len(), distinct.len());
    let dir = posediff_fixtures::temp_dir("export-points");
    for (format, sub) in [(ColmapFormat::Text, "text"), (ColmapFormat::Binary, "bin")] {
        model.write(&dir.join(sub), format).unwrap();
        let back = ColmapModel::read(&dir.join(sub)).unwrap();
        assert_eq!(back, model, "{sub}");
        let back = back.to_reconstruction(&dir.join(sub)).unwrap();
        assert_eq!(back.points.len(), recon.points.len());
        for (a, b) in back.points.iter().zip(&recon.points) {
            assert_eq!(a.xyz, b.xyz);
            assert_eq!(a.track, b.track);
        }
        for (a, b) in back.images.iter().zip(&recon.images) {
            for (x, y) in a.keypoints.iter().zip(&b.keypoints) {
                assert!((x.xy[0] - y.xy[0]).abs() < 1e-9 && (x.xy[1] - y.xy[1]).abs() < 1e-9);
                assert_eq!(x.point, y.point);
            }
        }
    }
    // The recorded errors are what the written cameras and 2-D points give (COLMAP pixels).
    let recomputed = model.recomputed_mean_error(&dir).unwrap().unwrap();
    assert!((recomputed - recon.mean_error_px().unwrap()).abs() < 1e-6);
    assert!(recomputed < 1e-4, "exact projections: {recomputed}");
    std::fs::remove_dir_all(&dir).unwrap();
}

#[test]
fn one_colmap_camera_per_distinct_intrinsics() {
    let (cams, _) = apple();
    let mut same: Vec<NamedCamera> = cams.clone();
    let first = same[0].camera;
    for c in &mut same {
        c.camera.intrinsics = first.intrinsics;
        c.camera.image_size = first.image_size;
    }
    same[3].camera.intrinsics =
        Intrinsics::new(first.intrinsics.fx() * 1.1, first.intrinsics.fy(), 1.0, 2.0).unwrap();
    let model = ColmapModel::from_reconstruction(&reconstruction_of(&same)).unwrap();
    assert_eq!(model.cameras.len(), 2);
    assert!(
        model
            .images
            .iter()
            .enumerate()
            .all(|(k, im)| im.camera_id == if k == 3 { 2 } else { 1 })
    );
}

#[test]
fn broken_binary_models_are_errors_that_name_the_file() {
    let (cams, _) = apple();
    let dir = posediff_fixtures::temp_dir("export-broken-bin");
    write_colmap(&dir, &reconstruction_of(&cams), ColmapFormat::Binary).unwrap();
    let images = dir.join("images.bin");
    let bytes = std::fs::read(&images).unwrap();
    // Truncated.
    std::fs::write(&images, &bytes[..bytes.len() - 5]).unwrap();
    let e = ColmapModel::read(&dir).unwrap_err().to_string();
    assert!(e.contains("images.bin") && e.contains("ends early"), "{e}");
    // A count no file could hold is refused before anything is allocated.
    let mut huge = bytes.clone();
    huge[..8].copy_from_slice(&u64::MAX.to_le_bytes());
    std::fs::write(&images, &huge).unwrap();
    let e = ColmapModel::read(&dir).unwrap_err().to_string();
    assert!(e.contains("cannot fit"), "{e}");
    // Trailing bytes.
    let mut long = bytes;
    long.extend_from_slice(&[0, 1, 2]);
    std::fs::write(&images, &long).unwrap();
    let e = ColmapModel::read(&dir).unwrap_err().to_string();
    assert!(e.contains("3 bytes after"), "{e}");
    std::fs::remove_dir_all(&dir).unwrap();
    // No model at all.
    let e = ColmapModel::read(&posediff_fixtures::temp_dir("export-empty-model"))
        .unwrap_err()
        .to_string();
    assert!(e.contains("no COLMAP model"), "{e}");
}

#[test]
fn ply_points_are_in_the_transformed_world_with_their_colours() {
    let (cams, _, pairs) = apple_scene();
    let images = image_cameras(&cams);
    let files: Vec<std::path::PathBuf> = cams
        .iter()
        .map(|c| shared_path("data/co3d_apple_posediffusion").join(&c.image))
        .collect();
    let (recon, _) =
        Reconstruction::triangulate(images, Some(&files), &pairs, &PointOptions::default())
            .unwrap();
    // Colours come from the images: not all the grey placeholder.
    assert!(recon.points.iter().any(|p| p.rgb != [128, 128, 128]));
    let dir = posediff_fixtures::temp_dir("export-ply");
    let path = dir.join("sparse_pc.ply");
    write_ply(&path, &recon.points, &nerfstudio_applied_transform()).unwrap();
    let back = read_ply(&path).unwrap();
    assert_eq!(back.len(), recon.points.len());
    for ((xyz, rgb), p) in back.iter().zip(&recon.points) {
        let expected = [p.xyz.x, p.xyz.z, -p.xyz.y];
        for k in 0..3 {
            assert!((f64::from(xyz[k]) - expected[k]).abs() < 1e-5 * (1.0 + expected[k].abs()));
        }
        assert_eq!(*rgb, p.rgb);
    }
    std::fs::remove_dir_all(&dir).unwrap();
}

/// An OPENCV lens (a wide-angle phone's `k1 k2 p1 p2`) around each apple camera.
fn wide_angle(c: &Camera) -> LensCamera {
    let k = &c.intrinsics;
    LensCamera::new(
        CameraModel::OpenCv,
        vec![k.fx(), k.fy(), k.cx(), k.cy(), -0.1, 0.01, 1e-3, -5e-4],
    )
    .unwrap()
}

/// A lens reaches every format once: COLMAP's 2-D points are where the lens images each point
/// (distortion applied, and only once), its recomputed errors are the photos', the model reads
/// back with the lens and the undistorted keypoints, and cameras.json and transforms.json carry
/// the coefficients.
#[test]
fn a_lens_reaches_every_format_and_comes_back() {
    let (cams, truth, pairs) = apple_scene();
    let mut images = image_cameras(&cams);
    for (im, c) in images.iter_mut().zip(&cams) {
        im.lens = Some(wide_angle(&c.camera));
    }
    let (recon, _) =
        Reconstruction::triangulate(images.clone(), None, &pairs, &PointOptions::default())
            .unwrap();
    assert_eq!(recon.points.len(), truth.len());
    assert!(recon.mean_error_px().unwrap() < 1e-4);
    let model = ColmapModel::from_reconstruction(&recon).unwrap();
    let mut moved = 0.0_f64;
    for (im, c) in model.images.iter().zip(&cams) {
        let lens = wide_angle(&c.camera);
        for (xy, id) in &im.points2d {
            let x = c
                .camera
                .cam_from_world
                .transform_point(&truth[id.unwrap() as usize - 1]);
            let q = lens.project(&x.coords).unwrap();
            let pinhole = c.camera.project(&truth[id.unwrap() as usize - 1]).unwrap();
            assert!(
                (xy[0] - 0.5 - q.x).abs() < 1e-6 && (xy[1] - 0.5 - q.y).abs() < 1e-6,
                "{xy:?} vs {q:?}"
            );
            moved = moved.max((q - pinhole.coords).norm());
        }
    }
    assert!(moved > 5.0, "the lens moves points by {moved} px at most");
    for cam in &model.cameras {
        assert_eq!(cam.model, "OPENCV");
        assert_eq!(&cam.params[4..], &[-0.1, 0.01, 1e-3, -5e-4]);
    }
    let dir = posediff_fixtures::temp_dir("export-lens");
    model
        .write(&dir.join("sparse"), ColmapFormat::Binary)
        .unwrap();
    let read = ColmapModel::read(&dir.join("sparse")).unwrap();
    assert!(read.recomputed_mean_error(&dir).unwrap().unwrap() < 1e-4);
    let back = read.to_reconstruction(&dir).unwrap();
    for (a, b) in back.images.iter().zip(&recon.images) {
        let (la, lb) = (
            a.camera.lens.as_ref().unwrap(),
            b.camera.lens.as_ref().unwrap(),
        );
        assert_eq!(la.model(), lb.model());
        for (x, y) in la.params().iter().zip(lb.params()) {
            assert!((x - y).abs() < 1e-9);
        }
        for (x, y) in a.keypoints.iter().zip(&b.keypoints) {
            assert!((x.xy[0] - y.xy[0]).abs() < 1e-6 && (x.xy[1] - y.xy[1]).abs() < 1e-6);
        }
    }
    // cameras.json: model and params, read back as the same lens.
    write_cameras_json_partial(&dir.join("cameras.json"), &images).unwrap();
    let json = read_cameras_json_partial(&dir.join("cameras.json")).unwrap();
    for (a, b) in json.iter().zip(&images) {
        assert_eq!(a.lens, b.lens);
    }
    // transforms.json: the apple's focals differ per frame, so the coefficients are per frame
    // and the top level has none (nerfstudio then reads each frame's).
    let nerf: Vec<NerfstudioCamera> = nerf_cameras(&cams)
        .into_iter()
        .zip(&images)
        .map(|(n, im)| NerfstudioCamera {
            lens: im.lens.clone(),
            ..n
        })
        .collect();
    write_nerfstudio(&dir.join("transforms.json"), &nerf, None).unwrap();
    let t: serde_json::Value =
        serde_json::from_str(&std::fs::read_to_string(dir.join("transforms.json")).unwrap())
            .unwrap();
    assert!(t.get("k1").is_none(), "{}", t["k1"]);
    for f in t["frames"].as_array().unwrap() {
        assert_eq!(
            [&f["k1"], &f["k2"], &f["p1"], &f["p2"]].map(|v| v.as_f64().unwrap()),
            [-0.1, 0.01, 1e-3, -5e-4]
        );
    }
    std::fs::remove_dir_all(&dir).unwrap();
}
