//! GGS's objective run to convergence: all cameras and one shared focal refined by
//! Levenberg–Marquardt on the Sampson residuals of the matches.
//!
//! The official GGS takes 7000 clipped SGD steps on the mean truncated Sampson error
//! ([`crate::ggs`]). Outside the diffusion loop there is no reason to stop at a fixed count:
//! here every match contributes the signed Sampson distance `r = x_bᵀFx_a / ‖(Fx_a)₁,₂,
//! (Fᵀx_b)₁,₂‖` (pixels; `r²` is the Sampson error GGS averages), robustified by a Cauchy loss
//! `ρ(r) = c²/2 · ln(1 + r²/c²)`, and the parameters move by damped Gauss–Newton steps until
//! the cost stops falling. A second stage then truncates the loss at `3c`, so that matches
//! far from their epipolar lines stop pulling at all (Cauchy's influence decays only as `1/r`).
//!
//! Parameters: per camera a rotation increment `ω` (`R ← exp(ω)R`) and its centre `C`
//! (world → camera `x = R(X − C)`, OpenCV), plus `log φ` with focal `f_i = φ·s_i` shared by all
//! images (principal points fixed). The reference camera is held fixed and the centres are
//! rescaled to unit mean distance from it after every step (the scale is not observable).
//! `∂r/∂F` is analytic; `∂F/∂θ` per pair by central differences of the closed form
//! `F = K_b⁻ᵀ [t]ₓ R K_a⁻¹` (13 parameters per pair, exact to ~1e-10).

use nalgebra::{DMatrix, DVector, Matrix3, Rotation3, SMatrix, SVector, Vector3};
use posediff_geometry::epipolar::skew;

use crate::error::{GuidanceError, Result};
use crate::matches::{MatchSet, PairGroup};

/// One camera's extrinsics: `x_cam = R (X − C)`.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct RefineCamera {
    /// World → camera rotation.
    pub rotation: Rotation3<f64>,
    /// Camera centre in the world.
    pub center: Vector3<f64>,
}

/// Fixed per-image intrinsics other than the shared focal factor.
#[derive(Debug, Clone, PartialEq)]
pub struct ImageIntrinsics {
    /// Principal point per image (pixels).
    pub principal: Vec<[f64; 2]>,
    /// `f_i = φ · scale_i` per image.
    pub scale: Vec<f64>,
}

/// Refinement settings.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct RefineConfig {
    /// Cauchy scale of the Sampson distance, pixels.
    pub cauchy_px: f64,
    /// Iteration limit (each iteration is one accepted step).
    pub max_iterations: usize,
    /// Refine `φ` (false: keep the given focal).
    pub refine_focal: bool,
    /// Converged when the relative cost decrease of a step is below this.
    pub tolerance: f64,
    /// A second stage where matches farther than this many Cauchy scales from their epipolar
    /// geometry stop pulling (a truncated loss); `None` skips it.
    pub gate_scales: Option<f64>,
}

impl Default for RefineConfig {
    fn default() -> Self {
        Self {
            cauchy_px: 1.0,
            max_iterations: 200,
            refine_focal: true,
            tolerance: 1e-10,
            gate_scales: Some(3.0),
        }
    }
}

/// What the refinement did.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct RefineReport {
    /// Accepted steps.
    pub iterations: usize,
    /// Whether it stopped because the cost stopped falling (not at the iteration limit).
    pub converged: bool,
    /// Robust cost before.
    pub initial_cost: f64,
    /// Robust cost after.
    pub final_cost: f64,
    /// Matches with `|r| < 3c` at the end.
    pub inliers: usize,
    /// Matches used.
    pub matches: usize,
    /// RMS of `r` over those inliers, pixels.
    pub inlier_rms_px: f64,
}

type PairJacobian = SMatrix<f64, 9, 13>;

/// Central-difference step of `∂F/∂θ`: radians, centre units (unit mean distance) and `log φ`
/// alike; the truncation error is ~1e-12 relative.
const DIFF_STEP: f64 = 1e-6;

fn intrinsics_inverse(phi: f64, scale: f64, principal: [f64; 2]) -> Matrix3<f64> {
    let f = phi * scale;
    Matrix3::new(
        1.0 / f,
        0.0,
        -principal[0] / f,
        0.0,
        1.0 / f,
        -principal[1] / f,
        0.0,
        0.0,
        1.0,
    )
}

/// `F_{b←a}` (`x_bᵀ F x_a = 0`) of two cameras with focal factor `phi`.
pub fn pair_fundamental(
    a: &RefineCamera,
    b: &RefineCamera,
    phi: f64,
    intrinsics: &ImageIntrinsics,
    ia: usize,
    ib: usize,
) -> Matrix3<f64> {
    let r = b.rotation * a.rotation.inverse();
    let t = b.rotation * (a.center - b.center);
    let e = skew(&t) * r.matrix();
    intrinsics_inverse(phi, intrinsics.scale[ib], intrinsics.principal[ib]).transpose()
        * e
        * intrinsics_inverse(phi, intrinsics.scale[ia], intrinsics.principal[ia])
}

/// The cameras of a pair moved by `theta = [ω_a, δC_a, ω_b, δC_b, δ log φ]`.
fn perturbed(
    a: &RefineCamera,
    b: &RefineCamera,
    phi: f64,
    theta: &SVector<f64, 13>,
) -> (RefineCamera, RefineCamera, f64) {
    let step = |c: &RefineCamera, o: usize| RefineCamera {
        rotation: Rotation3::from_scaled_axis(Vector3::new(theta[o], theta[o + 1], theta[o + 2]))
            * c.rotation,
        center: c.center + Vector3::new(theta[o + 3], theta[o + 4], theta[o + 5]),
    };
    (step(a, 0), step(b, 6), phi * theta[12].exp())
}

fn row_major(m: &Matrix3<f64>) -> [f64; 9] {
    [0, 1, 2, 3, 4, 5, 6, 7, 8].map(|k| m[(k / 3, k % 3)])
}

/// Signed Sampson distance of one match and its gradient with respect to `F` (row-major).
#[inline]
fn residual_and_gradient(f: &[f64; 9], x1: [f64; 2], x2: [f64; 2]) -> Option<(f64, [f64; 9])> {
    let p1 = [x1[0], x1[1], 1.0];
    let p2 = [x2[0], x2[1], 1.0];
    let l2 = [0, 1, 2].map(|r| f[3 * r] * p1[0] + f[3 * r + 1] * p1[1] + f[3 * r + 2]);
    let l1 = [0, 1].map(|c| f[c] * p2[0] + f[3 + c] * p2[1] + f[6 + c]);
    let e = p2[0] * l2[0] + p2[1] * l2[1] + l2[2];
    let d = l2[0] * l2[0] + l2[1] * l2[1] + l1[0] * l1[0] + l1[1] * l1[1];
    if d.is_nan() || d <= 1e-300 || !e.is_finite() {
        return None;
    }
    let sd = d.sqrt();
    let r = e / sd;
    let mut g = [0.0; 9];
    for a in 0..3 {
        for b in 0..3 {
            let de = p2[a] * p1[b];
            let mut dd = 0.0;
            if a < 2 {
                dd += 2.0 * l2[a] * p1[b];
            }
            if b < 2 {
                dd += 2.0 * l1[b] * p2[a];
            }
            g[3 * a + b] = de / sd - 0.5 * r * dd / d;
        }
    }
    Some((r, g))
}

/// The refinement problem: matches in original pixels, intrinsics, which cameras move.
struct Problem<'a> {
    matches: &'a MatchSet,
    intrinsics: &'a ImageIntrinsics,
    /// Global parameter offset of each camera's 6 values (`None`: fixed or not estimated).
    offset: Vec<Option<usize>>,
    /// Index of `log φ` when refined.
    focal_index: Option<usize>,
    n_params: usize,
    cauchy: f64,
    /// Residuals beyond this (px) cost a constant and do not pull (second stage).
    gate: Option<f64>,
}

impl Problem<'_> {
    /// Pairs with both cameras and a usable baseline.
    fn usable(&self, cams: &[Option<RefineCamera>], a: usize, b: usize) -> bool {
        match (cams[a], cams[b]) {
            (Some(ca), Some(cb)) => (ca.center - cb.center).norm() > 1e-9,
            _ => false,
        }
    }

    fn rho(&self, r: f64) -> f64 {
        let c2 = self.cauchy * self.cauchy;
        let r = match self.gate {
            Some(g) => r.abs().min(g),
            None => r,
        };
        0.5 * c2 * (1.0 + r * r / c2).ln()
    }

    /// The usable pairs with their two cameras and `F` (row-major).
    fn pairs<'s>(
        &'s self,
        cams: &'s [Option<RefineCamera>],
        phi: f64,
    ) -> impl Iterator<Item = (&'s PairGroup, RefineCamera, RefineCamera, [f64; 9])> + 's {
        self.matches.groups().iter().filter_map(move |g| {
            if !self.usable(cams, g.first, g.second) {
                return None;
            }
            let (a, b) = (cams[g.first]?, cams[g.second]?);
            let f = pair_fundamental(&a, &b, phi, self.intrinsics, g.first, g.second);
            Some((g, a, b, row_major(&f)))
        })
    }

    fn cost(&self, cams: &[Option<RefineCamera>], phi: f64) -> f64 {
        let m = self.matches;
        let mut total = 0.0;
        for (g, _, _, f) in self.pairs(cams, phi) {
            for k in g.start..g.end {
                if let Some((r, _)) =
                    residual_and_gradient(&f, [m.u1[k], m.v1[k]], [m.u2[k], m.v2[k]])
                {
                    total += self.rho(r);
                }
            }
        }
        total
    }

    /// Gauss–Newton normal equations with IRLS weights.
    fn normal_equations(
        &self,
        cams: &[Option<RefineCamera>],
        phi: f64,
    ) -> (DMatrix<f64>, DVector<f64>) {
        let m = self.matches;
        let mut h = DMatrix::<f64>::zeros(self.n_params, self.n_params);
        let mut grad = DVector::<f64>::zeros(self.n_params);
        let c2 = self.cauchy * self.cauchy;
        for (g, a, b, f0) in self.pairs(cams, phi) {
            let mut df = PairJacobian::zeros();
            for p in 0..13 {
                let step = DIFF_STEP;
                let mut theta = SVector::<f64, 13>::zeros();
                theta[p] = step;
                let (pa, pb, pf) = perturbed(&a, &b, phi, &theta);
                let plus = pair_fundamental(&pa, &pb, pf, self.intrinsics, g.first, g.second);
                theta[p] = -step;
                let (ma, mb, mf) = perturbed(&a, &b, phi, &theta);
                let minus = pair_fundamental(&ma, &mb, mf, self.intrinsics, g.first, g.second);
                let d = row_major(&((plus - minus) / (2.0 * step)));
                for (k, v) in d.iter().enumerate() {
                    df[(k, p)] = *v;
                }
            }
            let mut hp = SMatrix::<f64, 13, 13>::zeros();
            let mut gp = SVector::<f64, 13>::zeros();
            for k in g.start..g.end {
                let Some((r, gr)) =
                    residual_and_gradient(&f0, [m.u1[k], m.v1[k]], [m.u2[k], m.v2[k]])
                else {
                    continue;
                };
                let j = df.transpose() * SVector::<f64, 9>::from(gr);
                if self.gate.is_some_and(|g| r.abs() >= g) {
                    continue;
                }
                let w = 1.0 / (1.0 + r * r / c2);
                hp += j * j.transpose() * w;
                gp += j * (w * r);
            }
            let map: [Option<usize>; 13] = std::array::from_fn(|p| match p {
                0..6 => self.offset[g.first].map(|o| o + p),
                6..12 => self.offset[g.second].map(|o| o + p - 6),
                _ => self.focal_index,
            });
            for (p, gi) in map.iter().enumerate() {
                let Some(gi) = *gi else { continue };
                grad[gi] += gp[p];
                for (q, gj) in map.iter().enumerate() {
                    if let Some(gj) = *gj {
                        h[(gi, gj)] += hp[(p, q)];
                    }
                }
            }
        }
        (h, grad)
    }

    fn apply(
        &self,
        cams: &[Option<RefineCamera>],
        phi: f64,
        step: &DVector<f64>,
    ) -> (Vec<Option<RefineCamera>>, f64) {
        let moved = cams
            .iter()
            .zip(&self.offset)
            .map(|(c, o)| match (c, o) {
                (Some(c), Some(o)) => Some(RefineCamera {
                    rotation: Rotation3::from_scaled_axis(Vector3::new(
                        step[*o],
                        step[o + 1],
                        step[o + 2],
                    )) * c.rotation,
                    center: c.center + Vector3::new(step[o + 3], step[o + 4], step[o + 5]),
                }),
                (c, _) => *c,
            })
            .collect();
        let phi = self.focal_index.map_or(phi, |i| phi * step[i].exp());
        (moved, phi)
    }

    fn statistics(&self, cams: &[Option<RefineCamera>], phi: f64) -> (usize, usize, f64) {
        let m = self.matches;
        let (mut inliers, mut used, mut sum) = (0, 0, 0.0);
        for (g, _, _, f) in self.pairs(cams, phi) {
            for k in g.start..g.end {
                if let Some((r, _)) =
                    residual_and_gradient(&f, [m.u1[k], m.v1[k]], [m.u2[k], m.v2[k]])
                {
                    used += 1;
                    if r.abs() < 3.0 * self.cauchy {
                        inliers += 1;
                        sum += r * r;
                    }
                }
            }
        }
        let rms = if inliers > 0 {
            (sum / inliers as f64).sqrt()
        } else {
            0.0
        };
        (inliers, used, rms)
    }
}

/// Damped Gauss–Newton steps until the relative decrease falls below the tolerance, no step
/// lowers the cost, or `max_iterations` steps were taken. Returns the steps, whether it
/// converged and the final cost.
fn levenberg_marquardt(
    problem: &Problem<'_>,
    cameras: &mut [Option<RefineCamera>],
    phi: &mut f64,
    reference: usize,
    config: &RefineConfig,
    max_iterations: usize,
) -> (usize, bool, f64) {
    let n_params = problem.n_params;
    let mut cost = problem.cost(cameras, *phi);
    let mut lambda = 1e-4;
    let mut iterations = 0;
    let mut converged = n_params == 0;
    while !converged && iterations < max_iterations {
        let (h, g) = problem.normal_equations(cameras, *phi);
        let floor = 1e-12 * h.diagonal().max().max(1e-300);
        let mut accepted = false;
        for _ in 0..12 {
            let mut a = h.clone();
            for k in 0..n_params {
                a[(k, k)] += lambda * h[(k, k)] + floor;
            }
            let Some(chol) = a.cholesky() else {
                lambda *= 10.0;
                continue;
            };
            let step = chol.solve(&(-&g));
            let (mut moved, new_phi) = problem.apply(cameras, *phi, &step);
            normalize_scale(&mut moved, reference);
            let new_cost = problem.cost(&moved, new_phi);
            if new_cost.is_finite() && new_cost < cost && new_phi.is_finite() {
                let decrease = (cost - new_cost) / cost.max(1e-300);
                cameras.copy_from_slice(&moved);
                *phi = new_phi;
                cost = new_cost;
                lambda = (lambda / 3.0).max(1e-12);
                accepted = true;
                iterations += 1;
                converged = decrease < config.tolerance;
                break;
            }
            lambda *= 5.0;
        }
        if !accepted {
            converged = true;
        }
    }
    (iterations, converged, cost)
}

/// Where each camera's 6 parameters sit in the parameter vector (`None`: the reference or not
/// estimated), the focal's index when refined, and the parameter count, after checking the
/// inputs both adjustments share.
pub(crate) fn parameter_layout(
    n: usize,
    intrinsics: &ImageIntrinsics,
    cameras: &[Option<RefineCamera>],
    phi: f64,
    reference: usize,
    refine_focal: bool,
) -> Result<(Vec<Option<usize>>, Option<usize>, usize)> {
    for (what, len) in [
        ("cameras", cameras.len()),
        ("principal points", intrinsics.principal.len()),
        ("focal scales", intrinsics.scale.len()),
    ] {
        if len != n {
            return Err(GuidanceError::LengthMismatch {
                what,
                left: n,
                right: len,
            });
        }
    }
    if cameras.get(reference).copied().flatten().is_none() {
        return Err(GuidanceError::InvalidConfig {
            reason: "the reference camera must be estimated",
        });
    }
    if !(phi > 0.0 && phi.is_finite()) {
        return Err(GuidanceError::NonFinite {
            what: "focal factor",
        });
    }
    let mut next = 0;
    let offset: Vec<Option<usize>> = cameras
        .iter()
        .enumerate()
        .map(|(i, c)| {
            (c.is_some() && i != reference).then(|| {
                next += 6;
                next - 6
            })
        })
        .collect();
    let focal_index = refine_focal.then_some(next);
    Ok((offset, focal_index, next + usize::from(refine_focal)))
}

/// Rescales the centres about the reference's to unit mean distance.
fn normalize_scale(cams: &mut [Option<RefineCamera>], reference: usize) {
    let Some(origin) = cams.get(reference).copied().flatten().map(|c| c.center) else {
        return;
    };
    let distances: Vec<f64> = cams
        .iter()
        .flatten()
        .map(|c| (c.center - origin).norm())
        .collect();
    let mean = distances.iter().sum::<f64>() / distances.len().max(1) as f64;
    if mean > 0.0 && mean.is_finite() {
        for c in cams.iter_mut().flatten() {
            c.center = origin + (c.center - origin) / mean;
        }
    }
}

/// The robust cost `Σ ρ(r)` of all matches under `cameras`; a match whose pair lacks a camera
/// (or a baseline) costs `ρ(missing_px)`. Compares solutions that estimate different images.
///
/// # Errors
/// Inputs of the wrong length.
pub fn robust_cost(
    matches: &MatchSet,
    intrinsics: &ImageIntrinsics,
    cameras: &[Option<RefineCamera>],
    phi: f64,
    cauchy_px: f64,
    missing_px: f64,
) -> Result<f64> {
    let n = matches.n_frames();
    if cameras.len() != n || intrinsics.principal.len() != n || intrinsics.scale.len() != n {
        return Err(GuidanceError::LengthMismatch {
            what: "cameras / intrinsics",
            left: n,
            right: cameras.len(),
        });
    }
    let problem = Problem {
        matches,
        intrinsics,
        offset: vec![None; n],
        focal_index: None,
        n_params: 0,
        cauchy: cauchy_px,
        gate: None,
    };
    let counted: usize = matches
        .groups()
        .iter()
        .filter(|g| problem.usable(cameras, g.first, g.second))
        .map(|g| g.end - g.start)
        .sum();
    let missing = (matches.len() - counted) as f64 * problem.rho(missing_px);
    Ok(problem.cost(cameras, phi) + missing)
}

/// Refines `cameras` (`None`: not estimated, left alone) and `phi` in place on `matches`
/// (original-image pixels). `reference` stays fixed.
///
/// # Errors
/// Intrinsics or cameras of the wrong length, a reference without a camera, a non-positive
/// or non-finite `phi`, invalid settings.
pub fn refine_cameras(
    matches: &MatchSet,
    intrinsics: &ImageIntrinsics,
    cameras: &mut [Option<RefineCamera>],
    phi: &mut f64,
    reference: usize,
    config: &RefineConfig,
) -> Result<RefineReport> {
    if !(config.cauchy_px > 0.0 && config.cauchy_px.is_finite()) {
        return Err(GuidanceError::InvalidConfig {
            reason: "cauchy_px must be positive and finite",
        });
    }
    let (offset, focal_index, n_params) = parameter_layout(
        matches.n_frames(),
        intrinsics,
        cameras,
        *phi,
        reference,
        config.refine_focal,
    )?;
    let mut problem = Problem {
        matches,
        intrinsics,
        offset,
        focal_index,
        n_params,
        cauchy: config.cauchy_px,
        gate: None,
    };
    normalize_scale(cameras, reference);
    let initial_cost = problem.cost(cameras, *phi);
    let (mut iterations, mut converged, mut cost) = levenberg_marquardt(
        &problem,
        cameras,
        phi,
        reference,
        config,
        config.max_iterations,
    );
    if let Some(gate) = config.gate_scales {
        // Second stage: matches beyond the gate no longer pull at all.
        problem.gate = Some(gate * config.cauchy_px);
        let (more, done, gated) = levenberg_marquardt(
            &problem,
            cameras,
            phi,
            reference,
            config,
            config.max_iterations.saturating_sub(iterations),
        );
        iterations += more;
        converged &= done;
        cost = gated;
    }
    let (inliers, used, rms) = problem.statistics(cameras, *phi);
    Ok(RefineReport {
        iterations,
        converged,
        initial_cost,
        final_cost: cost,
        inliers,
        matches: used,
        inlier_rms_px: rms,
    })
}

#[cfg(test)]
mod tests {
    #![allow(clippy::unwrap_used)]
    use super::*;

    #[test]
    fn sampson_gradient_matches_finite_differences() {
        let f = [1e-6, 2e-5, -3e-3, -1e-5, 3e-6, 4e-3, 2e-3, -5e-3, 1.0];
        let (x1, x2) = ([100.0, 50.0], [120.0, 40.0]);
        let (_, g) = residual_and_gradient(&f, x1, x2).unwrap();
        for k in 0..9 {
            let h = 1e-7 * f[k].abs().max(1e-6);
            let mut p = f;
            p[k] += h;
            let mut m = f;
            m[k] -= h;
            let fd = (residual_and_gradient(&p, x1, x2).unwrap().0
                - residual_and_gradient(&m, x1, x2).unwrap().0)
                / (2.0 * h);
            assert!(
                (fd - g[k]).abs() <= 1e-5 * fd.abs().max(1e-3),
                "{k}: {fd} vs {}",
                g[k]
            );
        }
    }
}
