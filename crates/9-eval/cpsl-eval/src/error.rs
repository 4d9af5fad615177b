//! The evaluation's error: every library's error, bad options and missing data, and context
//! saying what was being done.

use std::path::PathBuf;
use thiserror::Error;

/// Why an evaluation failed.
#[derive(Debug, Error)]
pub enum EvalError {
    /// An option or input is unusable, or data is missing.
    #[error("{0}")]
    Invalid(String),
    /// A file operation.
    #[error("{path}: {source}")]
    File {
        /// The file.
        path: PathBuf,
        /// The cause.
        source: std::io::Error,
    },
    /// Reading or writing files.
    #[error(transparent)]
    Io(#[from] cpsl_io::IoError),
    /// A dataset.
    #[error(transparent)]
    Dataset(#[from] crate::datasets::DatasetError),
    /// Neural inference (depth, LPIPS).
    #[error(transparent)]
    Model(#[from] cpsl_models::ModelError),
    /// Layering one frame.
    #[error(transparent)]
    Layering(#[from] cpsl_layering::LayeringError),
    /// Layering a video.
    #[error(transparent)]
    Temporal(#[from] cpsl_temporal::VideoError),
    /// Coding layer streams.
    #[error(transparent)]
    Codec(#[from] cpsl_codec::CodecError),
    /// Reading a package.
    #[error(transparent)]
    Package(#[from] cpsl_package::PackageError),
    /// Playing a package.
    #[error(transparent)]
    Player(#[from] cpsl_player::PlayerError),
    /// Rendering.
    #[error(transparent)]
    Render(#[from] cpsl_render::RenderError),
    /// The GPU renderer.
    #[error(transparent)]
    Gpu(#[from] cpsl_render_gpu::GpuError),
    /// A pipeline (layering an image, depth sources).
    #[error(transparent)]
    Pipeline(#[from] cpsl_pipeline::PipelineError),
    /// Stereo matching.
    #[error(transparent)]
    Stereo(#[from] cpsl_stereo::StereoError),
    /// Camera tracking.
    #[error(transparent)]
    Track(#[from] cpsl_track::TrackError),
    /// Core validation.
    #[error(transparent)]
    Core(#[from] cpsl_core::CoreError),
    /// A depth source.
    #[error(transparent)]
    Depth(#[from] cpsl_core::DepthSourceError),
    /// What was being done when `source` happened.
    #[error("{context}")]
    Context {
        /// What was being done.
        context: String,
        /// What went wrong.
        #[source]
        source: Box<EvalError>,
    },
}

cpsl_core::error_context!(EvalError);

impl EvalError {
    /// A file operation's error with its path.
    pub fn file(path: impl Into<PathBuf>, source: std::io::Error) -> Self {
        Self::File {
            path: path.into(),
            source,
        }
    }
}
