//! Procedural textures in object-space metric coordinates.

use serde::{Deserialize, Serialize};

/// A procedural texture. Coordinates are in scene units on the object's surface.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(tag = "kind", rename_all = "snake_case")]
pub enum Texture {
    /// Two-colour checkerboard with fine noise.
    Checker {
        /// First colour.
        a: [u8; 3],
        /// Second colour.
        b: [u8; 3],
        /// Cell size in scene units.
        cell: f64,
    },
    /// Sinusoidal stripes.
    Stripes {
        /// First colour.
        a: [u8; 3],
        /// Second colour.
        b: [u8; 3],
        /// Stripe period in scene units.
        period: f64,
        /// Stripe direction in degrees.
        angle_deg: f64,
    },
    /// Fractal value noise between two colours.
    Noise {
        /// Dark colour.
        a: [u8; 3],
        /// Light colour.
        b: [u8; 3],
        /// Feature size in scene units.
        scale: f64,
        /// Random seed.
        seed: u32,
    },
    /// Brick wall with mortar lines over noise.
    Bricks {
        /// Brick colour.
        brick: [u8; 3],
        /// Mortar colour.
        mortar: [u8; 3],
        /// Brick width in scene units (height is half).
        size: f64,
    },
}

fn hash(x: i64, y: i64, seed: u32) -> f64 {
    let mut h = (x as u64).wrapping_mul(0x9E37_79B9_7F4A_7C15)
        ^ (y as u64).wrapping_mul(0xC2B2_AE3D_27D4_EB4F)
        ^ (seed as u64).wrapping_mul(0x1656_67B1_9E37_79F9);
    h ^= h >> 33;
    h = h.wrapping_mul(0xFF51_AFD7_ED55_8CCD);
    h ^= h >> 33;
    (h >> 11) as f64 / (1u64 << 53) as f64
}

/// Smooth value noise in [0, 1].
pub fn value_noise(x: f64, y: f64, seed: u32) -> f64 {
    let (xf, yf) = (x.floor(), y.floor());
    let (xi, yi) = (xf as i64, yf as i64);
    let (tx, ty) = (x - xf, y - yf);
    let s = |t: f64| t * t * (3.0 - 2.0 * t);
    let (sx, sy) = (s(tx), s(ty));
    let a = hash(xi, yi, seed);
    let b = hash(xi + 1, yi, seed);
    let c = hash(xi, yi + 1, seed);
    let d = hash(xi + 1, yi + 1, seed);
    let top = a + (b - a) * sx;
    let bot = c + (d - c) * sx;
    top + (bot - top) * sy
}

/// Three octaves of value noise, in [0, 1].
pub fn fractal_noise(x: f64, y: f64, seed: u32) -> f64 {
    (value_noise(x, y, seed) * 0.57
        + value_noise(x * 2.03, y * 2.03, seed + 1) * 0.29
        + value_noise(x * 4.11, y * 4.11, seed + 2) * 0.14)
        .clamp(0.0, 1.0)
}

fn mix(a: [u8; 3], b: [u8; 3], t: f64) -> [f64; 3] {
    let t = t.clamp(0.0, 1.0);
    [0, 1, 2].map(|i| a[i] as f64 * (1.0 - t) + b[i] as f64 * t)
}

impl Texture {
    /// Linear colour (0..255 per channel) at surface coordinates `(x, y)`.
    pub fn sample(&self, x: f64, y: f64) -> [f64; 3] {
        match *self {
            Texture::Checker { a, b, cell } => {
                let k = ((x / cell).floor() as i64 + (y / cell).floor() as i64) & 1;
                let n = value_noise(x / cell * 4.0, y / cell * 4.0, 7) * 0.25;
                mix(a, b, k as f64 * 0.75 + n)
            }
            Texture::Stripes {
                a,
                b,
                period,
                angle_deg,
            } => {
                let (s, c) = angle_deg.to_radians().sin_cos();
                let u = x * c + y * s;
                let t = 0.5 + 0.5 * (u / period * std::f64::consts::TAU).sin();
                mix(a, b, t * 0.85 + value_noise(x * 9.0, y * 9.0, 3) * 0.15)
            }
            Texture::Noise { a, b, scale, seed } => {
                mix(a, b, fractal_noise(x / scale, y / scale, seed))
            }
            Texture::Bricks {
                brick,
                mortar,
                size,
            } => {
                let bh = size * 0.5;
                let row = (y / bh).floor();
                let xo = x / size + if (row as i64) & 1 == 1 { 0.5 } else { 0.0 };
                let fx = xo - xo.floor();
                let fy = y / bh - row;
                let line = fx < 0.06 || fy < 0.12;
                if line {
                    mix(mortar, mortar, 0.0)
                } else {
                    let n = fractal_noise(x * 3.0, y * 3.0, 11);
                    let shade = 0.75 + 0.5 * hash(xo.floor() as i64, row as i64, 5) * 0.5;
                    mix(brick, [255, 255, 255], n * 0.25).map(|v| v * shade)
                }
            }
        }
    }
}
