//! The error type of the matching crate.

use std::path::PathBuf;

/// Everything that can go wrong in `posediff-matching`.
#[derive(Debug, thiserror::Error)]
#[non_exhaustive]
pub enum MatchingError {
    /// An image could not be read or decoded.
    #[error("cannot read image {path}: missing, unreadable or not an image OpenCV can decode")]
    UnreadableImage {
        /// The file.
        path: PathBuf,
    },
    /// An image file whose structure is broken (truncated, corrupt) or that is not a JPEG or
    /// PNG.
    #[error("{path}: {reason}")]
    CorruptImage {
        /// The file.
        path: std::path::PathBuf,
        /// What is wrong with it.
        reason: String,
    },
    /// Matching needs at least two images.
    #[error("need at least 2 images to match, got {got}")]
    TooFewImages {
        /// How many were given.
        got: usize,
    },
    /// A pair names an image that does not exist or an image with itself.
    #[error("invalid pair ({first}, {second}) for {n_images} images")]
    InvalidPair {
        /// First image index.
        first: usize,
        /// Second image index.
        second: usize,
        /// Number of images.
        n_images: usize,
    },
    /// An invalid configuration value.
    #[error("invalid matching configuration: {0}")]
    InvalidConfig(&'static str),
    /// A frame stream (video keyframe selection) that cannot go on: an empty frame, frames of
    /// two sizes, a mask of another size, options out of range.
    #[error("{0}")]
    Frames(String),
    /// OpenCV reported an error.
    #[error("OpenCV: {0}")]
    OpenCv(#[from] opencv::Error),
}

/// Shorthand for results of this crate.
pub type Result<T> = std::result::Result<T, MatchingError>;
