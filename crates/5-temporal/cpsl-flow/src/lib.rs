//! Dense optical flow between two grey images, coarse to fine, by one of two methods
//! ([`FlowMethod`]):
//!
//! - **DIS** (the default): OpenCV's Dense Inverse Search (Kroeger et al. 2016) at its fast
//!   preset, down to full resolution, without its variational refinement, on the images
//!   rounded to 8 bits (the settings `cpsl-track` takes for its multi-view depth), then
//!   [`POLISH_STEPS`] Lucas-Kanade steps on the full-precision images. Images whose smaller
//!   side is under [`DIS_MIN_SIDE`] take Lucas-Kanade.
//! - **Lucas-Kanade**, the crate's own: at every level of a factor-2 pyramid (coarsest first,
//!   the flow of the level above doubled as the start), a few Gauss-Newton steps of dense
//!   Lucas-Kanade: the second image is warped by the current flow, and each pixel solves the
//!   2x2 normal equations of the brightness-constancy residual summed over a `(2r+1)^2`
//!   window (box filtered), with a small Tikhonov term so that flat regions keep the flow
//!   they have; a 3x3 median of each component after every step removes outliers at motion
//!   boundaries. Its pyramid reaches further on small images: DIS's coarsest level is an
//!   eighth of a 320x180 grid, so it follows 20 pixels of motion there, not 30.
//!
//! On eight pairs of fox frames at the video layering's flow grid (180x320), DIS's flows
//! (before the polish) leave a smaller photometric residual than Lucas-Kanade's on seven; with
//! the polish a flow there takes 17.5 ms against Lucas-Kanade's 28.6, and the fox's coded
//! novel views gain up to 0.5 dB (BENCHMARKS.md and EVALUATION.md, "Optical flow").
//!
//! Convention: `flow(a, b)` returns `u` with `a(x) ~ b(x + u(x))` (per pixel `(dx, dy)`), i.e. the
//! position in `b` of what `a` shows at `x`: sampling anything attached to `b` at `x + u(x)`
//! carries it to `a` (backward warping).

use rayon::prelude::*;
use serde::{Deserialize, Serialize};
use thiserror::Error;

/// A grey image in `[0, 1]`, row major.
#[derive(Debug, Clone, PartialEq)]
pub struct Grey {
    /// Width.
    pub width: usize,
    /// Height.
    pub height: usize,
    /// Pixels.
    pub data: Vec<f32>,
}

pub use cpsl_core::Flow;

/// Lucas-Kanade steps (at the finest level, with the configuration's window) that polish a
/// DIS flow: on the synthetic 1080p clip of `cpsl eval-rd` DIS alone lost 0.3-0.4 dB against
/// Lucas-Kanade, one step 0.1, two none; the fox keeps DIS's gain with them.
pub const POLISH_STEPS: usize = 2;

/// Smallest side of an image DIS takes (two of its 8-pixel patches); smaller images take
/// Lucas-Kanade.
pub const DIS_MIN_SIDE: usize = 16;

/// Flow errors.
#[derive(Debug, Error, PartialEq)]
pub enum FlowError {
    /// The images differ in size or do not match their data.
    #[error("images of {a:?} and {b:?} pixels cannot be compared (both must be the same, non-empty and match their data)")]
    Size {
        /// First image's size.
        a: (usize, usize),
        /// Second image's size.
        b: (usize, usize),
    },
    /// OpenCV failed (its message).
    #[error("OpenCV's DIS optical flow failed: {0}")]
    Dis(String),
}

impl From<opencv::Error> for FlowError {
    fn from(e: opencv::Error) -> Self {
        Self::Dis(e.to_string())
    }
}

/// How [`flow`] estimates the motion.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default, Serialize, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum FlowMethod {
    /// OpenCV's Dense Inverse Search, polished by Lucas-Kanade (see the crate
    /// documentation).
    #[default]
    Dis,
    /// The crate's coarse-to-fine Lucas-Kanade, set by the rest of [`FlowConfig`].
    LucasKanade,
}

/// Flow configuration.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct FlowConfig {
    /// The method; the other fields set Lucas-Kanade.
    pub method: FlowMethod,
    /// Window radius `r` of the local least squares.
    pub radius: usize,
    /// Gauss-Newton steps per level.
    pub iterations: usize,
    /// Coarsest level's smaller side is at least this.
    pub min_side: usize,
    /// Tikhonov weight, relative to the window area.
    pub regularisation: f32,
}

impl Default for FlowConfig {
    fn default() -> Self {
        Self {
            method: FlowMethod::default(),
            radius: 3,
            iterations: 4,
            min_side: 8,
            regularisation: 1e-6,
        }
    }
}

/// Rec. 709 luma of an RGB byte triple, in [0, 1].
#[inline]
fn luma(p: &[u8]) -> f32 {
    (0.2126 * p[0] as f32 + 0.7152 * p[1] as f32 + 0.0722 * p[2] as f32) / 255.0
}

impl Grey {
    /// From interleaved RGB bytes (Rec. 709 luma).
    pub fn from_rgb8(rgb: &[u8], width: usize, height: usize) -> Self {
        let data = rgb.chunks_exact(3).map(luma).collect();
        Self {
            width,
            height,
            data,
        }
    }

    /// From interleaved RGB bytes, area-averaged down so that the long side is at most `side`.
    pub fn from_rgb8_scaled(rgb: &[u8], width: usize, height: usize, side: usize) -> Self {
        let (w, h) = (width, height);
        let s = (side as f32 / w.max(h) as f32).min(1.0);
        if s >= 1.0 {
            return Self::from_rgb8(rgb, width, height);
        }
        let (gw, gh) = (
            ((w as f32 * s).round() as usize).max(1),
            ((h as f32 * s).round() as usize).max(1),
        );
        let mut data = vec![0f32; gw * gh];
        data.par_chunks_mut(gw).enumerate().for_each(|(y, row)| {
            let (y0, y1) = (y * h / gh, ((y + 1) * h / gh).max(y * h / gh + 1));
            for (x, o) in row.iter_mut().enumerate() {
                let (x0, x1) = (x * w / gw, ((x + 1) * w / gw).max(x * w / gw + 1));
                // The luma of each pixel as `from_rgb8` has it, summed in the same order.
                let sum: f32 = (y0..y1)
                    .map(|yy| {
                        rgb[(yy * w + x0) * 3..(yy * w + x1) * 3]
                            .chunks_exact(3)
                            .map(luma)
                            .sum::<f32>()
                    })
                    .sum();
                *o = sum / ((y1 - y0) * (x1 - x0)) as f32;
            }
        });
        Self {
            width: gw,
            height: gh,
            data,
        }
    }

    /// Bilinear sample with clamping to the border.
    #[inline]
    pub fn sample(&self, x: f32, y: f32) -> f32 {
        let x = x.clamp(0.0, (self.width - 1) as f32);
        let y = y.clamp(0.0, (self.height - 1) as f32);
        // Non-negative after the clamp: truncation is the floor, without a libm call on the
        // baseline target.
        let (x0, y0) = (x as usize, y as usize);
        let (x1, y1) = ((x0 + 1).min(self.width - 1), (y0 + 1).min(self.height - 1));
        let (fx, fy) = (x - x0 as f32, y - y0 as f32);
        let d = &self.data;
        let w = self.width;
        let top = d[y0 * w + x0] * (1.0 - fx) + d[y0 * w + x1] * fx;
        let bot = d[y1 * w + x0] * (1.0 - fx) + d[y1 * w + x1] * fx;
        top * (1.0 - fy) + bot * fy
    }

    /// Half size, 2x2 average.
    fn half(&self) -> Self {
        let (w, h) = (self.width.div_ceil(2), self.height.div_ceil(2));
        let mut data = vec![0f32; w * h];
        for y in 0..h {
            for x in 0..w {
                let mut s = 0.0;
                for (dy, dx) in [(0, 0), (0, 1), (1, 0), (1, 1)] {
                    let sx = (2 * x + dx).min(self.width - 1);
                    let sy = (2 * y + dy).min(self.height - 1);
                    s += self.data[sy * self.width + sx];
                }
                data[y * w + x] = s / 4.0;
            }
        }
        Self {
            width: w,
            height: h,
            data,
        }
    }
}

/// Sum over the `(2r+1)^2` window around every pixel (clamped to the image), separably.
fn box_sum(src: &[f32], w: usize, h: usize, r: usize) -> Vec<f32> {
    let mut tmp = vec![0f32; w * h];
    tmp.par_chunks_mut(w).enumerate().for_each(|(y, row)| {
        let s = &src[y * w..(y + 1) * w];
        let mut acc: f32 = s[..(r + 1).min(w)].iter().sum();
        for (x, o) in row.iter_mut().enumerate() {
            *o = acc;
            if x + r + 1 < w {
                acc += s[x + r + 1];
            }
            if x >= r {
                acc -= s[x - r];
            }
        }
    });
    // Down the columns, a row at a time (each column's sums in the same order as walking
    // it; -0.0 starts them as `Sum` does).
    let mut out = vec![0f32; w * h];
    let mut acc = vec![-0.0f32; w];
    for row in tmp.chunks_exact(w).take((r + 1).min(h)) {
        acc.iter_mut().zip(row).for_each(|(a, &t)| *a += t);
    }
    for (y, o) in out.chunks_exact_mut(w).enumerate() {
        o.copy_from_slice(&acc);
        if y + r + 1 < h {
            let add = &tmp[(y + r + 1) * w..][..w];
            acc.iter_mut().zip(add).for_each(|(a, &t)| *a += t);
        }
        if y >= r {
            let sub = &tmp[(y - r) * w..][..w];
            acc.iter_mut().zip(sub).for_each(|(a, &t)| *a -= t);
        }
    }
    out
}

/// 3x3 median of one flow component (border pixels use their in-image neighbours).
fn median3(flow: &mut [f32], w: usize, h: usize, c: usize) {
    let src: Vec<f32> = flow.iter().skip(c).step_by(2).copied().collect();
    flow.par_chunks_mut(w * 2).enumerate().for_each(|(y, row)| {
        for x in 0..w {
            let mut v = [0f32; 9];
            let mut n = 0;
            for yy in y.saturating_sub(1)..(y + 2).min(h) {
                for xx in x.saturating_sub(1)..(x + 2).min(w) {
                    v[n] = src[yy * w + xx];
                    n += 1;
                }
            }
            row[x * 2 + c] = match n {
                9 => median9(v),
                _ => {
                    let v = &mut v[..n];
                    v.sort_unstable_by(f32::total_cmp);
                    v[n / 2]
                }
            };
        }
    });
}

/// The median of nine values in [`f32::total_cmp`]'s order (what sorting them and taking the
/// middle one gives), by a network of 19 compare-exchanges (Paeth's, as in Devillard's
/// `opt_med9`) on integer keys of that order.
fn median9(v: [f32; 9]) -> f32 {
    // The key orders as `total_cmp` does: negative values' magnitude bits flipped.
    let key = |f: f32| {
        let b = f.to_bits() as i32;
        b ^ (((b >> 31) as u32) >> 1) as i32
    };
    let mut p = v.map(key);
    let mut s = |a: usize, b: usize| {
        let (lo, hi) = (p[a].min(p[b]), p[a].max(p[b]));
        (p[a], p[b]) = (lo, hi);
    };
    for (a, b) in [
        (1, 2),
        (4, 5),
        (7, 8),
        (0, 1),
        (3, 4),
        (6, 7),
        (1, 2),
        (4, 5),
        (7, 8),
        (0, 3),
        (5, 8),
        (4, 7),
        (3, 6),
        (1, 4),
        (2, 5),
        (4, 7),
        (4, 2),
        (6, 4),
        (4, 2),
    ] {
        s(a, b);
    }
    // The key is its own inverse.
    f32::from_bits(key(f32::from_bits(p[4] as u32)) as u32)
}

/// One level: Gauss-Newton steps from `flow`.
fn refine(a: &Grey, b: &Grey, flow: &mut [f32], cfg: &FlowConfig) {
    let (w, h) = (a.width, a.height);
    let n = w * h;
    // Gradients of `a` (central differences): the template's, fixed over the steps.
    let mut gx = vec![0f32; n];
    let mut gy = vec![0f32; n];
    for y in 0..h {
        for x in 0..w {
            let at = |xx: usize, yy: usize| a.data[yy * w + xx];
            gx[y * w + x] = (at((x + 1).min(w - 1), y) - at(x.saturating_sub(1), y)) * 0.5;
            gy[y * w + x] = (at(x, (y + 1).min(h - 1)) - at(x, y.saturating_sub(1))) * 0.5;
        }
    }
    let r = cfg.radius;
    let sxx = box_sum(&gx.iter().map(|v| v * v).collect::<Vec<_>>(), w, h, r);
    let sxy = box_sum(
        &gx.iter().zip(&gy).map(|(a, b)| a * b).collect::<Vec<_>>(),
        w,
        h,
        r,
    );
    let syy = box_sum(&gy.iter().map(|v| v * v).collect::<Vec<_>>(), w, h, r);
    let lambda = cfg.regularisation * ((2 * r + 1) * (2 * r + 1)) as f32;
    // Reliability of each pixel's estimate: the smaller eigenvalue of its normal matrix
    // (small along edges, where only the normal component is known, and in flat regions).
    let conf: Vec<f32> = (0..n)
        .map(|p| {
            let (t, d) = (sxx[p] + syy[p], sxx[p] * syy[p] - sxy[p] * sxy[p]);
            (0.5 * (t - (t * t - 4.0 * d).max(0.0).sqrt())).max(0.0) + 1e-12
        })
        .collect();
    let cbox = box_sum(&conf, w, h, r);
    for _ in 0..cfg.iterations {
        // Residual of the warped second image.
        let it: Vec<f32> = (0..n)
            .into_par_iter()
            .map(|p| {
                let (x, y) = (
                    (p % w) as f32 + flow[p * 2],
                    (p / w) as f32 + flow[p * 2 + 1],
                );
                // No evidence where the match falls outside the second image.
                let inside = x >= 0.0 && y >= 0.0 && x <= (w - 1) as f32 && y <= (h - 1) as f32;
                if inside {
                    b.sample(x, y) - a.data[p]
                } else {
                    0.0
                }
            })
            .collect();
        let bx = box_sum(
            &gx.iter().zip(&it).map(|(g, t)| g * t).collect::<Vec<_>>(),
            w,
            h,
            r,
        );
        let by = box_sum(
            &gy.iter().zip(&it).map(|(g, t)| g * t).collect::<Vec<_>>(),
            w,
            h,
            r,
        );
        flow.par_chunks_mut(2).enumerate().for_each(|(p, f)| {
            let (a11, a12, a22) = (sxx[p] + lambda, sxy[p], syy[p] + lambda);
            let det = a11 * a22 - a12 * a12;
            if det <= 0.0 {
                return;
            }
            // Inverse compositional step: b(x + u) ~ a(x) - grad a . du  =>  du = -A^-1 g.
            let (du, dv) = (
                (a22 * bx[p] - a12 * by[p]) / det,
                (a11 * by[p] - a12 * bx[p]) / det,
            );
            f[0] -= du.clamp(-2.0, 2.0);
            f[1] -= dv.clamp(-2.0, 2.0);
        });
        // Reliable estimates fill in the aperture-limited ones around them.
        for c in 0..2 {
            let weighted: Vec<f32> = (0..n).map(|p| flow[p * 2 + c] * conf[p]).collect();
            let sum = box_sum(&weighted, w, h, r);
            for p in 0..n {
                flow[p * 2 + c] = sum[p] / cbox[p];
            }
            median3(flow, w, h, c);
        }
    }
}

/// Dense flow from `a` to `b` (see the module documentation for the convention and the
/// methods).
pub fn flow(a: &Grey, b: &Grey, cfg: &FlowConfig) -> Result<Flow, FlowError> {
    let ok = |g: &Grey| g.width > 0 && g.height > 0 && g.data.len() == g.width * g.height;
    if !ok(a) || !ok(b) || (a.width, a.height) != (b.width, b.height) {
        return Err(FlowError::Size {
            a: (a.width, a.height),
            b: (b.width, b.height),
        });
    }
    match cfg.method {
        FlowMethod::Dis if a.width.min(a.height) >= DIS_MIN_SIDE => {
            let mut f = dis(a, b)?;
            // DIS sees the pictures in 8 bits: Lucas-Kanade steps on the full-precision
            // images polish its flow.
            let polish = FlowConfig {
                iterations: POLISH_STEPS,
                ..*cfg
            };
            refine(a, b, &mut f.data, &polish);
            Ok(f)
        }
        _ => Ok(lucas_kanade(a, b, cfg)),
    }
}

/// OpenCV's DIS flow from `a` to `b` (same size, at least [`DIS_MIN_SIDE`] a side).
fn dis(a: &Grey, b: &Grey) -> Result<Flow, FlowError> {
    use opencv::core::{Mat, Vec2f};
    use opencv::prelude::*;
    use opencv::video::{DISOpticalFlow, DISOpticalFlow_PRESET_FAST};
    // Rounded to 8 bits (non-negative after the clamp: the cast truncates).
    let bytes = |g: &Grey| -> Vec<u8> {
        g.data
            .iter()
            .map(|&v| (v.clamp(0.0, 1.0) * 255.0 + 0.5) as u8)
            .collect()
    };
    let (a8, b8) = (bytes(a), bytes(b));
    let (rows, cols) = (a.height as i32, a.width as i32);
    let ma = Mat::new_rows_cols_with_data(rows, cols, &a8)?;
    let mb = Mat::new_rows_cols_with_data(rows, cols, &b8)?;
    let mut dis = DISOpticalFlow::create(DISOpticalFlow_PRESET_FAST)?;
    dis.set_finest_scale(0)?;
    dis.set_variational_refinement_iterations(0)?;
    let mut out = Mat::default();
    dis.calc(&ma, &mb, &mut out)?;
    let data = out
        .data_typed::<Vec2f>()?
        .iter()
        .flat_map(|v| [v[0], v[1]])
        .collect();
    Ok(Flow {
        width: a.width,
        height: a.height,
        data,
    })
}

/// The coarse-to-fine Lucas-Kanade flow from `a` to `b` (checked sizes).
fn lucas_kanade(a: &Grey, b: &Grey, cfg: &FlowConfig) -> Flow {
    let mut pyr = vec![(a.clone(), b.clone())];
    while pyr
        .last()
        .is_some_and(|(l, _)| l.width.min(l.height) >= 2 * cfg.min_side)
    {
        let (la, lb) = pyr.last().unwrap();
        let next = (la.half(), lb.half());
        pyr.push(next);
    }
    let mut f: Option<Flow> = None;
    for (la, lb) in pyr.iter().rev() {
        let mut data = match &f {
            Some(prev) => prev.resize(la.width, la.height).data,
            None => vec![0f32; la.width * la.height * 2],
        };
        refine(la, lb, &mut data, cfg);
        f = Some(Flow {
            width: la.width,
            height: la.height,
            data,
        });
    }
    f.expect("at least one level")
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn the_median_network_picks_what_sorting_picks() {
        // Signed zeros, duplicates, infinities and ordinary values, in many orders.
        let pool = [
            -0.0f32,
            0.0,
            1.5,
            -1.5,
            1.5,
            f32::INFINITY,
            f32::NEG_INFINITY,
            3.25,
            -7.0,
            1e-30,
            -1e-30,
            2.0,
        ];
        let mut state = 12345u64;
        for _ in 0..20000 {
            let v: [f32; 9] = std::array::from_fn(|_| {
                state = state
                    .wrapping_mul(6364136223846793005)
                    .wrapping_add(1442695040888963407);
                pool[(state >> 33) as usize % pool.len()]
            });
            let mut sorted = v;
            sorted.sort_unstable_by(f32::total_cmp);
            assert_eq!(median9(v).to_bits(), sorted[4].to_bits(), "{v:?}");
        }
    }
}
