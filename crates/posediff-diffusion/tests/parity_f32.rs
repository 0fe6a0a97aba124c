//! The network in F32, as `posediff estimate` runs it (the vectorised GELU and softmax, faer's
//! linear layers), against the official float32 outputs of `full/denoiser_io.safetensors`.
//!
//! Both sides round in float32 but sum in different orders, so they differ by the float32
//! rounding of the network, not by the f64 recomputation error the f64 parity tests measure:
//! `full/README.md` gives about 1e-6 relative for single passes. The features are
//! LayerNorm outputs of magnitude up to about 5 after 12 blocks: 1e-6 · 5 rounds up to the
//! backbone bound 1e-5 of the f64 tests; the denoiser outputs (|ε̂| ≲ 1) get 1e-6 · 1 = 1e-6 per
//! element, relative to the largest output. PyTorch's own math path and fast path differ
//! by 1.5e-7 on the same step (README).

#![allow(clippy::unwrap_used)]

use candle_core::{DType, Device, Tensor};
use posediff_diffusion::PoseDiffusionModel;
use posediff_fixtures::tensors::{tensor, values};
use posediff_fixtures::{SafetensorsFixture, assert_close, shared_path};

fn model() -> PoseDiffusionModel {
    let path = shared_path("reference/full/model_random.safetensors");
    PoseDiffusionModel::load(&path, DType::F32, &Device::Cpu).unwrap()
}

fn f32(fx: &SafetensorsFixture, name: &str) -> Tensor {
    tensor(fx, name).to_dtype(DType::F32).unwrap()
}

#[test]
fn f32_features_match_the_official_float32_ones() {
    let m = model();
    let fx = SafetensorsFixture::open(&shared_path("reference/full/denoiser_io.safetensors"));
    let z = m
        .image_features(&f32(&fx, "images").unsqueeze(0).unwrap())
        .unwrap();
    assert_eq!(z.dtype(), DType::F32);
    let worst = assert_close("z", &values(&z), &fx.tensor("z").data, 1e-5, 0.0);
    eprintln!("z: {worst:?}");
}

#[test]
fn f32_denoiser_steps_match_the_official_float32_ones() {
    let m = model();
    let fx = SafetensorsFixture::open(&shared_path("reference/full/denoiser_io.safetensors"));
    let (x, z) = (f32(&fx, "x_t"), f32(&fx, "z"));
    for t in [0usize, 37, 99] {
        let out = m.denoiser.forward(&x, &[t], &z).unwrap();
        let expected = fx.tensor(&format!("out_t{t}")).data;
        let scale = expected.iter().fold(0f64, |a, v| a.max(v.abs())).max(1.0);
        let worst = assert_close(
            &format!("out_t{t}"),
            &values(&out),
            &expected,
            1e-6 * scale,
            0.0,
        );
        eprintln!("t={t}: {worst:?}");
    }
}

/// More images than one ViT pass takes (11 = passes of 6 and 5) give each image the features
/// it gets alone: the passes split the batch and nothing else (the tiny checkpoint, F32; the
/// products' blocking may differ with the row count, hence float32 rounding, not equality).
#[test]
fn features_in_several_passes_match_one_image_at_a_time() {
    let path = shared_path("reference/tiny/model_tiny.safetensors");
    let m = PoseDiffusionModel::load(&path, DType::F32, &Device::Cpu).unwrap();
    let n = posediff_diffusion::features::ImageFeatureExtractor::MAX_IMAGES_PER_PASS + 1;
    let images = Tensor::rand(0f32, 1.0, (n, 3, 224, 224), &Device::Cpu).unwrap();
    let all = m.extractor.forward(&images).unwrap();
    assert_eq!(all.dims(), &[n, 384]);
    let one_by_one: Vec<Tensor> = (0..n)
        .map(|i| {
            m.extractor
                .forward(&images.narrow(0, i, 1).unwrap())
                .unwrap()
        })
        .collect();
    let one_by_one = Tensor::cat(&one_by_one, 0).unwrap();
    assert_close("passes", &values(&all), &values(&one_by_one), 1e-5, 0.0);
}

/// The one pass with the three scales' tokens stacked gives the average of the scales run
/// apart (the tiny checkpoint, F32; float32 rounding from the products' blocking only).
#[test]
fn stacked_scales_match_the_scales_run_apart() {
    let path = shared_path("reference/tiny/model_tiny.safetensors");
    let m = PoseDiffusionModel::load(&path, DType::F32, &Device::Cpu).unwrap();
    let images = Tensor::rand(0f32, 1.0, (3, 3, 224, 224), &Device::Cpu).unwrap();
    let ex = &m.extractor;
    let apart = ex.per_scale(&ex.normalize(&images).unwrap()).unwrap();
    let mean = ((&apart[0] + &apart[1]).unwrap() + &apart[2]).unwrap() / 3.0;
    let stacked = ex.forward(&images).unwrap();
    assert_eq!(stacked.dims(), &[3, 384]);
    assert_close(
        "stacked",
        &values(&stacked),
        &values(&mean.unwrap()),
        1e-5,
        0.0,
    );
}

/// Stacked rows that do not add up to the token sets are an error, not a silent mis-split.
#[test]
fn stacked_rows_must_add_up_to_the_sets() {
    let path = shared_path("reference/tiny/model_tiny.safetensors");
    let m = PoseDiffusionModel::load(&path, DType::F32, &Device::Cpu).unwrap();
    let block = &m.extractor.vit().blocks()[0];
    let x = Tensor::zeros((5, 384), DType::F32, &Device::Cpu).unwrap();
    let sets = posediff_diffusion::vit::TokenSets(vec![(1, 4)]);
    assert!(block.forward_sets(&x, &sets, false).is_err());
    assert!(sets.cls_rows(&x).is_err());
    let fits = posediff_diffusion::vit::TokenSets(vec![(1, 3), (1, 2)]);
    assert_eq!(fits.cls_rows(&x).unwrap().dims(), &[2, 384]);
    assert_eq!(
        block.forward_sets(&x, &fits, true).unwrap().dims(),
        &[2, 384]
    );
}
