//! The error type of the geometry crate.

/// Everything that can go wrong in `posediff-geometry`.
///
/// Degenerate input is reported here instead of producing NaN or panicking.
#[derive(Debug, Clone, PartialEq, thiserror::Error)]
#[non_exhaustive]
pub enum GeometryError {
    /// A quaternion with zero norm has no rotation.
    #[error("the zero quaternion has no rotation")]
    ZeroQuaternion,
    /// An input held NaN or an infinity.
    #[error("{what} is not finite")]
    NonFinite {
        /// Which input.
        what: &'static str,
    },
    /// Too few elements for the estimate to be defined.
    #[error("{what}: need at least {needed}, got {got}")]
    TooFew {
        /// What was counted.
        what: &'static str,
        /// The minimum.
        needed: usize,
        /// What was given.
        got: usize,
    },
    /// Two inputs that must have the same length do not.
    #[error("{what}: lengths differ ({left} vs {right})")]
    LengthMismatch {
        /// Which inputs.
        what: &'static str,
        /// Length of the first.
        left: usize,
        /// Length of the second.
        right: usize,
    },
    /// The configuration does not determine the result.
    #[error("{what} is degenerate: {reason}")]
    Degenerate {
        /// Which computation.
        what: &'static str,
        /// Why.
        reason: &'static str,
    },
    /// An image size with a zero side.
    #[error("invalid image size {width}x{height}: both sides must be positive")]
    InvalidImageSize {
        /// Width in pixels.
        width: u32,
        /// Height in pixels.
        height: u32,
    },
    /// Intrinsics that cannot describe a pinhole camera.
    #[error("invalid intrinsics: {reason}")]
    InvalidIntrinsics {
        /// Why.
        reason: &'static str,
    },
}

/// Shorthand for results of this crate.
pub type Result<T> = std::result::Result<T, GeometryError>;

/// Returns `Err(NonFinite)` unless every value is finite.
pub(crate) fn ensure_finite<'a>(
    what: &'static str,
    values: impl IntoIterator<Item = &'a f64>,
) -> Result<()> {
    if values.into_iter().all(|v| v.is_finite()) {
        Ok(())
    } else {
        Err(GeometryError::NonFinite { what })
    }
}
