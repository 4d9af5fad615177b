//! Synthetic layer sets with controlled coverage, for benchmarks and renderer tests.

use crate::texture::fractal_noise;
use cpsl_core::{Camera, Layer, LayerSet, Limits, PremulImage};

/// How much of each front layer is covered.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Coverage {
    /// Typical content: each front layer holds a few feathered shapes covering roughly a fifth
    /// of the frame; the back layer is opaque.
    Typical,
    /// Worst case: every layer is semi-transparent over the whole frame, so nothing can be
    /// skipped.
    Dense,
}

/// Deterministic pseudo-random numbers (SplitMix64).
struct Rng(u64);
impl Rng {
    fn next(&mut self) -> f64 {
        self.0 = self.0.wrapping_add(0x9E37_79B9_7F4A_7C15);
        let mut z = self.0;
        z = (z ^ (z >> 30)).wrapping_mul(0xBF58_476D_1CE4_E5B9);
        z = (z ^ (z >> 27)).wrapping_mul(0x94D0_49BB_1331_11EB);
        ((z ^ (z >> 31)) >> 11) as f64 / (1u64 << 53) as f64
    }
}

/// A `k`-layer set of `width x height` full-frame layers with depths spread geometrically
/// from 1.5 to 12 scene units, textured with noise, deterministic in `seed`.
pub fn synthetic_layer_set(
    width: u32,
    height: u32,
    k: usize,
    coverage: Coverage,
    seed: u64,
) -> LayerSet {
    let cam = Camera::from_fov(width, height, 60.0);
    let mut rng = Rng(seed);
    let (w, h) = (width as usize, height as usize);
    let k = k.max(1);
    let mut layers = Vec::with_capacity(k);
    for i in 0..k {
        let depth = if k == 1 {
            5.0
        } else {
            1.5 * (12.0f64 / 1.5).powf(i as f64 / (k - 1) as f64)
        };
        let tint = [rng.next(), rng.next(), rng.next()];
        let back = i + 1 == k;
        // Shapes: centre, radii, feather (px), rectangular or elliptic.
        let shapes: Vec<[f64; 6]> = (0..4)
            .map(|_| {
                [
                    rng.next() * w as f64,
                    rng.next() * h as f64,
                    (0.08 + rng.next() * 0.14) * w as f64,
                    (0.08 + rng.next() * 0.14) * h as f64,
                    2.0 + rng.next() * 3.0,
                    rng.next().round(),
                ]
            })
            .collect();
        let mut data = vec![0u8; w * h * 4];
        for y in 0..h {
            for x in 0..w {
                let n = fractal_noise(x as f64 / 23.0, y as f64 / 23.0, (seed as u32) ^ i as u32);
                let rgb = tint.map(|t| ((0.25 + 0.75 * n) * (0.3 + 0.7 * t) * 255.0).min(255.0));
                let alpha = if back {
                    1.0
                } else {
                    match coverage {
                        Coverage::Dense => 0.35 + 0.3 * n,
                        Coverage::Typical => shapes
                            .iter()
                            .map(|s| {
                                let (dx, dy) = ((x as f64 - s[0]) / s[2], (y as f64 - s[1]) / s[3]);
                                // Signed distance in px (approximate for ellipses).
                                let d = if s[5] > 0.5 {
                                    ((dx * dx + dy * dy).sqrt() - 1.0) * s[2].min(s[3])
                                } else {
                                    ((dx.abs() - 1.0) * s[2]).max((dy.abs() - 1.0) * s[3])
                                };
                                (0.5 - d / s[4]).clamp(0.0, 1.0)
                            })
                            .fold(0.0, f64::max),
                    }
                };
                let a = (alpha * 255.0).round() as u8;
                let o = (y * w + x) * 4;
                for c in 0..3 {
                    data[o + c] = cpsl_core::image::premultiply(rgb[c] as u8, a);
                }
                data[o + 3] = a;
            }
        }
        let image =
            PremulImage::from_premul(width, height, data).expect("premultiplied by construction");
        layers.push(Layer::new(image, depth));
    }
    LayerSet::new(cam, layers, &Limits::default()).expect("valid by construction")
}

/// `set` with every layer on a slanted plane through its depth at the image centre, tilted
/// like a floor (depth growing upwards) and turned a little about the vertical axis, each
/// layer's inverse depth changing by a third over the frame height: the renderers' test and
/// benchmark case for [`cpsl_core::Geometry::Slanted`].
pub fn slanted(set: LayerSet) -> LayerSet {
    let (cam, mut layers) = set.into_parts();
    let half_h = cam.height as f64 / 2.0 / cam.fy;
    for (i, l) in layers.iter_mut().enumerate() {
        let inv = 1.0 / l.depth;
        let turn = if i % 2 == 0 { 0.1 } else { -0.1 };
        l.geometry = cpsl_core::Geometry::Slanted(cpsl_core::Vec3::new(
            turn * inv,
            inv / (3.0 * half_h),
            inv,
        ));
    }
    LayerSet::new(cam, layers, &Limits::default()).expect("slanted planes stay in front")
}

/// `set` with every layer on a depth mesh of step `step`: inverse depth undulating by 5 %
/// around the layer's depth in both directions, like a curved surface: the renderers' test
/// and benchmark case for [`cpsl_core::Geometry::Mesh`].
pub fn meshed(set: LayerSet, step: u32) -> LayerSet {
    let (cam, mut layers) = set.into_parts();
    let (cols, rows) = cpsl_core::DepthGrid::dims(cam.width, cam.height, step);
    for (k, l) in layers.iter_mut().enumerate() {
        let inv = 1.0 / l.depth;
        let inverse_depth = (0..rows)
            .flat_map(|j| (0..cols).map(move |i| (i, j)))
            .map(|(i, j)| {
                let (x, y) = (i as f64 * 0.9 + k as f64, j as f64 * 0.7);
                (inv * (1.0 + 0.05 * (x.sin() * y.cos()))) as f32
            })
            .collect();
        l.geometry = cpsl_core::Geometry::Mesh(std::sync::Arc::new(cpsl_core::DepthGrid {
            step,
            cols,
            rows,
            inverse_depth,
        }));
    }
    LayerSet::new(cam, layers, &Limits::default()).expect("meshes stay in front")
}
