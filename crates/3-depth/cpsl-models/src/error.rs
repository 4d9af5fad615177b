//! Errors of model loading and inference.

use std::path::PathBuf;
use thiserror::Error;

/// A failure to load or run a model.
#[derive(Debug, Error)]
pub enum ModelError {
    /// The ONNX Runtime library could not be found or loaded.
    #[error("ONNX Runtime not available: {0} (run scripts/setup-models.sh, or set ORT_DYLIB_PATH to libonnxruntime.so)")]
    Runtime(String),
    /// A file could not be read.
    #[error("{path}: {cause}")]
    Io {
        /// Path involved.
        path: PathBuf,
        /// Underlying error (part of the message, not a separate source).
        cause: std::io::Error,
    },
    /// The model description is invalid.
    #[error("{path}: model description: {reason}")]
    Description {
        /// Description file.
        path: PathBuf,
        /// What is wrong.
        reason: String,
    },
    /// ONNX Runtime rejected the model file (not ONNX, unsupported operators, ...).
    #[error("{path}: not a usable ONNX model: {reason}")]
    Model {
        /// Model file.
        path: PathBuf,
        /// Runtime message.
        reason: String,
    },
    /// The model's inputs or outputs do not match the description.
    #[error("{path}: {reason}")]
    Interface {
        /// Model file.
        path: PathBuf,
        /// What does not match.
        reason: String,
    },
    /// Inference failed.
    #[error("inference failed: {0}")]
    Inference(String),
    /// The input image is unusable.
    #[error("input image: {0}")]
    Input(String),
}
