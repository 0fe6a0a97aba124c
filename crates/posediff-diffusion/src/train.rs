//! The official training step on candle (SPEC.md §7; `train.py`): ε-prediction with an L1 loss,
//! one diffusion step `t` per sequence, gradient-norm clipping at 1.0 and torch's AdamW.
//!
//! The parameters live in a [`VarMap`] under the official key names (the checkpoint's, without
//! the 13 `diffuser.*` schedule buffers), so a trained model saves in the official layout.
//! Gradients flow through the whole network; candle's fused softmax and layer norm have no
//! backward pass, so the network switches to their composed forms whenever a tensor tracks
//! gradients (inference keeps the fused kernels).

use candle_core::backprop::GradStore;
use candle_core::{DType, Device, Tensor, Var};
use candle_nn::{VarBuilder, VarMap};

use crate::checkpoint::Checkpoint;
use crate::error::{DiffusionError, Result};
use crate::{Denoiser, ImageFeatureExtractor, PoseDiffusionModel, Schedule};

/// `clip_grad_norm_`'s epsilon: the coefficient is `max_norm / (total + 1e-6)`.
pub const CLIP_EPS: f64 = 1e-6;

/// Whether a checkpoint key is a trainable parameter (not one of the schedule buffers
/// `diffuser.*` outside `diffuser.model.*`).
pub fn is_parameter(key: &str) -> bool {
    !key.starts_with("diffuser.") || key.starts_with("diffuser.model.")
}

/// A model whose parameters are variables.
pub struct Trainable {
    /// The parameters by official key.
    pub varmap: VarMap,
    /// The network built on them.
    pub model: PoseDiffusionModel,
}

impl std::fmt::Debug for Trainable {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("Trainable")
            .field("parameters", &self.varmap.all_vars().len())
            .finish()
    }
}

impl Trainable {
    /// Variables initialised from `checkpoint` (F32 on `device`) and the model over them.
    ///
    /// # Errors
    /// Tensor errors.
    pub fn from_checkpoint(checkpoint: &Checkpoint, device: &Device) -> Result<Self> {
        let varmap = VarMap::new();
        {
            let mut data = varmap
                .data()
                .lock()
                .map_err(|_| DiffusionError::Invalid("variable map lock poisoned"))?;
            for (key, tensor) in &checkpoint.tensors {
                if is_parameter(key) {
                    let value = tensor.to_dtype(DType::F32)?.to_device(device)?;
                    data.insert(key.to_string(), Var::from_tensor(&value)?);
                }
            }
        }
        let depths = checkpoint.depths();
        let vb = VarBuilder::from_varmap(&varmap, DType::F32, device);
        let model = PoseDiffusionModel {
            extractor: ImageFeatureExtractor::new(depths.vit_blocks, vb.clone())?,
            denoiser: Denoiser::new(depths.trunk_layers, vb)?,
            schedule: Schedule::from_checkpoint(checkpoint)?,
            depths,
        };
        Ok(Self { varmap, model })
    }

    /// The variables and their keys, sorted by key.
    pub fn named_variables(&self) -> Vec<(String, Var)> {
        let mut out: Vec<(String, Var)> = match self.varmap.data().lock() {
            Ok(data) => data.iter().map(|(k, v)| (k.clone(), v.clone())).collect(),
            Err(_) => Vec::new(),
        };
        out.sort_by(|a, b| a.0.cmp(&b.0));
        out
    }
}

/// The values of one training forward pass.
#[derive(Debug, Clone)]
pub struct StepForward {
    /// Image features `(B, N, 384)`.
    pub z: Tensor,
    /// `x_t = √ᾱ_t x0 + √(1 − ᾱ_t) ε`.
    pub x_t: Tensor,
    /// `ε̂`.
    pub pred_noise: Tensor,
    /// `mean |ε̂ − ε|`.
    pub loss: Tensor,
}

/// The official training forward (`PoseDiffusionModel.forward(training=True)` with the loss of
/// `train.py`) for images `(B, N, 3, H, W)` in `[0, 1]`, encodings `x0` `(B, N, 9)`, one step per
/// sequence and noise `ε` `(B, N, 9)`. With `freeze_backbone` the features are detached.
///
/// # Errors
/// Mismatched shapes, steps outside the schedule, tensor errors.
pub fn training_forward(
    model: &PoseDiffusionModel,
    images: &Tensor,
    x0: &Tensor,
    t: &[usize],
    noise: &Tensor,
    freeze_backbone: bool,
) -> Result<StepForward> {
    let (b, n, _) = x0.dims3()?;
    if t.len() != b || noise.dims3()? != (b, n, posediff_geometry::POSE_ENCODING_DIM) {
        return Err(DiffusionError::Invalid(
            "one step per sequence and noise shaped like x0",
        ));
    }
    let s = &model.schedule;
    if t.iter().any(|&t| t >= s.len()) {
        return Err(DiffusionError::Invalid(
            "diffusion step outside the schedule",
        ));
    }
    let mut z = model.image_features(images)?;
    if freeze_backbone {
        z = z.detach();
    }
    let (x_t, pred_noise, loss) = denoising_loss(&model.denoiser, s, &z, x0, t, noise)?;
    Ok(StepForward {
        z,
        x_t,
        pred_noise,
        loss,
    })
}

/// The denoiser part of the training forward for given features `z` `(B, N, 384)`: `x_t`, `ε̂`
/// and `mean |ε̂ − ε|`.
///
/// # Errors
/// Mismatched shapes, steps outside the schedule, tensor errors.
pub fn denoising_loss(
    denoiser: &Denoiser,
    schedule: &Schedule,
    z: &Tensor,
    x0: &Tensor,
    t: &[usize],
    noise: &Tensor,
) -> Result<(Tensor, Tensor, Tensor)> {
    let (b, n, _) = x0.dims3()?;
    if t.len() != b || noise.dims3()? != (b, n, posediff_geometry::POSE_ENCODING_DIM) {
        return Err(DiffusionError::Invalid(
            "one step per sequence and noise shaped like x0",
        ));
    }
    if t.iter().any(|&t| t >= schedule.len()) {
        return Err(DiffusionError::Invalid(
            "diffusion step outside the schedule",
        ));
    }
    let device = x0.device();
    let coef = |v: &[f64]| -> Result<Tensor> {
        let c: Vec<f32> = t.iter().map(|&t| v[t] as f32).collect();
        Ok(Tensor::from_vec(c, (b, 1, 1), device)?.to_dtype(x0.dtype())?)
    };
    let x_t = (x0.broadcast_mul(&coef(&schedule.sqrt_alphas_cumprod)?)?
        + noise.broadcast_mul(&coef(&schedule.sqrt_one_minus_alphas_cumprod)?)?)?;
    let pred_noise = denoiser.forward(&x_t, t, z)?;
    let loss = (&pred_noise - noise)?.abs()?.mean_all()?;
    Ok((x_t, pred_noise, loss))
}

/// `torch.nn.utils.clip_grad_norm_`: the 2-norm over all gradients of `vars` (accumulated in
/// f64), then every gradient times `min(1, max_norm / (norm + 1e-6))`. Returns the norm and the
/// coefficient.
///
/// # Errors
/// Tensor errors.
pub fn clip_grad_norm(grads: &mut GradStore, vars: &[Var], max_norm: f64) -> Result<(f64, f64)> {
    let mut sum = 0.0f64;
    for v in vars {
        if let Some(g) = grads.get(v) {
            sum += g
                .to_dtype(DType::F64)?
                .sqr()?
                .sum_all()?
                .to_scalar::<f64>()?;
        }
    }
    let norm = sum.sqrt();
    let coef = (max_norm / (norm + CLIP_EPS)).min(1.0);
    if coef < 1.0 {
        for v in vars {
            if let Some(g) = grads.get(v) {
                let scaled = (g * coef)?;
                grads.insert(v, scaled);
            }
        }
    }
    Ok((norm, coef))
}

/// torch's `AdamW` (decoupled weight decay on every parameter, bias-corrected moments) with its
/// state exposed for checkpoints: the first step is exactly the one the parity fixture records.
#[derive(Debug)]
pub struct AdamW {
    /// `(key, parameter, first moment, second moment)`.
    params: Vec<(String, Var, Tensor, Tensor)>,
    /// Steps taken.
    pub step: u64,
    /// β₁.
    pub beta1: f64,
    /// β₂.
    pub beta2: f64,
    /// ε.
    pub eps: f64,
    /// Decoupled weight decay.
    pub weight_decay: f64,
}

impl AdamW {
    /// torch's defaults (β 0.9/0.999, ε 1e-8, weight decay 0.01) over `params`.
    ///
    /// # Errors
    /// Tensor errors.
    pub fn new(params: Vec<(String, Var)>) -> Result<Self> {
        let params = params
            .into_iter()
            .map(|(k, v)| {
                let zeros = v.as_tensor().zeros_like()?;
                Ok((k, v, zeros.clone(), zeros))
            })
            .collect::<Result<Vec<_>>>()?;
        Ok(Self {
            params,
            step: 0,
            beta1: 0.9,
            beta2: 0.999,
            eps: 1e-8,
            weight_decay: 0.01,
        })
    }

    /// The parameters it updates.
    pub fn vars(&self) -> Vec<Var> {
        self.params.iter().map(|p| p.1.clone()).collect()
    }

    /// One step at learning rate `lr` with `grads` (parameters without a gradient only decay
    /// when torch would update them, i.e. never: they are skipped).
    ///
    /// # Errors
    /// Tensor errors.
    pub fn step(&mut self, grads: &GradStore, lr: f64) -> Result<()> {
        self.step += 1;
        let t = self.step as i32;
        let (b1, b2) = (self.beta1, self.beta2);
        let scale_m = 1.0 / (1.0 - b1.powi(t));
        let scale_v = 1.0 / (1.0 - b2.powi(t));
        for (_, var, m, v) in &mut self.params {
            let Some(g) = grads.get(var) else { continue };
            *m = ((&*m * b1)? + (g * (1.0 - b1))?)?;
            *v = ((&*v * b2)? + (g.sqr()? * (1.0 - b2))?)?;
            let update = ((&*m * scale_m)? / ((&*v * scale_v)?.sqrt()? + self.eps)?)?;
            let decayed = (var.as_tensor() * (1.0 - lr * self.weight_decay))?;
            var.set(&(decayed - (update * lr)?)?)?;
        }
        Ok(())
    }

    /// The moments as `m.<key>` / `v.<key>` tensors (for a checkpoint).
    pub fn state_tensors(&self) -> Vec<(String, Tensor)> {
        self.params
            .iter()
            .flat_map(|(k, _, m, v)| [(format!("m.{k}"), m.clone()), (format!("v.{k}"), v.clone())])
            .collect()
    }

    /// Restores the moments from [`Self::state_tensors`] and the step count.
    ///
    /// # Errors
    /// A missing or mis-shaped moment.
    pub fn load_state(
        &mut self,
        tensors: &std::collections::HashMap<String, Tensor>,
        step: u64,
    ) -> Result<()> {
        for (k, var, m, v) in &mut self.params {
            for (prefix, slot) in [("m", &mut *m), ("v", &mut *v)] {
                let saved =
                    tensors
                        .get(&format!("{prefix}.{k}"))
                        .ok_or(DiffusionError::Invalid(
                            "optimizer state misses a parameter",
                        ))?;
                if saved.dims() != var.as_tensor().dims() {
                    return Err(DiffusionError::Invalid("optimizer state has a wrong shape"));
                }
                *slot = saved.to_dtype(var.dtype())?.to_device(var.device())?;
            }
        }
        self.step = step;
        Ok(())
    }
}

/// The official `WarmupCosineRestarts` learning rate at iteration `it` (0-based): linear warm-up
/// from `warmup_init` to `base` over `warmup` iterations, then cosine annealing to 0 restarting
/// every `period` iterations.
pub fn learning_rate(it: u64, base: f64, warmup_init: f64, warmup: u64, period: u64) -> f64 {
    if it < warmup {
        return warmup_init + (base - warmup_init) * it as f64 / warmup.max(1) as f64;
    }
    let period = period.max(1);
    let phase = ((it - warmup) % period) as f64 / period as f64;
    0.5 * base * (1.0 + (std::f64::consts::PI * phase).cos())
}

/// A freshly initialised model of `depths` as a validated checkpoint (F32): PyTorch's default
/// initialisation for the denoiser (`Linear`: weights and biases `U(±1/√fan_in)`;
/// `MultiheadAttention`: Xavier-uniform `in_proj_weight`, zero projection biases; `LayerNorm`:
/// 1 and 0), DINO's for the ViT (normal σ = 0.02, truncated at ±2 as timm does, for `Linear`
/// weights, the position table and the class token; zero biases; the patch convolution
/// `U(±1/√fan_in)`), and the
/// official schedule buffers. Deterministic for a seed.
///
/// # Errors
/// Tensor errors.
pub fn initial_checkpoint(
    depths: crate::checkpoint::ModelDepths,
    seed: u64,
    device: &Device,
) -> Result<Checkpoint> {
    use rand::{Rng, SeedableRng};
    use rand_distr::{Distribution, StandardNormal};
    let mut rng = rand::rngs::StdRng::seed_from_u64(seed);
    let params = crate::checkpoint::expected_parameters(depths);
    let shapes: std::collections::HashMap<&str, &Vec<usize>> =
        params.iter().map(|(k, s)| (k.as_str(), s)).collect();
    let fan_in = |shape: &[usize]| shape[1..].iter().product::<usize>().max(1) as f64;
    let mut tensors = Vec::with_capacity(params.len() + 13);
    for (key, shape) in &params {
        let count: usize = shape.iter().product();
        let is_vit = key.starts_with(crate::checkpoint::VIT_PREFIX);
        let leaf = key.rsplit('.').next().unwrap_or("");
        let is_norm = key.contains("norm") || key.contains("_last.1.");
        let uniform = |rng: &mut rand::rngs::StdRng, bound: f64| -> Vec<f32> {
            (0..count)
                .map(|_| rng.random_range(-bound..=bound) as f32)
                .collect()
        };
        // timm's `trunc_normal_(std=0.02)` truncates at ±2 in absolute units: 100σ, never hit.
        let trunc_normal = |rng: &mut rand::rngs::StdRng| -> Vec<f32> {
            (0..count)
                .map(|_| {
                    let v: f64 = StandardNormal.sample(rng);
                    (0.02 * v).clamp(-2.0, 2.0) as f32
                })
                .collect()
        };
        let values: Vec<f32> = if is_norm {
            vec![if leaf == "weight" { 1.0 } else { 0.0 }; count]
        } else if key.ends_with("in_proj_weight") {
            let bound = (6.0 / (shape[0] / 3 + shape[1]) as f64).sqrt();
            uniform(&mut rng, bound)
        } else if key.ends_with("in_proj_bias") || key.ends_with("out_proj.bias") {
            vec![0.0; count]
        } else if is_vit && (leaf == "cls_token" || leaf == "pos_embed") {
            trunc_normal(&mut rng)
        } else if is_vit && !key.contains("patch_embed") {
            if leaf == "weight" {
                trunc_normal(&mut rng)
            } else {
                vec![0.0; count]
            }
        } else if leaf == "weight" {
            uniform(&mut rng, 1.0 / fan_in(shape).sqrt())
        } else {
            // A bias: bounded by its weight's fan-in.
            let weight = format!("{}.weight", key.trim_end_matches(".bias"));
            let fan = shapes.get(weight.as_str()).map_or(1.0, |s| fan_in(s));
            uniform(&mut rng, 1.0 / fan.sqrt())
        };
        tensors.push((
            key.clone(),
            Tensor::from_vec(values, shape.as_slice(), device)?,
        ));
    }
    let schedule = Schedule::official();
    for (name, values) in crate::checkpoint::SCHEDULE_BUFFERS
        .iter()
        .zip(schedule.buffers())
    {
        let v: Vec<f32> = values.iter().map(|&x| x as f32).collect();
        tensors.push((
            format!("{}.{name}", crate::checkpoint::SCHEDULE_PREFIX),
            Tensor::from_vec(v, values.len(), device)?,
        ));
    }
    Checkpoint::from_tensors(tensors)
}

#[cfg(test)]
mod tests {
    #![allow(clippy::unwrap_used)]
    use super::*;
    use crate::checkpoint::ModelDepths;

    #[test]
    fn a_fresh_model_validates_and_has_the_default_statistics() {
        let depths = ModelDepths {
            vit_blocks: 1,
            trunk_layers: 1,
        };
        let ckpt = initial_checkpoint(depths, 3, &Device::Cpu).unwrap();
        let t = ckpt.tensor_map();
        let stats = |k: &str| {
            let v: Vec<f32> = t[k].flatten_all().unwrap().to_vec1().unwrap();
            let max = v.iter().map(|x| x.abs()).fold(0.0f32, f32::max);
            let sd = (v.iter().map(|x| x * x).sum::<f32>() / v.len() as f32).sqrt();
            (max, sd)
        };
        // Linear 702 → 512: U(±1/√702).
        let (max, _) = stats("diffuser.model._first.weight");
        assert!(max <= 1.0 / 702f32.sqrt() && max > 0.9 / 702f32.sqrt());
        let (_, sd) = stats("image_feature_extractor._net.pos_embed");
        assert!((sd - 0.02).abs() < 0.002, "{sd}");
        assert!(stats("diffuser.model._trunk.layers.0.norm1.bias").0 == 0.0);
        let (max, sd) = stats("diffuser.model._trunk.layers.0.norm1.weight");
        assert!(max == 1.0 && sd == 1.0);
        // Deterministic; another seed differs.
        let again = initial_checkpoint(depths, 3, &Device::Cpu).unwrap();
        let other = initial_checkpoint(depths, 4, &Device::Cpu).unwrap();
        let first = |c: &Checkpoint| -> Vec<f32> {
            c.tensor_map()["diffuser.model._first.bias"]
                .to_vec1()
                .unwrap()
        };
        assert_eq!(first(&ckpt), first(&again));
        assert_ne!(first(&ckpt), first(&other));
        // It runs.
        let trainable = Trainable::from_checkpoint(&ckpt, &Device::Cpu).unwrap();
        assert_eq!(trainable.named_variables().len(), expected_count(depths));
    }

    fn expected_count(depths: ModelDepths) -> usize {
        crate::checkpoint::expected_parameters(depths).len()
    }
}
