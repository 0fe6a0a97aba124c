//! Softmax over the last dimension for F32 on the CPU, vectorised.
//!
//! candle's fused softmax calls the scalar `expf` per element; attention over thousands of
//! tokens (LightGlue's 2048 × 2048 per head, the ViT's 197 × 197 per head and image) spends most
//! of its time there. This kernel evaluates `exp` with Cephes' single-precision polynomial
//! after the range reduction `x = n·ln 2 + r` (`|r| ≤ ln 2 / 2`; relative error about
//! 2·10⁻⁷, below two float ulps), written branch-free so that the loop vectorises, compiled for
//! AVX-512 or AVX2+FMA where the CPU has it (pulp's safe runtime dispatch). Rows are split over candle's
//! threads. Other dtypes, devices and tracked tensors keep candle's op.

use candle_core::{DType, Tensor};

use crate::error::Result;

const LOG2E: f32 = std::f32::consts::LOG2_E;
/// ln 2 split in two for an exact `n·ln 2` (Cephes).
const LN2_HI: f32 = 0.693_359_4;
const LN2_LO: f32 = -2.121_944_4e-4;
/// Cephes `expf` polynomial, highest power first.
const P: [f32; 6] = [
    1.987_569_1e-4,
    1.398_2e-3,
    8.333_452e-3,
    4.166_579_6e-2,
    1.666_666_5e-1,
    0.5,
];
/// Below this `exp` underflows to the smallest normal range; inputs are clamped to it.
const MIN_X: f32 = -87.336_55;
const MAX_X: f32 = 88.376_26;

/// `exp(x)` to about two ulps (inputs clamped to the normal range).
#[inline(always)]
pub fn exp_f32(x: f32) -> f32 {
    let x = x.clamp(MIN_X, MAX_X);
    // Round to nearest by the 1.5·2²³ shift (no call to rintf: the loop stays vectorised on
    // every x86-64; |x·log2 e| < 128).
    let n = (x * LOG2E + ROUNDER) - ROUNDER;
    let r = x - n * LN2_HI - n * LN2_LO;
    let mut p = P[0];
    for c in &P[1..] {
        p = p * r + c;
    }
    let y = p * r * r + r + 1.0;
    // 2ⁿ by the exponent bits, n ∈ [−126, 127] after the clamp: adding 1.5·2²³ + 127 leaves
    // n + 127 in the low mantissa bits (no float-to-int conversion, so the loop vectorises).
    let biased = (n + (ROUNDER + 127.0)).to_bits();
    y * f32::from_bits(biased << 23)
}

/// [`exp_f32`] on a vector, with fused multiply-adds: the same Cephes reduction and
/// polynomial, each `a·b + c` rounded once instead of twice, so within about two ulps of
/// [`exp_f32`] but not bit-identical to it. For [`crate::tiles`] only, whose products keep
/// about 16 bits of each weight (`MatmulPrecision::High`); the F32 kernels keep [`exp_f32`].
/// Written on pulp's vector type because the compiler does not vectorise the scalar form's
/// sum and splitting as well as one register per operation.
#[inline(always)]
pub(crate) fn exp_fused<S: pulp::Simd>(simd: S, x: S::f32s) -> S::f32s {
    let x = simd.min_f32s(
        simd.max_f32s(x, simd.splat_f32s(MIN_X)),
        simd.splat_f32s(MAX_X),
    );
    let rounder = simd.splat_f32s(ROUNDER);
    let n = simd.sub_f32s(
        simd.mul_add_f32s(x, simd.splat_f32s(LOG2E), rounder),
        rounder,
    );
    let r = simd.mul_add_f32s(n, simd.splat_f32s(-LN2_HI), x);
    let r = simd.mul_add_f32s(n, simd.splat_f32s(-LN2_LO), r);
    let mut p = simd.splat_f32s(P[0]);
    for &c in &P[1..] {
        p = simd.mul_add_f32s(p, r, simd.splat_f32s(c));
    }
    let y = simd.add_f32s(
        simd.mul_add_f32s(p, simd.mul_f32s(r, r), r),
        simd.splat_f32s(1.0),
    );
    // 2ⁿ by the exponent bits, as in `exp_f32`.
    let biased = simd.add_f32s(n, simd.splat_f32s(ROUNDER + 127.0));
    let scale = simd.wrapping_dyn_shl_u32s(simd.transmute_u32s_f32s(biased), simd.splat_u32s(23));
    simd.mul_f32s(y, simd.transmute_f32s_u32s(scale))
}

/// The exponent below which a term of a softmax row of `len` terms is set to zero: its
/// normalised value `exp(d) / sum` (the sum is at most `len`) would be below the smallest
/// normal float, `exp(MIN_X)`. One unit of margin covers `exp`'s rounding; a zeroed term is
/// below `e · len · exp(MIN_X)` (7e-35 for 2048 terms), far under an ulp of any row's
/// largest term (1).
#[inline(always)]
pub(crate) fn flush_below(len: usize) -> f32 {
    MIN_X + (len.max(1) as f32).ln() + 1.0
}

/// 1.5·2²³: adding it rounds a float of magnitude below 2²² to an integer.
const ROUNDER: f32 = 12_582_912.0;

/// Lanes of the manual reductions (one AVX register of f32).
const LANES: usize = 8;

/// Softmax of every `row`-long row of `values`, in place: [`exp_rows`], then each row scaled
/// by its `1 / Σ`.
#[inline(always)]
fn softmax_rows(values: &mut [f32], row: usize) {
    for r in values.chunks_exact_mut(row) {
        let mut inv = [0f32];
        exp_rows(r, row, &mut inv);
        for v in r.iter_mut() {
            *v *= inv[0];
        }
    }
}

/// The unnormalised softmax of every `row`-long row of `values`, in place: `exp(x − max)`, with
/// each row's `1 / Σ` written to `inv_sums`. The maximum and the sum run in [`LANES`] partial
/// lanes (a sequential float reduction would not vectorise); `exp` is a pure map. A term whose
/// normalised value would be subnormal is zero ([`flush_below`]): subnormal floats take
/// microcode assists on Intel cores in the product with the values, and without this a fifth
/// of LightGlue's attention weights were subnormal. The exponentials and the sum share one
/// pass; attention scales its `d`-wide output rows by `1 / Σ` instead of the `n`-wide
/// weights.
#[inline(always)]
fn exp_rows(values: &mut [f32], row: usize, inv_sums: &mut [f32]) {
    for (r, inv) in values.chunks_exact_mut(row).zip(inv_sums) {
        let max = row_max(r);
        let cut = flush_below(r.len());
        let mut sums = [0f32; LANES];
        let mut blocks = r.chunks_exact_mut(LANES);
        for b in &mut blocks {
            for (s, v) in sums.iter_mut().zip(b.iter_mut()) {
                let d = *v - max;
                let e = exp_f32(d);
                *v = if d < cut { 0.0 } else { e };
                *s += *v;
            }
        }
        let mut sum: f32 = sums.iter().sum();
        for v in blocks.into_remainder() {
            let d = *v - max;
            let e = exp_f32(d);
            *v = if d < cut { 0.0 } else { e };
            sum += *v;
        }
        *inv = 1.0 / sum;
    }
}

struct ExpRows<'a> {
    values: &'a mut [f32],
    row: usize,
    inv_sums: &'a mut [f32],
}

impl pulp::WithSimd for ExpRows<'_> {
    type Output = ();

    #[inline(always)]
    fn with_simd<S: pulp::Simd>(self, _simd: S) {
        exp_rows(self.values, self.row, self.inv_sums);
    }
}

/// [`exp_rows`] on the calling thread, compiled for the CPU's features.
pub(crate) fn exp_rows_dispatch(values: &mut [f32], row: usize, inv_sums: &mut [f32]) {
    pulp::Arch::new().dispatch(ExpRows {
        values,
        row,
        inv_sums,
    });
}

/// The largest value of a row (NaNs ignored), reduced in [`MAX_LANES`] lanes (vectorised where
/// the caller is compiled for the CPU's features). The lanes are a local array indexed by
/// constants only, and the comparison is `>` rather than `f32::max` (whose NaN rule costs a
/// compare and a blend per vector): written so, the lanes stay in one register instead of a
/// stack slot stored and reloaded on every block.
#[inline(always)]
pub(crate) fn row_max(r: &[f32]) -> f32 {
    let larger = |m: f32, v: f32| if v > m { v } else { m };
    let mut lanes = [f32::NEG_INFINITY; MAX_LANES];
    let mut blocks = r.chunks_exact(MAX_LANES);
    for b in &mut blocks {
        for i in 0..MAX_LANES {
            lanes[i] = larger(lanes[i], b[i]);
        }
    }
    let mut max = f32::NEG_INFINITY;
    for &v in blocks.remainder() {
        max = larger(max, v);
    }
    for lane in lanes {
        max = larger(max, lane);
    }
    max
}

/// Lanes of [`row_max`]: one AVX-512 register of f32 (two AVX registers).
const MAX_LANES: usize = 16;

/// `weights = exp(scores − offsets[column])` for row-major `row`-wide blocks, terms below `cut`
/// zero, each column's sum added to `sums` (cross-attention's column direction).
#[inline(always)]
fn exp_offsets(
    scores: &[f32],
    weights: &mut [f32],
    row: usize,
    offsets: &[f32],
    cut: f32,
    sums: &mut [f32],
) {
    for (r, w) in scores.chunks_exact(row).zip(weights.chunks_exact_mut(row)) {
        for (((w, &x), &o), s) in w.iter_mut().zip(r).zip(offsets).zip(sums.iter_mut()) {
            let d = x - o;
            let e = exp_f32(d);
            *w = if d < cut { 0.0 } else { e };
            *s += *w;
        }
    }
}

struct ExpOffsets<'a> {
    scores: &'a [f32],
    weights: &'a mut [f32],
    row: usize,
    offsets: &'a [f32],
    cut: f32,
    sums: &'a mut [f32],
}

impl pulp::WithSimd for ExpOffsets<'_> {
    type Output = ();

    #[inline(always)]
    fn with_simd<S: pulp::Simd>(self, _simd: S) {
        exp_offsets(
            self.scores,
            self.weights,
            self.row,
            self.offsets,
            self.cut,
            self.sums,
        );
    }
}

/// [`exp_offsets`] on the calling thread, compiled for the CPU's features.
pub(crate) fn exp_offsets_dispatch(
    scores: &[f32],
    weights: &mut [f32],
    row: usize,
    offsets: &[f32],
    cut: f32,
    sums: &mut [f32],
) {
    pulp::Arch::new().dispatch(ExpOffsets {
        scores,
        weights,
        row,
        offsets,
        cut,
        sums,
    });
}

/// The rows for pulp's dispatch: `with_simd` is inlined into a function compiled for the CPU's
/// features (a plain closure is not, and would run the baseline code).
struct Rows<'a> {
    values: &'a mut [f32],
    row: usize,
}

impl pulp::WithSimd for Rows<'_> {
    type Output = ();

    #[inline(always)]
    fn with_simd<S: pulp::Simd>(self, _simd: S) {
        softmax_rows(self.values, self.row);
    }
}

/// Softmax of every `row`-long row of `values` on the calling thread (the fused attention's
/// rows).
pub(crate) fn softmax_rows_dispatch(values: &mut [f32], row: usize) {
    pulp::Arch::new().dispatch(Rows { values, row });
}

/// Over candle's threads, whole rows per thread.
fn softmax_parallel(values: &mut [f32], row: usize) {
    crate::activation::split_over_threads(values, row, PARALLEL_MIN, |part| {
        softmax_rows_dispatch(part, row);
    });
}

/// Elements below which one thread does the whole tensor.
const PARALLEL_MIN: usize = 1 << 15;

/// The softmax over the last dimension as a candle op ([`crate::SliceOp`]), copying or in
/// place.
const SOFTMAX_F32: crate::SliceOp = crate::SliceOp {
    name: "softmax-last-dim-f32",
    kernel: softmax_parallel,
};

fn fast_path(x: &Tensor) -> bool {
    x.dtype() == DType::F32 && x.device().is_cpu() && !x.track_op() && x.rank() > 0
}

/// Softmax over the last dimension (the vectorised kernel where it applies).
///
/// # Errors
/// Tensor errors.
pub fn softmax_last_dim(x: &Tensor) -> Result<Tensor> {
    if fast_path(x) {
        return Ok(x.contiguous()?.apply_op1_no_bwd(&SOFTMAX_F32)?);
    }
    softmax_last_dim_candle(x)
}

/// candle's softmax: its fused kernel, or the composed, differentiable one when gradients are
/// tracked.
///
/// # Errors
/// Tensor errors.
pub fn softmax_last_dim_candle(x: &Tensor) -> Result<Tensor> {
    Ok(if x.track_op() {
        candle_nn::ops::softmax(x, candle_core::D::Minus1)?
    } else {
        candle_nn::ops::softmax_last_dim(x)?
    })
}

/// As [`softmax_last_dim`], in place when `x` is a contiguous F32 CPU tensor that nothing
/// else holds (e.g. a product just computed).
///
/// # Errors
/// Tensor errors.
pub fn softmax_last_dim_owned(x: Tensor) -> Result<Tensor> {
    if fast_path(&x) && x.is_contiguous() {
        x.inplace_op1(&SOFTMAX_F32)?;
        return Ok(x);
    }
    softmax_last_dim(&x)
}

#[cfg(test)]
mod tests {
    use candle_core::Device;

    use super::*;

    #[test]
    fn exp_is_within_two_ulps_of_libm() {
        let mut worst = 0f64;
        let mut x = -87.0f32;
        while x < 88.0 {
            let (a, e) = (f64::from(exp_f32(x)), f64::from(x.exp()));
            worst = worst.max((a - e).abs() / e);
            x += 0.000_37;
        }
        assert!(worst < 2.5e-7, "worst relative error {worst:e}");
        assert_eq!(exp_f32(0.0), 1.0);
        assert!(exp_f32(-1000.0) >= 0.0 && exp_f32(-1000.0) < 1e-37);
    }

    /// [`exp_fused`] on every vector width pulp dispatches to here, against f64 over the
    /// whole clamped range, the same bound as [`exp_f32`].
    #[test]
    fn fused_exp_is_within_two_ulps() {
        struct Probe<'a>(&'a [f32], &'a mut [f32]);
        impl pulp::WithSimd for Probe<'_> {
            type Output = ();
            #[inline(always)]
            fn with_simd<S: pulp::Simd>(self, simd: S) {
                let (xs, _) = S::as_simd_f32s(self.0);
                let (ys, _) = S::as_mut_simd_f32s(self.1);
                for (&x, y) in xs.iter().zip(ys.iter_mut()) {
                    *y = exp_fused(simd, x);
                }
            }
        }
        let xs: Vec<f32> = (0..473_000).map(|i| -87.0 + i as f32 * 0.000_37).collect();
        let mut ys = vec![f32::NAN; xs.len()];
        pulp::Arch::new().dispatch(Probe(&xs, &mut ys));
        // The scalar tail of `as_simd_f32s` (under one vector) is left out.
        let done = xs.len() / 16 * 16;
        let mut worst = 0f64;
        for (&x, &y) in xs.iter().zip(&ys).take(done) {
            let e = f64::from(x).exp();
            worst = worst.max((f64::from(y) - e).abs() / e);
        }
        assert!(worst < 2.5e-7, "worst relative error {worst:e}");
        let mut edge = [0f32; 16];
        let inputs = [
            0.0f32, -1000.0, 1000.0, -87.336_55, 88.0, -0.5, 0.5, 1.0, -1.0, 10.0, -10.0, 20.0,
            -20.0, 40.0, -40.0, -80.0,
        ];
        pulp::Arch::new().dispatch(Probe(&inputs, &mut edge));
        assert_eq!(edge[0], 1.0);
        assert!(
            edge[1] >= 0.0 && edge[1] < 1e-37,
            "exp(-1000) = {}",
            edge[1]
        );
        assert!(
            edge[2].is_finite() && edge[2] > 1e38,
            "exp(1000) = {}",
            edge[2]
        );
    }

    /// Against an f64 softmax: `exp` adds two ulps, the f32 row sum up to `√n` ulps
    /// (n ≤ 2048: 45 · 6e-8 ≈ 3e-6); candle's kernel is held to the same bound.
    #[test]
    fn matches_an_f64_softmax_as_closely_as_candles() -> anyhow::Result<()> {
        for shape in [(3usize, 5usize, 7usize), (2, 64, 2048), (1, 1, 1)] {
            let x = (Tensor::randn(0f32, 1.0, shape, &Device::Cpu)? * 10.0)?;
            let row = shape.2;
            let xs = x.flatten_all()?.to_vec1::<f32>()?;
            let truth: Vec<f64> = xs
                .chunks(row)
                .flat_map(|r| {
                    let m = r
                        .iter()
                        .fold(f64::NEG_INFINITY, |a, &b| a.max(f64::from(b)));
                    let e: Vec<f64> = r.iter().map(|&v| (f64::from(v) - m).exp()).collect();
                    let s: f64 = e.iter().sum();
                    e.into_iter().map(move |v| v / s)
                })
                .collect();
            let ours = softmax_last_dim(&x)?.flatten_all()?.to_vec1::<f32>()?;
            let owned = softmax_last_dim_owned(x.copy()?)?
                .flatten_all()?
                .to_vec1::<f32>()?;
            let theirs = candle_nn::ops::softmax_last_dim(&x)?
                .flatten_all()?
                .to_vec1::<f32>()?;
            for (((a, b), c), t) in ours.iter().zip(&theirs).zip(&owned).zip(&truth) {
                let bound = 5e-6 * t + 1e-30;
                assert!((f64::from(*a) - t).abs() <= bound, "ours {a} vs {t}");
                assert!((f64::from(*b) - t).abs() <= bound, "candle {b} vs {t}");
                assert_eq!(a, c);
            }
        }
        Ok(())
    }

    /// No weight of a row is subnormal (they slow down the product with the values on Intel
    /// cores), however wide the logits; the row still sums to one and every weight that is
    /// not flushed is the f64 softmax's within the bound above.
    #[test]
    fn no_weight_is_subnormal() -> anyhow::Result<()> {
        for row in [3usize, 64, 2048] {
            // Logits spread over 0 .. -200: a broad band of terms between exp(-87) and
            // exp(-104) that would otherwise be subnormal after normalisation.
            let xs: Vec<f32> = (0..2 * row)
                .map(|i| -200.0 * ((i * 7919) % row) as f32 / row as f32)
                .collect();
            let x = Tensor::from_vec(xs.clone(), (2, row), &Device::Cpu)?;
            for s in [
                softmax_last_dim(&x)?.flatten_all()?.to_vec1::<f32>()?,
                softmax_last_dim_owned(x.copy()?)?
                    .flatten_all()?
                    .to_vec1::<f32>()?,
            ] {
                assert!(s.iter().all(|v| !v.is_subnormal() && v.is_finite()));
                for (r, sr) in xs.chunks(row).zip(s.chunks(row)) {
                    let m = r
                        .iter()
                        .fold(f64::NEG_INFINITY, |a, &b| a.max(f64::from(b)));
                    let total: f64 = r.iter().map(|&v| (f64::from(v) - m).exp()).sum();
                    for (&v, &p) in r.iter().zip(sr) {
                        let t = (f64::from(v) - m).exp() / total;
                        assert!((f64::from(p) - t).abs() <= 5e-6 * t + 1e-34, "{p} vs {t}");
                    }
                    let sum: f32 = sr.iter().sum();
                    assert!((sum - 1.0).abs() < 1e-5);
                }
            }
        }
        Ok(())
    }

    #[test]
    fn rows_sum_to_one_with_extreme_logits() -> anyhow::Result<()> {
        let x = Tensor::from_vec(vec![1e4f32, 0.0, -1e4, 3.0, 3.0, 3.0], (2, 3), &Device::Cpu)?;
        let s = softmax_last_dim(&x)?.to_vec2::<f32>()?;
        assert_eq!(s[0][0], 1.0);
        assert!(s[0][1] < 1e-37);
        for v in &s[1] {
            assert!((v - 1.0 / 3.0).abs() < 1e-7);
        }
        Ok(())
    }
}
