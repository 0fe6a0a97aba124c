//! Tracks: pairwise matches joined into multi-view observations of one scene point by
//! union-find over keypoint identities `(image, keypoint index)`, as COLMAP builds its
//! correspondence graph. A track that sees one image twice (two keypoints of an image joined
//! through other images) is inconsistent and dropped.

use posediff_geometry::PairMatches;

use crate::error::{Result, SfmError};
use crate::view_graph::UnionFind;

/// One observation of a track.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Observation {
    /// Image index.
    pub image: usize,
    /// Index of the keypoint in its image.
    pub keypoint: u32,
    /// Pixel coordinates (OpenCV).
    pub xy: [f64; 2],
}

/// Observations of one scene point, sorted by image.
pub type Track = Vec<Observation>;

/// What [`build_tracks`] did.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default)]
#[cfg_attr(feature = "serde", derive(serde::Serialize))]
pub struct TrackReport {
    /// Distinct keypoints in any match.
    pub keypoints: usize,
    /// Consistent tracks kept.
    pub tracks: usize,
    /// Tracks dropped because they see an image twice.
    pub inconsistent: usize,
    /// Observations in the kept tracks.
    pub observations: usize,
}

/// Tracks from the matches of `pairs` over `n_images`, in a deterministic order (by the first
/// observation's image and keypoint). Memory and time are linear in the matches.
///
/// # Errors
/// A pair naming an image out of range or itself, lists of different lengths.
pub fn build_tracks(n_images: usize, pairs: &[PairMatches]) -> Result<(Vec<Track>, TrackReport)> {
    // Dense ids per image: offset of image i plus the keypoint index.
    let mut extent = vec![0usize; n_images];
    for p in pairs {
        if p.first >= n_images || p.second >= n_images || p.first == p.second {
            return Err(SfmError::InvalidInput(format!(
                "tracks: a pair ({}, {}) of {n_images} images",
                p.first, p.second
            )));
        }
        if !p.is_consistent() {
            return Err(SfmError::LengthMismatch {
                what: "tracks: keypoints and keypoint indices of a pair",
                left: p.kp1.len(),
                right: p.idx1.len().min(p.idx2.len()).min(p.kp2.len()),
            });
        }
        for (&i, &j) in p.idx1.iter().zip(&p.idx2) {
            extent[p.first] = extent[p.first].max(i as usize + 1);
            extent[p.second] = extent[p.second].max(j as usize + 1);
        }
    }
    let mut offset = Vec::with_capacity(n_images + 1);
    let mut total = 0usize;
    for &e in &extent {
        offset.push(total);
        total += e;
    }
    // Compact node numbers for the keypoints that occur.
    const NONE: u32 = u32::MAX;
    let mut node = vec![NONE; total];
    let mut nodes: Vec<Observation> = Vec::new();
    let mut id = |image: usize, keypoint: u32, xy: [f64; 2], nodes: &mut Vec<Observation>| {
        let slot = &mut node[offset[image] + keypoint as usize];
        if *slot == NONE {
            *slot = nodes.len() as u32;
            nodes.push(Observation {
                image,
                keypoint,
                xy,
            });
        }
        *slot as usize
    };
    for p in pairs {
        for k in 0..p.len() {
            id(p.first, p.idx1[k], p.kp1[k], &mut nodes);
            id(p.second, p.idx2[k], p.kp2[k], &mut nodes);
        }
    }
    // A second pass joins them (no list of every match's node pair: at 1000 frames that
    // was 16.8 M pairs, 270–540 MB while it grew).
    let mut forest = UnionFind::new(nodes.len());
    for p in pairs {
        for (&i, &j) in p.idx1.iter().zip(&p.idx2) {
            let a = node[offset[p.first] + i as usize] as usize;
            let b = node[offset[p.second] + j as usize] as usize;
            forest.union(a, b);
        }
    }
    // Group by root: count, then fill (no hashing).
    let roots: Vec<usize> = (0..nodes.len()).map(|k| forest.find(k)).collect();
    let mut slot_of_root = vec![usize::MAX; nodes.len()];
    let mut tracks: Vec<Track> = Vec::new();
    for (k, &r) in roots.iter().enumerate() {
        if slot_of_root[r] == usize::MAX {
            slot_of_root[r] = tracks.len();
            tracks.push(Vec::new());
        }
        tracks[slot_of_root[r]].push(nodes[k]);
    }
    let mut report = TrackReport {
        keypoints: nodes.len(),
        ..TrackReport::default()
    };
    let mut kept: Vec<Track> = Vec::with_capacity(tracks.len());
    for mut t in tracks {
        t.sort_by_key(|o| (o.image, o.keypoint));
        if t.len() < 2 {
            continue;
        }
        if t.windows(2).any(|w| w[0].image == w[1].image) {
            report.inconsistent += 1;
            continue;
        }
        kept.push(t);
    }
    kept.sort_by_key(|t| (t[0].image, t[0].keypoint));
    report.tracks = kept.len();
    report.observations = kept.iter().map(Vec::len).sum();
    Ok((kept, report))
}

#[cfg(test)]
mod tests {
    #![allow(clippy::unwrap_used)]
    use super::*;

    fn pair(first: usize, second: usize, m: &[(u32, u32)]) -> PairMatches {
        PairMatches {
            first,
            second,
            kp1: m.iter().map(|&(i, _)| [f64::from(i), 0.0]).collect(),
            kp2: m.iter().map(|&(_, j)| [f64::from(j), 1.0]).collect(),
            idx1: m.iter().map(|&(i, _)| i).collect(),
            idx2: m.iter().map(|&(_, j)| j).collect(),
        }
    }

    #[test]
    fn tracks_join_matches_through_shared_keypoint_ids() {
        // 0:5 – 1:7 – 2:3 is one track; 0:1 matched to 2:8 and (via 1:2) to 2:9: inconsistent.
        let pairs = [
            pair(0, 1, &[(5, 7), (1, 2)]),
            pair(1, 2, &[(7, 3), (2, 9)]),
            pair(0, 2, &[(1, 8)]),
        ];
        let (tracks, report) = build_tracks(3, &pairs).unwrap();
        assert_eq!(tracks.len(), 1);
        let ids: Vec<(usize, u32)> = tracks[0].iter().map(|o| (o.image, o.keypoint)).collect();
        assert_eq!(ids, vec![(0, 5), (1, 7), (2, 3)]);
        assert_eq!(tracks[0][1].xy, [7.0, 1.0]);
        assert_eq!(report.inconsistent, 1);
        assert_eq!(report.observations, 3);
        // Identical coordinates but different keypoints stay apart.
        let mut same_xy = pair(0, 1, &[(1, 1), (2, 2)]);
        same_xy.kp1 = vec![[3.0, 3.0]; 2];
        let (tracks, _) = build_tracks(2, &[same_xy]).unwrap();
        assert_eq!(tracks.len(), 2);
    }

    #[test]
    fn bad_pairs_are_errors() {
        assert!(build_tracks(2, &[pair(0, 2, &[(0, 0)])]).is_err());
        let mut p = pair(0, 1, &[(0, 0)]);
        p.idx2.clear();
        assert!(build_tracks(2, &[p]).is_err());
    }
}
