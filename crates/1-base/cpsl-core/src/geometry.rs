//! The surface a layer's pixels lie on.
//!
//! The paper gives every layer a fronto-parallel plane at its depth `z_k`
//! ([`Geometry::Plane`]). A [`Geometry::Slanted`] layer lies on any plane in front of the
//! reference camera: written `m . X = 1` in the reference camera frame (`m = n / d` for a plane
//! `n . X = d`), its inverse depth is affine in normalised image coordinates,
//! `1 / z = m_x x_n + m_y y_n + m_z` with `x_n = (u - c_x) / f_x`, `y_n = (v - c_y) / f_y`, so
//! the same three numbers serve every resolution of the layer. Both are drawn with one
//! plane-induced homography ([`Geometry::inverse_homography`]).
//!
//! A [`Geometry::Mesh`] layer lies on a coarse grid of inverse depths ([`DepthGrid`]): vertex
//! `(i, j)` sits at reference pixel `(min(i s, w) - 1/2, min(j s, h) - 1/2)` for a step `s`,
//! so the grid spans the whole image; each cell is cut along its diagonal from the top-left
//! to the bottom-right vertex into two triangles. Inverse depth is affine over each triangle,
//! so each triangle is a planar patch drawn with its own homography
//! ([`DepthGrid::triangle_plane`]); neighbouring triangles share vertices, so the surface has
//! no cracks.

use crate::camera::Camera;
use crate::homography::{Homography, MIN_PLANE_DISTANCE};
use crate::math::{Mat3, Vec3};
use crate::pose::Pose;
use serde::{Deserialize, Serialize};
use std::ops::Range;
use std::sync::Arc;

/// A layer's surface in the reference camera; see the [module docs](self).
#[derive(Debug, Clone, PartialEq, Default, Serialize, Deserialize)]
#[serde(rename_all = "snake_case", deny_unknown_fields)]
pub enum Geometry {
    /// The fronto-parallel plane at the layer's depth (the paper's equation 1).
    #[default]
    Plane,
    /// The plane `m . X = 1` (reference camera frame), given as `m`.
    Slanted(#[serde(with = "vec3_array")] Vec3),
    /// A grid of inverse depths, one planar triangle per half cell.
    Mesh(Arc<DepthGrid>),
}

/// Inverse depths on a regular grid over the reference image; see the [module docs](self).
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct DepthGrid {
    /// Vertex spacing `s` in reference pixels.
    pub step: u32,
    /// Vertices per row: `ceil(w / s) + 1`.
    pub cols: u32,
    /// Vertex rows: `ceil(h / s) + 1`.
    pub rows: u32,
    /// Inverse depth at each vertex, row by row: finite and above zero.
    pub inverse_depth: Vec<f32>,
}

/// A grid's values at pixel centres ([`DepthGrid::pixels`]).
#[derive(Debug, Clone)]
pub struct GridPixels {
    grid: DepthGrid,
    /// Per pixel column: the cell's column and the position across it.
    xs: Vec<(u32, f32)>,
    /// Per pixel row: the cell's row and the position across it.
    ys: Vec<(u32, f32)>,
}

impl GridPixels {
    /// The value at pixel `(x, y)`: affine over the triangle that holds its centre.
    #[inline]
    pub fn at(&self, x: usize, y: usize) -> f32 {
        let ((ci, fx), (cj, fy)) = (self.xs[x], self.ys[y]);
        let g = &self.grid;
        let at = |i: u32, j: u32| g.inverse_depth[(j * g.cols + i) as usize];
        let (a, b, c, d) = (
            at(ci, cj),
            at(ci + 1, cj),
            at(ci, cj + 1),
            at(ci + 1, cj + 1),
        );
        if fx >= fy {
            a + (b - a) * fx + (d - b) * fy
        } else {
            a + (c - a) * fy + (d - c) * fx
        }
    }
}

/// Why a depth grid does not fit its layer.
#[derive(Debug, Clone, PartialEq)]
pub enum GridError {
    /// Step zero or too large for the image, or a vertex count that does not match.
    Size(String),
    /// A vertex's inverse depth is not finite or not above zero.
    Value {
        /// Vertex column.
        col: u32,
        /// Vertex row.
        row: u32,
        /// The value.
        value: f32,
    },
}

impl std::fmt::Display for GridError {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        match self {
            Self::Size(s) => f.write_str(s),
            Self::Value { col, row, value } => write!(
                f,
                "vertex ({col}, {row}) has inverse depth {value}, finite and above 0 required"
            ),
        }
    }
}

impl DepthGrid {
    /// Largest vertex spacing.
    pub const MAX_STEP: u32 = 256;

    /// Vertex columns and rows of a grid of step `step` over a `width x height` image.
    pub fn dims(width: u32, height: u32, step: u32) -> (u32, u32) {
        (width.div_ceil(step) + 1, height.div_ceil(step) + 1)
    }

    /// Checks the grid against a `width x height` layer.
    pub fn check(&self, width: u32, height: u32) -> Result<(), GridError> {
        if self.step == 0 || self.step > Self::MAX_STEP {
            return Err(GridError::Size(format!(
                "step {} outside 1..={}",
                self.step,
                Self::MAX_STEP
            )));
        }
        let (c, r) = Self::dims(width, height, self.step);
        if (self.cols, self.rows) != (c, r) || self.inverse_depth.len() != (c * r) as usize {
            return Err(GridError::Size(format!(
                "{}x{} vertices ({} values), a {width}x{height} layer at step {} needs {c}x{r}",
                self.cols,
                self.rows,
                self.inverse_depth.len(),
                self.step
            )));
        }
        match self
            .inverse_depth
            .iter()
            .position(|v| !(v.is_finite() && *v > 0.0))
        {
            Some(i) => Err(GridError::Value {
                col: i as u32 % c,
                row: i as u32 / c,
                value: self.inverse_depth[i],
            }),
            None => Ok(()),
        }
    }

    /// Reference pixel position of vertex `(i, j)` in a `width x height` image.
    #[inline]
    pub fn vertex(&self, i: u32, j: u32, width: u32, height: u32) -> (f64, f64) {
        (
            (i * self.step).min(width) as f64 - 0.5,
            (j * self.step).min(height) as f64 - 0.5,
        )
    }

    /// Inverse depth at vertex `(i, j)`.
    #[inline]
    pub fn at(&self, i: u32, j: u32) -> f64 {
        self.inverse_depth[(j * self.cols + i) as usize] as f64
    }

    /// The three vertices `(i, j)` of triangle `t` (0: upper right, 1: lower left) of cell
    /// `(ci, cj)`, in the same winding for both.
    #[inline]
    pub fn triangle(ci: u32, cj: u32, t: u32) -> [(u32, u32); 3] {
        if t == 0 {
            [(ci, cj), (ci + 1, cj), (ci + 1, cj + 1)]
        } else {
            [(ci, cj), (ci + 1, cj + 1), (ci, cj + 1)]
        }
    }

    /// The reference-frame point of vertex `(i, j)` seen by `cam`.
    pub fn point(&self, cam: &Camera, i: u32, j: u32) -> Vec3 {
        let (u, v) = self.vertex(i, j, cam.width, cam.height);
        cam.unproject(u, v, 1.0 / self.at(i, j))
    }

    /// The plane `m` (with `m . X = 1`) of triangle `t` of cell `(ci, cj)`; `None` when its
    /// vertices are collinear in space.
    pub fn triangle_plane(&self, cam: &Camera, ci: u32, cj: u32, t: u32) -> Option<Vec3> {
        let p = Self::triangle(ci, cj, t).map(|(i, j)| self.point(cam, i, j));
        let rows = Mat3([p[0].0, p[1].0, p[2].0]);
        let m = rows.inverse()? * Vec3::new(1.0, 1.0, 1.0);
        m.is_finite().then_some(m)
    }

    /// Which cells hold a pixel where `covered` holds (pixel `y * width + x` of a
    /// `width x height` image), one pixel wider on each side for bilinear taps; cell
    /// `(ci, cj)` at `cj * (cols - 1) + ci`.
    pub fn occupied(&self, width: u32, height: u32, covered: impl Fn(usize) -> bool) -> Vec<bool> {
        self.occupied_in(width, height, (0..width, 0..height), covered)
    }

    /// [`Self::occupied`] where `covered` holds nowhere outside columns `xs` and rows `ys`.
    pub fn occupied_in(
        &self,
        width: u32,
        height: u32,
        (xs, ys): (Range<u32>, Range<u32>),
        covered: impl Fn(usize) -> bool,
    ) -> Vec<bool> {
        let (cw, ch) = (self.cols - 1, self.rows - 1);
        let mut cells = vec![false; (cw * ch) as usize];
        let s = self.step;
        let x_end = xs.end.min(width);
        // A pixel in column x marks the cell columns (x - 1) / s ..= (x + 1) / s (at most the
        // last), so cell column i is marked by columns i * s - 1 ..= (i + 1) * s: per row,
        // each cell column's range is looked at until its first covered pixel.
        let ranges: Vec<(u32, u32)> = (0..cw)
            .map(|i| {
                (
                    (i * s).saturating_sub(1).max(xs.start),
                    ((i + 1) * s + 1).min(x_end),
                )
            })
            .collect();
        let mut marked = vec![false; cw as usize];
        for y in ys.start..ys.end.min(height) {
            let row = y * width;
            let mut any = false;
            for (m, &(lo, hi)) in marked.iter_mut().zip(&ranges) {
                *m = (lo..hi).any(|x| covered((row + x) as usize));
                any |= *m;
            }
            if !any {
                continue;
            }
            let (j0, j1) = (y.saturating_sub(1) / s, ((y + 1) / s).min(ch - 1));
            for j in j0..=j1 {
                let cells = &mut cells[(j * cw) as usize..((j + 1) * cw) as usize];
                for (c, &m) in cells.iter_mut().zip(&marked) {
                    *c |= m;
                }
            }
        }
        cells
    }

    /// Sets every vertex that no occupied cell (see [`DepthGrid::occupied`]) uses to `value`:
    /// renderers draw nothing there, and a constant codes to almost nothing.
    pub fn settle_unused(&mut self, occupied: &[bool], value: f32) {
        let used = self.used_vertices(occupied);
        for (v, u) in self.inverse_depth.iter_mut().zip(used) {
            if !u {
                *v = value;
            }
        }
    }

    /// Per vertex (row by row), whether a cell of `occupied` ([`DepthGrid::occupied`]) has it
    /// as a corner.
    pub fn used_vertices(&self, occupied: &[bool]) -> Vec<bool> {
        let (cols, cw) = (self.cols, self.cols - 1);
        let mut used = vec![false; self.inverse_depth.len()];
        for (c, _) in occupied.iter().enumerate().filter(|(_, &o)| o) {
            let (ci, cj) = (c as u32 % cw, c as u32 / cw);
            for (i, j) in [(ci, cj), (ci + 1, cj), (ci, cj + 1), (ci + 1, cj + 1)] {
                used[(j * cols + i) as usize] = true;
            }
        }
        used
    }

    /// This grid at `factor` times its step over a `width x height` image, for a layer whose
    /// pixels occupy this grid's cells `occupied` ([`DepthGrid::occupied`]): each vertex takes
    /// this grid's surface at its position; vertices that only the coarser cells use are
    /// filled from their neighbours by push-pull in inverse depth, so the coarser cells stay
    /// on the layer's surface. A coarse cell is occupied where a cell of this grid within it
    /// is; the vertices no occupied coarse cell uses are set to `unused`
    /// ([`DepthGrid::settle_unused`]). `None` for a factor below 2, when the step would pass
    /// [`DepthGrid::MAX_STEP`] or the grid would have fewer than 2x2 cells.
    pub fn coarsened(
        &self,
        width: u32,
        height: u32,
        factor: u32,
        occupied: &[bool],
        unused: f32,
    ) -> Option<Self> {
        let step = self.step.checked_mul(factor)?;
        let (cols, rows) = Self::dims(width, height, step);
        if factor < 2 || step > Self::MAX_STEP || cols < 3 || rows < 3 {
            return None;
        }
        let used = self.used_vertices(occupied);
        // A coarse vertex at an exact position of this grid's vertex takes it when used.
        let (mut inv, mut known) = (Vec::new(), Vec::new());
        for j in 0..rows {
            for i in 0..cols {
                let fine = |n: u32, last: u32| (n * factor).min(last);
                let (fi, fj) = (fine(i, self.cols - 1), fine(j, self.rows - 1));
                let k = (fj * self.cols + fi) as usize;
                inv.push(self.inverse_depth[k]);
                known.push(if used[k] { 1.0 } else { 0.0 });
            }
        }
        let mut grid = Self {
            step,
            cols,
            rows,
            inverse_depth: inv,
        };
        if !crate::fill::push_pull(
            &mut grid.inverse_depth,
            &known,
            cols as usize,
            rows as usize,
            1,
        ) {
            return None;
        }
        let (cw, fw) = (cols - 1, self.cols - 1);
        let mut cells = vec![false; (cw * (rows - 1)) as usize];
        for (k, _) in occupied.iter().enumerate().filter(|(_, &o)| o) {
            let (fi, fj) = (k as u32 % fw, k as u32 / fw);
            let (ci, cj) = ((fi / factor).min(cw - 1), (fj / factor).min(rows - 2));
            cells[(cj * cw + ci) as usize] = true;
        }
        grid.settle_unused(&cells, unused);
        grid.check(width, height).ok().map(|()| grid)
    }

    /// The grid's values at the pixels of a `width x height` image, each asked for alone (as
    /// [`DepthGrid::inverse_depth_at`] gives at pixel centres; for a grid of other values per
    /// vertex, such as their logarithms, the same interpolation of those).
    pub fn pixels(self, width: u32, height: u32) -> GridPixels {
        let s = self.step;
        // Per column (row): cell and position across it.
        let along = |n: u32, v: u32| {
            let c = ((v + 1) / s).min(n.div_ceil(s) - 1);
            let (a, b) = ((c * s) as f32, ((c + 1) * s).min(n) as f32);
            (c, (v as f32 + 0.5 - a) / (b - a))
        };
        GridPixels {
            xs: (0..width).map(|x| along(width, x)).collect(),
            ys: (0..height).map(|y| along(height, y)).collect(),
            grid: self,
        }
    }

    /// Inverse depth at reference pixel `(u, v)`: affine over the triangle that holds it.
    pub fn inverse_depth_at(&self, cam: &Camera, u: f64, v: f64) -> f64 {
        let s = self.step as f64;
        let (gx, gy) = ((u + 0.5) / s, (v + 0.5) / s);
        let ci = (gx.floor().max(0.0) as u32).min(self.cols.saturating_sub(2));
        let cj = (gy.floor().max(0.0) as u32).min(self.rows.saturating_sub(2));
        let (x0, y0) = self.vertex(ci, cj, cam.width, cam.height);
        let (x1, y1) = self.vertex(ci + 1, cj + 1, cam.width, cam.height);
        let fx = ((u - x0) / (x1 - x0).max(1e-9)).clamp(0.0, 1.0);
        let fy = ((v - y0) / (y1 - y0).max(1e-9)).clamp(0.0, 1.0);
        let (a, b, c, d) = (
            self.at(ci, cj),
            self.at(ci + 1, cj),
            self.at(ci, cj + 1),
            self.at(ci + 1, cj + 1),
        );
        if fx >= fy {
            // Upper right triangle (a, b, d).
            a + (b - a) * fx + (d - b) * fy
        } else {
            a + (c - a) * fy + (d - c) * fx
        }
    }
}

mod vec3_array {
    use crate::math::Vec3;
    use serde::{Deserialize, Deserializer, Serialize, Serializer};

    pub fn serialize<S: Serializer>(v: &Vec3, s: S) -> Result<S::Ok, S::Error> {
        v.0.serialize(s)
    }
    pub fn deserialize<'de, D: Deserializer<'de>>(d: D) -> Result<Vec3, D::Error> {
        <[f64; 3]>::deserialize(d).map(Vec3)
    }
}

impl Geometry {
    /// True for the paper's fronto-parallel plane.
    pub fn is_plane(&self) -> bool {
        matches!(self, Self::Plane)
    }

    /// The name the command line and reports use.
    pub fn name(&self) -> &'static str {
        match self {
            Self::Plane => "plane",
            Self::Slanted(_) => "slanted",
            Self::Mesh(_) => "mesh",
        }
    }

    /// The plane `m` (with `m . X = 1`) of a layer at reference depth `depth`: its own for a
    /// plane, the fronto-parallel plane at `depth` for a mesh.
    pub fn plane(&self, depth: f64) -> Vec3 {
        match self {
            Self::Slanted(m) => *m,
            Self::Plane | Self::Mesh(_) => Vec3::new(0.0, 0.0, 1.0 / depth),
        }
    }

    /// Inverse depth at reference pixel `(u, v)` of a layer at reference depth `depth` seen by
    /// `cam` (may be zero or negative off the layer's extent for a slanted plane).
    pub fn inverse_depth_at(&self, depth: f64, cam: &Camera, u: f64, v: f64) -> f64 {
        if let Self::Mesh(g) = self {
            return g.inverse_depth_at(cam, u, v);
        }
        let m = self.plane(depth);
        m.x() * (u - cam.cx) / cam.fx + m.y() * (v - cam.cy) / cam.fy + m.z()
    }

    /// For a plane (fronto-parallel or slanted) at reference depth `depth` seen by `cam`, the
    /// inverse depth as `(a, b, c)` with `1 / z = a u + b v + c` at pixel `(u, v)`; `None`
    /// for a mesh.
    pub fn pixel_plane(&self, depth: f64, cam: &Camera) -> Option<[f64; 3]> {
        if let Self::Mesh(_) = self {
            return None;
        }
        let m = self.plane(depth);
        let (a, b) = (m.x() / cam.fx, m.y() / cam.fy);
        Some([a, b, m.z() - a * cam.cx - b * cam.cy])
    }

    /// For a plane, the least inverse depth over the pixel box `[u0, v0, u1, v1]` and the
    /// corner `(u, v)` that has it (inverse depth is affine in pixels, so the least value is at
    /// a corner; a non-finite value counts as least).
    pub fn least_inverse_depth(
        &self,
        depth: f64,
        cam: &Camera,
        [u0, v0, u1, v1]: [f64; 4],
    ) -> (f64, f64, f64) {
        [(u0, v0), (u1, v0), (u0, v1), (u1, v1)]
            .map(|(u, v)| (self.inverse_depth_at(depth, cam, u, v), u, v))
            .into_iter()
            .reduce(|a, b| {
                if !b.0.is_finite() || (a.0.is_finite() && b.0 < a.0) {
                    b
                } else {
                    a
                }
            })
            .expect("four corners")
    }

    /// The inverse plane-induced homography (viewer pixels of `dst` to reference pixels of
    /// `src`) of a layer at reference depth `depth`, for the viewer at `pose`; `None` when the
    /// viewer is not on the reference camera's side of the plane. A [`Geometry::Plane`] gives
    /// exactly [`Homography::plane_inverse`]; a mesh has one per triangle
    /// ([`plane_inverse`]).
    pub fn inverse_homography(
        &self,
        depth: f64,
        src: &Camera,
        dst: &Camera,
        pose: &Pose,
    ) -> Option<Homography> {
        match self {
            Self::Plane => Homography::plane_inverse(src, dst, pose, depth),
            Self::Slanted(m) => plane_inverse(*m, src, dst, pose),
            Self::Mesh(_) => None,
        }
    }
}

/// The inverse homography of the plane `m . X = 1` (see [`Geometry::inverse_homography`]).
pub fn plane_inverse(m: Vec3, src: &Camera, dst: &Camera, pose: &Pose) -> Option<Homography> {
    // Viewer ray r = R K_t^-1 q meets m . (l r + t) = 1 at l = (1 - m.t) / (m . r), so the
    // reference point is proportional to ((1 - m.t) I + t m^T) r; positive w where the
    // ray meets the plane in front of the viewer and in front of the reference camera.
    let gap = 1.0 - m.dot(pose.translation);
    if gap.partial_cmp(&(MIN_PLANE_DISTANCE * m.norm())) != Some(std::cmp::Ordering::Greater) {
        return None;
    }
    if pose.rotation == Mat3::IDENTITY && pose.translation == Vec3::ZERO && src == dst {
        // Exact identity: no rounding from K * K^-1.
        return Some(Homography::IDENTITY);
    }
    let a = Mat3::IDENTITY
        .scale(gap)
        .add(&Mat3::outer(pose.translation, m));
    Some(Homography(src.k() * a * pose.rotation * dst.k_inv()))
}

/// Robust fit of a slanted plane to samples `(x_n, y_n, inverse depth, weight)` in normalised
/// image coordinates: weighted least squares of the affine inverse depth, re-weighted
/// (Cauchy, scale from the median residual) `iterations` times. `None` with fewer than three
/// independent samples.
pub fn fit_plane(samples: &[[f64; 4]], iterations: usize) -> Option<Vec3> {
    let solve = |weight: &dyn Fn(&[f64; 4]) -> f64| -> Option<Vec3> {
        let (mut a, mut b) = ([[0.0f64; 3]; 3], [0.0f64; 3]);
        for s in samples {
            let w = weight(s);
            if w <= 0.0 {
                continue;
            }
            let p = [s[0], s[1], 1.0];
            for i in 0..3 {
                for j in 0..3 {
                    a[i][j] += w * p[i] * p[j];
                }
                b[i] += w * p[i] * s[2];
            }
        }
        let inv = Mat3(a).inverse()?;
        let m = inv * Vec3(b);
        m.is_finite().then_some(m)
    };
    let mut m = solve(&|s| s[3])?;
    for _ in 0..iterations {
        let res = |s: &[f64; 4]| (m.x() * s[0] + m.y() * s[1] + m.z() - s[2]).abs();
        let mut r: Vec<f64> = samples.iter().filter(|s| s[3] > 0.0).map(res).collect();
        let mid = r.len() / 2;
        let scale = 1.4826 * *r.select_nth_unstable_by(mid, f64::total_cmp).1;
        let c = (2.385 * scale).max(1e-12);
        let cur = m;
        let res = |s: &[f64; 4]| (cur.x() * s[0] + cur.y() * s[1] + cur.z() - s[2]).abs();
        m = solve(&|s| s[3] / (1.0 + (res(s) / c).powi(2)))?;
    }
    Some(m)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn occupied_cells_are_those_next_to_a_covered_pixel() {
        // The definition, pixel by pixel: each covered pixel marks the cells its bilinear taps
        // reach.
        let reference = |g: &DepthGrid, w: u32, h: u32, covered: &[bool]| {
            let (cw, ch) = (g.cols - 1, g.rows - 1);
            let mut cells = vec![false; (cw * ch) as usize];
            for y in 0..h {
                for x in 0..w {
                    if !covered[(y * w + x) as usize] {
                        continue;
                    }
                    let s = g.step;
                    for j in y.saturating_sub(1) / s..=((y + 1) / s).min(ch - 1) {
                        for i in x.saturating_sub(1) / s..=((x + 1) / s).min(cw - 1) {
                            cells[(j * cw + i) as usize] = true;
                        }
                    }
                }
            }
            cells
        };
        let mut seed = 7u32;
        let mut next = || {
            seed = seed.wrapping_mul(1_664_525).wrapping_add(1_013_904_223);
            seed >> 8
        };
        for (w, h) in [(1, 1), (5, 3), (37, 29), (64, 48), (130, 71)] {
            for step in [1, 2, 3, 4, 8, 16] {
                let (cols, rows) = DepthGrid::dims(w, h, step);
                let g = DepthGrid {
                    step,
                    cols,
                    rows,
                    inverse_depth: vec![1.0; (cols * rows) as usize],
                };
                for density in [0, 1, 20, 200, 256] {
                    let covered: Vec<bool> = (0..w * h).map(|_| next() % 256 < density).collect();
                    let want = reference(&g, w, h, &covered);
                    assert_eq!(
                        g.occupied(w, h, |p| covered[p]),
                        want,
                        "{w}x{h} step {step}"
                    );
                    // A box that holds every covered pixel gives the same cells.
                    let (mut x0, mut y0, mut x1, mut y1) = (w, h, 0, 0);
                    for p in (0..w * h).filter(|&p| covered[p as usize]) {
                        (x0, y0) = (x0.min(p % w), y0.min(p / w));
                        (x1, y1) = (x1.max(p % w + 1), y1.max(p / w + 1));
                    }
                    let boxed = g.occupied_in(w, h, (x0..x1, y0..y1), |p| covered[p]);
                    assert_eq!(boxed, want, "{w}x{h} step {step} in a box");
                }
            }
        }
    }

    fn cam() -> Camera {
        Camera::from_fov(320, 240, 70.0)
    }

    #[test]
    fn coarsened_grid_keeps_the_surface_and_fills_what_only_it_uses() {
        // 100x60 at step 10: an inverse depth affine in the pixel position (exact on any grid);
        // the fine grid's right third is unused and holds garbage.
        let (w, h) = (100, 60);
        let (cols, rows) = DepthGrid::dims(w, h, 10);
        let f = |u: f64, v: f64| (0.2 + 0.001 * u + 0.002 * v) as f32;
        let mut inv = Vec::new();
        for j in 0..rows {
            for i in 0..cols {
                let (u, v) = ((i * 10).min(w) as f64 - 0.5, (j * 10).min(h) as f64 - 0.5);
                inv.push(if i <= 7 { f(u, v) } else { 9.0 });
            }
        }
        // The layer occupies the cells left of vertex column 7.
        let occupied: Vec<bool> = (0..(cols - 1) * (rows - 1))
            .map(|c| c % (cols - 1) <= 6)
            .collect();
        let g = DepthGrid {
            step: 10,
            cols,
            rows,
            inverse_depth: inv,
        };
        let c = g.coarsened(w, h, 2, &occupied, 0.3).unwrap();
        assert_eq!((c.step, c.cols, c.rows), (20, 6, 4));
        c.check(w, h).unwrap();
        for j in 0..c.rows {
            for i in 0..c.cols {
                let (u, v) = c.vertex(i, j, w, h);
                let got = c.at(i, j) as f32;
                if i <= 3 {
                    assert!((got - f(u, v)).abs() < 1e-6, "({i}, {j}) {got}");
                } else if i == 4 {
                    // Used only by the coarse cells: filled from the used vertices, never the
                    // garbage.
                    assert!(got > 0.1 && got < 0.6 && got != 0.3, "({i}, {j}) {got}");
                } else {
                    // No occupied coarse cell uses it.
                    assert_eq!(got, 0.3, "({i}, {j})");
                }
            }
        }
        assert!(g.coarsened(w, h, 1, &occupied, 0.3).is_none());
        assert!(
            g.coarsened(w, h, 8, &occupied, 0.3).is_none(),
            "fewer than 2x2 cells"
        );
    }

    #[test]
    fn fronto_slant_matches_plane_homography() {
        let c = cam();
        let pose = Pose::from_euler_deg(Vec3::new(0.1, -0.05, 0.2), 3.0, -4.0, 1.0);
        let a = Geometry::Plane
            .inverse_homography(4.0, &c, &c, &pose)
            .unwrap();
        let b = Geometry::Slanted(Vec3::new(0.0, 0.0, 0.25))
            .inverse_homography(4.0, &c, &c, &pose)
            .unwrap();
        for (x, y) in [(0.0, 0.0), (160.0, 120.0), (319.0, 239.0)] {
            let (p, q) = (a.apply(x, y).unwrap(), b.apply(x, y).unwrap());
            assert!((p.0 - q.0).abs() < 1e-9 && (p.1 - q.1).abs() < 1e-9);
        }
    }

    #[test]
    fn slanted_homography_follows_the_plane() {
        // A floor-like plane: depth grows towards the top of the image.
        let c = cam();
        let g = Geometry::Slanted(Vec3::new(0.0, 0.3, 0.25));
        let pose = Pose::from_euler_deg(Vec3::new(0.2, 0.1, -0.3), 2.0, 5.0, -1.0);
        let h = g.inverse_homography(4.0, &c, &c, &pose).unwrap();
        for (u, v) in [(20.0, 200.0), (160.0, 120.0), (300.0, 180.0)] {
            let z = 1.0 / g.inverse_depth_at(4.0, &c, u, v);
            let seen = c.project(pose.ref_to_view(c.unproject(u, v, z))).unwrap();
            let (u2, v2) = h.apply(seen.0, seen.1).unwrap();
            assert!((u2 - u).abs() < 1e-6 && (v2 - v).abs() < 1e-6, "{u2},{v2}");
        }
        // Crossing the plane hides it.
        let through = Pose::from_translation(Vec3::new(0.0, 0.0, 5.0));
        assert!(g.inverse_homography(4.0, &c, &c, &through).is_none());
    }

    #[test]
    fn mesh_triangles_are_planes_through_their_vertices() {
        let c = cam();
        let (cols, rows) = DepthGrid::dims(c.width, c.height, 32);
        let grid = DepthGrid {
            step: 32,
            cols,
            rows,
            inverse_depth: (0..cols * rows)
                .map(|k| 0.2 + 0.01 * (k % 7) as f32 + 0.003 * (k / cols) as f32)
                .collect(),
        };
        grid.check(c.width, c.height).unwrap();
        assert!(grid.check(c.width + 40, c.height).is_err());
        let pixels = grid.clone().pixels(c.width, c.height);
        for (ci, cj, t) in [(0, 0, 0), (3, 2, 1), (8, 6, 0), (8, 6, 1)] {
            let m = grid.triangle_plane(&c, ci, cj, t).unwrap();
            for (i, j) in DepthGrid::triangle(ci, cj, t) {
                assert!((m.dot(grid.point(&c, i, j)) - 1.0).abs() < 1e-9);
            }
            // Inside the triangle the plane and the pixels' interpolation agree.
            let (x0, y0) = grid.vertex(ci, cj, c.width, c.height);
            let (u, v) = if t == 0 {
                (x0 + 20.5, y0 + 8.5)
            } else {
                (x0 + 8.5, y0 + 20.5)
            };
            let on_plane = Geometry::Slanted(m).inverse_depth_at(1.0, &c, u, v);
            let at = grid.inverse_depth_at(&c, u, v);
            let px = pixels.at(u as usize, v as usize) as f64;
            assert!(
                (on_plane - at).abs() < 1e-6 && (at - px).abs() < 1e-5,
                "{on_plane} {at} {px}"
            );
        }
    }

    #[test]
    fn robust_fit_ignores_outliers() {
        let truth = Vec3::new(0.1, -0.2, 0.5);
        let mut s = Vec::new();
        for i in 0..40 {
            for j in 0..30 {
                let (x, y) = (i as f64 / 40.0 - 0.5, j as f64 / 30.0 - 0.5);
                let mut d = truth.x() * x + truth.y() * y + truth.z();
                if (i * 7 + j) % 10 == 0 {
                    d *= 3.0; // 10 % gross outliers
                }
                s.push([x, y, d, 1.0]);
            }
        }
        let m = fit_plane(&s, 6).unwrap();
        assert!((m - truth).norm() < 1e-3, "{m:?}");
        assert!(fit_plane(&s[..2], 3).is_none());
    }
}
