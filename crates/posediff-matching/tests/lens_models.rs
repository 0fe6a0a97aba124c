//! The lens models of `posediff_geometry::lens` against OpenCV's own: `projectPoints` and
//! `undistortPoints` for the radial and OPENCV models, `fisheye::projectPoints` and
//! `fisheye::undistortPoints` for OPENCV_FISHEYE. A parameter read in the wrong order, a sign
//! flipped or a distortion applied twice moves pixels by far more than the tolerances.
//! (The geometry crate is nalgebra-only, so the comparison lives here, beside OpenCV.)

// Test helpers outside #[test] functions unwrap too: a failure is the test failing.
#![allow(clippy::unwrap_used)]

use nalgebra::{Vector2, Vector3};
use opencv::core::{Mat, Point2d, Point3d, TermCriteria, TermCriteria_Type, Vector};
use opencv::prelude::*;
use posediff_geometry::{CameraModel, LensCamera};

/// OpenCV's camera matrix and distortion vector for a COLMAP-ordered model.
fn opencv_parts(camera: &LensCamera) -> (Mat, Mat) {
    let ((fx, fy), (cx, cy)) = (camera.focal(), camera.principal());
    let k = Mat::from_slice_2d(&[[fx, 0.0, cx], [0.0, fy, cy], [0.0, 0.0, 1.0]]).unwrap();
    let d = camera.distortion();
    let coefficients: Vec<f64> = match camera.model() {
        CameraModel::SimplePinhole | CameraModel::Pinhole => vec![0.0; 4],
        CameraModel::SimpleRadial => vec![d[0], 0.0, 0.0, 0.0],
        CameraModel::Radial => vec![d[0], d[1], 0.0, 0.0],
        CameraModel::OpenCv | CameraModel::OpenCvFisheye => d.to_vec(),
    };
    (
        k,
        Mat::from_slice(&coefficients).unwrap().try_clone().unwrap(),
    )
}

fn cameras() -> Vec<LensCamera> {
    let camera = |model, params: &[f64]| LensCamera::new(model, params.to_vec()).unwrap();
    vec![
        camera(CameraModel::SimplePinhole, &[700.0, 320.0, 240.0]),
        camera(CameraModel::Pinhole, &[700.0, 690.0, 321.0, 238.0]),
        camera(CameraModel::SimpleRadial, &[700.0, 320.0, 240.0, -0.12]),
        camera(CameraModel::Radial, &[700.0, 320.0, 240.0, -0.12, 0.02]),
        camera(
            CameraModel::OpenCv,
            &[700.0, 690.0, 321.0, 238.0, -0.1, 0.03, 0.001, -0.002],
        ),
        camera(
            CameraModel::OpenCvFisheye,
            &[400.0, 405.0, 320.0, 240.0, 0.05, -0.01, 0.002, -0.0005],
        ),
    ]
}

/// Camera-frame points up to about 35° off the axis (the image corners of a wide lens).
fn points() -> Vec<Vector3<f64>> {
    let mut out = Vec::new();
    for i in -3..=3 {
        for j in -2..=2 {
            out.push(Vector3::new(0.22 * f64::from(i), 0.2 * f64::from(j), 1.0) * 2.5);
        }
    }
    out
}

fn opencv_project(camera: &LensCamera, points: &[Vector3<f64>]) -> Vec<Vector2<f64>> {
    let (k, d) = opencv_parts(camera);
    let object: Vector<Point3d> = points.iter().map(|p| Point3d::new(p.x, p.y, p.z)).collect();
    let zero = Mat::from_slice(&[0.0f64, 0.0, 0.0])
        .unwrap()
        .try_clone()
        .unwrap();
    let mut image: Vector<Point2d> = Vector::new();
    if camera.model() == CameraModel::OpenCvFisheye {
        opencv::calib3d::fisheye_project_points_vec_def(&object, &mut image, &zero, &zero, &k, &d)
            .unwrap();
    } else {
        opencv::calib3d::project_points_def(&object, &zero, &zero, &k, &d, &mut image).unwrap();
    }
    image.iter().map(|p| Vector2::new(p.x, p.y)).collect()
}

fn opencv_unproject(camera: &LensCamera, pixels: &[Vector2<f64>]) -> Vec<Vector2<f64>> {
    let (k, d) = opencv_parts(camera);
    let src: Vector<Point2d> = pixels.iter().map(|p| Point2d::new(p.x, p.y)).collect();
    let mut dst: Vector<Point2d> = Vector::new();
    let criteria = TermCriteria::new(
        TermCriteria_Type::COUNT as i32 + TermCriteria_Type::EPS as i32,
        200,
        1e-14,
    )
    .unwrap();
    let none = Mat::default();
    if camera.model() == CameraModel::OpenCvFisheye {
        opencv::calib3d::fisheye_undistort_points(&src, &mut dst, &k, &d, &none, &none, criteria)
            .unwrap();
    } else {
        opencv::calib3d::undistort_points_iter(&src, &mut dst, &k, &d, &none, &none, criteria)
            .unwrap();
    }
    dst.iter().map(|p| Vector2::new(p.x, p.y)).collect()
}

#[test]
fn projection_matches_opencv_for_every_model() {
    let points = points();
    for camera in cameras() {
        let theirs = opencv_project(&camera, &points);
        for (p, q) in points.iter().zip(&theirs) {
            let ours = camera.project(p).unwrap();
            assert!(
                (ours - q).norm() < 1e-6,
                "{}: {p:?} projects to {ours:?} here, {q:?} in OpenCV",
                camera.model().name()
            );
        }
        // A lens model that distorts moves the corner points by pixels, so the comparison
        // above would have caught the distortion left out.
        if camera.is_distorted() {
            let pinhole = LensCamera::new(
                CameraModel::Pinhole,
                vec![
                    camera.focal().0,
                    camera.focal().1,
                    camera.principal().0,
                    camera.principal().1,
                ],
            )
            .unwrap();
            let moved = points
                .iter()
                .map(|p| (camera.project(p).unwrap() - pinhole.project(p).unwrap()).norm())
                .fold(0.0f64, f64::max);
            assert!(moved > 2.0, "{}: moved {moved}", camera.model().name());
        }
    }
}

#[test]
fn unprojection_matches_opencv_for_every_model() {
    let points = points();
    for camera in cameras() {
        let pixels: Vec<Vector2<f64>> = points.iter().map(|p| camera.project(p).unwrap()).collect();
        let theirs = opencv_unproject(&camera, &pixels);
        for ((pixel, q), p) in pixels.iter().zip(&theirs).zip(&points) {
            let ours = camera.unproject(pixel).unwrap();
            let truth = Vector2::new(p.x / p.z, p.y / p.z);
            assert!(
                (ours - q).norm() < 1e-7,
                "{}: {pixel:?} unprojects to {ours:?} here, {q:?} in OpenCV",
                camera.model().name()
            );
            assert!(
                (ours - truth).norm() < 1e-9,
                "{}: {ours:?} vs {truth:?}",
                camera.model().name()
            );
        }
    }
}
