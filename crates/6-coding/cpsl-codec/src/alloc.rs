//! Per-layer bitrate allocation under a total budget (equation 5 of the paper):
//! minimise `sum_k w_k D_k(r_k)` subject to `sum_k r_k <= R`.
//!
//! Each layer stream's rate and distortion are modelled as functions of the encoder's quality
//! setting `q` (CRF) from trial encodes of the segment's first frames: the key frame's bits
//! `I(q)`, the mean bits of the other pictures `P(q)` and the distortion `D(q)`, each
//! piecewise linear in its logarithm through the measured points (rate roughly halves every 6
//! CRF steps but flattens towards a fixed cost at high `q`, so a line through two points
//! extrapolates low; distortion grows geometrically). A segment of `n` frames costs
//! `I(q) + (n - 1) P(q)`, so trials on a few frames predict a whole segment, and a model
//! carried to the next segment is re-anchored on what the stream really cost
//! ([`RdModel::anchor`]). A stream has one such model per rung of the resolution ladder
//! ([`crate::scale`]), its distortion measured at the frame size after upsampling, so that
//! rungs compete on the same scale. The constrained problem is solved by Lagrangian relaxation
//! on the grid of rungs and integer qualities: for a multiplier `lambda`, every layer
//! independently picks the `(rung, q)` minimising `w_k D_k + lambda r_k`; `lambda` is bisected
//! (in log space) to the smallest value whose total rate fits the budget, and what is left is
//! spent greedily.
//!
use cpsl_core::PremulImage;

/// One trial encode of a stream: quality, the key frame's bits (with the container's), the
/// mean bits of the other pictures, and the proxy distortion per frame.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Trial {
    /// The quality (CRF).
    pub q: f32,
    /// Bits of the key frame and the container.
    pub intra: f64,
    /// Mean bits of the other pictures (`None`: the trial had only the key frame).
    pub inter: Option<f64>,
    /// Distortion ([`distortion`], per frame).
    pub distortion: f64,
}

/// A rate-distortion model of one layer stream, fitted to its trial encodes, for a segment
/// of [`RdModel::frames`] frames.
///
/// Key-frame bits, other pictures' bits and distortion are piecewise linear in their
/// logarithms through the measured points: the trials, and for the rates also each final
/// encode ([`RdModel::anchor`]), so that a quality between measured points is interpolated
/// and only the ends extrapolate.
#[derive(Debug, Clone, PartialEq)]
pub struct RdModel {
    /// Measured `(q, ln bits)` of the key frame, sorted by quality, at least two.
    intra: Vec<(f64, f64)>,
    /// Measured `(q, ln mean bits)` of the other pictures, sorted by quality, at least two.
    inter: Vec<(f64, f64)>,
    /// Measured `(q, ln distortion)`, sorted by quality, at least two.
    distortions: Vec<(f64, f64)>,
    /// Frames of the segment the rate is for.
    frames: usize,
    /// Whether the other pictures' bits were measured (else they are guessed as a tenth of
    /// the key frame's, which only a one-frame segment can afford).
    inter_measured: bool,
}

/// Smallest value a logarithm is taken of (an empty layer codes without error).
const MIN_D: f64 = 1e-4;

/// Fewest quality steps between the points that set an end's extrapolation slope (nearer
/// points give noisy slopes).
const MIN_SPAN: f64 = 4.0;

/// Least slope of `ln r` (falling) and `ln D` (rising) per quality step.
const MIN_SLOPE: f64 = 1e-3;

impl RdModel {
    /// Fits the model through trials at two or more distinct qualities, in increasing order,
    /// for segments of `frames` frames. Rates are forced to fall and distortions to rise with
    /// `q`, as encoders behave.
    ///
    /// # Panics
    /// With fewer than two trials.
    pub fn fit(trials: &[Trial], frames: usize) -> Self {
        assert!(trials.len() >= 2, "an RD model needs two trials");
        let ln = |v: f64| v.max(MIN_D).ln();
        let mut m = Self {
            intra: Vec::new(),
            inter: Vec::new(),
            distortions: Vec::new(),
            frames: frames.max(1),
            inter_measured: trials.iter().all(|t| t.inter.is_some()),
        };
        for t in trials {
            let q = t.q as f64;
            let inter = t.inter.unwrap_or(0.1 * t.intra);
            let (mut li, mut lp, mut ld) = (ln(t.intra), ln(inter), ln(t.distortion));
            if let Some(&(pq, pd)) = m.distortions.last() {
                let dq: f64 = q - pq;
                li = li.min(m.intra.last().expect("as long").1 - MIN_SLOPE * dq);
                lp = lp.min(m.inter.last().expect("as long").1 - MIN_SLOPE * dq);
                ld = ld.max(pd + MIN_SLOPE * dq);
            }
            m.intra.push((q, li));
            m.inter.push((q, lp));
            m.distortions.push((q, ld));
        }
        m
    }

    /// The model for segments of `frames` frames.
    pub fn for_frames(mut self, frames: usize) -> Self {
        self.frames = frames.max(1);
        self
    }

    /// Frames of the segment the rate is for.
    pub fn frames(&self) -> usize {
        self.frames
    }

    /// The model with `other`'s other-picture rates (measured over whole segments) in place
    /// of its own.
    pub fn with_inter_of(mut self, other: &RdModel) -> Self {
        self.inter.clone_from(&other.inter);
        self.inter_measured = other.inter_measured;
        self
    }

    /// Whether the model may serve a longer segment than its trials': the other pictures'
    /// bits were measured.
    pub fn carries(&self) -> bool {
        self.inter_measured
    }

    /// Adds a trial (replacing a point at the same quality).
    pub fn add(&mut self, t: &Trial) {
        let q = t.q as f64;
        let put = |points: &mut Vec<(f64, f64)>, v: f64| {
            points.retain(|p| (p.0 - q).abs() >= 0.5);
            let at = points.partition_point(|p| p.0 < q);
            points.insert(at, (q, v.max(MIN_D).ln()));
        };
        put(&mut self.intra, t.intra);
        if let Some(inter) = t.inter {
            put(&mut self.inter, inter);
        }
        put(&mut self.distortions, t.distortion);
    }

    /// The highest quality value measured.
    pub fn max_q(&self) -> f32 {
        self.distortions.last().map_or(0.0, |p| p.0 as f32)
    }

    /// The lowest quality value measured.
    pub fn min_q(&self) -> f32 {
        self.distortions.first().map_or(0.0, |p| p.0 as f32)
    }

    /// The best quality the model is trusted at: 4 steps (`MIN_SPAN`) beyond its best measured
    /// one (rates grow faster than a line towards the best qualities).
    pub fn best_q(&self) -> f32 {
        self.distortions
            .first()
            .map_or(0.0, |p| (p.0 - MIN_SPAN) as f32)
    }

    /// Re-anchors the rates on key-frame bits and mean bits of the other pictures measured
    /// at quality `q` (`inter` is `None` when the segment had only its key frame): each rate
    /// curve is scaled to run through its measurement, keeping its shape, so that content
    /// that got simpler or busier shifts the whole curve.
    pub fn anchor(&mut self, q: f32, intra: f64, inter: Option<f64>) {
        let shift = |points: &mut Vec<(f64, f64)>, bits: f64| {
            let by = bits.max(MIN_D).ln() - piecewise(points, q as f64, |s| s.min(-MIN_SLOPE));
            points.iter_mut().for_each(|p| p.1 += by);
        };
        shift(&mut self.intra, intra);
        if let Some(inter) = inter {
            shift(&mut self.inter, inter);
        }
    }

    /// Re-anchors the distortion on one measured at quality `q`: the curve is scaled to run
    /// through it, keeping its shape.
    pub fn anchor_distortion(&mut self, q: f32, distortion: f64) {
        let by = distortion.max(MIN_D).ln()
            - piecewise(&self.distortions, q as f64, |s| s.max(MIN_SLOPE));
        self.distortions.iter_mut().for_each(|p| p.1 += by);
    }

    /// Modelled key-frame bits and mean bits of the other pictures at quality `q`.
    pub fn intra_inter(&self, q: f32) -> (f64, f64) {
        let clamp = |s: f64| s.min(-MIN_SLOPE);
        (
            piecewise(&self.intra, q as f64, clamp).exp(),
            piecewise(&self.inter, q as f64, clamp).exp(),
        )
    }

    /// Modelled bits of a segment of [`RdModel::frames`] frames at quality `q`.
    pub fn rate(&self, q: f32) -> f64 {
        let (i, p) = self.intra_inter(q);
        i + (self.frames - 1) as f64 * p
    }

    /// Modelled distortion per frame at quality `q`.
    pub fn distortion(&self, q: f32) -> f64 {
        piecewise(&self.distortions, q as f64, |s| s.max(MIN_SLOPE)).exp()
    }
}

/// The piecewise-linear function through `p` (sorted, at least two points) at `q`; beyond an
/// end, the slope to the nearest point at least [`MIN_SPAN`] away, passed through `clamp`.
fn piecewise(p: &[(f64, f64)], q: f64, clamp: impl Fn(f64) -> f64) -> f64 {
    let i = p.partition_point(|pt| pt.0 <= q);
    if i == 0 || i == p.len() {
        let (end, other) = if i == 0 {
            let o = p.iter().find(|pt| pt.0 - p[0].0 >= MIN_SPAN);
            (p[0], *o.unwrap_or(&p[p.len() - 1]))
        } else {
            let last = p[p.len() - 1];
            let o = p.iter().rev().find(|pt| last.0 - pt.0 >= MIN_SPAN);
            (last, *o.unwrap_or(&p[0]))
        };
        end.1 + clamp((other.1 - end.1) / (other.0 - end.0)) * (q - end.0)
    } else {
        let (a, b) = (p[i - 1], p[i]);
        a.1 + (b.1 - a.1) * (q - a.0) / (b.0 - a.0)
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
/// holds stream `k`'s model per rung (at least one), each trusted only up to its
/// [`RdModel::best_q`]. After the Lagrangian search, what the
/// budget has left is spent greedily, on the change that lowers `w_k D_k` most per extra bit:
/// the multiplier's choices jump between discrete options, so the search alone may leave much
/// unspent.
pub fn allocate(
    models: &[Vec<RdModel>],
    weights: &[f32],
    budget: f64,
    q_min: f32,
    q_max: f32,
) -> Allocation {
    allocate_within(models, weights, budget, (q_min, q_max), None)
}

/// [`allocate`], stream `k` limited to the choices whose modelled rate is at most `caps[k]`
/// (the models must offer each stream one: after [`RdModel::anchor`] on a measured coding,
/// that coding is).
pub fn allocate_capped(
    models: &[Vec<RdModel>],
    weights: &[f32],
    budget: f64,
    (q_min, q_max): (f32, f32),
    caps: &[f64],
) -> Allocation {
    allocate_within(models, weights, budget, (q_min, q_max), Some(caps))
}

fn allocate_within(
    models: &[Vec<RdModel>],
    weights: &[f32],
    budget: f64,
    (q_min, q_max): (f32, f32),
    caps: Option<&[f64]>,
) -> Allocation {
    let grid: Vec<f32> = (q_min.ceil() as i32..=q_max.floor() as i32)
        .map(|q| q as f32)
        .collect();
    let rate = |k: usize, (r, q): (usize, f32)| models[k][r].rate(q);
    let cost = |k: usize, (r, q): (usize, f32)| weights[k] as f64 * models[k][r].distortion(q);
    let options = |k: usize| {
        let grid = &grid;
        let cap = caps.map_or(f64::INFINITY, |c| c[k] * (1.0 + 1e-9));
        (0..models[k].len())
            .flat_map(move |r| {
                let best = models[k][r].best_q();
                grid.iter()
                    .filter(move |&&q| q >= best)
                    .map(move |&q| (r, q))
            })
            .filter(move |&o| rate(k, o) <= cap)
    };
    let within = "a stream has a rung and the grid a quality";
    let cheapest = |k: usize| {
        options(k)
            .min_by(|&a, &b| rate(k, a).total_cmp(&rate(k, b)))
            .expect(within)
    };
    let pick = |lambda: f64| -> Vec<(usize, f32)> {
        (0..models.len())
            .map(|k| {
                let c = |o| cost(k, o) + lambda * rate(k, o);
                options(k)
                    .min_by(|&a, &b| c(a).total_cmp(&c(b)))
                    .expect(within)
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
    let floor: Vec<(usize, f32)> = (0..models.len()).map(cheapest).collect();
    if total(&floor) > budget {
        return finish(floor, false);
    }
    let (mut lo, mut hi) = (-40.0f64, 40.0f64);
    let mut choice = pick(lo.exp());
    if total(&choice) > budget {
        for _ in 0..80 {
            let mid = 0.5 * (lo + hi);
            if total(&pick(mid.exp())) <= budget {
                hi = mid;
            } else {
                lo = mid;
            }
        }
        choice = pick(hi.exp());
    }
    // Spend the rest greedily.
    let mut spent = total(&choice);
    loop {
        let mut best: Option<(f64, usize, (usize, f32))> = None;
        for (k, &now) in choice.iter().enumerate() {
            let (r0, c0) = (rate(k, now), cost(k, now));
            for o in options(k) {
                let (r, c) = (rate(k, o), cost(k, o));
                if c < c0 && spent - r0 + r <= budget {
                    let gain = (c0 - c) / (r - r0).max(1e-9);
                    if best.is_none_or(|b| gain > b.0) {
                        best = Some((gain, k, o));
                    }
                }
            }
        }
        let Some((_, k, o)) = best else { break };
        spent += rate(k, o) - rate(k, choice[k]);
        choice[k] = o;
    }
    finish(choice, true)
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
    /// Pixels taken through all the layers at a time, their products kept in a small buffer.
    const RUN: usize = 1024;
    let n = (width * height) as usize;
    let mut out = vec![0u8; n];
    // What each alpha lets through, as the product takes it.
    let clear: [f32; 256] = std::array::from_fn(|a| 1.0 - a as f32 / 255.0);
    let mut t = [0f32; RUN];
    for (start, out) in (0..n).step_by(RUN).zip(out.chunks_mut(RUN)) {
        let t = &mut t[..out.len()];
        t.fill(1.0);
        for l in front {
            let px = &l.as_bytes()[4 * start..4 * (start + t.len())];
            for (t, px) in t.iter_mut().zip(px.chunks_exact(4)) {
                *t *= clear[px[3] as usize];
            }
        }
        // Rounded half away from zero (`f32::round`, a library call here) for values in
        // [0, 255]: the fraction after truncation is exact (`cpsl_core::image::round_to_u8`
        // without its clamp, which costs this loop a tenth of its time).
        for (o, &v) in out.iter_mut().zip(t.iter()) {
            let x = v * 255.0;
            let i = x as u32;
            *o = (i + u32::from(x - i as f32 >= 0.5)) as u8;
        }
    }
    out
}

/// The proxy distortion of one decoded layer against its source: squared error summed over
/// premultiplied R, G, B and alpha, each pixel weighted by `0.2 + 0.8 * visibility`. `D_k` is
/// its sum over a stream's sampled frames divided by the same (picture-size) constant for
/// every stream, so that a small layer weighs its share of the picture.
pub fn distortion(src: &PremulImage, dec: &PremulImage, vis: &[u8]) -> f64 {
    // In integers, exactly: the weight is (255 + 4 v) / 1275. A pixel's weighted error is
    // below 2^29, so a block of eight sums in 32 bits; a block alike in both (transparent
    // there, as most of a layer is) adds nothing.
    let pixel = |s: &[u8], d: &[u8], v: u8| -> u32 {
        let e: u32 = (0..4).map(|c| u32::from(s[c].abs_diff(d[c])).pow(2)).sum();
        e * (255 + 4 * u32::from(v))
    };
    let (s, d) = (src.as_bytes(), dec.as_bytes());
    let blocks = s
        .chunks_exact(32)
        .zip(d.chunks_exact(32))
        .zip(vis.chunks_exact(8));
    let mut err: u64 = blocks
        .map(|((s, d), v)| {
            let (s, d): (&[u8; 32], &[u8; 32]) = (s.try_into().unwrap(), d.try_into().unwrap());
            if s == d {
                return 0;
            }
            let sq: [u16; 32] = std::array::from_fn(|j| u16::from(s[j].abs_diff(d[j])).pow(2));
            let e: [u32; 8] = std::array::from_fn(|i| {
                let e = sq[4 * i..4 * i + 4]
                    .iter()
                    .map(|&x| u32::from(x))
                    .sum::<u32>();
                e * (255 + 4 * u32::from(v[i]))
            });
            u64::from(e.iter().sum::<u32>())
        })
        .sum();
    let done = vis.len() / 8 * 8;
    for i in done..vis.len() {
        err += u64::from(pixel(&s[4 * i..4 * i + 4], &d[4 * i..4 * i + 4], vis[i]));
    }
    err as f64 / 1275.0
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn visibility_and_distortion_follow_their_formulas() {
        // Soft, opaque and clear pixels; a size that leaves partial runs and blocks.
        let (w, h) = (37u32, 29u32);
        let layer = |seed: u32| {
            let data: Vec<u8> = (0..w * h)
                .flat_map(|i| {
                    let a = match (i.wrapping_mul(2654435761) ^ seed) % 5 {
                        0 | 1 => 0,
                        2 => ((i * 7 + seed) % 256) as u8,
                        _ => 255,
                    };
                    [a / 2, a / 3, ((i + seed) % 256) as u8 % (a / 4 + 1), a]
                })
                .collect();
            PremulImage::from_premul(w, h, data).unwrap()
        };
        let layers: Vec<PremulImage> = (0..4).map(layer).collect();
        let front: Vec<&PremulImage> = layers[..3].iter().collect();
        let vis = visibility(&front, w, h);
        for (i, &v) in vis.iter().enumerate() {
            let t = front.iter().fold(1f32, |t, l| {
                t * (1.0 - l.as_bytes()[4 * i + 3] as f32 / 255.0)
            });
            assert_eq!(v, (t * 255.0).round() as u8, "pixel {i}");
        }
        let (s, d) = (layers[3].as_bytes(), layers[0].as_bytes());
        let expected: f64 = (0..vis.len())
            .map(|i| {
                let e: f64 = (0..4)
                    .map(|c| (s[4 * i + c] as f64 - d[4 * i + c] as f64).powi(2))
                    .sum();
                e * (0.2 + 0.8 * vis[i] as f64 / 255.0)
            })
            .sum();
        let got = distortion(&layers[3], &layers[0], &vis);
        assert!(
            (got - expected).abs() <= 1e-9 * expected,
            "{got} against {expected}"
        );
        assert_eq!(distortion(&layers[3], &layers[3], &vis), 0.0);
    }

    fn trial(q: f32, intra: f64, inter: f64, distortion: f64) -> Trial {
        Trial {
            q,
            intra,
            inter: Some(inter),
            distortion,
        }
    }

    /// A one-frame model: rate halves and distortion doubles every 6 steps.
    fn model(r_at_20: f64, d_at_20: f64) -> RdModel {
        RdModel::fit(
            &[
                trial(20.0, r_at_20, r_at_20 / 10.0, d_at_20),
                trial(26.0, r_at_20 / 2.0, r_at_20 / 20.0, d_at_20 * 2.0),
            ],
            1,
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
        // A generous budget gets the best quality the models are trusted at: four steps
        // beyond their best trial (20).
        let d = allocate(&models, &weights, 1e12, 10.0, 51.0);
        assert!(d.quality.iter().all(|&q| q == 16.0), "{d:?}");
    }

    #[test]
    fn capped_streams_cost_no_more_than_their_caps() {
        let models = vec![vec![model(1e6, 10.0)]; 3];
        let weights = [4.0, 1.0, 1.0];
        let free = allocate(&models, &weights, 1.2e6, 10.0, 51.0);
        // Stream 0 capped below its free choice: cheaper for it, the rest goes to the others.
        let caps = [0.5 * free.bits[0], 1e12, 1e12];
        let a = allocate_capped(&models, &weights, 1.2e6, (10.0, 51.0), &caps);
        assert!(a.feasible && a.bits[0] <= caps[0], "{a:?}");
        assert!(a.quality[0] > free.quality[0] && a.quality[1] <= free.quality[1]);
        assert!(a.bits.iter().sum::<f64>() <= 1.2e6);
    }

    #[test]
    fn what_the_search_leaves_is_spent() {
        // Streams of different sizes, so that the multiplier's choices jump unevenly.
        let models: Vec<Vec<RdModel>> = (0..3)
            .map(|k| vec![model(1e6 * (1 + 3 * k) as f64, 10.0 * (k + 1) as f64)])
            .collect();
        for weights in [[4.0, 1.0, 1.0], [1.0, 2.0, 3.0]] {
            for budget in [5e5, 9e5, 1.3e6, 3.1e6] {
                let a = allocate(&models, &weights, budget, 10.0, 51.0);
                let spent: f64 = a.bits.iter().sum();
                assert!(a.feasible && spent <= budget, "{budget}: {spent}");
                // No stream can take one quality step better within the budget.
                for ((m, &q), &bits) in models.iter().zip(&a.quality).zip(&a.bits) {
                    if q > 10.0 {
                        let more = m[0].rate(q - 1.0) - bits;
                        assert!(spent + more > budget, "{budget} {weights:?}: {a:?}");
                    }
                }
            }
        }
    }

    #[test]
    fn a_budget_below_the_full_size_floor_goes_down_the_ladder() {
        // Rung 1 costs a quarter of the rate and carries a distortion floor of its own.
        let full = model(1e6, 10.0);
        let half = RdModel::fit(
            &[
                trial(20.0, 2.5e5, 2.5e4, 40.0),
                trial(26.0, 1.25e5, 1.25e4, 60.0),
            ],
            1,
        );
        let models = vec![vec![full.clone(), half]; 2];
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
    fn a_segment_costs_its_key_frame_and_its_other_pictures() {
        let m = RdModel::fit(
            &[trial(20.0, 8e5, 1e5, 10.0), trial(32.0, 2e5, 2.5e4, 40.0)],
            8,
        );
        assert!((m.rate(20.0) - (8e5 + 7.0 * 1e5)).abs() < 1e-3);
        let long = m.clone().for_frames(30);
        assert_eq!(long.frames(), 30);
        assert!((long.rate(32.0) - (2e5 + 29.0 * 2.5e4)).abs() < 1e-3);
        // Geometric in between; the distortion does not depend on the length.
        let (i, p) = long.intra_inter(26.0);
        assert!((i / 4e5 - 1.0).abs() < 1e-9 && (p / 5e4 - 1.0).abs() < 1e-9);
        assert_eq!(m.distortion(26.0), long.distortion(26.0));
        assert!(m.carries());
        // Trials of a key frame alone serve a one-frame segment, and are not carried on.
        let key = |q, intra| Trial {
            q,
            intra,
            inter: None,
            distortion: 1.0,
        };
        let one = RdModel::fit(&[key(20.0, 8e5), key(32.0, 2e5)], 1);
        assert!(!one.carries());
        assert!((one.rate(20.0) - 8e5).abs() < 1e-3);
    }

    #[test]
    fn added_trials_interpolate_and_extrapolate_from_points_apart() {
        let mut m = model(1e6, 10.0).for_frames(2);
        let (i30, p30) = m.intra_inter(30.0);
        m.add(&trial(30.0, 2.0 * i30, 3.0 * p30, 50.0));
        let (i, p) = m.intra_inter(30.0);
        assert!((i / (2.0 * i30) - 1.0).abs() < 1e-9 && (p / (3.0 * p30) - 1.0).abs() < 1e-9);
        assert!((m.distortion(30.0) / 50.0 - 1.0).abs() < 1e-9);
        assert_eq!(m.max_q(), 30.0);
        // Between 26 and 30: geometric interpolation; the first trials stay as measured.
        let mid = (m.intra_inter(26.0).0 * m.intra_inter(30.0).0).sqrt();
        assert!((m.intra_inter(28.0).0 / mid - 1.0).abs() < 1e-9);
        assert!((m.intra_inter(20.0).0 / 1e6 - 1.0).abs() < 1e-9);
        // A point 2 steps from the end does not set the slope beyond it: 26 (6 steps) does.
        m.add(&trial(32.0, 1.3 * i30, p30, 60.0));
        let at = |q: f32| m.intra_inter(q).0;
        let slope = (at(32.0) / at(26.0)).ln() / 6.0;
        assert!((at(40.0) / (at(32.0) * (8.0 * slope).exp()) - 1.0).abs() < 1e-9);
        // Adding the same quality again replaces the point.
        m.add(&trial(32.0, 1.1 * i30, p30, 60.0));
        assert!((m.intra_inter(32.0).0 / (1.1 * i30) - 1.0).abs() < 1e-9);
    }

    #[test]
    fn anchoring_shifts_each_rate_curve_through_the_measurement() {
        let mut m = model(1e6, 10.0).for_frames(5);
        let before = |q: f32| m.clone().intra_inter(q);
        let (i20, p20) = before(20.0);
        let (i40, p40) = before(40.0);
        let d = m.distortion(23.0);
        let (i23, p23) = before(23.0);
        m.anchor(23.0, 2.0 * i23, Some(0.5 * p23));
        let (i, p) = m.intra_inter(23.0);
        assert!((i / (2.0 * i23) - 1.0).abs() < 1e-9 && (p / (0.5 * p23) - 1.0).abs() < 1e-9);
        // The whole curve moves; the distortion stays.
        let (j20, q20) = m.intra_inter(20.0);
        let (j40, q40) = m.intra_inter(40.0);
        assert!((j20 / i20 - 2.0).abs() < 1e-9 && (j40 / i40 - 2.0).abs() < 1e-9);
        assert!((q20 / p20 - 0.5).abs() < 1e-9 && (q40 / p40 - 0.5).abs() < 1e-9);
        assert_eq!(m.distortion(23.0), d);
        // A key frame alone moves only the key frame's curve.
        m.anchor(23.0, i23, None);
        assert!((m.intra_inter(23.0).1 / (0.5 * p23) - 1.0).abs() < 1e-9);
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
