//! A shared focal length from pairwise fundamental matrices (Mendonça & Cipolla, CVPR 1999).
//!
//! With the right intrinsics `K`, `E = K_bᵀ F K_a` is essential: its two non-zero singular values
//! are equal. For a focal `f_i = φ·s_i` (one unknown `φ` for all images, `s_i` a per-image scale
//! such as the longer side; principal points fixed) the cost is the inlier-weighted sum of
//! `(σ₁ − σ₂)/(σ₁ + σ₂)` over the pairs; `φ` is found by a log-spaced grid search followed by a
//! golden-section refinement around the best grid point.
//!
//! The cost is flat for pure rotations and for pairs whose fundamental matrix is poorly
//! conditioned (tiny baselines); those pairs should be left out. The result is only a start:
//! the refinement ([`crate::sampson_refine`]) adjusts the focal together with the poses.
//!
//! Without parallax anywhere (pure rotations), [`focal_from_homographies`] finds the `φ` at
//! which the pairs' homographies `K_b R K_a⁻¹` are closest to rotations.

use nalgebra::Matrix3;
use posediff_geometry::homography_rotation;

use crate::intrinsics::{ImageIntrinsics, k_matrix};

/// One pair's fundamental matrix and the intrinsics it depends on.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct PairFundamental {
    /// `F` with `x_bᵀ F x_a = 0` (pixels).
    pub f: Matrix3<f64>,
    /// Principal point of image `a` (pixels).
    pub principal_a: [f64; 2],
    /// Principal point of image `b`.
    pub principal_b: [f64; 2],
    /// `f_a = φ · scale_a`.
    pub scale_a: f64,
    /// `f_b = φ · scale_b`.
    pub scale_b: f64,
    /// Confidence (e.g. inlier count).
    pub weight: f64,
}

fn intrinsics(phi: f64, scale: f64, principal: [f64; 2]) -> Matrix3<f64> {
    k_matrix(phi * scale, principal)
}

/// How far `K_bᵀ F K_a` is from essential at `phi`: `(σ₁ − σ₂)/(σ₁ + σ₂)` in `[0, 1]`.
pub fn essential_cost(pair: &PairFundamental, phi: f64) -> f64 {
    let e = intrinsics(phi, pair.scale_b, pair.principal_b).transpose()
        * pair.f
        * intrinsics(phi, pair.scale_a, pair.principal_a);
    let mut s = e.singular_values();
    s.as_mut_slice().sort_by(|a, b| b.total_cmp(a));
    if s[0] + s[1] <= 0.0 || !(s[0] + s[1]).is_finite() {
        return 1.0;
    }
    (s[0] - s[1]) / (s[0] + s[1])
}

/// The weighted cost of all pairs at `phi`.
pub fn total_cost(pairs: &[PairFundamental], phi: f64) -> f64 {
    pairs
        .iter()
        .map(|p| p.weight * essential_cost(p, phi))
        .sum()
}

/// Search range and resolution of [`self_calibrate`].
#[derive(Debug, Clone, Copy, PartialEq)]
#[cfg_attr(
    feature = "serde",
    derive(serde::Serialize, serde::Deserialize),
    serde(default, deny_unknown_fields)
)]
pub struct FocalSearch {
    /// Smallest `φ`.
    pub min: f64,
    /// Largest `φ`.
    pub max: f64,
    /// Grid points (log-spaced).
    pub steps: usize,
}

impl Default for FocalSearch {
    /// With `s_i` the longer image side: fields of view from about 14° (`φ = 4`) to 127°
    /// (`φ = 0.25`) across the longer side.
    fn default() -> Self {
        Self {
            min: 0.25,
            max: 4.0,
            steps: 200,
        }
    }
}

/// The `φ` minimising [`total_cost`], `None` without pairs or for an invalid range.
pub fn self_calibrate(pairs: &[PairFundamental], search: &FocalSearch) -> Option<f64> {
    if pairs.is_empty()
        || search.steps < 2
        || !(search.min > 0.0 && search.max > search.min && search.max.is_finite())
    {
        return None;
    }
    let (lo, hi) = (search.min.ln(), search.max.ln());
    let step = (hi - lo) / (search.steps - 1) as f64;
    let best = (0..search.steps)
        .map(|k| (k, total_cost(pairs, (lo + step * k as f64).exp())))
        .min_by(|a, b| a.1.total_cmp(&b.1))?
        .0;
    // Golden section on log φ within the neighbouring grid cells.
    let (mut a, mut b) = (
        lo + step * best.saturating_sub(1) as f64,
        lo + step * (best + 1).min(search.steps - 1) as f64,
    );
    let g = (5f64.sqrt() - 1.0) / 2.0;
    let cost = |x: f64| total_cost(pairs, x.exp());
    let (mut c, mut d) = (b - g * (b - a), a + g * (b - a));
    let (mut fc, mut fd) = (cost(c), cost(d));
    for _ in 0..60 {
        if fc < fd {
            b = d;
            d = c;
            fd = fc;
            c = b - g * (b - a);
            fc = cost(c);
        } else {
            a = c;
            c = d;
            fc = fd;
            d = a + g * (b - a);
            fd = cost(d);
        }
    }
    Some(((a + b) / 2.0).exp())
}

/// `φ` from rotation-only homographies `(a, b, H_ab)`: `K_b⁻¹ H K_a` is a rotation at the right
/// focal. A grid search over the range of `search`; `None` without pairs.
pub fn focal_from_homographies(
    pairs: &[(usize, usize, Matrix3<f64>)],
    layout: &ImageIntrinsics,
    search: &FocalSearch,
) -> Option<f64> {
    if pairs.is_empty() || !(search.min > 0.0 && search.max > search.min) {
        return None;
    }
    let cost = |phi: f64| -> f64 {
        pairs
            .iter()
            .map(|(a, b, h)| {
                homography_rotation(h, &layout.k(phi, *a), &layout.k_inverse(phi, *b))
                    .map_or(1.0, |(_, ratio)| ratio - 1.0)
            })
            .sum()
    };
    let steps = search.steps.max(2);
    let (lo, hi) = (search.min.ln(), search.max.ln());
    (0..steps)
        .map(|k| (lo + (hi - lo) * k as f64 / (steps - 1) as f64).exp())
        .map(|phi| (phi, cost(phi)))
        .min_by(|a, b| a.1.total_cmp(&b.1))
        .map(|(phi, _)| phi)
}

#[cfg(test)]
mod tests {
    #![allow(clippy::unwrap_used)]
    use super::*;
    use nalgebra::{Rotation3, Vector3};
    use posediff_geometry::epipolar::skew;

    #[test]
    fn recovers_the_focal_of_exact_fundamentals() {
        let phi_true = 1.3;
        let scale = 640.0;
        let pp = [320.0, 240.0];
        let k = intrinsics(phi_true, scale, pp);
        let k_inv = k.try_inverse().unwrap();
        let pairs: Vec<PairFundamental> = (0..4)
            .map(|i| {
                let r = Rotation3::from_euler_angles(0.1 * i as f64, 0.3 + 0.05 * i as f64, 0.02);
                let t = Vector3::new(1.0, 0.2 * i as f64, 0.3).normalize();
                let e = skew(&t) * r.matrix();
                PairFundamental {
                    f: k_inv.transpose() * e * k_inv,
                    principal_a: pp,
                    principal_b: pp,
                    scale_a: scale,
                    scale_b: scale,
                    weight: 1.0,
                }
            })
            .collect();
        assert!(essential_cost(&pairs[0], phi_true) < 1e-12);
        assert!(essential_cost(&pairs[0], 2.0 * phi_true) > 1e-3);
        let phi = self_calibrate(&pairs, &FocalSearch::default()).unwrap();
        assert!((phi / phi_true - 1.0).abs() < 1e-6, "{phi}");
        assert!(self_calibrate(&[], &FocalSearch::default()).is_none());
    }

    #[test]
    fn homographies_of_rotations_give_the_focal() {
        let layout = ImageIntrinsics::new(vec![[320.0, 240.0]; 3], vec![640.0; 3]);
        let phi_true = 0.9;
        let pairs: Vec<(usize, usize, Matrix3<f64>)> = (1..3)
            .map(|b| {
                let r = Rotation3::from_euler_angles(0.05 * b as f64, 0.2, -0.03);
                (
                    0,
                    b,
                    layout.k(phi_true, b) * r.matrix() * layout.k_inverse(phi_true, 0),
                )
            })
            .collect();
        let search = FocalSearch {
            steps: 2000,
            ..FocalSearch::default()
        };
        let phi = focal_from_homographies(&pairs, &layout, &search).unwrap();
        assert!((phi / phi_true - 1.0).abs() < 2e-3, "{phi}");
        assert!(focal_from_homographies(&[], &layout, &search).is_none());
    }
}
