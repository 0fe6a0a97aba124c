//! Keyframe bundle adjustment: when more cameras are estimated than
//! [`KeyframeOptions::max_keyframes`], the points and the focal factors are adjusted with a
//! subset of the cameras (keyframes, evenly spaced in image order), and every other camera is
//! then refined alone against the adjusted points (its pose only: 6 parameters, the same Cauchy
//! loss, an independent problem per camera), starting where the keyframe it shares the most
//! points with took it ([`CameraPose::warped`]). Its observations are kept as the points' `alone` ones.
//!
//! Why: on a video the tracks span more frames as the frames get denser, so every camera shares
//! points with more of the others; the reduced camera system's band, and with it the explicit
//! Schur complement and its Cholesky, grow faster than the frames (N^1.6–1.7 from 300 to 1000
//! frames, docs/BENCHMARKS.md "Video-scale speed"). With keyframes the joint adjustment keeps a
//! bounded size and the rest is linear in the frames.
//!
//! A camera that sees fewer than [`KeyframeOptions::min_points`] points through the keyframes'
//! tracks becomes a keyframe itself, as does the first estimated image of a camera group with no
//! keyframe (its focal factor is only refined jointly); the counts are in
//! [`super::BundleReport::keyframes`].

use nalgebra::{Matrix3, SMatrix, SVector, Vector3};

use crate::camera::CameraPose;
use crate::error::Result;
use crate::intrinsics::ImageIntrinsics;
use crate::lm::{CauchySum, LeastSquares, LmOptions, minimize};

/// Keyframe bundle adjustment ([`super::BundleOptions::keyframes`]).
#[derive(Debug, Clone, Copy, PartialEq)]
#[cfg_attr(
    feature = "serde",
    derive(serde::Serialize, serde::Deserialize),
    serde(default, deny_unknown_fields)
)]
pub struct KeyframeOptions {
    /// Cameras adjusted jointly at most before promotions: with more estimated cameras, this
    /// many evenly spaced in image order (the first and last included) are the keyframes. 300
    /// keeps every set of up to 300 images (all of bench-real, the 300-frame walks) adjusted
    /// jointly as before.
    pub max_keyframes: usize,
    /// A camera whose observations see fewer points than this (points of tracks with at least
    /// two keyframe observations) becomes a keyframe: a pose refined alone needs enough points
    /// around it to be as well determined as in the joint adjustment.
    pub min_points: usize,
    /// Levenberg–Marquardt steps of each camera refined alone.
    pub max_iterations: usize,
    /// Relative cost decrease at which a camera refined alone has converged. A pose is 6
    /// parameters against a few hundred points, so it is run to 1e-10 (a full solve costs
    /// microseconds), not to the joint adjustment's 1e-6.
    pub tolerance: f64,
    /// Points within `max_error_px` a camera refined alone needs, at the start and at the end;
    /// with fewer it stays where the keyframes' warp put it (`unrefined` in the report). Six:
    /// twice the three a pose needs.
    pub min_inliers: usize,
    /// When fewer than `min_inliers` points are within `max_error_px` of a camera's start, the
    /// first refinement takes those within this many times the distance. On the 1000-frame
    /// forward walk without it, 2 of 700 cameras refined alone found too few and stayed where
    /// the warp put them; with 8, none.
    pub start_slack: f64,
    /// Refinements of a camera refined alone at most, each on the points within
    /// `max_error_px` of the last one's pose; it stops earlier when that set no longer
    /// changes (at least two). Two fixed passes left the 1000-frame orbit's cameras where a
    /// start from the most co-visible keyframe's warp had first selected their points: mean
    /// rotation error 0.0138° against 0.0121° once the sets settle (translation direction
    /// 0.542° against 0.471°); the forward walk is the same either way (docs/BENCHMARKS.md,
    /// "A stop for the crawling Sampson refinement").
    pub max_passes: usize,
}

impl Default for KeyframeOptions {
    fn default() -> Self {
        Self {
            max_keyframes: 300,
            min_points: 50,
            max_iterations: 50,
            tolerance: 1e-10,
            min_inliers: 6,
            start_slack: 8.0,
            max_passes: 4,
        }
    }
}

/// The keyframes of `cameras` (`None`: not estimated), or `None` when all estimated cameras
/// are adjusted jointly (no more than `max_keyframes`). `reference` is always a keyframe.
pub(super) fn spaced(
    cameras: &[Option<CameraPose>],
    reference: usize,
    options: &KeyframeOptions,
) -> Option<Vec<bool>> {
    let estimated: Vec<usize> = (0..cameras.len())
        .filter(|&i| cameras[i].is_some())
        .collect();
    let (n, m) = (estimated.len(), options.max_keyframes.max(2));
    if n <= m {
        return None;
    }
    let mut key = vec![false; cameras.len()];
    for k in 0..m {
        key[estimated[(k * (n - 1) + (m - 1) / 2) / (m - 1)]] = true;
    }
    if let Some(r) = key.get_mut(reference) {
        *r = true;
    }
    Some(key)
}

/// Makes keyframes of the estimated cameras that would be refined alone on fewer than
/// `min_points` points (`seen[i]`: points of tracks with two keyframe observations that
/// image `i` observes) and of the first estimated image of each camera group without one.
/// Returns how many were promoted.
pub(super) fn promote(
    key: &mut [bool],
    cameras: &[Option<CameraPose>],
    seen: &[usize],
    intrinsics: &ImageIntrinsics,
    min_points: usize,
) -> usize {
    let mut promoted = 0;
    for i in 0..key.len() {
        if cameras[i].is_some() && !key[i] && seen[i] < min_points {
            key[i] = true;
            promoted += 1;
        }
    }
    let mut has_key = vec![false; intrinsics.groups()];
    for i in 0..key.len() {
        if key[i] {
            has_key[intrinsics.group[i]] = true;
        }
    }
    for i in 0..key.len() {
        let g = intrinsics.group[i];
        if cameras[i].is_some() && !has_key[g] {
            key[i] = true;
            has_key[g] = true;
            promoted += 1;
        }
    }
    promoted
}

/// One camera's pose (and its focal, when `refine_focal`) against fixed points: `(point,
/// observed pixel)` pairs, principal point `pp`, pinhole.
struct PoseOnly<'a> {
    points: &'a [(Vector3<f64>, [f64; 2])],
    pp: [f64; 2],
    refine_focal: bool,
    cauchy: f64,
    h: SMatrix<f64, 7, 7>,
    g: SVector<f64, 7>,
}

impl PoseOnly<'_> {
    fn n(&self) -> usize {
        if self.refine_focal { 7 } else { 6 }
    }
}

impl LeastSquares for PoseOnly<'_> {
    /// The pose and the focal (pixels).
    type State = (CameraPose, f64);

    fn n_params(&self) -> usize {
        self.n()
    }

    fn cost(&self, (c, f): &(CameraPose, f64)) -> f64 {
        let mut total = CauchySum::new(self.cauchy);
        for (x, xy) in self.points {
            total.add(match super::project(c, *f, self.pp, x) {
                Some((uv, _)) => (uv[0] - xy[0]).powi(2) + (uv[1] - xy[1]).powi(2),
                None => 1e6,
            });
        }
        total.total()
    }

    fn linearize(&mut self, (c, f): &(CameraPose, f64)) -> Result<()> {
        let (f, c2) = (*f, self.cauchy * self.cauchy);
        self.h = SMatrix::zeros();
        self.g = SVector::zeros();
        for (x, xy) in self.points {
            let Some((uv, xc)) = super::project(c, f, self.pp, x) else {
                continue;
            };
            let r = SVector::<f64, 2>::new(uv[0] - xy[0], uv[1] - xy[1]);
            let w = 1.0 / (1.0 + r.norm_squared() / c2);
            let d = super::pinhole_jacobian(f, &xc);
            // As the bundle adjustment's: x_c = exp(ω) R (X − C), ∂uv/∂log f = uv − pp.
            let skew = Matrix3::new(0.0, -xc.z, xc.y, xc.z, 0.0, -xc.x, -xc.y, xc.x, 0.0);
            let mut j = SMatrix::<f64, 2, 7>::zeros();
            j.fixed_view_mut::<2, 3>(0, 0).copy_from(&(d * (-skew)));
            j.fixed_view_mut::<2, 3>(0, 3)
                .copy_from(&(-(d * c.rotation.matrix())));
            if self.refine_focal {
                j[(0, 6)] = uv[0] - self.pp[0];
                j[(1, 6)] = uv[1] - self.pp[1];
            }
            self.h += j.transpose() * j * w;
            self.g += j.transpose() * r * w;
        }
        Ok(())
    }

    fn solve(&mut self, lambda: f64) -> Result<Option<Vec<f64>>> {
        // Without the focal its row and column are zero: the ε keeps the pivot positive and
        // its step is 0.
        let mut a = self.h;
        for k in 0..7 {
            a[(k, k)] = a[(k, k)] * (1.0 + lambda) + 1e-12;
        }
        Ok(a.cholesky().map(|ch| {
            let step = -ch.solve(&self.g);
            step.iter().take(self.n()).copied().collect()
        }))
    }

    fn apply(&self, (c, f): &(CameraPose, f64), step: &[f64]) -> (CameraPose, f64) {
        let f = match step.get(6) {
            Some(s) if self.refine_focal => f * s.exp(),
            _ => *f,
        };
        (c.moved(step), f)
    }
}

/// What [`refine_pose`] kept.
pub(crate) struct Refined {
    pub pose: CameraPose,
    /// The focal (the one given when it was not refined).
    pub focal: f64,
    /// Indices into the given correspondences within `max_error_px` at the end.
    pub inliers: Vec<usize>,
}

/// Refines `start` (a pose, and a focal to refine with it or `None`) on `points` (`(point,
/// observed pixel)`) as the bundle adjustment does its cameras (`options`' Cauchy scale and
/// `max_error_px`): correspondences farther than `max_error_px` at the start are left out
/// (`alone.start_slack` times farther when too few are within it), the pose refined, the far
/// ones left out again and the pose refined once more, and again while that set changes (up
/// to `alone.max_passes` refinements). `(f, pp)`: the focal (the start's when
/// refined) and principal point. `None` when fewer than `alone.min_inliers` correspondences
/// are left.
pub(crate) fn refine_pose(
    (start, focal): (CameraPose, Option<f64>),
    points: &[(Vector3<f64>, [f64; 2])],
    (f, pp): (f64, [f64; 2]),
    options: &super::BundleOptions,
    alone: &KeyframeOptions,
) -> Result<Option<Refined>> {
    let close = |(c, f): &(CameraPose, f64), max_error_px: f64| -> Vec<usize> {
        (0..points.len())
            .filter(|&k| {
                let (x, xy) = &points[k];
                super::project(c, *f, pp, x)
                    .is_some_and(|(uv, _)| (uv[0] - xy[0]).hypot(uv[1] - xy[1]) <= max_error_px)
            })
            .collect()
    };
    let lm = LmOptions {
        max_iterations: alone.max_iterations,
        tolerance: alone.tolerance,
        ..LmOptions::default()
    };
    let mut state = (start, focal.unwrap_or(f));
    let mut last: Vec<usize> = Vec::new();
    for pass in 0..alone.max_passes.max(2) {
        let mut used = close(&state, options.max_error_px);
        if pass == 0 && used.len() < alone.min_inliers {
            // A start farther off than the adjustment's cameras: once more, farther.
            used = close(&state, alone.start_slack * options.max_error_px);
        }
        if used.len() < alone.min_inliers {
            return Ok(None);
        }
        if pass >= 2 && used == last {
            break;
        }
        let subset: Vec<(Vector3<f64>, [f64; 2])> = used.iter().map(|&k| points[k]).collect();
        let mut problem = PoseOnly {
            points: &subset,
            pp,
            refine_focal: focal.is_some(),
            cauchy: options.cauchy_px,
            h: SMatrix::zeros(),
            g: SVector::zeros(),
        };
        minimize(&mut problem, &mut state, &lm)?;
        last = used;
    }
    let inliers = close(&state, options.max_error_px);
    Ok((inliers.len() >= alone.min_inliers).then_some(Refined {
        pose: state.0,
        focal: state.1,
        inliers,
    }))
}

#[cfg(test)]
mod tests {
    #![allow(clippy::unwrap_used)]
    use nalgebra::Rotation3;

    use super::*;

    fn origin() -> CameraPose {
        CameraPose {
            rotation: Rotation3::identity(),
            center: Vector3::zeros(),
        }
    }

    #[test]
    fn keyframes_are_evenly_spaced_over_the_estimated_images_with_the_reference() {
        let mut cameras = vec![Some(origin()); 10];
        cameras[3] = None;
        let options = KeyframeOptions {
            max_keyframes: 4,
            ..KeyframeOptions::default()
        };
        let key = spaced(&cameras, 5, &options).unwrap();
        // Estimated: 0 1 2 4 5 6 7 8 9; four spaced: 0, 4, 6, 9; the reference 5 added.
        let chosen: Vec<usize> = (0..10).filter(|&i| key[i]).collect();
        assert_eq!(chosen, [0, 4, 5, 6, 9]);
        assert!(!key[3]);
        let all = KeyframeOptions {
            max_keyframes: 9,
            ..KeyframeOptions::default()
        };
        assert!(spaced(&cameras, 5, &all).is_none());
    }

    #[test]
    fn cameras_seeing_too_few_points_and_lone_groups_are_promoted() {
        let cameras = vec![Some(origin()); 6];
        let mut intrinsics = ImageIntrinsics::new(vec![[0.0; 2]; 6], vec![1.0; 6]);
        intrinsics.group = vec![0, 0, 0, 0, 1, 1];
        let mut key = vec![true, false, true, false, false, false];
        let seen = [100, 100, 100, 10, 100, 100];
        let promoted = promote(&mut key, &cameras, &seen, &intrinsics, 50);
        assert_eq!(promoted, 2);
        assert_eq!(key, [true, false, true, true, true, false]);
    }

    /// The warp takes the keyframe to its new pose and keeps every camera's view of the
    /// warped world.
    #[test]
    fn a_warp_keeps_what_the_cameras_see() {
        let before = CameraPose {
            rotation: Rotation3::from_euler_angles(0.3, 0.1, -0.2),
            center: Vector3::new(1.0, 2.0, -3.0),
        };
        let after = CameraPose {
            rotation: Rotation3::from_euler_angles(0.31, 0.08, -0.21),
            center: Vector3::new(1.1, 1.9, -3.05),
        };
        let other = CameraPose {
            rotation: Rotation3::from_euler_angles(-0.2, 0.4, 0.1),
            center: Vector3::new(-1.0, 0.5, 2.0),
        };
        let k = before.warped(&before, &after, 1.0);
        assert!((k.rotation.matrix() - after.rotation.matrix()).norm() < 1e-12);
        assert!((k.center - after.center).norm() < 1e-12);
        let q = after.rotation.inverse() * before.rotation;
        let world = |x: Vector3<f64>| q * (x - before.center) + after.center;
        let moved = other.warped(&before, &after, 1.0);
        let x = Vector3::new(0.2, -0.7, 1.3);
        let seen = other.rotation * (x - other.center);
        let seen_after = moved.rotation * (world(x) - moved.center);
        assert!((seen - seen_after).norm() < 1e-12);
    }

    /// A camera moved off its pose finds it again on exact points; a few wrong
    /// correspondences are left out.
    #[test]
    fn a_pose_refined_alone_returns_to_the_truth() {
        let truth = CameraPose {
            rotation: Rotation3::from_euler_angles(0.1, -0.2, 0.05),
            center: Vector3::new(0.3, -0.1, -4.0),
        };
        let (f, pp) = (500.0, [320.0, 240.0]);
        let mut s = 11u64;
        let mut next = || {
            s = s
                .wrapping_mul(6364136223846793005)
                .wrapping_add(1442695040888963407);
            (s >> 11) as f64 / (1u64 << 53) as f64 - 0.5
        };
        let mut points = Vec::new();
        for k in 0..200 {
            let x = Vector3::new(2.0 * next(), 2.0 * next(), 2.0 * next());
            let (mut uv, _) = super::super::project(&truth, f, pp, &x).unwrap();
            if k % 20 == 0 {
                uv[0] += 30.0;
            }
            points.push((x, uv));
        }
        let start = truth.moved(&[0.002, -0.001, 0.0015, 0.01, 0.005, -0.01]);
        let options = crate::bundle::BundleOptions::default();
        let alone = KeyframeOptions::default();
        let refined = refine_pose((start, None), &points, (f, pp), &options, &alone)
            .unwrap()
            .unwrap();
        let angle = (refined.pose.rotation.inverse() * truth.rotation).angle();
        assert!(angle < 1e-9, "{angle}");
        assert!((refined.pose.center - truth.center).norm() < 1e-8);
        assert_eq!(refined.inliers.len(), 190);
        assert!(refined.inliers.iter().all(|k| k % 20 != 0));
        // Too few correspondences: none.
        assert!(
            refine_pose((start, None), &points[..5], (f, pp), &options, &alone)
                .unwrap()
                .is_none()
        );
        // With the focal 2 % off: both come back.
        let refined = refine_pose(
            (start, Some(f * 1.02)),
            &points,
            (f * 1.02, pp),
            &options,
            &alone,
        )
        .unwrap()
        .unwrap();
        assert!((refined.focal / f - 1.0).abs() < 1e-9, "{}", refined.focal);
        assert!((refined.pose.center - truth.center).norm() < 1e-8);
        assert_eq!(refined.inliers.len(), 190);
    }
}
