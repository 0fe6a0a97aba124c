//! Keypoints and descriptors through OpenCV.
//!
//! Each image is read once, as grey, and shrunk once (area interpolation) when its longer side
//! exceeds `max_image_side`. Keypoints are reported in OpenCV pixel coordinates of the
//! **original** image: the centre of the top-left pixel is `(0, 0)`. A keypoint `x` found in an
//! image shrunk by `s` maps back to `(x + 0.5)/s − 0.5` (pixel centres, not corners, scale).
//!
//! OpenCV's SIFT reports positions `0.25` px (of the image it ran on) too far right and down: it
//! detects on a 2× upsampled copy and halves coordinates without the half-pixel correction
//! (`x_up / 2` instead of `(x_up + 0.5)/2 − 0.5`). We subtract [`SIFT_UPSAMPLING_OFFSET`]; the
//! test on a synthetic blob then finds it within a few hundredths of a pixel at full and half
//! size (0.27 and 0.53 px off without the correction).

use std::path::Path;

use opencv::core::{KeyPoint, Mat, Size, Vector};
use opencv::features2d::{ORB, ORB_ScoreType, SIFT};
use opencv::prelude::*;
use posediff_geometry::ImageSize;

use crate::error::{MatchingError, Result};

/// Which OpenCV detector and descriptor.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default)]
#[cfg_attr(
    feature = "serde",
    derive(serde::Serialize, serde::Deserialize),
    serde(rename_all = "snake_case")
)]
pub enum Detector {
    /// SIFT: 128 float descriptors, L2.
    #[default]
    Sift,
    /// ORB: 256-bit binary descriptors, Hamming.
    Orb,
}

/// Feature extraction settings.
#[derive(Debug, Clone, Copy, PartialEq)]
#[cfg_attr(
    feature = "serde",
    derive(serde::Serialize, serde::Deserialize),
    serde(default, deny_unknown_fields)
)]
pub struct FeatureConfig {
    /// Detector and descriptor.
    pub detector: Detector,
    /// Keep at most this many keypoints per image (the official hloc setting: 4096).
    pub max_keypoints: usize,
    /// Shrink images whose longer side exceeds this before detection (hloc: 1600).
    pub max_image_side: u32,
    /// SIFT contrast threshold (OpenCV default 0.04; lower finds more on weak texture).
    pub contrast_threshold: f64,
}

impl Default for FeatureConfig {
    fn default() -> Self {
        Self {
            detector: Detector::Sift,
            max_keypoints: 4096,
            max_image_side: 1600,
            contrast_threshold: 0.04,
        }
    }
}

/// OpenCV's SIFT defaults besides the contrast threshold.
const SIFT_OCTAVE_LAYERS: i32 = 3;
const SIFT_EDGE_THRESHOLD: f64 = 10.0;
const SIFT_SIGMA: f64 = 1.6;
/// The offset OpenCV's SIFT adds to every coordinate (its doubled first octave), in pixels of
/// the image it ran on.
pub const SIFT_UPSAMPLING_OFFSET: f64 = 0.25;

/// OpenCV's ORB defaults.
const ORB_SCALE_FACTOR: f32 = 1.2;
const ORB_LEVELS: i32 = 8;
const ORB_EDGE_THRESHOLD: i32 = 31;
const ORB_PATCH_SIZE: i32 = 31;
const ORB_FAST_THRESHOLD: i32 = 20;

/// Descriptors of one image, row-major.
#[derive(Debug, Clone, PartialEq)]
pub enum Descriptors {
    /// `n × dim` floats (learned descriptors; SIFT values that are not whole bytes).
    Float {
        /// Values.
        data: Vec<f32>,
        /// Width.
        dim: usize,
    },
    /// `n × dim` whole values 0–255, compared by L2 like [`Self::Float`]: OpenCV's SIFT
    /// (its floats are whole numbers, the 8 bits COLMAP's database stores). A quarter of the
    /// floats' memory: 1000 video frames of 4096 keypoints hold 0.5 GB instead of 2.1 GB.
    Bytes {
        /// Values.
        data: Vec<u8>,
        /// Width.
        dim: usize,
    },
    /// `n × words` 64-bit words (ORB: 4 words = 256 bits).
    Binary {
        /// Bits.
        data: Vec<u64>,
        /// Words per descriptor.
        words: usize,
    },
}

impl Descriptors {
    /// `data` (`n × dim` floats) as [`Self::Bytes`] when every value is a whole number 0–255,
    /// else as [`Self::Float`]: the same distances either way.
    #[must_use]
    pub fn from_floats(data: Vec<f32>, dim: usize) -> Self {
        match whole_bytes(&data) {
            Some(bytes) => Self::Bytes { data: bytes, dim },
            None => Self::Float { data, dim },
        }
    }

    /// The rows as floats (a copy for [`Self::Bytes`]; binary descriptors have none).
    #[must_use]
    pub fn floats(&self) -> Option<(std::borrow::Cow<'_, [f32]>, usize)> {
        match self {
            Self::Float { data, dim } => Some((std::borrow::Cow::Borrowed(data), *dim)),
            Self::Bytes { data, dim } => Some((std::borrow::Cow::Owned(byte_floats(data)), *dim)),
            Self::Binary { .. } => None,
        }
    }

    /// Number of descriptors.
    pub fn len(&self) -> usize {
        match self {
            Self::Float { data, dim } => data.len() / (*dim).max(1),
            Self::Bytes { data, dim } => data.len() / (*dim).max(1),
            Self::Binary { data, words } => data.len() / (*words).max(1),
        }
    }

    /// True when there are none.
    pub fn is_empty(&self) -> bool {
        self.len() == 0
    }
}

/// Byte descriptor values as the floats they stand for ([`Descriptors::Bytes`]).
#[must_use]
pub fn byte_floats(v: &[u8]) -> Vec<f32> {
    v.iter().map(|&b| f32::from(b)).collect()
}

/// `v` as bytes when every value is a whole number 0–255 (OpenCV's SIFT), else `None`.
#[must_use]
pub fn whole_bytes(v: &[f32]) -> Option<Vec<u8>> {
    // The saturating cast round-trips exactly the whole numbers 0–255 (not NaN, fractions,
    // negatives or values above 255), and vectorises where `fract` is a libm call per value.
    // No short cut on the first failure: a fold over chunks of 64 vectorises.
    let bytes: Vec<u8> = v.iter().map(|&x| x as u8).collect();
    let whole = bytes.chunks(64).zip(v.chunks(64)).all(|(b, x)| {
        b.iter()
            .zip(x)
            .fold(true, |ok, (&b, &x)| ok & (f32::from(b) == x))
    });
    whole.then_some(bytes)
}

/// Keypoints and descriptors of one image.
#[derive(Debug, Clone, PartialEq)]
pub struct ImageFeatures {
    /// The original image's size.
    pub image_size: ImageSize,
    /// Keypoints, OpenCV pixel coordinates of the original image.
    pub keypoints: Vec<[f64; 2]>,
    /// One descriptor per keypoint.
    pub descriptors: Descriptors,
    /// The descriptors were computed on the image turned by 180° (a learned extractor's, which
    /// is not invariant to in-plane rotation); the keypoints are still in the original image's
    /// pixels. A learned matcher gives them its positional encoding where they lie in the
    /// turned image.
    pub half_turned: bool,
}

impl ImageFeatures {
    /// Keeps the keypoints (and their descriptors) for which `keep` holds; returns how many
    /// were dropped.
    pub fn retain(&mut self, keep: impl Fn([f64; 2]) -> bool) -> usize {
        let flags: Vec<bool> = self.keypoints.iter().map(|p| keep(*p)).collect();
        let before = self.keypoints.len();
        let mut k = 0;
        self.keypoints.retain(|_| {
            k += 1;
            flags[k - 1]
        });
        match &mut self.descriptors {
            Descriptors::Float { data, dim } => keep_rows(data, *dim, &flags),
            Descriptors::Bytes { data, dim } => keep_rows(data, *dim, &flags),
            Descriptors::Binary { data, words } => keep_rows(data, *words, &flags),
        }
        before - self.keypoints.len()
    }
}

/// Keeps the rows (of `width` values) of `data` whose flag is set.
fn keep_rows<T: Copy>(data: &mut Vec<T>, width: usize, flags: &[bool]) {
    let mut out = Vec::with_capacity(data.len());
    for (row, _) in flags.iter().enumerate().filter(|(_, f)| **f) {
        out.extend_from_slice(&data[row * width..(row + 1) * width]);
    }
    *data = out;
}

/// Maps a keypoint of an image resized by `scale = (sx, sy)` back to the original image: pixel
/// centres, not pixel corners, scale, so `x ↦ (x + 0.5)/s − 0.5`.
pub fn to_original_pixels(kp: [f64; 2], scale: [f64; 2]) -> [f64; 2] {
    [
        (kp[0] + 0.5) / scale[0] - 0.5,
        (kp[1] + 0.5) / scale[1] - 0.5,
    ]
}

/// Reads an image as grey, once.
///
/// # Errors
/// [`MatchingError::UnreadableImage`] for missing or unreadable files,
/// [`MatchingError::CorruptImage`] for broken ones ([`crate::image_check`]).
pub fn read_grey(path: &Path) -> Result<Mat> {
    crate::image_check::decode(path, opencv::imgcodecs::IMREAD_GRAYSCALE)
}

/// Detects and describes keypoints of a grey image.
///
/// # Errors
/// OpenCV errors, an invalid configuration.
pub fn extract_from_grey(grey: &Mat, config: &FeatureConfig) -> Result<ImageFeatures> {
    if config.max_keypoints == 0 || config.max_image_side == 0 {
        return Err(MatchingError::InvalidConfig(
            "max_keypoints and max_image_side must be positive",
        ));
    }
    let (w, h) = (grey.cols(), grey.rows());
    let image_size = ImageSize::new(w as u32, h as u32)
        .map_err(|_| MatchingError::InvalidConfig("empty image"))?;
    let longer = w.max(h) as f64;
    let scale = (f64::from(config.max_image_side) / longer).min(1.0);
    let shrunk;
    let input = if scale < 1.0 {
        let mut dst = Mat::default();
        let size = Size::new(
            ((w as f64) * scale).round() as i32,
            ((h as f64) * scale).round() as i32,
        );
        opencv::imgproc::resize(grey, &mut dst, size, 0.0, 0.0, opencv::imgproc::INTER_AREA)?;
        shrunk = dst;
        &shrunk
    } else {
        grey
    };
    // The exact per-axis scale of the resized image.
    let (sx, sy) = (
        f64::from(input.cols()) / f64::from(w),
        f64::from(input.rows()) / f64::from(h),
    );
    let n = i32::try_from(config.max_keypoints)
        .map_err(|_| MatchingError::InvalidConfig("max_keypoints too large"))?;
    let mut keypoints: Vector<KeyPoint> = Vector::new();
    let mut desc = Mat::default();
    let mask = Mat::default();
    match config.detector {
        Detector::Sift => {
            let mut sift = SIFT::create(
                n,
                SIFT_OCTAVE_LAYERS,
                config.contrast_threshold,
                SIFT_EDGE_THRESHOLD,
                SIFT_SIGMA,
            )?;
            sift.detect_and_compute(input, &mask, &mut keypoints, &mut desc, false)?;
        }
        Detector::Orb => {
            let mut orb = ORB::create(
                n,
                ORB_SCALE_FACTOR,
                ORB_LEVELS,
                ORB_EDGE_THRESHOLD,
                0,
                2,
                ORB_ScoreType::HARRIS_SCORE,
                ORB_PATCH_SIZE,
                ORB_FAST_THRESHOLD,
            )?;
            orb.detect_and_compute(input, &mask, &mut keypoints, &mut desc, false)?;
        }
    }
    let offset = match config.detector {
        Detector::Sift => SIFT_UPSAMPLING_OFFSET,
        Detector::Orb => 0.0,
    };
    let pts: Vec<[f64; 2]> = keypoints
        .iter()
        .map(|k| {
            let p = k.pt();
            to_original_pixels([f64::from(p.x) - offset, f64::from(p.y) - offset], [sx, sy])
        })
        .collect();
    let descriptors = if pts.is_empty() || desc.empty() {
        match config.detector {
            Detector::Sift => Descriptors::Bytes {
                data: Vec::new(),
                dim: 128,
            },
            Detector::Orb => Descriptors::Binary {
                data: Vec::new(),
                words: 4,
            },
        }
    } else {
        let desc = if desc.is_continuous() {
            desc
        } else {
            desc.try_clone()?
        };
        let cols = desc.cols() as usize;
        match config.detector {
            Detector::Sift => Descriptors::from_floats(desc.data_typed::<f32>()?.to_vec(), cols),
            Detector::Orb => {
                let bytes = desc.data_typed::<u8>()?;
                let words = cols.div_ceil(8);
                let mut data = vec![0u64; pts.len() * words];
                for (r, row) in bytes.chunks(cols).enumerate() {
                    for (b, byte) in row.iter().enumerate() {
                        data[r * words + b / 8] |= u64::from(*byte) << (8 * (b % 8));
                    }
                }
                Descriptors::Binary { data, words }
            }
        }
    };
    Ok(ImageFeatures {
        image_size,
        keypoints: pts,
        descriptors,
        half_turned: false,
    })
}

/// Reads an image and extracts its features.
///
/// # Errors
/// Unreadable images, OpenCV errors.
pub fn extract(path: &Path, config: &FeatureConfig) -> Result<ImageFeatures> {
    extract_from_grey(&read_grey(path)?, config)
}
