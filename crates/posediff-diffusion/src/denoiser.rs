//! The official pose denoiser (`models/denoiser.py`, SPEC.md §4.2): predicts the noise ε̂ of
//! noisy 9-D pose encodings given the diffusion step and per-frame image features.
//!
//! `feed = [harmonic(x) (189), time(t) (128), z (384), pivot (1)]` → `_first` Linear(702, 512) →
//! pre-LN transformer encoder layers (4 heads, FF 1024, ReLU, LayerNorm eps 1e-5, no final norm)
//! → `_last`: Linear(512, 128), LayerNorm, ReLU, Linear(128, 9).
//!
//! # Pitfalls
//! - The time embedding is **cos first**: `[cos(t f), sin(t f)]`; its frequencies are float32
//!   in the official code, reproduced here bit for bit.
//! - The harmonic embedding is dimension-major: `sin(x_0 f_0..f_9), sin(x_1 f_0..), …`, then the
//!   cos block, then `x`.
//! - The pivot flag marks frame 0 of every sequence.

use candle_core::{D, DType, Device, Tensor};
use candle_nn::VarBuilder;

use crate::linear::{Linear, linear};

use crate::norm::LayerNorm;

use crate::checkpoint::{DENOISER_DIM, DENOISER_FEED_DIM, DENOISER_FF_DIM, TIME_EMBED_DIM};
use crate::error::{DiffusionError, Result};

/// Heads of the trunk's self-attention.
const HEADS: usize = 4;
/// LayerNorm epsilon of the trunk and of `_last`.
const LN_EPS: f64 = 1e-5;
/// `max_period` of the time embedding.
const MAX_PERIOD: f64 = 10000.0;
/// Harmonic functions of the pose embedding (frequencies 2^0..2^9).
pub const HARMONICS: usize = 10;
/// Pose encoding width (the official 9-D encoding).
use posediff_geometry::POSE_ENCODING_DIM as POSE_DIM;
/// Image feature width.
pub const FEATURE_DIM: usize = 384;

/// The sinusoids of the official `TimeStepEmbedding` for step `t`: `[cos(t f_k), sin(t f_k)]`,
/// `f_k = exp(−ln(10000)·k/128)`, with the frequencies and the products `t·f_k` rounded to
/// float32 as the official float32 code computes them.
pub fn timestep_sinusoids(t: f64) -> Vec<f64> {
    let half = TIME_EMBED_DIM / 2;
    let neg_log = -(MAX_PERIOD.ln() as f32);
    let args: Vec<f64> = (0..half)
        .map(|k| {
            let freq = ((neg_log * k as f32) / half as f32).exp();
            f64::from(t as f32 * freq)
        })
        .collect();
    args.iter()
        .map(|a| a.cos())
        .chain(args.iter().map(|a| a.sin()))
        .collect()
}

/// PyTorch3D `HarmonicEmbedding(n_harmonic_functions=10, omega_0=1, logspace=True,
/// append_input=True)` of `(..., 9)` → `(..., 189)`.
///
/// # Errors
/// Tensor errors.
pub fn harmonic_embedding(x: &Tensor) -> Result<Tensor> {
    let dims = x.dims().to_vec();
    let freqs: Vec<f64> = (0..HARMONICS).map(|k| 2f64.powi(k as i32)).collect();
    let freqs = Tensor::from_vec(freqs, HARMONICS, x.device())?.to_dtype(x.dtype())?;
    let mut shape = dims.clone();
    let last = shape.pop().unwrap_or(0);
    let embed = x.unsqueeze(D::Minus1)?.broadcast_mul(&freqs)?;
    let mut flat_shape = shape.clone();
    flat_shape.push(last * HARMONICS);
    let embed = embed.reshape(flat_shape)?;
    Ok(Tensor::cat(&[&embed.sin()?, &embed.cos()?, x], D::Minus1)?)
}

/// One `nn.TransformerEncoderLayer(norm_first=True, activation=relu)`.
#[derive(Debug, Clone)]
pub struct EncoderLayer {
    in_proj: Linear,
    out_proj: Linear,
    linear1: Linear,
    linear2: Linear,
    norm1: LayerNorm,
    norm2: LayerNorm,
}

impl EncoderLayer {
    fn new(vb: VarBuilder) -> Result<Self> {
        let sa = vb.pp("self_attn");
        Ok(Self {
            in_proj: Linear::new(
                sa.get((3 * DENOISER_DIM, DENOISER_DIM), "in_proj_weight")?,
                Some(sa.get(3 * DENOISER_DIM, "in_proj_bias")?),
            )?,
            out_proj: linear(DENOISER_DIM, DENOISER_DIM, sa.pp("out_proj"))?,
            linear1: linear(DENOISER_DIM, DENOISER_FF_DIM, vb.pp("linear1"))?,
            linear2: linear(DENOISER_FF_DIM, DENOISER_DIM, vb.pp("linear2"))?,
            norm1: LayerNorm::new(DENOISER_DIM, LN_EPS, vb.pp("norm1"))?,
            norm2: LayerNorm::new(DENOISER_DIM, LN_EPS, vb.pp("norm2"))?,
        })
    }

    fn self_attention(&self, x: &Tensor) -> Result<Tensor> {
        let head_dim = DENOISER_DIM / HEADS;
        let scale = 1.0 / (head_dim as f64).sqrt();
        let out = crate::attention::self_attention(&self.in_proj.forward(x)?, HEADS, scale)?;
        self.out_proj.forward(&out)
    }

    /// `x + SA(LN1(x))`, then `+ linear2(ReLU(linear1(LN2(x))))`.
    ///
    /// # Errors
    /// Tensor errors.
    pub fn forward(&self, x: &Tensor) -> Result<Tensor> {
        let x = (x + self.self_attention(&self.norm1.forward(x)?)?)?;
        let h = self.linear1.forward(&self.norm2.forward(&x)?)?.relu()?;
        Ok((&x + self.linear2.forward(&h)?)?)
    }
}

/// The denoiser (`diffuser.model`).
#[derive(Debug, Clone)]
pub struct Denoiser {
    time_linear0: Linear,
    time_linear2: Linear,
    first: Linear,
    layers: Vec<EncoderLayer>,
    last0: Linear,
    last1: LayerNorm,
    last3: Linear,
}

/// Intermediate values of one denoiser call, for parity checks.
#[derive(Debug, Clone)]
pub struct DenoiserTrace {
    /// `(1, 256)` sinusoids of the first sequence's step.
    pub timestep_sinusoids: Tensor,
    /// `(B, 128)` time embeddings.
    pub time_embedding: Tensor,
    /// `(B, N, 189)`.
    pub harmonic: Tensor,
    /// `(B, N, 702)`.
    pub feed: Tensor,
    /// `(B, N, 512)` after `_first`.
    pub first: Tensor,
    /// `(B, N, 512)` after each trunk layer.
    pub layers: Vec<Tensor>,
    /// `(B, N, 9)`, the predicted noise.
    pub output: Tensor,
}

impl Denoiser {
    /// Loads a denoiser with `layers` trunk layers from `vb` at the root of the state dict.
    ///
    /// # Errors
    /// Missing or mis-shaped weights.
    pub fn new(layers: usize, vb: VarBuilder) -> Result<Self> {
        let vb = vb.pp("diffuser").pp("model");
        let half = TIME_EMBED_DIM / 2;
        let te = vb.pp("time_embed").pp("linear");
        let last = vb.pp("_last");
        Ok(Self {
            time_linear0: linear(TIME_EMBED_DIM, half, te.pp(0))?,
            time_linear2: linear(half, half, te.pp(2))?,
            first: linear(DENOISER_FEED_DIM, DENOISER_DIM, vb.pp("_first"))?,
            layers: (0..layers)
                .map(|i| EncoderLayer::new(vb.pp("_trunk").pp("layers").pp(i)))
                .collect::<Result<_>>()?,
            last0: linear(DENOISER_DIM, half, last.pp(0))?,
            last1: LayerNorm::new(half, LN_EPS, last.pp(1))?,
            last3: linear(half, POSE_DIM, last.pp(3))?,
        })
    }

    fn time_embedding(
        &self,
        t: &[usize],
        dtype: DType,
        device: &Device,
    ) -> Result<(Tensor, Tensor)> {
        let values: Vec<f64> = t
            .iter()
            .flat_map(|&s| timestep_sinusoids(s as f64))
            .collect();
        let sinusoids =
            Tensor::from_vec(values, (t.len(), TIME_EMBED_DIM), device)?.to_dtype(dtype)?;
        let h = candle_nn::ops::silu(&self.time_linear0.forward(&sinusoids)?)?;
        Ok((sinusoids, self.time_linear2.forward(&h)?))
    }

    fn run(
        &self,
        x: &Tensor,
        t: &[usize],
        z: &Tensor,
        keep: bool,
    ) -> Result<(Tensor, Option<DenoiserTrace>)> {
        let (b, n, d) = x.dims3()?;
        if d != POSE_DIM || t.len() != b || z.dims() != [b, n, FEATURE_DIM] {
            return Err(DiffusionError::Shape {
                what: "denoiser inputs",
                expected: "x (B, N, 9), t (B), z (B, N, 384)",
                got: vec![b, n, d, t.len(), z.elem_count()],
            });
        }
        let (dtype, device) = (x.dtype(), x.device());
        let (sinusoids, t_emb) = self.time_embedding(t, dtype, device)?;
        let harmonic = harmonic_embedding(x)?;
        let mut pivot = vec![0.0f64; b * n];
        for s in 0..b {
            pivot[s * n] = 1.0;
        }
        let pivot = Tensor::from_vec(pivot, (b, n, 1), device)?.to_dtype(dtype)?;
        let t_broadcast = t_emb
            .unsqueeze(1)?
            .broadcast_as((b, n, TIME_EMBED_DIM / 2))?;
        let feed = Tensor::cat(&[&harmonic, &t_broadcast, z, &pivot], D::Minus1)?;
        let first = self.first.forward(&feed)?;
        let mut h = first.clone();
        let mut layers = Vec::new();
        for layer in &self.layers {
            h = layer.forward(&h)?;
            if keep {
                layers.push(h.clone());
            }
        }
        let out = self.last0.forward(&h)?;
        let out = self.last1.forward(&out)?.relu()?;
        let output = self.last3.forward(&out)?;
        let trace = keep.then(|| DenoiserTrace {
            timestep_sinusoids: sinusoids.clone(),
            time_embedding: t_emb,
            harmonic,
            feed,
            first,
            layers,
            output: output.clone(),
        });
        Ok((output, trace))
    }

    /// The predicted noise `ε̂` for noisy encodings `x` `(B, N, 9)`, steps `t` (one per
    /// sequence) and image features `z` `(B, N, 384)`.
    ///
    /// # Errors
    /// Mismatched shapes, tensor errors.
    pub fn forward(&self, x: &Tensor, t: &[usize], z: &Tensor) -> Result<Tensor> {
        Ok(self.run(x, t, z, false)?.0)
    }

    /// [`Self::forward`] keeping every intermediate.
    ///
    /// # Errors
    /// As [`Self::forward`].
    pub fn forward_traced(&self, x: &Tensor, t: &[usize], z: &Tensor) -> Result<DenoiserTrace> {
        self.run(x, t, z, true)?
            .1
            .ok_or(DiffusionError::Invalid("trace was not recorded"))
    }
}
