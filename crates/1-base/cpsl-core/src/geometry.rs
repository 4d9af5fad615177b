//! The surface a layer's pixels lie on.
//!
//! The paper gives every layer a fronto-parallel plane at its depth `z_k`
//! ([`Geometry::Plane`]). A [`Geometry::Slanted`] layer lies on any plane in front of the
//! reference camera: written `m . X = 1` in the reference camera frame (`m = n / d` for a plane
//! `n . X = d`), its inverse depth is affine in normalised image coordinates,
//! `1 / z = m_x x_n + m_y y_n + m_z` with `x_n = (u - c_x) / f_x`, `y_n = (v - c_y) / f_y`, so
//! the same three numbers serve every resolution of the layer. Both are drawn with one
//! plane-induced homography ([`Geometry::inverse_homography`]).

use crate::camera::Camera;
use crate::homography::{Homography, MIN_PLANE_DISTANCE};
use crate::math::{Mat3, Vec3};
use crate::pose::Pose;
use serde::{Deserialize, Serialize};

/// A layer's surface in the reference camera; see the [module docs](self).
#[derive(Debug, Clone, Copy, PartialEq, Default, Serialize, Deserialize)]
#[serde(rename_all = "snake_case", deny_unknown_fields)]
pub enum Geometry {
    /// The fronto-parallel plane at the layer's depth (the paper's equation 1).
    #[default]
    Plane,
    /// The plane `m . X = 1` (reference camera frame), given as `m`.
    Slanted(#[serde(with = "vec3_array")] Vec3),
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

    /// The plane `m` (with `m . X = 1`) of a layer at reference depth `depth`.
    pub fn plane(&self, depth: f64) -> Vec3 {
        match *self {
            Self::Plane => Vec3::new(0.0, 0.0, 1.0 / depth),
            Self::Slanted(m) => m,
        }
    }

    /// Inverse depth at reference pixel `(u, v)` of a layer at reference depth `depth` seen by
    /// `cam` (may be zero or negative off the layer's extent for a slanted plane).
    pub fn inverse_depth_at(&self, depth: f64, cam: &Camera, u: f64, v: f64) -> f64 {
        let m = self.plane(depth);
        m.x() * (u - cam.cx) / cam.fx + m.y() * (v - cam.cy) / cam.fy + m.z()
    }

    /// The inverse plane-induced homography (viewer pixels of `dst` to reference pixels of
    /// `src`) of a layer at reference depth `depth`, for the viewer at `pose`; `None` when the
    /// viewer is not on the reference camera's side of the plane. A [`Geometry::Plane`] gives
    /// exactly [`Homography::plane_inverse`].
    pub fn inverse_homography(
        &self,
        depth: f64,
        src: &Camera,
        dst: &Camera,
        pose: &Pose,
    ) -> Option<Homography> {
        let m = match *self {
            Self::Plane => return Homography::plane_inverse(src, dst, pose, depth),
            Self::Slanted(m) => m,
        };
        // Viewer ray r = R K_t^-1 q meets m . (l r + t) = 1 at l = (1 - m.t) / (m . r), so the
        // reference point is proportional to ((1 - m.t) I + t m^T) r; positive w where the
        // ray meets the plane in front of the viewer and in front of the reference camera.
        let gap = 1.0 - m.dot(pose.translation);
        if gap.partial_cmp(&(MIN_PLANE_DISTANCE * m.norm())) != Some(std::cmp::Ordering::Greater) {
            return None;
        }
        let a = Mat3::IDENTITY
            .scale(gap)
            .add(&Mat3::outer(pose.translation, m));
        Some(Homography(src.k() * a * pose.rotation * dst.k_inv()))
    }
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

    fn cam() -> Camera {
        Camera::from_fov(320, 240, 70.0)
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
