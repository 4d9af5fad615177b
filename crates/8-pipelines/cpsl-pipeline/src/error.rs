//! The pipelines' error: every library's error, bad options, and context saying what was
//! being done.

use std::path::PathBuf;
use thiserror::Error;

/// Why a pipeline failed.
#[derive(Debug, Error)]
pub enum PipelineError {
    /// An option or input is unusable.
    #[error("{0}")]
    Invalid(String),
    /// Reading or writing files.
    #[error(transparent)]
    Io(#[from] cpsl_io::IoError),
    /// A file operation outside `cpsl-io`.
    #[error("{path}: {source}")]
    File {
        /// The file.
        path: PathBuf,
        /// The cause.
        source: std::io::Error,
    },
    /// A JSON file does not parse.
    #[error("{path}: {source}")]
    Json {
        /// The file.
        path: PathBuf,
        /// The cause.
        source: serde_json::Error,
    },
    /// Neural inference.
    #[error(transparent)]
    Model(#[from] cpsl_models::ModelError),
    /// A depth source.
    #[error(transparent)]
    Depth(#[from] cpsl_core::DepthSourceError),
    /// Layering one frame.
    #[error(transparent)]
    Layering(#[from] cpsl_layering::LayeringError),
    /// Layering a video.
    #[error(transparent)]
    Temporal(#[from] cpsl_temporal::VideoError),
    /// Reading video.
    #[error(transparent)]
    Media(#[from] cpsl_media::MediaError),
    /// Coding layer streams.
    #[error(transparent)]
    Codec(#[from] cpsl_codec::CodecError),
    /// Writing or reading a package.
    #[error(transparent)]
    Package(#[from] cpsl_package::PackageError),
    /// A camera is invalid.
    #[error(transparent)]
    Core(#[from] cpsl_core::CoreError),
    /// Camera tracking.
    #[error(transparent)]
    Track(#[from] cpsl_track::TrackError),
    /// Stereo matching.
    #[error(transparent)]
    Stereo(#[from] cpsl_stereo::StereoError),
    /// The caller asked to stop.
    #[error("interrupted; no {0} written")]
    Interrupted(&'static str),
    /// What was being done when `source` happened.
    #[error("{context}")]
    Context {
        /// What was being done.
        context: String,
        /// What went wrong.
        #[source]
        source: Box<PipelineError>,
    },
}

cpsl_core::error_context!(PipelineError);
