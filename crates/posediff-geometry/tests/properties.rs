//! Property tests (seeded): round trips and invariants that must hold for any input.

// Test helpers outside #[test] functions unwrap too: a failure is the test failing.
#![allow(clippy::unwrap_used)]

use nalgebra::{Matrix3, Point2, Point3, Vector2, Vector3};
use posediff_geometry::{
    Camera, ImageSize, Intrinsics, Pose, PoseEncoding, Pytorch3dCamera, Quaternion, QuaternionSign,
    Sim3, fundamental_from_cameras, sampson_error, umeyama, umeyama_with_scale,
};
use proptest::prelude::*;
use proptest::test_runner::{Config, RngSeed};

fn config() -> Config {
    Config {
        cases: 256,
        rng_seed: RngSeed::Fixed(0x9d_2023),
        failure_persistence: None,
        ..Config::default()
    }
}

prop_compose! {
    /// A non-unit quaternion away from zero.
    fn quaternion()(w in -2.0..2.0f64, x in -2.0..2.0f64, y in -2.0..2.0f64, z in -2.0..2.0f64)
        -> Quaternion {
        let q = Quaternion::new(w, x, y, z);
        if q.norm_squared() < 1e-2 { Quaternion::new(w + 1.0, x, y, z) } else { q }
    }
}

prop_compose! {
    fn rotation()(q in quaternion()) -> Matrix3<f64> {
        q.to_rotation_matrix().unwrap()
    }
}

prop_compose! {
    fn vector(scale: f64)(x in -1.0..1.0f64, y in -1.0..1.0f64, z in -1.0..1.0f64) -> Vector3<f64> {
        Vector3::new(x, y, z) * scale
    }
}

prop_compose! {
    fn image_size()(w in 16u32..2000, h in 16u32..2000) -> ImageSize {
        ImageSize::new(w, h).unwrap()
    }
}

prop_compose! {
    /// A camera looking roughly at the origin from distance ~4.
    fn camera()(r in rotation(), jitter in vector(0.5), size in image_size(),
                f in 0.5..3.0f64, aspect in 0.9..1.1f64, pp in vector(0.05)) -> Camera {
        let t = Vector3::new(0.0, 0.0, 4.0) + jitter;
        let s = f64::from(size.min_side()) / 2.0;
        let k = Intrinsics::new(
            f * s,
            f * aspect * s,
            f64::from(size.width()) / 2.0 + pp.x * s,
            f64::from(size.height()) / 2.0 + pp.y * s,
        )
        .unwrap();
        Camera::new(k, Pose::new(r, t), size)
    }
}

proptest! {
    #![proptest_config(config())]

    #[test]
    fn quaternion_to_matrix_is_a_rotation_and_round_trips(q in quaternion()) {
        let m = q.to_rotation_matrix().unwrap();
        prop_assert!((m.transpose() * m - Matrix3::identity()).norm() < 1e-12);
        prop_assert!((m.determinant() - 1.0).abs() < 1e-12);
        for sign in [QuaternionSign::LargestComponentPositive, QuaternionSign::NonNegativeReal] {
            let back = Quaternion::from_rotation_matrix(&m, sign).unwrap();
            prop_assert!((back.norm_squared() - 1.0).abs() < 1e-12);
            // Same rotation; the quaternion is ±q / |q|.
            let n = q.norm_squared().sqrt();
            let dot: f64 = back.to_wxyz().iter().zip(q.to_wxyz()).map(|(a, b)| a * b / n).sum();
            prop_assert!((dot.abs() - 1.0).abs() < 1e-10);
            prop_assert!((back.to_rotation_matrix().unwrap() - m).norm() < 1e-12);
        }
        let std = Quaternion::from_rotation_matrix(&m, QuaternionSign::NonNegativeReal).unwrap();
        prop_assert!(std.w >= 0.0);
        let big = Quaternion::from_rotation_matrix(&m, QuaternionSign::LargestComponentPositive).unwrap();
        let largest = big.to_wxyz().into_iter().fold(0.0f64, |a, v| if v.abs() > a.abs() { v } else { a });
        prop_assert!(largest > 0.0);
    }

    #[test]
    fn opencv_pytorch3d_round_trip_at_any_image_size(cam in camera()) {
        let p3d = Pytorch3dCamera::from_opencv(&cam);
        let back = p3d.to_opencv(cam.image_size).unwrap();
        prop_assert!((back.cam_from_world.rotation - cam.cam_from_world.rotation).norm() < 1e-12);
        prop_assert!((back.cam_from_world.translation - cam.cam_from_world.translation).norm() < 1e-12);
        prop_assert!((back.intrinsics.matrix() - cam.intrinsics.matrix()).norm() < 1e-9);
        // Both describe the same projection of a point in front of the camera.
        let x = Point3::new(0.1, -0.2, 0.3);
        let px = cam.project(&x).unwrap();
        let x_view = p3d.r.transpose() * x.coords + p3d.t; // (X R + T)ᵀ
        let ndc = Vector2::new(
            p3d.intrinsics.focal.x * x_view.x / x_view.z + p3d.intrinsics.principal_point.x,
            p3d.intrinsics.focal.y * x_view.y / x_view.z + p3d.intrinsics.principal_point.y,
        );
        let s = f64::from(cam.image_size.min_side()) / 2.0;
        let expected = Point2::new(
            f64::from(cam.image_size.width()) / 2.0 - ndc.x * s,
            f64::from(cam.image_size.height()) / 2.0 - ndc.y * s,
        );
        prop_assert!((px - expected).norm() < 1e-8 * (1.0 + px.coords.norm()));
    }

    #[test]
    fn pose_encoding_round_trips_through_cameras(cam in camera()) {
        // The encoding stores no principal point: use the centred one.
        let size = cam.image_size;
        let mut p3d = Pytorch3dCamera::from_opencv(&cam);
        p3d.intrinsics.principal_point = Vector2::zeros();
        let cam = p3d.to_opencv(size).unwrap();
        let enc = PoseEncoding::from_camera(&cam, QuaternionSign::LargestComponentPositive).unwrap();
        let back = enc.to_camera(size).unwrap();
        prop_assert!((back.cam_from_world.rotation - cam.cam_from_world.rotation).norm() < 1e-12);
        prop_assert!((back.cam_from_world.translation - cam.cam_from_world.translation).norm() < 1e-12);
        prop_assert!((back.intrinsics.matrix() - cam.intrinsics.matrix()).norm() < 1e-8);
        // Decoding a scaled quaternion gives the same camera.
        let mut scaled = enc;
        for v in &mut scaled.0[3..7] { *v *= 3.7; }
        let again = scaled.to_camera(size).unwrap();
        prop_assert!((again.cam_from_world.rotation - back.cam_from_world.rotation).norm() < 1e-12);
    }

    #[test]
    fn umeyama_recovers_a_known_similarity(
        r in rotation(), t in vector(5.0), log_s in -2.0..2.0f64,
        pts in proptest::collection::vec(vector(3.0), 0..30),
    ) {
        let truth = Sim3 { rotation: r, translation: t, scale: log_s.exp() };
        // Three fixed non-collinear points keep the problem well posed.
        let src: Vec<Point3<f64>> = [Vector3::x(), Vector3::y() * 2.0, -Vector3::z()]
            .iter()
            .chain(&pts)
            .map(|v| Point3::from(*v))
            .collect();
        let dst: Vec<Point3<f64>> = src.iter().map(|p| truth.transform_point(p)).collect();
        let est = umeyama_with_scale(&src, &dst).unwrap();
        prop_assert!((est.rotation - r).norm() < 1e-9);
        prop_assert!((est.translation - t).norm() < 1e-9 * (1.0 + t.norm()));
        prop_assert!((est.scale - truth.scale).abs() < 1e-9 * truth.scale);
        let rigid = Sim3 { scale: 1.0, ..truth };
        let dst: Vec<Point3<f64>> = src.iter().map(|p| rigid.transform_point(p)).collect();
        let est = umeyama(&src, &dst).unwrap();
        prop_assert!((est.rotation - r).norm() < 1e-9);
        prop_assert!((est.translation - t).norm() < 1e-9 * (1.0 + t.norm()));
        prop_assert_eq!(est.scale, 1.0);
    }

    #[test]
    fn similarity_keeps_projections_and_epipolar_geometry(
        c1 in camera(), c2 in camera(), r in rotation(), t in vector(5.0), log_s in -1.0..1.0f64,
        x in vector(0.5),
    ) {
        let sim = Sim3 { rotation: r, translation: t, scale: log_s.exp() };
        let x = Point3::from(x);
        let moved = sim.transform_camera(&c1);
        let (Some(a), Some(b)) = (c1.project(&x), moved.project(&sim.transform_point(&x))) else {
            return Ok(());
        };
        prop_assert!((a - b).norm() < 1e-8 * (1.0 + a.coords.norm()));
        // F up to scale is invariant: the same match has zero Sampson error in both worlds.
        let f = fundamental_from_cameras(&c1, &c2);
        let f2 = fundamental_from_cameras(&moved, &sim.transform_camera(&c2));
        let cos = f.dot(&f2) / (f.norm() * f2.norm());
        prop_assert!((cos.abs() - 1.0).abs() < 1e-9);
    }

    #[test]
    fn fundamental_matrix_has_rank_two_and_vanishes_on_projections(c1 in camera(), c2 in camera(), x in vector(0.5)) {
        // x2ᵀ F x1 = 0 for the projections of any point (asymmetry: see the test below).
        let x = Point3::from(x);
        let (Some(p1), Some(p2)) = (c1.project(&x), c2.project(&x)) else { return Ok(()) };
        let f = fundamental_from_cameras(&c1, &c2);
        if (c1.center() - c2.center()).norm() < 0.1 { return Ok(()); }
        let s = sampson_error(&f, &p1, &p2).unwrap();
        prop_assert!(s < 1e-12, "sampson {}", s);
        let rank = f.svd(false, false).singular_values;
        prop_assert!(rank[2] <= 1e-9 * rank[0]);
    }
}

#[test]
fn transposed_fundamental_matrix_gives_large_errors() {
    // Two cameras side by side, the second also rotated: F ≠ ±Fᵀ.
    let size = ImageSize::new(640, 480).unwrap();
    let k = Intrinsics::new(500.0, 500.0, 320.0, 240.0).unwrap();
    let r = Quaternion::new(0.98, 0.05, 0.15, 0.02)
        .to_rotation_matrix()
        .unwrap();
    let c1 = Camera::new(k, Pose::identity(), size);
    let c2 = Camera::new(k, Pose::new(r, Vector3::new(-1.0, 0.1, 0.2)), size);
    let f = fundamental_from_cameras(&c1, &c2);
    let points = [
        [0.3, 0.2, 5.0],
        [-0.4, 0.1, 6.0],
        [0.0, -0.5, 4.0],
        [0.5, 0.5, 7.0],
    ];
    for p in points {
        let x = Point3::new(p[0], p[1], p[2]);
        let (p1, p2) = (c1.project(&x).unwrap(), c2.project(&x).unwrap());
        let e = p2.to_homogeneous().dot(&(f * p1.to_homogeneous()));
        let wrong = p1.to_homogeneous().dot(&(f * p2.to_homogeneous()));
        assert!(e.abs() < 1e-12 * f.norm() * 1e6, "x2ᵀ F x1 = {e}");
        assert!(sampson_error(&f, &p1, &p2).unwrap() < 1e-18);
        assert!(wrong.abs() > 1e-3 * f.norm(), "x1ᵀ F x2 = {wrong}");
        assert!(sampson_error(&f.transpose(), &p1, &p2).unwrap() > 1.0);
    }
}
