//! Symmetric positive definite systems with a block sparsity pattern, solved by faer.
//!
//! Every normal-equation system of the mapper (rotation and translation averaging, the Sampson
//! refinement, the bundle adjustment's reduced camera system) has unknowns in small blocks
//! (3 per rotation or centre, 6 per camera, 1 for the shared focal) and non-zero blocks where two
//! unknowns share a measurement. [`BlockSystem`] fixes that pattern once: its symbolic sparse
//! Cholesky factorisation (with faer's fill-reducing ordering) is computed at construction and
//! reused for every numeric factorisation, so a Levenberg–Marquardt or IRLS loop only refills
//! values and factorises numerically. [`Solver::Dense`] solves the same values by a dense faer
//! Cholesky (for small systems and as the reference in tests).

use std::collections::HashMap;

use faer::linalg::solvers::Solve;
use faer::sparse::linalg::solvers::{Llt, SymbolicLlt};
use faer::sparse::{Pair, SparseColMat, SymbolicSparseColMat};
use faer::{Mat, Side};

use crate::error::{Result, SfmError};

/// How a [`BlockSystem`] is factorised.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default)]
#[cfg_attr(
    feature = "serde",
    derive(serde::Serialize, serde::Deserialize),
    serde(rename_all = "snake_case")
)]
pub enum Solver {
    /// Sparse Cholesky with the symbolic factorisation reused (the default).
    #[default]
    Sparse,
    /// Dense Cholesky of the same matrix (reference; only for small systems).
    Dense,
}

/// The values of a [`BlockSystem`]'s pattern filled apart from it ([`BlockSystem::zero_part`]).
#[derive(Debug, Clone)]
pub struct BlockValues {
    values: Vec<f64>,
    rhs: Vec<f64>,
}

/// Adds block `(bi, bj)`'s `m` to `values` at `base` (the stored lower triangle).
fn add_block_values(
    sizes: &[usize],
    values: &mut [f64],
    base: usize,
    bi: usize,
    bj: usize,
    m: impl Fn(usize, usize) -> f64,
) {
    let (hi, lo, swap) = if bi >= bj {
        (bi, bj, false)
    } else {
        (bj, bi, true)
    };
    let at = |r: usize, c: usize| if swap { m(c, r) } else { m(r, c) };
    if hi == lo {
        let mut k = base;
        for r in 0..sizes[hi] {
            for c in 0..=r {
                values[k] += at(r, c);
                k += 1;
            }
        }
    } else {
        let cols = sizes[lo];
        for r in 0..sizes[hi] {
            for c in 0..cols {
                values[base + r * cols + c] += at(r, c);
            }
        }
    }
}

/// Adds `v(k)` to block `b`'s entries of `rhs`.
fn add_rhs_values(
    offsets: &[usize],
    sizes: &[usize],
    rhs: &mut [f64],
    b: usize,
    v: impl Fn(usize) -> f64,
) {
    let o = offsets[b];
    for k in 0..sizes[b] {
        rhs[o + k] += v(k);
    }
}

/// A symmetric system `H x = b` whose non-zeros lie in fixed blocks; only the lower triangle
/// is stored.
pub struct BlockSystem {
    what: &'static str,
    offsets: Vec<usize>,
    sizes: Vec<usize>,
    dim: usize,
    /// (block row, block column) with row ≥ column → position of the block's first value.
    slots: HashMap<(usize, usize), usize>,
    /// Lower-triangle values in the order of `entries`.
    values: Vec<f64>,
    /// Position of each diagonal entry in `values`.
    diagonal: Vec<usize>,
    /// The right-hand side.
    rhs: Vec<f64>,
    /// The matrix handed to faer (lower triangle, compressed columns), refilled in place.
    matrix: SparseColMat<usize, f64>,
    /// Position in `matrix`'s values of each stored value.
    csc_position: Vec<usize>,
    llt: Option<SymbolicLlt<usize>>,
}

impl std::fmt::Debug for BlockSystem {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("BlockSystem")
            .field("what", &self.what)
            .field("dim", &self.dim)
            .field("blocks", &self.sizes.len())
            .field("stored", &self.values.len())
            .finish()
    }
}

impl BlockSystem {
    /// A system with blocks of `sizes` and non-zero blocks at `pairs` (either order; the
    /// diagonal blocks are always present). `what` names it in errors.
    ///
    /// # Errors
    /// A pair naming a block that does not exist; faer failing to build the pattern.
    pub fn new(
        what: &'static str,
        sizes: &[usize],
        pairs: impl IntoIterator<Item = (usize, usize)>,
        solver: Solver,
    ) -> Result<Self> {
        let mut offsets = Vec::with_capacity(sizes.len());
        let mut dim = 0;
        for &s in sizes {
            offsets.push(dim);
            dim += s;
        }
        let mut blocks: Vec<(usize, usize)> = (0..sizes.len()).map(|i| (i, i)).collect();
        for (a, b) in pairs {
            if a >= sizes.len() || b >= sizes.len() {
                return Err(SfmError::InvalidInput(format!(
                    "{what}: block pair ({a}, {b}) of {} blocks",
                    sizes.len()
                )));
            }
            blocks.push((a.max(b), a.min(b)));
        }
        blocks.sort_unstable();
        blocks.dedup();
        let mut slots = HashMap::with_capacity(blocks.len());
        let mut entries: Vec<Pair<usize, usize>> = Vec::new();
        let mut diagonal = vec![0; dim];
        for &(bi, bj) in &blocks {
            slots.insert((bi, bj), entries.len());
            for r in 0..sizes[bi] {
                let cols = if bi == bj { r + 1 } else { sizes[bj] };
                for c in 0..cols {
                    let (row, col) = (offsets[bi] + r, offsets[bj] + c);
                    if row == col {
                        diagonal[row] = entries.len();
                    }
                    entries.push(Pair::new(row, col));
                }
            }
        }
        let linalg = |e: &dyn std::fmt::Debug| SfmError::Linalg {
            what,
            detail: format!("{e:?}"),
        };
        let (symbolic, argsort) = SymbolicSparseColMat::try_new_from_indices(dim, dim, &entries)
            .map_err(|e| linalg(&e))?;
        // Where each entry lands in compressed-column order (entries are unique).
        let order: Vec<f64> = (0..entries.len()).map(|k| k as f64).collect();
        let matrix =
            SparseColMat::new_from_argsort(symbolic, &argsort, &order).map_err(|e| linalg(&e))?;
        let mut csc_position = vec![0; entries.len()];
        for (position, &k) in matrix.val().iter().enumerate() {
            csc_position[k as usize] = position;
        }
        let llt = match solver {
            Solver::Sparse if dim > 0 => {
                Some(SymbolicLlt::try_new(matrix.symbolic(), Side::Lower).map_err(|e| linalg(&e))?)
            }
            _ => None,
        };
        Ok(Self {
            what,
            sizes: sizes.to_vec(),
            offsets,
            dim,
            slots,
            values: vec![0.0; entries.len()],
            diagonal,
            rhs: vec![0.0; dim],
            matrix,
            csc_position,
            llt,
        })
    }

    /// Number of unknowns.
    pub fn dim(&self) -> usize {
        self.dim
    }

    /// Zeroes the matrix and the right-hand side (the pattern stays).
    pub fn clear(&mut self) {
        self.values.fill(0.0);
        self.rhs.fill(0.0);
    }

    /// Adds `m(r, c)` for `r` in block `bi`, `c` in block `bj` (the block `H[bi][bj]`; its
    /// transpose is implied). Pairs outside the pattern are an error.
    ///
    /// # Errors
    /// A block pair that is not in the pattern.
    pub fn add_block(
        &mut self,
        bi: usize,
        bj: usize,
        m: impl Fn(usize, usize) -> f64,
    ) -> Result<()> {
        let Some(base) = self.slot(bi, bj) else {
            return Err(SfmError::InvalidInput(format!(
                "{}: block ({bi}, {bj}) is not in the sparsity pattern",
                self.what
            )));
        };
        self.add_block_at(base, bi, bj, m);
        Ok(())
    }

    /// Where the values of block `(bi, bj)` (either order) start, `None` outside the pattern;
    /// for [`Self::add_block_at`] in loops that add to the same blocks every iteration.
    pub fn slot(&self, bi: usize, bj: usize) -> Option<usize> {
        self.slots.get(&(bi.max(bj), bi.min(bj))).copied()
    }

    /// [`Self::add_block`] at a `base` from [`Self::slot`]`(bi, bj)` (no lookup).
    pub fn add_block_at(
        &mut self,
        base: usize,
        bi: usize,
        bj: usize,
        m: impl Fn(usize, usize) -> f64,
    ) {
        add_block_values(&self.sizes, &mut self.values, base, bi, bj, m);
    }

    /// Adds `v(k)` to the right-hand side of block `b`.
    pub fn add_rhs(&mut self, b: usize, v: impl Fn(usize) -> f64) {
        add_rhs_values(&self.offsets, &self.sizes, &mut self.rhs, b, v);
    }

    /// Zero values and right-hand side of this pattern, to be filled apart from the system
    /// (one part per task) and added into it by [`Self::set_parts`].
    pub fn zero_part(&self) -> BlockValues {
        BlockValues {
            values: vec![0.0; self.values.len()],
            rhs: vec![0.0; self.rhs.len()],
        }
    }

    /// [`Self::add_block_at`] into a part.
    pub fn add_block_in(
        &self,
        part: &mut BlockValues,
        base: usize,
        bi: usize,
        bj: usize,
        m: impl Fn(usize, usize) -> f64,
    ) {
        add_block_values(&self.sizes, &mut part.values, base, bi, bj, m);
    }

    /// [`Self::add_rhs`] into a part.
    pub fn add_rhs_in(&self, part: &mut BlockValues, b: usize, v: impl Fn(usize) -> f64) {
        add_rhs_values(&self.offsets, &self.sizes, &mut part.rhs, b, v);
    }

    /// The matrix and right-hand side set to the sum of `parts` (added in their order, so the
    /// result does not depend on which thread filled which part).
    pub fn set_parts<'p>(&mut self, parts: impl IntoIterator<Item = &'p BlockValues>) {
        self.clear();
        for p in parts {
            self.add_part(p);
        }
    }

    /// Adds `part` to the matrix and right-hand side: [`Self::set_parts`] one part at a time
    /// (after [`Self::clear`]), so that a caller need not hold every part at once.
    pub fn add_part(&mut self, part: &BlockValues) {
        for (v, x) in self.values.iter_mut().zip(&part.values) {
            *v += x;
        }
        for (v, x) in self.rhs.iter_mut().zip(&part.rhs) {
            *v += x;
        }
    }

    /// The right-hand side.
    pub fn rhs(&self) -> &[f64] {
        &self.rhs
    }

    /// Solves `(H + diag(d)) x = rhs` where `d_k = lambda·H_kk + floor` (Levenberg–Marquardt
    /// damping; `lambda = 0, floor = 0` for the plain system). Returns `Ok(None)` when the
    /// damped matrix is not positive definite (the caller raises the damping or reports it).
    ///
    /// # Errors
    /// faer failing for a reason other than a non-positive pivot; a non-finite solution.
    pub fn solve_damped(&mut self, lambda: f64, floor: f64) -> Result<Option<Vec<f64>>> {
        if self.dim == 0 {
            return Ok(Some(Vec::new()));
        }
        let csc = self.matrix.val_mut();
        for (k, &v) in self.values.iter().enumerate() {
            csc[self.csc_position[k]] = v;
        }
        for &k in &self.diagonal {
            csc[self.csc_position[k]] += lambda * self.values[k] + floor;
        }
        let mut x = Mat::<f64>::from_fn(self.dim, 1, |i, _| self.rhs[i]);
        match &self.llt {
            Some(symbolic) => {
                match Llt::try_new_with_symbolic(
                    symbolic.clone(),
                    self.matrix.as_ref(),
                    Side::Lower,
                ) {
                    Ok(llt) => llt.solve_in_place(x.as_mut()),
                    Err(faer::sparse::linalg::LltError::Numeric(_)) => return Ok(None),
                    Err(e) => return Err(self.linalg_error(e)),
                }
            }
            None => match self.matrix.to_dense().llt(Side::Lower) {
                Ok(llt) => llt.solve_in_place(x.as_mut()),
                Err(_) => return Ok(None),
            },
        }
        let out: Vec<f64> = (0..self.dim).map(|i| x[(i, 0)]).collect();
        if out.iter().any(|v| !v.is_finite()) {
            return Err(SfmError::NotPositiveDefinite {
                what: self.what,
                detail: "the solution is not finite".into(),
            });
        }
        Ok(Some(out))
    }

    /// [`Self::solve_damped`] with the floor `1e-12 · max_k H_kk` that every system of the
    /// mapper uses (a regularisation far below the data's scale).
    ///
    /// # Errors
    /// As [`Self::solve_damped`].
    pub fn solve_regularised(&mut self, lambda: f64) -> Result<Option<Vec<f64>>> {
        let largest = self
            .diagonal
            .iter()
            .map(|&k| self.values[k])
            .fold(0.0, f64::max)
            .max(1e-300);
        self.solve_damped(lambda, 1e-12 * largest)
    }

    /// [`Self::solve_damped`] for the plain system: not positive definite is an error.
    ///
    /// # Errors
    /// As [`Self::solve_damped`]; a matrix that is not positive definite.
    pub fn solve(&mut self) -> Result<Vec<f64>> {
        self.solve_damped(0.0, 0.0)?
            .ok_or_else(|| SfmError::NotPositiveDefinite {
                what: self.what,
                detail: "non-positive pivot".into(),
            })
    }

    fn linalg_error(&self, e: impl std::fmt::Debug) -> SfmError {
        SfmError::Linalg {
            what: self.what,
            detail: format!("{e:?}"),
        }
    }
}

#[cfg(test)]
mod tests {
    #![allow(clippy::unwrap_used)]
    use super::*;

    /// A block tridiagonal SPD system solved sparse and dense against a hand-checked residual.
    #[test]
    fn parts_filled_apart_add_up_to_the_system() {
        let sizes = [3, 2, 3, 1];
        let pairs = [(0, 1), (2, 1), (3, 0), (3, 2)];
        let fill = |s: &mut BlockSystem, b: usize| {
            s.add_block(b, b, |r, c| if r == c { 4.0 + b as f64 } else { 0.5 })
                .unwrap();
            s.add_rhs(b, |k| (b + k) as f64 - 1.5);
        };
        let mut whole = BlockSystem::new("test", &sizes, pairs, Solver::Sparse).unwrap();
        for b in 0..4 {
            fill(&mut whole, b);
        }
        for &(a, b) in &pairs {
            whole
                .add_block(a, b, |r, c| 0.1 * (r as f64 + 1.0) - 0.05 * c as f64)
                .unwrap();
        }
        // The same terms split over two parts (the off-diagonal blocks by their swapped
        // transposes in the second), and stale values in the system that set_parts replaces.
        let mut split = BlockSystem::new("test", &sizes, pairs, Solver::Sparse).unwrap();
        fill(&mut split, 0);
        let (mut first, mut second) = (split.zero_part(), split.zero_part());
        for b in 0..4 {
            let part = if b % 2 == 0 { &mut first } else { &mut second };
            let base = split.slot(b, b).unwrap();
            split.add_block_in(
                part,
                base,
                b,
                b,
                |r, c| {
                    if r == c { 4.0 + b as f64 } else { 0.5 }
                },
            );
            split.add_rhs_in(part, b, |k| (b + k) as f64 - 1.5);
        }
        for &(a, b) in &pairs {
            let base = split.slot(a, b).unwrap();
            split.add_block_in(&mut second, base, b, a, |c, r| {
                0.1 * (r as f64 + 1.0) - 0.05 * c as f64
            });
        }
        split.set_parts([&first, &second]);
        assert_eq!(split.values, whole.values);
        assert_eq!(split.rhs(), whole.rhs());
        assert_eq!(split.solve().unwrap(), whole.solve().unwrap());
    }

    #[test]
    fn sparse_and_dense_agree_and_solve() {
        let sizes = [3, 2, 3, 1];
        let pairs = [(0, 1), (2, 1), (3, 0), (3, 2)];
        let mut solutions = Vec::new();
        for solver in [Solver::Sparse, Solver::Dense] {
            let mut s = BlockSystem::new("test", &sizes, pairs, solver).unwrap();
            for b in 0..4 {
                s.add_block(b, b, |r, c| if r == c { 4.0 + b as f64 } else { 0.5 })
                    .unwrap();
                s.add_rhs(b, |k| (b + k) as f64 - 1.5);
            }
            for &(a, b) in &pairs {
                s.add_block(a, b, |r, c| 0.1 * (r as f64 + 1.0) - 0.05 * c as f64)
                    .unwrap();
            }
            assert!(s.add_block(0, 2, |_, _| 1.0).is_err());
            let x = s.solve().unwrap();
            solutions.push((x, s));
        }
        let (x, s) = &solutions[0];
        for (a, b) in x.iter().zip(&solutions[1].0) {
            assert!((a - b).abs() < 1e-12, "{a} vs {b}");
        }
        // Residual of the full symmetric matrix.
        let mut lower = s.matrix.clone();
        for (k, &v) in s.values.iter().enumerate() {
            lower.val_mut()[s.csc_position[k]] = v;
        }
        let dense = lower.to_dense();
        for i in 0..s.dim() {
            let mut acc = 0.0;
            for j in 0..s.dim() {
                let v = if i >= j { dense[(i, j)] } else { dense[(j, i)] };
                acc += v * x[j];
            }
            assert!((acc - s.rhs()[i]).abs() < 1e-12);
        }
    }

    #[test]
    fn an_indefinite_system_is_reported() {
        for solver in [Solver::Sparse, Solver::Dense] {
            let mut s = BlockSystem::new("test", &[2], [], solver).unwrap();
            s.add_block(0, 0, |r, c| if r == c { 1.0 } else { 2.0 })
                .unwrap();
            assert!(s.solve_damped(0.0, 0.0).unwrap().is_none());
            assert!(matches!(
                s.solve(),
                Err(SfmError::NotPositiveDefinite { .. })
            ));
            // Enough damping makes it definite.
            assert!(s.solve_damped(0.0, 2.0).unwrap().is_some());
        }
    }
}
