//! Layer generation: one frame (colour + depth) to a depth-ordered [`cpsl_core::LayerSet`].
//!
//! * [`slice`]: depth slicing, clustering inverse depth into `K` slices (the baseline and the
//!   demo's layering).
//! * [`fill`]: push-pull hole filling, used to extend colour behind nearer layers.

pub mod error;
pub mod fill;
pub mod slice;

pub use error::LayeringError;
pub use slice::{slice_by_depth, Bins, SliceConfig};
