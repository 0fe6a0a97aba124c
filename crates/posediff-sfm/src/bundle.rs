//! Bundle adjustment with tracks: the cameras, the shared focal and triangulated points refined
//! together on reprojection errors (the last stage of the mapper).
//!
//! 1. Each track ([`crate::tracks`]) is triangulated (linear, from normalised rays, by a faer
//!    SVD) from the estimated cameras; points behind a camera, with a widest ray angle below
//!    `min_angle_deg` or observations farther than `max_error_px` from their projections are
//!    left out.
//! 2. Levenberg–Marquardt ([`crate::lm`]) on the reprojection errors (Cauchy loss), with the
//!    points eliminated by the Schur complement: the reduced camera system is a sparse block
//!    system (6 per camera, 1 for the focal; a block wherever two cameras see a common point)
//!    whose symbolic Cholesky factorisation is computed once per adjustment. Gauge as in
//!    [`crate::camera`] (points rescaled with the centres).
//! 3. Observations off by more than `max_error_px` are dropped and the adjustment runs again.
//!
//! Jacobians are analytic: `x_c = exp(ω) R (X − C)` gives `∂x_c/∂ω = −[x_c]ₓ`,
//! `∂x_c/∂C = −R`, `∂x_c/∂X = R`, and `∂uv/∂log φ = uv − pp`.

use nalgebra::{Matrix3, SMatrix, SVector, Vector3};
use rayon::prelude::*;

use crate::camera::{CameraPose, ParameterLayout, gauge_scale};
use crate::error::Result;
use crate::intrinsics::ImageIntrinsics;
use crate::linalg::{BlockSystem, Solver};
use crate::lm::{LeastSquares, LmOptions, Termination, minimize};
use crate::sampson_refine::check_inputs;
use crate::tracks::{Observation, Track};

/// Bundle-adjustment settings.
#[derive(Debug, Clone, Copy, PartialEq)]
#[cfg_attr(
    feature = "serde",
    derive(serde::Serialize, serde::Deserialize),
    serde(default, deny_unknown_fields)
)]
pub struct BundleOptions {
    /// Cauchy scale of the reprojection error, pixels.
    pub cauchy_px: f64,
    /// Observations farther than this from their projection are dropped (pixels).
    pub max_error_px: f64,
    /// Smallest widest-ray angle of a triangulated point, degrees.
    pub min_angle_deg: f64,
    /// Refine the shared focal factor.
    pub refine_focal: bool,
    /// Iterations per adjustment.
    pub max_iterations: usize,
    /// Converged when the relative cost decrease of a step is below this.
    pub tolerance: f64,
    /// Linear solver of the reduced camera system.
    pub solver: Solver,
    /// Observations kept per track, spread evenly over its images (in image order: the widest
    /// baselines of a video stay). The Schur complement costs `Σ k²` per iteration, so a dense
    /// video whose points are seen in hundreds of frames would otherwise make the adjustment
    /// grow with the square of the frames.
    pub max_track_length: usize,
}

impl Default for BundleOptions {
    fn default() -> Self {
        Self {
            cauchy_px: 1.0,
            max_error_px: 4.0,
            min_angle_deg: 1.0,
            refine_focal: true,
            max_iterations: 100,
            tolerance: 1e-10,
            solver: Solver::Sparse,
            max_track_length: 20,
        }
    }
}

/// At most `max` of `obs`, evenly spaced, the first and the last kept.
fn spread(obs: Vec<Observation>, max: usize) -> Vec<Observation> {
    let n = obs.len();
    if max < 2 || n <= max {
        return obs;
    }
    (0..max)
        .map(|i| obs[(i * (n - 1) + (max - 1) / 2) / (max - 1)])
        .collect()
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
    /// Why the last adjustment stopped.
    pub termination: Termination,
    /// Whether both adjustments stopped at a minimum (not at the iteration limit).
    pub converged: bool,
    /// RMS reprojection error of the used observations at the end, pixels.
    pub rms_px: f64,
}

/// A triangulated point with the observations it keeps.
#[derive(Debug, Clone, PartialEq)]
pub struct Point {
    /// World position.
    pub xyz: Vector3<f64>,
    /// Its observations.
    pub observations: Vec<Observation>,
}

/// Projection of `x` by camera `c` with focal `f`, and the point in the camera frame; `None`
/// behind the camera.
pub fn project(
    c: &CameraPose,
    f: f64,
    pp: [f64; 2],
    x: &Vector3<f64>,
) -> Option<([f64; 2], Vector3<f64>)> {
    let xc = c.rotation * (x - c.center);
    (xc.z > 1e-12).then(|| ([f * xc.x / xc.z + pp[0], f * xc.y / xc.z + pp[1]], xc))
}

/// Linear triangulation from normalised rays (faer SVD); `None` when degenerate, behind a
/// camera or narrower than `min_angle` (radians).
pub fn triangulate(
    obs: &[Observation],
    cameras: &[Option<CameraPose>],
    intrinsics: &ImageIntrinsics,
    phi: f64,
    min_angle: f64,
) -> Option<Vector3<f64>> {
    let used: Vec<(&Observation, CameraPose)> = obs
        .iter()
        .filter_map(|o| cameras.get(o.image).copied().flatten().map(|c| (o, c)))
        .collect();
    if used.len() < 2 {
        return None;
    }
    let mut rays = Vec::with_capacity(used.len());
    let mut rows = Vec::with_capacity(used.len());
    for (o, c) in &used {
        let x = intrinsics.k_inverse(phi, o.image) * Vector3::new(o.xy[0], o.xy[1], 1.0);
        rows.push(([x.x, x.y], *c.rotation.matrix(), c.translation()));
        rays.push(c.rotation.inverse() * x.normalize());
    }
    let point = crate::points::dlt(&rows)?;
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

/// One observation's linearisation.
#[derive(Debug, Clone, Copy)]
struct ObservationLinearisation {
    image: usize,
    /// `∂uv/∂[ω, δC, log φ]`.
    jc: SMatrix<f64, 2, 7>,
    /// `∂uv/∂X`.
    jp: SMatrix<f64, 2, 3>,
    r: SVector<f64, 2>,
    w: f64,
}

/// One point's linearisation: `C = Σ w J_pᵀJ_p`, `g_p`, and its observations.
#[derive(Debug, Clone)]
struct PointLinearisation {
    c: Matrix3<f64>,
    g: Vector3<f64>,
    obs: Vec<ObservationLinearisation>,
}

type State = (Vec<Option<CameraPose>>, f64, Vec<Vector3<f64>>);

struct Problem<'a> {
    intrinsics: &'a ImageIntrinsics,
    /// Each point's observations (borrowed from the points being adjusted).
    observations: Vec<&'a [Observation]>,
    layout: ParameterLayout,
    reference: usize,
    cauchy: f64,
    system: BlockSystem,
    linear: Vec<PointLinearisation>,
    /// Point steps of the last solve.
    point_steps: Vec<Vector3<f64>>,
    /// Per point, for its observation pairs `(k, l)`, `l < k` in order: the slot of the two
    /// cameras' block (unused where one is fixed).
    pair_slots: Vec<Vec<usize>>,
    /// Per block, the slot of its diagonal block.
    diagonal_slot: Vec<usize>,
    /// Per camera block, the slot of the focal × camera block (unused without a focal).
    focal_slot: Vec<usize>,
}

/// The slots [`Problem::solve`] adds to, looked up once per adjustment.
fn slots(
    system: &BlockSystem,
    layout: &ParameterLayout,
    observations: &[&[Observation]],
) -> (Vec<Vec<usize>>, Vec<usize>, Vec<usize>) {
    let pair_slots = observations
        .iter()
        .map(|obs| {
            let mut s = Vec::with_capacity(obs.len() * obs.len().saturating_sub(1) / 2);
            for k in 0..obs.len() {
                for l in 0..k {
                    let slot = match (layout.block[obs[k].image], layout.block[obs[l].image]) {
                        (Some(a), Some(b)) => system.slot(a, b).unwrap_or(usize::MAX),
                        _ => usize::MAX,
                    };
                    s.push(slot);
                }
            }
            s
        })
        .collect();
    let blocks = layout.block_sizes.len();
    let diagonal_slot = (0..blocks)
        .map(|b| system.slot(b, b).unwrap_or(usize::MAX))
        .collect();
    let focal_slot = (0..blocks)
        .map(|b| {
            layout
                .focal_block
                .and_then(|f| system.slot(f, b))
                .unwrap_or(usize::MAX)
        })
        .collect();
    (pair_slots, diagonal_slot, focal_slot)
}

impl Problem<'_> {
    fn rho(&self, e2: f64) -> f64 {
        let c2 = self.cauchy * self.cauchy;
        0.5 * c2 * (1.0 + e2 / c2).ln()
    }
}

impl LeastSquares for Problem<'_> {
    type State = State;

    fn n_params(&self) -> usize {
        self.layout.n_params
    }

    fn cost(&self, (cams, phi, points): &State) -> f64 {
        let per_point: Vec<f64> = self
            .observations
            .par_iter()
            .zip(points)
            .map(|(obs, x)| {
                let mut total = 0.0;
                for o in obs.iter() {
                    let Some(c) = cams[o.image] else { continue };
                    let f = self.intrinsics.focal(*phi, o.image);
                    total += match project(&c, f, self.intrinsics.principal[o.image], x) {
                        Some((uv, _)) => {
                            self.rho((uv[0] - o.xy[0]).powi(2) + (uv[1] - o.xy[1]).powi(2))
                        }
                        None => self.rho(1e6),
                    };
                }
                total
            })
            .collect();
        per_point.iter().sum()
    }

    fn linearize(&mut self, (cams, phi, points): &State) -> Result<()> {
        let c2 = self.cauchy * self.cauchy;
        let intrinsics = self.intrinsics;
        self.linear = self
            .observations
            .par_iter()
            .zip(points)
            .map(|(obs, x)| {
                let mut lin = PointLinearisation {
                    c: Matrix3::zeros(),
                    g: Vector3::zeros(),
                    obs: Vec::with_capacity(obs.len()),
                };
                for o in obs.iter() {
                    let Some(cam) = cams[o.image] else { continue };
                    let f = intrinsics.focal(*phi, o.image);
                    let pp = intrinsics.principal[o.image];
                    let Some((uv, xc)) = project(&cam, f, pp, x) else {
                        continue;
                    };
                    let r = SVector::<f64, 2>::new(uv[0] - o.xy[0], uv[1] - o.xy[1]);
                    let w = 1.0 / (1.0 + r.norm_squared() / c2);
                    let iz = 1.0 / xc.z;
                    let d = SMatrix::<f64, 2, 3>::new(
                        f * iz,
                        0.0,
                        -f * xc.x * iz * iz,
                        0.0,
                        f * iz,
                        -f * xc.y * iz * iz,
                    );
                    let jp = d * cam.rotation.matrix();
                    let skew = Matrix3::new(0.0, -xc.z, xc.y, xc.z, 0.0, -xc.x, -xc.y, xc.x, 0.0);
                    let mut jc = SMatrix::<f64, 2, 7>::zeros();
                    jc.fixed_view_mut::<2, 3>(0, 0).copy_from(&(d * (-skew)));
                    jc.fixed_view_mut::<2, 3>(0, 3).copy_from(&(-jp));
                    jc[(0, 6)] = uv[0] - pp[0];
                    jc[(1, 6)] = uv[1] - pp[1];
                    lin.c += jp.transpose() * jp * w;
                    lin.g += jp.transpose() * r * w;
                    lin.obs.push(ObservationLinearisation {
                        image: o.image,
                        jc,
                        jp,
                        r,
                        w,
                    });
                }
                lin
            })
            .collect();
        Ok(())
    }

    fn solve(&mut self, lambda: f64) -> Result<Option<Vec<f64>>> {
        self.system.clear();
        let mut inverses = Vec::with_capacity(self.linear.len());
        let focal = self.layout.focal_block;
        let mut es: Vec<SMatrix<f64, 7, 3>> = Vec::new();
        let mut ecs: Vec<SMatrix<f64, 7, 3>> = Vec::new();
        let mut blocks: Vec<Option<usize>> = Vec::new();
        let mut focal_rows: Vec<SVector<f64, 6>> = Vec::new();
        // Per point: the camera terms minus the point's elimination, S = A − Σ E C⁻¹ Eᵀ and
        // rhs = −g + Σ E C⁻¹ g_p, each block added once (lower triangle), slots precomputed.
        for (p, lin) in self.linear.iter().enumerate() {
            let mut c = lin.c;
            for k in 0..3 {
                c[(k, k)] = c[(k, k)] * (1.0 + lambda) + 1e-12;
            }
            let Some(c_inv) = c.try_inverse() else {
                // Not invertible at this damping: more damping makes it so.
                return Ok(None);
            };
            // Per observation: E = J_cᵀ W J_p, E C⁻¹, its camera block, and its focal row
            // (focal × that camera's pose); buffers reused from point to point.
            es.clear();
            es.extend(lin.obs.iter().map(|o| o.jc.transpose() * o.jp * o.w));
            ecs.clear();
            ecs.extend(es.iter().map(|e| e * c_inv));
            blocks.clear();
            blocks.extend(lin.obs.iter().map(|o| self.layout.block[o.image]));
            focal_rows.clear();
            focal_rows.resize(lin.obs.len(), SVector::zeros());
            let cg = c_inv * lin.g;
            let mut focal_diag = 0.0;
            let mut pair = 0;
            for (k, o) in lin.obs.iter().enumerate() {
                let hcc = o.jc.transpose() * o.jc * o.w;
                let gc = o.jc.transpose() * o.r * o.w;
                let v = es[k] * cg;
                let own = hcc - ecs[k] * es[k].transpose();
                if let Some(b) = blocks[k] {
                    self.system.add_rhs(b, |i| -gc[i] + v[i]);
                    self.system
                        .add_block_at(self.diagonal_slot[b], b, b, |i, j| own[(i, j)]);
                }
                if let Some(f) = focal {
                    self.system.add_rhs(f, |_| -gc[6] + v[6]);
                    focal_diag += own[(6, 6)];
                }
                for i in 0..6 {
                    focal_rows[k][i] += own[(6, i)];
                }
                for l in 0..k {
                    let slot = self.pair_slots[p][pair];
                    pair += 1;
                    let m = ecs[k] * es[l].transpose();
                    if let (Some(bk), Some(bl)) = (blocks[k], blocks[l]) {
                        self.system.add_block_at(slot, bk, bl, |i, j| -m[(i, j)]);
                    }
                    // m_lk = m_klᵀ: its focal row is m_kl's focal column.
                    for i in 0..6 {
                        focal_rows[l][i] -= m[(6, i)];
                        focal_rows[k][i] -= m[(i, 6)];
                    }
                    focal_diag -= 2.0 * m[(6, 6)];
                }
            }
            if let Some(f) = focal {
                for (k, row) in focal_rows.iter().enumerate() {
                    if let Some(b) = blocks[k] {
                        self.system
                            .add_block_at(self.focal_slot[b], f, b, |_, j| row[j]);
                    }
                }
                self.system
                    .add_block_at(self.diagonal_slot[f], f, f, |_, _| focal_diag);
            }
            inverses.push(c_inv);
        }
        let Some(delta) = self.system.solve_regularised(lambda)? else {
            return Ok(None);
        };
        // Back-substitution: δp = −C⁻¹ (g_p + Σ Eᵀ δc).
        self.point_steps = self
            .linear
            .iter()
            .zip(&inverses)
            .map(|(lin, c_inv)| {
                let mut v = lin.g;
                for o in &lin.obs {
                    let mut dc = SVector::<f64, 7>::zeros();
                    if let Some(off) = self.layout.offset[o.image] {
                        for i in 0..6 {
                            dc[i] = delta[off + i];
                        }
                    }
                    if let Some(fi) = self.layout.focal {
                        dc[6] = delta[fi];
                    }
                    v += (o.jc.transpose() * o.jp * o.w).transpose() * dc;
                }
                -(c_inv * v)
            })
            .collect();
        Ok(Some(delta))
    }

    fn apply(&self, (cams, phi, points): &State, step: &[f64]) -> State {
        let (mut moved, phi) = self.layout.apply(cams, *phi, step);
        let mut points: Vec<Vector3<f64>> = points
            .iter()
            .zip(&self.point_steps)
            .map(|(x, s)| x + s)
            .collect();
        if let Some((origin, s)) = gauge_scale(&moved, self.reference) {
            for c in moved.iter_mut().flatten() {
                c.center = origin + (c.center - origin) * s;
            }
            for x in &mut points {
                *x = origin + (*x - origin) * s;
            }
        }
        (moved, phi, points)
    }
}

/// Keeps the observations within `max_error_px` of their projection; points with fewer than
/// two left are dropped.
fn filter(
    points: Vec<Point>,
    cameras: &[Option<CameraPose>],
    intrinsics: &ImageIntrinsics,
    phi: f64,
    max_error_px: f64,
) -> Vec<Point> {
    points
        .into_iter()
        .filter_map(|mut p| {
            p.observations.retain(|o| {
                cameras[o.image].is_some_and(|c| {
                    project(
                        &c,
                        intrinsics.focal(phi, o.image),
                        intrinsics.principal[o.image],
                        &p.xyz,
                    )
                    .is_some_and(|(uv, _)| (uv[0] - o.xy[0]).hypot(uv[1] - o.xy[1]) <= max_error_px)
                })
            });
            (p.observations.len() >= 2).then_some(p)
        })
        .collect()
}

/// One adjustment of `points` (in place) with the cameras and `φ`.
fn adjust(
    points: &mut [Point],
    intrinsics: &ImageIntrinsics,
    cameras: &mut [Option<CameraPose>],
    phi: &mut f64,
    reference: usize,
    options: &BundleOptions,
) -> Result<(usize, Termination)> {
    let layout = ParameterLayout::new(cameras, reference, options.refine_focal);
    let mut block_pairs = Vec::new();
    for p in points.iter() {
        for (k, a) in p.observations.iter().enumerate() {
            let ba = layout.block[a.image];
            if let (Some(x), Some(f)) = (ba, layout.focal_block) {
                block_pairs.push((x, f));
            }
            for b in &p.observations[k + 1..] {
                if let (Some(x), Some(y)) = (ba, layout.block[b.image]) {
                    block_pairs.push((x, y));
                }
            }
        }
    }
    block_pairs.sort_unstable();
    block_pairs.dedup();
    let system = BlockSystem::new(
        "bundle adjustment (reduced camera system)",
        &layout.block_sizes,
        block_pairs,
        options.solver,
    )?;
    let observations: Vec<&[Observation]> =
        points.iter().map(|p| p.observations.as_slice()).collect();
    let (pair_slots, diagonal_slot, focal_slot) = slots(&system, &layout, &observations);
    let mut problem = Problem {
        intrinsics,
        observations,
        layout,
        reference,
        cauchy: options.cauchy_px,
        system,
        linear: Vec::new(),
        point_steps: Vec::new(),
        pair_slots,
        diagonal_slot,
        focal_slot,
    };
    let mut state: State = (
        cameras.to_vec(),
        *phi,
        points.iter().map(|p| p.xyz).collect(),
    );
    let lm = LmOptions {
        max_iterations: options.max_iterations,
        tolerance: options.tolerance,
        ..LmOptions::default()
    };
    let report = minimize(&mut problem, &mut state, &lm)?;
    drop(problem);
    cameras.copy_from_slice(&state.0);
    *phi = state.1;
    for (p, x) in points.iter_mut().zip(state.2) {
        p.xyz = x;
    }
    Ok((report.iterations, report.termination))
}

/// Adjusts `cameras` (`None`: not estimated) and `phi` in place on `tracks`; the reference
/// camera is held fixed. Returns the adjusted points with the observations they keep.
///
/// # Errors
/// Cameras or intrinsics of the wrong length, a reference without a camera, a non-positive
/// focal factor, a reduced camera system that is not positive definite at any damping.
pub fn bundle_adjust(
    tracks: &[Track],
    intrinsics: &ImageIntrinsics,
    cameras: &mut [Option<CameraPose>],
    phi: &mut f64,
    reference: usize,
    options: &BundleOptions,
) -> Result<(Vec<Point>, BundleReport)> {
    check_inputs(cameras.len(), intrinsics, cameras, *phi, reference)?;
    let min_angle = options.min_angle_deg.to_radians();
    let points: Vec<Point> = tracks
        .par_iter()
        .filter_map(|t| {
            let t: Vec<Observation> = spread(
                t.iter()
                    .filter(|o| cameras.get(o.image).copied().flatten().is_some())
                    .copied()
                    .collect(),
                options.max_track_length,
            );
            triangulate(&t, cameras, intrinsics, *phi, min_angle).map(|xyz| Point {
                xyz,
                observations: t,
            })
        })
        .collect();
    let mut points = filter(points, cameras, intrinsics, *phi, options.max_error_px);
    let mut report = BundleReport {
        tracks: tracks.len(),
        converged: true,
        termination: Termination::NothingToRefine,
        ..BundleReport::default()
    };
    if points.is_empty() {
        return Ok((points, report));
    }
    let (first, t1) = adjust(&mut points, intrinsics, cameras, phi, reference, options)?;
    points = filter(points, cameras, intrinsics, *phi, options.max_error_px);
    let (second, t2) = adjust(&mut points, intrinsics, cameras, phi, reference, options)?;
    report.iterations = first + second;
    report.converged = t1.converged() && t2.converged();
    report.termination = t2;
    let (mut sum, mut count) = (0.0, 0usize);
    for p in &points {
        for o in &p.observations {
            if let Some(c) = cameras[o.image]
                && let Some((uv, _)) = project(
                    &c,
                    intrinsics.focal(*phi, o.image),
                    intrinsics.principal[o.image],
                    &p.xyz,
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
    Ok((points, report))
}

#[cfg(test)]
mod tests {
    #![allow(clippy::unwrap_used)]
    use super::*;
    use nalgebra::Rotation3;

    #[test]
    fn long_tracks_are_spread_evenly() {
        let obs: Vec<Observation> = (0..100)
            .map(|i| Observation {
                image: i,
                keypoint: 0,
                xy: [0.0, 0.0],
            })
            .collect();
        let kept: Vec<usize> = spread(obs.clone(), 5).iter().map(|o| o.image).collect();
        assert_eq!(kept.len(), 5);
        assert_eq!((kept[0], kept[4]), (0, 99));
        assert!(
            kept.windows(2).all(|w| w[1] > w[0] && w[1] - w[0] >= 24),
            "{kept:?}"
        );
        assert_eq!(spread(obs[..4].to_vec(), 5).len(), 4);
    }

    /// The analytic reprojection Jacobian against central differences.
    #[test]
    fn reprojection_jacobian_matches_finite_differences() {
        let intrinsics = ImageIntrinsics {
            principal: vec![[320.0, 240.0]],
            scale: vec![640.0],
        };
        let cam = CameraPose {
            rotation: Rotation3::from_euler_angles(0.1, -0.2, 0.3),
            center: Vector3::new(0.2, -0.1, -3.0),
        };
        let x = Vector3::new(0.3, 0.2, 0.5);
        let phi = 1.1;
        let obs = vec![Observation {
            image: 0,
            keypoint: 0,
            xy: [0.0, 0.0],
        }];
        let layout = ParameterLayout::new(&[Some(cam)], usize::MAX, true);
        let mut problem = Problem {
            intrinsics: &intrinsics,
            observations: vec![&obs],
            layout,
            reference: usize::MAX,
            cauchy: 1.0,
            system: BlockSystem::new("t", &[6, 1], [(0, 1)], Solver::Dense).unwrap(),
            linear: Vec::new(),
            point_steps: Vec::new(),
            pair_slots: vec![Vec::new()],
            diagonal_slot: vec![0, 0],
            focal_slot: vec![0],
        };
        problem.linearize(&(vec![Some(cam)], phi, vec![x])).unwrap();
        let lin = problem.linear[0].obs[0];
        let uv = |theta: &[f64; 10]| {
            let c = cam.moved(&theta[0..6]);
            let p = x + Vector3::new(theta[7], theta[8], theta[9]);
            project(
                &c,
                intrinsics.focal(phi * theta[6].exp(), 0),
                [320.0, 240.0],
                &p,
            )
            .unwrap()
            .0
        };
        let h = 1e-6;
        for q in 0..10 {
            let (mut plus, mut minus) = ([0.0; 10], [0.0; 10]);
            plus[q] = h;
            minus[q] = -h;
            let (a, b) = (uv(&plus), uv(&minus));
            for row in 0..2 {
                let fd = (a[row] - b[row]) / (2.0 * h);
                let analytic = if q < 7 {
                    lin.jc[(row, q)]
                } else {
                    lin.jp[(row, q - 7)]
                };
                assert!(
                    (fd - analytic).abs() <= 1e-6 * fd.abs().max(1.0),
                    "param {q} row {row}: {fd} vs {analytic}"
                );
            }
        }
    }
}
