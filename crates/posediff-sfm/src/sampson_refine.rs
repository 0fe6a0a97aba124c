//! GGS's objective run to convergence: all cameras and one shared focal refined by
//! Levenberg–Marquardt ([`crate::lm`]) on the Sampson residuals of the matches.
//!
//! The official GGS takes 7000 clipped SGD steps on the mean truncated Sampson error
//! (`posediff-guidance`). Outside the diffusion loop there is no reason to stop at a fixed
//! count: here every match contributes the signed Sampson distance `r = x_bᵀFx_a /
//! ‖(Fx_a)₁,₂, (Fᵀx_b)₁,₂‖` (pixels; `r²` is the Sampson error GGS averages), robustified by a
//! Cauchy loss `ρ(r) = c²/2 · ln(1 + r²/c²)`. A second stage then truncates the loss at `3c`,
//! so that matches far from their epipolar lines stop pulling at all.
//!
//! Parameters and gauge: [`crate::camera`] (6 per camera, the reference fixed, unit mean
//! distance), plus `log φ`. The Jacobian is analytic: `∂r/∂F` in closed form and `∂F/∂θ` of
//! `F = K_b⁻ᵀ [t]ₓ R K_a⁻¹` (`R = R_b R_aᵀ`, `t = R_b (C_a − C_b)`):
//! `∂E/∂ω_a = −E[e_k]ₓ`, `∂E/∂ω_b = [e_k]ₓE`, `∂E/∂C_a = [R_b e_k]ₓR = −∂E/∂C_b`,
//! `∂K⁻¹/∂log φ = −(K⁻¹ − e₃e₃ᵀ)`. The normal equations are a sparse block system (one 6×6
//! block per camera, one per pair, a focal row), factorised symbolically once.

use nalgebra::{Matrix3, SMatrix, SVector, Vector3};
use posediff_geometry::PairMatches;
use posediff_geometry::epipolar::skew;
use rayon::prelude::*;

use crate::camera::{CameraPose, ParameterLayout, normalize_scale};
use crate::error::{Result, SfmError};
use crate::intrinsics::ImageIntrinsics;
use crate::linalg::{BlockSystem, Solver};
use crate::lm::{CauchySum, LeastSquares, LmOptions, LmReport, Termination, minimize};

/// Refinement settings.
#[derive(Debug, Clone, Copy, PartialEq)]
#[cfg_attr(
    feature = "serde",
    derive(serde::Serialize, serde::Deserialize),
    serde(default, deny_unknown_fields)
)]
pub struct SampsonRefineOptions {
    /// Cauchy scale of the Sampson distance, pixels.
    pub cauchy_px: f64,
    /// Iteration limit over both stages (each iteration is one accepted step).
    pub max_iterations: usize,
    /// Refine `φ` (false: keep the given focal).
    pub refine_focal: bool,
    /// Converged when the relative cost decrease of a step is below this.
    pub tolerance: f64,
    /// A second stage where matches farther than this many Cauchy scales from their epipolar
    /// geometry stop pulling (a truncated loss); `None` skips it.
    pub gate_scales: Option<f64>,
    /// Linear solver.
    pub solver: Solver,
    /// Where the pairs hold more than `thin_above_matches` matches in all, each pair takes
    /// part with at most this many (evenly spaced in its match order); `None`: all. The
    /// refinement only initialises the bundle adjustment and its time is linear in the
    /// matches: on a 300-frame forward walk (3.1 M matches, 760 per pair) 128 (above 100,000
    /// in all) took `posediff map` from 96.6 s to 67.7 s at the same mAA(30) 0.998, on a
    /// 300-frame orbit (1.7 M) from 61.7–70.0 s to 50.8 s at mAA(30) 1.000
    /// (`docs/BENCHMARKS.md`, issue 43).
    pub max_matches_per_pair: Option<usize>,
    /// Sets with no more matches than this stay whole. The 16-image temple (3,820 matches) is
    /// so sensitive that thinning its few pairs above 128 moved it from mAA(30) 0.966 to 0.744;
    /// a budget of 500,000 in all instead left the focal starts' 60-image subsets of the
    /// forward walk whole and the mapper took 92 s there.
    pub thin_above_matches: usize,
    /// Where the set holds more than `thin_above_matches` matches (the sets that are thinned),
    /// converged at this relative cost decrease instead of `tolerance`. The refinement only
    /// initialises the bundle adjustment; on the 300-frame forward walk (and on its focal
    /// starts' 60-image subsets) the last hundred of ~120–190 iterations each lowered the cost
    /// by less than 1e-6, relatively. At 1e-6 `posediff map` took 26 s instead of 36 s there,
    /// 26.8 s against 27.5 s on the orbit, with the same cameras to 0.01° and the same mAA(30)
    /// (docs/BENCHMARKS.md, "Video-scale speed", third session). Small sets keep `tolerance`:
    /// 1e-6 everywhere cost apple (all frames) 0.957 → 0.950 in `bench-real`.
    pub large_set_tolerance: f64,
    /// Where the set is thinned (as `large_set_tolerance`), also converged when no parameter
    /// moves by more than this in a step (radians for the rotations, the unit mean distance
    /// for the centres, `log φ` for the focal; 0: the cost alone decides). On the 1000-frame
    /// forward walk both stages otherwise crawled for a hundred steps each (the cost falling by
    /// 2–6e-6 a step, every parameter by under 1e-5, the focal drifting by 2e-7 a step) to the
    /// iteration limit where the keypoints came from a database, and stopped at 94 steps only
    /// by chance elsewhere (docs/BENCHMARKS.md, "A stop for the crawling Sampson refinement").
    pub large_set_step_tolerance: f64,
}

impl Default for SampsonRefineOptions {
    fn default() -> Self {
        Self {
            cauchy_px: 1.0,
            max_iterations: 200,
            refine_focal: true,
            tolerance: 1e-10,
            gate_scales: Some(3.0),
            solver: Solver::Sparse,
            max_matches_per_pair: Some(128),
            thin_above_matches: 100_000,
            large_set_tolerance: 1e-6,
            large_set_step_tolerance: 1e-5,
        }
    }
}

/// At most `max` of the pair's matches, evenly spaced in its match order; `None` where the
/// pair has no more than that (use it as it is).
fn thinned(p: &PairMatches, max: usize) -> Option<PairMatches> {
    let n = p.len();
    if n <= max {
        return None;
    }
    let keep: Vec<usize> = (0..max).map(|i| i * n / max).collect();
    let pick = |v: &[[f64; 2]]| keep.iter().map(|&k| v[k]).collect();
    let pick_id = |v: &[u32]| keep.iter().map(|&k| v[k]).collect();
    Some(PairMatches {
        first: p.first,
        second: p.second,
        kp1: pick(&p.kp1),
        kp2: pick(&p.kp2),
        idx1: pick_id(&p.idx1),
        idx2: pick_id(&p.idx2),
    })
}

/// What the refinement did.
#[derive(Debug, Clone, Copy, PartialEq, Default)]
#[cfg_attr(feature = "serde", derive(serde::Serialize))]
pub struct SampsonRefineReport {
    /// Accepted steps over both stages.
    pub iterations: usize,
    /// Whether both stages stopped at a minimum (not at the iteration limit).
    pub converged: bool,
    /// Why the last stage stopped.
    pub termination: Termination,
    /// Robust cost before.
    pub initial_cost: f64,
    /// Robust cost after (of the last stage's loss).
    pub final_cost: f64,
    /// Matches with `|r| < 3c` at the end.
    pub inliers: usize,
    /// Matches used.
    pub matches: usize,
    /// Each pair thinned to at most this many matches (`max_matches_per_pair`, the set above
    /// `thin_above_matches`); `None`: all used.
    pub per_pair_cap: Option<usize>,
    /// The convergence tolerance used (`tolerance`, or `large_set_tolerance` above
    /// `thin_above_matches`).
    pub tolerance: f64,
    /// The step tolerance used (`large_set_step_tolerance` above `thin_above_matches`, else
    /// 0: none).
    pub step_tolerance: f64,
    /// RMS of `r` over those inliers, pixels.
    pub inlier_rms_px: f64,
}

/// `F_{b←a}` (`x_bᵀ F x_a = 0`) of two cameras with focal factor `phi`.
pub fn pair_fundamental(
    a: &CameraPose,
    b: &CameraPose,
    phi: f64,
    intrinsics: &ImageIntrinsics,
    ia: usize,
    ib: usize,
) -> Matrix3<f64> {
    let (_, _, e) = pair_essential(a, b);
    intrinsics.k_inverse(phi, ib).transpose() * e * intrinsics.k_inverse(phi, ia)
}

/// `R = R_b R_aᵀ`, `t = R_b (C_a − C_b)` and `E = [t]ₓ R` of a pair.
fn pair_essential(a: &CameraPose, b: &CameraPose) -> (Matrix3<f64>, Vector3<f64>, Matrix3<f64>) {
    let r = *(b.rotation * a.rotation.inverse()).matrix();
    let t = b.rotation * (a.center - b.center);
    (r, t, skew(&t) * r)
}

/// `F` of the pair and its 13 analytic derivatives with respect to
/// `θ = [ω_a, δC_a, ω_b, δC_b, δ log φ]` (see the module documentation).
pub fn pair_fundamental_jacobian(
    a: &CameraPose,
    b: &CameraPose,
    phi: f64,
    intrinsics: &ImageIntrinsics,
    ia: usize,
    ib: usize,
) -> (Matrix3<f64>, [Matrix3<f64>; 13]) {
    let (r, _, e) = pair_essential(a, b);
    let (ka_inv, kb_inv) = (intrinsics.k_inverse(phi, ia), intrinsics.k_inverse(phi, ib));
    let kb_inv_t = kb_inv.transpose();
    let f = kb_inv_t * e * ka_inv;
    let rb = *b.rotation.matrix();
    let mut d = [Matrix3::zeros(); 13];
    for k in 0..3 {
        let mut unit = Vector3::zeros();
        unit[k] = 1.0;
        let de_wa = -(e * skew(&unit));
        let de_wb = skew(&unit) * e;
        let de_ca = skew(&(rb * unit)) * r;
        d[k] = kb_inv_t * de_wa * ka_inv;
        d[3 + k] = kb_inv_t * de_ca * ka_inv;
        d[6 + k] = kb_inv_t * de_wb * ka_inv;
        d[9 + k] = -d[3 + k];
    }
    let strip = |mut m: Matrix3<f64>| {
        m[(2, 2)] = 0.0;
        m
    };
    let (da, db) = (strip(ka_inv), strip(kb_inv));
    d[12] = -(kb_inv_t * e * da) - db.transpose() * e * ka_inv;
    (f, d)
}

fn row_major(m: &Matrix3<f64>) -> [f64; 9] {
    [0, 1, 2, 3, 4, 5, 6, 7, 8].map(|k| m[(k / 3, k % 3)])
}

/// The epipolar lines of a match (`l2 = F x₁`, the first two entries of `l1 = Fᵀ x₂`), its
/// algebraic error `e = x₂ᵀ F x₁` and the Sampson denominator `d`; `None` where `d` vanishes
/// or a value is not finite.
#[inline]
fn sampson_terms(
    f: &[f64; 9],
    x1: [f64; 2],
    x2: [f64; 2],
) -> Option<([f64; 3], [f64; 2], f64, f64)> {
    let l2 = [0, 1, 2].map(|r| f[3 * r] * x1[0] + f[3 * r + 1] * x1[1] + f[3 * r + 2]);
    let l1 = [0, 1].map(|c| f[c] * x2[0] + f[3 + c] * x2[1] + f[6 + c]);
    let e = x2[0] * l2[0] + x2[1] * l2[1] + l2[2];
    let d = l2[0] * l2[0] + l2[1] * l2[1] + l1[0] * l1[0] + l1[1] * l1[1];
    if d.is_nan() || d <= 1e-300 || !e.is_finite() {
        return None;
    }
    Some((l2, l1, e, d))
}

/// Signed Sampson distance of one match (what [`sampson_residual`] returns first, without
/// the gradient: the costs evaluate millions of these per step).
#[inline]
pub fn sampson_distance(f: &[f64; 9], x1: [f64; 2], x2: [f64; 2]) -> Option<f64> {
    let (_, _, e, d) = sampson_terms(f, x1, x2)?;
    Some(e / d.sqrt())
}

/// Signed Sampson distance of one match and its gradient with respect to `F` (row-major).
#[inline]
pub fn sampson_residual(f: &[f64; 9], x1: [f64; 2], x2: [f64; 2]) -> Option<(f64, [f64; 9])> {
    let (l2, l1, e, d) = sampson_terms(f, x1, x2)?;
    let p1 = [x1[0], x1[1], 1.0];
    let p2 = [x2[0], x2[1], 1.0];
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

/// Cauchy loss with an optional truncation.
#[derive(Debug, Clone, Copy)]
struct Loss {
    cauchy: f64,
    gate: Option<f64>,
}

impl Loss {
    /// The residual the loss sees: `|r|` capped at the gate.
    fn clamped(&self, r: f64) -> f64 {
        match self.gate {
            Some(g) => r.abs().min(g),
            None => r,
        }
    }

    fn rho(&self, r: f64) -> f64 {
        let c2 = self.cauchy * self.cauchy;
        let r = self.clamped(r);
        0.5 * c2 * (1.0 + r * r / c2).ln()
    }
}

/// Pairs with both cameras and a usable baseline.
fn usable(cams: &[Option<CameraPose>], a: usize, b: usize) -> Option<(CameraPose, CameraPose)> {
    match (
        cams.get(a).copied().flatten(),
        cams.get(b).copied().flatten(),
    ) {
        (Some(ca), Some(cb)) if (ca.center - cb.center).norm() > 1e-9 => Some((ca, cb)),
        _ => None,
    }
}

/// The robust cost of `pairs` (per pair in parallel, summed in pair order: deterministic).
fn cost_of(
    pairs: &[&PairMatches],
    intrinsics: &ImageIntrinsics,
    cams: &[Option<CameraPose>],
    phi: f64,
    loss: Loss,
) -> f64 {
    let per_pair: Vec<f64> = pairs
        .par_iter()
        .map(|p| {
            let Some((a, b)) = usable(cams, p.first, p.second) else {
                return 0.0;
            };
            let f = row_major(&pair_fundamental(
                &a, &b, phi, intrinsics, p.first, p.second,
            ));
            let mut sum = CauchySum::new(loss.cauchy);
            for (x1, x2) in p.kp1.iter().zip(&p.kp2) {
                if let Some(r) = sampson_distance(&f, *x1, *x2) {
                    sum.add(loss.clamped(r).powi(2));
                }
            }
            sum.total()
        })
        .collect();
    per_pair.iter().sum()
}

/// The state of the refinement: cameras and `φ`.
type State = (Vec<Option<CameraPose>>, f64);

struct Problem<'a> {
    pairs: Vec<&'a PairMatches>,
    intrinsics: &'a ImageIntrinsics,
    layout: ParameterLayout,
    reference: usize,
    loss: Loss,
    system: BlockSystem,
}

impl LeastSquares for Problem<'_> {
    type State = State;

    fn n_params(&self) -> usize {
        self.layout.n_params
    }

    fn cost(&self, (cams, phi): &State) -> f64 {
        cost_of(&self.pairs, self.intrinsics, cams, *phi, self.loss)
    }

    fn linearize(&mut self, (cams, phi): &State) -> Result<()> {
        let c2 = self.loss.cauchy * self.loss.cauchy;
        let (intrinsics, loss) = (self.intrinsics, self.loss);
        let per_pair: Vec<Option<(SMatrix<f64, 13, 13>, SVector<f64, 13>)>> = self
            .pairs
            .par_iter()
            .map(|p| {
                let (a, b) = usable(cams, p.first, p.second)?;
                let (f0, d) =
                    pair_fundamental_jacobian(&a, &b, *phi, intrinsics, p.first, p.second);
                let f0 = row_major(&f0);
                let mut df = SMatrix::<f64, 9, 13>::zeros();
                for (q, m) in d.iter().enumerate() {
                    for (k, v) in row_major(m).iter().enumerate() {
                        df[(k, q)] = *v;
                    }
                }
                // Summed over the matches in F's 9 entries, then carried to the 13 parameters
                // once: Σ w Dᵀg gᵀD = Dᵀ (Σ w g gᵀ) D (the matches' sum costs 45 products
                // each instead of 13 × 13 + 13 × 9).
                let mut h9 = [[0.0f64; 9]; 9];
                let mut g9 = [0.0f64; 9];
                for (x1, x2) in p.kp1.iter().zip(&p.kp2) {
                    let Some((r, gr)) = sampson_residual(&f0, *x1, *x2) else {
                        continue;
                    };
                    if loss.gate.is_some_and(|g| r.abs() >= g) {
                        continue;
                    }
                    let w = 1.0 / (1.0 + r * r / c2);
                    for (a, row) in h9.iter_mut().enumerate() {
                        let wa = w * gr[a];
                        for (h, &gb) in row.iter_mut().zip(&gr).take(a + 1) {
                            *h += wa * gb;
                        }
                        g9[a] += wa * r;
                    }
                }
                let h9 = SMatrix::<f64, 9, 9>::from_fn(|a, b| h9[a.max(b)][a.min(b)]);
                let hp = df.transpose() * h9 * df;
                let gp = df.transpose() * SVector::<f64, 9>::from(g9);
                Some((hp, gp))
            })
            .collect();
        self.system.clear();
        let layout = &self.layout;
        for (p, sums) in self.pairs.iter().zip(per_pair) {
            let Some((hp, gp)) = sums else { continue };
            // (block, first local parameter) of the pair's 13 parameters: camera a, camera b,
            // the focal — three different blocks, so each lower block is added once.
            let parts = [
                (layout.block[p.first], 0),
                (layout.block[p.second], 6),
                (layout.focal_block[0], 12),
            ];
            for &(bi, oi) in &parts {
                let Some(bi) = bi else { continue };
                self.system.add_rhs(bi, |k| -gp[oi + k]);
                for &(bj, oj) in &parts {
                    let Some(bj) = bj else { continue };
                    if bj > bi {
                        continue;
                    }
                    self.system.add_block(bi, bj, |r, c| hp[(oi + r, oj + c)])?;
                }
            }
        }
        Ok(())
    }

    fn solve(&mut self, lambda: f64) -> Result<Option<Vec<f64>>> {
        self.system.solve_regularised(lambda)
    }

    fn apply(&self, (cams, phi): &State, step: &[f64]) -> State {
        // Block order equals parameter order (cameras by index, then the focal).
        let (mut moved, phi) = self.layout.apply(cams, &[*phi], step);
        normalize_scale(&mut moved, self.reference);
        (moved, phi[0])
    }
}

/// Checks the inputs both refinements share: lengths, an estimated reference, a valid `φ`.
pub(crate) fn check_inputs(
    n: usize,
    intrinsics: &ImageIntrinsics,
    cameras: &[Option<CameraPose>],
    phi: f64,
    reference: usize,
) -> Result<()> {
    intrinsics.check(n)?;
    if cameras.len() != n {
        return Err(SfmError::LengthMismatch {
            what: "cameras",
            left: n,
            right: cameras.len(),
        });
    }
    if cameras.get(reference).copied().flatten().is_none() {
        return Err(SfmError::InvalidInput(format!(
            "the reference camera {reference} must be estimated"
        )));
    }
    if !(phi > 0.0 && phi.is_finite()) {
        return Err(SfmError::InvalidInput(format!(
            "the focal factor must be positive and finite, got {phi}"
        )));
    }
    Ok(())
}

/// The robust cost of the matches of pairs whose cameras share a centre (a rotation-only
/// pair, e.g. a repeated viewpoint): they have no epipolar geometry, but the cameras still
/// predict where each match lands, through the infinite homography `K_b R_b R_aᵀ K_a⁻¹`; `r`
/// is the pixel distance to that prediction (`missing_px` behind the camera).
fn tied_cost(
    pairs: &[&PairMatches],
    intrinsics: &ImageIntrinsics,
    cams: &[Option<CameraPose>],
    phi: f64,
    loss: Loss,
    missing_px: f64,
) -> f64 {
    let per_pair: Vec<f64> = pairs
        .par_iter()
        .map(|p| {
            let (Some(a), Some(b)) = (
                cams.get(p.first).copied().flatten(),
                cams.get(p.second).copied().flatten(),
            ) else {
                return 0.0;
            };
            if usable(cams, p.first, p.second).is_some() {
                return 0.0;
            }
            let h = intrinsics.k(phi, p.second)
                * (b.rotation * a.rotation.inverse()).matrix()
                * intrinsics.k_inverse(phi, p.first);
            p.kp1
                .iter()
                .zip(&p.kp2)
                .map(|(x1, x2)| {
                    let y = h * Vector3::new(x1[0], x1[1], 1.0);
                    if y.z > 1e-12 {
                        loss.rho(((y.x / y.z - x2[0]).powi(2) + (y.y / y.z - x2[1]).powi(2)).sqrt())
                    } else {
                        loss.rho(missing_px)
                    }
                })
                .sum()
        })
        .collect();
    per_pair.iter().sum()
}

/// The robust cost `Σ ρ(r)` of all matches under `cameras`: `r` is the Sampson distance, or
/// for a pair whose cameras share a centre the distance to the rotation's prediction
/// (see `tied_cost`); a match whose pair lacks a camera costs `ρ(missing_px)`. Compares
/// solutions that estimate different images.
///
/// # Errors
/// Inputs of the wrong length.
pub fn robust_cost(
    pairs: &[&PairMatches],
    intrinsics: &ImageIntrinsics,
    cameras: &[Option<CameraPose>],
    phi: f64,
    cauchy_px: f64,
    missing_px: f64,
) -> Result<f64> {
    intrinsics.check(cameras.len())?;
    let loss = Loss {
        cauchy: cauchy_px,
        gate: None,
    };
    let estimated = |i: usize| cameras.get(i).copied().flatten().is_some();
    let missing: usize = pairs
        .iter()
        .filter(|p| !(estimated(p.first) && estimated(p.second)))
        .map(|p| p.len())
        .sum();
    Ok(cost_of(pairs, intrinsics, cameras, phi, loss)
        + tied_cost(pairs, intrinsics, cameras, phi, loss, missing_px)
        + missing as f64 * loss.rho(missing_px))
}

/// Refines `cameras` (`None`: not estimated, left alone) and `phi` in place on the matches of
/// `pairs` (original-image pixels). `reference` stays fixed.
///
/// # Errors
/// Intrinsics or cameras of the wrong length, a reference without a camera, a non-positive
/// or non-finite `phi`, invalid settings, a pair naming an image that does not exist.
pub fn refine_sampson(
    pairs: &[&PairMatches],
    intrinsics: &ImageIntrinsics,
    cameras: &mut [Option<CameraPose>],
    phi: &mut f64,
    reference: usize,
    options: &SampsonRefineOptions,
) -> Result<SampsonRefineReport> {
    if !(options.cauchy_px > 0.0 && options.cauchy_px.is_finite()) {
        return Err(SfmError::InvalidInput(
            "cauchy_px must be positive and finite".into(),
        ));
    }
    let n = cameras.len();
    check_inputs(n, intrinsics, cameras, *phi, reference)?;
    if let Some(p) = pairs
        .iter()
        .find(|p| p.first >= n || p.second >= n || p.first == p.second)
    {
        return Err(SfmError::InvalidInput(format!(
            "a pair ({}, {}) of {n} images",
            p.first, p.second
        )));
    }
    for (name, t) in [
        ("tolerance", options.tolerance),
        ("large_set_tolerance", options.large_set_tolerance),
    ] {
        if !(t.is_finite() && t >= 0.0) {
            return Err(SfmError::InvalidInput(format!(
                "{name} must be a relative decrease of 0 or more, not {t}"
            )));
        }
    }
    let step = options.large_set_step_tolerance;
    if !(step.is_finite() && step >= 0.0) {
        return Err(SfmError::InvalidInput(format!(
            "large_set_step_tolerance must be a parameter change of 0 or more, not {step}"
        )));
    }
    if options.max_matches_per_pair == Some(0) {
        return Err(SfmError::InvalidInput(
            "max_matches_per_pair must be at least 1 (or none: all matches)".into(),
        ));
    }
    let layout = ParameterLayout::new(cameras, reference, options.refine_focal);
    let used: Vec<&PairMatches> = pairs
        .iter()
        .copied()
        .filter(|p| !p.is_empty() && cameras[p.first].is_some() && cameras[p.second].is_some())
        .collect();
    let total: usize = used.iter().map(|p| p.len()).sum();
    let large = total > options.thin_above_matches;
    let cap = options.max_matches_per_pair.filter(|_| large);
    let tolerance = if large {
        options.large_set_tolerance
    } else {
        options.tolerance
    };
    let thin: Vec<Option<PairMatches>> = used
        .iter()
        .map(|p| cap.and_then(|m| thinned(p, m)))
        .collect();
    let used: Vec<&PairMatches> = used
        .iter()
        .zip(&thin)
        .map(|(p, t)| t.as_ref().unwrap_or(p))
        .collect();
    let block_pairs: Vec<(usize, usize)> = used
        .iter()
        .flat_map(|p| {
            let (a, b, f) = (
                layout.block[p.first],
                layout.block[p.second],
                layout.focal_block[0],
            );
            [(a, b), (a, f), (b, f)]
                .into_iter()
                .filter_map(|(x, y)| Some((x?, y?)))
        })
        .collect();
    let system = BlockSystem::new(
        "Sampson refinement",
        &layout.block_sizes,
        block_pairs,
        options.solver,
    )?;
    let mut problem = Problem {
        pairs: used,
        intrinsics,
        layout,
        reference,
        loss: Loss {
            cauchy: options.cauchy_px,
            gate: None,
        },
        system,
    };
    normalize_scale(cameras, reference);
    let mut state: State = (cameras.to_vec(), *phi);
    let lm = LmOptions {
        max_iterations: options.max_iterations,
        tolerance,
        step_tolerance: if large { step } else { 0.0 },
        ..LmOptions::default()
    };
    let first = minimize(&mut problem, &mut state, &lm)?;
    let mut report = SampsonRefineReport {
        iterations: first.iterations,
        converged: first.termination.converged(),
        termination: first.termination,
        initial_cost: first.initial_cost,
        final_cost: first.final_cost,
        ..SampsonRefineReport::default()
    };
    if let Some(gate) = options.gate_scales {
        // Second stage: matches beyond the gate no longer pull at all.
        problem.loss.gate = Some(gate * options.cauchy_px);
        let lm = LmOptions {
            max_iterations: options.max_iterations.saturating_sub(first.iterations),
            ..lm
        };
        let second: LmReport = minimize(&mut problem, &mut state, &lm)?;
        report.iterations += second.iterations;
        report.converged &= second.termination.converged();
        report.termination = second.termination;
        report.final_cost = second.final_cost;
    }
    cameras.copy_from_slice(&state.0);
    *phi = state.1;
    let (mut inliers, mut used, mut sum) = (0, 0, 0.0);
    for p in &problem.pairs {
        let Some((a, b)) = usable(cameras, p.first, p.second) else {
            continue;
        };
        let f = row_major(&pair_fundamental(
            &a, &b, *phi, intrinsics, p.first, p.second,
        ));
        for (x1, x2) in p.kp1.iter().zip(&p.kp2) {
            if let Some(r) = sampson_distance(&f, *x1, *x2) {
                used += 1;
                if r.abs() < 3.0 * options.cauchy_px {
                    inliers += 1;
                    sum += r * r;
                }
            }
        }
    }
    report.inliers = inliers;
    report.matches = used;
    report.per_pair_cap = cap;
    report.tolerance = tolerance;
    report.step_tolerance = lm.step_tolerance;
    report.inlier_rms_px = if inliers > 0 {
        (sum / inliers as f64).sqrt()
    } else {
        0.0
    };
    Ok(report)
}

#[cfg(test)]
mod tests {
    #![allow(clippy::unwrap_used)]
    use super::*;
    use nalgebra::{Rotation3, Vector3};

    #[test]
    fn sampson_gradient_matches_finite_differences() {
        let f = [1e-6, 2e-5, -3e-3, -1e-5, 3e-6, 4e-3, 2e-3, -5e-3, 1.0];
        let (x1, x2) = ([100.0, 50.0], [120.0, 40.0]);
        let (r, g) = sampson_residual(&f, x1, x2).unwrap();
        assert_eq!(sampson_distance(&f, x1, x2), Some(r));
        for k in 0..9 {
            let h = 1e-7 * f[k].abs().max(1e-6);
            let mut p = f;
            p[k] += h;
            let mut m = f;
            m[k] -= h;
            let fd = (sampson_residual(&p, x1, x2).unwrap().0
                - sampson_residual(&m, x1, x2).unwrap().0)
                / (2.0 * h);
            assert!(
                (fd - g[k]).abs() <= 1e-5 * fd.abs().max(1e-3),
                "{k}: {fd} vs {}",
                g[k]
            );
        }
    }

    /// The analytic `∂F/∂θ` against central differences of the closed form.
    #[test]
    fn fundamental_jacobian_matches_finite_differences() {
        let intrinsics =
            ImageIntrinsics::new(vec![[310.0, 245.0], [330.0, 236.0]], vec![640.0, 600.0]);
        let a = CameraPose {
            rotation: Rotation3::from_euler_angles(0.1, -0.3, 0.2),
            center: Vector3::new(0.3, -0.2, 0.1),
        };
        let b = CameraPose {
            rotation: Rotation3::from_euler_angles(-0.2, 0.4, 0.05),
            center: Vector3::new(-0.5, 0.1, 0.4),
        };
        let phi = 1.1;
        let (f, d) = pair_fundamental_jacobian(&a, &b, phi, &intrinsics, 0, 1);
        assert!((f - pair_fundamental(&a, &b, phi, &intrinsics, 0, 1)).norm() < 1e-15);
        let h = 1e-6;
        for q in 0..13 {
            let at = |s: f64| {
                let mut theta = [0.0; 13];
                theta[q] = s;
                let (pa, pb) = (a.moved(&theta[0..6]), b.moved(&theta[6..12]));
                pair_fundamental(&pa, &pb, phi * theta[12].exp(), &intrinsics, 0, 1)
            };
            let fd = (at(h) - at(-h)) / (2.0 * h);
            let err = (fd - d[q]).norm();
            assert!(
                err <= 1e-7 * fd.norm().max(1e-9),
                "θ{q}: {err:e} of {:e}",
                fd.norm()
            );
        }
    }

    /// A repeated viewpoint (two cameras on one centre) is scored by the rotation's
    /// prediction of its matches, not as unestimated: the right rotation and focal cost
    /// nothing, a wrong focal costs, and neither pays the missing-pair penalty.
    #[test]
    fn pairs_on_one_centre_are_scored_by_their_rotation() {
        let intrinsics =
            ImageIntrinsics::new(vec![[320.0, 240.0], [320.0, 240.0]], vec![640.0, 640.0]);
        let phi = 1.5;
        let a = CameraPose {
            rotation: Rotation3::identity(),
            center: Vector3::new(0.1, 0.2, 0.3),
        };
        let b = CameraPose {
            rotation: Rotation3::from_euler_angles(0.02, -0.05, 0.01),
            center: a.center,
        };
        let h = intrinsics.k(phi, 1) * b.rotation.matrix() * intrinsics.k_inverse(phi, 0);
        let kp1: Vec<[f64; 2]> = (0..50)
            .map(|i| [40.0 + 11.0 * f64::from(i), 30.0 + 7.0 * f64::from(i % 13)])
            .collect();
        let kp2 = kp1
            .iter()
            .map(|x| {
                let y = h * Vector3::new(x[0], x[1], 1.0);
                [y.x / y.z, y.y / y.z]
            })
            .collect();
        let pair = PairMatches {
            first: 0,
            second: 1,
            kp1,
            kp2,
            idx1: (0..50).collect(),
            idx2: (0..50).collect(),
        };
        let cams = [Some(a), Some(b)];
        let at = |phi: f64, cams: &[Option<CameraPose>]| {
            robust_cost(&[&pair], &intrinsics, cams, phi, 2.0, 10.0).unwrap()
        };
        assert!(at(phi, &cams) < 1e-12, "{}", at(phi, &cams));
        let missing = at(phi, &[Some(a), None]);
        assert!((missing - 50.0 * 0.5 * 4.0 * (1.0 + 25.0f64).ln()).abs() < 1e-9);
        let wrong_focal = at(0.5, &cams);
        assert!(
            wrong_focal > 1.0 && wrong_focal.is_finite(),
            "{wrong_focal}"
        );
        let turned = CameraPose {
            rotation: Rotation3::from_euler_angles(0.0, 0.02, 0.0) * b.rotation,
            ..b
        };
        assert!(at(phi, &[Some(a), Some(turned)]) > 1.0);
    }
}
