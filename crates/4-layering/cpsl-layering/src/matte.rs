//! From the working-resolution plan to full-resolution layers: label upsampling guided by
//! depth and colour, soft alpha from the signed distance to each layer's contour with an
//! adaptive feather, extension of each layer behind the layers in front of it with push-pull
//! colour fill, premultiplied colour, and the Edge-Depth Cache along layer boundaries.
//!
//! Alpha of layer `k` at pixel `x` owned by layer `S(x)`, with `D` the distance to the
//! nearest pixel of layer `k`, `m` the extension margin and `w(x)` the feather width:
//!
//! * `S(x) = k`: 1;
//! * `S(x) > k` (behind, outside the contour): `max(0, 1 - D / (w + 1))`;
//! * `S(x) < k` (in front): 1 within `D <= m` (the extension that parallax can reveal),
//!   then `max(0, 1 - (D - m) / (w + 1))`, but only where layer `k` is the layer behind
//!   `S(x)` whose pixels are nearest (within one pixel): behind an occluder, each side is
//!   continued by the surface that borders it there, never by a layer that merely lies within
//!   reach (that would show a ghost copy of its edge, a double edge, when the occluder moves
//!   away); the farthest layer is opaque everywhere.
//!
//! Colour is the input wherever a layer is visible at the reference view (own and behind
//! pixels), so the reference composite reproduces the input exactly; behind nearer layers it
//! is filled from the layer's own pixels. `w(x) = w0 + a |grad ln z| + b (1 - sigma_z)`,
//! clamped to `max_feather`: wider where depth changes fast or is uncertain.

use crate::cues::Cues;
use crate::error::LayeringError;
use crate::geometry::{fit_geometry, GeometryMode, LayerDepth};
use crate::grid::{distance, label_runs};
use crate::promote::{Kind, Plan};
use cpsl_core::fill::push_pull;
use cpsl_core::resample::source_coord;
use cpsl_core::{
    Camera, Edc, EdcSample, Layer, LayerMeta, LayerRole, LayerSet, Limits, PremulImage,
};
use rayon::prelude::*;
use serde::{Deserialize, Serialize};
use std::collections::HashSet;

/// Configuration of matting, extension and the Edge-Depth Cache.
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields, default)]
pub struct MatteConfig {
    /// `w0`: base feather width in pixels.
    pub feather_base: f32,
    /// `a`: feather pixels per unit of `|grad ln z|`.
    pub feather_gradient: f32,
    /// `b`: feather pixels per unit of depth uncertainty `1 - sigma_z`.
    pub feather_uncertainty: f32,
    /// Largest feather width in pixels.
    pub max_feather: f32,
    /// How far each layer extends behind nearer layers, as a fraction of the long side.
    pub extend: f32,
    /// Weight of colour similarity when upsampling labels at region boundaries.
    pub colour_weight: f32,
    /// Edge-Depth Cache: at most one sample per layer pair in each `edc_cell` x `edc_cell`
    /// pixel cell.
    pub edc_cell: u32,
    /// Edge-Depth Cache quantisation step of `ln z`.
    pub edc_step: f32,
    /// Which surfaces layers may have.
    pub geometry: GeometryMode,
    /// Vertex spacing of mesh layers in pixels; 0 picks it from the frame size
    /// ([`crate::geometry::auto_mesh_step`]).
    pub mesh_step: u32,
}

impl Default for MatteConfig {
    fn default() -> Self {
        Self {
            feather_base: 1.0,
            feather_gradient: 4.0,
            feather_uncertainty: 2.0,
            max_feather: 4.0,
            extend: 0.04,
            colour_weight: 4.0,
            edc_cell: 4,
            edc_step: 1.0 / 128.0,
            geometry: GeometryMode::default(),
            mesh_step: 0,
        }
    }
}

/// Upsamples the plan's owner map to full resolution: where the four nearest working pixels
/// disagree, the candidate with the least depth cost plus colour distance wins.
pub fn upsample_owner(
    cues: &Cues,
    rgb: &[u8],
    plan: &Plan,
    sigma: f32,
    truncation: f32,
    cfg: &MatteConfig,
) -> Vec<u8> {
    let (w, h) = (cues.width, cues.height);
    let (ww, wh) = (cues.work.width, cues.work.height);
    let wrgb = &cues.work.rgb;
    let mut out = vec![0u8; w * h];
    out.par_chunks_mut(w).enumerate().for_each(|(y, row)| {
        let sy = source_coord(y, h, wh);
        let (y0, y1) = (sy.floor() as usize, (sy.floor() as usize + 1).min(wh - 1));
        for (x, o) in row.iter_mut().enumerate() {
            let sx = source_coord(x, w, ww);
            let (x0, x1) = (sx.floor() as usize, (sx.floor() as usize + 1).min(ww - 1));
            let taps = [y0 * ww + x0, y0 * ww + x1, y1 * ww + x0, y1 * ww + x1];
            let first = plan.owner[taps[0]];
            if taps.iter().all(|&t| plan.owner[t] == first) {
                *o = first;
                continue;
            }
            let p = y * w + x;
            let wd = 0.1 + 0.9 * cues.confidence[p];
            let mut best = (f32::INFINITY, first);
            for &t in &taps {
                let c = plan.owner[t];
                let (mut col, mut cnt) = ([0f32; 3], 0.0);
                for &u in taps.iter().filter(|&&u| plan.owner[u] == c) {
                    for (k, v) in col.iter_mut().enumerate() {
                        *v += wrgb[u * 3 + k];
                    }
                    cnt += 1.0;
                }
                let r = cues.disparity[p] - plan.layers[c as usize].disparity;
                let mut cost = wd * ((r / sigma).powi(2)).min(truncation);
                let mut dc = 0.0;
                for (k, v) in col.iter().enumerate() {
                    let own = rgb[p * 3 + k] as f32 / 255.0;
                    dc += (own - v / cnt).powi(2);
                }
                cost += cfg.colour_weight * dc.sqrt();
                if cost < best.0 {
                    best = (cost, c);
                }
            }
            *o = best.1;
        }
    });
    out
}

/// Feather width per pixel.
fn feather(cues: &Cues, cfg: &MatteConfig) -> Vec<f32> {
    cues.depth_gradient
        .iter()
        .zip(&cues.confidence)
        .map(|(&g, &c)| {
            (cfg.feather_base + cfg.feather_gradient * g + cfg.feather_uncertainty * (1.0 - c))
                .clamp(0.0, cfg.max_feather)
        })
        .collect()
}

/// A rectangle `[x0, x1) x [y0, y1)`.
#[derive(Debug, Clone, Copy)]
struct Rect {
    x0: usize,
    y0: usize,
    x1: usize,
    y1: usize,
}

impl Rect {
    /// The whole `w x h` image.
    fn all(w: usize, h: usize) -> Self {
        Rect {
            x0: 0,
            y0: 0,
            x1: w,
            y1: h,
        }
    }

    /// The bounding box of each label's pixels in `labels` (an image `w` wide; labels from
    /// 0 to `k - 1`), if it has any.
    fn of_labels(labels: &[u8], w: usize, k: usize) -> Vec<Option<Self>> {
        let mut boxes: Vec<Option<Self>> = vec![None; k];
        for (y, row) in labels.chunks_exact(w).enumerate() {
            for (l, xs) in label_runs(row) {
                if let Some(b) = boxes.get_mut(l as usize) {
                    let r = b.get_or_insert(Rect {
                        x0: xs.start,
                        y0: y,
                        x1: xs.end,
                        y1: y + 1,
                    });
                    (r.x0, r.x1, r.y1) = (r.x0.min(xs.start), r.x1.max(xs.end), y + 1);
                }
            }
        }
        boxes
    }

    /// The bounding box of the pixels of `self` (in an image `w` wide) where `f` holds, if
    /// any.
    fn bounding_in(self, w: usize, f: impl Fn(usize) -> bool) -> Option<Self> {
        let mut r = Rect {
            x0: self.x1,
            y0: self.y1,
            x1: 0,
            y1: 0,
        };
        for y in self.y0..self.y1 {
            for x in self.x0..self.x1 {
                if f(y * w + x) {
                    r = Rect {
                        x0: r.x0.min(x),
                        y0: r.y0.min(y),
                        x1: r.x1.max(x + 1),
                        y1: r.y1.max(y + 1),
                    };
                }
            }
        }
        (r.x1 > r.x0).then_some(r)
    }

    fn grow(self, by: usize, w: usize, h: usize) -> Self {
        Rect {
            x0: self.x0.saturating_sub(by),
            y0: self.y0.saturating_sub(by),
            x1: (self.x1 + by).min(w),
            y1: (self.y1 + by).min(h),
        }
    }

    fn width(&self) -> usize {
        self.x1 - self.x0
    }

    fn height(&self) -> usize {
        self.y1 - self.y0
    }
}

/// Fills `col` (RGB, full frame) at the pixels where `hidden` holds from the pixels where
/// `known` holds, by push-pull at half resolution within `rect`, bilinearly upsampled.
/// Returns `false` (changing nothing) when no known pixel lies in `rect`.
fn fill_half(
    col: &mut [u8],
    w: usize,
    rect: Rect,
    known: impl Fn(usize) -> bool,
    hidden: impl Fn(usize) -> bool,
) -> bool {
    let (hw, hh) = (rect.width().div_ceil(2), rect.height().div_ceil(2));
    let mut sub = vec![0f32; hw * hh * 3];
    let mut wt = vec![0f32; hw * hh];
    for y in rect.y0..rect.y1 {
        for x in rect.x0..rect.x1 {
            let p = y * w + x;
            if known(p) {
                let q = ((y - rect.y0) / 2) * hw + (x - rect.x0) / 2;
                wt[q] += 1.0;
                for c in 0..3 {
                    sub[q * 3 + c] += col[p * 3 + c] as f32;
                }
            }
        }
    }
    for (q, &n) in wt.iter().enumerate() {
        if n > 0.0 {
            (0..3).for_each(|c| sub[q * 3 + c] /= n);
        }
    }
    let wt: Vec<f32> = wt.iter().map(|&n| (n > 0.0) as u8 as f32).collect();
    if !push_pull(&mut sub, &wt, hw, hh, 3) {
        return false;
    }
    for y in rect.y0..rect.y1 {
        let sy = ((y - rect.y0) as f32 + 0.5) / 2.0 - 0.5;
        let sy = sy.clamp(0.0, (hh - 1) as f32);
        // Non-negative: truncation is the floor, and the fraction after it exact.
        let ya = sy as usize;
        let fy = sy - ya as f32;
        let yb = (ya + 1).min(hh - 1);
        for x in rect.x0..rect.x1 {
            let p = y * w + x;
            if !hidden(p) {
                continue;
            }
            let sx = (((x - rect.x0) as f32 + 0.5) / 2.0 - 0.5).clamp(0.0, (hw - 1) as f32);
            let xa = sx as usize;
            let fx = sx - xa as f32;
            let xb = (xa + 1).min(hw - 1);
            for c in 0..3 {
                let s = |yy: usize, xx: usize| sub[(yy * hw + xx) * 3 + c];
                let v = (s(ya, xa) * (1.0 - fx) + s(ya, xb) * fx) * (1.0 - fy)
                    + (s(yb, xa) * (1.0 - fx) + s(yb, xb) * fx) * fy;
                col[p * 3 + c] = cpsl_core::image::round_to_u8(v);
            }
        }
    }
    true
}

/// Builds the layer set: alpha, colour (input where visible, filled behind nearer layers),
/// premultiplied, with each layer at the median depth of its pixels and on the surface
/// [`fit_geometry`] gives it.
pub fn build_layers(
    cues: &Cues,
    rgb: &[u8],
    owner: &[u8],
    plan: &Plan,
    camera: Camera,
    cfg: &MatteConfig,
) -> Result<LayerSet, LayeringError> {
    let (w, h) = (cues.width, cues.height);
    let k = plan.layers.len();
    let wf = feather(cues, cfg);
    let margin = cfg.extend * w.max(h) as f32;
    // Median depth of each layer's own pixels.
    let mut per: Vec<Vec<f32>> = vec![Vec::new(); k];
    for (p, &o) in owner.iter().enumerate() {
        per[o as usize].push(cues.depth[p]);
    }
    // Distance to every layer's own pixels, within reach of them (the back layer too: where
    // it is the nearest layer behind an occluder, nothing else extends there).
    let reach = (margin + cfg.max_feather).ceil() as usize + 2;
    let boxes = Rect::of_labels(owner, w, k);
    let dists: Vec<Option<(Rect, Vec<f32>)>> = boxes
        .into_par_iter()
        .enumerate()
        .map(|(i, r)| {
            let r = r?.grow(reach, w, h);
            let mut inside = Vec::with_capacity(r.width() * r.height());
            for y in r.y0..r.y1 {
                inside.extend(
                    owner[y * w + r.x0..y * w + r.x1]
                        .iter()
                        .map(|&o| o as usize == i),
                );
            }
            Some((r, distance(&inside, r.width(), r.height())))
        })
        .collect();
    let dist = |l: usize, x: usize, y: usize| -> f32 {
        let Some((r, d)) = &dists[l] else {
            return f32::INFINITY;
        };
        if x < r.x0 || x >= r.x1 || y < r.y0 || y >= r.y1 {
            return f32::INFINITY;
        }
        d[(y - r.y0) * r.width() + x - r.x0]
    };
    let layers: Vec<Layer> = (0..k)
        .into_par_iter()
        .map(|i| {
            let back = i + 1 == k;
            let own = |p: usize| owner[p] as usize == i;
            // Alpha: 1 everywhere on the back layer; elsewhere from the distance to the own
            // region, which only matters within reach of it.
            let mut alpha = vec![0f32; w * h];
            if back {
                alpha.fill(1.0);
            } else if let Some((r, di)) = &dists[i] {
                for (y, drow) in (r.y0..).zip(di.chunks_exact(r.width())) {
                    for (x, &d) in (r.x0..).zip(drow) {
                        let p = y * w + x;
                        let o = owner[p] as usize;
                        let ramp = |excess: f32| (1.0 - excess / (wf[p] + 1.0)).clamp(0.0, 1.0);
                        alpha[p] = if o == i {
                            1.0
                        } else if o > i {
                            ramp(d)
                        } else {
                            // Behind a nearer layer: extend only where this layer is the one
                            // nearest the occluder's pixel among the layers behind it, so a
                            // layer never shows through where another surface borders the
                            // occluder.
                            let nearest = (o + 1..k)
                                .map(|l| dist(l, x, y))
                                .fold(f32::INFINITY, f32::min);
                            ramp((d - margin).max(0.0)).min((1.0 - (d - nearest)).clamp(0.0, 1.0))
                        };
                    }
                }
            }
            // Where alpha can be above zero: everywhere on the back layer, within the box of
            // the distances elsewhere (and nowhere for a layer without pixels).
            let reach_box = if back {
                Some(Rect::all(w, h))
            } else {
                dists[i].as_ref().map(|(r, _)| *r)
            };
            // Colour: the input where visible at the reference view, filled behind nearer
            // layers from the layer's own pixels.
            let mut col = rgb.to_vec();
            let hidden = |p: usize| (owner[p] as usize) < i && alpha[p] > 0.0;
            if let Some(r) = reach_box.and_then(|b| b.bounding_in(w, hidden)) {
                let pad = (margin.ceil() as usize + 2).max(8);
                let near = r.grow(pad, w, h);
                if !fill_half(&mut col, w, near, own, hidden) {
                    // No own pixel near: fill from the whole layer.
                    fill_half(&mut col, w, Rect::all(w, h), own, hidden);
                }
            }
            let mut data = vec![0u8; w * h * 4];
            if let Some(r) = reach_box {
                for y in r.y0..r.y1 {
                    for p in y * w + r.x0..y * w + r.x1 {
                        let a = alpha[p];
                        if a <= 0.0 {
                            continue;
                        }
                        let a8 = cpsl_core::image::round_to_u8(a * 255.0);
                        for c in 0..3 {
                            data[p * 4 + c] = cpsl_core::image::premultiply(col[p * 3 + c], a8);
                        }
                        data[p * 4 + 3] = a8;
                    }
                }
            }
            let mut zs = per[i].clone();
            let m = zs.len() / 2;
            let depth = if zs.is_empty() {
                let d = plan.layers[i].disparity;
                let (lo, hi) = cues.disparity_range;
                1.0 / (lo + d * (hi - lo)) as f64
            } else {
                *zs.select_nth_unstable_by(m, f32::total_cmp).1 as f64
            };
            let extent = reach_box
                .and_then(|b| b.bounding_in(w, |p| alpha[p] > 0.0))
                .map(|r| [r.x0, r.y0, r.x1 - 1, r.y1 - 1]);
            let px = LayerDepth {
                width: w,
                height: h,
                depth: &cues.depth,
                confidence: Some(&cues.confidence),
                owner,
                label: i as u8,
                covered: &|p: usize| alpha[p] >= 0.5 / 255.0,
                // Own pixels have alpha 1, so the extent of the alpha holds them.
                bounds: extent,
            };
            let (step, finest) = match cfg.mesh_step {
                0 => (
                    crate::geometry::auto_mesh_step(camera.width, camera.height),
                    crate::geometry::FINEST_MESH_STEP,
                ),
                s => (s, s),
            };
            let geometry = fit_geometry(cfg.geometry, &camera, &px, depth, extent, step, finest);
            let planned = &plan.layers[i];
            let (name, role) = match (planned.kind, back) {
                (_, true) => (format!("background {i}"), LayerRole::Background),
                (Kind::Promoted, false) => (format!("instance {i}"), LayerRole::Instance),
                (Kind::Background, false) => (format!("region {i}"), LayerRole::Region),
            };
            Ok(Layer {
                image: PremulImage::from_premul(w as u32, h as u32, data)?,
                depth,
                geometry,
                meta: LayerMeta {
                    name: Some(name),
                    role: Some(role),
                    saliency: Some(planned.saliency),
                    track: None,
                },
            })
        })
        .collect::<Result<_, LayeringError>>()?;
    let mut layers = layers;
    for i in 1..layers.len() {
        if layers[i].depth <= layers[i - 1].depth {
            layers[i].depth = layers[i - 1].depth * (1.0 + 1e-6);
        }
    }
    Ok(LayerSet::new(camera, layers, &Limits::default())?)
}

/// Samples the Edge-Depth Cache along the boundaries of `owner` (see [`cpsl_core::edc`]).
pub fn edge_depth_cache(cues: &Cues, owner: &[u8], set: &LayerSet, cfg: &MatteConfig) -> Edc {
    edge_depth_cache_from(&cues.depth, cues.width, cues.height, owner, set, cfg)
}

/// [`edge_depth_cache`] from a `w x h` z-depth map.
///
/// Every 4-neighbour pair of pixels with different owners is a candidate, keyed by the
/// `edc_cell` cell of its front pixel and its layer pair; the first candidate of each key in
/// scan order is kept. Bands of `edc_cell` rows are scanned in parallel: a key belongs to the
/// band of its front pixel, so only a band's vertical pairs across its last row can meet a
/// key of the next band, and the merge keeps the earlier candidate, as one serial scan would.
pub fn edge_depth_cache_from(
    depth: &[f32],
    w: usize,
    h: usize,
    owner: &[u8],
    set: &LayerSet,
    cfg: &MatteConfig,
) -> Edc {
    let k = set.len();
    let mut edc = Edc::empty(w as u32, h as u32, k as u16, cfg.edc_step);
    let cell = cfg.edc_cell.max(1) as usize;
    let cols = w.div_ceil(cell);
    let z = depth;
    let layer_depth: Vec<f64> = set.layers().iter().map(|l| l.depth).collect();
    let quantise = |v: f64| edc.quantise(v);
    let bands: Vec<Vec<(usize, usize, EdcSample)>> = (0..h.div_ceil(cell))
        .into_par_iter()
        .map(|band| {
            let mut seen = HashSet::new();
            let mut out = Vec::new();
            // Sixteen owners (as one integer) starting at `x` of a row.
            let run = |row: &[u8], x: usize| {
                u128::from_ne_bytes(row[x..x + 16].try_into().expect("sixteen bytes"))
            };
            for y in band * cell..((band + 1) * cell).min(h) {
                let row = &owner[y * w..(y + 1) * w];
                // The last row has no pairs downwards: it stands in for its own next row.
                let below = if y + 1 < h {
                    &owner[(y + 1) * w..(y + 2) * w]
                } else {
                    row
                };
                let mut x = 0;
                while x < w {
                    // Sixteen pixels with the owners of their right and lower neighbours
                    // hold no pair: skipped at once.
                    if x + 17 <= w && run(row, x) == run(row, x + 1) && run(row, x) == run(below, x)
                    {
                        x += 16;
                        continue;
                    }
                    let p = y * w + x;
                    for (dir, q) in [(x + 1 < w).then(|| p + 1), (y + 1 < h).then(|| p + w)]
                        .into_iter()
                        .enumerate()
                    {
                        let Some(q) = q else { continue };
                        let (a, b) = (owner[p] as usize, owner[q] as usize);
                        if a == b {
                            continue;
                        }
                        let (fp, bp) = if a < b { (p, q) } else { (q, p) };
                        let (f, bk) = (a.min(b), a.max(b));
                        let (fx, fy) = (fp % w, fp / w);
                        let key = (((fy / cell) * cols + fx / cell) * k + f) * k + bk;
                        if !seen.insert(key) {
                            continue;
                        }
                        let sample = EdcSample {
                            x: fx as u16,
                            y: fy as u16,
                            front: f as u8,
                            back: bk as u8,
                            front_offset: quantise((z[fp] as f64 / layer_depth[f]).ln()),
                            back_offset: quantise((z[bp] as f64 / layer_depth[bk]).ln()),
                        };
                        out.push((key, p * 2 + dir, sample));
                    }
                    x += 1;
                }
            }
            out
        })
        .collect();
    let mut all: Vec<(usize, usize, EdcSample)> = bands.into_iter().flatten().collect();
    all.sort_unstable_by_key(|&(key, order, _)| (key, order));
    all.dedup_by_key(|c| c.0);
    edc.samples = all.into_iter().map(|(_, _, s)| s).collect();
    edc.samples.sort_by_key(|s| (s.y, s.x, s.front, s.back));
    edc.samples.dedup();
    edc
}

#[cfg(test)]
mod tests {
    use super::*;
    use cpsl_core::{Camera, Layer, PremulImage};

    /// The cache as one serial scan: the first candidate of each key wins.
    fn serial(
        depth: &[f32],
        w: usize,
        h: usize,
        owner: &[u8],
        set: &LayerSet,
        cfg: &MatteConfig,
    ) -> Vec<EdcSample> {
        let k = set.len();
        let edc = Edc::empty(w as u32, h as u32, k as u16, cfg.edc_step);
        let cell = cfg.edc_cell.max(1) as usize;
        let cols = w.div_ceil(cell);
        let mut seen = HashSet::new();
        let mut out = Vec::new();
        for p in 0..w * h {
            let (x, y) = (p % w, p / w);
            for q in [(x + 1 < w).then(|| p + 1), (y + 1 < h).then(|| p + w)]
                .into_iter()
                .flatten()
            {
                let (a, b) = (owner[p] as usize, owner[q] as usize);
                if a == b {
                    continue;
                }
                let (fp, bp) = if a < b { (p, q) } else { (q, p) };
                let (f, bk) = (a.min(b), a.max(b));
                let key = ((((fp / w) / cell) * cols + (fp % w) / cell) * k + f) * k + bk;
                if seen.insert(key) {
                    out.push(EdcSample {
                        x: (fp % w) as u16,
                        y: (fp / w) as u16,
                        front: f as u8,
                        back: bk as u8,
                        front_offset: edc.quantise((depth[fp] as f64 / set.layers()[f].depth).ln()),
                        back_offset: edc.quantise((depth[bp] as f64 / set.layers()[bk].depth).ln()),
                    });
                }
            }
        }
        out.sort_by_key(|s| (s.y, s.x, s.front, s.back));
        out.dedup();
        out
    }

    #[test]
    fn the_banded_cache_equals_one_serial_scan() {
        let (w, h, k) = (67usize, 45usize, 4usize);
        let camera = Camera::from_fov(w as u32, h as u32, 60.0);
        let layers = (0..k)
            .map(|i| Layer::new(PremulImage::new(w as u32, h as u32), 1.0 + i as f64))
            .collect();
        let set = LayerSet::new(camera, layers, &Limits::default()).unwrap();
        let mut lcg = crate::lcg::Lcg(3);
        let mut next = move || lcg.index();
        let depth: Vec<f32> = (0..w * h)
            .map(|_| 1.0 + (next() % 400) as f32 / 100.0)
            .collect();
        // Blocky owners with noisy edges, so that keys repeat within and across bands; and
        // wide blocks with rare noise, whose uniform runs the scan skips.
        for (side, noise) in [(9, 3), (23, 40)] {
            let owner: Vec<u8> = (0..w * h)
                .map(|p| {
                    (((p % w) / side + (p / w) / 7 + (next() % noise == 0) as usize) % k) as u8
                })
                .collect();
            for cell in [1, 3, 4, 8] {
                let cfg = MatteConfig {
                    edc_cell: cell,
                    ..MatteConfig::default()
                };
                let got = edge_depth_cache_from(&depth, w, h, &owner, &set, &cfg).samples;
                assert_eq!(got, serial(&depth, w, h, &owner, &set, &cfg), "cell {cell}");
                assert!(!got.is_empty());
            }
        }
    }
}
