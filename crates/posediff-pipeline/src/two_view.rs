//! OpenCV's two-view geometry (`posediff_matching::two_view`) behind the mapper's
//! [`GeometrySolver`], with a cache of the results that the mapper runs of one estimate share
//! (the first map, the second pass's map).

use std::collections::HashMap;
use std::sync::Mutex;

use nalgebra::Matrix3;
use posediff_matching::two_view::{
    fundamental_least_squares, homography_fit, relative_pose_with_homography,
};
use posediff_matching::{PairMatches, TwoViewConfig};
use posediff_sfm::SfmError;
use posediff_sfm::mapper::{GeometrySolver, RelativePose};
use posediff_sfm::resection::AbsolutePose;

/// OpenCV two-view geometry for the mapper, with the results of earlier mapper runs of the same
/// estimate when it has a cache.
pub(crate) struct OpenCvTwoView<'a> {
    /// The two-view settings.
    pub(crate) config: &'a TwoViewConfig,
    /// Earlier results of the same estimate.
    pub(crate) cache: Option<&'a TwoViewCache>,
}

#[cfg(test)]
impl<'a> OpenCvTwoView<'a> {
    pub(crate) fn new(config: &'a TwoViewConfig) -> Self {
        Self {
            config,
            cache: None,
        }
    }
}

/// A pair within one estimate: its images and its match count (a pair's matches do not change
/// within an estimate).
type PairKey = (usize, usize, usize);

/// One kind of two-view result per key.
type Results<K, V> = Mutex<HashMap<K, Option<V>>>;

/// The two-view results of one estimate, kept between its mapper runs: the second pass maps the
/// first pass's pairs again, at the same fixed focal starts. The solvers are deterministic
/// (OpenCV's RANSAC seeds its own generator), so a cached result is the one a new call would
/// give; the cache only saves the time.
#[derive(Default)]
pub(crate) struct TwoViewCache {
    homography: Results<PairKey, (Matrix3<f64>, f64)>,
    fundamental: Results<PairKey, Matrix3<f64>>,
    /// Also keyed by both calibrations' bits.
    relative: Results<(PairKey, [u64; 18]), RelativePose>,
}

fn pair_key(p: &PairMatches) -> PairKey {
    (p.first, p.second, p.len())
}

/// `map[key]`, computed by `make` (outside the lock) when missing.
fn cached<K: std::hash::Hash + Eq, V: Copy>(
    map: Option<&Mutex<HashMap<K, V>>>,
    key: K,
    make: impl FnOnce() -> posediff_sfm::Result<V>,
) -> posediff_sfm::Result<V> {
    let Some(map) = map else { return make() };
    if let Some(v) = map.lock().ok().and_then(|m| m.get(&key).copied()) {
        return Ok(v);
    }
    let v = make()?;
    if let Ok(mut m) = map.lock() {
        m.insert(key, v);
    }
    Ok(v)
}

fn two_view_error(p: &PairMatches, e: impl std::fmt::Display) -> SfmError {
    SfmError::TwoView {
        first: p.first,
        second: p.second,
        detail: e.to_string(),
    }
}

impl GeometrySolver for OpenCvTwoView<'_> {
    fn homography(&self, p: &PairMatches) -> posediff_sfm::Result<Option<(Matrix3<f64>, f64)>> {
        cached(self.cache.map(|c| &c.homography), pair_key(p), || {
            homography_fit(&p.kp1, &p.kp2, self.config).map_err(|e| two_view_error(p, e))
        })
    }

    fn fundamental(&self, p: &PairMatches) -> posediff_sfm::Result<Option<Matrix3<f64>>> {
        cached(self.cache.map(|c| &c.fundamental), pair_key(p), || {
            fundamental_least_squares(&p.kp1, &p.kp2).map_err(|e| two_view_error(p, e))
        })
    }

    fn relative_pose(
        &self,
        p: &PairMatches,
        homography: Option<(Matrix3<f64>, f64)>,
        k_a: &Matrix3<f64>,
        k_b: &Matrix3<f64>,
    ) -> posediff_sfm::Result<Option<RelativePose>> {
        let mut bits = [0u64; 18];
        for (b, v) in bits.iter_mut().zip(k_a.iter().chain(k_b.iter())) {
            *b = v.to_bits();
        }
        cached(self.cache.map(|c| &c.relative), (pair_key(p), bits), || {
            relative_pose_with_homography(&p.kp1, &p.kp2, homography, k_a, k_b, self.config)
                .map_err(|e| two_view_error(p, e))
        })
    }

    fn absolute_pose(
        &self,
        image: usize,
        points: &[nalgebra::Vector3<f64>],
        pixels: &[[f64; 2]],
        k: &Matrix3<f64>,
        threshold_px: f64,
    ) -> posediff_sfm::Result<Option<AbsolutePose>> {
        let pose = posediff_matching::resection::absolute_pose(points, pixels, k, threshold_px)
            .map_err(|e| SfmError::Resection {
                image,
                detail: e.to_string(),
            })?;
        Ok(pose.map(|p| AbsolutePose {
            rotation: p.rotation,
            translation: p.translation,
            inliers: p.inliers,
        }))
    }
}
