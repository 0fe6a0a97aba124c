//! A `k × k` convolution, stride 1, zero padding, for one F32 image on the CPU: im2col in bands
//! of output rows (each patch row a shifted copy of an input row) and one faer product per band
//! (its kernel chosen at run time: AVX-512 where the CPU has it). ALIKED's full-resolution
//! 3×3 convolutions; candle's `conv2d` copies its im2col element by element, which was a fifth
//! of an ALIKED + LightGlue run on a 2-core host.

use faer::{Accum, MatMut, MatRef, Par};
use rayon::prelude::*;

/// Patch-matrix elements one band holds at most (4 MiB of F32).
const BAND: usize = 1 << 20;

/// `weight ∗ x` for `x` `(c, h, w)` and `weight` `(o, c, k, k)`, both row-major, with `pad`
/// zeros on every side and stride 1: `(o, h + 2·pad − k + 1, w + 2·pad − k + 1)`, row-major,
/// and that shape's `(height, width)`. No bias.
///
/// # Errors
/// Buffers that do not match the shape, a kernel larger than the padded input.
pub fn conv2d(
    x: &[f32],
    (c, h, w): (usize, usize, usize),
    weight: &[f32],
    (o, k): (usize, usize),
    pad: usize,
) -> Result<(Vec<f32>, (usize, usize)), String> {
    if x.len() != c * h * w || weight.len() != o * c * k * k {
        return Err(format!(
            "conv2d: {} input values for {c}×{h}×{w}, {} weights for {o}×{c}×{k}×{k}",
            x.len(),
            weight.len()
        ));
    }
    if k == 0 || h + 2 * pad < k || w + 2 * pad < k {
        return Err(format!(
            "conv2d: a {k}×{k} kernel on a {h}×{w} input padded by {pad}"
        ));
    }
    let (oh, ow) = (h + 2 * pad + 1 - k, w + 2 * pad + 1 - k);
    let depth = c * k * k;
    let rows = (BAND / (depth * ow).max(1)).clamp(1, oh);
    // Wᵀ as faer sees the row-major (o, c·k·k) weight: column-major (c·k·k) × o.
    let wt = MatRef::from_column_major_slice(weight, depth, o);
    let plane = oh * ow;
    let mut y = vec![0f32; o * plane];
    // Each band's rows of every output channel: `segments[band][channel]`.
    let mut segments: Vec<Vec<&mut [f32]>> = (0..oh.div_ceil(rows)).map(|_| Vec::new()).collect();
    for out_plane in y.chunks_mut(plane) {
        for (band, seg) in out_plane.chunks_mut(rows * ow).enumerate() {
            segments[band].push(seg);
        }
    }
    segments
        .into_par_iter()
        .enumerate()
        // The patch matrix and the product are reused from band to band of a worker (cleared
        // and zero-filled, not allocated and page-faulted anew).
        .for_each_init(
            || (Vec::new(), Vec::new()),
            |(cols, out): &mut (Vec<f32>, Vec<f32>), (band, mut dst)| {
                let y0 = band * rows;
                let len = rows.min(oh - y0);
                let pixels = len * ow;
                // Patch matrix, row-major (c·k·k) × pixels: row (ch, ky, kx) holds input channel
                // ch shifted by (ky − pad, kx − pad), zeros outside.
                cols.clear();
                cols.resize(depth * pixels, 0.0);
                for (r, dst) in cols.chunks_exact_mut(pixels).enumerate() {
                    let (ch, ky, kx) = (r / (k * k), (r / k) % k, r % k);
                    let plane = &x[ch * h * w..(ch + 1) * h * w];
                    // Output column xo reads input column xo + kx − pad.
                    let lo = pad.saturating_sub(kx);
                    let hi = (w + pad).saturating_sub(kx).min(ow);
                    for (yy, out_row) in dst.chunks_exact_mut(ow).enumerate() {
                        let sy = (y0 + yy + ky).wrapping_sub(pad);
                        if sy >= h || lo >= hi {
                            continue;
                        }
                        let src = &plane[sy * w..(sy + 1) * w];
                        out_row[lo..hi].copy_from_slice(&src[lo + kx - pad..hi + kx - pad]);
                    }
                }
                // Output (o × pixels) row-major = column-major pixels × o = colsᵀ · Wᵀ.
                out.resize(o * pixels, 0.0);
                let out = &mut out[..o * pixels];
                let lhs = MatRef::from_column_major_slice(cols, pixels, depth);
                let prod = MatMut::from_column_major_slice_mut(out, pixels, o);
                faer::linalg::matmul::matmul(prod, Accum::Replace, lhs, wt, 1.0f32, Par::Seq);
                for (seg, row) in dst.iter_mut().zip(out.chunks_exact(pixels)) {
                    seg.copy_from_slice(row);
                }
            },
        );
    Ok((y, (oh, ow)))
}

/// [`conv2d`] as a candle op on a contiguous `(1, c, h, w)` F32 CPU tensor, which it reads in
/// place (no copy of a full-resolution input); the weights are kept row-major on the host.
#[derive(Debug, Clone)]
pub(crate) struct Conv2dOp {
    /// `(o, c, k, k)` row-major.
    pub weight: Vec<f32>,
    /// Output channels.
    pub out: usize,
    /// Kernel side.
    pub kernel: usize,
    /// Zero padding on every side.
    pub pad: usize,
}

impl candle_core::CustomOp1 for Conv2dOp {
    fn name(&self) -> &'static str {
        "conv2d-f32-bands"
    }

    fn cpu_fwd(
        &self,
        storage: &candle_core::CpuStorage,
        layout: &candle_core::Layout,
    ) -> candle_core::Result<(candle_core::CpuStorage, candle_core::Shape)> {
        let (candle_core::CpuStorage::F32(data), Some((start, end))) =
            (storage, layout.contiguous_offsets())
        else {
            candle_core::bail!("conv2d-f32-bands takes a contiguous F32 tensor");
        };
        let (b, c, h, w) = layout.shape().dims4()?;
        if b != 1 {
            candle_core::bail!("conv2d-f32-bands takes one image, got {b}");
        }
        let (y, (oh, ow)) = conv2d(
            &data[start..end],
            (c, h, w),
            &self.weight,
            (self.out, self.kernel),
            self.pad,
        )
        .map_err(candle_core::Error::Msg)?;
        Ok((
            candle_core::CpuStorage::F32(y),
            candle_core::Shape::from((1, self.out, oh, ow)),
        ))
    }
}

#[cfg(test)]
mod tests {
    use candle_core::{DType, Device, Tensor};

    use super::*;

    /// Against candle's `conv2d` in F64 for ALIKED's shapes (3×3, padding 1; several bands at
    /// full width) and odd ones (1×1, 5×5 with padding 2, no padding, one channel out, an
    /// input narrower than the kernel's reach).
    #[test]
    fn matches_candles_convolution() -> anyhow::Result<()> {
        for (c, h, w, o, k, pad) in [
            (16, 70, 513, 16, 3, 1),
            (3, 9, 11, 5, 3, 1),
            (4, 6, 5, 1, 3, 1),
            (2, 7, 8, 3, 1, 0),
            (3, 6, 9, 2, 5, 2),
            (2, 5, 6, 3, 3, 0),
            (1, 2, 1, 2, 3, 1),
        ] {
            let x = Tensor::randn(0f32, 1.0, (1, c, h, w), &Device::Cpu)?;
            let wt = Tensor::randn(0f32, 0.3, (o, c, k, k), &Device::Cpu)?;
            let (ours, (oh, ow)) = conv2d(
                &x.flatten_all()?.to_vec1()?,
                (c, h, w),
                &wt.flatten_all()?.to_vec1()?,
                (o, k),
                pad,
            )
            .map_err(anyhow::Error::msg)?;
            let truth = x
                .to_dtype(DType::F64)?
                .conv2d(&wt.to_dtype(DType::F64)?, pad, 1, 1, 1)?;
            assert_eq!(truth.dims(), &[1, o, oh, ow]);
            let truth = truth.flatten_all()?.to_vec1::<f64>()?;
            assert_eq!(ours.len(), truth.len());
            let err = ours
                .iter()
                .zip(&truth)
                .map(|(a, b)| (f64::from(*a) - b).abs())
                .fold(0f64, f64::max);
            assert!(err < 1e-4, "{c}×{h}×{w} → {o}, {k}×{k} pad {pad}: {err:e}");
        }
        Ok(())
    }

    /// Mismatched buffers and a kernel that does not fit are errors, not panics.
    #[test]
    fn bad_shapes_are_errors() {
        assert!(conv2d(&[0.0; 5], (1, 2, 3), &[0.0; 9], (1, 3), 1).is_err());
        assert!(conv2d(&[0.0; 4], (1, 2, 2), &[0.0; 25], (1, 5), 0).is_err());
    }
}
