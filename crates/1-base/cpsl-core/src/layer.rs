//! Layers and validated layer sets.

use crate::camera::Camera;
use crate::error::CoreError;
use crate::geometry::Geometry;
use crate::homography::Homography;
use crate::image::PremulImage;
use crate::limits::Limits;
use crate::pose::Pose;
use serde::{Deserialize, Serialize};

/// What a layer holds, as decided by the layering stage.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum LayerRole {
    /// A promoted salient instance.
    Instance,
    /// A depth region (merged background or depth slice).
    Region,
    /// The farthest layer, filled behind everything in front of it.
    Background,
}

/// Optional descriptive metadata of a layer.
#[derive(Debug, Clone, Default, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct LayerMeta {
    /// Human-readable name.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub name: Option<String>,
    /// The layer's role.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub role: Option<LayerRole>,
    /// Mean saliency of the layer's pixels, in [0, 1].
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub saliency: Option<f32>,
    /// Identity across the frames of a video: layers of consecutive frames with the same track
    /// hold the same content (layer indices follow depth order and may change).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub track: Option<u32>,
}

/// One CPSL layer `L_k = (C_k, alpha_k, z_k)`: premultiplied colour and alpha, the layer's
/// reference depth and the surface its pixels lie on.
#[derive(Debug, Clone, PartialEq)]
pub struct Layer {
    /// Premultiplied RGBA.
    pub image: PremulImage,
    /// Reference depth `z_k` (scene units along the optical axis): the depth of a
    /// fronto-parallel layer, the median depth of a slanted one. Layers are ordered by it.
    pub depth: f64,
    /// The layer's surface (the paper's fronto-parallel plane by default).
    pub geometry: Geometry,
    /// Optional metadata.
    pub meta: LayerMeta,
}

impl Layer {
    /// A fronto-parallel layer without metadata.
    pub fn new(image: PremulImage, depth: f64) -> Self {
        Self {
            image,
            depth,
            geometry: Geometry::Plane,
            meta: LayerMeta::default(),
        }
    }

    /// The inverse homography that draws this layer (viewer pixels of `dst` to reference
    /// pixels of `src`) for the viewer at `pose`; `None` when the layer is not visible.
    pub fn inverse_homography(
        &self,
        src: &Camera,
        dst: &Camera,
        pose: &Pose,
    ) -> Option<Homography> {
        self.geometry.inverse_homography(self.depth, src, dst, pose)
    }

    /// Bounding box `[x0, y0, x1, y1]` (inclusive) of the pixels with alpha above zero.
    pub fn extent(&self) -> Option<[u32; 4]> {
        let (w, h) = (self.image.width() as usize, self.image.height() as usize);
        let bytes = self.image.as_bytes();
        let mut b: Option<[u32; 4]> = None;
        for y in 0..h {
            let row = &bytes[y * w * 4..(y + 1) * w * 4];
            let covered = |p: &[u8]| p[3] != 0;
            let Some(x0) = row.chunks_exact(4).position(covered) else {
                continue;
            };
            let x1 = row.chunks_exact(4).rposition(covered).unwrap_or(x0);
            let (x0, x1, y) = (x0 as u32, x1 as u32, y as u32);
            b = Some(match b {
                None => [x0, y, x1, y],
                Some([a, c, d, _]) => [a.min(x0), c, d.max(x1), y],
            });
        }
        b
    }

    /// Cheaper surfaces for a mesh layer, in the order a coder under a budget gives up its
    /// grid: the grid at twice and four times its step ([`crate::DepthGrid::coarsened`],
    /// where the frame allows), then the plane that best fits it. Empty for other layers.
    pub fn geometry_ladder(&self, cam: &Camera) -> Vec<Geometry> {
        let Geometry::Mesh(g) = &self.geometry else {
            return Vec::new();
        };
        let (w, h) = (cam.width, cam.height);
        let bytes = self.image.as_bytes();
        let occupied = g.occupied(w, h, |p| bytes[p * 4 + 3] != 0);
        let used = g.used_vertices(&occupied);
        let mut ladder: Vec<Geometry> = [2, 4]
            .into_iter()
            .filter_map(|factor| g.coarsened(w, h, factor, &occupied, (1.0 / self.depth) as f32))
            .map(|coarse| Geometry::Mesh(std::sync::Arc::new(coarse)))
            .collect();
        ladder.push(self.flattened(cam, g, &used));
        ladder
    }

    /// A plane for mesh layer with grid `g` whose `used` vertices its pixels occupy: the
    /// slanted plane that best fits them, or the fronto-parallel plane where that plane would
    /// not keep the layer's extent in front of the camera.
    fn flattened(&self, cam: &Camera, g: &crate::DepthGrid, used: &[bool]) -> Geometry {
        let mut samples = Vec::new();
        for j in 0..g.rows {
            for i in 0..g.cols {
                if used[(j * g.cols + i) as usize] {
                    let (u, v) = g.vertex(i, j, cam.width, cam.height);
                    samples.push([
                        (u - cam.cx) / cam.fx,
                        (v - cam.cy) / cam.fy,
                        g.at(i, j),
                        1.0,
                    ]);
                }
            }
        }
        let Some(m) = crate::geometry::fit_plane(&samples, 3) else {
            return Geometry::Plane;
        };
        let plane = Geometry::Slanted(m);
        let in_front = self
            .grown_extent()
            .is_none_or(|b| plane.least_inverse_depth(self.depth, cam, b).0 > 0.0);
        if in_front {
            plane
        } else {
            Geometry::Plane
        }
    }

    /// Makes transparent every pixel where the layer's surface is not in front of the
    /// reference camera with a pixel to spare, and then, while the layer's extent (the box
    /// around its pixels, grown by one) still reaches behind the camera at a corner, the
    /// extent's outermost row or column at that corner (the one with fewer pixels), so that
    /// the layer passes the check of [`LayerSet::new`]. Lossy coding spreads faint alpha
    /// beyond a layer's extent; beyond a slanted plane's horizon such texels are noise.
    /// (Pixels in front of the camera one by one can still span a box whose far corner is
    /// not: a decoded P-frame of the fox did, and its package could not be read.)
    pub fn clip_to_geometry(&mut self, cam: &Camera) {
        self.clip_pixels_to_geometry(cam);
        while let Some(e @ [x0, y0, x1, y1]) = self.extent() {
            let (inv, u, v) = self.geometry.least_inverse_depth(self.depth, cam, grow(e));
            if inv.is_finite() && inv > 0.0 {
                return;
            }
            let col = if u < f64::from(x0) { x0 } else { x1 } as usize;
            let row = if v < f64::from(y0) { y0 } else { y1 } as usize;
            let w = self.image.width() as usize;
            let bytes = self.image.as_bytes();
            let in_col = bytes.chunks_exact(w * 4).filter(|l| l[col * 4 + 3] != 0);
            let in_row = bytes[row * w * 4..(row + 1) * w * 4].chunks_exact(4);
            // The edge with fewer pixels goes.
            let row_goes = in_row.filter(|p| p[3] != 0).count() < in_col.count();
            let bytes = self.image.as_bytes_mut();
            if row_goes {
                bytes[row * w * 4..(row + 1) * w * 4].fill(0);
            } else {
                let lines = bytes.chunks_exact_mut(w * 4);
                lines.for_each(|l| l[col * 4..col * 4 + 4].fill(0));
            }
        }
    }

    /// The per-pixel part of [`Layer::clip_to_geometry`].
    fn clip_pixels_to_geometry(&mut self, cam: &Camera) {
        if !matches!(self.geometry, Geometry::Slanted(_)) {
            return;
        }
        let Some([a, b, c]) = self.geometry.pixel_plane(self.depth, cam) else {
            return;
        };
        let margin = a.abs() + b.abs();
        let w = self.image.width() as usize;
        for (y, row) in self
            .image
            .as_bytes_mut()
            .chunks_exact_mut(w * 4)
            .enumerate()
        {
            let base = b * y as f64 + c;
            for (x, p) in row.chunks_exact_mut(4).enumerate() {
                if p[3] != 0 && a * x as f64 + base <= margin {
                    p.fill(0);
                }
            }
        }
    }

    /// The layer's extent grown by one pixel (the bilinear footprint), as `[u0, v0, u1, v1]`.
    fn grown_extent(&self) -> Option<[f64; 4]> {
        self.extent().map(grow)
    }

    /// Checks the geometry against the camera: finite, and a depth above zero over the
    /// layer's extent (grown by one pixel for the bilinear footprint).
    fn check_geometry(&self, index: usize, cam: &Camera) -> Result<(), CoreError> {
        let bad = |reason: String| CoreError::BadGeometry { index, reason };
        let m = match &self.geometry {
            Geometry::Plane => return Ok(()),
            Geometry::Mesh(g) => {
                return g
                    .check(cam.width, cam.height)
                    .map_err(|e| bad(format!("mesh: {e}")))
            }
            Geometry::Slanted(m) => *m,
        };
        if !m.is_finite() {
            return Err(bad(format!("plane {:?} is not finite", m.0)));
        }
        let Some(b) = self.grown_extent() else {
            return Ok(());
        };
        let (inv, u, v) = self.geometry.least_inverse_depth(self.depth, cam, b);
        if !(inv.is_finite() && inv > 0.0) {
            return Err(bad(format!(
                "plane {:?} puts pixel ({u}, {v}) of the layer's extent at depth {}",
                m.0,
                1.0 / inv
            )));
        }
        Ok(())
    }
}

/// An extent `[u0, v0, u1, v1]` grown by one pixel on every side.
fn grow([x0, y0, x1, y1]: [u32; 4]) -> [f64; 4] {
    [
        f64::from(x0) - 1.0,
        f64::from(y0) - 1.0,
        f64::from(x1) + 1.0,
        f64::from(y1) + 1.0,
    ]
}

/// A validated, depth-ordered stack of layers seen by one reference camera.
///
/// Invariants (checked by [`LayerSet::new`]): at least one layer and at most
/// `limits.max_layers`; the camera is valid and within the size limits; every layer has the
/// camera's size; depths are finite, positive and strictly increasing (nearest first); images
/// are premultiplied.
#[derive(Debug, Clone, PartialEq)]
pub struct LayerSet {
    camera: Camera,
    layers: Vec<Layer>,
}

impl LayerSet {
    /// Validates and builds a layer set.
    pub fn new(camera: Camera, layers: Vec<Layer>, limits: &Limits) -> Result<Self, CoreError> {
        Self::build(camera, layers, limits, true)
    }

    /// [`LayerSet::new`] for layers whose images are premultiplied by construction (for
    /// example resampled from a layer set with a filter that treats every channel alike):
    /// every other invariant is checked, premultiplication only in debug builds. It saves a
    /// pass over every pixel of every layer, about 3 ms per 720p video frame of six layers.
    pub fn new_premultiplied(
        camera: Camera,
        layers: Vec<Layer>,
        limits: &Limits,
    ) -> Result<Self, CoreError> {
        Self::build(camera, layers, limits, cfg!(debug_assertions))
    }

    fn build(
        camera: Camera,
        layers: Vec<Layer>,
        limits: &Limits,
        check_premultiplied: bool,
    ) -> Result<Self, CoreError> {
        camera.validate()?;
        limits.check_size("camera", camera.width, camera.height)?;
        if layers.is_empty() {
            return Err(CoreError::Empty);
        }
        if layers.len() > limits.max_layers {
            return Err(CoreError::TooManyLayers {
                found: layers.len(),
                max: limits.max_layers,
            });
        }
        let mut previous: Option<f64> = None;
        for (index, layer) in layers.iter().enumerate() {
            let (w, h) = (layer.image.width(), layer.image.height());
            if (w, h) != (camera.width, camera.height) {
                return Err(CoreError::SizeMismatch {
                    index,
                    width: w,
                    height: h,
                    cam_width: camera.width,
                    cam_height: camera.height,
                });
            }
            if !(layer.depth.is_finite() && layer.depth > 0.0) {
                return Err(CoreError::BadDepth {
                    index,
                    depth: layer.depth,
                });
            }
            if let Some(p) = previous {
                if layer.depth <= p {
                    return Err(CoreError::DepthOrder {
                        index,
                        depth: layer.depth,
                        previous: p,
                    });
                }
            }
            previous = Some(layer.depth);
            layer.check_geometry(index, &camera)?;
        }
        if !check_premultiplied {
            return Ok(Self { camera, layers });
        }
        let check = |(index, layer): (usize, &Layer)| {
            layer.image.check_premultiplied(&format!("layer {index}"))
        };
        let pixels = camera.width as usize * camera.height as usize * layers.len();
        if pixels < 1 << 20 {
            layers.iter().enumerate().try_for_each(check)?;
        } else {
            // Large sets (a video frame's layers): one thread per layer; the first error in
            // layer order is reported.
            std::thread::scope(|s| {
                let checks: Vec<_> = layers
                    .iter()
                    .enumerate()
                    .map(|l| s.spawn(move || check(l)))
                    .collect();
                checks
                    .into_iter()
                    .map(|c| c.join().expect("premultiplied check"))
                    .collect::<Result<Vec<()>, CoreError>>()
            })?;
        }
        Ok(Self { camera, layers })
    }

    /// The reference camera.
    pub fn camera(&self) -> &Camera {
        &self.camera
    }
    /// Layers, nearest first.
    pub fn layers(&self) -> &[Layer] {
        &self.layers
    }
    /// Number of layers `K`.
    pub fn len(&self) -> usize {
        self.layers.len()
    }
    /// Always false: a valid layer set has at least one layer.
    pub fn is_empty(&self) -> bool {
        self.layers.is_empty()
    }
    /// Consumes the set, returning camera and layers.
    pub fn into_parts(self) -> (Camera, Vec<Layer>) {
        (self.camera, self.layers)
    }

    /// Closed-form composite of equation 2 at the reference view, in `[0, 1]` premultiplied
    /// RGBA: `I = sum_k P_k prod_{j<k} (1 - alpha_j)`. This is the ground truth an identity
    /// render must reproduce.
    pub fn composite_reference(&self) -> Vec<[f32; 4]> {
        let n = self.camera.width as usize * self.camera.height as usize;
        let mut out = vec![[0.0f32; 4]; n];
        for (i, o) in out.iter_mut().enumerate() {
            let mut t = 1.0f32;
            for l in &self.layers {
                let p = &l.image.as_bytes()[i * 4..i * 4 + 4];
                for c in 0..4 {
                    o[c] += t * (p[c] as f32 / 255.0);
                }
                t *= 1.0 - p[3] as f32 / 255.0;
            }
        }
        out
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn cam() -> Camera {
        Camera::from_fov(4, 3, 60.0)
    }
    fn layer(d: f64) -> Layer {
        Layer::new(PremulImage::new(4, 3), d)
    }

    #[test]
    fn clipping_keeps_the_extent_in_front_of_the_camera() {
        // Inverse depth 0.2 - 0.01 u + 0.01 v (pixels): two pixels in front, each with a pixel
        // to spare, whose grown box reaches (51, 4), where the plane is behind the camera.
        let c = Camera {
            width: 64,
            height: 48,
            fx: 50.0,
            fy: 50.0,
            cx: 32.0,
            cy: 24.0,
        };
        let mut l = Layer::new(PremulImage::new(64, 48), 5.0);
        l.geometry = Geometry::Slanted(crate::Vec3::new(-0.5, 0.5, 0.12));
        l.image.set_pixel(10, 5, [0, 0, 0, 255]);
        l.image.set_pixel(50, 40, [0, 0, 0, 255]);
        let err = LayerSet::new(c, vec![l.clone()], &Limits::default()).unwrap_err();
        assert!(
            matches!(err, CoreError::BadGeometry { index: 0, .. }),
            "{err}"
        );
        l.clip_to_geometry(&c);
        assert_eq!(l.extent(), Some([10, 5, 10, 5]), "one pixel left");
        assert!(LayerSet::new(c, vec![l], &Limits::default()).is_ok());
    }

    #[test]
    fn trusting_premultiplication_checks_everything_else() {
        let l = Limits::default();
        let ok = LayerSet::new_premultiplied(cam(), vec![layer(1.0), layer(2.0)], &l);
        assert_eq!(ok, LayerSet::new(cam(), vec![layer(1.0), layer(2.0)], &l));
        assert!(matches!(
            LayerSet::new_premultiplied(cam(), vec![layer(2.0), layer(2.0)], &l),
            Err(CoreError::DepthOrder { index: 1, .. })
        ));
        let mut bad = layer(1.0);
        bad.image.set_pixel(1, 1, [200, 0, 0, 100]);
        // Checked in debug builds only.
        assert_eq!(
            LayerSet::new_premultiplied(cam(), vec![bad], &l).is_err(),
            cfg!(debug_assertions)
        );
    }

    #[test]
    fn accepts_valid_and_rejects_each_violation() {
        let l = Limits::default();
        assert!(LayerSet::new(cam(), vec![layer(1.0), layer(2.0)], &l).is_ok());
        assert_eq!(LayerSet::new(cam(), vec![], &l), Err(CoreError::Empty));
        assert!(matches!(
            LayerSet::new(cam(), vec![layer(2.0), layer(2.0)], &l),
            Err(CoreError::DepthOrder { index: 1, .. })
        ));
        assert!(matches!(
            LayerSet::new(cam(), vec![layer(f64::NAN)], &l),
            Err(CoreError::BadDepth { index: 0, .. })
        ));
        assert!(matches!(
            LayerSet::new(cam(), vec![layer(-1.0)], &l),
            Err(CoreError::BadDepth { .. })
        ));
        let small = Layer::new(PremulImage::new(2, 3), 1.0);
        assert!(matches!(
            LayerSet::new(cam(), vec![small], &l),
            Err(CoreError::SizeMismatch { index: 0, .. })
        ));
        let tight = Limits {
            max_layers: 1,
            ..Limits::default()
        };
        assert!(matches!(
            LayerSet::new(cam(), vec![layer(1.0), layer(2.0)], &tight),
            Err(CoreError::TooManyLayers { .. })
        ));
    }
}
