//! The error type of posediff (the umbrella crate re-exports it).

use std::path::PathBuf;

/// Everything that can go wrong in `posediff`.
#[derive(Debug, thiserror::Error)]
#[non_exhaustive]
pub enum PosediffError {
    /// An input path that does not exist.
    #[error("no such file or directory: {0}")]
    NotFound(PathBuf),
    /// An error while reading one of the inputs a flag names.
    #[error("{what}: {source}")]
    Context {
        /// What was being done, naming the flag and the file.
        what: String,
        /// Why it failed.
        source: Box<PosediffError>,
    },
    /// A folder without images.
    #[error("no .png/.jpg/.jpeg images in {0}")]
    NoImages(PathBuf),
    /// Fewer images than the method needs.
    #[error("need at least {needed} images, got {got}")]
    TooFewImages {
        /// The minimum.
        needed: usize,
        /// How many were found.
        got: usize,
    },
    /// No image pair has enough verified matches to relate two cameras.
    #[error(
        "no two of the {images} images share enough verified matches: the images do not overlap \
         (or are too different in viewpoint, texture or exposure); no camera can be estimated"
    )]
    NoMatches {
        /// Number of images.
        images: usize,
    },
    /// An invalid argument value.
    #[error("{0}")]
    InvalidArgument(String),
    /// An image that cannot be decoded.
    #[error("cannot read image {0}: missing, unreadable or not an image")]
    UnreadableImage(PathBuf),
    /// Reading an input failed.
    #[error("cannot read {path}: {source}")]
    Read {
        /// The file.
        path: PathBuf,
        /// Why.
        source: std::io::Error,
    },
    /// An input file that does not have the expected content.
    #[error("{path}: {reason}")]
    InvalidFile {
        /// The file.
        path: PathBuf,
        /// What is wrong, naming the field where there is one.
        reason: String,
    },
    /// Writing an output failed.
    #[error("cannot write {path}: {source}")]
    Write {
        /// The file.
        path: PathBuf,
        /// Why.
        source: std::io::Error,
    },
    /// A camera could not be converted.
    #[error(transparent)]
    Geometry(#[from] posediff_geometry::GeometryError),
    /// OpenCV reported an error.
    #[error("OpenCV: {0}")]
    OpenCv(#[from] opencv::Error),
    /// The network failed (checkpoint layout, shapes).
    #[error(transparent)]
    Model(#[from] posediff_diffusion::DiffusionError),
    /// Matching failed.
    #[error(transparent)]
    Matching(#[from] posediff_matching::MatchingError),
    /// The learned matcher failed (weights, shapes).
    #[error(transparent)]
    Learned(Box<posediff_learned::LearnedError>),
    /// GGS failed.
    #[error(transparent)]
    Guidance(#[from] posediff_guidance::GuidanceError),
    /// The checkpoint-free mapper failed.
    #[error("mapper: {0}")]
    Mapper(posediff_sfm::SfmError),
    /// A tensor operation failed.
    #[error(transparent)]
    Tensor(#[from] candle_core::Error),
    /// JSON could not be written.
    #[error("JSON: {0}")]
    Json(#[from] serde_json::Error),
}

impl From<posediff_learned::LearnedError> for PosediffError {
    fn from(e: posediff_learned::LearnedError) -> Self {
        Self::Learned(Box::new(e))
    }
}

impl PosediffError {
    /// The innermost error (past every [`PosediffError::Context`]).
    pub fn root(&self) -> &Self {
        match self {
            Self::Context { source, .. } => source.root(),
            other => other,
        }
    }

    /// A read failure of `path`.
    #[must_use]
    pub fn read(path: &std::path::Path, source: std::io::Error) -> Self {
        Self::Read {
            path: path.to_owned(),
            source,
        }
    }

    /// `path` read but its content is wrong.
    #[must_use]
    pub fn invalid(path: &std::path::Path, reason: impl std::fmt::Display) -> Self {
        Self::InvalidFile {
            path: path.to_owned(),
            reason: reason.to_string(),
        }
    }
}

/// A whole text file; a failure names it.
///
/// # Errors
/// The file cannot be read.
pub fn read_text(path: &std::path::Path) -> Result<String> {
    std::fs::read_to_string(path).map_err(|e| PosediffError::read(path, e))
}

/// Shorthand for results of this crate.
pub type Result<T> = std::result::Result<T, PosediffError>;
