//! The CPU reference renderer of CPSL.
//!
//! For a viewer pose, every layer is warped with the inverse plane-induced homography
//! ([`cpsl_core::Homography::plane_inverse`]), sampled bilinearly (premultiplied RGBA, texels
//! outside the layer are transparent) and composited front to back exactly as equation 2 of
//! the paper: `I = sum_k P_k prod_{j<k} (1 - alpha_j)`.
//!
//! Speed comes from: layers prepared once into padded `u32` textures; the output cut into
//! 64x16 tiles processed in parallel (rayon); per tile and layer, the source footprint is
//! bounded from the tile corners and checked against per-block occupancy sums so that empty
//! footprints are skipped and fully opaque ones end the layer loop; inside a tile the
//! homography is evaluated exactly at sub-span boundaries (sized so that linear interpolation
//! stays within 1/512 px) and stepped in 16.16 fixed point in between; spans whose source rows
//! are empty are skipped, and so are rows whose pixels are all opaque already; bilinear
//! filtering runs in 8-bit fixed point on four channels at once, eight pixels at a time with
//! AVX2 where the CPU has it (bit-identical to the scalar kernel).
//!
//! After compositing, the Dynamic Pixel Strip ([`PreparedLayers::render_dps_into`]) bridges
//! thin cracks between independently warped layers, guided by the Edge-Depth Cache.
//!
//! Sampling precision: positions are within 1/256 px of the exact homography on each axis
//! (1/512 px from linear stepping, 1/512 px from rounding) and each bilinear stage rounds to
//! 8 bits, so a sample is within 1 LSB of exact bilinear filtering at the rounded position and
//! within 3 LSB of exact filtering at the exact one. At the identity pose every
//! sample is exact and the render equals the closed form
//! ([`cpsl_core::LayerSet::composite_reference`]) up to `f32` rounding.

mod dps;
pub mod mesh;
mod prepared;
mod raster;
mod renderer;
#[cfg(target_arch = "x86_64")]
mod simd;

pub use dps::{strip_width, DpsConfig, DpsStats, EdgeOffsets};
pub use prepared::{Filter, PreparedLayers};
pub use raster::RenderStats;
pub use renderer::{CpuRenderer, FrameLayers, RenderError, Renderer};
