//! Resource limits that every reader checks before allocating.

use serde::{Deserialize, Serialize};

/// Bounds on the size of what a reader accepts. The defaults are generous for real content
/// (8K frames, 64 layers) and stop absurd or hostile inputs before memory is allocated.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize)]
pub struct Limits {
    /// Largest accepted width or height, in pixels (default 16384).
    pub max_side: u32,
    /// Largest accepted pixel count of one image (default 64 Mpx: 8K UHD is 33 Mpx).
    pub max_pixels: u64,
    /// Largest accepted number of layers in one layer set (default 64).
    pub max_layers: usize,
    /// Largest accepted manifest file, in bytes (default 16 MiB: version 2 manifests hold mesh
    /// layers' grids inline).
    pub max_manifest_bytes: u64,
    /// Largest accepted single file (an encoded layer image), in bytes (default 512 MiB).
    pub max_file_bytes: u64,
}

impl Default for Limits {
    fn default() -> Self {
        Self {
            max_side: 16_384,
            max_pixels: 64 * 1024 * 1024,
            max_layers: 64,
            max_manifest_bytes: 16 << 20,
            max_file_bytes: 512 << 20,
        }
    }
}

impl Limits {
    /// Checks an image size against the limits.
    pub fn check_size(&self, what: &str, width: u32, height: u32) -> Result<(), crate::CoreError> {
        if width == 0 || height == 0 {
            return Err(crate::CoreError::ZeroSize {
                what: what.into(),
                width,
                height,
            });
        }
        if width > self.max_side
            || height > self.max_side
            || width as u64 * height as u64 > self.max_pixels
        {
            return Err(crate::CoreError::TooLarge {
                what: what.into(),
                width,
                height,
                max_side: self.max_side,
                max_pixels: self.max_pixels,
            });
        }
        Ok(())
    }
}
