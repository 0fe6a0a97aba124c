//! One official training step (`../shared/reference/train/train_io_tiny.safetensors`, see its
//! README): forward values and the L1 loss, gradients of the listed parameters (backbone trained
//! and frozen), the clipped total norm, and the parameters after one clipped AdamW step — all
//! within the README's float32 tolerances.
#![allow(clippy::unwrap_used)]

use candle_core::{DType, Device, IndexOp, Tensor, Var};
use posediff_diffusion::checkpoint::Checkpoint;
use posediff_diffusion::train::{AdamW, Trainable, clip_grad_norm, training_forward};
use posediff_fixtures::tensors::{tensor, values};
use posediff_fixtures::{SafetensorsFixture, shared_path};

/// The parameters whose gradients and after-step values the fixture stores.
const KEYS: [&str; 10] = [
    "diffuser.model._first.weight",
    "diffuser.model._trunk.layers.0.linear1.weight",
    "diffuser.model._trunk.layers.1.self_attn.in_proj_weight",
    "diffuser.model._last.3.weight",
    "diffuser.model._last.3.bias",
    "diffuser.model.time_embed.linear.0.weight",
    "image_feature_extractor._net.blocks.0.attn.qkv.weight",
    "image_feature_extractor._net.patch_embed.proj.weight",
    "image_feature_extractor._net.pos_embed",
    "image_feature_extractor._net.cls_token",
];

struct Setup {
    fx: SafetensorsFixture,
    trainable: Trainable,
    images: Tensor,
    x0: Tensor,
    noise: Tensor,
    t: Vec<usize>,
}

fn f32(fx: &SafetensorsFixture, name: &str) -> Tensor {
    tensor(fx, name).to_dtype(DType::F32).unwrap()
}

fn setup() -> Setup {
    let fx = SafetensorsFixture::open(&shared_path("reference/train/train_io_tiny.safetensors"));
    let ckpt = Checkpoint::load(
        &shared_path("reference/tiny/model_tiny.safetensors"),
        &Device::Cpu,
    )
    .unwrap();
    let trainable = Trainable::from_checkpoint(&ckpt, &Device::Cpu).unwrap();
    // images_u8 / 255 as correctly rounded f32 divisions.
    let u8s = f32(&fx, "images_u8");
    let images = u8s
        .broadcast_div(&Tensor::new(255f32, &Device::Cpu).unwrap())
        .unwrap();
    let t: Vec<usize> = values(&tensor(&fx, "t"))
        .iter()
        .map(|&v| v as usize)
        .collect();
    Setup {
        x0: f32(&fx, "x0"),
        noise: f32(&fx, "noise"),
        fx,
        trainable,
        images,
        t,
    }
}

fn max_abs_diff(a: &[f64], b: &[f64]) -> f64 {
    assert_eq!(a.len(), b.len());
    a.iter()
        .zip(b)
        .map(|(x, y)| (x - y).abs())
        .fold(0.0, f64::max)
}

/// Our full gradient restricted to the fixture's stored rows (when it stores a subset).
fn stored_rows(fx: &SafetensorsFixture, key: &str, full: &Tensor) -> Vec<f64> {
    let rows_key = format!("rows.{key}");
    match fx.names().contains(&rows_key) {
        true => {
            let rows: Vec<f64> = values(&tensor(fx, &rows_key));
            rows.iter()
                .flat_map(|&r| values(&full.i(r as usize).unwrap()))
                .collect()
        }
        false => values(full),
    }
}

fn var_of(trainable: &Trainable, key: &str) -> Var {
    trainable
        .named_variables()
        .into_iter()
        .find(|(k, _)| k == key)
        .unwrap_or_else(|| panic!("no variable {key}"))
        .1
}

#[test]
fn training_step_matches_the_official_one() {
    let s = setup();
    let fwd =
        training_forward(&s.trainable.model, &s.images, &s.x0, &s.t, &s.noise, false).unwrap();
    // Forward values.
    for (name, ours, tol) in [
        ("z", &fwd.z, 1e-5),
        ("x_t", &fwd.x_t, 1e-6),
        ("pred_noise", &fwd.pred_noise, 1e-6),
    ] {
        let err = max_abs_diff(&values(ours), &values(&tensor(&s.fx, name)));
        assert!(err <= tol, "{name}: {err}");
    }
    let loss = values(&fwd.loss)[0];
    let want = s.fx.tensor("loss").data[0];
    assert!((loss - want).abs() <= 1e-6, "loss {loss} vs {want}");

    // Gradients before clipping.
    let mut grads = fwd.loss.backward().unwrap();
    for key in KEYS {
        let g = grads.get(&var_of(&s.trainable, key)).unwrap();
        let ours = stored_rows(&s.fx, key, g);
        let theirs = values(&tensor(&s.fx, &format!("grad.{key}")));
        let scale = theirs.iter().map(|v| v.abs()).fold(0.0, f64::max);
        let err = max_abs_diff(&ours, &theirs);
        let norm_err = ours
            .iter()
            .zip(&theirs)
            .map(|(a, b)| (a - b).powi(2))
            .sum::<f64>()
            .sqrt()
            / theirs.iter().map(|v| v * v).sum::<f64>().sqrt();
        assert!(err <= 1e-5 * scale, "{key}: max err {err} of {scale}");
        assert!(norm_err <= 1e-5, "{key}: relative norm error {norm_err}");
    }

    // Clipping over all parameters.
    let vars: Vec<Var> = s
        .trainable
        .named_variables()
        .into_iter()
        .map(|(_, v)| v)
        .collect();
    assert_eq!(vars.len(), 66, "the official 66 parameters");
    let (norm, coef) = clip_grad_norm(&mut grads, &vars, 1.0).unwrap();
    let want_norm = s.fx.tensor("grad_norm_total_f64acc").data[0];
    assert!(
        (norm / want_norm - 1.0).abs() <= 1e-5,
        "norm {norm} vs {want_norm}"
    );
    let want_coef = s.fx.tensor("clip_coef").data[0];
    assert!(
        (coef / want_coef - 1.0).abs() <= 3e-5,
        "coef {coef} vs {want_coef}"
    );

    // One AdamW step with torch's defaults (weight decay 0.01 on every parameter).
    let mut opt = AdamW::new(s.trainable.named_variables()).unwrap();
    opt.step(&grads, 1e-4).unwrap();
    for key in KEYS {
        let v = var_of(&s.trainable, key);
        let ours = stored_rows(&s.fx, key, v.as_tensor());
        let theirs = values(&tensor(&s.fx, &format!("value.{key}_after_step")));
        let err = max_abs_diff(&ours, &theirs);
        assert!(err <= 5e-6, "{key} after the step: {err}");
    }
}

#[test]
fn a_frozen_backbone_gives_the_same_denoiser_gradients_and_no_backbone_ones() {
    let s = setup();
    let fwd = training_forward(&s.trainable.model, &s.images, &s.x0, &s.t, &s.noise, true).unwrap();
    let loss = values(&fwd.loss)[0];
    assert!((loss - s.fx.tensor("loss_frozen").data[0]).abs() <= 1e-6);
    let mut grads = fwd.loss.backward().unwrap();
    for key in KEYS.iter().filter(|k| k.starts_with("diffuser.")) {
        let g = grads.get(&var_of(&s.trainable, key)).unwrap();
        let ours = stored_rows(&s.fx, key, g);
        let theirs = values(&tensor(&s.fx, &format!("grad.{key}_frozen")));
        let scale = theirs.iter().map(|v| v.abs()).fold(0.0, f64::max);
        assert!(max_abs_diff(&ours, &theirs) <= 1e-5 * scale, "{key}");
    }
    for key in KEYS
        .iter()
        .filter(|k| k.starts_with("image_feature_extractor."))
    {
        assert!(
            grads.get(&var_of(&s.trainable, key)).is_none(),
            "{key} has a gradient"
        );
    }
    let vars: Vec<Var> = s
        .trainable
        .named_variables()
        .into_iter()
        .map(|(_, v)| v)
        .collect();
    let (norm, _) = clip_grad_norm(&mut grads, &vars, 1.0).unwrap();
    let want = s.fx.tensor("grad_norm_total_frozen_f64acc").data[0];
    assert!(
        (norm / want - 1.0).abs() <= 1e-5,
        "frozen norm {norm} vs {want}"
    );
}
