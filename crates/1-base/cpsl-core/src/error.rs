//! Errors of the core crate.

use thiserror::Error;

/// A validation failure of a camera, layer or layer set. Messages name the field, what was
/// expected and what was found.
#[derive(Debug, Error, Clone, PartialEq)]
pub enum CoreError {
    /// A camera parameter is not usable.
    #[error("camera: {field} must be {expected}, found {found}")]
    Camera {
        /// The offending field.
        field: &'static str,
        /// What a valid value looks like.
        expected: &'static str,
        /// The value found.
        found: String,
    },
    /// A layer set has no layers.
    #[error("layer set is empty: at least one layer is required")]
    Empty,
    /// Too many layers for the configured limits.
    #[error("layer set has {found} layers, more than the limit of {max}")]
    TooManyLayers {
        /// Number of layers present.
        found: usize,
        /// Configured maximum.
        max: usize,
    },
    /// An image is larger than the configured limits.
    #[error(
        "{what} is {width}x{height}, above the limit of {max_side} px per side / {max_pixels} px"
    )]
    TooLarge {
        /// What was measured.
        what: String,
        /// Width found.
        width: u32,
        /// Height found.
        height: u32,
        /// Limit per side.
        max_side: u32,
        /// Limit on the pixel count.
        max_pixels: u64,
    },
    /// An image has a zero dimension.
    #[error("{what} has a zero dimension ({width}x{height})")]
    ZeroSize {
        /// What was measured.
        what: String,
        /// Width found.
        width: u32,
        /// Height found.
        height: u32,
    },
    /// A layer's geometry is not usable.
    #[error("layer {index}: geometry: {reason}")]
    BadGeometry {
        /// Layer index.
        index: usize,
        /// What is wrong.
        reason: String,
    },
    /// A layer's size differs from the camera's.
    #[error(
        "layer {index}: size {width}x{height} differs from the camera's {cam_width}x{cam_height}"
    )]
    SizeMismatch {
        /// Layer index (0 = nearest).
        index: usize,
        /// Layer width.
        width: u32,
        /// Layer height.
        height: u32,
        /// Camera width.
        cam_width: u32,
        /// Camera height.
        cam_height: u32,
    },
    /// A layer depth is NaN, infinite, zero or negative.
    #[error("layer {index}: depth must be finite and > 0, found {depth}")]
    BadDepth {
        /// Layer index.
        index: usize,
        /// Depth found.
        depth: f64,
    },
    /// Layer depths are not strictly increasing (nearest first).
    #[error("layer {index}: depths must increase strictly from front to back, found {depth} after {previous}")]
    DepthOrder {
        /// Layer index.
        index: usize,
        /// Depth of this layer.
        depth: f64,
        /// Depth of the previous layer.
        previous: f64,
    },
    /// A buffer has the wrong length for its declared size.
    #[error("{what}: buffer holds {found} bytes, {expected} expected for its size")]
    BufferLength {
        /// What was checked.
        what: String,
        /// Expected bytes.
        expected: usize,
        /// Found bytes.
        found: usize,
    },
    /// A premultiplied pixel has a colour channel above its alpha.
    #[error("{what}: pixel ({x}, {y}) is not premultiplied (colour {colour} > alpha {alpha})")]
    NotPremultiplied {
        /// What was checked.
        what: String,
        /// Pixel column.
        x: u32,
        /// Pixel row.
        y: u32,
        /// The larger colour value.
        colour: u8,
        /// Alpha value.
        alpha: u8,
    },
}
