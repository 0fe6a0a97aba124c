//! Correspondences for GGS, grouped by ordered frame pair in structure-of-arrays layout.
//!
//! Keypoints are pixel coordinates of the image the model saw (the 224×224 centre crop in the
//! official pipeline), OpenCV convention. A match `(kp1, kp2, (i, j))` says `kp1` in frame `i`
//! and `kp2` in frame `j` see the same point; its Sampson error is taken under
//! `F_{j←i}` (`kp2ᵀ F kp1 = 0`). Both directions of a pair may occur; each is its own group.

use crate::error::{GuidanceError, Result};

/// One ordered frame pair and the range of its matches in the [`MatchSet`] arrays.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct PairGroup {
    /// Frame of `kp1`.
    pub first: usize,
    /// Frame of `kp2`.
    pub second: usize,
    /// Start of the pair's matches in the arrays.
    pub start: usize,
    /// End (exclusive).
    pub end: usize,
}

/// Matches grouped by ordered pair, coordinates as separate arrays (`u1, v1, u2, v2`).
#[derive(Debug, Clone, PartialEq)]
pub struct MatchSet {
    n_frames: usize,
    groups: Vec<PairGroup>,
    /// x of `kp1`, grouped.
    pub(crate) u1: Vec<f64>,
    /// y of `kp1`, grouped.
    pub(crate) v1: Vec<f64>,
    /// x of `kp2`, grouped.
    pub(crate) u2: Vec<f64>,
    /// y of `kp2`, grouped.
    pub(crate) v2: Vec<f64>,
    /// Position in the caller's order of each grouped match.
    original_index: Vec<usize>,
}

impl MatchSet {
    /// Groups matches given as parallel lists (the official `kp1`, `kp2`, `i12`).
    ///
    /// # Errors
    /// Lists of different lengths, fewer than two frames, frame indices out of range, a frame
    /// matched with itself, non-finite coordinates.
    pub fn new(
        n_frames: usize,
        kp1: &[[f64; 2]],
        kp2: &[[f64; 2]],
        frames: &[(usize, usize)],
    ) -> Result<Self> {
        if n_frames < 2 {
            return Err(GuidanceError::TooFewFrames {
                needed: 2,
                got: n_frames,
            });
        }
        for (what, len) in [("kp2", kp2.len()), ("frame pairs", frames.len())] {
            if len != kp1.len() {
                return Err(GuidanceError::LengthMismatch {
                    what,
                    left: kp1.len(),
                    right: len,
                });
            }
        }
        for (index, &(i, j)) in frames.iter().enumerate() {
            for frame in [i, j] {
                if frame >= n_frames {
                    return Err(GuidanceError::FrameOutOfRange {
                        index,
                        frame,
                        n_frames,
                    });
                }
            }
            if i == j {
                return Err(GuidanceError::SelfMatch { index, frame: i });
            }
        }
        if !kp1.iter().chain(kp2).flatten().all(|v| v.is_finite()) {
            return Err(GuidanceError::NonFinite {
                what: "keypoint coordinates",
            });
        }
        // Stable order: by pair index i·N + j (the official `pair_idx`), then input order.
        let mut order: Vec<usize> = (0..kp1.len()).collect();
        order.sort_by_key(|&k| frames[k].0 * n_frames + frames[k].1);
        let mut groups: Vec<PairGroup> = Vec::new();
        for (pos, &k) in order.iter().enumerate() {
            let (i, j) = frames[k];
            match groups.last_mut() {
                Some(g) if g.first == i && g.second == j => g.end = pos + 1,
                _ => groups.push(PairGroup {
                    first: i,
                    second: j,
                    start: pos,
                    end: pos + 1,
                }),
            }
        }
        Ok(Self {
            n_frames,
            groups,
            u1: order.iter().map(|&k| kp1[k][0]).collect(),
            v1: order.iter().map(|&k| kp1[k][1]).collect(),
            u2: order.iter().map(|&k| kp2[k][0]).collect(),
            v2: order.iter().map(|&k| kp2[k][1]).collect(),
            original_index: order,
        })
    }

    /// Number of frames the matches refer to.
    pub fn n_frames(&self) -> usize {
        self.n_frames
    }

    /// Total number of matches.
    pub fn len(&self) -> usize {
        self.u1.len()
    }

    /// True when there are no matches (GGS then has nothing to do).
    pub fn is_empty(&self) -> bool {
        self.u1.is_empty()
    }

    /// The ordered pairs that have matches.
    pub fn groups(&self) -> &[PairGroup] {
        &self.groups
    }

    /// For each grouped match, its index in the caller's order.
    pub fn original_index(&self) -> &[usize] {
        &self.original_index
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn groups_by_ordered_pair_and_remembers_the_order() {
        let kp = [[1.0, 2.0], [3.0, 4.0], [5.0, 6.0], [7.0, 8.0]];
        let frames = [(1, 0), (0, 1), (1, 0), (0, 2)];
        let m = MatchSet::new(3, &kp, &kp, &frames).unwrap();
        let pairs: Vec<(usize, usize, usize)> = m
            .groups()
            .iter()
            .map(|g| (g.first, g.second, g.end - g.start))
            .collect();
        assert_eq!(pairs, vec![(0, 1, 1), (0, 2, 1), (1, 0, 2)]);
        assert_eq!(m.original_index(), &[1, 3, 0, 2]);
        assert_eq!(m.u1, vec![3.0, 7.0, 1.0, 5.0]);
    }

    #[test]
    fn bad_matches_are_errors() {
        let kp = [[1.0, 2.0]];
        assert!(matches!(
            MatchSet::new(2, &kp, &kp, &[(0, 2)]),
            Err(GuidanceError::FrameOutOfRange { .. })
        ));
        assert!(matches!(
            MatchSet::new(2, &kp, &kp, &[(1, 1)]),
            Err(GuidanceError::SelfMatch { .. })
        ));
        assert!(matches!(
            MatchSet::new(2, &[[f64::NAN, 0.0]], &kp, &[(0, 1)]),
            Err(GuidanceError::NonFinite { .. })
        ));
        assert!(matches!(
            MatchSet::new(2, &kp, &[], &[(0, 1)]),
            Err(GuidanceError::LengthMismatch { .. })
        ));
        assert!(matches!(
            MatchSet::new(1, &[], &[], &[]),
            Err(GuidanceError::TooFewFrames { .. })
        ));
    }
}
