//! What the F32 attention kernels ([`crate::attention`]) and their tile versions
//! ([`crate::tiles`]) share: the head loops themselves ([`self_head`], [`cross_head`],
//! [`for_each_head`]), generic over the products ([`HeadProducts`], [`ColumnProducts`]: faer's
//! F32 products or AMX tiles), the bound on a head's score block, the per-thread scratch kept
//! between calls, and the column side of the cross-attention's running softmax.

use rayon::prelude::*;

use crate::error::Result;

/// One head's products, which the head loops are generic over: faer's F32 products
/// ([`crate::attention`]) or AMX tiles ([`crate::tiles`]). The keys and values are the
/// implementor's (set when it was made for the head).
pub(crate) trait HeadProducts {
    /// `s` (`len × n`, row-major) = `rows` (`len × d`, row-major) · keysᵀ.
    fn scores(&mut self, rows: &[f32], len: usize, s: &mut [f32]) -> Result<()>;

    /// `o` (`len × d`) = `exp(s − row max) · values` with the softmax's subnormal flush,
    /// unnormalised, and each row's `1/Σ` in `inv` (`s` may be overwritten).
    fn weighted_values(&mut self, s: &mut [f32], inv: &mut [f32], o: &mut [f32]) -> Result<()>;
}

/// The column side of cross-attention's products: the `n`-side output accumulated block by
/// block under running column maxima ([`raise_column_maxima`]), owned by the implementor until
/// [`ColumnProducts::finish_columns`] writes it out.
pub(crate) trait ColumnProducts {
    /// The row side's products (the other side's keys and values).
    type Rows: HeadProducts;

    /// The row side.
    fn rows(&mut self) -> &mut Self::Rows;

    /// Scales what column `j` accumulated by `alpha[j]` (1 where its maximum did not rise).
    fn rescale_columns(&mut self, alpha: &[f32]);

    /// Accumulates `other_valuesᵀ · W` with `W = exp(s − col_max[column])` (terms below `cut`
    /// zero), each column's weights added to `col_sum`; `other_values` are the block's `len`
    /// rows of the other side's values (`len × d`).
    fn accumulate_columns(
        &mut self,
        s: &[f32],
        columns: (&[f32], f32, &mut [f32]),
        other_values: &[f32],
        len: usize,
    ) -> Result<()>;

    /// Writes the column side's output (`n × d`, row-major), each column divided by its sum.
    fn finish_columns(self, col_sum: &[f32]);
}

/// Runs `head` on each `chunk`-long part of `out` (one head's output) with its index: in
/// parallel over rayon's threads when there are several heads and threads.
pub(crate) fn for_each_head(
    out: &mut [f32],
    chunk: usize,
    heads: usize,
    head: impl Fn((usize, &mut [f32])) -> Result<()> + Send + Sync,
) -> Result<()> {
    if heads > 1 && crate::threads() > 1 {
        out.par_chunks_mut(chunk).enumerate().try_for_each(head)
    } else {
        out.chunks_mut(chunk).enumerate().try_for_each(head)
    }
}

/// One head of self-attention: `out = softmax_rows(q Kᵀ) V` (`q` `m × d`, `out` `m × d`),
/// `rows` query rows a block, each block's scores in the thread's [`SCORES`], its output
/// scaled by its rows' `1/Σ` (`d` multiplications a row instead of `n`).
pub(crate) fn self_head<P: HeadProducts>(
    products: &mut P,
    q: &[f32],
    out: &mut [f32],
    (m, n, d): (usize, usize, usize),
    rows: usize,
) -> Result<()> {
    SCORES.with_borrow_mut(|(scores, inv)| {
        if scores.len() < rows * n {
            scores.resize(rows * n, 0.0);
        }
        if inv.len() < rows {
            inv.resize(rows, 0.0);
        }
        for start in (0..m).step_by(rows) {
            let len = rows.min(m - start);
            let s = &mut scores[..len * n];
            products.scores(&q[start * d..(start + len) * d], len, s)?;
            let o = &mut out[start * d..(start + len) * d];
            products.weighted_values(s, &mut inv[..len], o)?;
            for (row, &c) in o.chunks_exact_mut(d).zip(inv.iter()) {
                row.iter_mut().for_each(|x| *x *= c);
            }
        }
        Ok(())
    })
}

/// One head of bidirectional cross-attention: with `S = a Bᵀ` (`a` `m × d`), `out_a =
/// softmax_rows(S) vb` (`m × d`) through [`ColumnProducts::rows`], and `softmax_rows(Sᵀ) va`
/// through the [`ColumnProducts`]' column side (running column maxima and sums, the flash-attention rescaling): each
/// block of `S`'s rows is computed once and serves both directions.
pub(crate) fn cross_head<P: ColumnProducts>(
    mut products: P,
    (a, va): (&[f32], &[f32]),
    out_a: &mut [f32],
    (m, n, d): (usize, usize, usize),
    rows: usize,
) -> Result<()> {
    let mut col_max = vec![f32::NEG_INFINITY; n];
    let mut col_sum = vec![0f32; n];
    let mut alpha = vec![1f32; n];
    let cut = crate::softmax::flush_below(m);
    CROSS.with_borrow_mut(|(scores, inv, block_max)| -> Result<()> {
        scores.resize(rows * n, 0.0);
        inv.resize(rows, 0.0);
        block_max.resize(n, 0.0);
        for start in (0..m).step_by(rows) {
            let len = rows.min(m - start);
            let s = &mut scores[..len * n];
            products
                .rows()
                .scores(&a[start * d..(start + len) * d], len, s)?;
            // Columns: raise the maxima, rescale what was accumulated, this block's weights.
            alpha.fill(1.0);
            let mut rescaled = false;
            raise_column_maxima(s, block_max, (&mut col_max, &mut col_sum), cut, |j, f| {
                alpha[j] = f;
                rescaled = true;
            });
            if rescaled && start > 0 {
                products.rescale_columns(&alpha);
            }
            let other = &va[start * d..(start + len) * d];
            products.accumulate_columns(s, (&col_max, cut, &mut col_sum), other, len)?;
            // Rows: this block's softmax times vb.
            let o = &mut out_a[start * d..(start + len) * d];
            products.rows().weighted_values(s, &mut inv[..len], o)?;
            for (row, &c) in o.chunks_exact_mut(d).zip(inv.iter()) {
                row.iter_mut().for_each(|x| *x *= c);
            }
        }
        Ok(())
    })?;
    products.finish_columns(&col_sum);
    Ok(())
}

/// Score elements one head's block of query rows holds at most in [`crate::attention::attend_heads`] (1 MiB of
/// F32, within L2): 128 rows of 2048 keys.
pub(crate) const HEAD_BLOCK: usize = 1 << 18;

thread_local! {
    /// [`self_head`]'s score block of the thread, kept between calls (LightGlue calls it
    /// four times a layer: a fresh megabyte each time was zeroed and page-faulted anew).
    /// With it, the rows' reciprocal sums.
    pub(crate) static SCORES: std::cell::RefCell<(Vec<f32>, Vec<f32>)> =
        const { std::cell::RefCell::new((Vec::new(), Vec::new())) };
}

/// Scores, reciprocal row sums, column maxima of a block.
type CrossScratch = (Vec<f32>, Vec<f32>, Vec<f32>);

thread_local! {
    /// [`cross_head`]'s score block, reciprocal row sums and the block's column maxima, kept
    /// between calls.
    static CROSS: std::cell::RefCell<CrossScratch> =
        const { std::cell::RefCell::new((Vec::new(), Vec::new(), Vec::new())) };
    /// The F32 column side's weight block ([`crate::attention`]), kept between calls.
    pub(crate) static COLUMN_WEIGHTS: std::cell::RefCell<Vec<f32>> =
        const { std::cell::RefCell::new(Vec::new()) };
}

/// The column side of a block of scores `s` (row-major, `block_max.len()` wide): each column's
/// running maximum `col_max` rises to the block's (`block_max`, scratch), and what was
/// accumulated under the old maximum — the sum `col_sum` here, the caller's output through
/// `rescale(column, factor)` — is scaled by `exp(old − new)`. A factor that would leave
/// subnormal sums (below `cut`) clears them instead.
pub(crate) fn raise_column_maxima(
    s: &[f32],
    block_max: &mut [f32],
    (col_max, col_sum): (&mut [f32], &mut [f32]),
    cut: f32,
    mut rescale: impl FnMut(usize, f32),
) {
    pulp::Arch::new().dispatch(ColumnMaxima { s, block_max });
    for (j, &bm) in block_max.iter().enumerate() {
        if bm > col_max[j] {
            let alpha = crate::softmax::exp_f32(col_max[j] - bm);
            let alpha = if col_max[j] - bm < cut { 0.0 } else { alpha };
            col_sum[j] *= alpha;
            rescale(j, alpha);
            col_max[j] = bm;
        }
    }
}

/// Each column's maximum over the rows of `s` into `block_max` (NaNs ignored), compiled for
/// the CPU's features; `>` rather than `f32::max`, whose NaN rule costs a compare and a blend.
struct ColumnMaxima<'a> {
    s: &'a [f32],
    block_max: &'a mut [f32],
}

impl pulp::WithSimd for ColumnMaxima<'_> {
    type Output = ();

    #[inline(always)]
    fn with_simd<S: pulp::Simd>(self, _simd: S) {
        let Self { s, block_max } = self;
        block_max.fill(f32::NEG_INFINITY);
        for row in s.chunks_exact(block_max.len().max(1)) {
            for (m, &x) in block_max.iter_mut().zip(row) {
                *m = if x > *m { x } else { *m };
            }
        }
    }
}
