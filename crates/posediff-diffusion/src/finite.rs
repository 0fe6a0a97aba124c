//! Finiteness checks of tensors (the checkpoint reader and the sampler both check).

use candle_core::Tensor;

use crate::error::Result;

/// Whether every value of `t` is finite (one reduction in f64: a NaN or ±inf makes the sum
/// of squares non-finite; f32/f16 values squared cannot overflow f64).
///
/// # Errors
/// Tensor errors.
pub fn all_finite(t: &Tensor) -> Result<bool> {
    let s = t.to_dtype(candle_core::DType::F64)?.sqr()?.sum_all()?;
    Ok(s.to_scalar::<f64>()?.is_finite())
}
