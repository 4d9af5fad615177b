//! Dense motion between two frames, as the decoder's motion vectors or optical flow give it.

use crate::resample::resize_bilinear;

/// A dense motion field: per pixel `(dx, dy)` interleaved, pointing from a pixel of one frame
/// to where its content is in the other (see `cpsl-flow` for the convention of estimated
/// flow; decoder motion points to the previous frame).
#[derive(Debug, Clone, PartialEq)]
pub struct Flow {
    /// Width.
    pub width: usize,
    /// Height.
    pub height: usize,
    /// `[dx0, dy0, dx1, dy1, ...]`.
    pub data: Vec<f32>,
}

impl Flow {
    /// The flow at pixel `(x, y)`.
    #[inline]
    pub fn at(&self, x: usize, y: usize) -> (f32, f32) {
        let p = (y * self.width + x) * 2;
        (self.data[p], self.data[p + 1])
    }

    /// Bilinear resampling to `width x height` ([`crate::resample::resize_bilinear`]),
    /// vectors scaled with the size.
    pub fn resize(&self, width: usize, height: usize) -> Flow {
        let (sx, sy) = (
            width as f32 / self.width as f32,
            height as f32 / self.height as f32,
        );
        let mut data = resize_bilinear(&self.data, self.width, self.height, 2, width, height);
        for v in data.chunks_exact_mut(2) {
            v[0] *= sx;
            v[1] *= sy;
        }
        Flow {
            width,
            height,
            data,
        }
    }
}
