//! Errors of layer generation.

use thiserror::Error;

/// Why layers could not be built.
#[derive(Debug, Error, Clone, PartialEq)]
pub enum LayeringError {
    /// Colour and depth buffers do not match the camera.
    #[error("{what}: {found} values, {expected} expected for a {width}x{height} camera")]
    Size {
        /// Which input.
        what: &'static str,
        /// Values found.
        found: usize,
        /// Values expected.
        expected: usize,
        /// Camera width.
        width: u32,
        /// Camera height.
        height: u32,
    },
    /// The depth map has no finite positive value.
    #[error("depth map has no finite positive value")]
    NoValidDepth,
    /// A depth value is negative, zero or infinite.
    #[error("depth at pixel ({x}, {y}) is {value}: depth must be finite and > 0 (NaN marks a missing value)")]
    BadDepth {
        /// Column.
        x: usize,
        /// Row.
        y: usize,
        /// The value.
        value: f32,
    },
    /// The depth map has missing (NaN) values and missing depth is not allowed.
    #[error("depth map has {count} missing (NaN) values, the first at pixel ({x}, {y}); allow missing depth to fill them from their neighbours")]
    MissingDepth {
        /// Number of missing values.
        count: usize,
        /// Column of the first.
        x: usize,
        /// Row of the first.
        y: usize,
    },
    /// A configuration value is out of range.
    #[error("{field} must be in {range}, found {found}")]
    Config {
        /// Field name.
        field: &'static str,
        /// Accepted range.
        range: &'static str,
        /// Value found.
        found: String,
    },
    /// The result broke a layer-set invariant (a bug, reported rather than panicking).
    #[error("layer set invalid: {0}")]
    Invalid(#[from] cpsl_core::CoreError),
}

/// Checks that `rgb` (3 bytes per pixel) and `depth` (one value per pixel) fit a
/// `width x height` frame.
pub(crate) fn check_frame(
    rgb: &[u8],
    depth: &[f32],
    width: u32,
    height: u32,
) -> Result<(), LayeringError> {
    let n = width as usize * height as usize;
    for (what, found, expected) in [("colour", rgb.len(), n * 3), ("depth", depth.len(), n)] {
        if found != expected {
            return Err(LayeringError::Size {
                what,
                found,
                expected,
                width,
                height,
            });
        }
    }
    Ok(())
}
