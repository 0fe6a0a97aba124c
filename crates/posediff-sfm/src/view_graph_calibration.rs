//! A focal per camera from the view graph's fundamental matrices (the model: COLMAP 4's and
//! GLOMAP's `ViewGraphCalibrator`), and the grouping of images into cameras where nothing else
//! (EXIF, folders, the user) says which photos share a lens.
//!
//! Each pair's cost is [`crate::focal::essential_cost`]'s `(σ₁ − σ₂)/(σ₁ + σ₂)` of
//! `K_bᵀ F K_a`, now with each camera's own focal `f_i = φ · ρ_{g(i)} · s_i`: `φ` the shared
//! self-calibrated factor, `ρ_g` one ratio per group. The ratios are found by coordinate
//! descent (a log grid around 1, then golden section), sweeping the groups in order, each
//! sweep followed by a search over their common scale (that direction is the cost's valley,
//! along which one group at a time moves slowly); a group
//! whose pairs do not fix its focal (too few pairs, or the best ratio at the edge of the search)
//! keeps `ρ = 1` and is reported as undetermined.
//!
//! [`group_by_focal`] turns per-image ratios into cameras: the largest set of determined images
//! whose ratios span at most `group_tolerance` is one camera (with every undetermined image);
//! each other image is a camera of its own, as in COLMAP's default of a camera per image. A
//! set taken with one lens thus stays one camera (its shared focal is the best-determined), and
//! a zoomed photo gets a focal of its own.

use nalgebra::Matrix3;
use rayon::prelude::*;

use crate::focal::PairFundamental;
use crate::intrinsics::k_matrix;

/// Settings of the view-graph calibration and of the grouping from data.
#[derive(Debug, Clone, Copy, PartialEq)]
#[cfg_attr(
    feature = "serde",
    derive(serde::Serialize, serde::Deserialize),
    serde(default, deny_unknown_fields)
)]
pub struct ViewGraphCalibrationOptions {
    /// Each group's ratio is searched in `[1 / range, range]` around the shared focal. 3
    /// covers a 3× zoom either way of the set's self-calibrated focal.
    pub range: f64,
    /// Log-spaced grid points of each group's search (then 40 golden-section steps).
    pub steps: usize,
    /// Sweeps over the groups.
    pub sweeps: usize,
    /// A group needs pairs with fundamental matrices to at least this many distinct other
    /// images to be determined.
    pub min_partners: usize,
    /// Images whose calibrated focals lie within this relative span are one camera when the
    /// cameras are decided from the data. Chosen from the spread of the per-image focals on
    /// the shared single-camera sets and the zoomed copies of docs/BENCHMARKS.md ("Real
    /// cameras"): the zoom factors there start at 1.3.
    pub group_tolerance: f64,
}

impl Default for ViewGraphCalibrationOptions {
    fn default() -> Self {
        Self {
            range: 3.0,
            steps: 41,
            sweeps: 4,
            min_partners: 2,
            group_tolerance: 0.15,
        }
    }
}

/// One pair's fundamental matrix between images `a` and `b`.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct ImagePair {
    /// First image.
    pub a: usize,
    /// Second image.
    pub b: usize,
    /// `F`, principal points, focal scales and weight.
    pub fundamental: PairFundamental,
}

/// `(σ₁ − σ₂)/(σ₁ + σ₂)` of `K_bᵀ F K_a` at focals `fa`, `fb`, in closed form: for a rank-2
/// `E`, `σ₁² + σ₂² = ‖E‖²` and `σ₁ σ₂ = ‖cof E‖` (Cauchy–Binet), so no SVD.
pub fn pair_cost(p: &PairFundamental, fa: f64, fb: f64) -> f64 {
    let e: Matrix3<f64> =
        k_matrix(fb, p.principal_b).transpose() * p.f * k_matrix(fa, p.principal_a);
    let sum_sq = e.norm_squared();
    let mut cof = 0.0;
    for (r1, r2) in [(0, 1), (0, 2), (1, 2)] {
        for (c1, c2) in [(0, 1), (0, 2), (1, 2)] {
            let m = e[(r1, c1)] * e[(r2, c2)] - e[(r1, c2)] * e[(r2, c1)];
            cof += m * m;
        }
    }
    let prod = cof.sqrt();
    let (lo, hi) = ((sum_sq - 2.0 * prod).max(0.0), sum_sq + 2.0 * prod);
    if !(hi > 0.0 && hi.is_finite()) {
        return 1.0;
    }
    (lo / hi).sqrt()
}

/// The calibration's result.
#[derive(Debug, Clone, PartialEq)]
pub struct GroupCalibration {
    /// Per group, `ρ_g` (1 where undetermined).
    pub ratio: Vec<f64>,
    /// Per group, whether its pairs fixed its focal.
    pub determined: Vec<bool>,
}

/// Each group's ratio `ρ_g` to the shared factor `phi` (`group[i]`: image `i`'s group, `groups`
/// of them) from the pairs' fundamental matrices. Where the pairs' cost is flat in the focal
/// (narrow fields of view, object-centric rings) the common scale and with it the ratios can
/// be off: the mapper keeps the cameras only when they explain the matches better.
pub fn calibrate_groups(
    pairs: &[ImagePair],
    group: &[usize],
    groups: usize,
    phi: f64,
    options: &ViewGraphCalibrationOptions,
) -> GroupCalibration {
    let mut touching: Vec<Vec<usize>> = vec![Vec::new(); groups];
    let mut partners: Vec<Vec<usize>> = vec![Vec::new(); groups];
    for (k, p) in pairs.iter().enumerate() {
        let (ga, gb) = (group[p.a], group[p.b]);
        touching[ga].push(k);
        partners[ga].push(p.b);
        if gb != ga {
            touching[gb].push(k);
        }
        partners[gb].push(p.a);
    }
    for p in &mut partners {
        p.sort_unstable();
        p.dedup();
    }
    let mut ratio = vec![1.0; groups];
    let mut at_edge = vec![false; groups];
    let active: Vec<usize> = (0..groups)
        .filter(|&g| partners[g].len() >= options.min_partners)
        .collect();
    let span = options.range.max(1.0 + 1e-6).ln();
    let steps = options.steps.max(3);
    for _ in 0..options.sweeps.max(1) {
        for &g in &active {
            let cost = |log_r: f64| -> f64 {
                let r = log_r.exp();
                touching[g]
                    .iter()
                    .map(|&k| {
                        let p = &pairs[k];
                        let rho = |i: usize| if group[i] == g { r } else { ratio[group[i]] };
                        let fa = phi * rho(p.a) * p.fundamental.scale_a;
                        let fb = phi * rho(p.b) * p.fundamental.scale_b;
                        p.fundamental.weight * pair_cost(&p.fundamental, fa, fb)
                    })
                    .sum()
            };
            let grid: Vec<(usize, f64)> = (0..steps)
                .into_par_iter()
                .map(|k| (k, cost(-span + 2.0 * span * k as f64 / (steps - 1) as f64)))
                .collect();
            let Some(best) = grid
                .iter()
                .min_by(|a, b| a.1.total_cmp(&b.1))
                .map(|(k, _)| *k)
            else {
                continue;
            };
            at_edge[g] = best == 0 || best == steps - 1;
            let step = 2.0 * span / (steps - 1) as f64;
            let x = -span + step * best as f64;
            ratio[g] = golden(&cost, x - step, x + step).exp();
        }
        // The shared scale of all focals is the cost's valley (weakly fixed by each pair, and
        // one group at a time moves along it slowly): one search over a common factor. The
        // relative focals come out right only near the right common scale.
        let common = |log_s: f64| -> f64 {
            let s = log_s.exp();
            pairs
                .iter()
                .map(|p| {
                    let fa = phi * s * ratio[group[p.a]] * p.fundamental.scale_a;
                    let fb = phi * s * ratio[group[p.b]] * p.fundamental.scale_b;
                    p.fundamental.weight * pair_cost(&p.fundamental, fa, fb)
                })
                .sum()
        };
        let half = 0.5 * span;
        let step = 2.0 * half / (steps - 1) as f64;
        let grid = (0..steps)
            .map(|k| -half + step * k as f64)
            .map(|x| (x, common(x)))
            .min_by(|a, b| a.1.total_cmp(&b.1));
        if let Some((x, _)) = grid {
            let s = golden(&common, x - step, x + step).exp();
            for &g in &active {
                ratio[g] *= s;
            }
        }
    }
    let determined = (0..groups)
        .map(|g| partners[g].len() >= options.min_partners && !at_edge[g])
        .collect::<Vec<_>>();
    for g in 0..groups {
        if !determined[g] {
            ratio[g] = 1.0;
        }
    }
    GroupCalibration { ratio, determined }
}

/// The minimum of `f` on `[a, b]` by golden section.
fn golden(f: &dyn Fn(f64) -> f64, mut a: f64, mut b: f64) -> f64 {
    let g = (5f64.sqrt() - 1.0) / 2.0;
    let (mut c, mut d) = (b - g * (b - a), a + g * (b - a));
    let (mut fc, mut fd) = (f(c), f(d));
    for _ in 0..40 {
        if fc < fd {
            b = d;
            d = c;
            fd = fc;
            c = b - g * (b - a);
            fc = f(c);
        } else {
            a = c;
            c = d;
            fc = fd;
            d = a + g * (b - a);
            fd = f(d);
        }
    }
    (a + b) / 2.0
}

/// Cameras from per-image ratios: returns each image's group (0 is the largest set of
/// determined images spanning at most `tolerance`, together with the undetermined ones; every
/// other image its own group, numbered in image order), each group's ratio relative to group
/// 0's, and group 0's ratio (the median of its determined images; 1 without any).
pub fn group_by_focal(
    ratio: &[f64],
    determined: &[bool],
    tolerance: f64,
) -> (Vec<usize>, Vec<f64>, f64) {
    let n = ratio.len();
    let mut order: Vec<usize> = (0..n).filter(|&i| determined[i]).collect();
    order.sort_by(|&a, &b| ratio[a].total_cmp(&ratio[b]).then(a.cmp(&b)));
    let limit = (1.0 + tolerance.max(0.0)).ln();
    // The widest window [lo, hi] of sorted log ratios with span ≤ limit.
    let (mut best, mut lo) = ((0, 0), 0);
    for hi in 0..order.len() {
        while ratio[order[hi]].ln() - ratio[order[lo]].ln() > limit {
            lo += 1;
        }
        if hi + 1 - lo > best.1 - best.0 {
            best = (lo, hi + 1);
        }
    }
    let mut in_main = vec![false; n];
    for &i in &order[best.0..best.1] {
        in_main[i] = true;
    }
    for i in 0..n {
        if !determined[i] {
            in_main[i] = true;
        }
    }
    let mut main: Vec<f64> = order[best.0..best.1].iter().map(|&i| ratio[i]).collect();
    main.sort_by(f64::total_cmp);
    let base = if main.is_empty() {
        1.0
    } else {
        main[main.len() / 2]
    };
    let mut group = vec![0; n];
    let mut ratios = vec![1.0];
    for i in 0..n {
        if !in_main[i] {
            group[i] = ratios.len();
            ratios.push(ratio[i] / base);
        }
    }
    (group, ratios, base)
}

#[cfg(test)]
mod tests {
    #![allow(clippy::unwrap_used)]
    use super::*;
    use crate::focal::essential_cost;
    use nalgebra::{Rotation3, Vector3};
    use posediff_geometry::epipolar::skew;

    fn fundamental(fa: f64, fb: f64, r: Rotation3<f64>, t: Vector3<f64>) -> Matrix3<f64> {
        let pp = [320.0, 240.0];
        let e = skew(&t.normalize()) * r.matrix();
        k_matrix(fb, pp).try_inverse().unwrap().transpose()
            * e
            * k_matrix(fa, pp).try_inverse().unwrap()
    }

    #[test]
    fn the_closed_form_cost_is_the_svd_cost() {
        let f = fundamental(
            700.0,
            900.0,
            Rotation3::from_euler_angles(0.1, 0.3, -0.05),
            Vector3::new(1.0, 0.1, 0.2),
        );
        let p = PairFundamental {
            f,
            principal_a: [320.0, 240.0],
            principal_b: [320.0, 240.0],
            scale_a: 640.0,
            scale_b: 640.0,
            weight: 1.0,
        };
        for phi in [0.8, 1.0, 1.2, 1.5] {
            let svd = essential_cost(&p, phi);
            let closed = pair_cost(&p, phi * 640.0, phi * 640.0);
            assert!((svd - closed).abs() < 1e-9, "{phi}: {svd} vs {closed}");
        }
        assert!(pair_cost(&p, 700.0, 900.0) < 1e-9);
    }

    /// Six images on a ring, every second one zoomed 1.5×: the per-image ratios come back,
    /// and the grouping gives the unzoomed images one camera and each zoomed one its own.
    #[test]
    fn per_image_focals_and_their_cameras_are_recovered() {
        let n = 6;
        let base = 640.0;
        let focal = |i: usize| if i % 2 == 1 { 1.5 * base } else { base };
        let pose = |i: usize| {
            let a = 0.25 * i as f64;
            let r = Rotation3::from_euler_angles(0.05 * i as f64, a, 0.02);
            let c = Vector3::new(4.0 * a.sin(), 0.3 * i as f64, -4.0 * a.cos());
            (r, c)
        };
        let mut pairs = Vec::new();
        for a in 0..n {
            for b in a + 1..n {
                let ((ra, ca), (rb, cb)) = (pose(a), pose(b));
                let r = rb * ra.inverse();
                let t = rb * (ca - cb);
                pairs.push(ImagePair {
                    a,
                    b,
                    fundamental: PairFundamental {
                        f: fundamental(focal(a), focal(b), r, t),
                        principal_a: [320.0, 240.0],
                        principal_b: [320.0, 240.0],
                        scale_a: base,
                        scale_b: base,
                        weight: 1.0,
                    },
                });
            }
        }
        let phi = 1.2;
        let group: Vec<usize> = (0..n).collect();
        let c = calibrate_groups(
            &pairs,
            &group,
            n,
            phi,
            &ViewGraphCalibrationOptions::default(),
        );
        for i in 0..n {
            assert!(c.determined[i]);
            let f = phi * c.ratio[i] * base;
            assert!((f / focal(i) - 1.0).abs() < 1e-3, "{i}: {f}");
        }
        let (groups, ratios, _) = group_by_focal(&c.ratio, &c.determined, 0.15);
        assert_eq!(groups, vec![0, 1, 0, 2, 0, 3]);
        assert_eq!(ratios.len(), 4);
        assert!((ratios[1] - 1.5).abs() < 2e-3, "{ratios:?}");
        // One lens: one camera.
        let (one, r, base) = group_by_focal(&[1.0, 1.05, 0.97, 1.02], &[true; 4], 0.15);
        assert_eq!((one, r, base), (vec![0; 4], vec![1.0], 1.02));
        // An undetermined image joins the main camera.
        let (g, _, _) = group_by_focal(&[1.0, 1.0, 2.0], &[true, true, false], 0.15);
        assert_eq!(g, vec![0; 3]);
    }
}
