//! Bundle adjustment with tracks: the cameras, the shared focal and triangulated points refined
//! together on reprojection errors (the last stage of the checkpoint-free path).
//!
//! The Sampson objective ([`crate::refine`]) only sees pairs; a point seen in three or more
//! images ties the pairs together (the trifocal constraints), which matters where some pairs
//! have few matches. Here:
//!
//! 1. [`build_tracks`]: pairwise matches → tracks by union-find over keypoints (a keypoint is an
//!    image and its exact coordinates); tracks that see one image twice are dropped.
//! 2. Each track is triangulated (linear, normalised rays) from the estimated cameras; points
//!    behind a camera, with a ray angle below `min_angle_deg` or observations farther than
//!    `max_error_px` from their projections are left out.
//! 3. Levenberg–Marquardt on the reprojection errors (Cauchy loss), with the points eliminated
//!    by the Schur complement; camera parametrisation and gauge as in [`crate::refine`] (the
//!    reference camera fixed, centres and points rescaled to unit mean camera distance).
//! 4. Observations off by more than `max_error_px` are dropped and the adjustment runs again.

use std::collections::HashMap;

use nalgebra::{DMatrix, DVector, Matrix3, Rotation3, SMatrix, SVector, Vector3};

use crate::averaging::find;
use crate::error::Result;
use crate::refine::{ImageIntrinsics, RefineCamera, parameter_layout};

/// One observation of a track: an image and pixel coordinates.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Observation {
    /// Image index.
    pub image: usize,
    /// Pixel coordinates (OpenCV).
    pub xy: [f64; 2],
}

/// Observations of one scene point.
pub type Track = Vec<Observation>;

/// Tracks from pairwise matches `(first, second, kp1, kp2)` over `n_images`.
pub fn build_tracks<'a>(
    n_images: usize,
    pairs: impl IntoIterator<Item = (usize, usize, &'a [[f64; 2]], &'a [[f64; 2]])>,
) -> Vec<Track> {
    let mut ids: HashMap<(usize, u64, u64), usize> = HashMap::new();
    let mut nodes: Vec<Observation> = Vec::new();
    let mut parent: Vec<usize> = Vec::new();
    let mut id =
        |image: usize, xy: [f64; 2], nodes: &mut Vec<Observation>, parent: &mut Vec<usize>| {
            *ids.entry((image, xy[0].to_bits(), xy[1].to_bits()))
                .or_insert_with(|| {
                    nodes.push(Observation { image, xy });
                    parent.push(parent.len());
                    parent.len() - 1
                })
        };
    for (a, b, kp1, kp2) in pairs {
        if a >= n_images || b >= n_images || a == b {
            continue;
        }
        for (p, q) in kp1.iter().zip(kp2) {
            let i = id(a, *p, &mut nodes, &mut parent);
            let j = id(b, *q, &mut nodes, &mut parent);
            let (ri, rj) = (find(&mut parent, i), find(&mut parent, j));
            if ri != rj {
                parent[ri] = rj;
            }
        }
    }
    let mut groups: HashMap<usize, Track> = HashMap::new();
    for (k, node) in nodes.iter().enumerate() {
        let root = find(&mut parent, k);
        groups.entry(root).or_default().push(*node);
    }
    let mut tracks: Vec<Track> = groups
        .into_values()
        .filter(|t| {
            let mut images: Vec<usize> = t.iter().map(|o| o.image).collect();
            images.sort_unstable();
            images.windows(2).all(|w| w[0] != w[1]) && t.len() >= 2
        })
        .collect();
    // Deterministic order (HashMap iteration is not).
    for t in &mut tracks {
        t.sort_by_key(|o| o.image);
    }
    tracks.sort_by(|a, b| {
        (a[0].image, a[0].xy[0].to_bits(), a[0].xy[1].to_bits()).cmp(&(
            b[0].image,
            b[0].xy[0].to_bits(),
            b[0].xy[1].to_bits(),
        ))
    });
    tracks
}

/// Bundle-adjustment settings.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct BundleConfig {
    /// Cauchy scale of the reprojection error, pixels.
    pub cauchy_px: f64,
    /// Observations farther than this from their projection are dropped (pixels).
    pub max_error_px: f64,
    /// Smallest largest-ray-angle of a triangulated point, degrees.
    pub min_angle_deg: f64,
    /// Refine the shared focal factor.
    pub refine_focal: bool,
    /// Iterations per adjustment.
    pub max_iterations: usize,
    /// Converged when the relative cost decrease of a step is below this.
    pub tolerance: f64,
}

impl Default for BundleConfig {
    fn default() -> Self {
        Self {
            cauchy_px: 1.0,
            max_error_px: 4.0,
            min_angle_deg: 1.0,
            refine_focal: true,
            max_iterations: 100,
            tolerance: 1e-10,
        }
    }
}

/// What the adjustment did.
#[derive(Debug, Clone, Copy, PartialEq, Default)]
pub struct BundleReport {
    /// Tracks given.
    pub tracks: usize,
    /// Points triangulated and adjusted.
    pub points: usize,
    /// Observations used in the last adjustment.
    pub observations: usize,
    /// Accepted steps over both adjustments.
    pub iterations: usize,
    /// RMS reprojection error of the used observations at the end, pixels.
    pub rms_px: f64,
}

fn k_inverse(phi: f64, intrinsics: &ImageIntrinsics, i: usize) -> Matrix3<f64> {
    let f = phi * intrinsics.scale[i];
    let c = intrinsics.principal[i];
    Matrix3::new(
        1.0 / f,
        0.0,
        -c[0] / f,
        0.0,
        1.0 / f,
        -c[1] / f,
        0.0,
        0.0,
        1.0,
    )
}

fn project(
    c: &RefineCamera,
    f: f64,
    pp: [f64; 2],
    x: &Vector3<f64>,
) -> Option<([f64; 2], Vector3<f64>)> {
    let xc = c.rotation * (x - c.center);
    (xc.z > 1e-12).then(|| ([f * xc.x / xc.z + pp[0], f * xc.y / xc.z + pp[1]], xc))
}

/// Linear triangulation from normalised rays; `None` when degenerate or behind a camera.
fn triangulate(
    obs: &[Observation],
    cameras: &[Option<RefineCamera>],
    intrinsics: &ImageIntrinsics,
    phi: f64,
    min_angle: f64,
) -> Option<Vector3<f64>> {
    let used: Vec<(&Observation, RefineCamera)> = obs
        .iter()
        .filter_map(|o| cameras[o.image].map(|c| (o, c)))
        .collect();
    if used.len() < 2 {
        return None;
    }
    let mut a = DMatrix::<f64>::zeros(2 * used.len(), 4);
    let mut rays = Vec::with_capacity(used.len());
    for (k, (o, c)) in used.iter().enumerate() {
        let x = k_inverse(phi, intrinsics, o.image) * Vector3::new(o.xy[0], o.xy[1], 1.0);
        let r = c.rotation.matrix();
        let t = -(r * c.center);
        for (row, (coord, axis)) in [(x.x, 0usize), (x.y, 1usize)].into_iter().enumerate() {
            for j in 0..3 {
                a[(2 * k + row, j)] = coord * r[(2, j)] - r[(axis, j)];
            }
            a[(2 * k + row, 3)] = coord * t.z - t[axis];
        }
        rays.push(c.rotation.inverse() * x.normalize());
    }
    let svd = a.svd(false, true);
    let v_t = svd.v_t?;
    let h = v_t.row(3);
    if h[3].abs() < 1e-12 {
        return None;
    }
    let point = Vector3::new(h[0] / h[3], h[1] / h[3], h[2] / h[3]);
    let mut widest: f64 = 0.0;
    for (i, ri) in rays.iter().enumerate() {
        for rj in &rays[i + 1..] {
            widest = widest.max(ri.dot(rj).clamp(-1.0, 1.0).acos());
        }
    }
    let in_front = used
        .iter()
        .all(|(_, c)| (c.rotation * (point - c.center)).z > 0.0);
    (in_front && widest >= min_angle && point.iter().all(|v| v.is_finite())).then_some(point)
}

/// A triangulated point with the observations it keeps.
#[derive(Debug, Clone)]
struct Point {
    x: Vector3<f64>,
    obs: Vec<Observation>,
}

struct Layout<'a> {
    intrinsics: &'a ImageIntrinsics,
    /// Parameter offset of each camera's 6 values.
    offset: Vec<Option<usize>>,
    focal_index: Option<usize>,
    n_params: usize,
    cauchy: f64,
}

impl Layout<'_> {
    fn rho(&self, e2: f64) -> f64 {
        let c2 = self.cauchy * self.cauchy;
        0.5 * c2 * (1.0 + e2 / c2).ln()
    }

    fn cost(&self, cameras: &[Option<RefineCamera>], phi: f64, points: &[Point]) -> f64 {
        let mut total = 0.0;
        for p in points {
            for o in &p.obs {
                let Some(c) = cameras[o.image] else { continue };
                let f = phi * self.intrinsics.scale[o.image];
                match project(&c, f, self.intrinsics.principal[o.image], &p.x) {
                    Some((uv, _)) => {
                        let e2 = (uv[0] - o.xy[0]).powi(2) + (uv[1] - o.xy[1]).powi(2);
                        total += self.rho(e2);
                    }
                    None => total += self.rho(1e6),
                }
            }
        }
        total
    }
}

/// Indices (≤ 7) of one observation's camera parameters: 6 pose values and the focal.
type ParamIndex = [Option<usize>; 7];

/// One LM iteration's linear system, reduced to the cameras.
#[allow(clippy::type_complexity)]
fn step(
    layout: &Layout<'_>,
    cameras: &[Option<RefineCamera>],
    phi: f64,
    points: &[Point],
    lambda: f64,
) -> Option<(DVector<f64>, Vec<Vector3<f64>>)> {
    let m = layout.n_params;
    let c2 = layout.cauchy * layout.cauchy;
    let mut a = DMatrix::<f64>::zeros(m, m);
    let mut g = DVector::<f64>::zeros(m);
    // Per point: C⁻¹, g_p, and per observation (indices, E = J_cᵀ W J_p).
    let mut per_point: Vec<(
        Matrix3<f64>,
        Vector3<f64>,
        Vec<(ParamIndex, SMatrix<f64, 7, 3>)>,
    )> = Vec::with_capacity(points.len());
    for p in points {
        let mut cpt = Matrix3::<f64>::zeros();
        let mut gp = Vector3::<f64>::zeros();
        let mut blocks = Vec::with_capacity(p.obs.len());
        for o in &p.obs {
            let Some(cam) = cameras[o.image] else {
                continue;
            };
            let f = phi * layout.intrinsics.scale[o.image];
            let pp = layout.intrinsics.principal[o.image];
            let Some((uv, xc)) = project(&cam, f, pp, &p.x) else {
                continue;
            };
            let r = SVector::<f64, 2>::new(uv[0] - o.xy[0], uv[1] - o.xy[1]);
            let w = 1.0 / (1.0 + r.norm_squared() / c2);
            let iz = 1.0 / xc.z;
            // ∂uv/∂x_cam.
            let d = SMatrix::<f64, 2, 3>::new(
                f * iz,
                0.0,
                -f * xc.x * iz * iz,
                0.0,
                f * iz,
                -f * xc.y * iz * iz,
            );
            let rm = cam.rotation.matrix();
            let j_point = d * rm;
            // x_cam = exp(ω) R (X − C): ∂/∂ω = −[x_cam]ₓ, ∂/∂C = −R.
            let skew = Matrix3::new(0.0, -xc.z, xc.y, xc.z, 0.0, -xc.x, -xc.y, xc.x, 0.0);
            let j_rot = d * (-skew);
            let j_centre = -j_point;
            let mut j_cam = SMatrix::<f64, 2, 7>::zeros();
            j_cam.fixed_view_mut::<2, 3>(0, 0).copy_from(&j_rot);
            j_cam.fixed_view_mut::<2, 3>(0, 3).copy_from(&j_centre);
            // ∂uv/∂log φ = uv − pp.
            j_cam[(0, 6)] = uv[0] - pp[0];
            j_cam[(1, 6)] = uv[1] - pp[1];
            let idx: ParamIndex = std::array::from_fn(|k| match k {
                0..6 => layout.offset[o.image].map(|off| off + k),
                _ => layout.focal_index,
            });
            cpt += j_point.transpose() * j_point * w;
            gp += j_point.transpose() * r * w;
            let jc_w = j_cam.transpose() * w;
            let hcc = jc_w * j_cam;
            let gc = jc_w * r;
            for (k, ik) in idx.iter().enumerate() {
                let Some(ik) = *ik else { continue };
                g[ik] += gc[k];
                for (l, il) in idx.iter().enumerate() {
                    if let Some(il) = *il {
                        a[(ik, il)] += hcc[(k, l)];
                    }
                }
            }
            blocks.push((idx, jc_w * j_point));
        }
        for k in 0..3 {
            cpt[(k, k)] *= 1.0 + lambda;
            cpt[(k, k)] += 1e-12;
        }
        let c_inv = cpt.try_inverse().unwrap_or_else(Matrix3::zeros);
        per_point.push((c_inv, gp, blocks));
    }
    let floor = 1e-12 * a.diagonal().max().max(1e-300);
    for k in 0..m {
        a[(k, k)] += lambda * a[(k, k)] + floor;
    }
    // Schur complement: S = A − Σ E C⁻¹ Eᵀ, rhs = −g + Σ E C⁻¹ g_p.
    let mut rhs = -g;
    for (c_inv, gp, blocks) in &per_point {
        let cg = c_inv * gp;
        for (idx_a, ea) in blocks {
            let eac = ea * c_inv;
            let v = ea * cg;
            for (k, ik) in idx_a.iter().enumerate() {
                let Some(ik) = *ik else { continue };
                rhs[ik] += v[k];
                for (idx_b, eb) in blocks {
                    let prod = eac * eb.transpose();
                    for (l, il) in idx_b.iter().enumerate() {
                        if let Some(il) = *il {
                            a[(ik, il)] -= prod[(k, l)];
                        }
                    }
                }
            }
        }
    }
    let delta = if m > 0 {
        a.cholesky()?.solve(&rhs)
    } else {
        DVector::zeros(0)
    };
    // Back-substitution: δp = −C⁻¹ (g_p + Σ Eᵀ δc).
    let point_steps = per_point
        .iter()
        .map(|(c_inv, gp, blocks)| {
            let mut v = *gp;
            for (idx, e) in blocks {
                let mut dc = SVector::<f64, 7>::zeros();
                for (k, ik) in idx.iter().enumerate() {
                    if let Some(ik) = *ik {
                        dc[k] = delta[ik];
                    }
                }
                v += e.transpose() * dc;
            }
            -(c_inv * v)
        })
        .collect();
    Some((delta, point_steps))
}

/// Rescales centres and points about the reference's centre to unit mean camera distance.
fn normalize(cameras: &mut [Option<RefineCamera>], points: &mut [Point], reference: usize) {
    let Some(origin) = cameras.get(reference).copied().flatten().map(|c| c.center) else {
        return;
    };
    let d: Vec<f64> = cameras
        .iter()
        .flatten()
        .map(|c| (c.center - origin).norm())
        .collect();
    let mean = d.iter().sum::<f64>() / d.len().max(1) as f64;
    if mean > 0.0 && mean.is_finite() {
        for c in cameras.iter_mut().flatten() {
            c.center = origin + (c.center - origin) / mean;
        }
        for p in points {
            p.x = origin + (p.x - origin) / mean;
        }
    }
}

fn adjust(
    layout: &Layout<'_>,
    cameras: &mut [Option<RefineCamera>],
    phi: &mut f64,
    points: &mut [Point],
    reference: usize,
    config: &BundleConfig,
) -> usize {
    let mut cost = layout.cost(cameras, *phi, points);
    let mut lambda = 1e-4;
    let mut iterations = 0;
    while iterations < config.max_iterations {
        let mut accepted = false;
        for _ in 0..12 {
            let Some((delta, point_steps)) = step(layout, cameras, *phi, points, lambda) else {
                lambda *= 10.0;
                continue;
            };
            let mut moved: Vec<Option<RefineCamera>> = cameras.to_vec();
            for (c, off) in moved.iter_mut().zip(&layout.offset) {
                if let (Some(c), Some(o)) = (c.as_mut(), off) {
                    let w = Vector3::new(delta[*o], delta[o + 1], delta[o + 2]);
                    c.rotation = Rotation3::from_scaled_axis(w) * c.rotation;
                    c.center += Vector3::new(delta[o + 3], delta[o + 4], delta[o + 5]);
                }
            }
            let new_phi = layout.focal_index.map_or(*phi, |i| *phi * delta[i].exp());
            let mut new_points: Vec<Point> = points.to_vec();
            for (p, s) in new_points.iter_mut().zip(&point_steps) {
                p.x += s;
            }
            normalize(&mut moved, &mut new_points, reference);
            let new_cost = layout.cost(&moved, new_phi, &new_points);
            if new_cost.is_finite() && new_cost < cost && new_phi.is_finite() {
                let decrease = (cost - new_cost) / cost.max(1e-300);
                cameras.copy_from_slice(&moved);
                points.clone_from_slice(&new_points);
                *phi = new_phi;
                cost = new_cost;
                lambda = (lambda / 3.0).max(1e-12);
                accepted = true;
                iterations += 1;
                if decrease < config.tolerance {
                    return iterations;
                }
                break;
            }
            lambda *= 5.0;
        }
        if !accepted {
            break;
        }
    }
    iterations
}

/// Keeps the observations within `max_error_px` of their projection; points with fewer than
/// two left are dropped.
fn filter(
    points: Vec<Point>,
    cameras: &[Option<RefineCamera>],
    intrinsics: &ImageIntrinsics,
    phi: f64,
    max_error_px: f64,
) -> Vec<Point> {
    points
        .into_iter()
        .filter_map(|mut p| {
            p.obs.retain(|o| {
                cameras[o.image].is_some_and(|c| {
                    project(
                        &c,
                        phi * intrinsics.scale[o.image],
                        intrinsics.principal[o.image],
                        &p.x,
                    )
                    .is_some_and(|(uv, _)| (uv[0] - o.xy[0]).hypot(uv[1] - o.xy[1]) <= max_error_px)
                })
            });
            (p.obs.len() >= 2).then_some(p)
        })
        .collect()
}

/// Adjusts `cameras` (`None`: not estimated) and `phi` in place on `tracks`; the reference
/// camera is held fixed.
///
/// # Errors
/// Cameras or intrinsics of the wrong length, a reference without a camera, a non-positive
/// focal factor.
pub fn bundle_adjust(
    tracks: &[Track],
    intrinsics: &ImageIntrinsics,
    cameras: &mut [Option<RefineCamera>],
    phi: &mut f64,
    reference: usize,
    config: &BundleConfig,
) -> Result<BundleReport> {
    let (offset, focal_index, n_params) = parameter_layout(
        cameras.len(),
        intrinsics,
        cameras,
        *phi,
        reference,
        config.refine_focal,
    )?;
    let layout = Layout {
        intrinsics,
        offset,
        focal_index,
        n_params,
        cauchy: config.cauchy_px,
    };
    let min_angle = config.min_angle_deg.to_radians();
    let points: Vec<Point> = tracks
        .iter()
        .filter_map(|t| {
            triangulate(t, cameras, intrinsics, *phi, min_angle).map(|x| Point {
                x,
                obs: t
                    .iter()
                    .filter(|o| cameras[o.image].is_some())
                    .copied()
                    .collect(),
            })
        })
        .collect();
    let mut points = filter(points, cameras, intrinsics, *phi, config.max_error_px);
    let mut report = BundleReport {
        tracks: tracks.len(),
        ..BundleReport::default()
    };
    if points.is_empty() {
        return Ok(report);
    }
    report.iterations += adjust(&layout, cameras, phi, &mut points, reference, config);
    points = filter(points, cameras, intrinsics, *phi, config.max_error_px);
    report.iterations += adjust(&layout, cameras, phi, &mut points, reference, config);
    let (mut sum, mut count) = (0.0, 0usize);
    for p in &points {
        for o in &p.obs {
            if let Some(c) = cameras[o.image]
                && let Some((uv, _)) = project(
                    &c,
                    *phi * intrinsics.scale[o.image],
                    intrinsics.principal[o.image],
                    &p.x,
                )
            {
                sum += (uv[0] - o.xy[0]).powi(2) + (uv[1] - o.xy[1]).powi(2);
                count += 1;
            }
        }
    }
    report.points = points.len();
    report.observations = count;
    report.rms_px = if count > 0 {
        (sum / count as f64).sqrt()
    } else {
        0.0
    };
    Ok(report)
}

#[cfg(test)]
mod tests {
    #![allow(clippy::unwrap_used)]
    use super::*;

    #[test]
    fn tracks_join_matches_through_shared_keypoints() {
        let (a, b, c) = ([1.0, 2.0], [3.0, 4.0], [5.0, 6.0]);
        let kp_ab = ([a], [b]);
        let kp_bc = ([b], [c]);
        // A keypoint of image 0 matched to two keypoints of image 2: inconsistent, dropped.
        let bad1 = [[9.0, 9.0], [9.0, 9.0]];
        let bad2 = [[7.0, 7.0], [8.0, 8.0]];
        let tracks = build_tracks(
            3,
            [
                (0, 1, &kp_ab.0[..], &kp_ab.1[..]),
                (1, 2, &kp_bc.0[..], &kp_bc.1[..]),
                (0, 2, &bad1[..], &bad2[..]),
            ],
        );
        assert_eq!(tracks.len(), 1);
        let images: Vec<usize> = tracks[0].iter().map(|o| o.image).collect();
        assert_eq!(images, vec![0, 1, 2]);
    }
}
