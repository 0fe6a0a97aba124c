//! LayerNorm over the last dimension (`nn.LayerNorm`: biased variance, affine). candle's fused
//! kernel serves F32/F16/BF16; F64 (parity checks) takes the plain tensor-op path.

use candle_core::{D, DType, Tensor};
use candle_nn::VarBuilder;

use crate::error::Result;

/// An affine LayerNorm.
#[derive(Debug, Clone)]
pub struct LayerNorm {
    weight: Tensor,
    bias: Tensor,
    eps: f64,
}

impl LayerNorm {
    /// Loads `weight` and `bias` of width `size` from `vb`.
    ///
    /// # Errors
    /// Missing or mis-shaped weights.
    pub fn new(size: usize, eps: f64, vb: VarBuilder) -> Result<Self> {
        Ok(Self {
            weight: vb.get(size, "weight")?,
            bias: vb.get(size, "bias")?,
            eps,
        })
    }

    /// Normalises the last dimension.
    ///
    /// # Errors
    /// Tensor errors.
    pub fn forward(&self, x: &Tensor) -> Result<Tensor> {
        // candle's fused layer norm has no backward pass: the explicit formula (also the F64
        // path) when gradients are tracked.
        let tracked = x.track_op() || self.weight.track_op() || self.bias.track_op();
        if x.dtype() != DType::F64 && !tracked {
            return Ok(candle_nn::ops::layer_norm(
                &x.contiguous()?,
                &self.weight,
                &self.bias,
                self.eps as f32,
            )?);
        }
        let mean = x.mean_keepdim(D::Minus1)?;
        let centered = x.broadcast_sub(&mean)?;
        let var = centered.sqr()?.mean_keepdim(D::Minus1)?;
        let normed = centered.broadcast_div(&(var + self.eps)?.sqrt()?)?;
        Ok(normed
            .broadcast_mul(&self.weight)?
            .broadcast_add(&self.bias)?)
    }
}

/// Softmax over the last dimension: the vectorised F32 kernel of [`crate::softmax`] on the CPU,
/// else candle's fused kernel, or (it has no backward pass) the composed, differentiable one
/// when gradients are tracked.
///
/// # Errors
/// Tensor errors.
pub fn softmax_last_dim(x: &Tensor) -> Result<Tensor> {
    crate::softmax::softmax_last_dim(x)
}

pub use crate::softmax::softmax_last_dim_candle;
