//! Keypoint matches of an image pair, as the matcher produces them and the mapper consumes
//! them: coordinates in original-image OpenCV pixels and, as COLMAP's matches do, the index of
//! each keypoint in its image's keypoint list (so tracks are joined by identity, never by
//! comparing coordinates). [`TwoViewPose`]: what two-view geometry says of a pair.

use nalgebra::{Matrix3, Vector3};

/// The matches of one image pair.
#[derive(Debug, Clone, PartialEq, Default)]
pub struct PairMatches {
    /// Index of the first image.
    pub first: usize,
    /// Index of the second image.
    pub second: usize,
    /// Keypoints in the first image (pixels).
    pub kp1: Vec<[f64; 2]>,
    /// The matching keypoints in the second image.
    pub kp2: Vec<[f64; 2]>,
    /// Index of each `kp1` in the first image's keypoints.
    pub idx1: Vec<u32>,
    /// Index of each `kp2` in the second image's keypoints.
    pub idx2: Vec<u32>,
}

impl PairMatches {
    /// `count` matches between `first` and `second` with every keypoint at the origin and
    /// keypoint ids `0..count`: a pair whose count is all that matters (view-graph tests, pair
    /// strengths).
    pub fn placeholder(first: usize, second: usize, count: usize) -> Self {
        Self {
            first,
            second,
            kp1: vec![[0.0; 2]; count],
            kp2: vec![[0.0; 2]; count],
            idx1: (0..count as u32).collect(),
            idx2: (0..count as u32).collect(),
        }
    }

    /// Number of matches.
    pub fn len(&self) -> usize {
        self.kp1.len()
    }

    /// True when the pair has no match.
    pub fn is_empty(&self) -> bool {
        self.kp1.is_empty()
    }

    /// Whether the four lists have one entry per match.
    pub fn is_consistent(&self) -> bool {
        let n = self.kp1.len();
        self.kp2.len() == n && self.idx1.len() == n && self.idx2.len() == n
    }

    /// The matches `keep` (indices into the lists), in that order.
    pub fn select(&self, keep: &[usize]) -> Self {
        Self {
            first: self.first,
            second: self.second,
            kp1: keep.iter().map(|&k| self.kp1[k]).collect(),
            kp2: keep.iter().map(|&k| self.kp2[k]).collect(),
            idx1: keep.iter().map(|&k| self.idx1[k]).collect(),
            idx2: keep.iter().map(|&k| self.idx2[k]).collect(),
        }
    }
}

/// The relative pose of an ordered pair `(a, b)`: `x_b = R x_a + t`.
#[derive(Debug, Clone, Copy, PartialEq)]
pub enum TwoViewPose {
    /// A baseline was measured: unit translation.
    General {
        /// `R_b R_aᵀ`.
        rotation: Matrix3<f64>,
        /// Unit translation in camera `b`'s frame.
        translation: Vector3<f64>,
        /// Inliers in front of both cameras.
        inliers: usize,
    },
    /// The matches fit a rotation-only homography: no baseline to measure (pure rotation,
    /// identical or nearly identical images).
    RotationOnly {
        /// `R_b R_aᵀ`.
        rotation: Matrix3<f64>,
        /// Homography inliers.
        inliers: usize,
    },
}
