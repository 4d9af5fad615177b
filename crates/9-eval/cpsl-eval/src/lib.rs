//! Evaluation of CPSL: metrics, coverage (hole and crack ratios), baselines and real datasets
//! with ground truth, and the three evaluations that use them, each one library call: novel
//! views of real scenes ([`views`]), temporal stability on moving clips ([`video`]) and
//! rate-distortion against DIBR streaming and MPI ([`rd`]); and speed ([`bench`](mod@bench)).

pub mod baselines;
pub mod bench;
pub mod coverage;
pub mod datasets;
mod error;
pub mod metrics;
pub mod rd;
pub mod report;
pub mod stereo;
pub mod temporal;
pub mod tracking;
pub mod video;
pub mod views;

pub use error::{Context, EvalError};
