//! Temporal stability metrics of a layered or rendered video (paper Table 2).
//!
//! All of them compensate the motion of the input: [`ClipMotion`] holds the dense flow from every
//! frame `t + 1` back to frame `t` of the *input* video (estimated with [`cpsl_flow`] on a
//! 320 px grid), with a forward-backward check marking the pixels visible in both frames.
//!
//! * **Boundary variance**: the mean squared distance (pixels^2, capped at 10 px) from where the
//!   flow carries each alpha-contour pixel of frame `t + 1` ([`alpha_owner`]: where the nearest
//!   layer with alpha >= 1/2 changes) back to frame `t`, to the contours of frame `t`;
//!   how much contours move beyond the motion of the content. Reported relative to frame-wise
//!   depth slicing on the same clip (slicing = 1.00), as in the paper.
//! * **F-SSIM**: mean SSIM between output frame `t` and output frame `t + 1` warped back by the
//!   flow, over the pixels visible in both, divided by the same score of the input video (1 = as
//!   stable as the input).
//! * **Warping error**: mean absolute difference (in [0, 1]) between output frame `t` and frame
//!   `t + 1` warped back, over the same pixels.
//! * **Flicker** (tLP): mean over `t` of `|d(g_t, g_{t-1}) - d(o_t, o_{t-1})|` for a perceptual
//!   distance `d` (LPIPS), output `o` and reference `g`.

use crate::metrics::ssim;
use cpsl_core::LayerSet;
use cpsl_flow::{flow, Flow, FlowConfig, FlowMethod, Grey};
use cpsl_layering::grid::distance;

/// Input motion between consecutive frames.
#[derive(Debug, Clone)]
pub struct ClipMotion {
    /// Width.
    pub width: usize,
    /// Height.
    pub height: usize,
    /// `back[t]`: flow from frame `t + 1` to frame `t`, full resolution.
    pub back: Vec<Flow>,
    /// `valid[t]`: pixels of frame `t + 1` whose match in frame `t` maps back within 1 px.
    pub valid: Vec<Vec<bool>>,
}

impl ClipMotion {
    /// Estimates the motion of RGB frames (3 bytes per pixel) of `width x height`.
    ///
    /// # Panics
    /// If a frame's size is wrong.
    pub fn estimate(frames: &[Vec<u8>], width: usize, height: usize) -> Self {
        let (w, h) = (width, height);
        let greys: Vec<Grey> = frames
            .iter()
            .map(|f| {
                assert_eq!(f.len(), w * h * 3, "ClipMotion::estimate: frame size");
                Grey::from_rgb8_scaled(f, w, h, 320)
            })
            .collect();
        // The metrics' motion stays the Lucas-Kanade flow of the earlier tables, whatever the
        // layerer's default.
        let cfg = FlowConfig {
            method: FlowMethod::LucasKanade,
            ..FlowConfig::default()
        };
        let (mut back, mut valid) = (Vec::new(), Vec::new());
        for pair in greys.windows(2) {
            let b = flow(&pair[1], &pair[0], &cfg)
                .expect("same size")
                .resize(w, h);
            let f = flow(&pair[0], &pair[1], &cfg)
                .expect("same size")
                .resize(w, h);
            let ok = (0..w * h)
                .map(|p| {
                    let (x, y) = ((p % w) as f32, (p / w) as f32);
                    let (u, v) = b.at(p % w, p / w);
                    let (sx, sy) = (x + u, y + v);
                    if sx < 0.0 || sy < 0.0 || sx > (w - 1) as f32 || sy > (h - 1) as f32 {
                        return false;
                    }
                    let (fu, fv) = f.at(sx.round() as usize, sy.round() as usize);
                    (u + fu).powi(2) + (v + fv).powi(2) <= 1.0
                })
                .collect();
            back.push(b);
            valid.push(ok);
        }
        Self {
            width: w,
            height: h,
            back,
            valid,
        }
    }

    /// The pixel of frame `t` that pixel `p` of frame `t + 1` shows.
    fn source(&self, t: usize, p: usize) -> usize {
        let (w, h) = (self.width, self.height);
        let (u, v) = self.back[t].at(p % w, p / w);
        let sx = ((p % w) as f32 + u).round().clamp(0.0, (w - 1) as f32) as usize;
        let sy = ((p / w) as f32 + v).round().clamp(0.0, (h - 1) as f32) as usize;
        sy * w + sx
    }

    /// Output frames `t` and `t + 1` lined up in frame `t + 1`'s pixels: `prev` sampled at
    /// each pixel's match in frame `t`, `next` as it is, and the pixels visible in both.
    fn align_next(&self, t: usize, prev: &[u8], next: &[u8]) -> (Vec<u8>, Vec<u8>, Vec<bool>) {
        let n = self.width * self.height;
        let mut a = vec![0u8; n * 3];
        for p in 0..n {
            let q = self.source(t, p);
            a[p * 3..p * 3 + 3].copy_from_slice(&prev[q * 3..q * 3 + 3]);
        }
        (a, next.to_vec(), self.valid[t].clone())
    }
}

/// The alpha contours of a layer set as a label map: per pixel, the nearest layer whose alpha
/// is at least one half (the layer count where none is). Boundary variance on these maps
/// follows the `alpha = 1/2` contour of every layer that is visible at the reference view.
pub fn alpha_owner(set: &LayerSet) -> Vec<u8> {
    let n = (set.camera().width * set.camera().height) as usize;
    (0..n)
        .map(|p| {
            set.layers()
                .iter()
                .position(|l| l.image.as_bytes()[p * 4 + 3] >= 128)
                .unwrap_or(set.len()) as u8
        })
        .collect()
}

/// Layer-boundary pixels of an owner map (a 4-neighbour has another label), on both sides.
fn boundary(owner: &[u8], w: usize, h: usize) -> Vec<bool> {
    (0..w * h)
        .map(|p| {
            let (x, y) = (p % w, p / w);
            (x + 1 < w && owner[p + 1] != owner[p])
                || (x > 0 && owner[p - 1] != owner[p])
                || (y + 1 < h && owner[p + w] != owner[p])
                || (y > 0 && owner[p - w] != owner[p])
        })
        .collect()
}

/// Mean squared distance (capped at 10 px) of each frame's boundary from the previous
/// frame's boundary (widened by one pixel), measured in the previous frame at the points the
/// input motion carries the boundary's pixels back to, over all frames after the first (see
/// the module documentation). Each boundary is a pair of 4-neighbours with different labels;
/// it moves with whichever side's motion explains it best (the other side is being uncovered
/// or covered). Measuring in the previous frame keeps a boundary a pixel ahead of an
/// occluding edge at a pixel: the set of pixels whose motion lands on the previous boundary
/// can be empty there. `owners[t]` is frame `t`'s layer index per pixel.
///
/// # Panics
/// If the counts or sizes disagree.
pub fn boundary_variance(owners: &[Vec<u8>], motion: &ClipMotion) -> f64 {
    let (w, h) = (motion.width, motion.height);
    assert_eq!(
        owners.len(),
        motion.back.len() + 1,
        "one owner map per frame"
    );
    let (mut sum, mut n) = (0f64, 0u64);
    for t in 0..motion.back.len() {
        // Distance in frame t to its boundary.
        let d = distance(&boundary(&owners[t], w, h), w, h);
        let cur = &owners[t + 1];
        let ok = &motion.valid[t];
        for p in 0..w * h {
            let (x, y) = (p % w, p / w);
            for q in [(x + 1 < w).then(|| p + 1), (y + 1 < h).then(|| p + w)]
                .into_iter()
                .flatten()
            {
                if cur[p] == cur[q] || !(ok[p] || ok[q]) {
                    continue;
                }
                // Where each side of the boundary came from, against the previous boundary;
                // a pixel's 4-neighbours count as its side too (a contour may sit a pixel off
                // the surface whose motion carries it).
                let at = |p: usize| {
                    if !ok[p] {
                        return f32::INFINITY;
                    }
                    let (x, y) = (p % w, p / w);
                    [
                        Some(p),
                        (x > 0).then(|| p - 1),
                        (x + 1 < w).then(|| p + 1),
                        (y > 0).then(|| p - w),
                        (y + 1 < h).then(|| p + w),
                    ]
                    .into_iter()
                    .flatten()
                    .filter(|&r| ok[r])
                    .map(|r| d[motion.source(t, r)])
                    .fold(f32::INFINITY, f32::min)
                };
                let (dp, dq) = (at(p), at(q));
                sum += (dp.min(dq).min(10.0) as f64).powi(2);
                n += 1;
            }
        }
    }
    if n == 0 {
        0.0
    } else {
        sum / n as f64
    }
}

/// Mean over consecutive pairs of the SSIM between output frame `t` carried along the motion
/// and frame `t + 1`, over the pixels visible in both.
fn pair_ssim(frames: &[Vec<u8>], motion: &ClipMotion) -> f64 {
    let (w, h) = (motion.width, motion.height);
    let s: f64 = (0..motion.back.len())
        .map(|t| {
            let (a, b, m) = motion.align_next(t, &frames[t], &frames[t + 1]);
            ssim(&a, &b, w, h, Some(&m))
        })
        .sum();
    s / motion.back.len().max(1) as f64
}

/// F-SSIM of `output` relative to `input` (see the module documentation).
///
/// # Panics
/// If the counts or sizes disagree.
pub fn f_ssim(output: &[Vec<u8>], input: &[Vec<u8>], motion: &ClipMotion) -> f64 {
    assert_eq!(output.len(), input.len(), "f_ssim: frame counts");
    pair_ssim(output, motion) / pair_ssim(input, motion).max(1e-9)
}

/// Warping error of `output` (see the module documentation).
///
/// # Panics
/// If the counts or sizes disagree.
pub fn warping_error(output: &[Vec<u8>], motion: &ClipMotion) -> f64 {
    let (mut sum, mut n) = (0f64, 0u64);
    for t in 0..motion.back.len() {
        let (a, b, m) = motion.align_next(t, &output[t], &output[t + 1]);
        for p in (0..m.len()).filter(|&p| m[p]) {
            for c in 0..3 {
                sum += (a[p * 3 + c] as f64 - b[p * 3 + c] as f64).abs() / 255.0;
            }
            n += 3;
        }
    }
    if n == 0 {
        0.0
    } else {
        sum / n as f64
    }
}

/// Flicker (tLP): mean of `|d(g_t, g_{t-1}) - d(o_t, o_{t-1})|` over `t >= 1`.
///
/// # Panics
/// If the counts disagree.
pub fn flicker(
    output: &[Vec<u8>],
    reference: &[Vec<u8>],
    mut d: impl FnMut(&[u8], &[u8]) -> f64,
) -> f64 {
    assert_eq!(output.len(), reference.len(), "flicker: frame counts");
    let terms: Vec<f64> = (1..output.len())
        .map(|t| (d(&reference[t], &reference[t - 1]) - d(&output[t], &output[t - 1])).abs())
        .collect();
    terms.iter().sum::<f64>() / terms.len().max(1) as f64
}

#[cfg(test)]
mod tests {
    use super::*;

    fn textured(w: usize, h: usize, shift: f32) -> Vec<u8> {
        (0..w * h)
            .flat_map(|p| {
                let (x, y) = ((p % w) as f32 - shift, (p / w) as f32);
                let v = 128.0 + 60.0 * (x * 0.21).sin() + 50.0 * (y * 0.17 + x * 0.05).cos();
                [v as u8, (255.0 - v) as u8, (v * 0.5) as u8]
            })
            .collect()
    }

    #[test]
    fn steady_video_scores_perfectly_and_jitter_does_not() {
        let (w, h) = (96, 64);
        // The content moves right by 2 px per frame.
        let frames: Vec<Vec<u8>> = (0..4).map(|t| textured(w, h, 2.0 * t as f32)).collect();
        let motion = ClipMotion::estimate(&frames, w, h);
        // A boundary that moves with the content has no variance; one that jumps 5 px against
        // it has 3 px left beyond the one-pixel tolerance on either side, 9 px^2.
        let owner =
            |edge: usize| -> Vec<u8> { (0..w * h).map(|p| (p % w >= edge) as u8).collect() };
        let steady: Vec<Vec<u8>> = (0..4).map(|t| owner(40 + 2 * t)).collect();
        let jitter: Vec<Vec<u8>> = (0..4).map(|t| owner(40 + 2 * t + 5 * (t % 2))).collect();
        let bs = boundary_variance(&steady, &motion);
        let bj = boundary_variance(&jitter, &motion);
        eprintln!("boundary variance: steady {bs:.3}, jitter {bj:.3}");
        assert!(bs < 0.2, "steady {bs}");
        assert!(bj > 8.0, "jitter {bj}");
        // An occluder (right of the edge) moving left over a still background by 4 px per
        // frame, its contour a pixel ahead of its true edge: a pixel off, no more (no pixel's
        // motion lands on the previous boundary there: measured in the current frame, this
        // scored the 10 px cap).
        let still: Vec<Vec<u8>> = (0..4).map(|_| textured(w, h, 0.0)).collect();
        let mut occluding = ClipMotion::estimate(&still, w, h);
        for (t, (f, v)) in occluding
            .back
            .iter_mut()
            .zip(&mut occluding.valid)
            .enumerate()
        {
            for (p, (uv, ok)) in f.data.chunks_exact_mut(2).zip(v.iter_mut()).enumerate() {
                let moving = p % w >= 60 - 4 * (t + 1);
                uv[0] = if moving { 4.0 } else { 0.0 };
                *ok = true;
            }
        }
        let ahead: Vec<Vec<u8>> = (0..4).map(|t| owner(60 - 4 * t - 1)).collect();
        let ba = boundary_variance(&ahead, &occluding);
        eprintln!("a pixel ahead of an occluding edge: {ba:.3}");
        assert!(ba <= 1.0 + 1e-9, "a pixel ahead of an occluding edge {ba}");
        // The input is as stable as itself; a flickering copy is not.
        assert!((f_ssim(&frames, &frames, &motion) - 1.0).abs() < 1e-9);
        assert!(warping_error(&frames, &motion) < 0.03);
        let flickering: Vec<Vec<u8>> = frames
            .iter()
            .enumerate()
            .map(|(t, f)| {
                f.iter()
                    .map(|&v| v.saturating_add(40 * (t % 2) as u8))
                    .collect()
            })
            .collect();
        assert!(f_ssim(&flickering, &frames, &motion) < 0.99);
        assert!(warping_error(&flickering, &motion) > warping_error(&frames, &motion) + 0.05);
        let mean_abs = |a: &[u8], b: &[u8]| {
            a.iter()
                .zip(b)
                .map(|(&x, &y)| (x as f64 - y as f64).abs())
                .sum::<f64>()
                / a.len() as f64
        };
        assert_eq!(flicker(&frames, &frames, mean_abs), 0.0);
        assert!(flicker(&flickering, &frames, mean_abs) > 10.0);
    }
}
