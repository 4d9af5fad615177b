//! The pipelines of cpsl as library calls, so that every front end (the CLI, the demo, the
//! evaluation) runs the same code:
//!
//! * [`image`]: one image to a layer set;
//! * [`video`]: a video (or image sequence) to layered frames, GOP by GOP, with `video.json`;
//! * [`encode`]: a video to one package, an archive or a set of bitrate variants; frames go
//!   from the decoder through layering into the package writers as they arrive;
//! * [`synthetic`]: the built-in ray-cast scene and its ground truth written to disk.
//!
//! Depth, camera and configuration come from [`sources`]. Long work reports through
//! [`cpsl_core::Progress`]; warnings are events, never prints.

pub mod encode;
mod error;
pub mod image;
pub mod sources;
pub mod synthetic;
pub mod track;
pub mod video;

pub use error::{Context, PipelineError};
