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
//!   then `max(0, 1 - (D - m) / (w + 1))`; the farthest layer is opaque everywhere.
//!
//! Colour is the input wherever a layer is visible at the reference view (own and behind
//! pixels), so the reference composite reproduces the input exactly; behind nearer layers it
//! is filled from the layer's own pixels. `w(x) = w0 + a |grad ln z| + b (1 - sigma_z)`,
//! clamped to `max_feather`: wider where depth changes fast or is uncertain.

use crate::cues::Cues;
use crate::error::LayeringError;
use crate::fill::push_pull;
use crate::grid::{distance, source_coord};
use crate::promote::{Kind, Plan};
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
    let (w, h) = (cues.width, cues.height);
    let z = &cues.depth;
    let mut out = vec![0f32; w * h];
    out.par_chunks_mut(w).enumerate().for_each(|(y, row)| {
        for (x, o) in row.iter_mut().enumerate() {
            // Largest |grad ln z| in the 5x5 neighbourhood, so that both sides of a depth
            // edge see it.
            let mut g = 0f32;
            for yy in y.saturating_sub(2)..(y + 3).min(h) {
                for xx in x.saturating_sub(2)..(x + 3).min(w) {
                    let at = |a: usize, b: usize| z[b * w + a].ln();
                    let gx = (at((xx + 1).min(w - 1), yy) - at(xx.saturating_sub(1), yy)) * 0.5;
                    let gy = (at(xx, (yy + 1).min(h - 1)) - at(xx, yy.saturating_sub(1))) * 0.5;
                    g = g.max((gx * gx + gy * gy).sqrt());
                }
            }
            let unc = 1.0 - cues.confidence[y * w + x];
            *o = (cfg.feather_base + cfg.feather_gradient * g + cfg.feather_uncertainty * unc)
                .clamp(0.0, cfg.max_feather);
        }
    });
    out
}

/// Builds the layer set: alpha, colour (input where visible, filled behind nearer layers),
/// premultiplied, with each layer at the median depth of its pixels.
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
    let layers: Vec<Layer> = (0..k)
        .into_par_iter()
        .map(|i| {
            let back = i + 1 == k;
            let own: Vec<bool> = owner.iter().map(|&o| o as usize == i).collect();
            let dist = if back {
                Vec::new()
            } else {
                distance(&own, w, h)
            };
            let alpha: Vec<f32> = (0..w * h)
                .map(|p| {
                    let o = owner[p] as usize;
                    if back || o == i {
                        1.0
                    } else if o > i {
                        (1.0 - dist[p] / (wf[p] + 1.0)).max(0.0)
                    } else if dist[p] <= margin {
                        1.0
                    } else {
                        (1.0 - (dist[p] - margin) / (wf[p] + 1.0)).max(0.0)
                    }
                })
                .collect();
            // Colour: the input where visible at the reference view, filled elsewhere from
            // the layer's own pixels, within the bounding box of the hidden part.
            let mut col: Vec<f32> = rgb.iter().map(|&v| v as f32).collect();
            let hidden = |p: usize| (owner[p] as usize) < i && alpha[p] > 0.0;
            let (mut x0, mut y0, mut x1, mut y1) = (w, h, 0, 0);
            for p in (0..w * h).filter(|&p| hidden(p)) {
                let (x, y) = (p % w, p / w);
                x0 = x0.min(x);
                y0 = y0.min(y);
                x1 = x1.max(x + 1);
                y1 = y1.max(y + 1);
            }
            if x1 > x0 {
                // Grow the box so that it holds own pixels to fill from.
                let pad = (margin.ceil() as usize + 2).max(8);
                let (x0, y0) = (x0.saturating_sub(pad), y0.saturating_sub(pad));
                let (x1, y1) = ((x1 + pad).min(w), (y1 + pad).min(h));
                let (bw, bh) = (x1 - x0, y1 - y0);
                let mut sub = vec![0f32; bw * bh * 3];
                let mut wt = vec![0f32; bw * bh];
                for y in 0..bh {
                    for x in 0..bw {
                        let p = (y + y0) * w + x + x0;
                        if own[p] {
                            wt[y * bw + x] = 1.0;
                            sub[(y * bw + x) * 3..(y * bw + x) * 3 + 3]
                                .copy_from_slice(&col[p * 3..p * 3 + 3]);
                        }
                    }
                }
                if !push_pull(&mut sub, &wt, bw, bh, 3) {
                    // No own pixel near: fill from the whole layer.
                    let wt: Vec<f32> = own.iter().map(|&b| b as u8 as f32).collect();
                    let mut all = col.clone();
                    push_pull(&mut all, &wt, w, h, 3);
                    sub = (0..bw * bh)
                        .flat_map(|q| {
                            let p = (q / bw + y0) * w + q % bw + x0;
                            [all[p * 3], all[p * 3 + 1], all[p * 3 + 2]]
                        })
                        .collect();
                }
                for y in 0..bh {
                    for x in 0..bw {
                        let p = (y + y0) * w + x + x0;
                        if hidden(p) {
                            col[p * 3..p * 3 + 3]
                                .copy_from_slice(&sub[(y * bw + x) * 3..(y * bw + x) * 3 + 3]);
                        }
                    }
                }
            }
            let mut data = vec![0u8; w * h * 4];
            for p in 0..w * h {
                let a = alpha[p];
                if a <= 0.0 {
                    continue;
                }
                let a8 = (a * 255.0).round() as u8;
                for c in 0..3 {
                    let v = col[p * 3 + c].round().clamp(0.0, 255.0) as u8;
                    data[p * 4 + c] = cpsl_core::image::premultiply(v, a8);
                }
                data[p * 4 + 3] = a8;
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
            let planned = &plan.layers[i];
            let (name, role) = match (planned.kind, back) {
                (_, true) => (format!("background {i}"), LayerRole::Background),
                (Kind::Promoted, false) => (format!("instance {i}"), LayerRole::Instance),
                (Kind::Background, false) => (format!("region {i}"), LayerRole::Region),
            };
            Ok(Layer {
                image: PremulImage::from_premul(w as u32, h as u32, data)?,
                depth,
                meta: LayerMeta {
                    name: Some(name),
                    role: Some(role),
                    saliency: Some(planned.saliency),
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
    let (w, h) = (cues.width, cues.height);
    let k = set.len();
    let mut edc = Edc {
        width: w as u32,
        height: h as u32,
        layers: k as u16,
        step: cfg.edc_step,
        samples: Vec::new(),
    };
    let cell = cfg.edc_cell.max(1) as usize;
    let cols = w.div_ceil(cell);
    let mut seen = HashSet::new();
    let depth = |l: usize| set.layers()[l].depth;
    for y in 0..h {
        for x in 0..w {
            let p = y * w + x;
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
                let (fx, fy) = (fp % w, fp / w);
                let key = (((fy / cell) * cols + fx / cell) * k + f) * k + bk;
                if !seen.insert(key) {
                    continue;
                }
                edc.samples.push(EdcSample {
                    x: fx as u16,
                    y: fy as u16,
                    front: f as u8,
                    back: bk as u8,
                    front_offset: edc.quantise((cues.depth[fp] as f64 / depth(f)).ln()),
                    back_offset: edc.quantise((cues.depth[bp] as f64 / depth(bk)).ln()),
                });
            }
        }
    }
    edc.samples.sort_by_key(|s| (s.y, s.x, s.front, s.back));
    edc.samples.dedup();
    edc
}
