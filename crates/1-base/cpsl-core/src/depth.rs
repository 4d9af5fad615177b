//! One interface for every source of per-pixel depth: monocular models, depth files, and
//! ground truth from synthetic scenes or datasets.

use thiserror::Error;

/// Why a depth source could not produce depth.
#[derive(Debug, Error)]
#[error("{source_name}: {cause}")]
pub struct DepthSourceError {
    /// The source's [`DepthSource::name`].
    pub source_name: String,
    /// The underlying error.
    pub cause: Box<dyn std::error::Error + Send + Sync>,
}

/// A source of z-depth (scene units along the optical axis) for an RGB frame. Sources are
/// `Send`: a video's driver runs one beside the layering of the frame before.
pub trait DepthSource: Send {
    /// A short human-readable description, saved with the output (e.g. `model fastdepth_7.onnx`).
    fn name(&self) -> String;
    /// Depth for `rgb` (3 bytes per pixel, row-major, `width x height`): one value per pixel.
    /// Missing values are NaN.
    fn depth(&mut self, rgb: &[u8], width: u32, height: u32) -> Result<Vec<f32>, DepthSourceError>;
}

/// Median of the finite positive values of a depth map; `None` when it has none.
pub fn median_depth(v: &[f32]) -> Option<f32> {
    let mut d: Vec<f32> = v
        .iter()
        .copied()
        .filter(|z| z.is_finite() && *z > 0.0)
        .collect();
    if d.is_empty() {
        return None;
    }
    let m = d.len() / 2;
    Some(*d.select_nth_unstable_by(m, f32::total_cmp).1)
}

/// A fixed depth map (ground truth from a synthetic scene or a dataset, or depth already read
/// from a file): returned for a frame of the same size.
#[derive(Debug, Clone)]
pub struct FixedDepth {
    /// Description.
    pub name: String,
    /// Width of the map.
    pub width: u32,
    /// Height of the map.
    pub height: u32,
    /// Depth values, row-major.
    pub depth: Vec<f32>,
}

impl DepthSource for FixedDepth {
    fn name(&self) -> String {
        self.name.clone()
    }

    fn depth(
        &mut self,
        _rgb: &[u8],
        width: u32,
        height: u32,
    ) -> Result<Vec<f32>, DepthSourceError> {
        if (width, height) != (self.width, self.height) {
            return Err(DepthSourceError {
                source_name: self.name(),
                cause: format!(
                    "depth is {}x{} but the image is {width}x{height}",
                    self.width, self.height
                )
                .into(),
            });
        }
        Ok(self.depth.clone())
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn fixed_depth_checks_size() {
        let mut d = FixedDepth {
            name: "gt".into(),
            width: 2,
            height: 1,
            depth: vec![1.0, 2.0],
        };
        assert_eq!(d.depth(&[0; 6], 2, 1).unwrap(), vec![1.0, 2.0]);
        let e = d.depth(&[0; 9], 3, 1).unwrap_err().to_string();
        assert!(
            e.contains("gt") && e.contains("2x1") && e.contains("3x1"),
            "{e}"
        );
    }
}
