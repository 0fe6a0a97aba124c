//! The reduced camera system solved without forming it: preconditioned conjugate gradients on
//! `S = A − E C⁻¹ Eᵀ`, each product `S v` computed observation by observation (Ceres'
//! `ITERATIVE_SCHUR` with the `SCHUR_JACOBI` preconditioner).
//!
//! The explicit Schur complement costs `Σ k²` block products per point and a sparse Cholesky
//! whose fill grows with how many cameras each camera shares a point with; on a slow video
//! the tracks span more frames as the frames grow, so both grow faster than the frames. Here
//! one product `S v` costs a few dozen multiply-adds per observation:
//!
//! 1. `y_o = J_o v` for each observation `o` of a point (its camera, focal and lens blocks);
//! 2. `z = Σ_o J_pᵀ W y_o`, `q = C⁻¹ z`;
//! 3. `S v += Σ_o J_oᵀ W (y_o − J_p q)`,
//!
//! which is `A v − E C⁻¹ Eᵀ v`. The preconditioner is the exact block diagonal of `S` (with
//! the same Levenberg–Marquardt damping as the explicit path), whose elimination costs `Σ k`
//! per point. Both are filled in [`super::SCHUR_PARTS`] runs of points added in order, so the
//! result does not depend on the thread count.

use nalgebra::{DMatrix, Matrix3, SMatrix, SVector, Vector2};
use rayon::prelude::*;

use super::{
    IterativeSchurOptions, PointBlocks, PointLinearisation, SCHUR_PARTS, add_coupling,
    damped_inverse,
};

/// The reduced system's block layout and the iteration count so far.
#[derive(Debug, Clone)]
pub(super) struct ImplicitSchur {
    /// First parameter of each block.
    offsets: Vec<usize>,
    /// Size of each block.
    sizes: Vec<usize>,
    /// Where each block's (full, row-major) diagonal block starts in the packed diagonal.
    diagonal_at: Vec<usize>,
    diagonal_len: usize,
    dim: usize,
    options: IterativeSchurOptions,
    /// Conjugate-gradient iterations over every solve.
    pub(super) iterations: usize,
    /// Solves that stopped at `max_iterations` before the tolerance.
    pub(super) unconverged: usize,
}

/// One part's share: the diagonal blocks of `S`, the right-hand side and each point's `C⁻¹`.
type Part = (Vec<f64>, Vec<f64>, Vec<Matrix3<f64>>);

impl ImplicitSchur {
    pub(super) fn new(sizes: &[usize], options: IterativeSchurOptions) -> Self {
        let mut offsets = Vec::with_capacity(sizes.len());
        let mut diagonal_at = Vec::with_capacity(sizes.len());
        let (mut dim, mut diagonal_len) = (0, 0);
        for &s in sizes {
            offsets.push(dim);
            diagonal_at.push(diagonal_len);
            dim += s;
            diagonal_len += s * s;
        }
        Self {
            offsets,
            sizes: sizes.to_vec(),
            diagonal_at,
            diagonal_len,
            dim,
            options,
            iterations: 0,
            unconverged: 0,
        }
    }

    /// Adds `m(i, j)` to block `b`'s diagonal block.
    fn add_diagonal(&self, diagonal: &mut [f64], b: usize, m: impl Fn(usize, usize) -> f64) {
        let (at, s) = (self.diagonal_at[b], self.sizes[b]);
        for i in 0..s {
            for j in 0..s {
                diagonal[at + i * s + j] += m(i, j);
            }
        }
    }

    /// The diagonal blocks of `S` and the right-hand side `−g + E C⁻¹ g_p` of `linear`'s
    /// points at damping `lambda`, with each point's `C⁻¹`; `None` when a point's `C` is not
    /// invertible.
    fn eliminate_diagonal(
        &self,
        linear: &[PointLinearisation],
        blocks: &[PointBlocks],
        lambda: f64,
    ) -> Option<Part> {
        let mut diagonal = vec![0.0; self.diagonal_len];
        let mut rhs = vec![0.0; self.dim];
        let mut inverses = Vec::with_capacity(linear.len());
        let mut es: Vec<SMatrix<f64, 6, 3>> = Vec::new();
        let mut gs: Vec<SVector<f64, 6>> = Vec::new();
        for (lin, blocks) in linear.iter().zip(blocks) {
            let c_inv = damped_inverse(&lin.c, lambda)?;
            let entries = blocks.entries.len();
            es.clear();
            es.resize(entries, SMatrix::zeros());
            gs.clear();
            gs.resize(entries, SVector::zeros());
            for o in &lin.obs {
                let (camera, focal, coefficient) = blocks.obs[o.index];
                add_coupling(o, (camera, focal, coefficient), &mut es, &mut gs);
                if let Some(u) = camera {
                    let h = o.jc.transpose() * o.jc * o.w;
                    self.add_diagonal(&mut diagonal, blocks.entries[u], |i, j| h[(i, j)]);
                }
                if let Some(v) = focal {
                    let h = o.jf.norm_squared() * o.w;
                    self.add_diagonal(&mut diagonal, blocks.entries[v], |_, _| h);
                }
                if let Some(l) = coefficient {
                    let h = o.jk.transpose() * o.jk * o.w;
                    self.add_diagonal(&mut diagonal, blocks.entries[l], |i, j| h[(i, j)]);
                }
            }
            let cg = c_inv * lin.g;
            for (u, &b) in blocks.entries.iter().enumerate() {
                let v = es[u] * cg;
                let o = self.offsets[b];
                for i in 0..self.sizes[b] {
                    rhs[o + i] += -gs[u][i] + v[i];
                }
                let m = es[u] * c_inv * es[u].transpose();
                self.add_diagonal(&mut diagonal, b, |i, j| -m[(i, j)]);
            }
            inverses.push(c_inv);
        }
        Some((diagonal, rhs, inverses))
    }

    /// `S x` over `linear`'s points (without the damping), added into `out`.
    fn product_into(
        &self,
        linear: &[PointLinearisation],
        blocks: &[PointBlocks],
        inverses: &[Matrix3<f64>],
        x: &[f64],
        out: &mut [f64],
    ) {
        let mut ys: Vec<Vector2<f64>> = Vec::new();
        for ((lin, blocks), c_inv) in linear.iter().zip(blocks).zip(inverses) {
            ys.clear();
            let mut z = SVector::<f64, 3>::zeros();
            for o in &lin.obs {
                let (camera, focal, coefficient) = blocks.obs[o.index];
                let mut y = Vector2::zeros();
                if let Some(u) = camera {
                    let at = self.offsets[blocks.entries[u]];
                    y += o.jc * SVector::<f64, 6>::from_column_slice(&x[at..at + 6]);
                }
                if let Some(v) = focal {
                    y += o.jf * x[self.offsets[blocks.entries[v]]];
                }
                if let Some(l) = coefficient {
                    let b = blocks.entries[l];
                    let at = self.offsets[b];
                    for c in 0..self.sizes[b] {
                        y += o.jk.column(c) * x[at + c];
                    }
                }
                z += o.jp.transpose() * y * o.w;
                ys.push(y);
            }
            let q = c_inv * z;
            for (o, y) in lin.obs.iter().zip(&ys) {
                let t = (y - o.jp * q) * o.w;
                let (camera, focal, coefficient) = blocks.obs[o.index];
                if let Some(u) = camera {
                    let at = self.offsets[blocks.entries[u]];
                    let v = o.jc.transpose() * t;
                    for i in 0..6 {
                        out[at + i] += v[i];
                    }
                }
                if let Some(v) = focal {
                    out[self.offsets[blocks.entries[v]]] += o.jf.dot(&t);
                }
                if let Some(l) = coefficient {
                    let b = blocks.entries[l];
                    let at = self.offsets[b];
                    for c in 0..self.sizes[b] {
                        out[at + c] += o.jk.column(c).dot(&t);
                    }
                }
            }
        }
    }

    /// Solves the damped reduced system of `linear`'s points (as the explicit path:
    /// `(S + diag(λ S_kk + 10⁻¹² max S_kk)) δ = rhs`) to the relative residual
    /// `options.tolerance`; returns `δ` and each point's `C⁻¹`, `None` when a point's `C` or a
    /// block of the preconditioner is not positive definite at this damping.
    pub(super) fn solve(
        &mut self,
        linear: &[PointLinearisation],
        blocks: &[PointBlocks],
        lambda: f64,
    ) -> Option<super::Solved> {
        let chunk = linear.len().div_ceil(SCHUR_PARTS).max(1);
        let this = &*self;
        let parts: Vec<Option<Part>> = linear
            .par_chunks(chunk)
            .zip(blocks.par_chunks(chunk))
            .map(|(l, b)| this.eliminate_diagonal(l, b, lambda))
            .collect();
        let mut diagonal = vec![0.0; self.diagonal_len];
        let mut rhs = vec![0.0; self.dim];
        let mut inverses = Vec::with_capacity(linear.len());
        for part in parts {
            let (d, r, inv) = part?;
            for (a, b) in diagonal.iter_mut().zip(&d) {
                *a += b;
            }
            for (a, b) in rhs.iter_mut().zip(&r) {
                *a += b;
            }
            inverses.extend(inv);
        }
        // The damping of the explicit path, on the diagonal of S.
        let mut damping = vec![0.0; self.dim];
        let mut largest: f64 = 1e-300;
        for (b, (&o, &s)) in self.offsets.iter().zip(&self.sizes).enumerate() {
            for i in 0..s {
                let v = diagonal[self.diagonal_at[b] + i * s + i];
                damping[o + i] = v;
                largest = largest.max(v);
            }
        }
        for d in &mut damping {
            *d = lambda * *d + 1e-12 * largest;
        }
        // Block-Jacobi preconditioner: each damped diagonal block inverted once (by Cholesky:
        // not positive definite is more damping), packed as the diagonal is.
        let mut preconditioner = vec![0.0; self.diagonal_len];
        for (b, (&o, &s)) in self.offsets.iter().zip(&self.sizes).enumerate() {
            let at = self.diagonal_at[b];
            let m = DMatrix::from_fn(s, s, |i, j| {
                diagonal[at + i * s + j] + if i == j { damping[o + i] } else { 0.0 }
            });
            preconditioner[at..at + s * s].copy_from_slice(m.cholesky()?.inverse().as_slice());
        }
        let precondition = |r: &[f64]| -> Vec<f64> {
            let mut z = vec![0.0; r.len()];
            for (b, (&o, &s)) in self.offsets.iter().zip(&self.sizes).enumerate() {
                let inverse = &preconditioner[self.diagonal_at[b]..][..s * s];
                for i in 0..s {
                    z[o + i] = (0..s).map(|j| inverse[i * s + j] * r[o + j]).sum();
                }
            }
            z
        };
        let product = |x: &[f64]| -> Vec<f64> {
            let parts: Vec<Vec<f64>> = linear
                .par_chunks(chunk)
                .zip(blocks.par_chunks(chunk))
                .zip(inverses.par_chunks(chunk))
                .map(|((l, b), inv)| {
                    let mut out = vec![0.0; this.dim];
                    this.product_into(l, b, inv, x, &mut out);
                    out
                })
                .collect();
            let mut out: Vec<f64> = x.iter().zip(&damping).map(|(x, d)| x * d).collect();
            for p in parts {
                for (a, b) in out.iter_mut().zip(&p) {
                    *a += b;
                }
            }
            out
        };
        let (x, iterations, converged) = conjugate_gradients(
            product,
            precondition,
            &rhs,
            self.options.tolerance,
            self.options.max_iterations,
        );
        self.iterations += iterations;
        self.unconverged += usize::from(!converged);
        Some((x, inverses))
    }
}

fn dot(a: &[f64], b: &[f64]) -> f64 {
    a.iter().zip(b).map(|(x, y)| x * y).sum()
}

/// Preconditioned conjugate gradients from zero on `A x = b` until `|r| ≤ tolerance · |b|`
/// or `max_iterations`; returns `x`, the iterations and whether the tolerance was reached.
/// Stops early, with the last iterate, if the curvature `pᵀ A p` is not positive.
fn conjugate_gradients(
    product: impl Fn(&[f64]) -> Vec<f64>,
    precondition: impl Fn(&[f64]) -> Vec<f64>,
    b: &[f64],
    tolerance: f64,
    max_iterations: usize,
) -> (Vec<f64>, usize, bool) {
    let mut x = vec![0.0; b.len()];
    let target = tolerance * dot(b, b).sqrt();
    let mut r = b.to_vec();
    if dot(&r, &r).sqrt() <= target {
        return (x, 0, true);
    }
    let mut z = precondition(&r);
    let mut p = z.clone();
    let mut rz = dot(&r, &z);
    for it in 1..=max_iterations {
        let ap = product(&p);
        let curvature = dot(&p, &ap);
        if curvature.partial_cmp(&0.0) != Some(std::cmp::Ordering::Greater) || !rz.is_finite() {
            return (x, it, false);
        }
        let alpha = rz / curvature;
        for ((x, r), (p, ap)) in x.iter_mut().zip(&mut r).zip(p.iter().zip(&ap)) {
            *x += alpha * p;
            *r -= alpha * ap;
        }
        if dot(&r, &r).sqrt() <= target {
            return (x, it, true);
        }
        z = precondition(&r);
        let rz_next = dot(&r, &z);
        let beta = rz_next / rz;
        rz = rz_next;
        for (p, z) in p.iter_mut().zip(&z) {
            *p = z + beta * *p;
        }
    }
    (x, max_iterations, false)
}

#[cfg(test)]
mod tests {
    #![allow(clippy::unwrap_used)]
    use super::*;
    use nalgebra::DVector;

    /// On a small symmetric positive definite system, the iterate solves it.
    #[test]
    fn conjugate_gradients_solve_a_positive_definite_system() {
        let n = 12;
        let m = DMatrix::from_fn(n, n, |i, j| ((i * 7 + j * 3) % 5) as f64 - 2.0);
        let a = &m * m.transpose() + DMatrix::identity(n, n);
        let truth = DVector::from_fn(n, |i, _| (i as f64).sin());
        let b = &a * &truth;
        let product = |x: &[f64]| (&a * DVector::from_column_slice(x)).as_slice().to_vec();
        let jacobi = |r: &[f64]| (0..n).map(|i| r[i] / a[(i, i)]).collect::<Vec<_>>();
        let (x, iterations, converged) =
            conjugate_gradients(product, jacobi, b.as_slice(), 1e-12, 100);
        assert!(converged && iterations <= n + 2, "{iterations}");
        let error = (DVector::from_column_slice(&x) - truth).amax();
        assert!(error < 1e-9, "{error}");
        // Too few iterations: reported as not converged.
        let (_, iterations, converged) =
            conjugate_gradients(product, jacobi, b.as_slice(), 1e-12, 2);
        assert!(!converged && iterations == 2);
    }
}
