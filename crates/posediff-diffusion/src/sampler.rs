//! DDPM reverse diffusion exactly as the official `GaussianDiffusion.p_sample_loop`
//! (ε-prediction, no clipping):
//!
//! ```text
//! x ← N(0, I)  (B, N, 9)
//! for t = T−1 … 0:
//!     ε̂  = denoiser(x, t, z)
//!     x̂0 = √(1/ᾱ_t)·x − √(1/ᾱ_t − 1)·ε̂
//!     μ  = coef1_t·x̂0 + coef2_t·x
//!     if a hook is set and t < start_step:  μ ← hook(μ, t); no noise      (GGS plugs in here)
//!     else: noise = N(0, I) if t > 0 else 0
//!     x ← μ + exp(½·log σ²_t)·noise
//! ```
//!
//! Several samples per image set are a batch dimension: repeat `z` along B.

use candle_core::Tensor;
use rand::SeedableRng;
use rand::rngs::StdRng;
use rand_distr::{Distribution, StandardNormal};

use crate::denoiser::Denoiser;
use crate::error::{DiffusionError, Result};
use crate::schedule::Schedule;
use posediff_geometry::POSE_ENCODING_DIM as POSE_DIM;

/// Where the sampler's Gaussian noise comes from.
pub trait NoiseSource {
    /// `count` standard normal values (one tensor's worth, row-major).
    ///
    /// # Errors
    /// A source that has run out (replayed noise).
    fn standard_normal(&mut self, count: usize) -> Result<Vec<f64>>;
}

/// Seeded Gaussian noise: the same seed gives the same samples.
#[derive(Debug, Clone)]
pub struct SeededNoise(StdRng);

impl SeededNoise {
    /// A source seeded with `seed`.
    pub fn new(seed: u64) -> Self {
        Self(StdRng::seed_from_u64(seed))
    }
}

impl NoiseSource for SeededNoise {
    fn standard_normal(&mut self, count: usize) -> Result<Vec<f64>> {
        Ok((0..count)
            .map(|_| StandardNormal.sample(&mut self.0))
            .collect())
    }
}

/// Noise given in advance, consumed in order (tests inject the official draws this way).
#[derive(Debug, Clone, Default)]
pub struct ReplayNoise {
    draws: std::collections::VecDeque<Vec<f64>>,
}

impl ReplayNoise {
    /// Replays `draws` in order.
    pub fn new(draws: impl IntoIterator<Item = Vec<f64>>) -> Self {
        Self {
            draws: draws.into_iter().collect(),
        }
    }
}

impl NoiseSource for ReplayNoise {
    fn standard_normal(&mut self, count: usize) -> Result<Vec<f64>> {
        let draw = self
            .draws
            .pop_front()
            .ok_or(DiffusionError::Invalid("replayed noise ran out"))?;
        if draw.len() != count {
            return Err(DiffusionError::Invalid("replayed noise has the wrong size"));
        }
        Ok(draw)
    }
}

/// Replaces the posterior mean at late steps (the official `cond_fn`, i.e. GGS).
pub trait MeanHook {
    /// The new mean `(B, N, 9)` for step `t`, given the model's.
    ///
    /// # Errors
    /// Whatever the hook reports.
    fn replace_mean(&mut self, mean: &Tensor, t: usize) -> Result<Tensor>;

    /// Called after every step `t` (from T−1 down to 0), whether or not the mean was replaced:
    /// progress reporting. Does nothing by default.
    fn step_done(&mut self, _t: usize) {}
}

/// The values of one reverse step.
#[derive(Debug, Clone)]
pub struct StepOutput {
    /// `ε̂`.
    pub pred_noise: Tensor,
    /// `x̂0`.
    pub pred_x_start: Tensor,
    /// The posterior mean `μ` (before any hook).
    pub model_mean: Tensor,
}

/// Every step of a sampling run (the official `pose_process` and the per-step values).
#[derive(Debug, Clone, Default)]
pub struct SamplingTrace {
    /// `x_T`, then `x` after each step (T + 1 tensors).
    pub pose_process: Vec<Tensor>,
    /// The step outputs, from t = T−1 down to 0.
    pub steps: Vec<StepOutput>,
}

/// One denoising step at `t` from `x` (no noise, no hook).
///
/// # Errors
/// `t` outside the schedule, mismatched shapes.
pub fn denoise_step(
    denoiser: &Denoiser,
    schedule: &Schedule,
    x: &Tensor,
    t: usize,
    z: &Tensor,
) -> Result<StepOutput> {
    if t >= schedule.len() {
        return Err(DiffusionError::Invalid(
            "diffusion step outside the schedule",
        ));
    }
    let b = x.dim(0)?;
    let pred_noise = denoiser.forward(x, &vec![t; b], z)?;
    let pred_x_start = ((x * schedule.sqrt_recip_alphas_cumprod[t])?
        - (&pred_noise * schedule.sqrt_recipm1_alphas_cumprod[t])?)?;
    let model_mean = ((&pred_x_start * schedule.posterior_mean_coef1[t])?
        + (x * schedule.posterior_mean_coef2[t])?)?;
    Ok(StepOutput {
        pred_noise,
        pred_x_start,
        model_mean,
    })
}

/// The official `p_sample_loop` for features `z` `(B, N, 384)`: returns the final encodings
/// `(B, N, 9)`. With `hook`, steps `t < start_step` replace the mean and add no noise.
///
/// # Errors
/// Mismatched shapes, a failing noise source or hook.
pub fn sample(
    denoiser: &Denoiser,
    schedule: &Schedule,
    z: &Tensor,
    noise: &mut dyn NoiseSource,
    hook: Option<(&mut dyn MeanHook, usize)>,
    trace: Option<&mut SamplingTrace>,
) -> Result<Tensor> {
    reverse_diffusion(denoiser, schedule, z, noise, None, hook, trace)
}

/// Reverse diffusion from an initial estimate (SDEdit, Meng et al. ICLR 2022): `x0` `(B, N, 9)`
/// is noised to step `from_step` by the forward process,
/// `x = √ᾱ_s·x0 + √(1 − ᾱ_s)·ε`, and the official reverse steps run from `t = from_step` down
/// to 0 (with the hook as in [`sample`]). `from_step = T − 1` is almost pure noise; small values
/// stay close to `x0`.
///
/// # Errors
/// `from_step` outside the schedule, mismatched shapes, a failing noise source or hook.
#[allow(clippy::too_many_arguments)] // the arguments of `sample` plus the start
pub fn sample_from(
    denoiser: &Denoiser,
    schedule: &Schedule,
    z: &Tensor,
    noise: &mut dyn NoiseSource,
    x0: &Tensor,
    from_step: usize,
    hook: Option<(&mut dyn MeanHook, usize)>,
    trace: Option<&mut SamplingTrace>,
) -> Result<Tensor> {
    if from_step >= schedule.len() {
        return Err(DiffusionError::Invalid("start step outside the schedule"));
    }
    reverse_diffusion(
        denoiser,
        schedule,
        z,
        noise,
        Some((x0, from_step)),
        hook,
        trace,
    )
}

pub use crate::finite::all_finite;

fn reverse_diffusion(
    denoiser: &Denoiser,
    schedule: &Schedule,
    z: &Tensor,
    noise: &mut dyn NoiseSource,
    start: Option<(&Tensor, usize)>,
    mut hook: Option<(&mut dyn MeanHook, usize)>,
    mut trace: Option<&mut SamplingTrace>,
) -> Result<Tensor> {
    let (b, n, _) = z.dims3()?;
    let (dtype, device) = (z.dtype(), z.device());
    let shape = (b, n, POSE_DIM);
    let gaussian = |noise: &mut dyn NoiseSource| -> Result<Tensor> {
        Ok(
            Tensor::from_vec(noise.standard_normal(b * n * POSE_DIM)?, shape, device)?
                .to_dtype(dtype)?,
        )
    };
    let (mut x, first) = match start {
        None => (gaussian(noise)?, schedule.len() - 1),
        Some((x0, s)) => {
            if x0.dims3()? != shape {
                return Err(DiffusionError::Invalid(
                    "initial encodings must be (B, N, 9) like the features",
                ));
            }
            let x0 = x0.to_dtype(dtype)?;
            let x = ((x0 * schedule.sqrt_alphas_cumprod[s])?
                + (gaussian(noise)? * schedule.sqrt_one_minus_alphas_cumprod[s])?)?;
            (x, s)
        }
    };
    if let Some(tr) = trace.as_deref_mut() {
        tr.pose_process.push(x.clone());
    }
    for t in (0..=first).rev() {
        let step = denoise_step(denoiser, schedule, &x, t, z)?;
        if !all_finite(&step.model_mean)? {
            return Err(DiffusionError::NonFinite {
                what: "denoiser's posterior mean",
                step: t,
            });
        }
        x = match hook.as_mut() {
            Some((h, start)) if t < *start => h.replace_mean(&step.model_mean, t)?,
            _ if t > 0 => {
                let sigma = (0.5 * schedule.posterior_log_variance_clipped[t]).exp();
                (&step.model_mean + (gaussian(noise)? * sigma)?)?
            }
            _ => step.model_mean.clone(),
        };
        if let Some((h, _)) = hook.as_mut() {
            h.step_done(t);
        }
        if let Some(tr) = trace.as_deref_mut() {
            tr.pose_process.push(x.clone());
            tr.steps.push(step);
        }
    }
    Ok(x)
}
