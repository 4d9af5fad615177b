//! Per-layer bitrate allocation under a total budget (equation 5 of the paper):
//! minimise `sum_k w_k D_k(r_k)` subject to `sum_k r_k <= R`.
//!
//! Each layer stream's rate and distortion are modelled as functions of the encoder's quality
//! setting `q` (CRF) from two trial encodes of the segment: `ln r_k(q)` and `ln D_k(q)` are
//! straight lines through the two measured points (rate roughly halves every 6 CRF steps;
//! distortion grows geometrically), so `D_k(r_k)` is a power law. A stream has one such model
//! per rung of the resolution ladder ([`crate::scale`]), its distortion measured at the frame
//! size after upsampling, so that rungs compete on the same scale. The constrained problem is
//! solved by Lagrangian relaxation on the grid of rungs and integer qualities: for a
//! multiplier `lambda`, every layer independently picks the `(rung, q)` minimising
//! `w_k D_k + lambda r_k`; `lambda` is bisected (in log space) to the smallest value whose
//! total rate fits the budget.
//!
//! `D_k` is the visibility-weighted squared error of the decoded premultiplied RGBA against the
//! source ([`distortion`]); `w_k` rises with the layer's saliency and its share of depth-edge
//! samples in the Edge-Depth Cache ([`weight`]).

use cpsl_core::PremulImage;

/// A rate-distortion model of one layer stream, fitted to two trial encodes.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct RdModel {
    q0: f64,
    ln_r0: f64,
    slope_r: f64,
    ln_d0: f64,
    slope_d: f64,
}

/// Smallest distortion the model takes (an empty layer codes without error).
const MIN_D: f64 = 1e-4;

impl RdModel {
    /// Fits the model through `(q, bits, distortion)` at two qualities `a.0 < b.0`. Rates are
    /// forced to fall and distortions to rise with `q`, as encoders behave.
    pub fn fit(a: (f32, f64, f64), b: (f32, f64, f64)) -> Self {
        let dq = (b.0 - a.0).max(1e-3) as f64;
        let ln = |v: f64| v.max(MIN_D).ln();
        Self {
            q0: a.0 as f64,
            ln_r0: ln(a.1),
            slope_r: ((ln(b.1) - ln(a.1)) / dq).min(-1e-3),
            ln_d0: ln(a.2),
            slope_d: ((ln(b.2) - ln(a.2)) / dq).max(1e-3),
        }
    }

    /// Moves the rate line (same slope) through a measured `bits` at quality `q`.
    pub fn anchor_rate(&mut self, q: f32, bits: f64) {
        self.ln_r0 = bits.max(MIN_D).ln() - self.slope_r * (q as f64 - self.q0);
    }

    /// Modelled bits at quality `q`.
    pub fn rate(&self, q: f32) -> f64 {
        (self.ln_r0 + self.slope_r * (q as f64 - self.q0)).exp()
    }

    /// Modelled distortion at quality `q`.
    pub fn distortion(&self, q: f32) -> f64 {
        (self.ln_d0 + self.slope_d * (q as f64 - self.q0)).exp()
    }
}

/// The result of [`allocate`].
#[derive(Debug, Clone, PartialEq)]
pub struct Allocation {
    /// Rung (index into the stream's models) per layer stream.
    pub rung: Vec<usize>,
    /// Quality per layer stream.
    pub quality: Vec<f32>,
    /// Modelled bits per layer stream.
    pub bits: Vec<f64>,
    /// Whether the budget is met by the model (false: even the cheapest choice is too costly,
    /// and every stream gets its cheapest rung at the lowest quality).
    pub feasible: bool,
}

/// Chooses a rung and a quality per stream, qualities on the integer grid `[q_min, q_max]`,
/// minimising `sum w_k D_k` with `sum r_k <= budget` (all in the models' units). `models[k]`
/// holds stream `k`'s model per rung (at least one).
pub fn allocate(
    models: &[Vec<RdModel>],
    weights: &[f32],
    budget: f64,
    q_min: f32,
    q_max: f32,
) -> Allocation {
    let grid: Vec<f32> = (q_min.ceil() as i32..=q_max.floor() as i32)
        .map(|q| q as f32)
        .collect();
    let options = |k: usize| {
        let grid = &grid;
        (0..models[k].len()).flat_map(move |r| grid.iter().map(move |&q| (r, q)))
    };
    let rate = |k: usize, (r, q): (usize, f32)| models[k][r].rate(q);
    let pick = |lambda: f64| -> Vec<(usize, f32)> {
        (0..models.len())
            .map(|k| {
                let cost = |o: (usize, f32)| {
                    weights[k] as f64 * models[k][o.0].distortion(o.1) + lambda * rate(k, o)
                };
                options(k)
                    .min_by(|&a, &b| cost(a).total_cmp(&cost(b)))
                    .expect("non-empty grid")
            })
            .collect()
    };
    let total =
        |c: &[(usize, f32)]| -> f64 { c.iter().enumerate().map(|(k, &o)| rate(k, o)).sum() };
    let finish = |choice: Vec<(usize, f32)>, feasible: bool| Allocation {
        bits: choice
            .iter()
            .enumerate()
            .map(|(k, &o)| rate(k, o))
            .collect(),
        rung: choice.iter().map(|o| o.0).collect(),
        quality: choice.iter().map(|o| o.1).collect(),
        feasible,
    };
    let cheapest: Vec<(usize, f32)> = (0..models.len())
        .map(|k| {
            options(k)
                .min_by(|&a, &b| rate(k, a).total_cmp(&rate(k, b)))
                .expect("non-empty grid")
        })
        .collect();
    if total(&cheapest) > budget {
        return finish(cheapest, false);
    }
    let (mut lo, mut hi) = (-40.0f64, 40.0f64);
    if total(&pick(lo.exp())) <= budget {
        return finish(pick(lo.exp()), true);
    }
    for _ in 0..80 {
        let mid = 0.5 * (lo + hi);
        if total(&pick(mid.exp())) <= budget {
            hi = mid;
        } else {
            lo = mid;
        }
    }
    finish(pick(hi.exp()), true)
}

/// The allocation weight of a layer: `(1 + saliency) * (1 + edge_share)`, where `edge_share`
/// is the layer's share of Edge-Depth Cache samples relative to the layer with the most.
pub fn weight(saliency: f32, edge_samples: usize, max_edge_samples: usize) -> f32 {
    let share = if max_edge_samples == 0 {
        0.0
    } else {
        edge_samples as f32 / max_edge_samples as f32
    };
    (1.0 + saliency.clamp(0.0, 1.0)) * (1.0 + share)
}

/// Visibility of a layer's pixels in the reference view, per pixel in [0, 255]: the
/// transmittance of the layers in front of it, so that hidden content (revealed only by
/// parallax) counts less but not nothing. `front` are the nearer layers.
pub fn visibility(front: &[&PremulImage], width: u32, height: u32) -> Vec<u8> {
    let n = (width * height) as usize;
    let mut t = vec![1f32; n];
    for l in front {
        for (i, px) in l.as_bytes().chunks_exact(4).enumerate() {
            t[i] *= 1.0 - px[3] as f32 / 255.0;
        }
    }
    t.into_iter().map(|v| (v * 255.0).round() as u8).collect()
}

/// The proxy distortion of one decoded layer against its source: squared error summed over
/// premultiplied R, G, B and alpha, each pixel weighted by `0.2 + 0.8 * visibility`. `D_k` is
/// its sum over a stream's sampled frames divided by the same (picture-size) constant for
/// every stream, so that a small layer weighs its share of the picture.
pub fn distortion(src: &PremulImage, dec: &PremulImage, vis: &[u8]) -> f64 {
    let mut err = 0f64;
    for ((s, d), &v) in src
        .as_bytes()
        .chunks_exact(4)
        .zip(dec.as_bytes().chunks_exact(4))
        .zip(vis)
    {
        let w = 0.2 + 0.8 * v as f64 / 255.0;
        let e: i32 = (0..4).map(|c| (s[c] as i32 - d[c] as i32).pow(2)).sum();
        err += w * e as f64;
    }
    err
}

#[cfg(test)]
mod tests {
    use super::*;

    fn model(r_at_20: f64, d_at_20: f64) -> RdModel {
        // Rate halves and distortion doubles every 6 steps.
        RdModel::fit(
            (20.0, r_at_20, d_at_20),
            (26.0, r_at_20 / 2.0, d_at_20 * 2.0),
        )
    }

    #[test]
    fn allocation_meets_the_budget_and_favours_heavy_layers() {
        let models = vec![vec![model(1e6, 10.0)]; 3];
        let weights = [4.0, 1.0, 1.0];
        let a = allocate(&models, &weights, 1.2e6, 10.0, 51.0);
        assert!(a.feasible);
        let spent: f64 = a.bits.iter().sum();
        assert!(spent <= 1.2e6 && spent > 1.0e6, "{spent}");
        assert!(a.quality[0] < a.quality[1], "{:?}", a.quality);
        assert_eq!(a.quality[1], a.quality[2]);
        // Equal weights split evenly.
        let b = allocate(&models, &[1.0; 3], 1.2e6, 10.0, 51.0);
        assert_eq!(b.quality[0], b.quality[1]);
        // A budget below the lowest quality's rate is infeasible and gets the lowest quality.
        let c = allocate(&models, &weights, 1.0, 10.0, 51.0);
        assert!(!c.feasible);
        assert!(c.quality.iter().all(|&q| q == 51.0));
        assert!(c.rung.iter().all(|&r| r == 0));
        // A generous budget gets the best quality.
        let d = allocate(&models, &weights, 1e12, 10.0, 51.0);
        assert!(d.quality.iter().all(|&q| q == 10.0));
    }

    #[test]
    fn a_budget_below_the_full_size_floor_goes_down_the_ladder() {
        // Rung 1 costs a quarter of the rate and carries a distortion floor of its own.
        let full = model(1e6, 10.0);
        let half = RdModel::fit((20.0, 2.5e5, 40.0), (26.0, 1.25e5, 60.0));
        let models = vec![vec![full, half]; 2];
        let floor_full = 2.0 * full.rate(51.0);
        // Generous: full size. Below the full-size floor: the half rung, within the budget.
        let a = allocate(&models, &[1.0; 2], 4e6, 10.0, 51.0);
        assert_eq!(a.rung, vec![0, 0]);
        let b = allocate(&models, &[1.0; 2], 0.8 * floor_full, 10.0, 51.0);
        assert!(b.feasible);
        assert_eq!(b.rung, vec![1, 1]);
        assert!(b.bits.iter().sum::<f64>() <= 0.8 * floor_full);
        // At a full-size quality whose distortion exceeds the half rung's at equal rate,
        // the half rung wins even above the floor.
        let r = full.rate(44.0) * 2.0;
        let c = allocate(&models, &[1.0; 2], r, 10.0, 51.0);
        let d = |a: &Allocation| -> f64 {
            (0..2)
                .map(|k| models[k][a.rung[k]].distortion(a.quality[k]))
                .sum()
        };
        assert!(d(&c) <= 2.0 * full.distortion(44.0), "{c:?}");
    }

    #[test]
    fn weights_rise_with_saliency_and_edges() {
        assert_eq!(weight(0.0, 0, 0), 1.0);
        assert!(weight(0.8, 0, 10) > weight(0.2, 0, 10));
        assert!(weight(0.2, 10, 10) > weight(0.2, 1, 10));
    }

    #[test]
    fn distortion_counts_hidden_pixels_less() {
        let a = PremulImage::from_rgb(2, 1, &[100, 100, 100, 100, 100, 100]).unwrap();
        let b = PremulImage::from_rgb(2, 1, &[110, 100, 100, 110, 100, 100]).unwrap();
        let e_vis = distortion(&a, &b, &[255, 255]);
        let e_hid = distortion(&a, &b, &[0, 0]);
        assert!((e_vis - 200.0).abs() < 1e-9);
        assert!((e_hid - 40.0).abs() < 1e-9);
    }
}
