//! Pinhole cameras.

use crate::error::CoreError;
use crate::math::{Mat3, Vec3};
use serde::{Deserialize, Serialize};

/// A pinhole camera: image size in pixels and intrinsics in pixels.
///
/// Integer pixel coordinates are pixel centres, so a centred principal point of a `W`-wide
/// image is `cx = (W - 1) / 2`.
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
pub struct Camera {
    /// Image width in pixels.
    pub width: u32,
    /// Image height in pixels.
    pub height: u32,
    /// Focal length along x, in pixels.
    pub fx: f64,
    /// Focal length along y, in pixels.
    pub fy: f64,
    /// Principal point x, in pixels.
    pub cx: f64,
    /// Principal point y, in pixels.
    pub cy: f64,
}

impl Camera {
    /// A camera with square pixels, a centred principal point and the given horizontal field
    /// of view in degrees.
    pub fn from_fov(width: u32, height: u32, fov_x_deg: f64) -> Self {
        Self::centred(
            width,
            height,
            0.5 * width as f64 / (0.5 * fov_x_deg.to_radians()).tan(),
        )
    }

    /// A camera with square pixels of focal length `f` (pixels) and a centred principal point.
    pub fn centred(width: u32, height: u32, f: f64) -> Self {
        Self {
            width,
            height,
            fx: f,
            fy: f,
            cx: (width as f64 - 1.0) * 0.5,
            cy: (height as f64 - 1.0) * 0.5,
        }
    }

    /// Checks that every parameter is finite, focal lengths are positive and the size is not
    /// zero.
    pub fn validate(&self) -> Result<(), CoreError> {
        let bad = |field, expected, found: String| CoreError::Camera {
            field,
            expected,
            found,
        };
        if self.width == 0 || self.height == 0 {
            return Err(bad(
                "width/height",
                "at least 1",
                format!("{}x{}", self.width, self.height),
            ));
        }
        for (name, v) in [("fx", self.fx), ("fy", self.fy)] {
            if !(v.is_finite() && v > 0.0) {
                return Err(bad(name, "finite and > 0", v.to_string()));
            }
        }
        for (name, v) in [("cx", self.cx), ("cy", self.cy)] {
            if !v.is_finite() {
                return Err(bad(name, "finite", v.to_string()));
            }
        }
        Ok(())
    }

    /// The intrinsic matrix `K`.
    pub fn k(&self) -> Mat3 {
        Mat3([
            [self.fx, 0.0, self.cx],
            [0.0, self.fy, self.cy],
            [0.0, 0.0, 1.0],
        ])
    }

    /// The inverse intrinsic matrix `K^-1`, computed in closed form.
    pub fn k_inv(&self) -> Mat3 {
        Mat3([
            [1.0 / self.fx, 0.0, -self.cx / self.fx],
            [0.0, 1.0 / self.fy, -self.cy / self.fy],
            [0.0, 0.0, 1.0],
        ])
    }

    /// The camera-space point at depth `z` (along the optical axis) seen at pixel `(u, v)`.
    pub fn unproject(&self, u: f64, v: f64, z: f64) -> Vec3 {
        Vec3::new((u - self.cx) / self.fx * z, (v - self.cy) / self.fy * z, z)
    }

    /// The pixel where camera-space point `p` projects, or `None` when it is not in front of
    /// the camera.
    pub fn project(&self, p: Vec3) -> Option<(f64, f64)> {
        if p.z() <= 0.0 {
            return None;
        }
        Some((
            self.fx * p.x() / p.z() + self.cx,
            self.fy * p.y() / p.z() + self.cy,
        ))
    }

    /// The same camera for an image scaled by `s` (both axes).
    pub fn scaled(&self, s: f64) -> Self {
        let w = ((self.width as f64) * s).round().max(1.0) as u32;
        let h = ((self.height as f64) * s).round().max(1.0) as u32;
        Self {
            width: w,
            height: h,
            fx: self.fx * s,
            fy: self.fy * s,
            cx: (self.cx + 0.5) * s - 0.5,
            cy: (self.cy + 0.5) * s - 0.5,
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn project_unproject_roundtrip() {
        let c = Camera::from_fov(640, 480, 60.0);
        let p = c.unproject(100.25, 300.5, 3.5);
        let (u, v) = c.project(p).unwrap();
        assert!((u - 100.25).abs() < 1e-9 && (v - 300.5).abs() < 1e-9);
        assert!(c.project(Vec3::new(0.0, 0.0, -1.0)).is_none());
    }

    #[test]
    fn k_inv_is_inverse() {
        let c = Camera::from_fov(333, 200, 75.0);
        let m = c.k() * c.k_inv();
        assert!((m.0[0][2]).abs() < 1e-12 && (m.0[0][0] - 1.0).abs() < 1e-15);
    }

    #[test]
    fn validation() {
        let mut c = Camera::from_fov(64, 48, 60.0);
        assert!(c.validate().is_ok());
        c.fx = f64::NAN;
        assert!(matches!(
            c.validate(),
            Err(CoreError::Camera { field: "fx", .. })
        ));
        c.fx = 10.0;
        c.width = 0;
        assert!(c.validate().is_err());
    }
}
