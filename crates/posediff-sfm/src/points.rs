//! Sparse points for export: every track of the verified matches triangulated with the final
//! cameras, whatever produced them (the mapper, PoseDiffusion, a given estimate), robustly:
//! linear triangulation (faer SVD), Gauss–Newton on the pixel reprojection error, then the
//! worst observation dropped while any is further than the threshold (as COLMAP's track
//! filtering), and points kept only with at least two observations, a triangulation angle and
//! positive depth in every camera that sees them.
//!
//! Each track is independent (rayon over tracks): time and memory are linear in the matches.

use faer::Mat;
use nalgebra::{Matrix3, Vector3};
use posediff_geometry::{Camera, PairMatches};
use rayon::prelude::*;

use crate::error::{Result, SfmError};
use crate::tracks::{Observation, TrackReport, build_tracks};

/// How points are triangulated and filtered.
#[derive(Debug, Clone, Copy, PartialEq)]
#[cfg_attr(
    feature = "serde",
    derive(serde::Serialize, serde::Deserialize),
    serde(default, deny_unknown_fields)
)]
pub struct PointOptions {
    /// An observation further than this from its point's projection is dropped, px.
    pub max_reprojection_px: f64,
    /// The widest angle between two rays of a kept point, at least, degrees.
    pub min_angle_deg: f64,
    /// Gauss–Newton iterations per triangulation.
    pub iterations: usize,
}

impl Default for PointOptions {
    fn default() -> Self {
        Self {
            max_reprojection_px: 4.0,
            min_angle_deg: 1.5,
            iterations: 10,
        }
    }
}

/// One triangulated point.
#[derive(Debug, Clone, PartialEq)]
pub struct SparsePoint {
    /// World position (the cameras' frame).
    pub xyz: Vector3<f64>,
    /// The observations kept, sorted by image.
    pub observations: Vec<Observation>,
    /// Mean pixel distance between the observations and the projections (COLMAP's `ERROR`).
    pub error_px: f64,
}

/// What [`triangulate_points`] did.
#[derive(Debug, Clone, Copy, PartialEq, Default)]
pub struct PointsReport {
    /// The tracks built from the matches.
    pub tracks: TrackReport,
    /// Points kept.
    pub points: usize,
    /// Observations of the kept points.
    pub observations: usize,
    /// Observations dropped from kept points (further than the threshold).
    pub dropped_observations: usize,
    /// Tracks with fewer than two observations in estimated cameras.
    pub unseen: usize,
    /// Tracks that no consistent point fits (degenerate, behind a camera, too narrow, or every
    /// observation pair beyond the threshold).
    pub rejected: usize,
    /// Mean of the points' errors, px (0 without points).
    pub mean_error_px: f64,
}

/// Triangulates the tracks of `pairs` with `cameras` (`None`: not estimated, its observations
/// unused). Points come in the tracks' deterministic order.
///
/// # Errors
/// A pair naming an image beyond `cameras`, inconsistent pair lists, options out of range.
pub fn triangulate_points(
    cameras: &[Option<Camera>],
    pairs: &[PairMatches],
    options: &PointOptions,
) -> Result<(Vec<SparsePoint>, PointsReport)> {
    let usable = options.max_reprojection_px.is_finite()
        && options.max_reprojection_px > 0.0
        && options.min_angle_deg.is_finite()
        && options.min_angle_deg >= 0.0;
    if !usable {
        return Err(SfmError::InvalidInput(format!(
            "points: threshold {} px and angle {}° must be positive and finite",
            options.max_reprojection_px, options.min_angle_deg
        )));
    }
    let (tracks, track_report) = build_tracks(cameras.len(), pairs)?;
    let outcomes: Vec<Outcome> = tracks
        .par_iter()
        .map(|t| triangulate_track(t, cameras, options))
        .collect();
    let mut report = PointsReport {
        tracks: track_report,
        ..PointsReport::default()
    };
    let mut points = Vec::new();
    for o in outcomes {
        match o {
            Outcome::Unseen => report.unseen += 1,
            Outcome::Rejected => report.rejected += 1,
            Outcome::Kept { point, dropped } => {
                report.dropped_observations += dropped;
                report.observations += point.observations.len();
                points.push(point);
            }
        }
    }
    report.points = points.len();
    if !points.is_empty() {
        report.mean_error_px = points.iter().map(|p| p.error_px).sum::<f64>() / points.len() as f64;
    }
    Ok((points, report))
}

enum Outcome {
    Unseen,
    Rejected,
    Kept { point: SparsePoint, dropped: usize },
}

fn triangulate_track(
    track: &[Observation],
    cameras: &[Option<Camera>],
    options: &PointOptions,
) -> Outcome {
    let mut obs: Vec<(Observation, Camera)> = track
        .iter()
        .filter_map(|o| cameras.get(o.image).copied().flatten().map(|c| (*o, c)))
        .collect();
    if obs.len() < 2 {
        return Outcome::Unseen;
    }
    let seen = obs.len();
    loop {
        let Some(x) = linear(&obs).map(|x| refine(x, &obs, options.iterations)) else {
            return Outcome::Rejected;
        };
        let errors: Vec<Option<f64>> = obs.iter().map(|(o, c)| residual(c, o, &x)).collect();
        // The worst observation: behind the camera counts as infinitely far.
        let (worst, worst_error) = errors
            .iter()
            .enumerate()
            .map(|(k, e)| (k, e.unwrap_or(f64::INFINITY)))
            .fold(
                (0, -1.0),
                |acc, (k, e)| if e > acc.1 { (k, e) } else { acc },
            );
        if worst_error > options.max_reprojection_px {
            if obs.len() <= 2 {
                return Outcome::Rejected;
            }
            obs.remove(worst);
            continue;
        }
        if widest_angle(&obs, &x) < options.min_angle_deg.to_radians() {
            return Outcome::Rejected;
        }
        let error_px = errors.iter().flatten().sum::<f64>() / obs.len() as f64;
        return Outcome::Kept {
            point: SparsePoint {
                xyz: x,
                observations: obs.iter().map(|(o, _)| *o).collect(),
                error_px,
            },
            dropped: seen - obs.len(),
        };
    }
}

/// Linear triangulation in normalised coordinates (`K⁻¹x`) from world-to-camera `(R, t)`:
/// the null vector of the stacked `x (r₃·X + t_z) − (r_i·X + t_i)` rows (faer SVD); `None`
/// at infinity or non-finite.
pub fn dlt(rows: &[([f64; 2], Matrix3<f64>, Vector3<f64>)]) -> Option<Vector3<f64>> {
    let mut a = Mat::<f64>::zeros(2 * rows.len(), 4);
    for (k, (x, r, t)) in rows.iter().enumerate() {
        for (row, (coord, axis)) in [(x[0], 0usize), (x[1], 1usize)].into_iter().enumerate() {
            for j in 0..3 {
                a[(2 * k + row, j)] = coord * r[(2, j)] - r[(axis, j)];
            }
            a[(2 * k + row, 3)] = coord * t.z - t[axis];
        }
    }
    let svd = a.thin_svd().ok()?;
    let v = svd.V();
    let h = [v[(0, 3)], v[(1, 3)], v[(2, 3)], v[(3, 3)]];
    if h[3].abs() < 1e-12 {
        return None;
    }
    let x = Vector3::new(h[0] / h[3], h[1] / h[3], h[2] / h[3]);
    x.iter().all(|v| v.is_finite()).then_some(x)
}

fn linear(obs: &[(Observation, Camera)]) -> Option<Vector3<f64>> {
    let rows: Vec<_> = obs
        .iter()
        .map(|(o, c)| {
            let x = c.intrinsics.inverse_matrix() * Vector3::new(o.xy[0], o.xy[1], 1.0);
            (
                [x.x, x.y],
                c.cam_from_world.rotation,
                c.cam_from_world.translation,
            )
        })
        .collect();
    dlt(&rows)
}

/// Pixel distance between an observation and the projection of `x`; `None` behind the camera.
fn residual(c: &Camera, o: &Observation, x: &Vector3<f64>) -> Option<f64> {
    let xc = c.cam_from_world.rotation * x + c.cam_from_world.translation;
    if xc.z <= 1e-12 {
        return None;
    }
    let k = &c.intrinsics;
    let u = k.fx() * xc.x / xc.z + k.cx() - o.xy[0];
    let v = k.fy() * xc.y / xc.z + k.cy() - o.xy[1];
    Some(u.hypot(v))
}

/// Gauss–Newton on the squared pixel residuals (3×3 normal equations, step halved while the
/// cost does not fall).
fn refine(mut x: Vector3<f64>, obs: &[(Observation, Camera)], iterations: usize) -> Vector3<f64> {
    let cost = |x: &Vector3<f64>| -> f64 {
        obs.iter()
            .map(|(o, c)| residual(c, o, x).map_or(f64::INFINITY, |r| r * r))
            .sum()
    };
    let mut current = cost(&x);
    for _ in 0..iterations {
        let mut h = Matrix3::zeros();
        let mut g = Vector3::zeros();
        for (o, c) in obs {
            let r = &c.cam_from_world.rotation;
            let xc = r * x + c.cam_from_world.translation;
            if xc.z <= 1e-12 {
                return x;
            }
            let k = &c.intrinsics;
            let (iz, iz2) = (1.0 / xc.z, 1.0 / (xc.z * xc.z));
            let du = Vector3::new(k.fx() * iz, 0.0, -k.fx() * xc.x * iz2);
            let dv = Vector3::new(0.0, k.fy() * iz, -k.fy() * xc.y * iz2);
            let ju = r.transpose() * du;
            let jv = r.transpose() * dv;
            let ru = k.fx() * xc.x * iz + k.cx() - o.xy[0];
            let rv = k.fy() * xc.y * iz + k.cy() - o.xy[1];
            h += ju * ju.transpose() + jv * jv.transpose();
            g += ju * ru + jv * rv;
        }
        let Some(step) = h.try_inverse().map(|hi| -(hi * g)) else {
            return x;
        };
        let mut scale = 1.0;
        let mut improved = false;
        for _ in 0..8 {
            let candidate = x + step * scale;
            let c = cost(&candidate);
            if c < current {
                (x, current, improved) = (candidate, c, true);
                break;
            }
            scale *= 0.5;
        }
        if !improved || step.norm() * scale < 1e-12 * (1.0 + x.norm()) {
            break;
        }
    }
    x
}

/// The widest angle between the rays of two observations, radians.
fn widest_angle(obs: &[(Observation, Camera)], x: &Vector3<f64>) -> f64 {
    let rays: Vec<Vector3<f64>> = obs
        .iter()
        .map(|(_, c)| (x - c.center().coords).normalize())
        .collect();
    let mut widest: f64 = 0.0;
    for (i, a) in rays.iter().enumerate() {
        for b in &rays[i + 1..] {
            widest = widest.max(a.dot(b).clamp(-1.0, 1.0).acos());
        }
    }
    widest
}

#[cfg(test)]
mod tests {
    #![allow(clippy::unwrap_used)]
    use super::*;
    use nalgebra::{Point3, Rotation3};
    use posediff_geometry::{ImageSize, Intrinsics, Pose};

    fn ring(n: usize) -> Vec<Option<Camera>> {
        (0..n)
            .map(|i| {
                let a = i as f64 * 0.3;
                let centre = Vector3::new(4.0 * a.sin(), 0.2, -4.0 * a.cos());
                // Look at the origin: z axis towards −centre.
                let z = (-centre).normalize();
                let x = Vector3::y().cross(&z).normalize();
                let y = z.cross(&x);
                let r = Matrix3::from_rows(&[x.transpose(), y.transpose(), z.transpose()]);
                let t = -(r * centre);
                Some(Camera::new(
                    Intrinsics::new(500.0, 510.0, 319.5, 239.5).unwrap(),
                    Pose::new(r, t),
                    ImageSize::new(640, 480).unwrap(),
                ))
            })
            .collect()
    }

    /// Matches between consecutive cameras of points on a cube, each pair's keypoint ids being
    /// the point ids, plus one observation of point 0 moved by `outlier_px` in image 2.
    fn matches(
        cameras: &[Option<Camera>],
        points: &[Point3<f64>],
        outlier_px: f64,
    ) -> Vec<PairMatches> {
        let project = |i: usize, k: usize| {
            let p = cameras[i].unwrap().project(&points[k]).unwrap();
            let shift = if i == 2 && k == 0 { outlier_px } else { 0.0 };
            [p.x + shift, p.y]
        };
        (0..cameras.len() - 1)
            .map(|i| PairMatches {
                first: i,
                second: i + 1,
                kp1: (0..points.len()).map(|k| project(i, k)).collect(),
                kp2: (0..points.len()).map(|k| project(i + 1, k)).collect(),
                idx1: (0..points.len() as u32).collect(),
                idx2: (0..points.len() as u32).collect(),
            })
            .collect()
    }

    fn cube() -> Vec<Point3<f64>> {
        let mut p = Vec::new();
        for i in 0..4 {
            for j in 0..4 {
                for k in 0..2 {
                    p.push(Point3::new(
                        i as f64 * 0.3 - 0.45,
                        j as f64 * 0.3 - 0.45,
                        k as f64 * 0.5,
                    ));
                }
            }
        }
        p
    }

    #[test]
    fn exact_matches_give_the_points_back_with_zero_error() {
        let cams = ring(5);
        let truth = cube();
        let (points, report) = triangulate_points(
            &cams,
            &matches(&cams, &truth, 0.0),
            &PointOptions::default(),
        )
        .unwrap();
        assert_eq!(points.len(), truth.len());
        assert_eq!(report.points, truth.len());
        assert_eq!(report.observations, 5 * truth.len());
        for (p, t) in points.iter().zip(&truth) {
            assert!((p.xyz - t.coords).norm() < 1e-9, "{} vs {}", p.xyz, t);
            assert!(p.error_px < 1e-7);
        }
    }

    #[test]
    fn an_outlying_observation_is_dropped_and_the_error_is_the_mean_distance() {
        let cams = ring(5);
        let truth = cube();
        let (points, report) = triangulate_points(
            &cams,
            &matches(&cams, &truth, 30.0),
            &PointOptions::default(),
        )
        .unwrap();
        assert_eq!(report.dropped_observations, 1);
        assert_eq!(points[0].observations.len(), 4);
        assert!(points[0].observations.iter().all(|o| o.image != 2));
        assert!((points[0].xyz - truth[0].coords).norm() < 1e-9);
        // A small shift is kept, and the error is the mean pixel distance.
        let (points, _) = triangulate_points(
            &cams,
            &matches(&cams, &truth, 1.0),
            &PointOptions::default(),
        )
        .unwrap();
        let p = &points[0];
        assert_eq!(p.observations.len(), 5);
        let mean: f64 = p
            .observations
            .iter()
            .map(|o| {
                let q = cams[o.image]
                    .unwrap()
                    .project(&Point3::from(p.xyz))
                    .unwrap();
                (q.x - o.xy[0]).hypot(q.y - o.xy[1])
            })
            .sum::<f64>()
            / 5.0;
        assert!((p.error_px - mean).abs() < 1e-12);
        assert!(p.error_px > 0.1 && p.error_px < 1.0, "{}", p.error_px);
    }

    #[test]
    fn unestimated_cameras_and_narrow_rays_give_no_points() {
        let mut cams = ring(3);
        let truth = cube();
        let pairs = matches(&cams, &truth, 0.0);
        cams[1] = None;
        // Images 0-1 and 1-2 are the only pairs: no track keeps two estimated images... except
        // through image 1's keypoints joining 0 and 2.
        let (points, report) = triangulate_points(&cams, &pairs, &PointOptions::default()).unwrap();
        assert_eq!(points.len(), truth.len());
        assert!(points.iter().all(|p| p.observations.len() == 2));
        assert_eq!(report.unseen, 0);
        // Two cameras a hair apart: every ray pair is narrower than 1.5°.
        let mut close = ring(2);
        let base = close[0].unwrap();
        let c1 = close[1].as_mut().unwrap();
        c1.cam_from_world = Pose::new(
            *Rotation3::from_euler_angles(0.0, 0.001, 0.0).matrix() * base.cam_from_world.rotation,
            base.cam_from_world.translation,
        );
        let (points, report) = triangulate_points(
            &close,
            &matches(&close, &truth, 0.0),
            &PointOptions::default(),
        )
        .unwrap();
        assert!(points.is_empty());
        assert_eq!(report.rejected, truth.len());
    }

    #[test]
    fn bad_options_and_pairs_are_errors() {
        let cams = ring(2);
        let bad = PointOptions {
            max_reprojection_px: f64::NAN,
            ..PointOptions::default()
        };
        assert!(triangulate_points(&cams, &[], &bad).is_err());
        let pairs = matches(&ring(3), &cube(), 0.0);
        assert!(triangulate_points(&cams, &pairs, &PointOptions::default()).is_err());
    }
}
