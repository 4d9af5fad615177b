//! Synthetic ground truth.
//!
//! * [`scene`]: a scene of planar, procedurally textured objects (fronto-parallel and slanted
//!   rectangles and discs, optionally moving) in front of a background wall, ray cast from any
//!   pose and time with supersampling. It yields the input view, exact z-depth and exact novel
//!   views, so every later stage can be scored against truth.
//! * [`layers`]: synthetic layer sets with controlled coverage, for renderer benchmarks.

pub mod layers;
pub mod scene;
pub mod texture;

pub use scene::{Frame, Object, Scene, Shape, View};
pub use texture::Texture;
