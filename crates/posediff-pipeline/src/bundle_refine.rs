//! The hybrid of the paper's future work (`--weights W --refine bundle`): cameras from
//! elsewhere refined by the mapper's Sampson refinement and bundle adjustment
//! ([`posediff_sfm::bundle_refine`]), with posediff's errors.

use posediff_geometry::{Camera, PairMatches};
use posediff_sfm::bundle::BundleOptions;
use posediff_sfm::sampson_refine::SampsonRefineOptions;

use crate::error::{PosediffError, Result};

pub use posediff_sfm::bundle_refine::BundleRefinement;

/// [`posediff_sfm::bundle_refine::bundle_refine_cameras`]: camera 0 held, the scene's scale
/// kept, one focal factor refined unless `known_intrinsics`, with the options tree's
/// `mapper.sampson` and `mapper.bundle` (their defaults where the tree turns them off).
///
/// # Errors
/// Fewer than two cameras ([`PosediffError::TooFewImages`]), malformed pairs, a degenerate
/// adjustment.
pub fn bundle_refine_cameras(
    cameras: &mut [Camera],
    pairs: &[PairMatches],
    known_intrinsics: bool,
    options: (&SampsonRefineOptions, &BundleOptions),
) -> Result<BundleRefinement> {
    if cameras.len() < 2 {
        return Err(PosediffError::TooFewImages {
            needed: 2,
            got: cameras.len(),
        });
    }
    Ok(posediff_sfm::bundle_refine::bundle_refine_cameras(
        cameras,
        pairs,
        known_intrinsics,
        options,
    )?)
}
