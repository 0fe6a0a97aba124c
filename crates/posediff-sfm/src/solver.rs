//! The geometry the mapper asks of its caller: two-view geometry from matches and one-view
//! geometry (resection) from 3D points. OpenCV implements it in the umbrella crate, so this
//! crate stays free of image libraries; the stages ([`crate::mapper`], [`crate::resection`])
//! only see this trait.

use nalgebra::{Matrix3, Vector3};
use posediff_geometry::PairMatches;

use crate::error::Result;

pub use posediff_geometry::TwoViewPose as RelativePose;

/// A pair's homography and the fraction of its matches it explains.
pub type Homography = Option<(Matrix3<f64>, f64)>;

/// A resected camera, `x_cam = R X + t`, and the indices of its inlier correspondences.
#[derive(Debug, Clone, PartialEq)]
pub struct AbsolutePose {
    /// World → camera rotation.
    pub rotation: Matrix3<f64>,
    /// Translation.
    pub translation: Vector3<f64>,
    /// Indices of the correspondences within the threshold.
    pub inliers: Vec<usize>,
}

/// Two-view geometry from matches and one-view geometry (resection) from 3D points, provided by
/// the caller (OpenCV in the umbrella crate), so this crate stays free of image libraries.
/// Called from several threads.
pub trait GeometrySolver: Sync {
    /// A homography fit and the fraction of matches it explains (within the solver's
    /// threshold); `None` when none can be fitted.
    ///
    /// # Errors
    /// The solver's own failures.
    fn homography(&self, pair: &PairMatches) -> Result<Option<(Matrix3<f64>, f64)>>;

    /// A least-squares fundamental matrix `x_bᵀ F x_a = 0` of the pair, `None` if degenerate.
    ///
    /// # Errors
    /// The solver's own failures.
    fn fundamental(&self, pair: &PairMatches) -> Result<Option<Matrix3<f64>>>;

    /// The relative pose at intrinsics `k_a`, `k_b`, given the pair's [`Self::homography`]
    /// (computed once, whatever the focal); `None` when there is none.
    ///
    /// # Errors
    /// The solver's own failures.
    fn relative_pose(
        &self,
        pair: &PairMatches,
        homography: Option<(Matrix3<f64>, f64)>,
        k_a: &Matrix3<f64>,
        k_b: &Matrix3<f64>,
    ) -> Result<Option<RelativePose>>;

    /// The pose of `image` (intrinsics `k`) that sees `points[i]` at `pixels[i]`, robust to
    /// outliers, with the correspondences within `threshold_px` of reprojection error as its
    /// inliers; `None` when no pose is found.
    ///
    /// # Errors
    /// The solver's own failures.
    fn absolute_pose(
        &self,
        image: usize,
        points: &[Vector3<f64>],
        pixels: &[[f64; 2]],
        k: &Matrix3<f64>,
        threshold_px: f64,
    ) -> Result<Option<AbsolutePose>>;
}
