//! Mesh layers ([`cpsl_core::Geometry::Mesh`]): every triangle of the layer's depth grid is a
//! planar patch with its own inverse homography.
//!
//! Per render, the grid's vertices are projected into the viewer; triangles over empty parts
//! of the layer, with a vertex behind the viewer, or turned away from it (the back of a fold)
//! are dropped; the rest are sorted nearest first and binned into the output tiles. A tile
//! draws each of its triangles row by row over the pixels whose centres the triangle holds,
//! with the plane kernels (`raster`): exact homography at sub-span ends, fixed-point
//! stepping in between. Pixel ownership follows a half-open rule on edge crossings computed
//! the same way by both triangles of an edge, so the triangles of a grid cover every pixel
//! once: no cracks, no double blending.

use crate::raster::{TILE_H, TILE_W};
use cpsl_core::geometry::plane_inverse;
use cpsl_core::{Camera, DepthGrid, Pose, PremulImage};

/// One visible triangle.
pub(crate) struct Triangle {
    /// Inverse homography of its plane: target pixel to source pixel.
    pub h: [[f64; 3]; 3],
    /// Target-space vertices sorted by `(y, x)`.
    v: [(f64, f64); 3],
}

impl Triangle {
    /// The half-open range of pixel rows whose centres it may hold.
    pub fn rows(&self) -> (i64, i64) {
        (ceil(self.v[0].1), ceil(self.v[2].1))
    }

    /// The half-open range `[xa, xb)` of pixels of row `y` whose centres it holds.
    #[inline]
    pub fn span(&self, y: i64) -> (i64, i64) {
        let [a, b, c] = self.v;
        let yf = y as f64;
        // Crossing of edge p -> q (p before q in (y, x) order) with row y: both triangles of
        // an edge compute it from the same numbers.
        let cross = |p: (f64, f64), q: (f64, f64)| p.0 + (yf - p.1) * (q.0 - p.0) / (q.1 - p.1);
        let long = cross(a, c);
        let short = if yf < b.1 { cross(a, b) } else { cross(b, c) };
        (ceil(long.min(short)), ceil(long.max(short)))
    }

    /// Whether it holds pixel `(x, y)`.
    pub fn holds(&self, x: i64, y: i64) -> bool {
        let (r0, r1) = self.rows();
        if y < r0 || y >= r1 {
            return false;
        }
        let (a, b) = self.span(y);
        x >= a && x < b
    }
}

/// `v.ceil() as i64` without the library call that `f64::ceil` is on x86-64 without SSE4.1
/// (the same for every value: saturating beyond `i64`, 0 for NaN).
#[inline(always)]
fn ceil(v: f64) -> i64 {
    let t = v as i64;
    t.saturating_add((v > t as f64) as i64)
}

/// A mesh layer prepared for one pose: its visible triangles, binned into output tiles.
pub(crate) struct MeshWarp {
    pub tris: Vec<Triangle>,
    /// Triangles of tile `t`: `index[start[t]..start[t + 1]]`, nearest first.
    start: Vec<u32>,
    index: Vec<u32>,
    tiles_x: usize,
}

/// Whether the vertex positions are far enough from overflow for the integer span maths.
const FAR: f64 = (1u64 << 30) as f64;

/// Which cells of `grid` hold a texel of `image` with alpha above zero, one texel wider on
/// each side for the bilinear taps ([`DepthGrid::occupied`]).
pub fn occupied_cells(image: &PremulImage, grid: &DepthGrid) -> Vec<bool> {
    let bytes = image.as_bytes();
    grid.occupied(image.width(), image.height(), |p| bytes[p * 4 + 3] != 0)
}

/// One triangle of a mesh layer as a viewer sees it.
#[derive(Debug, Clone, Copy)]
pub struct ProjectedTriangle {
    /// Target pixel position and viewer depth of each vertex.
    pub target: [(f64, f64, f64); 3],
    /// Inverse homography of its plane: target pixel to source pixel.
    pub h: [[f64; 3]; 3],
}

/// The triangles of a mesh layer (`grid`, with `occupied` from [`occupied_cells`]) that the
/// viewer `target` at `pose` sees: over occupied cells, every vertex in front of the viewer,
/// facing it (a triangle whose winding flips shows its back: the viewer has crossed its
/// plane), with a finite homography. Both renderers draw exactly these.
pub fn visible_triangles(
    grid: &DepthGrid,
    occupied: &[bool],
    cam: &Camera,
    target: &Camera,
    pose: &Pose,
) -> Vec<ProjectedTriangle> {
    let verts: Vec<Option<(f64, f64, f64)>> = (0..grid.rows)
        .flat_map(|j| (0..grid.cols).map(move |i| (i, j)))
        .map(|(i, j)| {
            let p = pose.ref_to_view(grid.point(cam, i, j));
            if p.z() <= 1e-9 {
                return None;
            }
            let (x, y) = target.project(p)?;
            (x.abs() < FAR && y.abs() < FAR).then_some((x, y, p.z()))
        })
        .collect();
    let mut out = Vec::new();
    let cw = grid.cols - 1;
    for cj in 0..grid.rows - 1 {
        for ci in 0..cw {
            if !occupied[(cj * cw + ci) as usize] {
                continue;
            }
            for t in 0..2 {
                let ids = DepthGrid::triangle(ci, cj, t);
                let [Some(a), Some(b), Some(c)] =
                    ids.map(|(i, j)| verts[(j * grid.cols + i) as usize])
                else {
                    continue;
                };
                // Same winding as in the reference image, or the triangle shows its back.
                let area = (b.0 - a.0) * (c.1 - a.1) - (b.1 - a.1) * (c.0 - a.0);
                // (Also drops degenerate and non-finite triangles.)
                if area.partial_cmp(&0.0) != Some(std::cmp::Ordering::Greater) {
                    continue;
                }
                let Some(h) = grid
                    .triangle_plane(cam, ci, cj, t)
                    .and_then(|m| plane_inverse(m, cam, target, pose))
                    .filter(|h| h.0.is_finite())
                else {
                    continue;
                };
                out.push(ProjectedTriangle {
                    target: [a, b, c],
                    h: h.0 .0,
                });
            }
        }
    }
    out
}

impl MeshWarp {
    /// Projects `grid` (of a layer seen by `cam` whose occupied cells are `occupied`) for the
    /// viewer `target` at `pose`.
    pub fn new(
        grid: &DepthGrid,
        occupied: &[bool],
        cam: &Camera,
        target: &Camera,
        pose: &Pose,
    ) -> Self {
        let (tw, th) = (target.width as usize, target.height as usize);
        let tiles_x = tw.div_ceil(TILE_W);
        let tiles = tiles_x * th.div_ceil(TILE_H);
        let mut tris: Vec<(f64, Triangle)> = visible_triangles(grid, occupied, cam, target, pose)
            .into_iter()
            .map(|p| {
                let mut v = p.target.map(|q| (q.0, q.1));
                v.sort_by(|a, b| a.1.total_cmp(&b.1).then(a.0.total_cmp(&b.0)));
                let z = p.target.iter().map(|q| q.2).sum::<f64>();
                (z, Triangle { h: p.h, v })
            })
            .collect();
        // Nearest first, so that where a fold overlaps itself the near side composites first.
        tris.sort_by(|a, b| a.0.total_cmp(&b.0));
        let tris: Vec<Triangle> = tris.into_iter().map(|t| t.1).collect();
        // Bins: the tiles each triangle's bounding box meets, counted, then filled.
        let range = |t: &Triangle| {
            let (xs, ys) = (t.v.map(|v| v.0), t.v.map(|v| v.1));
            let lo = |v: [f64; 3]| v.iter().copied().fold(f64::MAX, f64::min).ceil().max(0.0);
            let hi = |v: [f64; 3]| v.iter().copied().fold(f64::MIN, f64::max).ceil();
            let (x0, x1) = (lo(xs) as usize, (hi(xs).min(tw as f64)) as usize);
            let (y0, y1) = (lo(ys) as usize, (hi(ys).min(th as f64)) as usize);
            (x0 < x1 && y0 < y1).then(|| {
                (
                    x0 / TILE_W,
                    (x1 - 1) / TILE_W,
                    y0 / TILE_H,
                    (y1 - 1) / TILE_H,
                )
            })
        };
        let mut start = vec![0u32; tiles + 1];
        let ranges: Vec<_> = tris.iter().map(range).collect();
        for &(bx0, bx1, by0, by1) in ranges.iter().flatten() {
            for by in by0..=by1 {
                for bx in bx0..=bx1 {
                    start[by * tiles_x + bx + 1] += 1;
                }
            }
        }
        for t in 0..tiles {
            start[t + 1] += start[t];
        }
        let mut fill = start.clone();
        let mut index = vec![0u32; start[tiles] as usize];
        for (i, r) in ranges.iter().enumerate() {
            let Some((bx0, bx1, by0, by1)) = *r else {
                continue;
            };
            for by in by0..=by1 {
                for bx in bx0..=bx1 {
                    let f = &mut fill[by * tiles_x + bx];
                    index[*f as usize] = i as u32;
                    *f += 1;
                }
            }
        }
        Self {
            tris,
            start,
            index,
            tiles_x,
        }
    }

    /// The triangles of the tile whose top-left pixel is `(x0, y0)`, nearest first.
    pub fn bin(&self, x0: usize, y0: usize) -> &[u32] {
        let t = (y0 / TILE_H) * self.tiles_x + x0 / TILE_W;
        &self.index[self.start[t] as usize..self.start[t + 1] as usize]
    }

    /// Source position of target pixel `(x, y)` on the nearest triangle that holds it.
    pub fn source(&self, x: usize, y: usize) -> Option<(f64, f64)> {
        let (xi, yi) = (x as i64, y as i64);
        self.bin(x - x % TILE_W, y - y % TILE_H)
            .iter()
            .map(|&i| &self.tris[i as usize])
            .find(|t| t.holds(xi, yi))
            .and_then(|t| {
                let h = &t.h;
                let (u, v) = (x as f64, y as f64);
                let w = h[2][0] * u + h[2][1] * v + h[2][2];
                (w > 0.0).then(|| {
                    (
                        (h[0][0] * u + h[0][1] * v + h[0][2]) / w,
                        (h[1][0] * u + h[1][1] * v + h[1][2]) / w,
                    )
                })
            })
    }
}
