//! The error type of the mapper.

use posediff_geometry::GeometryError;

/// Everything that can go wrong in `posediff-sfm`.
#[derive(Debug, Clone, PartialEq, thiserror::Error)]
#[non_exhaustive]
pub enum SfmError {
    /// Inputs whose lengths must agree do not.
    #[error("{what}: lengths differ ({left} vs {right})")]
    LengthMismatch {
        /// Which inputs.
        what: &'static str,
        /// Length of the first.
        left: usize,
        /// Length of the second.
        right: usize,
    },
    /// An input or setting that cannot be used.
    #[error("invalid input: {0}")]
    InvalidInput(String),
    /// A linear system that should be positive definite is not (a degenerate configuration:
    /// e.g. a point seen along one ray, a camera without constraints).
    #[error("{what}: the normal equations are not positive definite ({detail})")]
    NotPositiveDefinite {
        /// Which system.
        what: &'static str,
        /// What the factorisation said.
        detail: String,
    },
    /// faer could not build or factorise a matrix.
    #[error("{what}: {detail}")]
    Linalg {
        /// Which system.
        what: &'static str,
        /// The cause.
        detail: String,
    },
    /// The two-view solver (e.g. OpenCV) failed.
    #[error("two-view geometry of images {first} and {second}: {detail}")]
    TwoView {
        /// First image.
        first: usize,
        /// Second image.
        second: usize,
        /// The cause.
        detail: String,
    },
    /// The solver failed to resect a camera.
    #[error("resection of image {image}: {detail}")]
    Resection {
        /// The image.
        image: usize,
        /// The cause.
        detail: String,
    },
    /// No pair of images has a usable relative pose.
    #[error("none of the {images} images shares a usable two-view geometry with another")]
    NoUsablePairs {
        /// Number of images.
        images: usize,
    },
    /// From the geometry crate.
    #[error(transparent)]
    Geometry(#[from] GeometryError),
}

/// Shorthand for results of this crate.
pub type Result<T> = std::result::Result<T, SfmError>;
