//! The error type of the diffusion crate.

use std::path::PathBuf;

/// Everything that can go wrong in `posediff-diffusion`.
#[derive(Debug, thiserror::Error)]
#[non_exhaustive]
pub enum DiffusionError {
    /// A checkpoint file could not be read.
    #[error("cannot read checkpoint {path}: {source}")]
    CheckpointRead {
        /// The file.
        path: PathBuf,
        /// What the reader said.
        source: candle_core::Error,
    },
    /// The file is neither a PyTorch zip checkpoint nor safetensors.
    #[error("{path} is neither a PyTorch (.pth, zip) nor a safetensors checkpoint")]
    UnknownFormat {
        /// The file.
        path: PathBuf,
    },
    /// A zip checkpoint whose pickle cannot be interpreted.
    #[error("{path}: malformed PyTorch checkpoint (its pickle cannot be read)")]
    MalformedCheckpoint {
        /// The file.
        path: PathBuf,
    },
    /// The checkpoint's keys do not describe a PoseDiffusion model.
    #[error("checkpoint does not match the PoseDiffusion layout:\n{}", .problems.join("\n"))]
    CheckpointLayout {
        /// Every missing, unexpected or mis-shaped key, one per line.
        problems: Vec<String>,
    },
    /// Tensors of the checkpoint that hold NaN or infinite values.
    #[error("checkpoint has NaN or infinite values in: {}", .keys.join(", "))]
    NonFiniteWeights {
        /// The keys, with how many values are not finite.
        keys: Vec<String>,
    },
    /// A network output that is NaN or infinite (the weights or the inputs are broken).
    #[error("non-finite values in the {what} at diffusion step {step}")]
    NonFinite {
        /// Which output.
        what: &'static str,
        /// The step (0–99; the features are computed before step 99).
        step: usize,
    },
    /// The mean hook (GGS) failed.
    #[error("{what} at diffusion step {step}: {detail}")]
    Hook {
        /// Which hook.
        what: &'static str,
        /// The step.
        step: usize,
        /// The cause.
        detail: String,
    },
    /// Inputs with the wrong shape.
    #[error("{what}: expected shape {expected}, got {got:?}")]
    Shape {
        /// Which input.
        what: &'static str,
        /// The expected shape, in words.
        expected: &'static str,
        /// The shape given.
        got: Vec<usize>,
    },
    /// An invalid argument.
    #[error("{0}")]
    Invalid(&'static str),
    /// A tensor operation failed.
    #[error(transparent)]
    Candle(#[from] candle_core::Error),
    /// An AMX tile product refused its operands.
    #[error(transparent)]
    Tiles(#[from] posediff_amx::AmxError),
}

/// Shorthand for results of this crate.
pub type Result<T> = std::result::Result<T, DiffusionError>;
