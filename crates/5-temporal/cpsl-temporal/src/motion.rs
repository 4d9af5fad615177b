//! Per-layer motion of a P-frame: the frame's motion on the flow grid, each layer's map into
//! its I-frame from the vectors of its own interior (where the depth agrees), composed over
//! time.

use crate::robust;
use cpsl_core::Flow;
use rayon::prelude::*;
use std::borrow::Cow;

/// Motion from a frame to the previous one: on the flow grid, and at full resolution when
/// given.
pub(crate) struct FrameMotion {
    pub(crate) grid: Flow,
    pub(crate) full: Option<Flow>,
}

impl FrameMotion {
    pub(crate) fn at_full(&self, w: usize, h: usize) -> Cow<'_, Flow> {
        match &self.full {
            Some(f) => Cow::Borrowed(f),
            None => Cow::Owned(self.grid.resize(w, h)),
        }
    }
}

/// A full-resolution flow on a `gw x gh` grid (nearest sample at each grid pixel's centre,
/// vectors in grid pixels).
pub(crate) fn shrink_flow(f: &Flow, gw: usize, gh: usize) -> Flow {
    let (sx, sy) = (f.width as f32 / gw as f32, f.height as f32 / gh as f32);
    let mut data = vec![0f32; gw * gh * 2];
    for gy in 0..gh {
        for gx in 0..gw {
            let x = (((gx as f32 + 0.5) * sx) as usize).min(f.width - 1);
            let y = (((gy as f32 + 0.5) * sy) as usize).min(f.height - 1);
            let (u, v) = f.at(x, y);
            data[(gy * gw + gx) * 2] = u / sx;
            data[(gy * gw + gx) * 2 + 1] = v / sy;
        }
    }
    Flow {
        width: gw,
        height: gh,
        data,
    }
}

/// Full-resolution position of the centre of grid pixel `(gx, gy)`.
#[inline]
pub(crate) fn grid_to_full(g: f32, scale: f32) -> f32 {
    (g + 0.5) * scale - 0.5
}

/// Index of the full-resolution pixel nearest to grid position `(gx, gy)` (clamped to the
/// image; the saturating cast takes negatives to 0).
#[inline]
pub(crate) fn nearest_pixel(
    gx: f32,
    gy: f32,
    (sx, sy): (f32, f32),
    (w, h): (usize, usize),
) -> usize {
    let x = ((grid_to_full(gx, sx) + 0.5) as usize).min(w - 1);
    let y = ((grid_to_full(gy, sy) + 0.5) as usize).min(h - 1);
    y * w + x
}

/// The map of a frame onto itself, on the grid.
pub(crate) fn identity_map(w: usize, h: usize, gw: usize, gh: usize) -> Vec<f32> {
    let (sx, sy) = (w as f32 / gw as f32, h as f32 / gh as f32);
    (0..gw * gh)
        .flat_map(|g| {
            [
                grid_to_full((g % gw) as f32, sx),
                grid_to_full((g / gw) as f32, sy),
            ]
        })
        .collect()
}

/// Where a layer's `map` into its I-frame (on a `gw x gh` grid over a `w x h` frame,
/// bilinearly interpolated) sends the frame's pixel position `(x, y)`.
pub(crate) fn mapped(
    map: &[f32],
    (gw, gh): (usize, usize),
    (w, h): (usize, usize),
    (x, y): (f64, f64),
) -> (f64, f64) {
    let (sx, sy) = (w as f64 / gw as f64, h as f64 / gh as f64);
    // The inverse of `grid_to_full`.
    let (gx, gy) = ((x + 0.5) / sx - 0.5, (y + 0.5) / sy - 0.5);
    let [mx, my] = sample2(map, gw, gh, gx as f32, gy as f32);
    (mx as f64, my as f64)
}

/// Bilinear sample of both channels of a 2-channel grid at `(x, y)` (clamped).
#[inline(always)]
pub(crate) fn sample2(d: &[f32], gw: usize, gh: usize, x: f32, y: f32) -> [f32; 2] {
    let x = x.clamp(0.0, (gw - 1) as f32);
    let y = y.clamp(0.0, (gh - 1) as f32);
    // Non-negative after the clamp: truncation is the floor.
    let (x0, y0) = (x as i32 as usize, y as i32 as usize);
    let (fx, fy) = (x - x0 as f32, y - y0 as f32);
    // Offsets of the right and lower taps (the same tap at the last column or row).
    let dx = if x0 + 1 < gw { 2 } else { 0 };
    let dy = if y0 + 1 < gh { gw * 2 } else { 0 };
    let a = (y0 * gw + x0) * 2;
    let (b, c, e) = (a + dx, a + dy, a + dy + dx);
    [0, 1].map(|k| {
        (d[a + k] * (1.0 - fx) + d[b + k] * fx) * (1.0 - fy)
            + (d[c + k] * (1.0 - fx) + d[e + k] * fx) * fy
    })
}

/// Per layer, the grid flow of its own interior: grid pixels whose match in the previous
/// frame lies inside the layer (one grid pixel from any other layer) keep their flow, and
/// push-pull fills the rest, so each layer moves with its own content; a layer without such
/// pixels stays where it is. Returns each layer's new map into the I-frame: its previous
/// map (`maps`) composed with that flow.
pub(crate) fn layer_maps(
    prev_owner: &[u8],
    flow: &Flow,
    maps: &[Vec<f32>],
    depths: &Depths<'_>,
) -> Vec<Vec<f32>> {
    let (w, h) = (depths.w, depths.h);
    let (gw, gh) = (flow.width, flow.height);
    let (sx, sy) = (w as f32 / gw as f32, h as f32 / gh as f32);
    // The previous owner on the grid (nearest pixel).
    let cell: Vec<u8> = (0..gw * gh)
        .map(|g| prev_owner[nearest_pixel((g % gw) as f32, (g / gw) as f32, (sx, sy), (w, h))])
        .collect();
    let reach = distance_inside(&cell, gw, gh, INTERIOR_RAMP + 1);
    let block = ((gw.max(gh) as f32 * MOTION_BLOCK).round() as usize).max(1);
    // The layer whose interior each grid pixel's match lies in (255: none), and how much its
    // vector counts: vectors measured near a layer boundary mix the motions of both sides, so
    // they count less the nearer their match lies to the boundary.
    let mut inside = vec![(u8::MAX, 0f32); gw * gh];
    inside
        .par_chunks_mut(gw)
        .zip(flow.data.par_chunks(gw * 2))
        .enumerate()
        .for_each(|(gy, (row, f))| {
            for (gx, (o, uv)) in row.iter_mut().zip(f.chunks_exact(2)).enumerate() {
                // Nearest grid pixel (floor of +1/2; negatives fail the test first).
                let qx = gx as f32 + uv[0] + 0.5;
                let qy = gy as f32 + uv[1] + 0.5;
                if qx < 0.0 || qy < 0.0 || qx >= gw as f32 || qy >= gh as f32 {
                    continue;
                }
                let q = qy as usize * gw + qx as usize;
                if reach[q] >= 2
                    && depths.same_surface(cell[q], (gx, gy), (qx - 0.5, qy - 0.5), (sx, sy))
                {
                    let ramp = (reach[q] - 1) as f32 / INTERIOR_RAMP as f32;
                    *o = (cell[q], ramp.min(1.0));
                }
            }
        });
    maps.par_iter()
        .enumerate()
        .map(|(l, map)| {
            let weight: Vec<f32> = inside
                .iter()
                .map(|&(i, c)| if i as usize == l { c } else { 0.0 })
                .collect();
            // Vectors that disagree with their neighbourhood lose their weight.
            let weight = robust::local_inliers(&flow.data, &weight, gw, gh, block);
            let Some(model) = robust::Affine::fit(&flow.data, &weight, gw, gh) else {
                return compose(map, &vec![0.0; gw * gh * 2], gw, gh);
            };
            // The model plus the residual of the vectors it keeps, filled in elsewhere.
            let mut data = flow.data.clone();
            model.add_to(&mut data, gw, -1.0);
            if !cpsl_core::fill::push_pull(&mut data, &weight, gw, gh, 2) {
                data.fill(0.0);
            }
            model.add_to(&mut data, gw, 1.0);
            compose(map, &data, gw, gh)
        })
        .collect()
}

/// What tells a pixel that still shows the surface its motion points to from one that a
/// moving occluder has just uncovered (or one a layer holds by mistake): this frame's depth
/// against the previous frame's at the match, and against the depths the layer spanned at
/// the I-frame.
pub(crate) struct Depths<'a> {
    now: &'a [f32],
    prev: &'a [f32],
    w: usize,
    h: usize,
    /// Bounds of `z_now / z_prev` on one surface.
    ratio: (f32, f32),
    /// Per layer, the bounds of its depth (widened by the tolerance).
    pub(crate) spans: Vec<(f32, f32)>,
}

impl<'a> Depths<'a> {
    /// `spans`: per layer, the 5 % and 95 % quantiles of `ln z` over its pixels;
    /// `tolerance` widens every bound in `ln z`.
    pub(crate) fn new(
        now: &'a [f32],
        prev: &'a [f32],
        (w, h): (usize, usize),
        spans: impl Iterator<Item = (f32, f32)>,
        tolerance: f32,
    ) -> Self {
        Self {
            now,
            prev,
            w,
            h,
            ratio: ((-tolerance).exp(), tolerance.exp()),
            spans: spans
                .map(|(lo, hi)| ((lo - tolerance).exp(), (hi + tolerance).exp()))
                .collect(),
        }
    }

    /// Whether grid pixel `(gx, gy)` shows the surface of layer `l` that its match
    /// `(mx, my)` (grid coordinates) showed in the previous frame: its depth agrees with the
    /// match's and lies within the layer's span. Pixels without a valid depth pass.
    #[inline]
    pub(crate) fn same_surface(
        &self,
        l: u8,
        (gx, gy): (usize, usize),
        (mx, my): (f32, f32),
        (sx, sy): (f32, f32),
    ) -> bool {
        let at = |gx: f32, gy: f32| nearest_pixel(gx, gy, (sx, sy), (self.w, self.h));
        let z = self.now[at(gx as f32, gy as f32)];
        let r = z / self.prev[at(mx, my)];
        let (lo, hi) = self.spans[l as usize];
        // Comparisons with NaN are false: a missing depth fails neither test.
        !(r < self.ratio.0 || r > self.ratio.1 || z < lo || z > hi)
    }
}

/// A layer's new map: the previous map sampled at each grid pixel's match (`flow`, on the
/// same grid).
pub(crate) fn compose(map: &[f32], flow: &[f32], gw: usize, gh: usize) -> Vec<f32> {
    let mut out = vec![0f32; gw * gh * 2];
    for (y, (row, f)) in out.chunks_mut(gw * 2).zip(flow.chunks(gw * 2)).enumerate() {
        for (x, (o, uv)) in row.chunks_exact_mut(2).zip(f.chunks_exact(2)).enumerate() {
            o.copy_from_slice(&sample2(map, gw, gh, x as f32 + uv[0], y as f32 + uv[1]));
        }
    }
    out
}

/// Grid pixels from a layer boundary within which interior vectors count less.
pub(crate) const INTERIOR_RAMP: u8 = 4;

/// Side of the blocks within which a layer's vectors are compared with their median, as a
/// share of the grid's long side.
pub(crate) const MOTION_BLOCK: f32 = 0.15;

/// Per pixel of a label map, its chessboard distance to the nearest pixel of another label
/// (1: a neighbour differs), at most `cap`: one plus the number of 3x3 erosions the set of
/// pixels without a differing neighbour survives.
pub(crate) fn distance_inside(label: &[u8], w: usize, h: usize, cap: u8) -> Vec<u8> {
    let lo = min3x3(label, w, h);
    let inv: Vec<u8> = label.iter().map(|&v| 255 - v).collect();
    let hi = min3x3(&inv, w, h);
    let mut inside: Vec<u8> = lo
        .iter()
        .zip(&hi)
        .map(|(&a, &b)| (a == 255 - b) as u8)
        .collect();
    let mut d: Vec<u8> = inside.iter().map(|&m| 1 + m).collect();
    for _ in 2..cap {
        inside = min3x3(&inside, w, h);
        d.iter_mut().zip(&inside).for_each(|(d, &m)| *d += m);
    }
    d
}

/// Minimum over the 3x3 window around every pixel (clamped at the edges), separably.
pub(crate) fn min3x3(v: &[u8], w: usize, h: usize) -> Vec<u8> {
    let row_min = |src: &[u8], out: &mut [u8]| {
        for (o, t) in out[1..].iter_mut().zip(src.windows(3)) {
            *o = t[0].min(t[1]).min(t[2]);
        }
        out[0] = src[0].min(src[w.min(2) - 1]);
        out[w - 1] = src[w - 1].min(src[w.saturating_sub(2)]);
    };
    let mut tmp = vec![0u8; w * h];
    tmp.chunks_mut(w)
        .zip(v.chunks(w))
        .for_each(|(o, src)| row_min(src, o));
    let mut out = vec![0u8; w * h];
    out.chunks_mut(w).enumerate().for_each(|(y, o)| {
        let (a, b, c) = (y.saturating_sub(1), y, (y + 1).min(h - 1));
        let (ra, rb, rc) = (
            &tmp[a * w..a * w + w],
            &tmp[b * w..b * w + w],
            &tmp[c * w..c * w + w],
        );
        for (((o, &x), &y), &z) in o.iter_mut().zip(ra).zip(rb).zip(rc) {
            *o = x.min(y).min(z);
        }
    });
    out
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    pub(crate) fn distance_inside_matches_brute_force() {
        let (w, h) = (37, 23);
        let label: Vec<u8> = (0..w * h)
            .map(|p| {
                let (x, y) = ((p % w) as i32, (p / w) as i32);
                ((x - 15).pow(2) + (y - 11).pow(2) < 64) as u8 + (x > 30 && y < 5) as u8 * 2
            })
            .collect();
        let got = distance_inside(&label, w, h, 6);
        for p in 0..w * h {
            let (x, y) = ((p % w) as i32, (p / w) as i32);
            let mut want = 6u8;
            for q in 0..w * h {
                let (qx, qy) = ((q % w) as i32, (q / w) as i32);
                if label[q] != label[p] {
                    want = want.min((qx - x).abs().max((qy - y).abs()) as u8);
                }
            }
            assert_eq!(got[p], want, "{x} {y}");
        }
    }
}
