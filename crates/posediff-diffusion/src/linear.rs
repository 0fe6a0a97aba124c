//! `nn.Linear` (`y = x Wᵀ + b`, weight `(out, in)` as PyTorch stores it) with faer's matrix
//! product for F32 on the CPU.
//!
//! candle's CPU matmul is the `gemm` crate built without its AVX-512 kernels (compiling them
//! in makes the denoiser's small products slower, BUILD_NOTES.md): about 134 GFLOP/s on the
//! ViT's products on the 2-core dev machine. faer's product chooses its kernels at run time
//! from the CPU's features and the shape (AVX-512 where present) and reaches about 200 GFLOP/s
//! on the same products and is faster on most of the denoiser's (`examples/gemm_probe.rs`,
//! docs/BENCHMARKS.md). The bias is the product's initial value (one pass less). Other dtypes
//! (the F64 parity tests), devices and tracked tensors (training) keep candle's ops.

use candle_core::{CpuStorage, DType, Layout, Shape, Tensor};
use candle_nn::VarBuilder;
use faer::{Accum, MatMut, MatRef, Par};

use std::sync::{Arc, OnceLock};

use crate::error::Result;
use crate::tiles::MatmulPrecision;

/// Products below this many multiply-adds run on the calling thread (splitting costs more).
const PARALLEL_MIN_FLOPS: usize = 1 << 20;

/// A linear layer with an optional bias.
#[derive(Debug, Clone)]
pub struct Linear {
    weight: Tensor,
    bias: Option<Tensor>,
    /// The weight packed for AMX tiles, made on the first product at
    /// [`MatmulPrecision::High`] (shared by clones).
    tiles: Arc<OnceLock<posediff_amx::PackedB>>,
}

/// `nn.Linear(in_dim, out_dim)` with a bias, from `vb` (`weight`, `bias`).
///
/// # Errors
/// Missing or mis-shaped weights.
pub fn linear(in_dim: usize, out_dim: usize, vb: VarBuilder) -> Result<Linear> {
    Linear::new(
        vb.get((out_dim, in_dim), "weight")?,
        Some(vb.get(out_dim, "bias")?),
    )
}

impl Linear {
    /// A layer from its weight `(out, in)` and bias `(out)`. An F32 CPU weight that is not
    /// trained is stored column-major (`Wᵀ` contiguous, viewed as `(out, in)`): faer then
    /// reads it without repacking (the small denoiser products run 1.4-1.6x faster).
    ///
    /// # Errors
    /// Tensor errors (the copy).
    pub fn new(weight: Tensor, bias: Option<Tensor>) -> Result<Self> {
        let weight = if weight.dtype() == DType::F32
            && weight.device().is_cpu()
            && !weight.track_op()
            && weight.rank() == 2
        {
            weight.t()?.contiguous()?.t()?
        } else {
            weight
        };
        Ok(Self {
            weight,
            bias,
            tiles: Arc::default(),
        })
    }

    fn fast_path(&self, x: &Tensor) -> bool {
        std::iter::once(x)
            .chain(std::iter::once(&self.weight))
            .chain(self.bias.as_ref())
            .all(|t| t.dtype() == DType::F32 && t.device().is_cpu() && !t.track_op())
    }

    /// candle's `Linear`: `x Wᵀ` broadcast over the leading dimensions, plus the bias.
    fn forward_candle(&self, x: &Tensor) -> Result<Tensor> {
        let y = x.broadcast_matmul(&self.weight.t()?)?;
        Ok(match &self.bias {
            Some(b) => y.broadcast_add(b)?,
            None => y,
        })
    }

    /// [`Self::forward`] with the product at `precision`: at [`MatmulPrecision::High`] on a CPU
    /// with AMX tiles, `x` (F32, untracked) times the weight packed once into BF16 pairs
    /// ([`crate::tiles`]); otherwise [`Self::forward`].
    ///
    /// # Errors
    /// Mismatched shapes, tensor errors.
    pub fn forward_with(&self, x: &Tensor, precision: MatmulPrecision) -> Result<Tensor> {
        if !precision.uses_tiles() || !self.fast_path(x) || self.weight.rank() != 2 {
            return self.forward(x);
        }
        let packed = match self.tiles.get() {
            Some(p) => p,
            None => {
                let (out_dim, in_dim) = self.weight.dims2()?;
                let column_major = self.weight.t()?.is_contiguous();
                let values = if column_major {
                    self.weight.t()?.flatten_all()?.to_vec1::<f32>()?
                } else {
                    self.weight.flatten_all()?.to_vec1::<f32>()?
                };
                let p = crate::tiles::pack_weight(&values, column_major, out_dim, in_dim)?;
                self.tiles.get_or_init(|| p)
            }
        };
        // The input's storage is read in place (no host copy); the op checks its width.
        let x = x.contiguous()?;
        let op = crate::CpuOp {
            name: "linear-tiles",
            run: |ops: &[crate::Operand<'_>]| linear_tiles(packed, ops[0], ops.get(1).copied()),
        };
        Ok(match &self.bias {
            Some(b) => x.apply_op2_no_bwd(&b.contiguous()?, &op)?,
            None => x.apply_op1_no_bwd(&op)?,
        })
    }

    /// `x Wᵀ + b` over the last dimension of `x`.
    ///
    /// # Errors
    /// Mismatched shapes, tensor errors.
    pub fn forward(&self, x: &Tensor) -> Result<Tensor> {
        if !self.fast_path(x) {
            return self.forward_candle(x);
        }
        let x = x.contiguous()?;
        let weight = if self.weight.is_contiguous() || self.weight.t()?.is_contiguous() {
            self.weight.clone()
        } else {
            self.weight.contiguous()?
        };
        let op = crate::CpuOp {
            name: "linear-f32",
            run: |ops: &[crate::Operand<'_>]| linear_f32(ops[0], ops[1], ops.get(2).copied()),
        };
        Ok(match &self.bias {
            Some(b) => x.apply_op3_no_bwd(&weight, &b.contiguous()?, &op)?,
            None => x.apply_op2_no_bwd(&weight, &op)?,
        })
    }
}

/// What both custom ops share: the input checked against the weight's width, and the output
/// started at the bias (or zeros) with the input's shape ending in `out_dim`.
struct Output<'a> {
    xs: &'a [f32],
    rows: usize,
    out: Vec<f32>,
    shape: Vec<usize>,
}

impl<'a> Output<'a> {
    fn new(
        op: &str,
        x: (&'a CpuStorage, &Layout),
        b: Option<(&CpuStorage, &Layout)>,
        in_dim: usize,
        out_dim: usize,
    ) -> candle_core::Result<Self> {
        let xs = crate::contiguous_f32(x.0, x.1, &format!("{op}: the input"))?;
        let dims = x.1.shape().dims();
        if dims.last() != Some(&in_dim) {
            candle_core::bail!(
                "{op}: input {:?} does not end in the weight's {in_dim} inputs",
                dims
            );
        }
        let rows = xs.len() / in_dim.max(1);
        let out = match b {
            Some(b) => {
                let bs = crate::contiguous_f32(b.0, b.1, &format!("{op}: the bias"))?;
                if bs.len() != out_dim {
                    candle_core::bail!("{op}: {} biases for {out_dim} outputs", bs.len());
                }
                bs.repeat(rows)
            }
            None => vec![0f32; rows * out_dim],
        };
        let mut shape = dims.to_vec();
        if let Some(last) = shape.last_mut() {
            *last = out_dim;
        }
        Ok(Self {
            xs,
            rows,
            out,
            shape,
        })
    }

    fn finish(self) -> (CpuStorage, Shape) {
        (CpuStorage::F32(self.out), Shape::from(self.shape))
    }
}

/// The tile product of [`Linear::forward_with`]: `x (…, in)` and the bias `(out)` contiguous
/// F32, the weight packed.
fn linear_tiles(
    packed: &posediff_amx::PackedB,
    x: (&CpuStorage, &Layout),
    b: Option<(&CpuStorage, &Layout)>,
) -> candle_core::Result<(CpuStorage, Shape)> {
    let (in_dim, out_dim) = (packed.rows(), packed.cols());
    let mut y = Output::new("linear-tiles", x, b, in_dim, out_dim)?;
    crate::tiles::linear(&mut y.out, y.xs, packed, y.rows, in_dim)
        .map_err(|e| candle_core::Error::Msg(e.to_string()))?;
    Ok(y.finish())
}

/// The weight's values and whether they are stored column-major.
fn weight_slice<'a>(
    storage: &'a CpuStorage,
    layout: &Layout,
) -> candle_core::Result<(&'a [f32], bool)> {
    let CpuStorage::F32(data) = storage else {
        candle_core::bail!("linear-f32: the weight must be F32");
    };
    let (out_dim, in_dim) = layout.shape().dims2()?;
    let start = layout.start_offset();
    let len = out_dim * in_dim;
    let column_major = match layout.stride() {
        [_, 1] if layout.is_contiguous() => false,
        [1, s] if *s == out_dim || in_dim == 1 => true,
        _ => candle_core::bail!("linear-f32: the weight must be row- or column-major"),
    };
    match data.get(start..start + len) {
        Some(values) => Ok((values, column_major)),
        None => candle_core::bail!("linear-f32: the weight's storage is too short"),
    }
}

/// The F32 op of [`Linear::forward`]: `x (…, in)` and `b (out)` contiguous F32, `w (out, in)`
/// F32 row-major (contiguous) or column-major (its transpose contiguous).
fn linear_f32(
    x: (&CpuStorage, &Layout),
    w: (&CpuStorage, &Layout),
    b: Option<(&CpuStorage, &Layout)>,
) -> candle_core::Result<(CpuStorage, Shape)> {
    let (ws, column_major) = weight_slice(w.0, w.1)?;
    let (out_dim, in_dim) = w.1.shape().dims2()?;
    let mut y = Output::new("linear-f32", x, b, in_dim, out_dim)?;
    product(
        &mut y.out,
        y.xs,
        (ws, column_major),
        y.rows,
        in_dim,
        out_dim,
        b.is_some(),
    );
    Ok(y.finish())
}

/// `out (rows, out_dim) (+)= x (rows, in_dim) · wᵀ`, `out` and `x` row-major. In faer's
/// column-major terms `outᵀ = w · xᵀ`: `w` `(out, in)`, `xᵀ` column-major `(in, rows)`.
fn product(
    out: &mut [f32],
    x: &[f32],
    (w, column_major): (&[f32], bool),
    rows: usize,
    in_dim: usize,
    out_dim: usize,
    accumulate: bool,
) {
    if rows == 0 || out_dim == 0 {
        return;
    }
    let lhs = if column_major {
        MatRef::from_column_major_slice(w, out_dim, in_dim)
    } else {
        MatRef::from_row_major_slice(w, out_dim, in_dim)
    };
    let rhs = MatRef::from_column_major_slice(x, in_dim, rows);
    let dst = MatMut::from_column_major_slice_mut(out, out_dim, rows);
    let threads = crate::threads();
    let par = if threads > 1 && rows * in_dim * out_dim >= PARALLEL_MIN_FLOPS {
        Par::rayon(threads)
    } else {
        Par::Seq
    };
    let accum = if accumulate {
        Accum::Add
    } else {
        Accum::Replace
    };
    faer::linalg::matmul::matmul(dst, accum, lhs, rhs, 1.0f32, par);
}

#[cfg(test)]
mod tests {
    use candle_core::{Device, Var};

    use super::*;

    /// Against candle's matmul + bias in F64: the difference is F32 rounding of `in_dim`-long
    /// dot products (`√in · ulp · |x||w|`), far below 1e-4 here.
    #[test]
    fn matches_candles_linear_on_every_shape_the_network_has() -> anyhow::Result<()> {
        for (lead, in_dim, out_dim) in [
            (vec![2usize, 197], 384usize, 1152usize),
            (vec![1, 20], 702, 512),
            (vec![3], 128, 9),
            (vec![1, 1, 7], 5, 3),
            (vec![0, 4], 8, 2),
        ] {
            let mut xs = lead.clone();
            xs.push(in_dim);
            let x = Tensor::randn(0f32, 1.0, xs, &Device::Cpu)?;
            let w = Tensor::randn(0f32, 0.05, (out_dim, in_dim), &Device::Cpu)?;
            let b = Tensor::randn(0f32, 1.0, out_dim, &Device::Cpu)?;
            for bias in [Some(b.clone()), None] {
                let layer = Linear::new(w.clone(), bias.clone())?;
                assert!(layer.weight.t()?.is_contiguous(), "stored column-major");
                // The same layer with the weight row-major, as PyTorch stores it.
                let row_major = Linear {
                    weight: w.clone(),
                    bias: layer.bias.clone(),
                    tiles: Arc::default(),
                };
                let truth = Linear::new(
                    w.to_dtype(DType::F64)?,
                    bias.map(|b| b.to_dtype(DType::F64)).transpose()?,
                )?
                .forward(&x.to_dtype(DType::F64)?)?;
                // At MatmulPrecision::High (AMX tiles where the CPU has them) the tolerance
                // scales with the unit roundoff: 2⁻¹⁶ / 2⁻²⁴ = 256.
                for (what, l, precision, tol) in [
                    ("column-major", &layer, MatmulPrecision::Highest, 1e-4),
                    ("row-major", &row_major, MatmulPrecision::Highest, 1e-4),
                    (
                        "column-major, high",
                        &layer,
                        MatmulPrecision::High,
                        256.0 * 1e-4,
                    ),
                    (
                        "row-major, high",
                        &row_major,
                        MatmulPrecision::High,
                        256.0 * 1e-4,
                    ),
                ] {
                    let ours = l.forward_with(&x, precision)?;
                    assert_eq!(ours.dtype(), DType::F32);
                    assert_eq!(ours.dims(), truth.dims(), "{what}");
                    if ours.elem_count() > 0 {
                        let err = (ours.to_dtype(DType::F64)? - &truth)?
                            .abs()?
                            .flatten_all()?
                            .max(0)?
                            .to_scalar::<f64>()?;
                        assert!(err < tol, "{what} {lead:?} {in_dim}→{out_dim}: {err:e}");
                    }
                }
            }
        }
        Ok(())
    }

    /// A strided input (a transpose) gives the same values as its contiguous copy.
    #[test]
    fn strided_inputs_are_made_contiguous() -> anyhow::Result<()> {
        let x = Tensor::randn(0f32, 1.0, (16, 4), &Device::Cpu)?.t()?;
        let w = Tensor::randn(0f32, 1.0, (3, 16), &Device::Cpu)?;
        let layer = Linear::new(w, None)?;
        let a = layer.forward(&x)?.to_vec2::<f32>()?;
        let b = layer.forward(&x.contiguous()?)?.to_vec2::<f32>()?;
        assert_eq!(a, b);
        Ok(())
    }

    /// Tracked weights (training) take candle's differentiable path: gradients flow.
    #[test]
    fn tracked_weights_keep_gradients() -> anyhow::Result<()> {
        let w = Var::randn(0f32, 1.0, (3, 5), &Device::Cpu)?;
        let layer = Linear::new(w.as_tensor().clone(), None)?;
        let x = Tensor::randn(0f32, 1.0, (2, 5), &Device::Cpu)?;
        let loss = layer.forward(&x)?.sum_all()?;
        let grads = loss.backward()?;
        let g = grads.get(w.as_tensor()).map(|g| g.dims().to_vec());
        assert_eq!(g, Some(vec![3, 5]));
        Ok(())
    }

    /// A wrong input width is an error naming both sizes, not a panic.
    #[test]
    fn a_mismatched_width_is_an_error() -> anyhow::Result<()> {
        let layer = Linear::new(Tensor::zeros((3, 5), DType::F32, &Device::Cpu)?, None)?;
        let x = Tensor::zeros((2, 4), DType::F32, &Device::Cpu)?;
        let err = layer.forward(&x).err().map(|e| e.to_string());
        assert!(err.is_some_and(|e| e.contains('5')), "expected an error");
        Ok(())
    }
}
