//! Network speed on the CPU (F32, the full official architecture with the random-weight
//! checkpoint of `../shared/reference/full`): the backbone per image (three scales) and one
//! denoiser step for N = 10, 20, 50, 100 frames.
//!
//! `cargo bench -p posediff-diffusion --bench network`

use candle_core::{DType, Device, Tensor};
use criterion::{BenchmarkId, Criterion, criterion_group, criterion_main};
use posediff_diffusion::PoseDiffusionModel;

/// The `posediff` binary's allocator, so that the benchmark times what it runs.
#[global_allocator]
static GLOBAL: mimalloc::MiMalloc = mimalloc::MiMalloc;

fn model() -> PoseDiffusionModel {
    let path = std::path::Path::new(env!("CARGO_MANIFEST_DIR"))
        .join("../../../shared/reference/full/model_random.safetensors");
    match PoseDiffusionModel::load(&path, DType::F32, &Device::Cpu) {
        Ok(m) => m,
        Err(e) => panic!("{}: {e}", path.display()),
    }
}

fn backbone(c: &mut Criterion) {
    let m = model();
    let mut group = c.benchmark_group("backbone_3_scales");
    group.sample_size(10);
    for n in [1, 4] {
        let Ok(images) = Tensor::rand(0f32, 1f32, (n, 3, 224, 224), &Device::Cpu) else {
            panic!("images");
        };
        group.bench_function(BenchmarkId::new("images", n), |b| {
            b.iter(|| match m.extractor.forward(&images) {
                Ok(f) => f,
                Err(e) => panic!("{e}"),
            });
        });
    }
    group.finish();
}

fn denoiser_step(c: &mut Criterion) {
    let m = model();
    let mut group = c.benchmark_group("denoiser_step");
    for n in [10, 20, 50, 100] {
        let (Ok(x), Ok(z)) = (
            Tensor::randn(0f32, 1f32, (1, n, 9), &Device::Cpu),
            Tensor::randn(0f32, 1f32, (1, n, 384), &Device::Cpu),
        ) else {
            panic!("inputs");
        };
        group.bench_function(BenchmarkId::new("frames", n), |b| {
            b.iter(|| match m.denoiser.forward(&x, &[50], &z) {
                Ok(e) => e,
                Err(e) => panic!("{e}"),
            });
        });
    }
    group.finish();
}

/// The ViT MLP's GELU on one image's hidden activations (197 tokens × 1536) and on four:
/// posediff's F32 op against candle's `gelu_erf`.
fn gelu(c: &mut Criterion) {
    let mut group = c.benchmark_group("gelu_erf");
    for n in [1, 4] {
        let Ok(x) = Tensor::randn(0f32, 1f32, (n, 197, 1536), &Device::Cpu) else {
            panic!("input");
        };
        group.bench_function(BenchmarkId::new("posediff", n), |b| {
            b.iter(|| match posediff_diffusion::activation::gelu_erf(&x) {
                Ok(y) => y,
                Err(e) => panic!("{e}"),
            });
        });
        group.bench_function(BenchmarkId::new("posediff_in_place", n), |b| {
            b.iter(|| {
                match posediff_diffusion::activation::gelu_erf_owned(
                    x.copy().unwrap_or_else(|e| panic!("{e}")),
                ) {
                    Ok(y) => y,
                    Err(e) => panic!("{e}"),
                }
            });
        });
        group.bench_function(BenchmarkId::new("copy_only", n), |b| {
            b.iter(|| match x.copy() {
                Ok(y) => y,
                Err(e) => panic!("{e}"),
            });
        });
        group.bench_function(BenchmarkId::new("candle", n), |b| {
            b.iter(|| match x.gelu_erf() {
                Ok(y) => y,
                Err(e) => panic!("{e}"),
            });
        });
    }
    group.finish();
}

/// Attention softmax: the ViT's (6 heads × 197 × 197, one image) and LightGlue's (4 heads ×
/// 256 query rows × 2048 keys, one block): posediff's F32 kernel against candle's.
fn softmax(c: &mut Criterion) {
    let mut group = c.benchmark_group("softmax");
    for (name, shape) in [
        ("vit_6x197x197", (6, 197, 197)),
        ("lightglue_4x256x2048", (4, 256, 2048)),
    ] {
        let Ok(x) = Tensor::randn(0f32, 3f32, shape, &Device::Cpu) else {
            panic!("input");
        };
        group.bench_function(BenchmarkId::new("posediff", name), |b| {
            b.iter(|| match posediff_diffusion::softmax::softmax_last_dim(&x) {
                Ok(y) => y,
                Err(e) => panic!("{e}"),
            });
        });
        group.bench_function(BenchmarkId::new("candle", name), |b| {
            b.iter(|| match candle_nn::ops::softmax_last_dim(&x) {
                Ok(y) => y,
                Err(e) => panic!("{e}"),
            });
        });
    }
    group.finish();
}

// criterion_group! generates an undocumented public function.
#[allow(missing_docs)]
mod group {
    use super::*;
    criterion_group!(benches, backbone, denoiser_step, gelu, softmax);
}
use group::benches;
criterion_main!(benches);
