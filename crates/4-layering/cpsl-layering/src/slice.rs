//! Depth slicing: pixels are clustered by inverse depth into at most `K` slices (1-D k-means
//! on a disparity histogram, initialised at quantiles), each slice becomes an opaque-where-owned
//! layer at the median depth of its pixels, and the farthest layer is filled everywhere by
//! push-pull so that parallax never reveals empty space.
//!
//! This is the frame-wise "depth only" baseline; content-promoted layering builds on it.

use crate::error::LayeringError;
use cpsl_core::fill::push_pull;
use cpsl_core::{Camera, Layer, LayerMeta, LayerRole, LayerSet, Limits, PremulImage};
use serde::{Deserialize, Serialize};

/// Configuration of depth slicing.
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
pub struct SliceConfig {
    /// Target number of layers `K` (fewer when the depth map has fewer distinct depths).
    pub layers: usize,
    /// Lloyd iterations of the 1-D k-means.
    pub iterations: usize,
    /// How slices are placed.
    #[serde(default)]
    pub bins: Bins,
}

/// How depth slices are placed.
#[derive(Debug, Clone, Copy, Default, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum Bins {
    /// k-means on inverse depth; each layer at the median depth of its pixels.
    #[default]
    KMeans,
    /// `K` equal intervals of inverse depth between the nearest and farthest pixel, each layer
    /// at its interval's centre (a uniform multiplane image; empty intervals are dropped).
    UniformInverse,
}

impl Default for SliceConfig {
    fn default() -> Self {
        Self {
            layers: 6,
            iterations: 30,
            bins: Bins::KMeans,
        }
    }
}

/// Number of disparity histogram bins.
const BINS: usize = 4096;

/// Disparity cluster centres, nearest (largest disparity) first, empty clusters removed.
pub(crate) fn cluster_disparity(disp: &[f32], k: usize, iterations: usize) -> Vec<f64> {
    let (lo, hi) = disp
        .iter()
        .fold((f32::MAX, f32::MIN), |(a, b), &d| (a.min(d), b.max(d)));
    let span = (hi - lo).max(1e-12) as f64;
    let bin_of = |d: f32| (((d - lo) as f64 / span) * (BINS - 1) as f64).round() as usize;
    let centre_of = |b: usize| lo as f64 + span * b as f64 / (BINS - 1) as f64;
    let mut hist = vec![0u64; BINS];
    for &d in disp {
        hist[bin_of(d)] += 1;
    }
    let total: u64 = hist.iter().sum();
    // Quantile initialisation.
    let mut centres: Vec<f64> = (0..k)
        .map(|i| {
            let target = ((i as f64 + 0.5) / k as f64 * total as f64) as u64;
            let mut acc = 0;
            let b = hist
                .iter()
                .position(|&h| {
                    acc += h;
                    acc > target
                })
                .unwrap_or(BINS - 1);
            centre_of(b)
        })
        .collect();
    centres.dedup_by(|a, b| (*a - *b).abs() < 1e-12);
    let lloyd = |centres: &mut Vec<f64>| -> Vec<(f64, u64, f64)> {
        let mut stats = Vec::new();
        for _ in 0..iterations.max(1) {
            // Per cluster: sum, count, sum of squares.
            let mut acc = vec![(0f64, 0u64, 0f64); centres.len()];
            for (b, &h) in hist.iter().enumerate().filter(|(_, &h)| h > 0) {
                let v = centre_of(b);
                let a = &mut acc[nearest(centres, v)];
                a.0 += v * h as f64;
                a.1 += h;
                a.2 += v * v * h as f64;
            }
            acc.retain(|a| a.1 > 0);
            let next: Vec<f64> = acc.iter().map(|a| a.0 / a.1 as f64).collect();
            let done = next == *centres;
            *centres = next;
            stats = acc;
            if done {
                break;
            }
        }
        stats
    };
    loop {
        let stats = lloyd(&mut centres);
        if centres.len() >= k {
            break;
        }
        // Split the cluster with the largest squared error, if any has spread.
        let (j, sse) = stats
            .iter()
            .map(|&(s, c, q)| q - s * s / c as f64)
            .enumerate()
            .fold(
                (0, 0.0),
                |best, (j, e)| if e > best.1 { (j, e) } else { best },
            );
        if sse <= 1e-18 {
            break;
        }
        let sd = (sse / stats[j].1 as f64).sqrt();
        let c = centres[j];
        centres[j] = c - sd;
        centres.push(c + sd);
    }
    centres.sort_by(|a, b| b.total_cmp(a));
    centres
}

/// Centres of `k` equal inverse-depth intervals that contain pixels, nearest first.
fn uniform_centres(disp: &[f32], k: usize) -> Vec<f64> {
    let (lo, hi) = disp
        .iter()
        .fold((f32::MAX, f32::MIN), |(a, b), &d| (a.min(d), b.max(d)));
    let (lo, hi) = (lo as f64, hi as f64);
    if hi - lo <= 0.0 {
        return vec![lo];
    }
    let step = (hi - lo) / k as f64;
    let mut used = vec![false; k];
    for &d in disp {
        used[(((d as f64 - lo) / step) as usize).min(k - 1)] = true;
    }
    (0..k)
        .rev()
        .filter(|&i| used[i])
        .map(|i| lo + (i as f64 + 0.5) * step)
        .collect()
}

fn nearest(centres: &[f64], v: f64) -> usize {
    let mut best = 0;
    for (j, c) in centres.iter().enumerate() {
        if (c - v).abs() < (centres[best] - v).abs() {
            best = j;
        }
    }
    best
}

/// Slices an RGB frame (`rgb`, 3 bytes per pixel) with per-pixel z-depth `depth` into a
/// layer set for `camera`. Non-finite or non-positive depths are treated as farthest.
pub fn slice_by_depth(
    rgb: &[u8],
    depth: &[f32],
    camera: Camera,
    config: &SliceConfig,
) -> Result<LayerSet, LayeringError> {
    if !(1..=64).contains(&config.layers) {
        return Err(LayeringError::Config {
            field: "layers",
            range: "1..=64",
            found: config.layers.to_string(),
        });
    }
    let (w, h) = (camera.width as usize, camera.height as usize);
    let n = w * h;
    crate::error::check_frame(rgb, depth, camera.width, camera.height)?;
    let valid = |z: f32| z.is_finite() && z > 0.0;
    let disp: Vec<f32> = depth
        .iter()
        .filter(|&&z| valid(z))
        .map(|&z| 1.0 / z)
        .collect();
    if disp.is_empty() {
        return Err(LayeringError::NoValidDepth);
    }
    let centres = match config.bins {
        Bins::KMeans => cluster_disparity(&disp, config.layers, config.iterations),
        Bins::UniformInverse => uniform_centres(&disp, config.layers),
    };
    let k = centres.len();
    let labels: Vec<usize> = depth
        .iter()
        .map(|&z| {
            if valid(z) {
                nearest(&centres, 1.0 / z as f64)
            } else {
                k - 1
            }
        })
        .collect();

    // Median depth of each slice.
    let mut per: Vec<Vec<f32>> = vec![Vec::new(); k];
    for (&l, &z) in labels.iter().zip(depth) {
        if valid(z) {
            per[l].push(z);
        }
    }
    let mut depths: Vec<f64> = per
        .iter_mut()
        .zip(&centres)
        .map(|(v, &c)| {
            if v.is_empty() || config.bins == Bins::UniformInverse {
                1.0 / c
            } else {
                let m = v.len() / 2;
                *v.select_nth_unstable_by(m, f32::total_cmp).1 as f64
            }
        })
        .collect();
    for i in 1..k {
        if depths[i] <= depths[i - 1] {
            depths[i] = depths[i - 1] * (1.0 + 1e-6);
        }
    }

    let mut layers = Vec::with_capacity(k);
    for (i, &z) in depths.iter().enumerate() {
        let back = i + 1 == k;
        let mut data = vec![0u8; n * 4];
        if back {
            // Own pixels are known; everything else is filled.
            let mut col: Vec<f32> = rgb.iter().map(|&v| v as f32).collect();
            let wt: Vec<f32> = labels.iter().map(|&l| (l == i) as u8 as f32).collect();
            push_pull(&mut col, &wt, w, h, 3);
            for p in 0..n {
                for c in 0..3 {
                    data[p * 4 + c] = cpsl_core::image::round_to_u8(col[p * 3 + c]);
                }
                data[p * 4 + 3] = 255;
            }
        } else {
            for p in (0..n).filter(|&p| labels[p] == i) {
                data[p * 4..p * 4 + 3].copy_from_slice(&rgb[p * 3..p * 3 + 3]);
                data[p * 4 + 3] = 255;
            }
        }
        layers.push(Layer {
            image: PremulImage::from_premul(camera.width, camera.height, data)?,
            depth: z,
            geometry: cpsl_core::Geometry::Plane,
            meta: LayerMeta {
                name: Some(format!("slice {i}")),
                role: Some(if back {
                    LayerRole::Background
                } else {
                    LayerRole::Region
                }),
                saliency: None,
                track: None,
            },
        });
    }
    Ok(LayerSet::new(camera, layers, &Limits::default())?)
}

#[cfg(test)]
mod tests {
    use super::*;
    use cpsl_core::Pose;
    use cpsl_render::PreparedLayers;
    use cpsl_synth::Scene;

    #[test]
    fn synthetic_scene_slices_into_ordered_layers_and_identity_reproduces_input() {
        let scene = Scene::default_scene(160, 120);
        let view = scene.render(&scene.camera, &Pose::IDENTITY, 0.0, 2);
        let set = slice_by_depth(
            &view.rgb,
            &view.depth,
            scene.camera,
            &SliceConfig::default(),
        )
        .unwrap();
        assert_eq!(set.len(), 6);
        // Large fronto-parallel objects land at their exact depth (the thin pole is too small
        // to win a slice of its own: depth slicing's known weakness).
        for z in [2.5, 4.0, 10.0] {
            assert!(
                set.layers().iter().any(|l| (l.depth - z).abs() < 1e-4),
                "a layer at depth {z}: {:?}",
                set.layers().iter().map(|l| l.depth).collect::<Vec<_>>()
            );
        }
        let out = PreparedLayers::new(&set).render(&Pose::IDENTITY);
        let rgb = out.over_background([0, 0, 0]);
        assert_eq!(
            rgb, view.rgb,
            "identity render reproduces the input exactly"
        );
    }

    #[test]
    fn uniform_bins_place_planes_at_interval_centres() {
        let cam = Camera::from_fov(4, 1, 60.0);
        // Inverse depths 1.0, 0.5, 0.25 and 0.25: two intervals of width 0.375 over [0.25, 1].
        let depth = [1.0f32, 2.0, 4.0, 4.0];
        let cfg = SliceConfig {
            layers: 2,
            bins: Bins::UniformInverse,
            ..SliceConfig::default()
        };
        let set = slice_by_depth(&[0; 12], &depth, cam, &cfg).unwrap();
        let d: Vec<f64> = set.layers().iter().map(|l| l.depth).collect();
        assert_eq!(d.len(), 2);
        assert!(
            (d[0] - 1.0 / 0.8125).abs() < 1e-9 && (d[1] - 1.0 / 0.4375).abs() < 1e-9,
            "{d:?}"
        );
    }

    #[test]
    fn rejects_bad_input() {
        let cam = Camera::from_fov(4, 4, 60.0);
        let cfg = SliceConfig::default();
        assert!(matches!(
            slice_by_depth(&[0; 47], &[1.0; 16], cam, &cfg),
            Err(LayeringError::Size { what: "colour", .. })
        ));
        assert_eq!(
            slice_by_depth(&[0; 48], &[f32::NAN; 16], cam, &cfg),
            Err(LayeringError::NoValidDepth)
        );
        let zero = SliceConfig { layers: 0, ..cfg };
        assert!(slice_by_depth(&[0; 48], &[1.0; 16], cam, &zero).is_err());
        // A flat depth map gives a single layer.
        let one = slice_by_depth(&[9; 48], &[2.0; 16], cam, &cfg).unwrap();
        assert_eq!(one.len(), 1);
    }
}
