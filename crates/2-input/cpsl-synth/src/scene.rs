//! Planar scenes ray cast from any pose.

use crate::texture::Texture;
use cpsl_core::{Camera, Pose, Vec3};
use rayon::prelude::*;
use serde::{Deserialize, Serialize};

/// A planar frame: centre and two orthogonal half-axis vectors spanning the surface.
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
pub struct Frame {
    /// Centre in reference-camera coordinates at time 0.
    pub centre: Vec3,
    /// Half-extent along the first surface axis.
    pub half_u: Vec3,
    /// Half-extent along the second surface axis.
    pub half_v: Vec3,
}

/// The outline of a planar object within its frame.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum Shape {
    /// The full rectangle `|s| <= 1, |t| <= 1`.
    Rect,
    /// The inscribed ellipse `s^2 + t^2 <= 1`.
    Ellipse,
}

/// One textured planar object.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct Object {
    /// Name (used as the object id in ground-truth masks).
    pub name: String,
    /// Outline.
    pub shape: Shape,
    /// Placement.
    pub frame: Frame,
    /// Surface texture.
    pub texture: Texture,
    /// Linear velocity in scene units per second.
    #[serde(default)]
    pub velocity: Vec3,
}

/// A scene: a reference camera and objects; the first object whose surface a ray meets
/// first is what that ray sees.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct Scene {
    /// Reference camera (the input view is rendered with it at the identity pose).
    pub camera: Camera,
    /// Objects, in any order.
    pub objects: Vec<Object>,
    /// Colour of rays that hit nothing.
    pub sky: [u8; 3],
}

/// What a ray cast of a view produced.
#[derive(Debug, Clone, PartialEq)]
pub struct View {
    /// Width in pixels.
    pub width: u32,
    /// Height in pixels.
    pub height: u32,
    /// RGB, 8 bits per channel, supersampled.
    pub rgb: Vec<u8>,
    /// z-depth in the viewing camera of the pixel-centre ray (`f32::INFINITY` where nothing
    /// was hit).
    pub depth: Vec<f32>,
    /// Index into `Scene::objects` hit by the pixel-centre ray (`u16::MAX` for none).
    pub object: Vec<u16>,
}

impl Object {
    /// Ray hit: distance along the ray and surface coordinates in scene units.
    fn hit(&self, origin: Vec3, dir: Vec3, time: f64) -> Option<(f64, f64, f64)> {
        let f = &self.frame;
        let c = f.centre + self.velocity * time;
        let n = f.half_u.cross(f.half_v);
        let denom = n.dot(dir);
        if denom.abs() < 1e-12 {
            return None;
        }
        let lambda = n.dot(c - origin) / denom;
        if lambda <= 1e-9 {
            return None;
        }
        let d = origin + dir * lambda - c;
        let (uu, vv) = (f.half_u.dot(f.half_u), f.half_v.dot(f.half_v));
        let s = d.dot(f.half_u) / uu;
        let t = d.dot(f.half_v) / vv;
        let inside = match self.shape {
            Shape::Rect => s.abs() <= 1.0 && t.abs() <= 1.0,
            Shape::Ellipse => s * s + t * t <= 1.0,
        };
        inside.then(|| (lambda, s * uu.sqrt(), t * vv.sqrt()))
    }
}

impl Scene {
    /// Nearest hit of a ray: object index, distance along the ray, colour.
    fn trace(&self, origin: Vec3, dir: Vec3, time: f64) -> Option<(usize, f64, [f64; 3])> {
        let mut best: Option<(usize, f64, f64, f64)> = None;
        for (i, o) in self.objects.iter().enumerate() {
            if let Some((l, s, t)) = o.hit(origin, dir, time) {
                if best.is_none_or(|b| l < b.1) {
                    best = Some((i, l, s, t));
                }
            }
        }
        best.map(|(i, l, s, t)| (i, l, self.objects[i].texture.sample(s, t)))
    }

    /// Ray casts the view of camera `cam` at `pose` (viewer in the reference frame) at `time`,
    /// with `ss x ss` supersamples per pixel for colour.
    pub fn render(&self, cam: &Camera, pose: &Pose, time: f64, ss: u32) -> View {
        let (w, h) = (cam.width as usize, cam.height as usize);
        let ss = ss.max(1);
        let mut rgb = vec![0u8; w * h * 3];
        let mut depth = vec![0f32; w * h];
        let mut object = vec![0u16; w * h];
        let sky = self.sky.map(|v| v as f64);
        rgb.par_chunks_mut(w * 3)
            .zip(depth.par_chunks_mut(w))
            .zip(object.par_chunks_mut(w))
            .enumerate()
            .for_each(|(y, ((rgb_row, depth_row), obj_row))| {
                for x in 0..w {
                    let ray = |u: f64, v: f64| {
                        let d_view = Vec3::new((u - cam.cx) / cam.fx, (v - cam.cy) / cam.fy, 1.0);
                        (d_view, pose.rotation * d_view)
                    };
                    // Centre ray: depth and object id. Since d_view.z = 1, the distance along
                    // the ray is the z-depth in the viewing camera.
                    let (_, dir) = ray(x as f64, y as f64);
                    match self.trace(pose.translation, dir, time) {
                        Some((i, l, _)) => {
                            depth_row[x] = l as f32;
                            obj_row[x] = i as u16;
                        }
                        None => {
                            depth_row[x] = f32::INFINITY;
                            obj_row[x] = u16::MAX;
                        }
                    }
                    let mut sum = [0.0f64; 3];
                    for sy in 0..ss {
                        for sx in 0..ss {
                            let u = x as f64 + (sx as f64 + 0.5) / ss as f64 - 0.5;
                            let v = y as f64 + (sy as f64 + 0.5) / ss as f64 - 0.5;
                            let (_, dir) = ray(u, v);
                            let c = self.trace(pose.translation, dir, time).map_or(sky, |h| h.2);
                            for i in 0..3 {
                                sum[i] += c[i];
                            }
                        }
                    }
                    let n = (ss * ss) as f64;
                    for i in 0..3 {
                        rgb_row[x * 3 + i] = (sum[i] / n).round().clamp(0.0, 255.0) as u8;
                    }
                }
            });
        View {
            width: cam.width,
            height: cam.height,
            rgb,
            depth,
            object,
        }
    }

    /// The built-in default scene: a brick wall at depth 10, a floor slanting from depth 2 to
    /// 10, and four objects between depth 2.5 and 6 (a fronto-parallel checker board, a
    /// striped disc, a slanted noisy panel and a thin pole), some of them moving.
    pub fn default_scene(width: u32, height: u32) -> Self {
        let camera = Camera::from_fov(width, height, 60.0);
        let v = Vec3::new;
        let obj = |name: &str, shape, centre, half_u, half_v, texture, velocity| Object {
            name: name.into(),
            shape,
            frame: Frame {
                centre,
                half_u,
                half_v,
            },
            texture,
            velocity,
        };
        let slant = 40f64.to_radians();
        Self {
            camera,
            sky: [40, 40, 48],
            objects: vec![
                obj(
                    "wall",
                    Shape::Rect,
                    v(0.0, 0.0, 10.0),
                    v(14.0, 0.0, 0.0),
                    v(0.0, 10.0, 0.0),
                    Texture::Bricks {
                        brick: [150, 70, 50],
                        mortar: [200, 195, 185],
                        size: 0.8,
                    },
                    Vec3::ZERO,
                ),
                obj(
                    "floor",
                    Shape::Rect,
                    v(0.0, 1.5, 6.0),
                    v(14.0, 0.0, 0.0),
                    v(0.0, 0.0, 4.0),
                    Texture::Checker {
                        a: [90, 90, 100],
                        b: [170, 165, 150],
                        cell: 0.5,
                    },
                    Vec3::ZERO,
                ),
                obj(
                    "board",
                    Shape::Rect,
                    v(-0.9, 0.1, 2.5),
                    v(0.45, 0.0, 0.0),
                    v(0.0, 0.6, 0.0),
                    Texture::Checker {
                        a: [200, 30, 40],
                        b: [240, 235, 225],
                        cell: 0.15,
                    },
                    v(0.25, 0.0, 0.0),
                ),
                obj(
                    "disc",
                    Shape::Ellipse,
                    v(1.0, -0.35, 4.0),
                    v(0.8, 0.0, 0.0),
                    v(0.0, 0.8, 0.0),
                    Texture::Stripes {
                        a: [30, 60, 200],
                        b: [250, 210, 40],
                        period: 0.3,
                        angle_deg: 30.0,
                    },
                    v(0.0, 0.15, 0.0),
                ),
                obj(
                    "panel",
                    Shape::Rect,
                    v(-0.6, -1.0, 6.0),
                    v(1.0 * slant.cos(), 0.0, 1.0 * slant.sin()),
                    v(0.0, 0.7, 0.0),
                    Texture::Noise {
                        a: [20, 90, 30],
                        b: [160, 230, 120],
                        scale: 0.25,
                        seed: 42,
                    },
                    Vec3::ZERO,
                ),
                obj(
                    "pole",
                    Shape::Rect,
                    v(0.25, 0.2, 3.2),
                    v(0.05, 0.0, 0.0),
                    v(0.0, 1.3, 0.0),
                    Texture::Stripes {
                        a: [240, 240, 240],
                        b: [20, 20, 20],
                        period: 0.2,
                        angle_deg: 90.0,
                    },
                    v(-0.1, 0.0, 0.0),
                ),
            ],
        }
    }

    /// The true motion between two views from the reference camera at the identity pose,
    /// `dt` seconds apart: for every pixel of the later view (`later`), where the surface it
    /// shows was in the earlier one (`dx, dy` interleaved, pixels), and whether the earlier
    /// view shows that surface there (the same object at the rounded position).
    pub fn backward_motion(&self, earlier: &View, later: &View, dt: f64) -> (Vec<f32>, Vec<bool>) {
        let cam = self.camera;
        let (w, h) = (later.width as usize, later.height as usize);
        let mut flow = vec![0f32; w * h * 2];
        let mut seen = vec![false; w * h];
        for p in 0..w * h {
            let o = later.object[p];
            if o == u16::MAX {
                continue;
            }
            let (x, y) = ((p % w) as f64, (p / w) as f64);
            let at = cam.unproject(x, y, later.depth[p] as f64);
            let Some((sx, sy)) = cam.project(at - self.objects[o as usize].velocity * dt) else {
                continue;
            };
            flow[p * 2] = (sx - x) as f32;
            flow[p * 2 + 1] = (sy - y) as f32;
            let (qx, qy) = (sx.round(), sy.round());
            if qx >= 0.0 && qy >= 0.0 && qx < w as f64 && qy < h as f64 {
                seen[p] = earlier.object[qy as usize * w + qx as usize] == o;
            }
        }
        (flow, seen)
    }

    /// Poses of the ground-truth novel views written by `cpsl synth`: a horizontal sweep, a
    /// vertical sweep, a dolly and small rotations.
    pub fn default_views() -> Vec<(String, Pose)> {
        let mut v = Vec::new();
        for i in 0..7 {
            let tx = (i as f64 - 3.0) * 0.1;
            v.push((
                format!("tx{tx:+.2}"),
                Pose::from_translation(Vec3::new(tx, 0.0, 0.0)),
            ));
        }
        for ty in [-0.2, 0.2] {
            v.push((
                format!("ty{ty:+.2}"),
                Pose::from_translation(Vec3::new(0.0, ty, 0.0)),
            ));
        }
        for tz in [-0.3, 0.3] {
            v.push((
                format!("tz{tz:+.2}"),
                Pose::from_translation(Vec3::new(0.0, 0.0, tz)),
            ));
        }
        v.push((
            "orbit_left".into(),
            Pose::from_euler_deg(Vec3::new(-0.25, 0.0, 0.0), 0.0, 3.0, 0.0),
        ));
        v.push((
            "orbit_right".into(),
            Pose::from_euler_deg(Vec3::new(0.25, 0.0, 0.0), 0.0, -3.0, 0.0),
        ));
        v
    }

    /// `n` camera poses orbiting a point `distance` ahead of the first: each frame turns
    /// `step_deg` to the left while moving to the right along the circle (the clips camera
    /// tracking and multi-view depth are tested and timed on).
    pub fn orbit_path(n: usize, step_deg: f64, distance: f64) -> Vec<Pose> {
        (0..n)
            .map(|i| {
                let a = step_deg * i as f64;
                let (s, c) = a.to_radians().sin_cos();
                let p = Pose::from_euler_deg(Vec3::ZERO, 0.0, -a, 0.0);
                Pose {
                    rotation: p.rotation,
                    translation: Vec3::new(distance * s, 0.0, distance * (1.0 - c)),
                }
            })
            .collect()
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn the_orbit_keeps_its_distance_and_looks_at_its_centre() {
        let centre = Vec3::new(0.0, 0.0, 4.0);
        for p in Scene::orbit_path(40, 1.5, 4.0) {
            let to_centre = centre - p.translation;
            assert!((to_centre.norm() - 4.0).abs() < 1e-9);
            let forward = p.rotation * Vec3::new(0.0, 0.0, 1.0);
            assert!((forward.dot(to_centre.normalized()) - 1.0).abs() < 1e-9);
        }
    }

    #[test]
    fn default_scene_depth_is_exact_at_fronto_objects() {
        let s = Scene::default_scene(160, 120);
        let v = s.render(&s.camera, &Pose::IDENTITY, 0.0, 1);
        // The board sits at z = 2.5: where its id is seen, depth must be 2.5.
        let board = s.objects.iter().position(|o| o.name == "board").unwrap() as u16;
        let n = v.object.iter().filter(|&&o| o == board).count();
        assert!(n > 100, "board visible ({n} px)");
        for (d, o) in v.depth.iter().zip(&v.object) {
            if *o == board {
                assert!((d - 2.5).abs() < 1e-5);
            }
            assert!(d.is_finite() && *d > 0.0);
        }
    }

    #[test]
    fn translation_moves_near_objects_more() {
        let s = Scene::default_scene(160, 120);
        let a = s.render(&s.camera, &Pose::IDENTITY, 0.0, 1);
        let b = s.render(
            &s.camera,
            &Pose::from_translation(Vec3::new(0.2, 0.0, 0.0)),
            0.0,
            1,
        );
        assert_ne!(a.rgb, b.rgb);
    }
}
