//! Rigid poses of a viewer relative to the reference camera.
//!
//! # Convention
//! A [`Pose`] `(R, t)` places the **viewer (target) camera in the reference (source) camera
//! frame**: a point with viewer coordinates `X_view` has reference coordinates
//! `X_ref = R * X_view + t`. So `t` is the viewer's position in reference coordinates (x right,
//! y down, z forward, in scene units) and the columns of `R` are the viewer's axes.
//! This is the paper's "(R, t) from target to source".
//!
//! Euler angles (degrees) compose as `R = Ry(ry) * Rx(rx) * Rz(rz)` (yaw, then pitch, then
//! roll, about the viewer's own axes). With y pointing down this means: positive `ry` turns
//! the view to the right, positive `rx` tilts it up, positive `rz` rolls the image
//! counter-clockwise as seen by the viewer (scene content turns clockwise on screen).

use crate::math::{Mat3, Vec3};
use serde::{Deserialize, Serialize};

/// A rigid transform from viewer coordinates to reference coordinates.
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
pub struct Pose {
    /// Rotation `R` (viewer axes as columns, in reference coordinates).
    pub rotation: Mat3,
    /// Translation `t` (viewer position in reference coordinates).
    pub translation: Vec3,
}

impl Default for Pose {
    fn default() -> Self {
        Self::IDENTITY
    }
}

impl Pose {
    /// The reference viewpoint itself.
    pub const IDENTITY: Self = Self {
        rotation: Mat3::IDENTITY,
        translation: Vec3::ZERO,
    };

    /// A pure translation.
    pub fn from_translation(t: Vec3) -> Self {
        Self {
            rotation: Mat3::IDENTITY,
            translation: t,
        }
    }

    /// A pose from a translation and Euler angles in degrees (see the module docs).
    pub fn from_euler_deg(t: Vec3, rx: f64, ry: f64, rz: f64) -> Self {
        let r = Mat3::rot_y(ry.to_radians())
            * Mat3::rot_x(rx.to_radians())
            * Mat3::rot_z(rz.to_radians());
        Self {
            rotation: r,
            translation: t,
        }
    }

    /// Parses `tx,ty,tz,rx,ry,rz` (translation in scene units, rotations in degrees).
    pub fn parse(s: &str) -> Result<Self, String> {
        let v: Vec<f64> = s
            .split(',')
            .map(|p| p.trim().parse::<f64>())
            .collect::<Result<_, _>>()
            .map_err(|e| format!("pose '{s}': {e}; expected tx,ty,tz,rx,ry,rz"))?;
        if v.len() != 6 || v.iter().any(|x| !x.is_finite()) {
            return Err(format!(
                "pose '{s}': expected 6 finite numbers tx,ty,tz,rx,ry,rz, found {}",
                v.len()
            ));
        }
        Ok(Self::from_euler_deg(
            Vec3::new(v[0], v[1], v[2]),
            v[3],
            v[4],
            v[5],
        ))
    }

    /// Euler angles `(rx, ry, rz)` in degrees such that `from_euler_deg` gives this rotation
    /// (for pitch within (-90, 90) degrees).
    pub fn euler_deg(&self) -> (f64, f64, f64) {
        // R = Ry Rx Rz: R[1][2] = -sin(rx); R[0][2] = sin(ry)cos(rx); R[2][2] = cos(ry)cos(rx);
        // R[1][0] = cos(rx) sin(rz); R[1][1] = cos(rx) cos(rz).
        let m = &self.rotation.0;
        let rx = (-m[1][2]).clamp(-1.0, 1.0).asin();
        let ry = m[0][2].atan2(m[2][2]);
        let rz = m[1][0].atan2(m[1][1]);
        (rx.to_degrees(), ry.to_degrees(), rz.to_degrees())
    }

    /// Maps a point from viewer coordinates to reference coordinates.
    pub fn view_to_ref(&self, p: Vec3) -> Vec3 {
        self.rotation * p + self.translation
    }

    /// Maps a point from reference coordinates to viewer coordinates.
    pub fn ref_to_view(&self, p: Vec3) -> Vec3 {
        self.rotation.transpose() * (p - self.translation)
    }

    /// The inverse pose (reference camera expressed in the viewer frame).
    pub fn inverse(&self) -> Self {
        let rt = self.rotation.transpose();
        Self {
            rotation: rt,
            translation: -(rt * self.translation),
        }
    }

    /// `other` seen from this pose: `other` with this pose's camera as the reference
    /// (`self⁻¹ · other`).
    pub fn relative_to(&self, other: &Pose) -> Self {
        Self {
            rotation: self.rotation.transpose() * other.rotation,
            translation: self.ref_to_view(other.translation),
        }
    }

    /// True when all entries are finite.
    pub fn is_finite(&self) -> bool {
        self.rotation.is_finite() && self.translation.is_finite()
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn relative_pose_maps_through_the_reference() {
        let a = Pose::from_euler_deg(Vec3::new(0.3, -0.1, 1.2), 5.0, -20.0, 3.0);
        let b = Pose::from_euler_deg(Vec3::new(-0.4, 0.2, 0.5), -7.0, 12.0, 1.0);
        let r = a.relative_to(&b);
        // A point in b's camera, taken to the reference through b, equals it taken to a's
        // camera through r and then to the reference through a.
        let p = Vec3::new(0.7, -0.3, 2.5);
        let d = a.view_to_ref(r.view_to_ref(p)) - b.view_to_ref(p);
        assert!(d.norm() < 1e-12);
        let same = a.relative_to(&a);
        assert!((same.rotation.log().norm() + same.translation.norm()) < 1e-12);
    }

    #[test]
    fn euler_roundtrip() {
        let p = Pose::from_euler_deg(Vec3::ZERO, 10.0, -25.0, 7.5);
        let (rx, ry, rz) = p.euler_deg();
        assert!((rx - 10.0).abs() < 1e-9 && (ry + 25.0).abs() < 1e-9 && (rz - 7.5).abs() < 1e-9);
    }

    #[test]
    fn positive_yaw_looks_right_and_positive_pitch_looks_up() {
        let yaw = Pose::from_euler_deg(Vec3::ZERO, 0.0, 10.0, 0.0);
        assert!(yaw.view_to_ref(Vec3::new(0.0, 0.0, 1.0)).x() > 0.0);
        let pitch = Pose::from_euler_deg(Vec3::ZERO, 10.0, 0.0, 0.0);
        assert!(pitch.view_to_ref(Vec3::new(0.0, 0.0, 1.0)).y() < 0.0);
    }

    #[test]
    fn inverse_composes_to_identity() {
        let p = Pose::from_euler_deg(Vec3::new(0.1, -0.2, 0.3), 5.0, 6.0, 7.0);
        let x = Vec3::new(1.0, 2.0, 3.0);
        let y = p.inverse().view_to_ref(p.view_to_ref(x));
        assert!((y - x).norm() < 1e-12);
        assert!((p.ref_to_view(p.view_to_ref(x)) - x).norm() < 1e-12);
    }

    #[test]
    fn parse_pose() {
        let p = Pose::parse("0.1, 0, 0, 0, 5, 0").unwrap();
        assert!((p.translation.x() - 0.1).abs() < 1e-15);
        assert!(Pose::parse("1,2,3").is_err());
        assert!(Pose::parse("1,2,3,a,5,6").is_err());
        assert!(Pose::parse("1,2,3,nan,5,6").is_err());
    }
}
