//! torchvision's `deform_conv2d` for the case ALIKED uses: a 3×3 kernel, stride 1, padding 1,
//! dilation 1, one offset group, no mask. Each output pixel samples its 9 taps at the regular
//! positions plus learned offsets (channel `2k` is the row offset of tap `k = 3i + j`,
//! `2k + 1` the column offset), bilinearly with zeros outside; the sampled columns are then one
//! matrix product with the weights (im2col, as torchvision's CPU kernel).

use candle_core::Tensor;
use rayon::prelude::*;

use crate::error::Result;
use crate::sampling::Tap;

/// `deform_conv2d(x, offsets, weight, padding=1)` for `x` `(1, C, H, W)`, `offsets`
/// `(1, 18, H, W)` and `weight` `(O, C, 3, 3)`; returns `(1, O, H, W)` on `x`'s device.
///
/// # Errors
/// Shape mismatches, tensor errors.
pub fn deform_conv3x3(x: &Tensor, offsets: &Tensor, weight: &Tensor) -> Result<Tensor> {
    let (_, c, h, w) = x.dims4()?;
    let (o, _, _, _) = weight.dims4()?;
    let plane = h * w;
    let xs = x.flatten_all()?.to_vec1::<f32>()?;
    let off = offsets.flatten_all()?.to_vec1::<f32>()?;
    if off.len() != 18 * plane {
        return Err(candle_core::Error::Msg(format!(
            "deformable conv: {} offset values for a {h}x{w} map (need 18 per pixel)",
            off.len()
        ))
        .into());
    }
    // The taps of every (kernel position, output pixel), shared by all channels.
    let taps: Vec<Tap> = (0..9 * plane)
        .into_par_iter()
        .map(|kp| {
            let (k, p) = (kp / plane, kp % plane);
            let (i, j) = (k / 3, k % 3);
            let (py, px) = (p / w, p % w);
            let dy = off[2 * k * plane + p];
            let dx = off[(2 * k + 1) * plane + p];
            let y = py as f32 - 1.0 + i as f32 + dy;
            let xx = px as f32 - 1.0 + j as f32 + dx;
            Tap::new(xx, y, w, h)
        })
        .collect();
    // Columns (C·9, H·W), rows ordered (channel, tap) as the weight's (C, 3, 3).
    let mut cols = vec![0f32; c * 9 * plane];
    cols.par_chunks_mut(9 * plane)
        .enumerate()
        .for_each(|(ch, rows)| {
            let src = &xs[ch * plane..(ch + 1) * plane];
            for (dst, tap) in rows.iter_mut().zip(&taps) {
                *dst = tap.sample(src);
            }
        });
    let cols = Tensor::from_vec(cols, (c * 9, plane), x.device())?;
    let y = weight.reshape((o, c * 9))?.matmul(&cols)?;
    Ok(y.reshape((1, o, h, w))?)
}

#[cfg(test)]
mod tests {
    use candle_core::{Device, Tensor};

    use super::*;

    /// With zero offsets the deformable convolution is the plain one (padding 1).
    #[test]
    fn zero_offsets_give_the_plain_convolution() -> anyhow::Result<()> {
        let dev = Device::Cpu;
        let x = Tensor::randn(0f32, 1.0, (1, 3, 5, 7), &dev)?;
        let wt = Tensor::randn(0f32, 1.0, (4, 3, 3, 3), &dev)?;
        let off = Tensor::zeros((1, 18, 5, 7), candle_core::DType::F32, &dev)?;
        let a = deform_conv3x3(&x, &off, &wt)?
            .flatten_all()?
            .to_vec1::<f32>()?;
        let b = x.conv2d(&wt, 1, 1, 1, 1)?.flatten_all()?.to_vec1::<f32>()?;
        for (p, q) in a.iter().zip(&b) {
            assert!((p - q).abs() < 1e-5, "{p} vs {q}");
        }
        Ok(())
    }

    /// An integer offset of +1 column on every tap shifts the input one pixel left (away from
    /// the left edge, where the plain convolution of the shifted input sees padding instead
    /// of the first column).
    #[test]
    fn integer_offsets_shift_the_sampling_grid() -> anyhow::Result<()> {
        let dev = Device::Cpu;
        let x = Tensor::randn(0f32, 1.0, (1, 2, 4, 6), &dev)?;
        let wt = Tensor::randn(0f32, 1.0, (3, 2, 3, 3), &dev)?;
        let mut off = vec![0f32; 18 * 24];
        for k in 0..9 {
            off[(2 * k + 1) * 24..(2 * k + 2) * 24].fill(1.0);
        }
        let off = Tensor::from_vec(off, (1, 18, 4, 6), &dev)?;
        let a = deform_conv3x3(&x, &off, &wt)?;
        // x shifted by one column (zero entering on the right), then the plain convolution.
        let shifted = Tensor::cat(
            &[
                x.narrow(3, 1, 5)?,
                Tensor::zeros((1, 2, 4, 1), x.dtype(), &dev)?,
            ],
            3,
        )?;
        let b = shifted.conv2d(&wt, 1, 1, 1, 1)?;
        let (a, b) = (
            a.flatten_all()?.to_vec1::<f32>()?,
            b.flatten_all()?.to_vec1::<f32>()?,
        );
        for (k, (p, q)) in a.iter().zip(&b).enumerate() {
            if k % 6 != 0 {
                assert!((p - q).abs() < 1e-5, "{k}: {p} vs {q}");
            }
        }
        Ok(())
    }
}
