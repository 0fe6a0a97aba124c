//! One camera's pose from 3D points and their pixels (resection, PnP) through OpenCV:
//! `solvePnPRansac` with the AP3P minimal solver, the inliers refitted by SQPnP (planar or
//! not) and polished by Levenberg–Marquardt.
//!
//! Conventions: OpenCV's, `x_cam = R X + t`, pixels of an undistorted pinhole camera `K`.

use nalgebra::{Matrix3, Vector3};
use opencv::core::{Mat, Point2d, Point3d, TermCriteria, Vector};
use opencv::prelude::*;

use crate::error::Result;

/// A resected camera: `x_cam = R X + t`, and the correspondences within the threshold.
#[derive(Debug, Clone, PartialEq)]
pub struct AbsolutePose {
    /// World → camera rotation.
    pub rotation: Matrix3<f64>,
    /// Translation.
    pub translation: Vector3<f64>,
    /// Indices of the inlier correspondences, ascending.
    pub inliers: Vec<usize>,
}

/// The pose of a camera with intrinsics `k` that sees `points[i]` at `pixels[i]`, inliers
/// within `threshold_px` of reprojection error (RANSAC with AP3P at confidence 0.9999, the
/// inliers refitted by SQPnP and polished by LM; the pose explaining the most is kept). `None` for fewer than 6 correspondences, lengths that
/// differ, or no pose OpenCV accepts.
///
/// # Errors
/// OpenCV errors.
pub fn absolute_pose(
    points: &[Vector3<f64>],
    pixels: &[[f64; 2]],
    k: &Matrix3<f64>,
    threshold_px: f64,
) -> Result<Option<AbsolutePose>> {
    if points.len() < 6
        || points.len() != pixels.len()
        || threshold_px.is_nan()
        || threshold_px <= 0.0
    {
        return Ok(None);
    }
    let object: Vector<Point3d> = points.iter().map(|p| Point3d::new(p.x, p.y, p.z)).collect();
    let image: Vector<Point2d> = pixels.iter().map(|q| Point2d::new(q[0], q[1])).collect();
    let camera = Mat::from_slice_2d(&[
        [k[(0, 0)], k[(0, 1)], k[(0, 2)]],
        [k[(1, 0)], k[(1, 1)], k[(1, 2)]],
        [k[(2, 0)], k[(2, 1)], k[(2, 2)]],
    ])?;
    let no_distortion = Mat::default();
    let (mut rvec, mut tvec, mut mask) = (Mat::default(), Mat::default(), Mat::default());
    let found = opencv::calib3d::solve_pnp_ransac(
        &object,
        &image,
        &camera,
        &no_distortion,
        &mut rvec,
        &mut tvec,
        false,
        10_000,
        threshold_px as f32,
        0.9999,
        &mut mask,
        opencv::calib3d::SOLVEPNP_AP3P,
    )?;
    if !found || rvec.rows() != 3 || tvec.rows() != 3 {
        return Ok(None);
    }
    let inliers: Vec<i32> = if mask.empty() {
        Vec::new()
    } else {
        mask.data_typed::<i32>()?.to_vec()
    };
    // OpenCV refits the RANSAC inliers with EPnP, which is unstable on nearly planar points
    // (a table top): refit them with SQPnP instead, polish by LM, and keep whichever of the
    // three poses explains the most correspondences.
    let mut best = pose_of(&rvec, &tvec, points, pixels, k, threshold_px)?;
    if inliers.len() >= 6 {
        let (o, i): (Vector<Point3d>, Vector<Point2d>) = inliers
            .iter()
            .filter_map(|&j| Some((object.get(j as usize).ok()?, image.get(j as usize).ok()?)))
            .unzip();
        let mut keep = |candidate: Option<AbsolutePose>| {
            if let Some(c) = candidate
                && best
                    .as_ref()
                    .is_none_or(|b| c.inliers.len() > b.inliers.len())
            {
                best = Some(c);
            }
        };
        // OpenCV 4.6's SQPnP can fail an internal assertion on exact points (its null-space
        // step, terzakig/sqpnp#16, fixed upstream after OpenCV's copy): LM then starts from
        // the RANSAC pose.
        let (mut rv, mut tv) = (Mat::default(), Mat::default());
        let refit = opencv::calib3d::solve_pnp(
            &o,
            &i,
            &camera,
            &no_distortion,
            &mut rv,
            &mut tv,
            false,
            opencv::calib3d::SOLVEPNP_SQPNP,
        );
        if matches!(refit, Ok(true)) && rv.rows() == 3 && tv.rows() == 3 {
            keep(pose_of(&rv, &tv, points, pixels, k, threshold_px)?);
        } else {
            (rv, tv) = (rvec.try_clone()?, tvec.try_clone()?);
        }
        let criteria = TermCriteria::new(
            opencv::core::TermCriteria_COUNT + opencv::core::TermCriteria_EPS,
            50,
            1e-10,
        )?;
        opencv::calib3d::solve_pnp_refine_lm(
            &o,
            &i,
            &camera,
            &no_distortion,
            &mut rv,
            &mut tv,
            criteria,
        )?;
        keep(pose_of(&rv, &tv, points, pixels, k, threshold_px)?);
    }
    Ok(best)
}

/// The pose of OpenCV's `rvec`, `tvec` with its inliers; `None` when not finite.
fn pose_of(
    rvec: &Mat,
    tvec: &Mat,
    points: &[Vector3<f64>],
    pixels: &[[f64; 2]],
    k: &Matrix3<f64>,
    threshold_px: f64,
) -> Result<Option<AbsolutePose>> {
    let mut r = Mat::default();
    opencv::calib3d::rodrigues_def(rvec, &mut r)?;
    let mut rotation = Matrix3::zeros();
    for a in 0..3 {
        for b in 0..3 {
            rotation[(a, b)] = *r.at_2d::<f64>(a as i32, b as i32)?;
        }
    }
    let translation = Vector3::new(
        *tvec.at_2d::<f64>(0, 0)?,
        *tvec.at_2d::<f64>(1, 0)?,
        *tvec.at_2d::<f64>(2, 0)?,
    );
    if !(rotation.iter().chain(translation.iter())).all(|v| v.is_finite()) {
        return Ok(None);
    }
    let inliers: Vec<usize> = points
        .iter()
        .zip(pixels)
        .enumerate()
        .filter(|(_, (p, q))| {
            let x = k * (rotation * *p + translation);
            x.z > 0.0 && (x.x / x.z - q[0]).hypot(x.y / x.z - q[1]) <= threshold_px
        })
        .map(|(j, _)| j)
        .collect();
    Ok(Some(AbsolutePose {
        rotation,
        translation,
        inliers,
    }))
}

#[cfg(test)]
mod tests {
    #![allow(clippy::unwrap_used)]
    use super::*;
    use nalgebra::Rotation3;

    #[test]
    fn a_camera_is_recovered_from_points_with_a_third_of_outliers() {
        let k = Matrix3::new(800.0, 0.0, 320.0, 0.0, 800.0, 240.0, 0.0, 0.0, 1.0);
        let r = *Rotation3::from_euler_angles(0.1, -0.4, 0.05).matrix();
        let t = Vector3::new(0.3, -0.1, 4.0);
        let mut s: u64 = 11;
        let mut rnd = || {
            s = s.wrapping_mul(6_364_136_223_846_793_005).wrapping_add(1);
            ((s >> 33) as f64) / f64::from(1u32 << 31) - 0.5
        };
        let (mut points, mut pixels) = (Vec::new(), Vec::new());
        for i in 0..60 {
            let p = Vector3::new(2.0 * rnd(), 2.0 * rnd(), 2.0 * rnd());
            let x = k * (r * p + t);
            let mut q = [x.x / x.z + 0.3 * rnd(), x.y / x.z + 0.3 * rnd()];
            if i % 3 == 0 {
                q = [q[0] + 80.0 + 100.0 * rnd(), q[1] - 60.0 + 100.0 * rnd()];
            }
            points.push(p);
            pixels.push(q);
        }
        let pose = absolute_pose(&points, &pixels, &k, 2.0).unwrap().unwrap();
        let dr = (pose.rotation * r.transpose()).trace();
        let angle = ((dr - 1.0) / 2.0).clamp(-1.0, 1.0).acos().to_degrees();
        assert!(angle < 0.1, "rotation off by {angle}°");
        assert!(
            (pose.translation - t).norm() < 0.01,
            "{:?}",
            pose.translation
        );
        assert_eq!(pose.inliers.len(), 40, "every inlier and no outlier");
        assert!(pose.inliers.iter().all(|i| i % 3 != 0));
        // Too few correspondences, or lengths that differ: no pose.
        assert!(
            absolute_pose(&points[..5], &pixels[..5], &k, 2.0)
                .unwrap()
                .is_none()
        );
        assert!(
            absolute_pose(&points, &pixels[..10], &k, 2.0)
                .unwrap()
                .is_none()
        );
    }
}
