//! What the F32 attention kernels ([`crate::attention`]) and their tile versions
//! ([`crate::tiles`]) share: the bound on a head's score block, the per-thread scratch kept
//! between calls, and the column side of the cross-attention's running softmax.

/// Score elements one head's block of query rows holds at most in [`crate::attention::attend_heads`] (1 MiB of
/// F32, within L2): 128 rows of 2048 keys.
pub(crate) const HEAD_BLOCK: usize = 1 << 18;

thread_local! {
    /// [`crate::attention::attend_heads`]' score block of the thread, kept between calls (LightGlue calls it
    /// four times a layer: a fresh megabyte each time was zeroed and page-faulted anew).
    /// With it, the rows' reciprocal sums.
    pub(crate) static SCORES: std::cell::RefCell<(Vec<f32>, Vec<f32>)> =
        const { std::cell::RefCell::new((Vec::new(), Vec::new())) };
}

/// Scores, weights, reciprocal row sums, column maxima of a block.
type CrossScratch = (Vec<f32>, Vec<f32>, Vec<f32>, Vec<f32>);

thread_local! {
    /// [`crate::attention::cross_attend_heads`]' score block, weight block, reciprocal row sums and the block's
    /// column maxima, kept between calls.
    pub(crate) static CROSS: std::cell::RefCell<CrossScratch> =
        const { std::cell::RefCell::new((Vec::new(), Vec::new(), Vec::new(), Vec::new())) };
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
