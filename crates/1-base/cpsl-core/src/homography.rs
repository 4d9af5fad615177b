//! Plane-induced homographies (paper, equation 1).
//!
//! For a fronto-parallel layer plane `n^T X_ref = d` with `n = (0, 0, 1)` and `d = z_k` in the
//! reference camera, and a viewer pose `X_ref = R X_view + t` (see [`crate::pose`]):
//!
//! * reference pixel -> viewer pixel (forward warp):
//!   `H_fwd = K_t R^T (I - t n^T / d) K_s^-1`
//! * viewer pixel -> reference pixel (inverse mapping used for rendering):
//!   `H_inv = K_s ((d - n.t) I + t n^T) R K_t^-1`, which is `H_fwd^-1` up to scale.
//!
//! `H_inv` is scaled so that the homogeneous `w` of a viewer pixel is positive exactly when its
//! ray meets the plane in front of the viewer. When the viewer is at or behind the plane
//! (`t_z >= d`) the layer is not visible and [`Homography::plane_inverse`] returns `None`.

use crate::camera::Camera;
use crate::math::{Mat3, Vec3};
use crate::pose::Pose;

/// Smallest distance, in scene units, between the viewer and a layer plane for the layer to be
/// drawn.
pub const MIN_PLANE_DISTANCE: f64 = 1e-6;

/// A 3x3 homography between pixel coordinate systems.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Homography(pub Mat3);

impl Homography {
    /// The identity mapping.
    pub const IDENTITY: Self = Self(Mat3::IDENTITY);

    /// Forward mapping of the plane at depth `depth` from reference pixels (`src`) to viewer
    /// pixels (`dst`), for the viewer at `pose`.
    pub fn plane_forward(src: &Camera, dst: &Camera, pose: &Pose, depth: f64) -> Self {
        let n = Vec3::new(0.0, 0.0, 1.0);
        let m = Mat3::IDENTITY.add(&Mat3::outer(pose.translation, n).scale(-1.0 / depth));
        Self(dst.k() * pose.rotation.transpose() * m * src.k_inv())
    }

    /// Inverse mapping of the plane at depth `depth`: viewer pixels (`dst`) to reference pixels
    /// (`src`). `None` when the viewer is not in front of the plane.
    pub fn plane_inverse(src: &Camera, dst: &Camera, pose: &Pose, depth: f64) -> Option<Self> {
        let n = Vec3::new(0.0, 0.0, 1.0);
        let gap = depth - n.dot(pose.translation);
        if gap.partial_cmp(&MIN_PLANE_DISTANCE) != Some(std::cmp::Ordering::Greater) {
            return None;
        }
        if pose.rotation == Mat3::IDENTITY && pose.translation == Vec3::ZERO && src == dst {
            // Exact identity: no rounding from K * K^-1.
            return Some(Self::IDENTITY);
        }
        let m = Mat3::IDENTITY
            .scale(gap)
            .add(&Mat3::outer(pose.translation, n));
        // Divide by depth so that H ~ identity-scaled for small motions (w ~ 1).
        Some(Self(
            (src.k() * m * pose.rotation * dst.k_inv()).scale(1.0 / depth),
        ))
    }

    /// Applies the homography to pixel `(x, y)`; `None` when the homogeneous `w` is not
    /// positive (the point is not visible through this mapping).
    pub fn apply(&self, x: f64, y: f64) -> Option<(f64, f64)> {
        let p = self.0 * Vec3::new(x, y, 1.0);
        if p.z() <= 0.0 {
            return None;
        }
        Some((p.x() / p.z(), p.y() / p.z()))
    }

    /// Inverse homography.
    pub fn inverse(&self) -> Option<Self> {
        self.0.inverse().map(Self)
    }

    /// True when the last row is `(0, 0, c)`: the mapping is affine and needs no division.
    pub fn is_affine(&self) -> bool {
        self.0 .0[2][0] == 0.0 && self.0 .0[2][1] == 0.0
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use proptest::prelude::*;

    fn cam() -> Camera {
        Camera::from_fov(320, 240, 70.0)
    }

    /// Unproject a reference pixel onto the plane, move it into the viewer frame, project.
    fn reference_path(c: &Camera, pose: &Pose, d: f64, u: f64, v: f64) -> Option<(f64, f64)> {
        let x_ref = c.unproject(u, v, d);
        c.project(pose.ref_to_view(x_ref))
    }

    proptest! {
        #[test]
        fn forward_matches_unproject_transform_project(
            tx in -0.5f64..0.5, ty in -0.5f64..0.5, tz in -0.5f64..0.5,
            rx in -15.0f64..15.0, ry in -15.0f64..15.0, rz in -15.0f64..15.0,
            d in 1.0f64..20.0, u in 0.0f64..320.0, v in 0.0f64..240.0,
        ) {
            let c = cam();
            let pose = Pose::from_euler_deg(Vec3::new(tx, ty, tz), rx, ry, rz);
            let h = Homography::plane_forward(&c, &c, &pose, d);
            let expect = reference_path(&c, &pose, d, u, v);
            let got = h.apply(u, v);
            match (expect, got) {
                (Some(e), Some(g)) => {
                    prop_assert!((e.0 - g.0).abs() < 1e-6 && (e.1 - g.1).abs() < 1e-6, "{e:?} vs {g:?}");
                }
                (None, None) => {}
                (e, g) => prop_assert!(false, "visibility differs: {e:?} vs {g:?}"),
            }
        }

        #[test]
        fn inverse_maps_back_to_reference_pixel(
            tx in -0.5f64..0.5, ty in -0.5f64..0.5, tz in -0.5f64..0.5,
            rx in -15.0f64..15.0, ry in -15.0f64..15.0, rz in -15.0f64..15.0,
            d in 1.0f64..20.0, u in 0.0f64..320.0, v in 0.0f64..240.0,
        ) {
            let c = cam();
            let pose = Pose::from_euler_deg(Vec3::new(tx, ty, tz), rx, ry, rz);
            let inv = Homography::plane_inverse(&c, &c, &pose, d).unwrap();
            if let Some((x, y)) = reference_path(&c, &pose, d, u, v) {
                let (u2, v2) = inv.apply(x, y).expect("visible point must map back");
                prop_assert!((u2 - u).abs() < 1e-6 && (v2 - v).abs() < 1e-6);
            }
        }
    }

    #[test]
    fn pure_translation_shifts_by_f_t_over_z() {
        let c = cam();
        let (t, z) = (0.2, 4.0);
        let pose = Pose::from_translation(Vec3::new(t, 0.0, 0.0));
        let h = Homography::plane_forward(&c, &c, &pose, z);
        let (x, y) = h.apply(100.0, 50.0).unwrap();
        // Moving the viewer right moves content left by f t / z.
        assert!((x - (100.0 - c.fx * t / z)).abs() < 1e-9);
        assert!((y - 50.0).abs() < 1e-12);
        assert!(h.is_affine());
    }

    #[test]
    fn identity_pose_gives_exact_identity() {
        let c = cam();
        let h = Homography::plane_inverse(&c, &c, &Pose::IDENTITY, 3.0).unwrap();
        assert_eq!(h, Homography::IDENTITY);
    }

    #[test]
    fn plane_behind_viewer_is_culled() {
        let c = cam();
        let pose = Pose::from_translation(Vec3::new(0.0, 0.0, 5.0));
        assert!(Homography::plane_inverse(&c, &c, &pose, 4.0).is_none());
        assert!(Homography::plane_inverse(&c, &c, &pose, 5.0).is_none());
        assert!(Homography::plane_inverse(&c, &c, &pose, 6.0).is_some());
    }
}
