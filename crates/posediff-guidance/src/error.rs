//! The error type of the guidance crate.

use posediff_geometry::GeometryError;

/// Everything that can go wrong in `posediff-guidance`.
#[derive(Debug, Clone, PartialEq, thiserror::Error)]
#[non_exhaustive]
pub enum GuidanceError {
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
    /// A match names a frame that does not exist.
    #[error("match {index} refers to frame {frame}, but there are {n_frames} frames")]
    FrameOutOfRange {
        /// Index of the match.
        index: usize,
        /// The frame it names.
        frame: usize,
        /// Number of frames.
        n_frames: usize,
    },
    /// A match between a frame and itself has no epipolar geometry.
    #[error("match {index} pairs frame {frame} with itself")]
    SelfMatch {
        /// Index of the match.
        index: usize,
        /// The frame.
        frame: usize,
    },
    /// Non-finite input.
    #[error("{what} is not finite")]
    NonFinite {
        /// Which input.
        what: &'static str,
    },
    /// Too few frames.
    #[error("need at least {needed} frames, got {got}")]
    TooFewFrames {
        /// The minimum.
        needed: usize,
        /// What was given.
        got: usize,
    },
    /// An invalid configuration value.
    #[error("invalid GGS configuration: {reason}")]
    InvalidConfig {
        /// Why.
        reason: &'static str,
    },
    /// A camera could not be decoded (e.g. a zero quaternion).
    #[error(transparent)]
    Geometry(#[from] GeometryError),
}

/// Shorthand for results of this crate.
pub type Result<T> = std::result::Result<T, GuidanceError>;
