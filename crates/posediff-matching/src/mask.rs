//! Masks as COLMAP takes them (`<mask folder>/<image name>.png`, zero = ignore): the keypoints
//! of an image that fall on masked pixels are dropped after extraction, before any matching,
//! whatever the extractor (SIFT, ORB, ALIKED, DISK).

use std::path::Path;

use opencv::prelude::*;

use crate::error::{MatchingError, Result};
use crate::features::ImageFeatures;
use crate::image_check::decode;

/// Drops the keypoints of `features` on pixels that are zero in the mask image `mask` (a
/// keypoint's nearest pixel); returns how many were dropped.
///
/// # Errors
/// An unreadable or broken mask, or one whose size is not the image's.
pub fn apply_mask(features: &mut ImageFeatures, mask: &Path) -> Result<usize> {
    let m = decode(mask, opencv::imgcodecs::IMREAD_GRAYSCALE)?;
    let size = features.image_size;
    if u32::try_from(m.cols()) != Ok(size.width()) || u32::try_from(m.rows()) != Ok(size.height()) {
        return Err(MatchingError::CorruptImage {
            path: mask.to_owned(),
            reason: format!(
                "the mask is {}x{}, its image {}x{}: a mask has its image's size",
                m.cols(),
                m.rows(),
                size.width(),
                size.height()
            ),
        });
    }
    let (w, h) = (m.cols(), m.rows());
    Ok(features.retain(|p| {
        let (x, y) = (p[0].round(), p[1].round());
        x >= 0.0
            && y >= 0.0
            && x < f64::from(w)
            && y < f64::from(h)
            && m.at_2d::<u8>(y as i32, x as i32).is_ok_and(|v| *v != 0)
    }))
}
