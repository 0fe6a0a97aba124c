//! The DDPM schedule of PoseDiffusion's `GaussianDiffusion` (`beta_schedule: custom`):
//! `β = linspace(1e-4, 0.1, 100)`, computed in f64 and stored as f32 buffers (SPEC.md §3).
//!
//! A checkpoint's own `diffuser.*` buffers take precedence ([`Schedule::from_checkpoint`]).

use crate::checkpoint::{Checkpoint, SCHEDULE_PREFIX, TIMESTEPS};
use crate::error::{DiffusionError, Result};

/// First β of the official schedule.
pub const BETA_START: f64 = 1e-4;
/// Last β of the official schedule.
pub const BETA_END: f64 = 0.1;
/// Floor of the posterior variance before the log (`posterior_log_variance_clipped`).
const POSTERIOR_VARIANCE_FLOOR: f64 = 1e-20;

/// The per-step coefficients the sampler uses, indexed by `t = 0..T`.
#[derive(Debug, Clone, PartialEq)]
pub struct Schedule {
    /// `β_t`.
    pub betas: Vec<f64>,
    /// `ᾱ_t`.
    pub alphas_cumprod: Vec<f64>,
    /// `ᾱ_{t−1}` (1 at t = 0).
    pub alphas_cumprod_prev: Vec<f64>,
    /// `√ᾱ_t`.
    pub sqrt_alphas_cumprod: Vec<f64>,
    /// `√(1 − ᾱ_t)`.
    pub sqrt_one_minus_alphas_cumprod: Vec<f64>,
    /// `log(1 − ᾱ_t)`.
    pub log_one_minus_alphas_cumprod: Vec<f64>,
    /// `√(1/ᾱ_t)`.
    pub sqrt_recip_alphas_cumprod: Vec<f64>,
    /// `√(1/ᾱ_t − 1)`.
    pub sqrt_recipm1_alphas_cumprod: Vec<f64>,
    /// `β_t (1 − ᾱ_{t−1}) / (1 − ᾱ_t)`.
    pub posterior_variance: Vec<f64>,
    /// `log(max(posterior_variance, 1e-20))`.
    pub posterior_log_variance_clipped: Vec<f64>,
    /// `β_t √ᾱ_{t−1} / (1 − ᾱ_t)`.
    pub posterior_mean_coef1: Vec<f64>,
    /// `(1 − ᾱ_{t−1}) √α_t / (1 − ᾱ_t)`.
    pub posterior_mean_coef2: Vec<f64>,
    /// 1 (`p2_loss_weight_gamma = 0`).
    pub p2_loss_weight: Vec<f64>,
}

impl Schedule {
    /// The official schedule computed in f64 (the values before the float32 cast).
    pub fn official_f64() -> Self {
        let t = TIMESTEPS;
        let betas: Vec<f64> = (0..t)
            .map(|i| BETA_START + (BETA_END - BETA_START) * i as f64 / (t - 1) as f64)
            .collect();
        let mut alphas_cumprod = Vec::with_capacity(t);
        let mut acc = 1.0;
        for b in &betas {
            acc *= 1.0 - b;
            alphas_cumprod.push(acc);
        }
        let mut alphas_cumprod_prev = vec![1.0];
        alphas_cumprod_prev.extend_from_slice(&alphas_cumprod[..t - 1]);
        let map = |f: &dyn Fn(usize) -> f64| (0..t).map(f).collect::<Vec<f64>>();
        let posterior_variance =
            map(&|i| betas[i] * (1.0 - alphas_cumprod_prev[i]) / (1.0 - alphas_cumprod[i]));
        Self {
            sqrt_alphas_cumprod: map(&|i| alphas_cumprod[i].sqrt()),
            sqrt_one_minus_alphas_cumprod: map(&|i| (1.0 - alphas_cumprod[i]).sqrt()),
            log_one_minus_alphas_cumprod: map(&|i| (1.0 - alphas_cumprod[i]).ln()),
            sqrt_recip_alphas_cumprod: map(&|i| (1.0 / alphas_cumprod[i]).sqrt()),
            sqrt_recipm1_alphas_cumprod: map(&|i| (1.0 / alphas_cumprod[i] - 1.0).sqrt()),
            posterior_log_variance_clipped: map(&|i| {
                posterior_variance[i].max(POSTERIOR_VARIANCE_FLOOR).ln()
            }),
            posterior_mean_coef1: map(&|i| {
                betas[i] * alphas_cumprod_prev[i].sqrt() / (1.0 - alphas_cumprod[i])
            }),
            posterior_mean_coef2: map(&|i| {
                (1.0 - alphas_cumprod_prev[i]) * (1.0 - betas[i]).sqrt() / (1.0 - alphas_cumprod[i])
            }),
            p2_loss_weight: vec![1.0; t],
            posterior_variance,
            betas,
            alphas_cumprod,
            alphas_cumprod_prev,
        }
    }

    /// The official schedule as the model uses it: the f64 values rounded to f32 (the registered
    /// buffers).
    pub fn official() -> Self {
        let mut s = Self::official_f64();
        for v in s.buffers_mut() {
            for x in v.iter_mut() {
                *x = f64::from(*x as f32);
            }
        }
        s
    }

    /// The schedule stored in a checkpoint (`diffuser.*` buffers), or [`Self::official`] when it
    /// stores none.
    ///
    /// # Errors
    /// Buffers that cannot be read as numbers.
    pub fn from_checkpoint(checkpoint: &Checkpoint) -> Result<Self> {
        if !checkpoint.has_schedule() {
            return Ok(Self::official());
        }
        let mut s = Self::official();
        for (name, v) in crate::checkpoint::SCHEDULE_BUFFERS
            .iter()
            .zip(s.buffers_mut())
        {
            let key = format!("{SCHEDULE_PREFIX}.{name}");
            let t = checkpoint
                .get(&key)
                .ok_or(DiffusionError::Invalid("schedule buffer missing"))?;
            *v = t.to_dtype(candle_core::DType::F64)?.to_vec1::<f64>()?;
        }
        Ok(s)
    }

    /// The 13 buffers in `SCHEDULE_BUFFERS` order.
    pub fn buffers(&self) -> [&Vec<f64>; 13] {
        [
            &self.betas,
            &self.alphas_cumprod,
            &self.alphas_cumprod_prev,
            &self.sqrt_alphas_cumprod,
            &self.sqrt_one_minus_alphas_cumprod,
            &self.log_one_minus_alphas_cumprod,
            &self.sqrt_recip_alphas_cumprod,
            &self.sqrt_recipm1_alphas_cumprod,
            &self.posterior_variance,
            &self.posterior_log_variance_clipped,
            &self.posterior_mean_coef1,
            &self.posterior_mean_coef2,
            &self.p2_loss_weight,
        ]
    }

    fn buffers_mut(&mut self) -> [&mut Vec<f64>; 13] {
        [
            &mut self.betas,
            &mut self.alphas_cumprod,
            &mut self.alphas_cumprod_prev,
            &mut self.sqrt_alphas_cumprod,
            &mut self.sqrt_one_minus_alphas_cumprod,
            &mut self.log_one_minus_alphas_cumprod,
            &mut self.sqrt_recip_alphas_cumprod,
            &mut self.sqrt_recipm1_alphas_cumprod,
            &mut self.posterior_variance,
            &mut self.posterior_log_variance_clipped,
            &mut self.posterior_mean_coef1,
            &mut self.posterior_mean_coef2,
            &mut self.p2_loss_weight,
        ]
    }

    /// Number of diffusion steps.
    pub fn len(&self) -> usize {
        self.betas.len()
    }

    /// True for an empty schedule.
    pub fn is_empty(&self) -> bool {
        self.betas.is_empty()
    }
}
