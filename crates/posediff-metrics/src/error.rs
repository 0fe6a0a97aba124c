//! The error type of the metrics crate.

use posediff_geometry::GeometryError;

/// Everything that can go wrong in `posediff-metrics`.
#[derive(Debug, Clone, PartialEq, thiserror::Error)]
#[non_exhaustive]
pub enum MetricsError {
    /// Predicted and ground-truth sets differ in length.
    #[error("{what}: {predicted} predicted vs {ground_truth} ground-truth cameras")]
    LengthMismatch {
        /// Which inputs.
        what: &'static str,
        /// Number of predictions.
        predicted: usize,
        /// Number of ground-truth cameras.
        ground_truth: usize,
    },
    /// Too few cameras or pairs to compute the metric.
    #[error("{what}: need at least {needed}, got {got}")]
    TooFew {
        /// What was counted.
        what: &'static str,
        /// The minimum.
        needed: usize,
        /// What was given.
        got: usize,
    },
    /// A rotation matrix whose trace is outside `[−1, 3]` (PyTorch3D raises here too).
    #[error("not a rotation: trace {trace} outside [-1, 3]")]
    NotARotation {
        /// The offending trace.
        trace: f64,
    },
    /// Non-finite input.
    #[error("{what} is not finite")]
    NonFinite {
        /// Which input.
        what: &'static str,
    },
    /// A geometric step (e.g. the Umeyama alignment) failed.
    #[error(transparent)]
    Geometry(#[from] GeometryError),
}

/// Shorthand for results of this crate.
pub type Result<T> = std::result::Result<T, MetricsError>;
