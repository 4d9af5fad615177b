//! Minimal 3-vector and 3x3 matrix maths in `f64` (all the geometry CPSL needs).

use serde::{Deserialize, Serialize};
use std::ops::{Add, Mul, Neg, Sub};

/// A 3-vector.
#[derive(Debug, Clone, Copy, PartialEq, Default, Serialize, Deserialize)]
pub struct Vec3(pub [f64; 3]);

impl Vec3 {
    /// Builds a vector from its components.
    pub const fn new(x: f64, y: f64, z: f64) -> Self {
        Self([x, y, z])
    }
    /// The zero vector.
    pub const ZERO: Self = Self([0.0; 3]);
    /// x component.
    pub fn x(self) -> f64 {
        self.0[0]
    }
    /// y component.
    pub fn y(self) -> f64 {
        self.0[1]
    }
    /// z component.
    pub fn z(self) -> f64 {
        self.0[2]
    }
    /// Dot product.
    pub fn dot(self, o: Self) -> f64 {
        self.0[0] * o.0[0] + self.0[1] * o.0[1] + self.0[2] * o.0[2]
    }
    /// Cross product.
    pub fn cross(self, o: Self) -> Self {
        let [a, b, c] = self.0;
        let [d, e, f] = o.0;
        Self([b * f - c * e, c * d - a * f, a * e - b * d])
    }
    /// Euclidean norm.
    pub fn norm(self) -> f64 {
        self.dot(self).sqrt()
    }
    /// Unit vector in the same direction (returns `self` when the norm is zero).
    pub fn normalized(self) -> Self {
        let n = self.norm();
        if n > 0.0 {
            self * (1.0 / n)
        } else {
            self
        }
    }
    /// True when every component is finite.
    pub fn is_finite(self) -> bool {
        self.0.iter().all(|v| v.is_finite())
    }
}

impl Add for Vec3 {
    type Output = Self;
    fn add(self, o: Self) -> Self {
        Self([self.0[0] + o.0[0], self.0[1] + o.0[1], self.0[2] + o.0[2]])
    }
}
impl Sub for Vec3 {
    type Output = Self;
    fn sub(self, o: Self) -> Self {
        Self([self.0[0] - o.0[0], self.0[1] - o.0[1], self.0[2] - o.0[2]])
    }
}
impl Neg for Vec3 {
    type Output = Self;
    fn neg(self) -> Self {
        Self([-self.0[0], -self.0[1], -self.0[2]])
    }
}
impl Mul<f64> for Vec3 {
    type Output = Self;
    fn mul(self, s: f64) -> Self {
        Self([self.0[0] * s, self.0[1] * s, self.0[2] * s])
    }
}

/// A 3x3 matrix stored row-major: `m.0[row][col]`.
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
pub struct Mat3(pub [[f64; 3]; 3]);

impl Default for Mat3 {
    fn default() -> Self {
        Self::IDENTITY
    }
}

impl Mat3 {
    /// The identity matrix.
    pub const IDENTITY: Self = Self([[1.0, 0.0, 0.0], [0.0, 1.0, 0.0], [0.0, 0.0, 1.0]]);

    /// Builds a matrix from its columns.
    pub fn from_cols(a: Vec3, b: Vec3, c: Vec3) -> Self {
        Self([
            [a.0[0], b.0[0], c.0[0]],
            [a.0[1], b.0[1], c.0[1]],
            [a.0[2], b.0[2], c.0[2]],
        ])
    }
    /// Column `j`.
    pub fn col(&self, j: usize) -> Vec3 {
        Vec3([self.0[0][j], self.0[1][j], self.0[2][j]])
    }
    /// Transpose.
    pub fn transpose(&self) -> Self {
        let m = &self.0;
        Self([
            [m[0][0], m[1][0], m[2][0]],
            [m[0][1], m[1][1], m[2][1]],
            [m[0][2], m[1][2], m[2][2]],
        ])
    }
    /// Determinant.
    pub fn det(&self) -> f64 {
        let m = &self.0;
        m[0][0] * (m[1][1] * m[2][2] - m[1][2] * m[2][1])
            - m[0][1] * (m[1][0] * m[2][2] - m[1][2] * m[2][0])
            + m[0][2] * (m[1][0] * m[2][1] - m[1][1] * m[2][0])
    }
    /// Inverse, or `None` when the matrix is singular or not finite.
    pub fn inverse(&self) -> Option<Self> {
        let d = self.det();
        if !d.is_finite() || d.abs() < 1e-300 {
            return None;
        }
        let m = &self.0;
        let inv_d = 1.0 / d;
        let c = |a: usize, b: usize, e: usize, f: usize| m[a][b] * m[e][f] - m[a][f] * m[e][b];
        Some(Self([
            [
                c(1, 1, 2, 2) * inv_d,
                -c(0, 1, 2, 2) * inv_d,
                c(0, 1, 1, 2) * inv_d,
            ],
            [
                -c(1, 0, 2, 2) * inv_d,
                c(0, 0, 2, 2) * inv_d,
                -c(0, 0, 1, 2) * inv_d,
            ],
            [
                c(1, 0, 2, 1) * inv_d,
                -c(0, 0, 2, 1) * inv_d,
                c(0, 0, 1, 1) * inv_d,
            ],
        ]))
    }
    /// Scales every entry.
    pub fn scale(&self, s: f64) -> Self {
        let mut r = *self;
        r.0.iter_mut().flatten().for_each(|v| *v *= s);
        r
    }
    /// Sum of two matrices.
    pub fn add(&self, o: &Self) -> Self {
        let mut r = *self;
        for i in 0..3 {
            for j in 0..3 {
                r.0[i][j] += o.0[i][j];
            }
        }
        r
    }
    /// Outer product `a b^T`.
    pub fn outer(a: Vec3, b: Vec3) -> Self {
        let mut r = [[0.0; 3]; 3];
        for (i, row) in r.iter_mut().enumerate() {
            for (j, v) in row.iter_mut().enumerate() {
                *v = a.0[i] * b.0[j];
            }
        }
        Self(r)
    }
    /// Rotation by `angle` radians about the x axis.
    pub fn rot_x(angle: f64) -> Self {
        let (s, c) = angle.sin_cos();
        Self([[1.0, 0.0, 0.0], [0.0, c, -s], [0.0, s, c]])
    }
    /// Rotation by `angle` radians about the y axis.
    pub fn rot_y(angle: f64) -> Self {
        let (s, c) = angle.sin_cos();
        Self([[c, 0.0, s], [0.0, 1.0, 0.0], [-s, 0.0, c]])
    }
    /// Rotation by `angle` radians about the z axis.
    pub fn rot_z(angle: f64) -> Self {
        let (s, c) = angle.sin_cos();
        Self([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])
    }
    /// Rotation by `angle` radians about a unit `axis` (Rodrigues).
    pub fn axis_angle(axis: Vec3, angle: f64) -> Self {
        let k = axis.normalized();
        let (s, c) = angle.sin_cos();
        let kx = Self([
            [0.0, -k.z(), k.y()],
            [k.z(), 0.0, -k.x()],
            [-k.y(), k.x(), 0.0],
        ]);
        Self::IDENTITY
            .add(&kx.scale(s))
            .add(&(kx * kx).scale(1.0 - c))
    }
    /// The rotation of a rotation vector (axis times angle in radians).
    pub fn exp(w: Vec3) -> Self {
        let th = w.norm();
        if th > 0.0 {
            Self::axis_angle(w * (1.0 / th), th)
        } else {
            Self::IDENTITY
        }
    }
    /// The rotation vector of a rotation matrix (inverse of [`Mat3::exp`]; angle in `[0, pi]`).
    pub fn log(&self) -> Vec3 {
        let m = &self.0;
        let v = Vec3([m[2][1] - m[1][2], m[0][2] - m[2][0], m[1][0] - m[0][1]]);
        let th = ((m[0][0] + m[1][1] + m[2][2] - 1.0) / 2.0)
            .clamp(-1.0, 1.0)
            .acos();
        if th < 1e-8 {
            return v * 0.5;
        }
        if th < std::f64::consts::PI - 1e-4 {
            return v * (th / (2.0 * th.sin()));
        }
        // Near a half turn the skew part vanishes: the axis is the largest column of R + I.
        let i = (0..3)
            .max_by(|&a, &b| m[a][a].total_cmp(&m[b][b]))
            .expect("three entries");
        let mut col = self.col(i);
        col.0[i] += 1.0;
        col.normalized() * th
    }
    /// True when every entry is finite.
    pub fn is_finite(&self) -> bool {
        self.0.iter().flatten().all(|v| v.is_finite())
    }
}

impl Mul for Mat3 {
    type Output = Self;
    fn mul(self, o: Self) -> Self {
        let mut r = [[0.0; 3]; 3];
        for (i, row) in r.iter_mut().enumerate() {
            for (j, v) in row.iter_mut().enumerate() {
                *v = (0..3).map(|k| self.0[i][k] * o.0[k][j]).sum();
            }
        }
        Self(r)
    }
}

impl Mul<Vec3> for Mat3 {
    type Output = Vec3;
    fn mul(self, v: Vec3) -> Vec3 {
        let m = &self.0;
        Vec3([
            m[0][0] * v.0[0] + m[0][1] * v.0[1] + m[0][2] * v.0[2],
            m[1][0] * v.0[0] + m[1][1] * v.0[1] + m[1][2] * v.0[2],
            m[2][0] * v.0[0] + m[2][1] * v.0[1] + m[2][2] * v.0[2],
        ])
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn log_inverts_exp() {
        for (axis, angle) in [
            (Vec3([0.0, 1.0, 0.0]), 0.3),
            (Vec3([1.0, 2.0, -0.5]).normalized(), 2.9),
            (
                Vec3([0.2, -1.0, 0.4]).normalized(),
                std::f64::consts::PI - 2e-5,
            ),
            (Vec3([0.0, 0.0, 1.0]), 1e-10),
        ] {
            let r = Mat3::axis_angle(axis, angle);
            let back = Mat3::exp(r.log());
            let d = (back.transpose() * r).0;
            let tr = d[0][0] + d[1][1] + d[2][2];
            let err = ((tr - 1.0) / 2.0).clamp(-1.0, 1.0).acos();
            assert!(err < 1e-4, "{angle}: {err} rad");
            assert!((r.log().norm() - angle).abs() < 1e-6, "{angle}");
        }
    }

    #[test]
    fn inverse_roundtrip() {
        let m = Mat3([[2.0, 1.0, 0.5], [0.0, 3.0, 1.0], [0.2, 0.0, 1.5]]);
        let p = m * m.inverse().unwrap();
        for i in 0..3 {
            for j in 0..3 {
                let e = if i == j { 1.0 } else { 0.0 };
                assert!((p.0[i][j] - e).abs() < 1e-12);
            }
        }
        assert!(Mat3([[0.0; 3]; 3]).inverse().is_none());
    }

    #[test]
    fn axis_angle_matches_elementary_rotations() {
        let a = 0.3;
        let r1 = Mat3::axis_angle(Vec3::new(0.0, 1.0, 0.0), a);
        let r2 = Mat3::rot_y(a);
        for i in 0..3 {
            for j in 0..3 {
                assert!((r1.0[i][j] - r2.0[i][j]).abs() < 1e-12);
            }
        }
    }
}
