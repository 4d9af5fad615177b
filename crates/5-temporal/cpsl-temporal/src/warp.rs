//! Nearest-pixel warping of per-pixel labels and values along a motion field.

use cpsl_core::Flow;
use rayon::prelude::*;

/// Carries labels of the previous frame to this one (nearest). Panics unless `prev` and
/// `flow` are `w x h`.
pub fn warp_labels(prev: &[u8], flow: &Flow, w: usize, h: usize) -> Vec<u8> {
    warp_nearest(prev, flow, w, h)
}

/// Carries per-pixel values of the previous frame to this one (nearest, so depth is never
/// mixed across an edge). Panics unless `prev` and `flow` are `w x h`.
pub fn warp_values(prev: &[f32], flow: &Flow, w: usize, h: usize) -> Vec<f32> {
    warp_nearest(prev, flow, w, h)
}

/// Every pixel of this frame takes the value of the previous frame's pixel nearest to where
/// the flow says it was (clamped to the image).
fn warp_nearest<T: Copy + Default + Send + Sync>(
    prev: &[T],
    flow: &Flow,
    w: usize,
    h: usize,
) -> Vec<T> {
    assert_eq!(prev.len(), w * h, "values for every pixel");
    assert_eq!(
        (flow.width, flow.height, flow.data.len()),
        (w, h, w * h * 2),
        "a flow of the frame's size"
    );
    let mut out = vec![T::default(); w * h];
    let (xmax, ymax) = ((w - 1) as f32, (h - 1) as f32);
    out.par_chunks_mut(w)
        .zip(flow.data.par_chunks(w * 2))
        .enumerate()
        .for_each(|(y, (row, f))| {
            for (x, (o, uv)) in row.iter_mut().zip(f.chunks_exact(2)).enumerate() {
                // Rounded to nearest by truncating after the clamp (no libm call on the
                // baseline target).
                let sx = (x as f32 + uv[0] + 0.5).clamp(0.0, xmax) as i32 as usize;
                let sy = (y as f32 + uv[1] + 0.5).clamp(0.0, ymax) as i32 as usize;
                *o = prev[sy * w + sx];
            }
        });
    out
}
