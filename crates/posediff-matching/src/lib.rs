//! Correspondences for geometry-guided sampling: OpenCV keypoints and descriptors, exact mutual
//! nearest-neighbour matching, optional geometric verification, all pairs in parallel.
//!
//! - [`features`]: SIFT (default) or ORB through the opencv crate; keypoints in OpenCV pixel
//!   coordinates of the original image.
//! - [`mnn`]: mutual nearest neighbours (blocked L2 products or Hamming), Lowe ratio test.
//! - [`two_view`] and [`resection`]: relative poses of pairs and absolute poses (PnP) of
//!   single cameras, for the mapper.
//! - [`match_images`]: images → features once each → matches of every requested pair, verified
//!   by OpenCV's USAC MAGSAC fundamental matrix when asked.
//!
//! The keypoints of a match are in each original image's pixels; map them into the model's
//! 224 crop with [`posediff_geometry::CenterCrop::to_model`].
#![deny(missing_docs)]
// Unsafe only in `mnn::vnni` (the AVX-512 VNNI kernel's loads and its dispatch).
#![deny(unsafe_code)]

pub mod error;
pub mod features;
pub mod image_check;
pub mod keyframes;
pub mod mask;
pub mod mnn;
pub mod pairs;
pub mod resection;
pub mod two_view;

use std::path::PathBuf;

use opencv::core::{Point2f, Vector};
use opencv::prelude::*;
use rayon::prelude::*;

pub use error::{MatchingError, Result};
pub use features::{Descriptors, Detector, FeatureConfig, ImageFeatures, extract};
pub use pairs::{AutoPairs, PairRule, PairSelection, select_pairs};
pub use two_view::{RelativePose, TwoViewConfig};

/// Geometric verification of a pair's matches.
#[derive(Debug, Clone, Copy, PartialEq)]
#[cfg_attr(
    feature = "serde",
    derive(serde::Serialize, serde::Deserialize),
    serde(default, deny_unknown_fields)
)]
pub struct Verification {
    /// Inlier threshold in pixels of the original images (OpenCV's `ransacReprojThreshold`).
    pub threshold_px: f64,
    /// RANSAC confidence.
    pub confidence: f64,
    /// Maximum iterations.
    pub max_iters: i32,
}

impl Default for Verification {
    fn default() -> Self {
        Self {
            threshold_px: 1.0,
            confidence: 0.999,
            max_iters: 10_000,
        }
    }
}

/// The fewest matches a fundamental matrix can be estimated from (eight-point; MAGSAC's
/// minimal sample is 7 but OpenCV's USAC needs more to refine).
pub const MIN_MATCHES_FOR_VERIFICATION: usize = 8;

/// Default Lowe ratio: Lowe's own 0.8. Measured on the shared sets (`cargo xtask
/// bench-matching`): 0.9 keeps more wrong matches on CO3D and Middlebury, 0.7 fewer pairs.
pub const DEFAULT_RATIO: f32 = 0.8;

/// Default minimum of verified matches per pair. On the shared sets, pairs whose MAGSAC
/// fundamental matrix has 10–19 inliers are mostly wrong (fitted to mismatches on wide
/// baselines): with no minimum 79 % of verified CO3D-apple matches lie within 4 px² of the
/// true epipolar geometry, with 20 it is 98.7 %. 20 is also above GGS's 10 matches per frame.
pub const DEFAULT_MIN_VERIFIED: usize = 20;

/// Matching settings.
#[derive(Debug, Clone, Copy, PartialEq)]
#[cfg_attr(
    feature = "serde",
    derive(serde::Serialize, serde::Deserialize),
    serde(default, deny_unknown_fields)
)]
pub struct MatchConfig {
    /// Keypoints and descriptors.
    pub features: FeatureConfig,
    /// Lowe's ratio, `None` for pure mutual nearest neighbours.
    pub ratio: Option<f32>,
    /// Keep only the inliers of a robust fundamental matrix, `None` for raw matches.
    pub verification: Option<Verification>,
    /// With verification: a pair whose inliers are fewer than this keeps no match (a
    /// fundamental matrix fitted to a handful of points is more often wrong than right).
    pub min_verified: usize,
}

impl Default for MatchConfig {
    fn default() -> Self {
        Self {
            features: FeatureConfig::default(),
            ratio: Some(DEFAULT_RATIO),
            verification: Some(Verification::default()),
            min_verified: DEFAULT_MIN_VERIFIED,
        }
    }
}

pub use posediff_geometry::PairMatches;

/// All pairs `(i, j)`, `i < j`.
pub fn exhaustive_pairs(n: usize) -> Vec<(usize, usize)> {
    (0..n)
        .flat_map(|i| (i + 1..n).map(move |j| (i, j)))
        .collect()
}

/// Robust fundamental-matrix inliers among `kp1 ↔ kp2` (indices), by OpenCV USAC MAGSAC.
///
/// # Errors
/// OpenCV errors.
pub fn verified_inliers(
    kp1: &[[f64; 2]],
    kp2: &[[f64; 2]],
    v: &Verification,
) -> Result<Vec<usize>> {
    if kp1.len() < MIN_MATCHES_FOR_VERIFICATION {
        return Ok(Vec::new());
    }
    let to_cv = |p: &[[f64; 2]]| -> Vector<Point2f> {
        p.iter()
            .map(|q| Point2f::new(q[0] as f32, q[1] as f32))
            .collect()
    };
    let (p1, p2) = (to_cv(kp1), to_cv(kp2));
    let mut mask = opencv::core::Mat::default();
    let f = opencv::calib3d::find_fundamental_mat(
        &p1,
        &p2,
        opencv::calib3d::USAC_MAGSAC,
        v.threshold_px,
        v.confidence,
        v.max_iters,
        &mut mask,
    )?;
    if f.empty() || mask.empty() {
        return Ok(Vec::new());
    }
    let flags = mask.data_typed::<u8>()?;
    Ok(flags
        .iter()
        .enumerate()
        .filter(|(_, m)| **m != 0)
        .map(|(i, _)| i)
        .collect())
}

/// Matches one pair of extracted images.
///
/// # Errors
/// OpenCV errors in verification.
pub fn match_pair(
    a: &ImageFeatures,
    b: &ImageFeatures,
    first: usize,
    second: usize,
    config: &MatchConfig,
) -> Result<PairMatches> {
    verify(mnn_matches(a, b, first, second, config), config)
}

/// The mutual nearest neighbours of two images' descriptors (with `config`'s ratio test) as
/// matches before verification: what [`match_pair`] verifies.
fn mnn_matches(
    a: &ImageFeatures,
    b: &ImageFeatures,
    first: usize,
    second: usize,
    config: &MatchConfig,
) -> PairMatches {
    let idx = mnn::mutual_nearest_neighbours(&a.descriptors, &b.descriptors, config.ratio);
    raw_matches(a, b, first, second, &idx)
}

/// The matches `idx` (keypoint index in `a`, in `b`) of images `first` and `second` with their
/// positions and keypoint ids, before any verification.
pub fn raw_matches(
    a: &ImageFeatures,
    b: &ImageFeatures,
    first: usize,
    second: usize,
    idx: &[(usize, usize)],
) -> PairMatches {
    PairMatches {
        first,
        second,
        kp1: idx.iter().map(|&(i, _)| a.keypoints[i]).collect(),
        kp2: idx.iter().map(|&(_, j)| b.keypoints[j]).collect(),
        idx1: idx.iter().map(|&(i, _)| keypoint_id(i)).collect(),
        idx2: idx.iter().map(|&(_, j)| keypoint_id(j)).collect(),
    }
}

/// The verification of `config` on a pair's raw matches: the MAGSAC inliers, or none when
/// they are fewer than `config.min_verified`; the raw matches without verification.
///
/// # Errors
/// OpenCV errors.
pub fn verify(raw: PairMatches, config: &MatchConfig) -> Result<PairMatches> {
    let Some(v) = &config.verification else {
        return Ok(raw);
    };
    let mut keep = verified_inliers(&raw.kp1, &raw.kp2, v)?;
    if keep.len() < config.min_verified {
        keep.clear();
    }
    Ok(raw.select(&keep))
}

/// A keypoint index as stored in [`PairMatches`] (at most `u32::MAX` keypoints per image; the
/// extractor keeps far fewer).
fn keypoint_id(i: usize) -> u32 {
    u32::try_from(i).unwrap_or(u32::MAX)
}

/// Extracts features of every image once (in parallel), then matches the given pairs (all
/// `i < j` when `pairs` is `None`) in parallel.
///
/// # Errors
/// Fewer than two images, unreadable images (named), invalid pairs, OpenCV errors.
pub fn match_images(
    images: &[PathBuf],
    pairs: Option<&[(usize, usize)]>,
    config: &MatchConfig,
) -> Result<(Vec<ImageFeatures>, Vec<PairMatches>)> {
    let pairs: Vec<(usize, usize)> = match pairs {
        Some(p) => p.to_vec(),
        None => exhaustive_pairs(images.len()),
    };
    // The cheap check before the extraction.
    check_pairs(images.len(), &pairs)?;
    let features = extract_all(images, config)?;
    let matches = match_pairs(&features, &pairs, config)?;
    Ok((features, matches))
}

/// Features of every image (in parallel).
///
/// # Errors
/// Fewer than two images, unreadable images (named), OpenCV errors.
pub fn extract_all(images: &[PathBuf], config: &MatchConfig) -> Result<Vec<ImageFeatures>> {
    if images.len() < 2 {
        return Err(MatchingError::TooFewImages { got: images.len() });
    }
    images
        .par_iter()
        .map(|p| extract(p, &config.features))
        .collect()
}

/// Matches `pairs` of extracted images in parallel.
///
/// # Errors
/// Invalid pairs, OpenCV errors.
pub fn match_pairs(
    features: &[ImageFeatures],
    pairs: &[(usize, usize)],
    config: &MatchConfig,
) -> Result<Vec<PairMatches>> {
    check_pairs(features.len(), pairs)?;
    pairs
        .par_iter()
        .map(|&(i, j)| match_pair(&features[i], &features[j], i, j, config))
        .collect()
}

/// [`match_pairs`] with each pair's matches before verification beside the verified ones
/// (`(raw, verified)`; COLMAP keeps both: its `matches` and `two_view_geometries` tables).
///
/// # Errors
/// As [`match_pairs`].
pub fn match_pairs_with_raw(
    features: &[ImageFeatures],
    pairs: &[(usize, usize)],
    config: &MatchConfig,
) -> Result<Vec<(PairMatches, PairMatches)>> {
    check_pairs(features.len(), pairs)?;
    pairs
        .par_iter()
        .map(|&(i, j)| {
            let raw = mnn_matches(&features[i], &features[j], i, j, config);
            let verified = verify(raw.clone(), config)?;
            Ok((raw, verified))
        })
        .collect()
}

/// Every pair names two different images of `n`.
///
/// # Errors
/// [`MatchingError::InvalidPair`] naming the first that does not.
pub fn check_pairs(n: usize, pairs: &[(usize, usize)]) -> Result<()> {
    match pairs.iter().find(|&&(a, b)| a >= n || b >= n || a == b) {
        Some(&(first, second)) => Err(MatchingError::InvalidPair {
            first,
            second,
            n_images: n,
        }),
        None => Ok(()),
    }
}
