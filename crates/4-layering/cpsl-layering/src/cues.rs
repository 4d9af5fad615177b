//! Per-pixel cues for the layering energy: validated depth with a confidence map (w_d),
//! saliency (w_s) and instance masks (w_i), at full resolution where matting needs them and
//! at a reduced working resolution where the energy is minimised.

use crate::error::LayeringError;
use crate::grid::{box_blur, components, distance, downsample};
use cpsl_core::fill::push_pull;
use cpsl_core::resample::resize_bilinear;
use rayon::prelude::*;
use serde::{Deserialize, Serialize};

/// Configuration of cue extraction.
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields, default)]
pub struct CueConfig {
    /// Long side of the working resolution of the energy (the image is area-downscaled to it).
    pub work_side: usize,
    /// Accept missing (NaN) depth values and fill them from their neighbours; otherwise they
    /// are an error.
    pub allow_missing_depth: bool,
    /// Largest normalised inverse-depth step between 4-neighbours of one depth-coherent
    /// component (classical instances).
    pub component_step: f32,
    /// Smallest instance, as a fraction of the image area.
    pub min_instance_area: f32,
    /// Largest inverse-depth spread (10th to 90th percentile, normalised) of an instance;
    /// wider components are surfaces such as floors, not objects.
    pub max_instance_spread: f32,
}

impl Default for CueConfig {
    fn default() -> Self {
        Self {
            work_side: 320,
            allow_missing_depth: false,
            component_step: 0.03,
            min_instance_area: 0.002,
            max_instance_spread: 0.12,
        }
    }
}

/// A prompt for a promptable segmentation model, in full-resolution pixels.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Prompt {
    /// A point inside the object.
    pub point: (f32, f32),
    /// The object's bounding box `[x0, y0, x1, y1]`, when known.
    pub bbox: Option<[f32; 4]>,
}

/// Where instance masks came from.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum InstanceSource {
    /// Connected components of depth-coherent regions.
    DepthComponents,
    /// Masks from a promptable segmentation model.
    Model,
}

/// Instance masks at working resolution.
#[derive(Debug, Clone, PartialEq)]
pub struct Instances {
    /// Instance id per working pixel; 0 is no instance, `i >= 1` indexes `confidence[i - 1]`.
    pub ids: Vec<u32>,
    /// Confidence of each instance in `[0, 1]`.
    pub confidence: Vec<f32>,
    /// Their origin.
    pub source: InstanceSource,
}

/// The cues at working resolution.
#[derive(Debug, Clone, PartialEq)]
pub struct Work {
    /// Width.
    pub width: usize,
    /// Height.
    pub height: usize,
    /// RGB in `[0, 1]`, interleaved.
    pub rgb: Vec<f32>,
    /// Normalised inverse depth (see [`Cues::disparity`]).
    pub disparity: Vec<f32>,
    /// Depth confidence.
    pub confidence: Vec<f32>,
    /// Saliency in `[0, 1]`.
    pub saliency: Vec<f32>,
    /// Instances.
    pub instances: Instances,
}

/// Cues of one frame.
#[derive(Debug, Clone, PartialEq)]
pub struct Cues {
    /// Width.
    pub width: usize,
    /// Height.
    pub height: usize,
    /// z-depth with missing values filled.
    pub depth: Vec<f32>,
    /// Inverse depth normalised to `[0, 1]` over the frame (1 nearest).
    pub disparity: Vec<f32>,
    /// `(min, max)` of inverse depth: `1/z = min + d (max - min)`.
    pub disparity_range: (f32, f32),
    /// Depth confidence `sigma_z` in `[0, 1]`: low where depth edges have no colour edge
    /// (bleeding, blur) and where depth was missing.
    pub confidence: Vec<f32>,
    /// `|grad ln z|`, the largest in each 5x5 neighbourhood (so both sides of a depth edge
    /// see it).
    pub depth_gradient: Vec<f32>,
    /// Number of missing depth values that were filled.
    pub missing: usize,
    /// Working-resolution cues.
    pub work: Work,
}

fn smoothstep(a: f32, b: f32, x: f32) -> f32 {
    let t = ((x - a) / (b - a)).clamp(0.0, 1.0);
    t * t * (3.0 - 2.0 * t)
}

/// Magnitude of the central-difference gradient.
fn gradient(v: &[f32], w: usize, h: usize) -> Vec<f32> {
    let mut g = vec![0f32; w * h];
    g.par_chunks_mut(w).enumerate().for_each(|(y, row)| {
        let (up, down) = (
            &v[y.saturating_sub(1) * w..][..w],
            &v[(y + 1).min(h - 1) * w..][..w],
        );
        let mid = &v[y * w..][..w];
        for (x, o) in row.iter_mut().enumerate() {
            let gx = (mid[(x + 1).min(w - 1)] - mid[x.saturating_sub(1)]) * 0.5;
            let gy = (down[x] - up[x]) * 0.5;
            *o = (gx * gx + gy * gy).sqrt();
        }
    });
    g
}

/// Max filter of radius `r`, separable.
fn dilate(v: &[f32], w: usize, h: usize, r: usize) -> Vec<f32> {
    let mut a = vec![0f32; w * h];
    a.par_chunks_mut(w).enumerate().for_each(|(y, row)| {
        let src = &v[y * w..][..w];
        let window = |x: usize| {
            src[x.saturating_sub(r)..(x + r + 1).min(w)]
                .iter()
                .fold(f32::MIN, |m, &q| m.max(q))
        };
        if w <= 2 * r {
            row.iter_mut().enumerate().for_each(|(x, o)| *o = window(x));
            return;
        }
        // Inside, the windows are whole: the maximum of the 2r + 1 shifted rows, a row at a
        // time (the same value: for values without NaN or negative zeros, as gradient
        // magnitudes are, the maximum does not depend on the order).
        let inner = &mut row[r..w - r];
        inner.copy_from_slice(&src[..w - 2 * r]);
        for d in 1..=2 * r {
            for (o, &q) in inner.iter_mut().zip(&src[d..w - 2 * r + d]) {
                *o = o.max(q);
            }
        }
        for x in (0..r).chain(w - r..w) {
            row[x] = window(x);
        }
    });
    let mut b = vec![f32::MIN; w * h];
    b.par_chunks_mut(w).enumerate().for_each(|(y, row)| {
        for yy in y.saturating_sub(r)..(y + r + 1).min(h) {
            for (o, &q) in row.iter_mut().zip(&a[yy * w..][..w]) {
                *o = o.max(q);
            }
        }
    });
    b
}

/// Luma (BT.709) in `[0, 1]` of interleaved RGB in `[0, 1]`.
pub fn luma(rgb: &[f32]) -> Vec<f32> {
    rgb.chunks_exact(3)
        .map(|p| 0.2126 * p[0] + 0.7152 * p[1] + 0.0722 * p[2])
        .collect()
}

/// Checks depth: every value finite and positive, NaN meaning missing (allowed only when
/// `allow_missing`). Returns the depth with missing values filled and their count.
fn validate_depth(
    depth: &[f32],
    w: usize,
    h: usize,
    allow_missing: bool,
) -> Result<(Vec<f32>, usize), LayeringError> {
    let mut missing = 0;
    for (i, &z) in depth.iter().enumerate() {
        if z.is_nan() {
            missing += 1;
        } else if !(z.is_finite() && z > 0.0) {
            return Err(LayeringError::BadDepth {
                x: i % w,
                y: i / w,
                value: z,
            });
        }
    }
    if missing == depth.len() {
        return Err(LayeringError::NoValidDepth);
    }
    if missing > 0 && !allow_missing {
        let first = depth.iter().position(|z| z.is_nan()).unwrap_or(0);
        return Err(LayeringError::MissingDepth {
            count: missing,
            x: first % w,
            y: first / w,
        });
    }
    let mut inv: Vec<f32> = depth
        .iter()
        .map(|&z| if z.is_nan() { 0.0 } else { 1.0 / z })
        .collect();
    if missing > 0 {
        let wt: Vec<f32> = depth.iter().map(|z| (!z.is_nan()) as u8 as f32).collect();
        push_pull(&mut inv, &wt, w, h, 1);
    }
    Ok((inv.iter().map(|&d| 1.0 / d).collect(), missing))
}

/// Minimum-barrier distance of every pixel to the image border, summed over channels
/// (FastMBD, Zhang et al. 2015: three forward/backward raster passes).
fn minimum_barrier(rgb: &[f32], w: usize, h: usize) -> Vec<f32> {
    let mut total = vec![0f32; w * h];
    for c in 0..3 {
        let img: Vec<f32> = rgb.chunks_exact(3).map(|p| p[c]).collect();
        let mut d = vec![f32::INFINITY; w * h];
        let (mut hi, mut lo) = (img.clone(), img.clone());
        for y in 0..h {
            for x in 0..w {
                if x == 0 || y == 0 || x + 1 == w || y + 1 == h {
                    d[y * w + x] = 0.0;
                }
            }
        }
        let relax = |p: usize, q: usize, d: &mut [f32], hi: &mut [f32], lo: &mut [f32]| {
            let (u, l) = (hi[q].max(img[p]), lo[q].min(img[p]));
            if u - l < d[p] {
                d[p] = u - l;
                hi[p] = u;
                lo[p] = l;
            }
        };
        for _ in 0..3 {
            for y in 1..h.saturating_sub(1) {
                for x in 1..w.saturating_sub(1) {
                    let p = y * w + x;
                    relax(p, p - 1, &mut d, &mut hi, &mut lo);
                    relax(p, p - w, &mut d, &mut hi, &mut lo);
                }
            }
            for y in (1..h.saturating_sub(1)).rev() {
                for x in (1..w.saturating_sub(1)).rev() {
                    let p = y * w + x;
                    relax(p, p + 1, &mut d, &mut hi, &mut lo);
                    relax(p, p + w, &mut d, &mut hi, &mut lo);
                }
            }
        }
        for (t, v) in total.iter_mut().zip(&d) {
            *t += if v.is_finite() { *v } else { 0.0 };
        }
    }
    total
}

fn normalise(v: &mut [f32]) {
    let max = v.iter().fold(0f32, |m, &x| m.max(x));
    if max > 0.0 {
        v.iter_mut().for_each(|x| *x /= max);
    }
}

/// Saliency in `[0, 1]`: minimum-barrier contrast to the border, combined with depth contrast
/// (being nearer than the surroundings).
fn saliency(rgb: &[f32], disparity: &[f32], w: usize, h: usize) -> Vec<f32> {
    let mut mbd = box_blur(&minimum_barrier(rgb, w, h), w, h, 1);
    normalise(&mut mbd);
    let surround = box_blur(disparity, w, h, (w.max(h) / 8).max(1));
    let mut contrast: Vec<f32> = disparity
        .iter()
        .zip(&surround)
        .map(|(d, s)| (d - s).max(0.0))
        .collect();
    normalise(&mut contrast);
    let mut s: Vec<f32> = mbd
        .iter()
        .zip(&contrast)
        .map(|(m, c)| 0.6 * m + 0.4 * c)
        .collect();
    normalise(&mut s);
    s
}

/// Connected components of depth-coherent regions as instances: 4-neighbours join when their
/// normalised inverse depth differs by at most `component_step`; components that are too
/// small, larger than half the image or spread over too much depth are dropped.
fn depth_components(
    work_disp: &[f32],
    work_conf: &[f32],
    w: usize,
    h: usize,
    cfg: &CueConfig,
) -> Instances {
    let (comp, n) = components(w, h, |p, q| {
        (work_disp[p] - work_disp[q]).abs() <= cfg.component_step
    });
    let mut members: Vec<Vec<usize>> = vec![Vec::new(); n];
    for (p, &c) in comp.iter().enumerate() {
        members[c as usize].push(p);
    }
    let area = (w * h) as f32;
    let mut id_of = vec![0u32; n];
    let mut confidence = Vec::new();
    for (c, m) in members.iter().enumerate() {
        let a = m.len() as f32;
        if a < cfg.min_instance_area * area || a > 0.5 * area {
            continue;
        }
        let mut d: Vec<f32> = m.iter().map(|&p| work_disp[p]).collect();
        d.sort_by(f32::total_cmp);
        let spread = d[d.len() * 9 / 10] - d[d.len() / 10];
        if spread > cfg.max_instance_spread {
            continue;
        }
        let conf = m.iter().map(|&p| work_conf[p]).sum::<f32>() / a;
        confidence.push(0.8 * conf);
        id_of[c] = confidence.len() as u32;
    }
    Instances {
        ids: comp.iter().map(|&c| id_of[c as usize]).collect(),
        confidence,
        source: InstanceSource::DepthComponents,
    }
}

impl Cues {
    /// Extracts the cues of an RGB frame (`rgb`: 3 bytes per pixel) with z-depth `depth`.
    pub fn compute(
        rgb: &[u8],
        depth: &[f32],
        width: usize,
        height: usize,
        cfg: &CueConfig,
    ) -> Result<Self, LayeringError> {
        let n = width * height;
        if n == 0 {
            return Err(LayeringError::Config {
                field: "image size",
                range: "at least 1x1",
                found: format!("{width}x{height}"),
            });
        }
        crate::error::check_frame(rgb, depth, width as u32, height as u32)?;
        if !(16..=4096).contains(&cfg.work_side) {
            return Err(LayeringError::Config {
                field: "work_side",
                range: "16..=4096",
                found: cfg.work_side.to_string(),
            });
        }
        let (w, h) = (width, height);
        let raw_depth = depth;
        let (depth, missing) = validate_depth(depth, w, h, cfg.allow_missing_depth)?;
        let (lo, hi) = depth.iter().fold((f32::MAX, f32::MIN), |(a, b), &z| {
            (a.min(1.0 / z), b.max(1.0 / z))
        });
        let span = (hi - lo).max(1e-12);
        let disparity: Vec<f32> = depth.iter().map(|&z| (1.0 / z - lo) / span).collect();

        // Confidence: depth edges unsupported by colour edges are unreliable.
        let rgbf: Vec<f32> = rgb.iter().map(|&v| v as f32 / 255.0).collect();
        let y = luma(&rgbf);
        let log_z: Vec<f32> = depth.par_iter().map(|z| z.ln()).collect();
        let gd = gradient(&log_z, w, h);
        let gc = dilate(&gradient(&y, w, h), w, h, 2);
        let mut confidence: Vec<f32> = gd
            .iter()
            .zip(&gc)
            .map(|(&d, &c)| {
                let ed = smoothstep(0.02, 0.15, d);
                let ec = smoothstep(0.02, 0.10, c);
                (1.0 - 0.3 * ed) * (1.0 - 0.7 * ed * (1.0 - ec))
            })
            .collect();
        for (c, z) in confidence.iter_mut().zip(raw_depth) {
            if z.is_nan() {
                *c = 0.05;
            }
        }

        let scale = (cfg.work_side as f32 / w.max(h) as f32).min(1.0);
        let (ww, wh) = (
            ((w as f32 * scale).round() as usize).max(1),
            ((h as f32 * scale).round() as usize).max(1),
        );
        let work_rgb = downsample(&rgbf, w, h, 3, ww, wh);
        let work_disp = downsample(&disparity, w, h, 1, ww, wh);
        let work_conf = downsample(&confidence, w, h, 1, ww, wh);
        let work_sal = saliency(&work_rgb, &work_disp, ww, wh);
        let instances = depth_components(&work_disp, &work_conf, ww, wh, cfg);
        Ok(Self {
            width: w,
            height: h,
            depth,
            disparity,
            disparity_range: (lo, hi),
            confidence,
            depth_gradient: dilate(&gd, w, h, 2),
            missing,
            work: Work {
                width: ww,
                height: wh,
                rgb: work_rgb,
                disparity: work_disp,
                confidence: work_conf,
                saliency: work_sal,
                instances,
            },
        })
    }

    /// Saliency at full resolution (bilinear from the working resolution).
    pub fn saliency_full(&self) -> Vec<f32> {
        resize_bilinear(
            &self.work.saliency,
            self.work.width,
            self.work.height,
            1,
            self.width,
            self.height,
        )
    }

    /// Prompts for a promptable segmentation model, in full-resolution pixels, most salient
    /// first: every salient depth-coherent component (a region bounded by depth
    /// discontinuities) as its innermost point plus its bounding box, and the strongest
    /// saliency peaks outside them as points.
    pub fn prompts(&self, max: usize) -> Vec<Prompt> {
        let (w, h) = (self.work.width, self.work.height);
        let (sx, sy) = (self.width as f32 / w as f32, self.height as f32 / h as f32);
        let at = |p: usize| (((p % w) as f32 + 0.5) * sx, ((p / w) as f32 + 0.5) * sy);
        let sal = &self.work.saliency;
        let mut found: Vec<(f32, Prompt)> = Vec::new();
        let inst = &self.work.instances;
        for id in 1..=inst.confidence.len() as u32 {
            let outside: Vec<bool> = inst.ids.iter().map(|&i| i != id).collect();
            let d = distance(&outside, w, h);
            let (mut best, mut inner) = (0f32, 0);
            let (mut s, mut a) = (0f32, 0usize);
            let (mut x0, mut y0, mut x1, mut y1) = (w, h, 0, 0);
            for p in (0..w * h).filter(|&p| inst.ids[p] == id) {
                s += sal[p];
                a += 1;
                if d[p] > best {
                    best = d[p];
                    inner = p;
                }
                let (x, y) = (p % w, p / w);
                (x0, y0, x1, y1) = (x0.min(x), y0.min(y), x1.max(x + 1), y1.max(y + 1));
            }
            if a > 0 && s / a as f32 >= 0.3 {
                let bbox = [
                    x0 as f32 * sx,
                    y0 as f32 * sy,
                    x1 as f32 * sx,
                    y1 as f32 * sy,
                ];
                found.push((
                    s / a as f32,
                    Prompt {
                        point: at(inner),
                        bbox: Some(bbox),
                    },
                ));
            }
        }
        // Saliency peaks: local maxima of blurred saliency above 0.5 outside the components.
        let blurred = box_blur(sal, w, h, 2);
        let r = (w.max(h) / 16).max(2);
        for y in 0..h {
            for x in 0..w {
                let p = y * w + x;
                let v = blurred[p];
                if v < 0.5 || inst.ids[p] != 0 {
                    continue;
                }
                let is_max = (y.saturating_sub(r)..(y + r + 1).min(h)).all(|yy| {
                    (x.saturating_sub(r)..(x + r + 1).min(w)).all(|xx| blurred[yy * w + xx] <= v)
                });
                if is_max {
                    found.push((
                        v,
                        Prompt {
                            point: at(p),
                            bbox: None,
                        },
                    ));
                }
            }
        }
        found.sort_by(|a, b| b.0.total_cmp(&a.0));
        found.into_iter().take(max).map(|f| f.1).collect()
    }

    /// Adds full-resolution instance masks (e.g. from a segmentation model), most confident
    /// first: each working pixel goes to the first mask covering at least half of it. A mask
    /// spread over more depth than `max_instance_spread` (it leaked onto a surface) is
    /// rejected. Depth components mostly left uncovered by the masks stay instances.
    pub fn add_instance_masks(&mut self, masks: &[(Vec<bool>, f32)], cfg: &CueConfig) {
        let (w, h) = (self.work.width, self.work.height);
        let disp = &self.work.disparity;
        let mut ids = vec![0u32; w * h];
        let mut confidence = Vec::new();
        let mut order: Vec<usize> = (0..masks.len()).collect();
        order.sort_by(|&a, &b| masks[b].1.total_cmp(&masks[a].1));
        for i in order {
            let (mask, conf) = &masks[i];
            if mask.len() != self.width * self.height {
                continue;
            }
            let m: Vec<f32> = mask.iter().map(|&b| b as u8 as f32).collect();
            let cover = downsample(&m, self.width, self.height, 1, w, h);
            let mut px: Vec<usize> = (0..w * h)
                .filter(|&p| cover[p] >= 0.5 && ids[p] == 0)
                .collect();
            if px.is_empty() {
                continue;
            }
            let mut d: Vec<f32> = px.iter().map(|&p| disp[p]).collect();
            d.sort_by(f32::total_cmp);
            if d[d.len() * 9 / 10] - d[d.len() / 10] > cfg.max_instance_spread {
                continue;
            }
            confidence.push(conf.clamp(0.0, 1.0));
            let id = confidence.len() as u32;
            px.drain(..).for_each(|p| ids[p] = id);
        }
        let old = &self.work.instances;
        for (c, &conf) in old.confidence.iter().enumerate() {
            let members: Vec<usize> = (0..w * h).filter(|&p| old.ids[p] == c as u32 + 1).collect();
            let free: Vec<usize> = members.iter().copied().filter(|&p| ids[p] == 0).collect();
            if !free.is_empty() && free.len() * 2 >= members.len() {
                confidence.push(conf);
                let id = confidence.len() as u32;
                free.into_iter().for_each(|p| ids[p] = id);
            }
        }
        self.work.instances = Instances {
            ids,
            confidence,
            source: InstanceSource::Model,
        };
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn dilation_is_the_maximum_over_each_window() {
        let mut lcg = crate::lcg::Lcg(7);
        for (w, h, r) in [
            (1, 1, 2),
            (4, 3, 2),
            (5, 7, 2),
            (6, 2, 2),
            (37, 11, 2),
            (40, 9, 5),
        ] {
            let v: Vec<f32> = (0..w * h).map(|_| lcg.unit()).collect();
            let d = dilate(&v, w, h, r);
            for y in 0..h {
                for x in 0..w {
                    let mut m = f32::MIN;
                    for yy in y.saturating_sub(r)..(y + r + 1).min(h) {
                        for xx in x.saturating_sub(r)..(x + r + 1).min(w) {
                            m = m.max(v[yy * w + xx]);
                        }
                    }
                    assert_eq!(d[y * w + x], m, "{w}x{h} r={r} at ({x}, {y})");
                }
            }
        }
    }
}
