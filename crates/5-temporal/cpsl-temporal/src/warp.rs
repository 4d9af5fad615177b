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

/// [`warp_values`] of two per-pixel maps along the same flow (one pass: each pixel's source
/// is found once). Panics unless `a`, `b` and `flow` are `w x h`.
pub(crate) fn warp_values_pair(
    a: &[f32],
    b: &[f32],
    flow: &Flow,
    w: usize,
    h: usize,
) -> (Vec<f32>, Vec<f32>) {
    check(a, flow, w, h);
    check(b, flow, w, h);
    let (mut out_a, mut out_b) = (vec![0f32; w * h], vec![0f32; w * h]);
    out_a
        .par_chunks_mut(w)
        .zip(out_b.par_chunks_mut(w))
        .zip(flow.data.par_chunks(w * 2))
        .enumerate()
        .for_each(|(y, ((ra, rb), f))| {
            for (x, ((oa, ob), uv)) in ra.iter_mut().zip(rb).zip(f.chunks_exact(2)).enumerate() {
                let i = source(x, y, uv, w, h);
                (*oa, *ob) = (a[i], b[i]);
            }
        });
    (out_a, out_b)
}

fn check<T>(prev: &[T], flow: &Flow, w: usize, h: usize) {
    assert_eq!(prev.len(), w * h, "values for every pixel");
    assert_eq!(
        (flow.width, flow.height, flow.data.len()),
        (w, h, w * h * 2),
        "a flow of the frame's size"
    );
}

/// The previous frame's pixel nearest to where the flow `uv` at pixel `(x, y)` says it was
/// (clamped to the image).
#[inline(always)]
fn source(x: usize, y: usize, uv: &[f32], w: usize, h: usize) -> usize {
    let (xmax, ymax) = ((w - 1) as f32, (h - 1) as f32);
    // Rounded to nearest by truncating after the clamp (no libm call on the baseline target).
    let sx = (x as f32 + uv[0] + 0.5).clamp(0.0, xmax) as i32 as usize;
    let sy = (y as f32 + uv[1] + 0.5).clamp(0.0, ymax) as i32 as usize;
    sy * w + sx
}

/// Every pixel of this frame takes the value of the previous frame's pixel nearest to where
/// the flow says it was (clamped to the image).
fn warp_nearest<T: Copy + Default + Send + Sync>(
    prev: &[T],
    flow: &Flow,
    w: usize,
    h: usize,
) -> Vec<T> {
    check(prev, flow, w, h);
    let mut out = vec![T::default(); w * h];
    out.par_chunks_mut(w)
        .zip(flow.data.par_chunks(w * 2))
        .enumerate()
        .for_each(|(y, (row, f))| {
            for (x, (o, uv)) in row.iter_mut().zip(f.chunks_exact(2)).enumerate() {
                *o = prev[source(x, y, uv, w, h)];
            }
        });
    out
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn a_pair_warps_as_each_map_alone() {
        let (w, h) = (13, 7);
        let flow = Flow {
            width: w,
            height: h,
            data: (0..w * h * 2)
                .map(|i| ((i * 37) % 11) as f32 - 5.3)
                .collect(),
        };
        let a: Vec<f32> = (0..w * h).map(|i| i as f32).collect();
        let b: Vec<f32> = (0..w * h).map(|i| -(i as f32) * 0.5).collect();
        let (pa, pb) = warp_values_pair(&a, &b, &flow, w, h);
        assert_eq!(pa, warp_values(&a, &flow, w, h));
        assert_eq!(pb, warp_values(&b, &flow, w, h));
        // Not the identity: the flow moves pixels.
        assert_ne!(pa, a);
    }
}
