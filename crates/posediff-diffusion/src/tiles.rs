//! The products of LightGlue-sized layers on AMX tiles at PyTorch's "high" F32 matmul
//! precision ([`MatmulPrecision::High`]): every F32 operand as the sum of two BF16 values,
//! products accumulated in F32 (`posediff_amx`, [`posediff_amx::Split::Two`]).
//!
//! The same algorithms as the F32 kernels of [`crate::attention`] and [`crate::linear`] (blocks
//! of query rows, the softmax with its subnormal flush, the column rescaling), with each faer
//! product replaced by packing the operands and one tile product. Two things differ: the
//! softmax numerators come from `softmax::exp_fused` (fused multiply-adds, within two
//! ulps of the F32 kernels' `exp`) and go straight into the packed BF16 terms, and
//! self-attention takes blocks of 32 query rows (sized for L2). Operands that serve many products are packed once:
//! a layer's weight when it is first used, a head's keys and values once per head.
//!
//! # Pitfalls
//! - The results differ from the F32 path by about `2⁻¹⁶` of each dot product's `Σ|aᵢbᵢ|`, not
//!   by F32 rounding: the reference's parity fixtures are checked on [`MatmulPrecision::Highest`].
//! - Only where [`posediff_amx::available`] is true; everything else runs the F32 kernels.

use std::cell::RefCell;

use posediff_amx::{PackedA, PackedB, Split};
use rayon::prelude::*;

use crate::error::Result;
use crate::head_scratch::{ColumnProducts, HeadProducts, cross_head, for_each_head, self_head};

/// How the F32 matrix products of a network are computed on the CPU, after PyTorch's
/// `torch.set_float32_matmul_precision`.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default)]
pub enum MatmulPrecision {
    /// F32 products (faer): the reference's arithmetic, what the parity fixtures check.
    #[default]
    Highest,
    /// Where the CPU has AMX tiles, each F32 operand as the sum of two BF16 values (about 16
    /// significant bits, PyTorch's "high"); F32 products elsewhere.
    High,
}

impl MatmulPrecision {
    /// Whether products at this precision run on AMX tiles in this process.
    pub fn uses_tiles(self) -> bool {
        self == MatmulPrecision::High && posediff_amx::available()
    }
}

/// The split of [`MatmulPrecision::High`].
pub(crate) const SPLIT: Split = Split::Two;

/// `out (rows, out_dim) += x (rows, in_dim) · Wᵀ` with `W` packed (`packed_w`: `B = Wᵀ`), `out`
/// holding the bias (or zeros). Rows are split among rayon's threads in blocks of 32, each
/// thread packing its own rows.
pub(crate) fn linear(
    out: &mut [f32],
    x: &[f32],
    packed_w: &PackedB,
    rows: usize,
    in_dim: usize,
) -> Result<()> {
    let out_dim = packed_w.cols();
    if rows == 0 || out_dim == 0 {
        return Ok(());
    }
    let threads = crate::threads().max(1);
    let chunk = rows.div_ceil(threads).div_ceil(posediff_amx::BLOCK).max(1) * posediff_amx::BLOCK;
    let run = |(c, dst): (usize, &mut [f32])| -> Result<()> {
        let r0 = c * chunk;
        let len = dst.len() / out_dim;
        ROWS.with_borrow_mut(|slot| {
            let a = slot.get_or_insert_with(|| Box::new(PackedA::new(SPLIT)));
            a.pack(&x[r0 * in_dim..(r0 + len) * in_dim], len, in_dim, in_dim)?;
            posediff_amx::matmul(dst, out_dim, a, 0..len, packed_w, true)
        })?;
        Ok(())
    };
    if threads > 1 && rows > chunk {
        out.par_chunks_mut(chunk * out_dim)
            .enumerate()
            .try_for_each(run)
    } else {
        out.chunks_mut(chunk * out_dim)
            .enumerate()
            .try_for_each(run)
    }
}

/// Packs a weight `(out, in)` stored row-major (or column-major, `w[i·out + o]`) as `B = Wᵀ`.
pub(crate) fn pack_weight(
    w: &[f32],
    column_major: bool,
    out_dim: usize,
    in_dim: usize,
) -> Result<PackedB> {
    let mut b = PackedB::new(SPLIT);
    if column_major {
        // Wᵀ (in × out) row-major is `w` itself.
        b.pack(w, in_dim, out_dim, out_dim)?;
    } else {
        b.pack_transposed(w, out_dim, in_dim, in_dim)?;
    }
    Ok(b)
}

/// A head's packed operands, the packed blocks and the column side's accumulator of one thread.
struct Scratch {
    keys: PackedB,
    values: PackedB,
    /// The column side's weights of a block, `W` (`len × n`) as `B`.
    column_weights: PackedB,
    rows: PackedA,
    weights: PackedA,
    /// The block's other values transposed, `vaᵀ` (`d × len`) as `A`.
    other_values: PackedA,
    /// `out_bᵀ` (`d × n`).
    column_out: Vec<f32>,
    /// One or two rows of softmax numerators before they are split into BF16 terms.
    numerators: Vec<f32>,
}

impl Scratch {
    fn new() -> Self {
        Self {
            keys: PackedB::new(SPLIT),
            values: PackedB::new(SPLIT),
            column_weights: PackedB::new(SPLIT),
            rows: PackedA::new(SPLIT),
            weights: PackedA::new(SPLIT),
            other_values: PackedA::new(SPLIT),
            column_out: Vec::new(),
            numerators: Vec::new(),
        }
    }
}

thread_local! {
    // Boxed, so that each slot is a pointer: a library loaded into another process (the Python
    // module) gets its thread-locals from a small static TLS reserve.
    /// The rows of `A` a thread packs for [`linear`].
    static ROWS: RefCell<Option<Box<PackedA>>> = const { RefCell::new(None) };
    /// [`attend_heads`]' and [`cross_attend_heads`]' packed operands.
    static SCRATCH: RefCell<Option<Box<Scratch>>> = const { RefCell::new(None) };
}

/// Scores per block of self-attention on tiles: 32 rows of 2048 keys. A block's scores and
/// packed weights (256 KiB each) then stay in L2 beside the head's packed keys and values;
/// with the F32 kernel's 128 rows they did not, and the head took 36 ms instead of 30 (4 × 2048
/// × 2048, one thread, `attention_speed`). Cross-attention keeps the F32 kernel's block: its
/// column side re-reads a `d × n` accumulator once per block, and 32 rows were slower there.
const SELF_BLOCK: usize = 1 << 16;

/// Query rows per block of at most `budget` scores, a multiple of 32 (whole tile rows).
fn block_rows(m: usize, n: usize, budget: usize) -> usize {
    let rows = (budget / n).max(posediff_amx::BLOCK);
    (rows / posediff_amx::BLOCK * posediff_amx::BLOCK).min(m)
}

/// [`crate::attention::attend_heads`] on tiles; the shapes are checked by the caller (`m`,
/// `n`, `h`, `d` all positive).
pub(crate) fn attend_heads(
    q: &[f32],
    k: &[f32],
    v: &[f32],
    out: &mut [f32],
    (h, m, n, d): (usize, usize, usize, usize),
) -> Result<()> {
    let rows = block_rows(m, n, SELF_BLOCK);
    for_each_head(out, m * d, h, |(i, dst)| {
        let (qh, kh, vh) = (
            &q[i * m * d..(i + 1) * m * d],
            &k[i * n * d..(i + 1) * n * d],
            &v[i * n * d..(i + 1) * n * d],
        );
        SCRATCH.with_borrow_mut(|slot| -> Result<()> {
            let t = slot.get_or_insert_with(|| Box::new(Scratch::new()));
            let mut products = TileProducts::new(t, kh, vh, (n, d))?;
            self_head(&mut products, qh, dst, (m, n, d), rows)
        })
    })
}

/// [`crate::attention::cross_attend_heads`] on tiles; the shapes are checked by the caller
/// (all sizes positive).
pub(crate) fn cross_attend_heads(
    (a, b): (&[f32], &[f32]),
    (va, vb): (&[f32], &[f32]),
    out: &mut [f32],
    (h, m, n, d): (usize, usize, usize, usize),
) -> Result<()> {
    let rows = block_rows(m, n, crate::head_scratch::HEAD_BLOCK);
    for_each_head(out, (m + n) * d, h, |(i, dst)| {
        let (dst_a, dst_b) = dst.split_at_mut(m * d);
        let (ah, vah) = (
            &a[i * m * d..(i + 1) * m * d],
            &va[i * m * d..(i + 1) * m * d],
        );
        let (bh, vbh) = (
            &b[i * n * d..(i + 1) * n * d],
            &vb[i * n * d..(i + 1) * n * d],
        );
        SCRATCH.with_borrow_mut(|slot| -> Result<()> {
            let t = slot.get_or_insert_with(|| Box::new(Scratch::new()));
            // The column side accumulates out_bᵀ = vaᵀ W (d × n): the block's weights W are
            // packed as they lie, without a transpose of len × n values.
            t.column_out.clear();
            t.column_out.resize(d * n, 0.0);
            let columns = TileColumns {
                rows: TileProducts::new(t, bh, vbh, (n, d))?,
                out: dst_b,
            };
            cross_head(columns, (ah, vah), dst_a, (m, n, d), rows)
        })
    })
}

/// One head's products on tiles ([`HeadProducts`]): its keys packed as `Kᵀ` and its values as
/// they lie, once per head; each block's rows and softmax numerators packed as they come.
struct TileProducts<'a> {
    t: &'a mut Scratch,
    n: usize,
    d: usize,
}

impl<'a> TileProducts<'a> {
    /// Packs the head's keys (`S = Q Kᵀ`: `B = Kᵀ`, `d × n`) and values (`O = P V`: `B = V`,
    /// `n × d`).
    fn new(t: &'a mut Scratch, k: &[f32], v: &[f32], (n, d): (usize, usize)) -> Result<Self> {
        t.keys.pack_transposed(k, n, d, d)?;
        t.values.pack(v, n, d, d)?;
        Ok(Self { t, n, d })
    }
}

impl HeadProducts for TileProducts<'_> {
    fn scores(&mut self, rows: &[f32], len: usize, s: &mut [f32]) -> Result<()> {
        let t = &mut *self.t;
        t.rows.pack(rows, len, self.d, self.d)?;
        posediff_amx::matmul(s, self.n, &t.rows, 0..len, &t.keys, false)?;
        Ok(())
    }

    fn weighted_values(&mut self, s: &mut [f32], inv: &mut [f32], o: &mut [f32]) -> Result<()> {
        let t = &mut *self.t;
        exp_rows_packed(s, self.n, inv, &mut t.weights, &mut t.numerators)?;
        posediff_amx::matmul(o, self.d, &t.weights, 0..inv.len(), &t.values, false)?;
        Ok(())
    }
}

/// The column side on tiles: `out_bᵀ` (`d × n`) accumulated in the scratch's `column_out`,
/// written transposed into `out` (`n × d`) at the end.
struct TileColumns<'a> {
    rows: TileProducts<'a>,
    out: &'a mut [f32],
}

impl<'a> ColumnProducts for TileColumns<'a> {
    type Rows = TileProducts<'a>;

    fn rows(&mut self) -> &mut Self::Rows {
        &mut self.rows
    }

    /// The accumulated `out_bᵀ`'s columns rescaled in one pass.
    fn rescale_columns(&mut self, alpha: &[f32]) {
        let n = self.rows.n;
        for row in self.rows.t.column_out.chunks_exact_mut(n) {
            row.iter_mut().zip(alpha).for_each(|(x, a)| *x *= a);
        }
    }

    fn accumulate_columns(
        &mut self,
        s: &[f32],
        (col_max, cut, col_sum): (&[f32], f32, &mut [f32]),
        other_values: &[f32],
        len: usize,
    ) -> Result<()> {
        let (n, d) = (self.rows.n, self.rows.d);
        let t = &mut *self.rows.t;
        // W = exp(S − column maxima), packed as it is computed.
        exp_offsets_packed(
            s,
            n,
            col_max,
            cut,
            col_sum,
            (&mut t.column_weights, &mut t.numerators),
        )?;
        // out_bᵀ (d × n) += vaᵀ (d × len) · W (len × n).
        t.other_values.pack_transposed(other_values, d, len, d)?;
        posediff_amx::matmul(
            &mut t.column_out,
            n,
            &t.other_values,
            0..d,
            &t.column_weights,
            true,
        )?;
        Ok(())
    }

    /// `out_b = (out_bᵀ)ᵀ / Σ` per column.
    fn finish_columns(self, col_sum: &[f32]) {
        let (n, d) = (self.rows.n, self.rows.d);
        let column_out = &self.rows.t.column_out;
        for (j, (row, &sum)) in self.out.chunks_exact_mut(d).zip(col_sum).enumerate() {
            let c = 1.0 / sum;
            for (r, x) in row.iter_mut().enumerate() {
                *x = column_out[r * n + j] * c;
            }
        }
    }
}

/// The row softmax's numerators of `s` (`row`-wide rows) into `a`'s two BF16 terms, with each
/// row's `1/Σ` in `inv`: the steps of [`crate::softmax`]'s row kernel (maximum, `exp(x − max)`
/// with the subnormal flush, sum), `exp` by [`crate::softmax::exp_fused`]. Each row's F32
/// numerators pass through `scratch` (one row, in L1) on their way to the terms.
fn exp_rows_packed(
    s: &[f32],
    row: usize,
    inv: &mut [f32],
    a: &mut PackedA,
    scratch: &mut Vec<f32>,
) -> Result<()> {
    let (hi, lo, stride) = a.two_terms_mut(inv.len(), row)?;
    scratch.resize(row, 0.0);
    pulp::Arch::new().dispatch(ExpRowsPacked {
        s,
        row,
        inv,
        hi,
        lo,
        stride,
        weights: scratch,
    });
    Ok(())
}

struct ExpRowsPacked<'a> {
    s: &'a [f32],
    row: usize,
    inv: &'a mut [f32],
    hi: &'a mut [u16],
    lo: &'a mut [u16],
    stride: usize,
    weights: &'a mut [f32],
}

impl pulp::WithSimd for ExpRowsPacked<'_> {
    type Output = ();

    #[inline(always)]
    fn with_simd<S: pulp::Simd>(self, simd: S) {
        let Self {
            s,
            row,
            inv,
            hi,
            lo,
            stride,
            weights,
        } = self;
        let cut = crate::softmax::flush_below(row);
        let (cutv, zero) = (simd.splat_f32s(cut), simd.splat_f32s(0.0));
        // One row's weights, then split into the packed terms in a second pass (in L1).
        for (r, (values, inv)) in s.chunks_exact(row).zip(inv.iter_mut()).enumerate() {
            let max = crate::softmax::row_max(values);
            let maxv = simd.splat_f32s(max);
            let (blocks, tail) = S::as_simd_f32s(values);
            let (wb, wt) = S::as_mut_simd_f32s(weights);
            let mut acc = zero;
            for (&v, w) in blocks.iter().zip(wb.iter_mut()) {
                let d = simd.sub_f32s(v, maxv);
                let e = crate::softmax::exp_fused(simd, d);
                *w = simd.select_f32s(simd.less_than_f32s(d, cutv), zero, e);
                acc = simd.add_f32s(acc, *w);
            }
            let mut sum = simd.reduce_sum_f32s(acc);
            for (&v, w) in tail.iter().zip(wt.iter_mut()) {
                let d = v - max;
                let e = crate::softmax::exp_f32(d);
                *w = if d < cut { 0.0 } else { e };
                sum += *w;
            }
            let h = &mut hi[r * stride..r * stride + row];
            let l = &mut lo[r * stride..r * stride + row];
            for ((&w, hv), lv) in weights.iter().zip(h.iter_mut()).zip(l.iter_mut()) {
                (*hv, *lv) = posediff_amx::split_two(w);
            }
            *inv = 1.0 / sum;
        }
    }
}

/// Cross-attention's column weights `exp(s − offsets[column])` (terms below `cut` zero, each
/// column's sum added to `sums`) into `b`'s BF16 pairs, two rows at a time through `scratch`
/// (two rows of F32, in L1).
fn exp_offsets_packed(
    s: &[f32],
    row: usize,
    offsets: &[f32],
    cut: f32,
    sums: &mut [f32],
    (b, scratch): (&mut PackedB, &mut Vec<f32>),
) -> Result<()> {
    let k = s.len() / row.max(1);
    let (hi, lo, stride) = b.two_term_pairs_mut(k, row)?;
    scratch.resize(2 * row, 0.0);
    let (even, odd) = scratch.split_at_mut(row);
    pulp::Arch::new().dispatch(ExpOffsetsPacked {
        s,
        row,
        offsets,
        cut,
        sums,
        hi,
        lo,
        stride,
        even,
        odd,
    });
    Ok(())
}

struct ExpOffsetsPacked<'a> {
    s: &'a [f32],
    row: usize,
    offsets: &'a [f32],
    cut: f32,
    sums: &'a mut [f32],
    hi: &'a mut [u32],
    lo: &'a mut [u32],
    stride: usize,
    even: &'a mut [f32],
    odd: &'a mut [f32],
}

impl pulp::WithSimd for ExpOffsetsPacked<'_> {
    type Output = ();

    #[inline(always)]
    fn with_simd<S: pulp::Simd>(self, simd: S) {
        let Self {
            s,
            row,
            offsets,
            cut,
            sums,
            hi,
            lo,
            stride,
            even,
            odd,
        } = self;
        let k = s.len() / row.max(1);
        for r in 0..k.div_ceil(2) {
            offset_weights(simd, &s[2 * r * row..(2 * r + 1) * row], offsets, cut, even);
            if 2 * r + 1 < k {
                let values = &s[(2 * r + 1) * row..(2 * r + 2) * row];
                offset_weights(simd, values, offsets, cut, odd);
            } else {
                odd.fill(0.0);
            }
            let h = &mut hi[r * stride..r * stride + row];
            let l = &mut lo[r * stride..r * stride + row];
            for ((((&we, &wo), sum), hv), lv) in even
                .iter()
                .zip(odd.iter())
                .zip(sums.iter_mut())
                .zip(h.iter_mut())
                .zip(l.iter_mut())
            {
                *sum += we + wo;
                let (eh, el) = posediff_amx::split_two(we);
                let (oh, ol) = posediff_amx::split_two(wo);
                *hv = eh as u32 | (oh as u32) << 16;
                *lv = el as u32 | (ol as u32) << 16;
            }
        }
    }
}

/// One row of [`ExpOffsetsPacked`]'s weights, `exp(values − offsets)` with the terms below `cut`
/// zero, written to `out` (a function, not a closure, so that it is compiled for `S`'s
/// features).
#[inline(always)]
fn offset_weights<S: pulp::Simd>(
    simd: S,
    values: &[f32],
    offsets: &[f32],
    cut: f32,
    out: &mut [f32],
) {
    let (cutv, zero) = (simd.splat_f32s(cut), simd.splat_f32s(0.0));
    let (blocks, tail) = S::as_simd_f32s(values);
    let (ob, ot) = S::as_simd_f32s(offsets);
    let (wb, wt) = S::as_mut_simd_f32s(out);
    for ((&v, &o), w) in blocks.iter().zip(ob).zip(wb.iter_mut()) {
        let d = simd.sub_f32s(v, o);
        let e = crate::softmax::exp_fused(simd, d);
        *w = simd.select_f32s(simd.less_than_f32s(d, cutv), zero, e);
    }
    for ((&v, &o), w) in tail.iter().zip(ot).zip(wt.iter_mut()) {
        let d = v - o;
        let e = crate::softmax::exp_f32(d);
        *w = if d < cut { 0.0 } else { e };
    }
}
