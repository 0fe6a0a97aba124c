//! Multi-head self-attention from a packed `qkv` projection, fused per image and head for F32
//! on the CPU: `softmax(s · Q Kᵀ) V` per head of the `(B, N, 3·C)` projection (PyTorch's
//! packing: `[q | k | v]`, each `H` heads of `D = C/H`), with the head's `Q`, `K`, `V`, its
//! `N × N` scores and its output in per-thread buffers reused across heads (L2-sized for the
//! ViT's 197 tokens), the scale folded into the product and the output written straight into
//! `(B, N, C)`.
//!
//! candle's path splits `q`, `k`, `v` into contiguous copies, multiplies them as a batch of
//! small matrices (about 56 GFLOP/s here), scales, applies the softmax and transposes the
//! result back: four extra passes and five allocations per layer. Other dtypes, devices and
//! tracked tensors keep that path ([`attention_candle`]).

use candle_core::{CpuStorage, DType, Shape, Tensor};
use faer::{Accum, MatMut, MatRef, Par};
use rayon::prelude::*;

use crate::error::Result;
use crate::tiles::MatmulPrecision;

/// `softmax(scale · Q Kᵀ) V` per head for `qkv` `(B, N, 3·C)` with `heads` heads: `(B, N, C)`.
///
/// # Errors
/// A last dimension that is not `3 · heads · D`, tensor errors.
pub fn self_attention(qkv: &Tensor, heads: usize, scale: f64) -> Result<Tensor> {
    if qkv.dtype() == DType::F32 && qkv.device().is_cpu() && !qkv.track_op() {
        let op = crate::CpuOp {
            name: "fused-self-attention-f32",
            run: |ops: &[crate::Operand<'_>]| fused_attention(ops[0], heads, scale as f32),
        };
        return Ok(qkv.contiguous()?.apply_op1_no_bwd(&op)?);
    }
    attention_candle(qkv, heads, scale)
}

/// The same with candle's tensor ops (differentiable; any dtype and device).
///
/// # Errors
/// As [`self_attention`].
pub fn attention_candle(qkv: &Tensor, heads: usize, scale: f64) -> Result<Tensor> {
    let (b, n, c3) = qkv.dims3()?;
    let c = c3 / 3;
    let d = c / heads.max(1);
    let p = qkv.reshape((b, n, 3, heads, d))?.permute((2, 0, 3, 1, 4))?;
    let (q, k, v) = (
        p.get(0)?.contiguous()?,
        p.get(1)?.contiguous()?,
        p.get(2)?.contiguous()?,
    );
    let attn = (q.matmul(&k.t()?)? * scale)?;
    let attn = crate::norm::softmax_last_dim(&attn)?;
    Ok(attn.matmul(&v)?.transpose(1, 2)?.reshape((b, n, c))?)
}

/// The op of [`self_attention`]: `qkv` `(B, N, 3·C)` contiguous F32 into `(B, N, C)`.
fn fused_attention(
    (storage, layout): crate::Operand<'_>,
    h: usize,
    scale: f32,
) -> candle_core::Result<(CpuStorage, Shape)> {
    let qkv = crate::contiguous_f32(storage, layout, "fused attention: qkv")?;
    let (b, n, c3) = layout.shape().dims3()?;
    if h == 0 || c3 % (3 * h) != 0 {
        candle_core::bail!("fused attention: {c3} is not 3 × {h} heads × a head width");
    }
    let c = c3 / 3;
    let mut out = vec![0f32; b * n * c];
    attend(qkv, &mut out, (b, n, c, h), scale);
    Ok((CpuStorage::F32(out), Shape::from((b, n, c))))
}

/// Per-thread buffers of one head: `Q`, `K`, `V`, the output (`N × D` each) and the scores.
struct Scratch {
    q: Vec<f32>,
    k: Vec<f32>,
    v: Vec<f32>,
    o: Vec<f32>,
    scores: Vec<f32>,
}

/// Images in parallel (each writes its own `N × C` block), heads in turn.
fn attend(qkv: &[f32], out: &mut [f32], (b, n, c, h): (usize, usize, usize, usize), scale: f32) {
    if b == 0 || n == 0 || c == 0 {
        return;
    }
    let d = c / h;
    let per_image = |(image, dst): (usize, &mut [f32])| {
        let src = &qkv[image * n * 3 * c..(image + 1) * n * 3 * c];
        let mut scratch = Scratch {
            q: vec![0f32; n * d],
            k: vec![0f32; n * d],
            v: vec![0f32; n * d],
            o: vec![0f32; n * d],
            scores: vec![0f32; n * n],
        };
        for head in 0..h {
            attend_head(src, dst, &mut scratch, (n, c, d, head), scale);
        }
    };
    if b > 1 && crate::threads() > 1 {
        out.par_chunks_mut(n * c).enumerate().for_each(per_image);
    } else {
        out.chunks_mut(n * c).enumerate().for_each(per_image);
    }
}

/// One head of one image: `S = scale · Q Kᵀ` (row-major `N × N`), its row softmax, then
/// `dst[:, head] = S V`. The head's `Q`, `K`, `V` are gathered into contiguous buffers first
/// and every product runs on contiguous matrices (faer 0.24 corrupted the heap on views with
/// gaps between rows: `munmap_chunk(): invalid pointer` for `N = 1`, `D = 3`).
fn attend_head(
    src: &[f32],
    dst: &mut [f32],
    buf: &mut Scratch,
    (n, c, d, head): (usize, usize, usize, usize),
    scale: f32,
) {
    for (i, row) in src.chunks_exact(3 * c).enumerate() {
        let at = head * d;
        buf.q[i * d..(i + 1) * d].copy_from_slice(&row[at..at + d]);
        buf.k[i * d..(i + 1) * d].copy_from_slice(&row[c + at..c + at + d]);
        buf.v[i * d..(i + 1) * d].copy_from_slice(&row[2 * c + at..2 * c + at + d]);
    }
    // Row-major N × D buffers are column-major D × N: Qᵀ, Kᵀ, Vᵀ.
    let qt = MatRef::from_column_major_slice(&buf.q, d, n);
    let kt = MatRef::from_column_major_slice(&buf.k, d, n);
    let vt = MatRef::from_column_major_slice(&buf.v, d, n);
    // Sᵀ = K Qᵀ, column-major: S row-major.
    let st = MatMut::from_column_major_slice_mut(&mut buf.scores, n, n);
    faer::linalg::matmul::matmul(st, Accum::Replace, kt.transpose(), qt, scale, Par::Seq);
    crate::softmax::softmax_rows_dispatch(&mut buf.scores, n);
    // Oᵀ = Vᵀ Sᵀ, column-major D × N: O row-major N × D.
    let st = MatRef::from_column_major_slice(&buf.scores, n, n);
    let ot = MatMut::from_column_major_slice_mut(&mut buf.o, d, n);
    faer::linalg::matmul::matmul(ot, Accum::Replace, vt, st, 1.0, Par::Seq);
    for (i, row) in buf.o.chunks_exact(d).enumerate() {
        dst[i * c + head * d..i * c + (head + 1) * d].copy_from_slice(row);
    }
}

use crate::head_scratch::{
    COLUMN_WEIGHTS, ColumnProducts, HEAD_BLOCK, HeadProducts, cross_head, for_each_head, self_head,
};

/// [`attend_heads`] on tensors: `q` `(h, m, d)` (already scaled), `k` and `v` `(h, n, d)`, F32
/// on the CPU, untracked; `(h, m, d)`. The buffers are read in place (no copies in or out).
///
/// # Errors
/// Other dtypes or devices, shapes that do not agree, tensor errors.
pub fn attention_heads(q: &Tensor, k: &Tensor, v: &Tensor) -> Result<Tensor> {
    attention_heads_with(q, k, v, MatmulPrecision::Highest)
}

/// [`attention_heads`] with the products at `precision` ([`attend_heads_with`]).
///
/// # Errors
/// As [`attention_heads`].
pub fn attention_heads_with(
    q: &Tensor,
    k: &Tensor,
    v: &Tensor,
    precision: MatmulPrecision,
) -> Result<Tensor> {
    let (h, _, d) = q.dims3()?;
    let (hk, n, dk) = k.dims3()?;
    if (hk, dk) != (h, d) || v.dims3()? != (h, n, d) {
        return Err(crate::DiffusionError::Shape {
            what: "attention k and v",
            expected: "(h, n, d) with q's h and d",
            got: [k.dims(), v.dims()].concat(),
        });
    }
    let op = crate::CpuOp {
        name: "attention-heads-f32",
        run: |ops: &[crate::Operand<'_>]| heads_attention(ops, precision),
    };
    Ok(q.contiguous()?
        .apply_op3_no_bwd(&k.contiguous()?, &v.contiguous()?, &op)?)
}

/// The op of [`attention_heads_with`]: `q`, `k`, `v` contiguous F32 into `(h, m, d)`.
fn heads_attention(
    ops: &[crate::Operand<'_>],
    precision: MatmulPrecision,
) -> candle_core::Result<(CpuStorage, Shape)> {
    let [(s1, l1), (s2, l2), (s3, l3)] = ops else {
        candle_core::bail!("attention: q, k and v expected");
    };
    let q = crate::contiguous_f32(s1, l1, "attention: q")?;
    let k = crate::contiguous_f32(s2, l2, "attention: k")?;
    let v = crate::contiguous_f32(s3, l3, "attention: v")?;
    let (h, m, d) = l1.shape().dims3()?;
    let n = l2.shape().dims3()?.1;
    let mut out = vec![0f32; h * m * d];
    attend_heads_with(q, k, v, &mut out, (h, m, n, d), precision)
        .map_err(|e| candle_core::Error::Msg(e.to_string()))?;
    Ok((CpuStorage::F32(out), Shape::from((h, m, d))))
}

/// `softmax(Q Kᵀ) V` per head for row-major per-head buffers: `q` `(h, m, d)` (already
/// scaled), `k` and `v` `(h, n, d)`, written to `out` `(h, m, d)`. Heads run in parallel over
/// rayon's threads, each on blocks of query rows whose scores never exceed `HEAD_BLOCK`
/// elements; every product is faer's (its kernel chosen at run time: AVX-512 where the CPU has
/// it), the softmax is [`crate::softmax`]'s. LightGlue's self- and cross-attention over
/// thousands of points, where candle's batched product runs its AVX2 kernel.
///
/// # Errors
/// Buffers whose lengths do not match the shape.
pub fn attend_heads(
    q: &[f32],
    k: &[f32],
    v: &[f32],
    out: &mut [f32],
    shape: (usize, usize, usize, usize),
) -> Result<()> {
    attend_heads_with(q, k, v, out, shape, MatmulPrecision::Highest)
}

/// [`attend_heads`] with the products at `precision`: on AMX tiles at
/// [`MatmulPrecision::High`] where the CPU has them ([`crate::tiles`]), faer's F32 products
/// otherwise.
///
/// # Errors
/// As [`attend_heads`]; a tile product's error.
pub fn attend_heads_with(
    q: &[f32],
    k: &[f32],
    v: &[f32],
    out: &mut [f32],
    (h, m, n, d): (usize, usize, usize, usize),
    precision: MatmulPrecision,
) -> Result<()> {
    if q.len() != h * m * d || k.len() != h * n * d || v.len() != h * n * d || out.len() != q.len()
    {
        return Err(crate::DiffusionError::Shape {
            what: "attention buffers",
            expected: "q and out h·m·d values, k and v h·n·d",
            got: vec![q.len(), k.len(), v.len(), out.len()],
        });
    }
    if h == 0 || m == 0 || d == 0 {
        return Ok(());
    }
    if n == 0 {
        // No keys: no message (PyTorch's softmax over nothing would give NaN rows).
        out.fill(0.0);
        return Ok(());
    }
    if precision.uses_tiles() {
        return crate::tiles::attend_heads(q, k, v, out, (h, m, n, d));
    }
    let rows = (HEAD_BLOCK / n).clamp(1, m);
    for_each_head(out, m * d, h, |(i, dst)| {
        let (qh, kh, vh) = (
            &q[i * m * d..(i + 1) * m * d],
            &k[i * n * d..(i + 1) * n * d],
            &v[i * n * d..(i + 1) * n * d],
        );
        let mut products = F32Products::new(kh, vh, n, d);
        self_head(&mut products, qh, dst, (m, n, d), rows)
    })
}

/// faer's F32 products of one head ([`HeadProducts`]): its keys and values as `Kᵀ`, `Vᵀ`
/// (row-major `n × d` buffers are column-major `d × n`).
struct F32Products<'a> {
    kt: MatRef<'a, f32>,
    vt: MatRef<'a, f32>,
}

impl<'a> F32Products<'a> {
    fn new(k: &'a [f32], v: &'a [f32], n: usize, d: usize) -> Self {
        Self {
            kt: MatRef::from_column_major_slice(k, d, n),
            vt: MatRef::from_column_major_slice(v, d, n),
        }
    }
}

impl HeadProducts for F32Products<'_> {
    fn scores(&mut self, rows: &[f32], len: usize, s: &mut [f32]) -> Result<()> {
        let (d, n) = (self.kt.nrows(), self.kt.ncols());
        let qt = MatRef::from_column_major_slice(rows, d, len);
        // Sᵀ = K Qᵀ column-major is S row-major (len × n).
        let st = MatMut::from_column_major_slice_mut(s, n, len);
        faer::linalg::matmul::matmul(st, Accum::Replace, self.kt.transpose(), qt, 1.0, Par::Seq);
        Ok(())
    }

    /// `exp(S − max)` per row ([`crate::softmax`]), then the product.
    fn weighted_values(&mut self, s: &mut [f32], inv: &mut [f32], o: &mut [f32]) -> Result<()> {
        let (d, n, len) = (self.vt.nrows(), self.vt.ncols(), inv.len());
        crate::softmax::exp_rows_dispatch(s, n, inv);
        let st = MatRef::from_column_major_slice(s, n, len);
        // Oᵀ = Vᵀ Sᵀ column-major is O row-major (len × d).
        let ot = MatMut::from_column_major_slice_mut(o, d, len);
        faer::linalg::matmul::matmul(ot, Accum::Replace, self.vt, st, 1.0, Par::Seq);
        Ok(())
    }
}

/// The F32 column side: the row products of the other side's keys and values, with the `n`
/// side's unnormalised output accumulated in place (`n × d` row-major, i.e. `d × n`
/// column-major) and the block's weights in the thread's `COLUMN_WEIGHTS`.
struct F32Columns<'a> {
    rows: F32Products<'a>,
    out: &'a mut [f32],
}

impl<'a> ColumnProducts for F32Columns<'a> {
    type Rows = F32Products<'a>;

    fn rows(&mut self) -> &mut Self::Rows {
        &mut self.rows
    }

    fn rescale_columns(&mut self, alpha: &[f32]) {
        let d = self.rows.kt.nrows();
        for (row, &a) in self.out.chunks_exact_mut(d).zip(alpha) {
            if a != 1.0 {
                row.iter_mut().for_each(|x| *x *= a);
            }
        }
    }

    fn accumulate_columns(
        &mut self,
        s: &[f32],
        (col_max, cut, col_sum): (&[f32], f32, &mut [f32]),
        other_values: &[f32],
        len: usize,
    ) -> Result<()> {
        let (d, n) = (self.rows.kt.nrows(), self.rows.kt.ncols());
        COLUMN_WEIGHTS.with_borrow_mut(|weights| {
            if weights.len() < len * n {
                weights.resize(len * n, 0.0);
            }
            let w = &mut weights[..len * n];
            crate::softmax::exp_offsets_dispatch(s, w, n, col_max, cut, col_sum);
            // out_b (d × n column-major) += vaᵀ (d × len) · W (len × n).
            let vat = MatRef::from_column_major_slice(other_values, d, len);
            let wt = MatRef::from_column_major_slice(w, n, len);
            let ob = MatMut::from_column_major_slice_mut(self.out, d, n);
            faer::linalg::matmul::matmul(ob, Accum::Add, vat, wt.transpose(), 1.0, Par::Seq);
        });
        Ok(())
    }

    fn finish_columns(self, col_sum: &[f32]) {
        let d = self.rows.kt.nrows();
        for (row, &sum) in self.out.chunks_exact_mut(d).zip(col_sum) {
            let c = 1.0 / sum;
            row.iter_mut().for_each(|x| *x *= c);
        }
    }
}

/// Bidirectional cross-attention with one similarity per head, as LightGlue's reference
/// computes it: for `a` `(h, m, d)` and `b` `(h, n, d)` (both already scaled) and values `va`
/// `(h, m, d)`, `vb` `(h, n, d)`, with `S = a bᵀ`, writes `out_a = softmax_rows(S) vb`
/// `(h, m, d)` and `out_b = softmax_rows(Sᵀ) va` `(h, n, d)`.
///
/// Each block of `S`'s rows is computed once and serves both directions: its rows' softmax
/// directly, its columns' through a running maximum and sum per column (the flash-attention
/// rescaling), so the `n`-side never needs the whole matrix. Three products per block instead of
/// the four of two [`attend_heads`] calls. Terms whose weight would be subnormal are zero, as
/// in the softmax.
///
/// # Errors
/// Buffers whose lengths do not match the shape.
pub fn cross_attend_heads(
    inputs: (&[f32], &[f32]),
    values: (&[f32], &[f32]),
    out: &mut [f32],
    shape: (usize, usize, usize, usize),
) -> Result<()> {
    cross_attend_heads_with(inputs, values, out, shape, MatmulPrecision::Highest)
}

/// [`cross_attend_heads`] with the products at `precision` (as [`attend_heads_with`]).
///
/// # Errors
/// As [`cross_attend_heads`]; a tile product's error.
pub fn cross_attend_heads_with(
    (a, b): (&[f32], &[f32]),
    (va, vb): (&[f32], &[f32]),
    out: &mut [f32],
    (h, m, n, d): (usize, usize, usize, usize),
    precision: MatmulPrecision,
) -> Result<()> {
    if a.len() != h * m * d
        || va.len() != h * m * d
        || b.len() != h * n * d
        || vb.len() != h * n * d
        || out.len() != h * (m + n) * d
    {
        return Err(crate::DiffusionError::Shape {
            what: "cross-attention buffers",
            expected: "a and va h·m·d values, b and vb h·n·d, out h·(m + n)·d",
            got: vec![a.len(), b.len(), va.len(), vb.len(), out.len()],
        });
    }
    if h == 0 || d == 0 {
        return Ok(());
    }
    if m == 0 || n == 0 {
        // No keys on one side: no message on the other (as `attend_heads`).
        out.fill(0.0);
        return Ok(());
    }
    if precision.uses_tiles() {
        return crate::tiles::cross_attend_heads((a, b), (va, vb), out, (h, m, n, d));
    }
    let rows = (HEAD_BLOCK / n).clamp(1, m);
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
        dst_b.fill(0.0);
        let columns = F32Columns {
            rows: F32Products::new(bh, vbh, n, d),
            out: dst_b,
        };
        cross_head(columns, (ah, vah), dst_a, (m, n, d), rows)
    })
}

/// [`cross_attend_heads`] on tensors: `a` `(h, m, d)`, `b` `(h, n, d)` (already scaled), `va`
/// `(h, m, d)`, `vb` `(h, n, d)`, F32 on the CPU; returns `(out_a, out_b)`.
///
/// # Errors
/// Other dtypes or devices, shapes that do not agree, tensor errors.
pub fn cross_attention_heads(
    a: &Tensor,
    b: &Tensor,
    va: &Tensor,
    vb: &Tensor,
) -> Result<(Tensor, Tensor)> {
    cross_attention_heads_with(a, b, va, vb, MatmulPrecision::Highest)
}

/// [`cross_attention_heads`] with the products at `precision`.
///
/// # Errors
/// As [`cross_attention_heads`].
pub fn cross_attention_heads_with(
    a: &Tensor,
    b: &Tensor,
    va: &Tensor,
    vb: &Tensor,
    precision: MatmulPrecision,
) -> Result<(Tensor, Tensor)> {
    let (h, m, d) = a.dims3()?;
    let (hb, n, db) = b.dims3()?;
    if (hb, db) != (h, d) || va.dims3()? != (h, m, d) || vb.dims3()? != (h, n, d) {
        return Err(crate::DiffusionError::Shape {
            what: "cross-attention b, va and vb",
            expected: "(h, n, d), (h, m, d), (h, n, d) with a's h, m and d",
            got: [b.dims(), va.dims(), vb.dims()].concat(),
        });
    }
    // The inputs are copied to the host (four (h, n, d) buffers: a small part of the work).
    let host = |t: &Tensor| -> Result<Vec<f32>> {
        if t.dtype() != DType::F32 || !t.device().is_cpu() {
            return Err(crate::DiffusionError::Invalid(
                "cross_attention_heads takes F32 tensors on the CPU",
            ));
        }
        Ok(t.flatten_all()?.to_vec1::<f32>()?)
    };
    let mut out = vec![0f32; h * (m + n) * d];
    cross_attend_heads_with(
        (&host(a)?, &host(b)?),
        (&host(va)?, &host(vb)?),
        &mut out,
        (h, m, n, d),
        precision,
    )?;
    let out = Tensor::from_vec(out, (h, m + n, d), a.device())?;
    Ok((out.narrow(1, 0, m)?, out.narrow(1, m, n)?))
}

#[cfg(test)]
mod tests {
    use candle_core::{Device, Var};

    use super::*;

    /// Against candle's composed attention in F64, for the ViT's and the denoiser's shapes
    /// (and a single image, a single token): F32 rounding of `D`- and `N`-long sums only.
    #[test]
    fn matches_the_composed_attention() -> anyhow::Result<()> {
        for (b, n, heads, d) in [
            (1, 1, 2, 3),
            (1, 2, 1, 2),
            (1, 20, 4, 128),
            (2, 17, 6, 64),
            (3usize, 197usize, 6usize, 64usize),
        ] {
            let qkv = Tensor::randn(0f32, 1.0, (b, n, 3 * heads * d), &Device::Cpu)?;
            let scale = (d as f64).powf(-0.5);
            let ours = self_attention(&qkv, heads, scale)?;
            let truth = attention_candle(&qkv.to_dtype(DType::F64)?, heads, scale)?;
            assert_eq!(ours.dims(), &[b, n, heads * d]);
            let err = (ours.to_dtype(DType::F64)? - truth)?
                .abs()?
                .flatten_all()?
                .max(0)?
                .to_scalar::<f64>()?;
            assert!(err < 2e-5, "{b}×{n}, {heads} heads of {d}: {err:e}");
        }
        Ok(())
    }

    /// Normal draws of `shape` with standard deviation `std` from `seed` (SplitMix64 and
    /// Box–Muller): the same inputs on every run, unlike `Tensor::randn`'s unseeded ones.
    fn seeded_normal(shape: (usize, usize, usize), std: f32, seed: u64) -> Result<Tensor> {
        let mut state = seed;
        let mut uniform = || {
            state = state.wrapping_add(0x9E37_79B9_7F4A_7C15);
            let mut z = state;
            z = (z ^ (z >> 30)).wrapping_mul(0xBF58_476D_1CE4_E5B9);
            z = (z ^ (z >> 27)).wrapping_mul(0x94D0_49BB_1331_11EB);
            z ^= z >> 31;
            ((z >> 11) as f64 + 0.5) / (1u64 << 53) as f64
        };
        let count = shape.0 * shape.1 * shape.2;
        let values: Vec<f32> = (0..count)
            .map(|_| {
                let (u, v) = (uniform(), uniform());
                ((-2.0 * u.ln()).sqrt() * (std::f64::consts::TAU * v).cos()) as f32 * std
            })
            .collect();
        Ok(Tensor::from_vec(values, shape, &Device::Cpu)?)
    }

    /// Both directions of one shared similarity against two separate attentions in F64, for
    /// shapes with several row blocks (2048 keys: 128 rows a block), scores spread wide enough
    /// that later blocks raise the columns' maxima, a single row and a single column. The
    /// inputs are seeded: with `Tensor::randn`'s the largest error of the first shape was
    /// random and went past the bound once in a CI run (3.05e-5; F32 sums of 600 to 2048
    /// terms of scores whose spread is 8).
    #[test]
    fn cross_attention_matches_two_separate_attentions() -> anyhow::Result<()> {
        for (case, (h, m, n, d, spread)) in [
            (4, 600, 2048, 64, 2.0),
            (2, 5, 1, 8, 0.5),
            (1, 1, 7, 3, 0.5),
            (3, 300, 40, 16, 6.0),
        ]
        .into_iter()
        .enumerate()
        {
            let seed = 4 * case as u64;
            let a = seeded_normal((h, m, d), spread, seed)?;
            let b = seeded_normal((h, n, d), 0.5, seed + 1)?;
            let va = seeded_normal((h, m, d), 1.0, seed + 2)?;
            let vb = seeded_normal((h, n, d), 1.0, seed + 3)?;
            let (oa, ob) = cross_attention_heads(&a, &b, &va, &vb)?;
            let f64_ = |t: &Tensor| t.to_dtype(DType::F64);
            let s = f64_(&a)?.matmul(&f64_(&b)?.t()?)?;
            let ta = crate::norm::softmax_last_dim_candle(&s)?.matmul(&f64_(&vb)?)?;
            let tb =
                crate::norm::softmax_last_dim_candle(&s.t()?.contiguous()?)?.matmul(&f64_(&va)?)?;
            for (ours, truth, what) in [(oa, ta, "a"), (ob, tb, "b")] {
                let err = (ours.to_dtype(DType::F64)? - truth)?
                    .abs()?
                    .flatten_all()?
                    .max(0)?
                    .to_scalar::<f64>()?;
                assert!(err < 2e-5, "{h}×{m}×{n}×{d}, side {what}: {err:e}");
            }
        }
        let x = Tensor::zeros((2, 3, 4), DType::F32, &Device::Cpu)?;
        let y = Tensor::zeros((2, 5, 4), DType::F32, &Device::Cpu)?;
        assert!(cross_attention_heads(&x, &y, &y, &y).is_err());
        Ok(())
    }

    /// At `MatmulPrecision::High` (AMX tiles where the CPU has them) both attention kernels stay
    /// within the F32 kernels' tolerance scaled by the ratio of the unit roundoffs (2⁻¹⁶ /
    /// 2⁻²⁴ = 256), against candle's composed attention in F64, at shapes with partial tile
    /// blocks; where tiles run, the results are not the F32 ones (the tile path was taken).
    #[test]
    fn tiles_keep_attention_within_their_precision() -> anyhow::Result<()> {
        let tol = 256.0 * 2e-5;
        for (h, m, n, d, spread) in [
            (4, 300, 2048, 64, 2.0),
            (2, 5, 1, 8, 0.5),
            (3, 70, 45, 16, 6.0),
        ] {
            let a = Tensor::randn(0f32, spread, (h, m, d), &Device::Cpu)?;
            let b = Tensor::randn(0f32, 0.5, (h, n, d), &Device::Cpu)?;
            let va = Tensor::randn(0f32, 1.0, (h, m, d), &Device::Cpu)?;
            let vb = Tensor::randn(0f32, 1.0, (h, n, d), &Device::Cpu)?;
            let f64_ = |t: &Tensor| t.to_dtype(DType::F64);
            let s = f64_(&a)?.matmul(&f64_(&b)?.t()?)?;
            let ta = crate::norm::softmax_last_dim_candle(&s)?.matmul(&f64_(&vb)?)?;
            let tb =
                crate::norm::softmax_last_dim_candle(&s.t()?.contiguous()?)?.matmul(&f64_(&va)?)?;
            let self_high = attention_heads_with(&a, &b, &vb, MatmulPrecision::High)?;
            let self_f32 = attention_heads(&a, &b, &vb)?;
            let (oa, ob) = cross_attention_heads_with(&a, &b, &va, &vb, MatmulPrecision::High)?;
            for (ours, truth, what) in [
                (self_high.clone(), ta.clone(), "self"),
                (oa, ta, "cross a"),
                (ob, tb, "cross b"),
            ] {
                let err = (ours.to_dtype(DType::F64)? - truth)?
                    .abs()?
                    .flatten_all()?
                    .max(0)?
                    .to_scalar::<f64>()?;
                assert!(err < tol, "{h}×{m}×{n}×{d}, {what}: {err:e}");
            }
            let differ = (self_high - self_f32)?
                .abs()?
                .flatten_all()?
                .max(0)?
                .to_scalar::<f32>()?
                > 0.0;
            assert_eq!(
                differ,
                MatmulPrecision::High.uses_tiles(),
                "{h}×{m}×{n}×{d}"
            );
        }
        Ok(())
    }

    /// The per-head kernel against candle's composed `softmax(Q Kᵀ) V` in F64, for shapes
    /// with several row blocks (2048 keys: 128 rows a block), a single key and a single query.
    #[test]
    fn attend_heads_matches_the_composed_attention() -> anyhow::Result<()> {
        for (h, m, n, d) in [
            (4, 300, 2048, 64),
            (2, 5, 1, 8),
            (1, 1, 7, 3),
            (3, 33, 40, 16),
        ] {
            let q = Tensor::randn(0f32, 0.5, (h, m, d), &Device::Cpu)?;
            let k = Tensor::randn(0f32, 0.5, (h, n, d), &Device::Cpu)?;
            let v = Tensor::randn(0f32, 1.0, (h, n, d), &Device::Cpu)?;
            let flat = |t: &Tensor| t.flatten_all()?.to_vec1::<f32>();
            let mut out = vec![f32::NAN; h * m * d];
            attend_heads(&flat(&q)?, &flat(&k)?, &flat(&v)?, &mut out, (h, m, n, d))?;
            let f64_ = |t: &Tensor| t.to_dtype(DType::F64);
            let s = f64_(&q)?.matmul(&f64_(&k)?.t()?)?;
            let truth = crate::norm::softmax_last_dim_candle(&s)?.matmul(&f64_(&v)?)?;
            let truth = truth.flatten_all()?.to_vec1::<f64>()?;
            let err = out
                .iter()
                .zip(&truth)
                .map(|(a, b)| (f64::from(*a) - b).abs())
                .fold(0f64, f64::max);
            assert!(err < 2e-5, "{h} heads, {m} × {n} of {d}: {err:e}");
        }
        // The tensor form reads the same buffers (and transposed, non-contiguous inputs).
        let q = Tensor::randn(0f32, 0.5, (3, 2, 9), &Device::Cpu)?;
        let k = Tensor::randn(0f32, 0.5, (3, 16, 9), &Device::Cpu)?;
        let v = Tensor::randn(0f32, 1.0, (3, 9, 16), &Device::Cpu)?.transpose(1, 2)?;
        let ours = attention_heads(&q, &k, &v)?;
        let truth = crate::norm::softmax_last_dim_candle(&q.matmul(&k.t()?)?)?.matmul(&v)?;
        let err = (ours - truth)?
            .abs()?
            .flatten_all()?
            .max(0)?
            .to_scalar::<f32>()?;
        assert!(err < 1e-5, "tensor form: {err:e}");
        assert!(attention_heads(&q, &k, &k.narrow(1, 0, 15)?).is_err());
        let mut out = vec![0f32; 4];
        assert!(attend_heads(&[0.0; 4], &[0.0; 3], &[0.0; 4], &mut out, (1, 2, 2, 2)).is_err());
        Ok(())
    }

    /// A width that does not split into three blocks of whole heads is an error.
    #[test]
    fn a_width_without_whole_heads_is_an_error() -> anyhow::Result<()> {
        let qkv = Tensor::zeros((1, 4, 20), DType::F32, &Device::Cpu)?;
        assert!(self_attention(&qkv, 3, 1.0).is_err());
        Ok(())
    }

    /// Tracked inputs (training) take the differentiable path.
    #[test]
    fn tracked_inputs_keep_gradients() -> anyhow::Result<()> {
        let qkv = Var::randn(0f32, 1.0, (1, 5, 12), &Device::Cpu)?;
        let loss = self_attention(qkv.as_tensor(), 2, 0.5)?.sqr()?.sum_all()?;
        let grads = loss.backward()?;
        assert!(grads.get(qkv.as_tensor()).is_some());
        Ok(())
    }
}
