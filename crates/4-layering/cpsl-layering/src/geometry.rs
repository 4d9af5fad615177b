//! Each layer's surface, chosen at layering time (see [`cpsl_core::Geometry`]).
//!
//! A slanted plane is a robust fit of the layer's inverse depth, affine in normalised image
//! coordinates, over its own pixels weighted by depth confidence
//! ([`cpsl_core::fit_plane`]). It replaces the fronto-parallel plane when it removes a clear
//! part of the geometric error (the mean truncated `|ln z_fit - ln z|` over the layer's own
//! pixels) and keeps every pixel of the layer's extent at a depth between zero and
//! [`MAX_EXTRAPOLATION`] times the layer's deepest own pixel; otherwise the layer stays
//! fronto-parallel. Three numbers per layer cost nothing against the layer's video, so no
//! rate term is needed.

use cpsl_core::fill::push_pull;
use cpsl_core::{fit_plane, Camera, DepthGrid, Geometry};
use serde::{Deserialize, Serialize};

/// Which surfaces the layering may give its layers.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default, Serialize, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum GeometryMode {
    /// Every layer fronto-parallel: the paper's representation.
    Plane,
    /// A slanted plane wherever it fits the layer's depth clearly better.
    Slanted,
    /// A depth mesh, or a slanted plane, wherever either fits clearly better.
    #[default]
    Mesh,
}

impl GeometryMode {
    /// The default for video (`layer-video`, `encode`, `demo`'s clip, `eval-video`,
    /// `eval-rd`): slanted planes (since 2026-11-29; the paper's planes before). On the fox
    /// (depth from the video, P-frames' depth carried by the camera's poses, `cpsl eval-rd
    /// --clip fox`, every view scored) they lead the planes by 0.6 dB uncompressed and 0.16 to
    /// 0.53 dB from 1 to 6 Mbit/s, trailing by 0.16 dB at 0.5 Mbit/s, and the meshes by 0.18
    /// to 0.74 dB under every budget (meshes lead uncompressed by 0.1 dB, their grids take
    /// bits from the pictures); on the 1080p synthetic clip (exact depth) slanted and
    /// fronto-parallel planes score within 0.05 dB of each other at every rate
    /// (EVALUATION.md). Single images default to meshes ([`GeometryMode::default`]).
    pub const VIDEO_DEFAULT: Self = Self::Slanted;

    /// The mode's name as the command line writes it.
    pub fn name(self) -> &'static str {
        match self {
            Self::Plane => "plane",
            Self::Slanted => "slanted",
            Self::Mesh => "mesh",
        }
    }
}

impl std::str::FromStr for GeometryMode {
    type Err = String;
    fn from_str(s: &str) -> Result<Self, String> {
        [Self::Plane, Self::Slanted, Self::Mesh]
            .into_iter()
            .find(|m| m.name() == s)
            .ok_or_else(|| format!("unknown geometry `{s}`: expected plane, slanted or mesh"))
    }
}

/// Samples fitted per layer at most (a regular subset of its pixels beyond that).
const MAX_SAMPLES: usize = 16_384;
/// Largest `|ln z_fit - ln z|` a pixel contributes to the geometric error.
const TRUNCATION: f64 = 0.25;
/// How far beyond its own pixels a slanted layer may recede: the depth anywhere over its
/// extent at most this many times its deepest own pixel.
pub const MAX_EXTRAPOLATION: f64 = 4.0;
/// A slanted plane must remove at least this share of the fronto-parallel plane's error...
/// (measured with ground-truth depth, `cpsl eval all`: 0.05 gives the best mean PSNR over the
/// five Middlebury scenes; 0.2 and above keep layers flat that gain from a slant)
const MIN_GAIN: f64 = 0.05;
/// ...and at least this much of it in absolute terms (mean `|ln z|` error).
const MIN_ABS_GAIN: f64 = 0.002;

/// The default vertex spacing of mesh layers: a 64th of the frame's long side, 8 to 32 px
/// (8 px at Middlebury's 463x370, 20 at 720p, 30 at 1080p). Measured with ground-truth depth
/// (`cpsl eval all`, mean over the five Middlebury scenes): 8 px 28.26 dB, 12 px 27.82,
/// 16 px 27.28.
pub fn auto_mesh_step(width: u32, height: u32) -> u32 {
    (width.max(height) as f64 / 64.0).round().clamp(8.0, 32.0) as u32
}

/// A mesh must remove at least this share of the best plane's error...
const MESH_GAIN: f64 = 0.3;
/// ...and at least this much of it in absolute terms: a grid costs bits a plane does not.
/// (`cpsl eval all`, ground-truth depth, mean over Middlebury: 28.17 dB at 0.3 / 0.005,
/// 28.26 at 0.05 / 0.002 where every layer takes a mesh; 0.01 and above lose two scenes'
/// meshes and 1.6 dB. The 480x270 `cpsl eval-rd` clip at 1 Mbit/s: 0.5 dB better at
/// 0.3 / 0.005 than at 0.05 / 0.002.)
const MESH_ABS_GAIN: f64 = 0.005;
/// A mesh at half the step must remove at least this share of the coarser mesh's error...
/// (measured with ground-truth depth, `cpsl eval all`, K = 6: 0.05 / 0.0005 refines the same
/// Middlebury layers as 0 / 0, Books 27.70 -> 27.98 dB, Dolls 29.32 -> 29.81, Teddy 29.22 ->
/// 29.88, mean 28.51 -> 28.85; 0.1 / 0.001 and 0.2 / 0.002 keep Books' and Dolls' layers at
/// the coarse step: 27.75 / 29.51 and 27.70 / 29.32 dB)
const REFINE_GAIN: f64 = 0.05;
/// ...and at least this much of it in absolute terms (mean `|ln z|` error).
const REFINE_ABS_GAIN: f64 = 0.0005;
/// The finest vertex spacing the default mesh refines to. (A fixed 2-px grid, `cpsl eval all
/// --filter cubic`: PSNR +0.1 to +0.3 dB over 4 px on Middlebury but LPIPS worse on every
/// scene, Books 0.0476 -> 0.0488, Dolls 0.0306 -> 0.0318.)
pub const FINEST_MESH_STEP: u32 = 4;

/// A layer's pixels as the fit sees them.
pub struct LayerDepth<'a> {
    /// Frame size.
    pub width: usize,
    /// Frame height.
    pub height: usize,
    /// z-depth per pixel.
    pub depth: &'a [f32],
    /// Confidence per pixel in `[0, 1]` (`None`: all 1).
    pub confidence: Option<&'a [f32]>,
    /// Per pixel, the layer that owns it.
    pub owner: &'a [u8],
    /// This layer's index in `owner`: its own pixels are those that carry it.
    pub label: u8,
    /// Whether the layer has alpha above zero at pixel `p` (read by the mesh fits only).
    pub covered: &'a (dyn Fn(usize) -> bool + Sync),
    /// An inclusive box `[x0, y0, x1, y1]` that holds every pixel that is the layer's own or
    /// covered (`None`: the whole frame): the fits look no further.
    pub bounds: Option<[usize; 4]>,
}

impl LayerDepth<'_> {
    /// [`Self::bounds`], or the whole frame: the columns and the rows to look at.
    fn span(&self) -> (std::ops::Range<usize>, std::ops::Range<usize>) {
        match self.bounds {
            Some([x0, y0, x1, y1]) => (x0..(x1 + 1).min(self.width), y0..(y1 + 1).min(self.height)),
            None => (0..self.width, 0..self.height),
        }
    }
}

/// Mean truncated `|ln z_fit - ln z|` over `samples` (`x_n, y_n, 1/z, w`) of a surface whose
/// inverse depth at a sample is `inv`.
fn error(samples: &[[f64; 4]], inv: impl Fn(&[f64; 4]) -> f64) -> f64 {
    let (mut e, mut wsum) = (0.0, 0.0);
    for s in samples {
        let inv = inv(s);
        let d = if inv > 0.0 {
            (inv / s[2]).ln().abs().min(TRUNCATION)
        } else {
            TRUNCATION
        };
        e += s[3] * d;
        wsum += s[3];
    }
    if wsum > 0.0 {
        e / wsum
    } else {
        0.0
    }
}

/// The layer's surface under `mode`: its reference depth is `depth` (the median of its own
/// pixels) and `extent` the inclusive bounding box `[x0, y0, x1, y1]` of its alpha; a mesh has
/// a vertex every `mesh_step` pixels, or every half, quarter... of that down to `finest` pixels
/// where the finer grid removes a clear part of the coarser one's error (`finest >=
/// mesh_step`: the step is fixed).
#[allow(clippy::too_many_arguments)]
pub fn fit_geometry(
    mode: GeometryMode,
    cam: &Camera,
    px: &LayerDepth<'_>,
    depth: f64,
    extent: Option<[usize; 4]>,
    mesh_step: u32,
    finest: u32,
) -> Geometry {
    if mode == GeometryMode::Plane {
        return Geometry::Plane;
    }
    let Some(extent) = extent else {
        return Geometry::Plane;
    };
    let (w, h) = (px.width, px.height);
    // A regular subset of the layer's own pixels.
    let runs = own_runs(px);
    let count: usize = runs.iter().map(|r| r.x.len()).sum();
    if count < 64 {
        return Geometry::Plane;
    }
    let stride = ((count as f64 / MAX_SAMPLES as f64).sqrt().ceil() as usize).max(1);
    let mut samples = Vec::with_capacity(count.min(MAX_SAMPLES * 2));
    let mut deepest = 0f64;
    let (sx, sy) = (cam.width as f64 / w as f64, cam.height as f64 / h as f64);
    for run in runs.iter().filter(|r| r.y % stride == 0) {
        let y = run.y;
        for x in (run.x.start.next_multiple_of(stride)..run.x.end).step_by(stride) {
            let p = y * w + x;
            let z = px.depth[p] as f64;
            if !(z.is_finite() && z > 0.0) {
                continue;
            }
            let c = px.confidence.map_or(1.0, |c| c[p] as f64).max(0.05);
            let (u, v) = ((x as f64 + 0.5) * sx - 0.5, (y as f64 + 0.5) * sy - 0.5);
            samples.push([(u - cam.cx) / cam.fx, (v - cam.cy) / cam.fy, 1.0 / z, c]);
            deepest = deepest.max(z);
        }
    }
    let mut best = Geometry::Plane;
    let mut e_best = error(&samples, |s| {
        Geometry::Plane
            .plane(depth)
            .dot(cpsl_core::Vec3([s[0], s[1], 1.0]))
    });
    let better = |e: f64, than: f64| e <= (1.0 - MIN_GAIN) * than && than - e >= MIN_ABS_GAIN;
    if let Some(m) = fit_plane(&samples, 5) {
        let e = error(&samples, |s| m.x() * s[0] + m.y() * s[1] + m.z());
        let g = Geometry::Slanted(m);
        if better(e, e_best) && in_front(&g, cam, depth, extent, (sx, sy), deepest) {
            (best, e_best) = (g, e);
        }
    }
    if mode == GeometryMode::Mesh {
        let grid_error = |grid: &DepthGrid| {
            error(&samples, |s| {
                grid.inverse_depth_at(cam, s[0] * cam.fx + cam.cx, s[1] * cam.fy + cam.cy)
            })
        };
        if let Some(mut grid) = grid_over(cam, px, &runs, mesh_step, depth) {
            let mut e = grid_error(&grid);
            // Finer where the depth bends: halve the step while that removes a clear part of
            // the error (four times the vertices each time).
            while grid.step / 2 >= finest.max(1) {
                let Some(fine) = grid_over(cam, px, &runs, grid.step / 2, depth) else {
                    break;
                };
                let e_fine = grid_error(&fine);
                if !(e_fine <= (1.0 - REFINE_GAIN) * e && e - e_fine >= REFINE_ABS_GAIN) {
                    break;
                }
                (grid, e) = (fine, e_fine);
            }
            if e <= (1.0 - MESH_GAIN) * e_best && e_best - e >= MESH_ABS_GAIN {
                best = Geometry::Mesh(std::sync::Arc::new(grid));
            }
        }
    }
    best
}

/// Whether a slanted plane keeps the layer's extent (one pixel wider) in front of the camera,
/// no deeper than [`MAX_EXTRAPOLATION`] times its deepest own pixel.
fn in_front(
    g: &Geometry,
    cam: &Camera,
    depth: f64,
    [ex0, ey0, ex1, ey1]: [usize; 4],
    (sx, sy): (f64, f64),
    deepest: f64,
) -> bool {
    // The extent in camera pixels, one pixel wider on each side.
    let px = |v: usize, s: f64| (v as f64 + 0.5) * s - 0.5;
    let grown = [
        px(ex0, sx) - 1.0,
        px(ey0, sy) - 1.0,
        px(ex1, sx) + 1.0,
        px(ey1, sy) + 1.0,
    ];
    let (inv, _, _) = g.least_inverse_depth(depth, cam, grown);
    inv.is_finite() && inv >= 1.0 / (MAX_EXTRAPOLATION * deepest)
}

/// A depth grid of step `step` over the layer: each vertex takes the confidence-weighted mean
/// inverse depth of the layer's own pixels in the cells around it (bilinear weights); vertices
/// with none are filled from their neighbours by push-pull, so the surface continues smoothly
/// behind nearer layers and over the layer's extension; vertices of cells the layer does not
/// cover take its reference depth `depth` ([`DepthGrid::settle_unused`]).
pub fn fit_grid(cam: &Camera, px: &LayerDepth<'_>, step: u32, depth: f64) -> Option<DepthGrid> {
    grid_over(cam, px, &own_runs(px), step, depth)
}

/// A row's run of a layer's own pixels: columns `x` of row `y`.
struct Run {
    y: usize,
    x: std::ops::Range<usize>,
}

/// The layer's own pixels within [`LayerDepth::span`] as runs along the rows, in row-major
/// order (so sums over them add in the order a scan of the span would).
fn own_runs(px: &LayerDepth<'_>) -> Vec<Run> {
    let (xs, ys) = px.span();
    let mut runs = Vec::new();
    for y in ys {
        let row = &px.owner[y * px.width..][xs.clone()];
        runs.extend(
            crate::grid::label_runs(row)
                .filter(|(l, _)| *l == px.label)
                .map(|(_, r)| Run {
                    y,
                    x: xs.start + r.start..xs.start + r.end,
                }),
        );
    }
    runs
}

/// [`fit_grid`] over the layer's own pixels `runs` ([`own_runs`]).
fn grid_over(
    cam: &Camera,
    px: &LayerDepth<'_>,
    runs: &[Run],
    step: u32,
    depth: f64,
) -> Option<DepthGrid> {
    let (w, h) = (px.width, px.height);
    let (cols, rows) = DepthGrid::dims(cam.width, cam.height, step);
    let (cw, ch) = (cols as usize, rows as usize);
    let mut sum = vec![0f32; cw * ch];
    let mut wsum = vec![0f32; cw * ch];
    let s = step as f32 * w as f32 / cam.width as f32;
    let t = step as f32 * h as f32 / cam.height as f32;
    let (xs, _) = px.span();
    // Per column: its cell's left and right vertex columns and its position across it.
    let columns: Vec<(usize, usize, f32)> = xs
        .clone()
        .map(|x| {
            let gx = (x as f32 + 0.5) / s;
            let i = gx.floor() as usize;
            (i.min(cw - 1), (i + 1).min(cw - 1), gx.fract())
        })
        .collect();
    for run in runs {
        let y = run.y;
        let gy = (y as f32 + 0.5) / t;
        let (j, fy) = (gy.floor() as usize, gy.fract());
        // The cell's upper and lower vertex rows.
        let (r0, r1) = (j.min(ch - 1) * cw, (j + 1).min(ch - 1) * cw);
        let cells = &columns[run.x.start - xs.start..run.x.end - xs.start];
        for (x, &(i0, i1, fx)) in run.x.clone().zip(cells) {
            let p = y * w + x;
            let z = px.depth[p];
            if !(z.is_finite() && z > 0.0) {
                continue;
            }
            let c = px.confidence.map_or(1.0, |c| c[p]).max(0.05);
            for (q, wt) in [
                (r0 + i0, (1.0 - fx) * (1.0 - fy)),
                (r0 + i1, fx * (1.0 - fy)),
                (r1 + i0, (1.0 - fx) * fy),
                (r1 + i1, fx * fy),
            ] {
                sum[q] += wt * c / z;
                wsum[q] += wt * c;
            }
        }
    }
    let known: Vec<f32> = wsum.iter().map(|&v| (v > 1e-3) as u8 as f32).collect();
    let mut inv: Vec<f32> = sum
        .iter()
        .zip(&wsum)
        .map(|(&a, &b)| if b > 1e-3 { a / b } else { 0.0 })
        .collect();
    if !push_pull(&mut inv, &known, cw, ch, 1) {
        return None;
    }
    let mut grid = DepthGrid {
        step,
        cols,
        rows,
        inverse_depth: inv,
    };
    let (xs, ys) = px.span();
    let (xs, ys) = (
        xs.start as u32..xs.end as u32,
        ys.start as u32..ys.end as u32,
    );
    let occupied = grid.occupied_in(w as u32, h as u32, (xs, ys), px.covered);
    grid.settle_unused(&occupied, (1.0 / depth) as f32);
    grid.check(cam.width, cam.height).ok().map(|()| grid)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn runs_hold_exactly_the_own_pixels_of_the_span_in_row_major_order() {
        let (w, h) = (37, 11);
        // Labels 0..3 in irregular patches, runs touching the span's edges.
        let owner: Vec<u8> = (0..w * h)
            .map(|p| ((p * 7 / 5 + p / w) % 3) as u8)
            .collect();
        let depth = vec![1.0; w * h];
        for bounds in [None, Some([3, 2, 30, 9]), Some([0, 0, 0, 0])] {
            for label in 0..4 {
                let px = LayerDepth {
                    width: w,
                    height: h,
                    depth: &depth,
                    confidence: None,
                    owner: &owner,
                    label,
                    covered: &|_| true,
                    bounds,
                };
                let (xs, ys) = px.span();
                let scanned: Vec<usize> = ys
                    .flat_map(|y| xs.clone().map(move |x| y * w + x))
                    .filter(|&p| owner[p] == label)
                    .collect();
                let runs = own_runs(&px);
                let listed: Vec<usize> = runs
                    .iter()
                    .flat_map(|r| r.x.clone().map(|x| r.y * w + x))
                    .collect();
                assert_eq!(listed, scanned, "label {label}, bounds {bounds:?}");
                assert!(runs.iter().all(|r| !r.x.is_empty()));
            }
        }
    }

    #[test]
    fn a_floor_gets_its_slant_and_a_wall_stays_flat() {
        let cam = Camera::from_fov(64, 48, 60.0);
        let truth = cpsl_core::Vec3::new(0.0, 0.4, 0.3);
        let floor: Vec<f32> = (0..64 * 48)
            .map(|p| {
                let g = Geometry::Slanted(truth);
                (1.0 / g.inverse_depth_at(1.0, &cam, (p % 64) as f64, (p / 64) as f64)) as f32
            })
            .collect();
        let owner = vec![0; 64 * 48];
        let px = LayerDepth {
            width: 64,
            height: 48,
            depth: &floor,
            confidence: None,
            owner: &owner,
            label: 0,
            covered: &|_| true,
            bounds: None,
        };
        let g = fit_geometry(
            GeometryMode::Slanted,
            &cam,
            &px,
            3.3,
            Some([0, 0, 63, 47]),
            16,
            16,
        );
        let Geometry::Slanted(m) = g else {
            panic!("{g:?}")
        };
        assert!((m - truth).norm() < 1e-4, "{m:?}");
        assert_eq!(
            fit_geometry(
                GeometryMode::Plane,
                &cam,
                &px,
                3.3,
                Some([0, 0, 63, 47]),
                16,
                16
            ),
            Geometry::Plane
        );
        let wall = vec![2.0f32; 64 * 48];
        let px = LayerDepth { depth: &wall, ..px };
        assert_eq!(
            fit_geometry(
                GeometryMode::Slanted,
                &cam,
                &px,
                2.0,
                Some([0, 0, 63, 47]),
                16,
                16
            ),
            Geometry::Plane
        );
    }

    #[test]
    fn a_slant_that_recedes_past_the_horizon_over_the_extent_is_refused() {
        // The plane's horizon lies just above the layer's pixels; its extent reaches above it.
        let cam = Camera::from_fov(64, 48, 60.0);
        let g = Geometry::Slanted(cpsl_core::Vec3::new(0.0, 1.0, 0.05));
        let depth: Vec<f32> = (0..64 * 48)
            .map(|p| (1.0 / g.inverse_depth_at(1.0, &cam, (p % 64) as f64, (p / 64) as f64)) as f32)
            .collect();
        // The lower half is the layer's (label 1).
        let owner: Vec<u8> = (0..64 * 48).map(|p| u8::from(p / 64 >= 24)).collect();
        let px = LayerDepth {
            width: 64,
            height: 48,
            depth: &depth,
            confidence: None,
            owner: &owner,
            label: 1,
            covered: &|p| p / 64 >= 24,
            bounds: None,
        };
        assert!(!fit_geometry(
            GeometryMode::Slanted,
            &cam,
            &px,
            5.0,
            Some([0, 24, 63, 47]),
            16,
            16
        )
        .is_plane());
        assert!(fit_geometry(
            GeometryMode::Slanted,
            &cam,
            &px,
            5.0,
            Some([0, 0, 63, 47]),
            16,
            16
        )
        .is_plane());
    }

    /// The mesh's step after fitting `inv(x, y)` (inverse depth) over a 128x96 frame, from 16 px
    /// refining down to `finest`.
    fn mesh_step_for(inv: impl Fn(f64, f64) -> f64, finest: u32) -> Option<u32> {
        let cam = Camera::from_fov(128, 96, 60.0);
        let depth: Vec<f32> = (0..128 * 96)
            .map(|p| (1.0 / inv((p % 128) as f64, (p / 128) as f64)) as f32)
            .collect();
        let owner = vec![0; 128 * 96];
        let px = LayerDepth {
            width: 128,
            height: 96,
            depth: &depth,
            confidence: None,
            owner: &owner,
            label: 0,
            covered: &|_| true,
            bounds: None,
        };
        let extent = Some([0, 0, 127, 95]);
        match fit_geometry(GeometryMode::Mesh, &cam, &px, 1.0, extent, 16, finest) {
            Geometry::Mesh(grid) => Some(grid.step),
            _ => None,
        }
    }

    #[test]
    fn the_mesh_is_finer_only_where_the_depth_bends() {
        // Bumps 16 px apart: a 16-px grid cannot follow them, a finer one can.
        let bumps = |x: f64, y: f64| {
            let t = std::f64::consts::TAU / 16.0;
            0.5 + 0.15 * (x * t).cos() * (y * t).cos()
        };
        let step = mesh_step_for(bumps, FINEST_MESH_STEP).expect("a mesh");
        assert!((FINEST_MESH_STEP..16).contains(&step), "{step}");
        // At a fixed 16-px step the mesh misses the bumps and fits no better than a plane.
        assert_eq!(mesh_step_for(bumps, 16), None);
        // A bowl under pixel noise (+-10 % in depth): no plane fits it, a 16-px mesh does up
        // to the noise, which finer meshes cannot remove either, so the coarse one is kept.
        let noisy_bowl = |x: f64, y: f64| {
            let noise = ((x * 12.9898 + y * 78.233).sin() * 43758.5453).fract();
            (0.5 + 0.3 * ((x - 64.0).powi(2) + (y - 48.0).powi(2)) / 4096.0) * (0.1 * noise).exp()
        };
        assert_eq!(mesh_step_for(noisy_bowl, FINEST_MESH_STEP), Some(16));
    }
}
