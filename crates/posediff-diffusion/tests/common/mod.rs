//! Helpers shared by the diffusion crate's integration tests.

// Each test binary uses a subset.
#![allow(dead_code, clippy::unwrap_used)]

use candle_core::{DType, Device, Tensor};
use posediff_fixtures::SafetensorsFixture;

/// A fixture tensor as an F64 candle tensor on the CPU.
pub fn tensor(fx: &SafetensorsFixture, name: &str) -> Tensor {
    let t = fx.tensor(name);
    Tensor::from_vec(t.data, t.shape, &Device::Cpu).unwrap()
}

/// A tensor's values as f64, row-major.
pub fn values(t: &Tensor) -> Vec<f64> {
    t.flatten_all()
        .unwrap()
        .to_dtype(DType::F64)
        .unwrap()
        .to_vec1()
        .unwrap()
}
