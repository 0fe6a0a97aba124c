//! DINO ViT-S/16 (facebookresearch/dino `vision_transformer.py`) as the official feature
//! extractor uses it: patch 16, width 384, 6 heads, MLP 1536 with exact (erf) GELU, pre-LN blocks
//! with LayerNorm eps 1e-6, output = final-LayerNorm'ed CLS token. For inputs other than 224 px
//! the 14×14 positional table is resized bicubically with DINO's `+0.1` scale factor
//! (`interpolate_pos_encoding`).

use candle_core::{DType, Device, IndexOp, Tensor};
use candle_nn::VarBuilder;

use crate::linear::{Linear, linear};

use crate::norm::LayerNorm;

use crate::checkpoint::{VIT_DIM, VIT_MLP_DIM, VIT_POS_TOKENS};
use crate::error::{DiffusionError, Result};
use crate::resize::bicubic_matrix;

/// Patch size.
pub const PATCH: usize = 16;
/// Attention heads.
const HEADS: usize = 6;
/// LayerNorm epsilon of the ViT.
const LN_EPS: f64 = 1e-6;
/// Side of the positional-embedding grid (224 / 16).
const POS_GRID: usize = 14;
/// DINO adds this to the target grid size before computing the bicubic scale factor.
const POS_SCALE_OFFSET: f64 = 0.1;

/// A matrix as a tensor of `dtype`.
pub(crate) fn matrix(
    values: Vec<f64>,
    rows: usize,
    cols: usize,
    dtype: DType,
    device: &Device,
) -> Result<Tensor> {
    Ok(Tensor::from_vec(values, (rows, cols), device)?.to_dtype(dtype)?)
}

/// `M_h · X · M_wᵀ` for `X` of shape `(B, H, W)`, `m_h` `(h, H)`, `m_w` `(w, W)`.
pub(crate) fn resize_separable(x: &Tensor, m_h: &Tensor, m_w: &Tensor) -> Result<Tensor> {
    let y = m_h.broadcast_matmul(x)?;
    Ok(y.broadcast_matmul(&m_w.t()?)?)
}

/// Multi-head self-attention with a packed qkv projection.
#[derive(Debug, Clone)]
struct Attention {
    qkv: Linear,
    proj: Linear,
}

impl Attention {
    fn new(vb: VarBuilder) -> Result<Self> {
        Ok(Self {
            qkv: linear(VIT_DIM, 3 * VIT_DIM, vb.pp("qkv"))?,
            proj: linear(VIT_DIM, VIT_DIM, vb.pp("proj"))?,
        })
    }

    fn forward(&self, x: &Tensor) -> Result<Tensor> {
        let head_dim = VIT_DIM / HEADS;
        let scale = (head_dim as f64).powf(-0.5);
        let out = crate::attention::self_attention(&self.qkv.forward(x)?, HEADS, scale)?;
        self.proj.forward(&out)
    }
}

/// One pre-LN transformer block.
#[derive(Debug, Clone)]
pub struct Block {
    norm1: LayerNorm,
    attn: Attention,
    norm2: LayerNorm,
    fc1: Linear,
    fc2: Linear,
}

impl Block {
    fn new(vb: VarBuilder) -> Result<Self> {
        Ok(Self {
            norm1: LayerNorm::new(VIT_DIM, LN_EPS, vb.pp("norm1"))?,
            attn: Attention::new(vb.pp("attn"))?,
            norm2: LayerNorm::new(VIT_DIM, LN_EPS, vb.pp("norm2"))?,
            fc1: linear(VIT_DIM, VIT_MLP_DIM, vb.pp("mlp").pp("fc1"))?,
            fc2: linear(VIT_MLP_DIM, VIT_DIM, vb.pp("mlp").pp("fc2"))?,
        })
    }

    /// `x + attn(LN1(x))`, then `+ fc2(GELU(fc1(LN2(x))))`.
    ///
    /// # Errors
    /// Tensor errors.
    pub fn forward(&self, x: &Tensor) -> Result<Tensor> {
        let x = (x + self.attn.forward(&self.norm1.forward(x)?)?)?;
        self.mlp_residual(&x)
    }

    /// `x + fc2(GELU(fc1(LN2(x))))`.
    fn mlp_residual(&self, x: &Tensor) -> Result<Tensor> {
        let h = crate::activation::gelu_erf_owned(self.fc1.forward(&self.norm2.forward(x)?)?)?;
        Ok((x + self.fc2.forward(&h)?)?)
    }

    /// The block on several token sets at once (see [`TokenSets`]): the norms, the linear
    /// layers and the GELU see the rows of every set in one call, the attention each set
    /// (`B` images of `T` tokens) apart. With `cls_only`, only each image's first token leaves
    /// the block: the attention still reads every token, the projection, the residual and the
    /// MLP run on the CLS rows alone (rows are independent there).
    ///
    /// # Errors
    /// Rows that do not add up to the sets, tensor errors.
    pub fn forward_sets(&self, x: &Tensor, sets: &TokenSets, cls_only: bool) -> Result<Tensor> {
        if x.dim(0)? != sets.rows() {
            return Err(DiffusionError::Invalid(
                "the stacked rows do not add up to the token sets",
            ));
        }
        let qkv = self.attn.qkv.forward(&self.norm1.forward(x)?)?;
        let head_dim = VIT_DIM / HEADS;
        let scale = (head_dim as f64).powf(-0.5);
        let mut attended = Vec::with_capacity(sets.0.len());
        let mut start = 0;
        for &(b, t) in &sets.0 {
            let rows = b * t;
            let set_qkv = qkv.narrow(0, start, rows)?.reshape((b, t, 3 * VIT_DIM))?;
            let out = crate::attention::self_attention(&set_qkv, HEADS, scale)?;
            attended.push(if cls_only {
                out.i((.., 0, ..))?
            } else {
                out.reshape((rows, VIT_DIM))?
            });
            start += rows;
        }
        let attended = Tensor::cat(&attended, 0)?;
        let x = if cls_only {
            sets.cls_rows(x)?
        } else {
            x.clone()
        };
        let x = (x + self.attn.proj.forward(&attended)?)?;
        self.mlp_residual(&x)
    }
}

/// Several token sets whose rows are stacked into one `(Σ B·T, C)` matrix, set after set and
/// image after image: each set's `(B, T)` (images, tokens per image).
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct TokenSets(pub Vec<(usize, usize)>);

impl TokenSets {
    /// Rows of the stacked matrix.
    pub fn rows(&self) -> usize {
        self.0.iter().map(|&(b, t)| b * t).sum()
    }

    /// Each image's first (CLS) row of the stacked `x`, set after set: `(Σ B, C)`.
    ///
    /// # Errors
    /// Rows that do not add up to the sets, tensor errors.
    pub fn cls_rows(&self, x: &Tensor) -> Result<Tensor> {
        let (rows, c) = x.dims2()?;
        if rows != self.rows() {
            return Err(DiffusionError::Invalid(
                "the stacked rows do not add up to the token sets",
            ));
        }
        let mut cls = Vec::with_capacity(self.0.len());
        let mut start = 0;
        for &(b, t) in &self.0 {
            cls.push(
                x.narrow(0, start, b * t)?
                    .reshape((b, t, c))?
                    .i((.., 0, ..))?,
            );
            start += b * t;
        }
        Ok(Tensor::cat(&cls, 0)?)
    }
}

/// The DINO ViT-S/16 trunk (`image_feature_extractor._net`).
#[derive(Debug, Clone)]
pub struct VisionTransformer {
    cls_token: Tensor,
    pos_embed: Tensor,
    patch_weight: Tensor,
    patch_bias: Tensor,
    blocks: Vec<Block>,
    norm: LayerNorm,
}

impl VisionTransformer {
    /// Loads `depth` blocks from `vb` (at `image_feature_extractor._net`).
    ///
    /// # Errors
    /// Missing or mis-shaped weights.
    pub fn new(depth: usize, vb: VarBuilder) -> Result<Self> {
        Ok(Self {
            cls_token: vb.get((1, 1, VIT_DIM), "cls_token")?,
            pos_embed: vb.get((1, VIT_POS_TOKENS, VIT_DIM), "pos_embed")?,
            patch_weight: vb.get((VIT_DIM, 3, PATCH, PATCH), "patch_embed.proj.weight")?,
            patch_bias: vb.get(VIT_DIM, "patch_embed.proj.bias")?,
            blocks: (0..depth)
                .map(|i| Block::new(vb.pp("blocks").pp(i)))
                .collect::<Result<_>>()?,
            norm: LayerNorm::new(VIT_DIM, LN_EPS, vb.pp("norm"))?,
        })
    }

    /// The transformer blocks.
    pub fn blocks(&self) -> &[Block] {
        &self.blocks
    }

    /// DINO `interpolate_pos_encoding` for an input of `height × width` pixels: the table itself
    /// at 224², else the 14×14 grid resized bicubically to `(height/16) × (width/16)`.
    ///
    /// # Errors
    /// Tensor errors.
    pub fn interpolate_pos_encoding(&self, height: usize, width: usize) -> Result<Tensor> {
        let (gh, gw) = (height / PATCH, width / PATCH);
        if gh == POS_GRID && gw == POS_GRID {
            return Ok(self.pos_embed.clone());
        }
        let (dtype, device) = (self.pos_embed.dtype(), self.pos_embed.device());
        let cls = self.pos_embed.i((.., 0..1, ..))?;
        let grid = self
            .pos_embed
            .i((0, 1.., ..))?
            .reshape((POS_GRID, POS_GRID, VIT_DIM))?
            .permute((2, 0, 1))?
            .contiguous()?;
        let factor = |g: usize| (g as f64 + POS_SCALE_OFFSET) / POS_GRID as f64;
        let m_h = matrix(
            bicubic_matrix(POS_GRID, gh, factor(gh)),
            gh,
            POS_GRID,
            dtype,
            device,
        )?;
        let m_w = matrix(
            bicubic_matrix(POS_GRID, gw, factor(gw)),
            gw,
            POS_GRID,
            dtype,
            device,
        )?;
        let resized = resize_separable(&grid, &m_h, &m_w)?
            .permute((1, 2, 0))?
            .reshape((1, gh * gw, VIT_DIM))?;
        Ok(Tensor::cat(&[&cls, &resized], 1)?)
    }

    /// Patch embedding (16×16 stride-16 convolution; trailing pixels ignored), CLS token and
    /// positional embedding: `(B, 3, H, W)` → `(B, 1 + (H/16)(W/16), 384)`.
    ///
    /// # Errors
    /// Tensor errors.
    pub fn prepare_tokens(&self, x: &Tensor) -> Result<Tensor> {
        let (b, _, h, w) = x.dims4()?;
        let patches = x
            .conv2d(&self.patch_weight, 0, PATCH, 1, 1)?
            .broadcast_add(&self.patch_bias.reshape((1, VIT_DIM, 1, 1))?)?
            .flatten_from(2)?
            .transpose(1, 2)?;
        let cls = self.cls_token.broadcast_as((b, 1, VIT_DIM))?;
        let tokens = Tensor::cat(&[&cls, &patches], 1)?;
        Ok(tokens.broadcast_add(&self.interpolate_pos_encoding(h, w)?)?)
    }

    /// The CLS token after all blocks, before the final LayerNorm: `(B, 384)`.
    ///
    /// # Errors
    /// Tensor errors.
    pub fn cls_before_norm(&self, x: &Tensor) -> Result<Tensor> {
        let mut t = self.prepare_tokens(x)?;
        for block in &self.blocks {
            t = block.forward(&t)?;
        }
        Ok(t.i((.., 0, ..))?)
    }

    /// The ViT output: the final-LayerNorm'ed CLS token, `(B, 384)`.
    ///
    /// # Errors
    /// Tensor errors.
    pub fn forward(&self, x: &Tensor) -> Result<Tensor> {
        self.norm.forward(&self.cls_before_norm(x)?)
    }

    /// [`Self::forward`] of several inputs (e.g. the scales of one batch) in one pass: their
    /// tokens go through each block's linear layers as one matrix ([`Block::forward_sets`]),
    /// and the last block computes only the CLS rows it returns. Per-row results are those of
    /// separate calls up to float32 rounding (the products' blocking depends on the rows).
    ///
    /// # Errors
    /// No input, inputs that are not `(B, 3, H, W)`, tensor errors.
    pub fn forward_many(&self, inputs: &[Tensor]) -> Result<Vec<Tensor>> {
        let mut tokens = Vec::with_capacity(inputs.len());
        let mut sets = Vec::with_capacity(inputs.len());
        for x in inputs {
            let t = self.prepare_tokens(x)?;
            let (b, n, c) = t.dims3()?;
            sets.push((b, n));
            tokens.push(t.reshape((b * n, c))?);
        }
        let sets = TokenSets(sets);
        let mut t = Tensor::cat(&tokens, 0)?;
        let last = self.blocks.len().saturating_sub(1);
        for (k, block) in self.blocks.iter().enumerate() {
            t = block.forward_sets(&t, &sets, k == last)?;
        }
        if self.blocks.is_empty() {
            // Without blocks the CLS rows are picked here.
            t = sets.cls_rows(&t)?;
        }
        let out = self.norm.forward(&t)?;
        let mut start = 0;
        sets.0
            .iter()
            .map(|&(b, _)| {
                let part = out.narrow(0, start, b)?;
                start += b;
                Ok(part)
            })
            .collect()
    }
}
