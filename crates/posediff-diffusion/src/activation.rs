//! The ViT's exact (erf) GELU, `x · (1 + erf(x/√2)) / 2`, as PyTorch's `nn.GELU()`.
//!
//! candle's `gelu_erf` evaluates erf element by element in f64 (about 20× PyTorch's cost on
//! this CPU, BUILD_NOTES.md). For F32 on the CPU without gradients this module evaluates erf
//! with the rational approximation Eigen and XLA use for float (`x·P(x²)/Q(x²)` inside
//! `|x| < 3.8325`, ±1 beyond; a few float ulps), branch-free so the loop vectorises. F64 (the
//! parity tests), other devices and tracked tensors keep candle's op.

use candle_core::{DType, Tensor};

use crate::error::Result;

/// Numerator coefficients of `erf(x) ≈ x·P(x²)/Q(x²)`, highest power first (given in
/// double precision, rounded to float).
const ALPHA: [f32; 7] = [
    -2.72614225801306e-10_f64 as f32,
    2.77068142495902e-08_f64 as f32,
    -2.10102402082508e-06_f64 as f32,
    -5.69250639462346e-05_f64 as f32,
    -7.34990630326855e-04_f64 as f32,
    -2.95459980854025e-03_f64 as f32,
    -1.60960333262415e-02_f64 as f32,
];

/// Denominator coefficients, highest power first.
const BETA: [f32; 5] = [
    -1.45660718464996e-05_f64 as f32,
    -2.13374055278905e-04_f64 as f32,
    -1.68282697438203e-03_f64 as f32,
    -7.37332916720468e-03_f64 as f32,
    -1.42647390514189e-02_f64 as f32,
];

/// Beyond `|z|` = 3.8325 erf rounds to ±1 in float; the rational form is evaluated inside.
const EDGE: f32 = 3.832_507;

/// `erf(z)` for f32 in a few ulps, without branches (the select compiles to a blend).
#[inline(always)]
fn erf_f32(z: f32) -> f32 {
    let x = z.clamp(-EDGE, EDGE);
    let x2 = x * x;
    let mut p = ALPHA[0];
    for a in &ALPHA[1..] {
        p = p * x2 + a;
    }
    let mut q = BETA[0];
    for b in &BETA[1..] {
        q = q * x2 + b;
    }
    let inside = (x * p / q).clamp(-1.0, 1.0);
    if z.abs() >= EDGE {
        1.0f32.copysign(z)
    } else {
        inside
    }
}

/// `x · (1 + erf(x/√2)) / 2`.
#[inline(always)]
fn gelu_f32(x: f32) -> f32 {
    0.5 * x * (1.0 + erf_f32(x * std::f32::consts::FRAC_1_SQRT_2))
}

/// GELU of `values` in place, compiled for the best instruction set this CPU has (AVX-512 or
/// AVX2 + FMA where present) by `pulp`'s safe runtime dispatch, the portable build otherwise.
fn gelu_slice(values: &mut [f32]) {
    pulp::Arch::new().dispatch(Blocks(values));
}

/// The values for pulp's dispatch: `with_simd` is inlined into a function compiled for the
/// CPU's features (a plain closure passed to `dispatch` is not, and runs the baseline code).
struct Blocks<'a>(&'a mut [f32]);

impl pulp::WithSimd for Blocks<'_> {
    type Output = ();

    #[inline(always)]
    fn with_simd<S: pulp::Simd>(self, _simd: S) {
        gelu_blocks(self.0);
    }
}

/// GELU of `values` in place, eight lanes at a time (fixed-size blocks the compiler turns into
/// SIMD), the remainder one by one. Inlined into [`gelu_slice`]'s dispatched code.
#[inline(always)]
fn gelu_blocks(values: &mut [f32]) {
    const LANES: usize = 8;
    let mut blocks = values.chunks_exact_mut(LANES);
    for b in &mut blocks {
        let mut block = [0f32; LANES];
        block.copy_from_slice(b);
        for v in &mut block {
            *v = gelu_f32(*v);
        }
        b.copy_from_slice(&block);
    }
    for v in blocks.into_remainder() {
        *v = gelu_f32(*v);
    }
}

/// [`gelu_slice`] on the threads candle uses (one below [`PARALLEL_MIN`] elements).
fn gelu_parallel(values: &mut [f32]) {
    split_over_threads(values, 1, PARALLEL_MIN, gelu_slice);
}

/// `f` on parts of `values` (whole multiples of `unit` elements), one per thread candle uses;
/// on the calling thread alone below `min_len` elements or with fewer than two units.
pub(crate) fn split_over_threads(
    values: &mut [f32],
    unit: usize,
    min_len: usize,
    f: impl Fn(&mut [f32]) + Sync,
) {
    let threads = crate::threads();
    let unit = unit.max(1);
    let units = values.len() / unit;
    if threads == 1 || values.len() < min_len || units < 2 {
        f(values);
        return;
    }
    let chunk = units.div_ceil(threads) * unit;
    let f = &f;
    std::thread::scope(|s| {
        for part in values.chunks_mut(chunk) {
            s.spawn(move || f(part));
        }
    });
}

/// Elements below which one thread does the whole tensor.
const PARALLEL_MIN: usize = 1 << 16;

/// The erf GELU as a candle op ([`crate::SliceOp`]), copying or in place.
const GELU_ERF_F32: crate::SliceOp = crate::SliceOp {
    name: "gelu-erf-f32",
    kernel: |values, _| gelu_parallel(values),
};

/// The exact GELU of a freshly computed `x`, overwriting it where the fast path applies (F32,
/// CPU, contiguous, untracked), so no output is allocated: for intermediate results nothing
/// else holds, such as a linear layer's output. Otherwise as [`gelu_erf`].
///
/// # Errors
/// Tensor errors.
pub fn gelu_erf_owned(x: Tensor) -> Result<Tensor> {
    if x.dtype() == DType::F32 && x.device().is_cpu() && !x.track_op() && x.is_contiguous() {
        x.inplace_op1(&GELU_ERF_F32)?;
        return Ok(x);
    }
    gelu_erf(&x)
}

/// The exact GELU of `x` (see the module documentation for which path runs).
///
/// # Errors
/// Tensor errors.
pub fn gelu_erf(x: &Tensor) -> Result<Tensor> {
    if x.dtype() == DType::F32 && x.device().is_cpu() && !x.track_op() {
        return Ok(x.contiguous()?.apply_op1_no_bwd(&GELU_ERF_F32)?);
    }
    Ok(x.gelu_erf()?)
}

#[cfg(test)]
mod tests {
    use candle_core::Device;

    use super::*;

    /// What float evaluation of `x·(1 + erf(x/√2))/2` allows: erf within 4e-7 of the truth
    /// (about three float ulps of 1; PyTorch's own vectorised float erf, Abramowitz–Stegun
    /// 7.1.26, is within 1.5e-7), times `|x|/2`, plus the rounding of the result. For negative
    /// `x` the `1 + erf` cancels, so this error is absolute, not relative, in PyTorch too.
    fn tolerance(x: f32, exact: f32) -> f32 {
        2e-7 * x.abs().max(1.0) + 4.0 * f32::EPSILON * exact.abs()
    }

    #[test]
    fn the_fast_path_matches_candles_gelu_erf() -> Result<()> {
        // A dense grid over the range the ViT sees and far beyond, both signs, and the tails
        // where erf saturates.
        let xs: Vec<f32> = (-40_000..=40_000).map(|i| i as f32 * 2.5e-4).collect();
        let t = Tensor::from_vec(xs.clone(), xs.len(), &Device::Cpu)?;
        let fast: Vec<f32> = gelu_erf(&t)?.to_vec1()?;
        let plain: Vec<f32> = t.gelu_erf()?.to_vec1()?;
        let mut worst = 0.0f32;
        for ((x, a), b) in xs.iter().zip(&fast).zip(&plain) {
            let err = (a - b).abs();
            let bound = tolerance(*x, *b);
            assert!(err <= bound, "x = {x}: fast {a}, candle {b}");
            worst = worst.max(err);
        }
        assert!(worst > 0.0, "the fast path did not run");
        Ok(())
    }

    #[test]
    fn the_in_place_path_equals_the_allocating_one() -> Result<()> {
        let x = Tensor::randn(0f32, 2f32, (3, 197, 1536), &Device::Cpu)?;
        let expected: Vec<f32> = gelu_erf(&x)?.flatten_all()?.to_vec1()?;
        let fresh = (&x * 1.0)?;
        let got: Vec<f32> = gelu_erf_owned(fresh)?.flatten_all()?.to_vec1()?;
        assert_eq!(got, expected);
        // F64 takes candle's op.
        let d = x.to_dtype(DType::F64)?;
        assert_eq!(
            gelu_erf_owned(d.clone())?.flatten_all()?.to_vec1::<f64>()?,
            d.gelu_erf()?.flatten_all()?.to_vec1::<f64>()?
        );
        Ok(())
    }

    #[test]
    fn other_dtypes_and_strided_inputs_take_a_correct_path() -> Result<()> {
        let t = Tensor::arange(-20f64, 20.0, &Device::Cpu)?.affine(0.25, 0.0)?;
        assert_eq!(
            gelu_erf(&t)?.to_vec1::<f64>()?,
            t.gelu_erf()?.to_vec1::<f64>()?
        );
        // A transposed (non-contiguous) F32 tensor.
        let m = Tensor::arange(-12f32, 12.0, &Device::Cpu)?
            .reshape((4, 6))?
            .t()?;
        let fast: Vec<f32> = gelu_erf(&m)?.flatten_all()?.to_vec1()?;
        let plain: Vec<f32> = m.gelu_erf()?.flatten_all()?.to_vec1()?;
        let xs: Vec<f32> = m.flatten_all()?.to_vec1()?;
        for ((x, a), b) in xs.iter().zip(&fast).zip(&plain) {
            assert!((a - b).abs() <= tolerance(*x, *b), "x = {x}: {a} vs {b}");
        }
        Ok(())
    }
}
