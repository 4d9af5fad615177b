//! Errors of file reading and writing. Every variant names the path involved.

use cpsl_core::{CoreError, ManifestError};
use std::path::PathBuf;
use thiserror::Error;

/// A failure to read or write CPSL files.
#[derive(Debug, Error)]
pub enum IoError {
    /// The operating system refused an operation.
    #[error("{path}: {cause}")]
    Io {
        /// Path involved.
        path: PathBuf,
        /// Underlying error (part of the message, not a separate source).
        cause: std::io::Error,
    },
    /// The manifest is malformed.
    #[error("{path}: {cause}")]
    Manifest {
        /// Manifest path.
        path: PathBuf,
        /// What is wrong.
        cause: ManifestError,
    },
    /// A file is larger than the limits allow.
    #[error("{path}: file is {size} bytes, above the limit of {max}")]
    FileTooLarge {
        /// File path.
        path: PathBuf,
        /// Its size.
        size: u64,
        /// The limit.
        max: u64,
    },
    /// An image could not be decoded or encoded.
    #[error("{path}: {message}")]
    Image {
        /// Image path.
        path: PathBuf,
        /// Decoder message.
        message: String,
    },
    /// A layer image's size differs from the camera in the manifest.
    #[error("{path}: image is {width}x{height} but the manifest camera is {expected_width}x{expected_height}")]
    ImageSize {
        /// Image path.
        path: PathBuf,
        /// Width found.
        width: u32,
        /// Height found.
        height: u32,
        /// Camera width.
        expected_width: u32,
        /// Camera height.
        expected_height: u32,
    },
    /// The content breaks a layer-set invariant (depth order, limits, ...).
    #[error("{path}: {cause}")]
    Invalid {
        /// The file the invariant belongs to (usually the manifest).
        path: PathBuf,
        /// The broken invariant.
        cause: CoreError,
    },
    /// An Edge-Depth Cache file is malformed or does not fit its layer set.
    #[error("{path}: {cause}")]
    Edc {
        /// The file.
        path: PathBuf,
        /// What is wrong.
        cause: String,
    },
    /// A mesh layer's grid file is malformed or does not fit its layer set.
    #[error("{path}: {cause}")]
    Grid {
        /// The file.
        path: PathBuf,
        /// What is wrong.
        cause: String,
    },
    /// A layered video's index is malformed.
    #[error("{path}: {cause}")]
    Video {
        /// The file.
        path: PathBuf,
        /// What is wrong.
        cause: String,
    },
    /// The write target exists and is not a layer set, so it is not replaced.
    #[error(
        "{path}: exists and is not a CPSL layer set (no manifest.json); refusing to replace it"
    )]
    TargetExists {
        /// Target path.
        path: PathBuf,
    },
    /// A depth file is malformed or of an unsupported kind.
    #[error("{path}: depth: {reason}")]
    Depth {
        /// File path.
        path: PathBuf,
        /// What is wrong.
        reason: String,
    },
    /// A PFM file is malformed.
    #[error("{path}: PFM {reason}")]
    Pfm {
        /// File path.
        path: PathBuf,
        /// What is wrong.
        reason: String,
    },
}

impl IoError {
    /// Wraps an `std::io::Error` with its path.
    pub fn io(path: impl Into<PathBuf>, cause: std::io::Error) -> Self {
        Self::Io {
            path: path.into(),
            cause,
        }
    }
}
