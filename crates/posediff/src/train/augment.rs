//! The official training augmentation (SPEC.md §7.2, `datasets/co3d_v2.py`): a jittered centre
//! square (scale U[0.8, 1.2], shift U[−0.07, 0.07]·side, integer box, zero padding outside the
//! image) resized to 224 with the camera adjusted alike, and colour jitter
//! (`ColorJitter(0.4, 0.4, 0.2, 0.1)` with p = 0.65, `RandomGrayscale` p = 0.15) drawn once per
//! sequence and applied to all its frames.
//!
//! Differences from torchvision, none of which the ground truth depends on: the resize is
//! bilinear with 2×2 supersampling (torchvision: antialiased bilinear), and the colour
//! operations run in a fixed order (brightness, contrast, saturation, hue) rather than a random
//! permutation; the hue shift rotates chroma in YIQ space.

use posediff_geometry::{Camera, ImageSize, Intrinsics};
use rand::Rng;
use rand::rngs::StdRng;

use crate::error::Result;

/// Augmentation settings; `Default` is the official training configuration.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct AugmentConfig {
    /// Range of the square's scale factor.
    pub scale: (f64, f64),
    /// Largest shift as a fraction of the side.
    pub shift: f64,
    /// Probability of colour jitter.
    pub jitter_p: f64,
    /// Brightness, contrast, saturation factor spreads and the hue spread.
    pub brightness: f64,
    /// Contrast spread.
    pub contrast: f64,
    /// Saturation spread.
    pub saturation: f64,
    /// Hue spread (fraction of the hue circle).
    pub hue: f64,
    /// Probability of greyscale.
    pub grey_p: f64,
}

impl Default for AugmentConfig {
    fn default() -> Self {
        Self {
            scale: (0.8, 1.2),
            shift: 0.07,
            jitter_p: 0.65,
            brightness: 0.4,
            contrast: 0.4,
            saturation: 0.2,
            hue: 0.1,
            grey_p: 0.15,
        }
    }
}

/// A square crop in original pixels (may extend past the image).
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct SquareCrop {
    /// Left edge.
    pub left: i64,
    /// Top edge.
    pub top: i64,
    /// Side.
    pub side: u32,
}

/// The official jittered centre square of an image.
pub fn jittered_crop(size: ImageSize, config: &AugmentConfig, rng: &mut StdRng) -> SquareCrop {
    let (w, h) = (f64::from(size.width()), f64::from(size.height()));
    let m = w.min(h);
    let side = (m * rng.random_range(config.scale.0..=config.scale.1))
        .round()
        .max(1.0);
    let dx = rng.random_range(-config.shift..=config.shift) * side;
    let dy = rng.random_range(-config.shift..=config.shift) * side;
    SquareCrop {
        left: (w / 2.0 + dx - side / 2.0).round() as i64,
        top: (h / 2.0 + dy - side / 2.0).round() as i64,
        side: side as u32,
    }
}

/// The camera of the crop resized to `target` (OpenCV pixel centres: `u' = (u − left + ½)·s − ½`).
///
/// # Errors
/// A degenerate crop.
pub fn crop_camera(camera: &Camera, crop: &SquareCrop, target: u32) -> Result<Camera> {
    let s = f64::from(target) / f64::from(crop.side);
    let k = &camera.intrinsics;
    let intrinsics = Intrinsics::new(
        k.fx() * s,
        k.fy() * s,
        (k.cx() - crop.left as f64 + 0.5) * s - 0.5,
        (k.cy() - crop.top as f64 + 0.5) * s - 0.5,
    )?;
    Ok(Camera::new(
        intrinsics,
        camera.cam_from_world,
        ImageSize::new(target, target)?,
    ))
}

/// `3 × target × target` RGB in `[0, 1]` (channel-major) of the crop of `rgb` (`size`, 8-bit,
/// interleaved), zeros outside the image.
pub fn crop_and_resize(rgb: &[u8], size: ImageSize, crop: &SquareCrop, target: u32) -> Vec<f32> {
    let (w, h) = (size.width() as i64, size.height() as i64);
    let t = target as usize;
    let s = f64::from(crop.side) / f64::from(target);
    let sample = |x: f64, y: f64, c: usize| -> f64 {
        // Bilinear at source coordinates (pixel centres at integers), zero outside.
        let (x0, y0) = (x.floor(), y.floor());
        let (fx, fy) = (x - x0, y - y0);
        let mut acc = 0.0;
        for (dy, wy) in [(0i64, 1.0 - fy), (1, fy)] {
            for (dx, wx) in [(0i64, 1.0 - fx), (1, fx)] {
                let (xi, yi) = (x0 as i64 + dx, y0 as i64 + dy);
                if (0..w).contains(&xi) && (0..h).contains(&yi) {
                    acc += wx * wy * f64::from(rgb[((yi * w + xi) as usize) * 3 + c]);
                }
            }
        }
        acc / 255.0
    };
    let mut out = vec![0f32; 3 * t * t];
    for r in 0..t {
        for col in 0..t {
            for c in 0..3 {
                let mut v = 0.0;
                for (oy, ox) in [(0.25, 0.25), (0.25, 0.75), (0.75, 0.25), (0.75, 0.75)] {
                    let x = crop.left as f64 + (col as f64 + ox) * s - 0.5;
                    let y = crop.top as f64 + (r as f64 + oy) * s - 0.5;
                    v += sample(x, y, c);
                }
                out[(c * t + r) * t + col] = (v / 4.0) as f32;
            }
        }
    }
    out
}

/// Colour changes drawn once per sequence.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct SequenceColour {
    /// `None`: no jitter; else brightness, contrast, saturation factors and the hue shift.
    pub jitter: Option<[f64; 4]>,
    /// Convert to greyscale.
    pub grey: bool,
}

impl SequenceColour {
    /// Draws the sequence's colour changes.
    pub fn draw(config: &AugmentConfig, rng: &mut StdRng) -> Self {
        let spread = |rng: &mut StdRng, a: f64| rng.random_range((1.0 - a).max(0.0)..=1.0 + a);
        let jitter = (rng.random::<f64>() < config.jitter_p).then(|| {
            [
                spread(rng, config.brightness),
                spread(rng, config.contrast),
                spread(rng, config.saturation),
                rng.random_range(-config.hue..=config.hue),
            ]
        });
        Self {
            jitter,
            grey: rng.random::<f64>() < config.grey_p,
        }
    }

    /// Applies the changes to `3 × n` channel-major pixels in `[0, 1]`.
    pub fn apply(&self, chw: &mut [f32]) {
        let n = chw.len() / 3;
        let grey_of = |r: f64, g: f64, b: f64| 0.299 * r + 0.587 * g + 0.114 * b;
        if let Some([bright, contrast, saturation, hue]) = self.jitter {
            let mean = (0..n)
                .map(|i| {
                    grey_of(
                        f64::from(chw[i]),
                        f64::from(chw[n + i]),
                        f64::from(chw[2 * n + i]),
                    )
                })
                .sum::<f64>()
                / n.max(1) as f64
                * bright;
            let (sin, cos) = (std::f64::consts::TAU * hue).sin_cos();
            for i in 0..n {
                let mut p = [chw[i], chw[n + i], chw[2 * n + i]]
                    .map(|v| (f64::from(v) * bright).clamp(0.0, 1.0));
                p = p.map(|v| (mean + (v - mean) * contrast).clamp(0.0, 1.0));
                let g = grey_of(p[0], p[1], p[2]);
                p = p.map(|v| (g + (v - g) * saturation).clamp(0.0, 1.0));
                // Hue: rotate the chroma (I, Q) of YIQ.
                let y = grey_of(p[0], p[1], p[2]);
                let i_ = 0.596 * p[0] - 0.274 * p[1] - 0.322 * p[2];
                let q_ = 0.211 * p[0] - 0.523 * p[1] + 0.312 * p[2];
                let (i2, q2) = (i_ * cos - q_ * sin, i_ * sin + q_ * cos);
                p = [
                    y + 0.956 * i2 + 0.621 * q2,
                    y - 0.272 * i2 - 0.647 * q2,
                    y - 1.106 * i2 + 1.703 * q2,
                ]
                .map(|v| v.clamp(0.0, 1.0));
                for (c, v) in p.iter().enumerate() {
                    chw[c * n + i] = *v as f32;
                }
            }
        }
        if self.grey {
            for i in 0..n {
                let g = grey_of(
                    f64::from(chw[i]),
                    f64::from(chw[n + i]),
                    f64::from(chw[2 * n + i]),
                ) as f32;
                chw[i] = g;
                chw[n + i] = g;
                chw[2 * n + i] = g;
            }
        }
    }
}

#[cfg(test)]
mod tests {
    #![allow(clippy::unwrap_used)]
    use super::*;
    use nalgebra::{Matrix3, Point3, Vector3};
    use posediff_geometry::Pose;
    use rand::SeedableRng;

    #[test]
    fn the_crop_camera_sees_points_where_the_crop_shows_them() {
        let size = ImageSize::new(320, 240).unwrap();
        let cam = Camera::new(
            Intrinsics::new(300.0, 300.0, 159.5, 119.5).unwrap(),
            Pose::new(Matrix3::identity(), Vector3::zeros()),
            size,
        );
        let mut rng = StdRng::seed_from_u64(3);
        for _ in 0..20 {
            let crop = jittered_crop(size, &AugmentConfig::default(), &mut rng);
            assert!((192..=288).contains(&crop.side), "{crop:?}");
            let c224 = crop_camera(&cam, &crop, 224).unwrap();
            let x = Point3::new(0.3, -0.2, 2.0);
            let (p, q) = (cam.project(&x).unwrap(), c224.project(&x).unwrap());
            let s = 224.0 / f64::from(crop.side);
            assert!((q.x - ((p.x - crop.left as f64 + 0.5) * s - 0.5)).abs() < 1e-9);
            assert!((q.y - ((p.y - crop.top as f64 + 0.5) * s - 0.5)).abs() < 1e-9);
        }
    }

    #[test]
    fn resizing_keeps_a_pixel_where_the_camera_says() {
        // A bright dot at (100, 60) in an otherwise black image lands at its mapped position.
        let size = ImageSize::new(200, 120).unwrap();
        let mut rgb = vec![0u8; 200 * 120 * 3];
        for y in 58..=62 {
            for x in 98..=102 {
                rgb[(y * 200 + x) * 3] = 255;
            }
        }
        let crop = SquareCrop {
            left: 20,
            top: -40,
            side: 200,
        };
        let out = crop_and_resize(&rgb, size, &crop, 100);
        let s: f64 = 0.5;
        let (u, v) = (
            (100.0 - 20.0 + 0.5) * s - 0.5,
            (60.0 + 40.0 + 0.5) * s - 0.5,
        );
        assert!(out[(v.round() as usize) * 100 + u.round() as usize] > 0.9);
        // Outside the image: zero padding (top rows).
        assert_eq!(out[0], 0.0);
    }

    #[test]
    fn greyscale_makes_channels_equal_and_jitter_stays_in_range() {
        let mut px = vec![0.2f32, 0.9, 0.5, 0.1, 0.4, 0.8];
        SequenceColour {
            jitter: Some([1.3, 0.7, 1.2, 0.05]),
            grey: true,
        }
        .apply(&mut px);
        assert!(px.iter().all(|v| (0.0..=1.0).contains(v)));
        assert_eq!(px[0], px[2]);
        assert_eq!(px[2], px[4]);
    }
}
