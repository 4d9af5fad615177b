//! The Dynamic Pixel Strip (paper §3.3, eq. 4): after all layers are warped and composited,
//! thin gaps left between independently warped layers (cracks along silhouettes) are bridged
//! by a strip whose colour and depth blend the foreground and background sides,
//!
//! `z_dps = (1 - gamma) z_f + gamma z_b`, `C_dps = (1 - gamma) C_f + gamma C_b`.
//!
//! * **Support.** Pixels with accumulated alpha below 1/2 (`V` is the rest) that have covered
//!   pixels within `2 s` on two opposite sides (along their row or column): gaps at most
//!   `4 s` wide, bounded on both sides. `s` follows the pose: the largest
//!   screen-space parallax between neighbouring layers at the image centre, plus one pixel,
//!   capped at [`DpsConfig::max_width`]. Covered pixels are never changed (no interior blur),
//!   and wide disocclusions or content outside the reference frame stay as they are.
//! * **Sides.** Along eight directions the nearest covered pixel within `2 s` is found; the
//!   visible layer there (the first with warped alpha >= 1/2) gives its depth. The nearest
//!   side with the smallest depth is the foreground `f`, with the largest the background `b`.
//! * **Blend weight.** `gamma = d_f / (d_f + d_b)` from the screen distances to both sides,
//!   sharpened by the Edge-Depth Cache: with `r` the ratio of the true log-depth step across
//!   the silhouette (plane step corrected by the cached offsets of that layer pair) to the
//!   planes' step, `gamma' = clamp(1/2 + (gamma - 1/2)(1 + r))`. A surface that is really
//!   continuous (`r` near 0) gets a linear ramp; a true depth edge a crisper transition.
//!
//! The strip fills the remaining transmittance: `I += (1 - A) C_dps`.

use crate::prepared::{Filter, PreparedLayers};
use crate::raster::Warp;
use cpsl_core::{Camera, Edc, Pose, PremulImage};
use rayon::prelude::*;
use std::collections::HashMap;

/// Configuration of the Dynamic Pixel Strip.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct DpsConfig {
    /// Largest strip half-width `s` in pixels.
    pub max_width: u32,
}

impl DpsConfig {
    /// The default strip: at most 8 px wide.
    pub const DEFAULT: Self = Self { max_width: 8 };
}

impl Default for DpsConfig {
    fn default() -> Self {
        Self::DEFAULT
    }
}

/// What one DPS pass did.
#[derive(Debug, Clone, Copy, Default, PartialEq)]
pub struct DpsStats {
    /// Strip half-width `s` used for this pose.
    pub width: u32,
    /// Pixels synthesised.
    pub pixels: usize,
}

/// Per layer pair `(front, back)`: mean cached log-depth offsets on both sides.
#[derive(Debug, Clone, Default)]
pub struct EdgeOffsets(HashMap<(u8, u8), (f64, f64)>);

impl EdgeOffsets {
    /// The mean offsets of every layer pair of `edc`.
    pub fn from_edc(edc: &Edc) -> Self {
        let mut acc: HashMap<(u8, u8), (f64, f64, f64)> = HashMap::new();
        for s in &edc.samples {
            let e = acc.entry((s.front, s.back)).or_default();
            e.0 += edc.dequantise(s.front_offset);
            e.1 += edc.dequantise(s.back_offset);
            e.2 += 1.0;
        }
        Self(
            acc.into_iter()
                .map(|(k, (f, b, n))| (k, (f / n, b / n)))
                .collect(),
        )
    }

    /// The mean front and back offsets of pair `(front, back)`; zero where the cache has none.
    pub fn get(&self, front: u8, back: u8) -> (f64, f64) {
        self.0.get(&(front, back)).copied().unwrap_or((0.0, 0.0))
    }
}

/// The strip half-width `s` for `pose`: the largest screen-space parallax between neighbouring
/// layers (at `depths`, nearest first) at the image centre, plus one pixel, within
/// `[1, cfg.max_width]`.
pub fn strip_width(
    camera: &Camera,
    depths: &[f64],
    pose: &Pose,
    target: &Camera,
    cfg: &DpsConfig,
) -> u32 {
    let (cx, cy) = (camera.cx, camera.cy);
    let at = |z: f64| {
        let p = pose.ref_to_view(camera.unproject(cx, cy, z));
        target.project(p)
    };
    let parallax = depths
        .windows(2)
        .filter_map(|l| {
            let (a, b) = (at(l[0])?, at(l[1])?);
            Some(((a.0 - b.0).powi(2) + (a.1 - b.1).powi(2)).sqrt())
        })
        .fold(0.0, f64::max);
    ((parallax.ceil() as u32) + 1).clamp(1, cfg.max_width.max(1))
}

const DIRS: [(i32, i32); 8] = [
    (1, 0),
    (-1, 0),
    (0, 1),
    (0, -1),
    (1, 1),
    (-1, -1),
    (1, -1),
    (-1, 1),
];

impl PreparedLayers {
    /// Index of the first layer whose warped alpha at target pixel `(x, y)` is at least 1/2.
    fn visible_layer(&self, warps: &[Option<Warp>], x: usize, y: usize) -> Option<usize> {
        let (sw, sh) = (self.camera.width as f64, self.camera.height as f64);
        warps.iter().enumerate().find_map(|(k, wp)| {
            let (sx, sy) = wp.as_ref()?.source(x, y)?;
            if !(sx > -1.0 && sy > -1.0 && sx < sw && sy < sh) {
                return None;
            }
            (self.layers[k].alpha_at(sx, sy) >= 0.5).then_some(k)
        })
    }

    /// The strip's colour at uncovered pixel `(x, y)` of the composite `bytes` (`size`), or
    /// `None` where no two opposite sides within `reach` show a layer.
    #[allow(clippy::too_many_arguments)]
    fn strip_pixel(
        &self,
        warps: &[Option<Warp>],
        covered: &[bool],
        bytes: &[u8],
        (w, h): (usize, usize),
        reach: i32,
        x: usize,
        y: usize,
    ) -> Option<[u8; 4]> {
        let p = y * w + x;
        // Nearest covered pixel along each direction: (distance, pixel, layer).
        let mut sides: Vec<(f64, usize, usize)> = Vec::new();
        let mut hit = [false; 8];
        for (dir, (dx, dy)) in DIRS.into_iter().enumerate() {
            for step in 1..=reach {
                let (xx, yy) = (x as i32 + dx * step, y as i32 + dy * step);
                if xx < 0 || yy < 0 || xx >= w as i32 || yy >= h as i32 {
                    break;
                }
                let q = yy as usize * w + xx as usize;
                if covered[q] {
                    if let Some(k) = self.visible_layer(warps, xx as usize, yy as usize) {
                        let len = ((dx * dx + dy * dy) as f64).sqrt() * step as f64;
                        sides.push((len, q, k));
                        hit[dir] = true;
                    }
                    break;
                }
            }
        }
        // Both sides must show a layer (DIRS holds opposite pairs).
        if !(0..4).any(|i| hit[2 * i] && hit[2 * i + 1]) {
            return None;
        }
        let f = sides.iter().map(|s| s.2).min()?;
        let b = sides.iter().map(|s| s.2).max().unwrap_or(f);
        let nearest = |k: usize| {
            sides
                .iter()
                .filter(|s| s.2 == k)
                .min_by(|a, c| a.0.total_cmp(&c.0))
                .copied()
                .unwrap_or(sides[0])
        };
        let (df, qf, _) = nearest(f);
        let (db, qb, _) = nearest(b);
        let mut gamma = if f == b { 0.0 } else { df / (df + db) };
        if f != b {
            let (zf, zb) = (self.layers[f].depth.ln(), self.layers[b].depth.ln());
            let (of, ob) = self.edge_offsets.get(f as u8, b as u8);
            let r = ((zb + ob - zf - of) / (zb - zf)).clamp(0.0, 2.0);
            gamma = (0.5 + (gamma - 0.5) * (1.0 + r)).clamp(0.0, 1.0);
        }
        let col = |q: usize, c: usize| {
            let a = bytes[q * 4 + 3] as f64;
            bytes[q * 4 + c] as f64 / a.max(1.0) * 255.0
        };
        let mut px = [0u8; 4];
        let t = 1.0 - bytes[p * 4 + 3] as f64 / 255.0;
        for (c, v) in px.iter_mut().enumerate().take(3) {
            let strip = (1.0 - gamma) * col(qf, c) + gamma * col(qb, c);
            *v = (bytes[p * 4 + c] as f64 + t * strip)
                .round()
                .clamp(0.0, 255.0) as u8;
        }
        px[3] = 255;
        Some(px)
    }

    /// Renders like [`PreparedLayers::render_into`], then bridges thin gaps between layers
    /// with the Dynamic Pixel Strip (see the module documentation).
    pub fn render_dps_into(
        &self,
        pose: &Pose,
        target: &Camera,
        out: &mut PremulImage,
        cfg: &DpsConfig,
    ) -> DpsStats {
        self.render_dps_into_with(pose, target, out, cfg, self.filter)
    }

    /// [`PreparedLayers::render_dps_into`] with `filter` instead of the prepared layers' own
    /// (the strip itself samples the composite, not the layers).
    pub fn render_dps_into_with(
        &self,
        pose: &Pose,
        target: &Camera,
        out: &mut PremulImage,
        cfg: &DpsConfig,
        filter: Filter,
    ) -> DpsStats {
        self.render_into_with(pose, target, out, filter);
        let (w, h) = (target.width as usize, target.height as usize);
        let depths: Vec<f64> = self.layers.iter().map(|l| l.depth).collect();
        let s = strip_width(&self.camera, &depths, pose, target, cfg);
        let mut stats = DpsStats {
            width: s,
            pixels: 0,
        };
        let bytes = out.as_bytes();
        let covered: Vec<bool> = bytes.par_chunks_exact(4).map(|p| p[3] >= 128).collect();
        if covered.par_iter().all(|&c| c) {
            return stats;
        }
        let warps = self.warps(pose, target);
        let reach = 2 * s as i32;
        // Whether a covered pixel lies within `reach` on both sides along the row, and along
        // the column: distances to the nearest covered pixel each way, found in linear time
        // (rows in parallel; columns in parallel bands of 64).
        let far = u16::MAX;
        let step = |d: &mut u16, c: bool| {
            *d = if c { 0 } else { d.saturating_add(1) };
            *d
        };
        let near = |d: u16| (d as i32) <= reach;
        let mut across = vec![false; w * h];
        across
            .par_chunks_mut(w)
            .zip(covered.par_chunks(w))
            .for_each(|(row, cov)| {
                let mut left = vec![far; w];
                let mut d = far;
                for x in 0..w {
                    left[x] = step(&mut d, cov[x]);
                }
                d = far;
                for x in (0..w).rev() {
                    row[x] = near(left[x]) && near(step(&mut d, cov[x]));
                }
            });
        const BAND: usize = 64;
        let bands: Vec<Vec<bool>> = (0..w.div_ceil(BAND))
            .into_par_iter()
            .map(|band| {
                let (x0, bw) = (band * BAND, BAND.min(w - band * BAND));
                let mut up = vec![far; bw * h];
                let mut d = vec![far; bw];
                for y in 0..h {
                    for i in 0..bw {
                        up[y * bw + i] = step(&mut d[i], covered[y * w + x0 + i]);
                    }
                }
                d.fill(far);
                let mut both = vec![false; bw * h];
                for y in (0..h).rev() {
                    for i in 0..bw {
                        let down = step(&mut d[i], covered[y * w + x0 + i]);
                        both[y * bw + i] = near(up[y * bw + i]) && near(down);
                    }
                }
                both
            })
            .collect();
        let along = |x: usize, y: usize| {
            let band = &bands[x / BAND];
            band[y * (band.len() / h) + x % BAND]
        };
        let writes: Vec<(usize, [u8; 4])> = (0..h)
            .into_par_iter()
            .flat_map_iter(|y| {
                let (warps, covered, across, along) = (&warps, &covered, &across, &along);
                (0..w).filter_map(move |x| {
                    let p = y * w + x;
                    if covered[p] || !(across[p] || along(x, y)) {
                        return None;
                    }
                    self.strip_pixel(warps, covered, bytes, (w, h), reach, x, y)
                        .map(|px| (p, px))
                })
            })
            .collect();
        stats.pixels = writes.len();
        let bytes = out.as_bytes_mut();
        for (p, px) in writes {
            bytes[p * 4..p * 4 + 4].copy_from_slice(&px);
        }
        stats
    }
}
