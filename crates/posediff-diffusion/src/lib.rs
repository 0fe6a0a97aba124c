//! The PoseDiffusion network on candle, loading the official checkpoints unchanged.
//!
//! - [`checkpoint`]: `.pth` / safetensors loading, layout validation, depth detection, converter.
//! - [`features`] + [`vit`]: the multi-scale DINO ViT-S/16 feature extractor.
//! - [`denoiser`]: the transformer that predicts the noise of pose encodings.
//! - [`schedule`] + [`sampler`]: the DDPM schedule and the official reverse-diffusion loop with
//!   an injectable noise source and a mean hook for geometry-guided sampling.
//!
//! Everything runs in the dtype the model is loaded with (F32 for use, F64 for parity checks).
#![deny(missing_docs)]
#![forbid(unsafe_code)]

pub mod activation;
pub mod attention;
pub mod checkpoint;
pub mod denoiser;
pub mod error;
pub mod features;
pub mod finite;
mod head_scratch;
pub mod linear;
pub mod norm;
pub mod resize;
pub mod sampler;
pub mod schedule;
pub mod softmax;
pub mod tiles;
pub mod train;
pub mod vit;

/// The values of a contiguous F32 CPU tensor, for the custom ops' `cpu_fwd`; `what` names the
/// operand in the error.
pub(crate) fn contiguous_f32<'a>(
    storage: &'a candle_core::CpuStorage,
    layout: &candle_core::Layout,
    what: &str,
) -> candle_core::Result<&'a [f32]> {
    match (storage, layout.contiguous_offsets()) {
        (candle_core::CpuStorage::F32(data), Some((start, end))) => Ok(&data[start..end]),
        _ => candle_core::bail!("{what} must be a contiguous F32 tensor"),
    }
}

/// The values of a contiguous F32 CPU tensor, writable, for the in-place ops' `cpu_fwd`;
/// `what` names the op in the error.
///
/// # Errors
/// Another dtype or a layout that is not contiguous.
pub fn contiguous_f32_mut<'a>(
    storage: &'a mut candle_core::CpuStorage,
    layout: &candle_core::Layout,
    what: &str,
) -> candle_core::Result<&'a mut [f32]> {
    match (storage, layout.contiguous_offsets()) {
        (candle_core::CpuStorage::F32(data), Some((start, end))) => Ok(&mut data[start..end]),
        _ => candle_core::bail!("{what} must be a contiguous F32 tensor"),
    }
}

/// A kernel over the values of a contiguous F32 CPU tensor as a candle op, in both forms:
/// copying (`CustomOp1`, `apply_op1_no_bwd`) and in place (`InplaceOp1`, for intermediate
/// results nothing else holds). `kernel(values, row)` gets the values and the length of the
/// last dimension (element-wise kernels ignore it). The one wrapper of the element- and
/// row-wise kernels (the erf GELU, the softmax).
pub(crate) struct SliceOp {
    /// The op's name in candle's errors.
    pub(crate) name: &'static str,
    /// The kernel.
    pub(crate) kernel: fn(&mut [f32], usize),
}

impl SliceOp {
    fn row(layout: &candle_core::Layout) -> usize {
        layout.shape().dims().last().copied().unwrap_or(1)
    }
}

impl candle_core::CustomOp1 for SliceOp {
    fn name(&self) -> &'static str {
        self.name
    }

    fn cpu_fwd(
        &self,
        storage: &candle_core::CpuStorage,
        layout: &candle_core::Layout,
    ) -> candle_core::Result<(candle_core::CpuStorage, candle_core::Shape)> {
        let mut out = contiguous_f32(storage, layout, self.name)?.to_vec();
        (self.kernel)(&mut out, Self::row(layout));
        Ok((candle_core::CpuStorage::F32(out), layout.shape().clone()))
    }
}

impl candle_core::InplaceOp1 for SliceOp {
    fn name(&self) -> &'static str {
        self.name
    }

    fn cpu_fwd(
        &self,
        storage: &mut candle_core::CpuStorage,
        layout: &candle_core::Layout,
    ) -> candle_core::Result<()> {
        let row = Self::row(layout);
        (self.kernel)(contiguous_f32_mut(storage, layout, self.name)?, row);
        Ok(())
    }
}

/// A CPU kernel over one, two or three contiguous tensors as a candle op (`CustomOp1`, `2` and
/// `3`, `apply_opN_no_bwd`): `run` gets each operand's storage and layout, in order, and
/// returns the output. The one wrapper of the products' ops (the linear layers at both
/// precisions, the attention kernels); [`SliceOp`] is the element- and row-wise kernels' (it
/// also runs in place).
pub(crate) struct CpuOp<F> {
    /// The op's name in candle's errors.
    pub(crate) name: &'static str,
    /// The kernel.
    pub(crate) run: F,
}

/// One operand of a [`CpuOp`].
pub(crate) type Operand<'a> = (&'a candle_core::CpuStorage, &'a candle_core::Layout);

type OpOutput = candle_core::Result<(candle_core::CpuStorage, candle_core::Shape)>;

impl<F: Fn(&[Operand<'_>]) -> OpOutput + Send + Sync> candle_core::CustomOp1 for CpuOp<F> {
    fn name(&self) -> &'static str {
        self.name
    }

    fn cpu_fwd(&self, s: &candle_core::CpuStorage, l: &candle_core::Layout) -> OpOutput {
        (self.run)(&[(s, l)])
    }
}

impl<F: Fn(&[Operand<'_>]) -> OpOutput + Send + Sync> candle_core::CustomOp2 for CpuOp<F> {
    fn name(&self) -> &'static str {
        self.name
    }

    fn cpu_fwd(
        &self,
        s1: &candle_core::CpuStorage,
        l1: &candle_core::Layout,
        s2: &candle_core::CpuStorage,
        l2: &candle_core::Layout,
    ) -> OpOutput {
        (self.run)(&[(s1, l1), (s2, l2)])
    }
}

impl<F: Fn(&[Operand<'_>]) -> OpOutput + Send + Sync> candle_core::CustomOp3 for CpuOp<F> {
    fn name(&self) -> &'static str {
        self.name
    }

    fn cpu_fwd(
        &self,
        s1: &candle_core::CpuStorage,
        l1: &candle_core::Layout,
        s2: &candle_core::CpuStorage,
        l2: &candle_core::Layout,
        s3: &candle_core::CpuStorage,
        l3: &candle_core::Layout,
    ) -> OpOutput {
        (self.run)(&[(s1, l1), (s2, l2), (s3, l3)])
    }
}

/// The threads the CPU kernels split over: candle's count (`RAYON_NUM_THREADS`, else the
/// physical cores), read once. candle's `get_num_threads` reads the environment and
/// `/proc/cpuinfo` on every call (about 3 % of a denoiser step in a profile).
pub fn threads() -> usize {
    static THREADS: std::sync::OnceLock<usize> = std::sync::OnceLock::new();
    *THREADS.get_or_init(|| candle_core::utils::get_num_threads().max(1))
}

use std::path::Path;

use candle_core::{DType, Device, Tensor};

pub use checkpoint::{Checkpoint, ModelDepths};
pub use denoiser::Denoiser;
pub use error::{DiffusionError, Result};
pub use features::ImageFeatureExtractor;
pub use sampler::{MeanHook, NoiseSource, ReplayNoise, SeededNoise, sample, sample_from};
pub use schedule::Schedule;
pub use tiles::MatmulPrecision;

/// The whole model: feature extractor, denoiser and schedule.
#[derive(Debug, Clone)]
pub struct PoseDiffusionModel {
    /// Image features.
    pub extractor: ImageFeatureExtractor,
    /// Noise prediction.
    pub denoiser: Denoiser,
    /// Diffusion coefficients (from the checkpoint when it stores them).
    pub schedule: Schedule,
    depths: ModelDepths,
}

impl PoseDiffusionModel {
    /// Builds the model from a validated checkpoint, computing in `dtype` on `device`.
    ///
    /// # Errors
    /// Tensor errors.
    pub fn from_checkpoint(checkpoint: &Checkpoint, dtype: DType, device: &Device) -> Result<Self> {
        let depths = checkpoint.depths();
        let vb = checkpoint.var_builder(dtype, device);
        Ok(Self {
            extractor: ImageFeatureExtractor::new(depths.vit_blocks, vb.clone())?,
            denoiser: Denoiser::new(depths.trunk_layers, vb)?,
            schedule: Schedule::from_checkpoint(checkpoint)?,
            depths,
        })
    }

    /// Loads a checkpoint file (`.pth` or safetensors).
    ///
    /// # Errors
    /// As [`Checkpoint::load`] and [`Self::from_checkpoint`].
    pub fn load(path: &Path, dtype: DType, device: &Device) -> Result<Self> {
        Self::from_checkpoint(&Checkpoint::load(path, device)?, dtype, device)
    }

    /// The depths read from the checkpoint.
    pub fn depths(&self) -> ModelDepths {
        self.depths
    }

    /// Features `(B, N, 384)` of `B` image sets of `N` images each, `(B, N, 3, H, W)` in `[0, 1]`.
    ///
    /// # Errors
    /// Wrong shapes, tensor errors.
    pub fn image_features(&self, images: &Tensor) -> Result<Tensor> {
        let (b, n, c, h, w) = images.dims5()?;
        let f = self.extractor.forward(&images.reshape((b * n, c, h, w))?)?;
        Ok(f.reshape((b, n, checkpoint::VIT_DIM))?)
    }
}
