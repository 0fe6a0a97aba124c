//! Radial distortion from the view graph, before any pose: each camera group's SIMPLE_RADIAL
//! coefficient is the one with which the verified matches of its pairs fit a fundamental
//! matrix best. A pinhole camera's matches satisfy `x_bᵀ F x_a = 0` exactly; a lens's radial
//! distortion bends them off every `F`, by pixels at the image corners, and no `F` absorbs it.
//!
//! Coordinates are normalised per image by `s_i` (the caller's focal guess: `x = (p − c) / s`),
//! and the model is COLMAP's SIMPLE_RADIAL, `x_d = x_u (1 + k r_u²)`, in those coordinates; with
//! the focal `f` estimated later, COLMAP's coefficient is `k · (f / s)²` ([`coefficient_at`]).
//!
//! Per candidate `k` and pair: both sides' points undistorted, `F` fitted by the normalised
//! eight-point algorithm with iteratively reweighted least squares (Cauchy weights on the
//! Sampson error), the pair's robust cost summed. A grid over `[−max_k, max_k]` then a golden
//! section refine each group in turn (coordinate descent, `sweeps` times). The distortion is
//! kept only when it lowers the cost by `min_improvement` against no distortion: a pinhole set
//! stays pinhole.

use nalgebra::{Matrix3, Point2, SMatrix, SymmetricEigen, Vector2};
use posediff_geometry::PairMatches;
use posediff_geometry::epipolar::sampson_error;
use posediff_geometry::lens::{CameraModel, LensCamera};
use rayon::prelude::*;

/// Settings of [`calibrate_distortion`]; the defaults were chosen on the shared sets and their
/// wide-angle copies (`posediff variant --radial=-0.12:0.02`, docs/BENCHMARKS.md, "Real
/// cameras"): the originals stay at `k = 0`; the fountain's copy gives SIMPLE_RADIAL's
/// `k = −0.099` (one coefficient for the truth's `k1 = −0.12, k2 = 0.02`).
#[derive(Debug, Clone, Copy, PartialEq)]
#[cfg_attr(
    feature = "serde",
    derive(serde::Serialize, serde::Deserialize),
    serde(default, deny_unknown_fields)
)]
pub struct DistortionCalibrationOptions {
    /// Largest `|k|` searched, in the normalised coordinates (a strong wide-angle lens is about
    /// −0.3 at a focal of 1.2 × the longer side). Candidates that fold inside an image (the
    /// distortion stops growing with the radius) are skipped.
    pub max_k: f64,
    /// Grid points over `[−max_k, max_k]` before the golden-section refinement.
    pub steps: usize,
    /// The strongest pairs used (a few dozen determine a lens; more only cost time).
    pub max_pairs: usize,
    /// Fewest verified matches of a pair used.
    pub min_matches: usize,
    /// Relative decrease of the robust cost against no distortion needed to keep one: 0.1
    /// leaves every original shared set at `k = 0` (their best `k` lowers it by under 3 %),
    /// while the fountain's wide-angle copy lowers it by 56 %. The temple's and the apple's
    /// copies stay under it too (their verified matches lie where the lens moves points by a
    /// few pixels at most): not measured, see docs/BENCHMARKS.md.
    pub min_improvement: f64,
    /// Cauchy scale of the Sampson error, pixels.
    pub cauchy_px: f64,
    /// Coordinate-descent sweeps over the groups.
    pub sweeps: usize,
}

impl Default for DistortionCalibrationOptions {
    fn default() -> Self {
        Self {
            max_k: 0.3,
            steps: 25,
            max_pairs: 40,
            min_matches: 30,
            min_improvement: 0.1,
            cauchy_px: 1.0,
            sweeps: 2,
        }
    }
}

/// The calibrated distortion of each camera group.
#[derive(Debug, Clone, PartialEq, Default)]
pub struct DistortionCalibration {
    /// Per group, `k` in the normalised coordinates (0 where kept pinhole).
    pub k: Vec<f64>,
    /// Per group, whether its pairs determined a distortion (`false`: none measured, or too
    /// few pairs).
    pub determined: Vec<bool>,
    /// The robust cost of the pairs used without distortion.
    pub cost_pinhole: f64,
    /// The same with the best coefficients found, kept or not (not kept when it is above
    /// `(1 − min_improvement) · cost_pinhole`).
    pub cost: f64,
    /// Pairs used.
    pub pairs: usize,
}

/// SIMPLE_RADIAL's `x_d = x_u (1 + k r_u²)` on coordinates already normalised: the lens of
/// [`posediff_geometry::lens`] (the one place lens models are computed) with a unit focal at
/// the origin; `None` for a coefficient that is not finite.
pub fn normalised_lens(k: f64) -> Option<LensCamera> {
    LensCamera::new(CameraModel::SimpleRadial, vec![1.0, 0.0, 0.0, k]).ok()
}

/// COLMAP's SIMPLE_RADIAL coefficient (coordinates normalised by the focal `f`) of `k` found in
/// coordinates normalised by `s`.
pub fn coefficient_at(k: f64, s: f64, f: f64) -> f64 {
    k * (f / s) * (f / s)
}

/// One pair's points, normalised per image.
struct PairPoints {
    a: usize,
    b: usize,
    xa: Vec<[f64; 2]>,
    xb: Vec<[f64; 2]>,
    /// Pixels per normalised unit (the mean of the two images' `s`), for the Cauchy scale.
    pixels: f64,
}

/// Hartley's normalisation of `points`: the transform and the normalised points.
fn hartley(points: &[[f64; 2]]) -> (Matrix3<f64>, Vec<[f64; 2]>) {
    let n = points.len() as f64;
    let (mx, my) = points
        .iter()
        .fold((0.0, 0.0), |(x, y), p| (x + p[0] / n, y + p[1] / n));
    let spread = points
        .iter()
        .map(|p| (p[0] - mx).hypot(p[1] - my))
        .sum::<f64>()
        / n;
    let s = if spread > 0.0 {
        std::f64::consts::SQRT_2 / spread
    } else {
        1.0
    };
    let t = Matrix3::new(s, 0.0, -s * mx, 0.0, s, -s * my, 0.0, 0.0, 1.0);
    let moved = points
        .iter()
        .map(|p| [s * (p[0] - mx), s * (p[1] - my)])
        .collect();
    (t, moved)
}

/// The robust cost of a pair's undistorted points against their best fundamental matrix
/// (eight-point, reweighted); `None` with fewer than eight points.
fn fit_cost(xa: &[[f64; 2]], xb: &[[f64; 2]], cauchy: f64) -> Option<f64> {
    if xa.len() < 8 {
        return None;
    }
    let (ta, na) = hartley(xa);
    let (tb, nb) = hartley(xb);
    let rows: Vec<SMatrix<f64, 9, 1>> = na
        .iter()
        .zip(&nb)
        .map(|(p, q)| {
            SMatrix::<f64, 9, 1>::from_column_slice(&[
                q[0] * p[0],
                q[0] * p[1],
                q[0],
                q[1] * p[0],
                q[1] * p[1],
                q[1],
                p[0],
                p[1],
                1.0,
            ])
        })
        .collect();
    let c2 = cauchy * cauchy;
    let mut weights = vec![1.0; rows.len()];
    let mut cost = f64::INFINITY;
    for _ in 0..4 {
        let mut m = SMatrix::<f64, 9, 9>::zeros();
        for (row, w) in rows.iter().zip(&weights) {
            m += row * row.transpose() * *w;
        }
        let eigen = SymmetricEigen::new(m);
        let (smallest, _) = eigen
            .eigenvalues
            .iter()
            .enumerate()
            .min_by(|a, b| a.1.total_cmp(b.1))?;
        let v = eigen.eigenvectors.column(smallest);
        let f = Matrix3::new(v[0], v[1], v[2], v[3], v[4], v[5], v[6], v[7], v[8]);
        // Rank 2, then back to the undistorted normalised coordinates.
        let svd = f.svd(true, true);
        let (u, vt) = (svd.u?, svd.v_t?);
        let mut sigma = svd.singular_values;
        sigma[2] = 0.0;
        let f = tb.transpose() * u * Matrix3::from_diagonal(&sigma) * vt * ta;
        cost = 0.0;
        for ((p, q), w) in xa.iter().zip(xb).zip(weights.iter_mut()) {
            // A match whose epipolar lines vanish contributes nothing.
            let e2 = sampson_error(&f, &Point2::from(*p), &Point2::from(*q)).unwrap_or(0.0);
            cost += 0.5 * c2 * (1.0 + e2 / c2).ln();
            *w = 1.0 / (1.0 + e2 / c2);
        }
    }
    cost.is_finite().then_some(cost)
}

impl PairPoints {
    /// The pair's robust cost with the groups' coefficients `ka`, `kb` (in pixels², through
    /// `pixels`); `None` where a point cannot be undistorted.
    fn cost(&self, ka: f64, kb: f64, cauchy_px: f64) -> Option<f64> {
        let undistorted = |points: &[[f64; 2]], k: f64| -> Option<Vec<[f64; 2]>> {
            let lens = normalised_lens(k)?;
            points
                .iter()
                .map(|x| lens.unproject(&Vector2::from(*x)).ok().map(Into::into))
                .collect()
        };
        let (ua, ub) = (undistorted(&self.xa, ka), undistorted(&self.xb, kb));
        let cauchy = cauchy_px / self.pixels;
        fit_cost(&ua?, &ub?, cauchy).map(|c| c * self.pixels * self.pixels)
    }
}

/// Each group's radial coefficient from the verified matches of `pairs` (see the module).
///
/// `group[i]` is image `i`'s camera, `centre[i]` its principal point, `scale[i]` its `s`, and
/// `corner[i]` its largest normalised radius (a candidate must not fold inside any image).
pub fn calibrate_distortion(
    pairs: &[PairMatches],
    group: &[usize],
    centre: &[[f64; 2]],
    scale: &[f64],
    corner: &[f64],
    options: &DistortionCalibrationOptions,
) -> DistortionCalibration {
    let groups = group.iter().max().map_or(0, |g| g + 1);
    let mut strong: Vec<&PairMatches> = pairs
        .iter()
        .filter(|p| p.len() >= options.min_matches.max(8))
        .collect();
    strong.sort_by_key(|p| std::cmp::Reverse(p.len()));
    strong.truncate(options.max_pairs);
    let normalise = |i: usize, p: &[f64; 2]| {
        [
            (p[0] - centre[i][0]) / scale[i],
            (p[1] - centre[i][1]) / scale[i],
        ]
    };
    let points: Vec<PairPoints> = strong
        .iter()
        .map(|p| PairPoints {
            a: p.first,
            b: p.second,
            xa: p.kp1.iter().map(|x| normalise(p.first, x)).collect(),
            xb: p.kp2.iter().map(|x| normalise(p.second, x)).collect(),
            pixels: 0.5 * (scale[p.first] + scale[p.second]),
        })
        .collect();
    // The fold of `k < 0` lies at r_u = 1/√(−3k), where r_d = (2/3) r_u: beyond every corner.
    let mut lowest = vec![-options.max_k; groups];
    for (i, &g) in group.iter().enumerate() {
        let r = corner[i].max(1e-9);
        lowest[g] = lowest[g].max(-4.0 / (27.0 * r * r) * 0.999);
    }
    let total = |k: &[f64], only: Option<usize>| -> f64 {
        points
            .par_iter()
            .filter(|p| only.is_none_or(|g| group[p.a] == g || group[p.b] == g))
            .map(|p| {
                p.cost(k[group[p.a]], k[group[p.b]], options.cauchy_px)
                    .unwrap_or(f64::INFINITY)
            })
            .sum()
    };
    let zero = vec![0.0; groups];
    let cost_pinhole = total(&zero, None);
    let mut used = vec![false; groups];
    for p in &points {
        used[group[p.a]] = true;
        used[group[p.b]] = true;
    }
    let mut k = zero.clone();
    let steps = options.steps.max(3);
    for _ in 0..options.sweeps.max(1) {
        for g in (0..groups).filter(|g| used[*g]) {
            let at = |value: f64, k: &[f64]| {
                let mut trial = k.to_vec();
                trial[g] = value;
                total(&trial, Some(g))
            };
            let (lo, hi) = (lowest[g], options.max_k);
            let step = (hi - lo) / (steps - 1) as f64;
            let grid: Vec<f64> = (0..steps).map(|i| lo + step * i as f64).collect();
            let Some((best, _)) = grid
                .iter()
                .map(|v| (*v, at(*v, &k)))
                .min_by(|a, b| a.1.total_cmp(&b.1))
            else {
                continue;
            };
            // Golden section on the grid cell either side.
            let (mut a, mut b) = ((best - step).max(lo), (best + step).min(hi));
            let ratio = 0.5 * (5f64.sqrt() - 1.0);
            let (mut c, mut d) = (b - ratio * (b - a), a + ratio * (b - a));
            let (mut fc, mut fd) = (at(c, &k), at(d, &k));
            for _ in 0..12 {
                if fc < fd {
                    (b, d, fd) = (d, c, fc);
                    c = b - ratio * (b - a);
                    fc = at(c, &k);
                } else {
                    (a, c, fc) = (c, d, fd);
                    d = a + ratio * (b - a);
                    fd = at(d, &k);
                }
            }
            k[g] = 0.5 * (a + b);
        }
    }
    let cost = total(&k, None);
    let kept = cost.is_finite() && cost < (1.0 - options.min_improvement) * cost_pinhole;
    DistortionCalibration {
        determined: used.iter().map(|u| *u && kept).collect(),
        k: if kept { k } else { zero },
        cost_pinhole,
        cost,
        pairs: points.len(),
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use nalgebra::{Rotation3, Vector3};

    /// The normalised lens the calibration undistorts with: its undistortion inverts its
    /// distortion, refuses the fold, and its coefficient converts between normalisations.
    #[test]
    fn undistortion_inverts_distortion_and_refuses_the_fold() {
        for k in [-0.3, -0.12, 0.0, 0.2] {
            let lens = normalised_lens(k).unwrap();
            for x in [[0.3, -0.2], [0.6, 0.4], [0.0, 0.0]] {
                let x = Vector2::from(x);
                let u = lens
                    .unproject(&lens.distort_pixel(&x))
                    .unwrap_or(Vector2::repeat(f64::NAN));
                assert!(u.metric_distance(&x) < 1e-12, "{k} {x:?}");
            }
        }
        // k = −0.5: r_d peaks at 0.544 (r_u = 0.816); r_d = 0.6 has no preimage.
        let folded = normalised_lens(-0.5).unwrap();
        assert!(folded.unproject(&Vector2::new(0.6, 0.0)).is_err());
        assert!((coefficient_at(-0.1, 1000.0, 1200.0) + 0.144).abs() < 1e-12);
    }

    /// A synthetic pair of views of a 3-D scene through a lens of `k` (true) normalised by
    /// `s`: the calibration finds `k` with distortion, and keeps 0 without.
    #[test]
    fn the_coefficient_of_a_distorted_view_graph_is_found() {
        let f = 800.0;
        let s = 700.0;
        let centre = [320.0, 240.0];
        let points: Vec<Vector3<f64>> = (0..400)
            .map(|i| {
                let t = f64::from(i);
                Vector3::new(
                    (t * 0.37).sin() * 2.0,
                    (t * 0.73).cos() * 1.5,
                    5.0 + (t * 0.11).sin() * 2.0,
                )
            })
            .collect();
        let cameras: Vec<(Rotation3<f64>, Vector3<f64>)> = (0..4)
            .map(|c| {
                let a = 0.08 * f64::from(c);
                (
                    Rotation3::from_euler_angles(0.02 * f64::from(c), -a, 0.01),
                    Vector3::new(0.6 * f64::from(c), 0.1 * f64::from(c), 0.0),
                )
            })
            .collect();
        let pairs = |k_true: f64| -> Vec<PairMatches> {
            let mut out = Vec::new();
            let lens = normalised_lens(coefficient_at(k_true, s, f)).unwrap();
            let pixel = |c: usize, x: &Vector3<f64>| {
                let (r, t) = cameras[c];
                let xc = r * x + t;
                let d = lens.distort_pixel(&Vector2::new(xc.x / xc.z, xc.y / xc.z));
                [f * d.x + centre[0], f * d.y + centre[1]]
            };
            for a in 0..4 {
                for b in a + 1..4 {
                    let mut p = PairMatches::placeholder(a, b, 0);
                    for x in &points {
                        p.kp1.push(pixel(a, x));
                        p.kp2.push(pixel(b, x));
                    }
                    p.idx1 = (0..points.len() as u32).collect();
                    p.idx2 = p.idx1.clone();
                    out.push(p);
                }
            }
            out
        };
        let options = DistortionCalibrationOptions::default();
        let run = |k_true: f64| {
            calibrate_distortion(
                &pairs(k_true),
                &[0; 4],
                &[centre; 4],
                &[s; 4],
                &[0.6; 4],
                &options,
            )
        };
        let found = run(-0.12);
        assert!(found.determined[0], "{found:?}");
        assert!((found.k[0] + 0.12).abs() < 0.005, "{found:?}");
        let none = run(0.0);
        assert_eq!((none.k[0], none.determined[0]), (0.0, false), "{none:?}");
    }
}
