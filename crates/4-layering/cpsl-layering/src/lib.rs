//! Layer generation: one frame (colour + depth) to a depth-ordered [`cpsl_core::LayerSet`].
//!
//! * [`pipeline`]: content-promoted layering (paper §3.2): [`cues`] (depth confidence,
//!   saliency, instances) -> [`fuse`] (energy of eq. 3 by alpha-expansion over
//!   [`maxflow`]) -> [`promote`] (instance promotion, background merging to `K`) ->
//!   [`matte`] (soft alpha, extension behind nearer layers with [`cpsl_core::fill`], each layer's
//!   surface from [`geometry`], Edge-Depth Cache).
//! * [`slice`](mod@slice): depth slicing, clustering inverse depth into `K` slices (a baseline).

pub mod cues;
pub mod error;
pub mod fuse;
pub mod geometry;
pub mod grid;
pub mod matte;
pub mod maxflow;
pub mod pipeline;
pub mod promote;
pub mod slice;

pub use cues::{CueConfig, Cues, Prompt};
pub use error::LayeringError;
pub use geometry::GeometryMode;
pub use pipeline::{layer_cues, layer_frame, Layered, LayeringConfig};
pub use slice::{slice_by_depth, Bins, SliceConfig};

#[cfg(test)]
pub(crate) mod lcg {
    /// The tests' deterministic generator (Knuth's MMIX linear congruential step).
    pub(crate) struct Lcg(pub u64);

    impl Lcg {
        fn step(&mut self) -> u64 {
            self.0 = self
                .0
                .wrapping_mul(6364136223846793005)
                .wrapping_add(1442695040888963407);
            self.0
        }

        /// A value in `[0, 1)` (the state's top 24 bits).
        pub(crate) fn unit(&mut self) -> f32 {
            ((self.step() >> 40) as f32) / (1u64 << 24) as f32
        }

        /// The state's top 31 bits.
        pub(crate) fn index(&mut self) -> usize {
            (self.step() >> 33) as usize
        }
    }
}
