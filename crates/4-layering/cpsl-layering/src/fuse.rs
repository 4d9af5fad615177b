//! Depth-semantic fusion (paper eq. 3): a layer label per working pixel minimising
//!
//! `E(S) = sum_x [ w_d rho(d - d_S) + w_s phi(c, S) + w_i psi(iota, S) ]
//!         + lambda_b sum_(x,y) omega_xy [S(x) != S(y)]`
//!
//! over 4-neighbours, by alpha-expansion graph cuts ([`crate::maxflow`]), with the
//! representative inverse depths `d_l` re-estimated between rounds. Depth is compared in
//! normalised inverse depth `d` (see [`crate::cues::Cues::disparity`]).
//!
//! Beyond the paper, with slanted labels ([`FusionConfig::slanted_labels`], for slanted and
//! mesh geometry) `d_l` is a plane in inverse depth over the image, `c + a u + b v`, refitted
//! to the label's pixels between rounds (reweighted least squares): a slanted floor costs one
//! label instead of a staircase of slabs. The first round starts from the paper's flat
//! representatives, so the labels only tilt where the depth asks for it.
//!
//! * `rho(r) = min((r / sigma)^2, T)`: truncated quadratic, robust to outliers;
//!   `w_d = 0.1 + 0.9 sigma_z` (depth confidence).
//! * `phi(c, l) = min(max(0, d - d_l) / sigma, T)`: a salient pixel put on a layer *behind*
//!   itself tears it from its object; `w_s = sigmoid(10 (saliency - 0.5))`.
//! * `psi(iota, l) = [l != L(iota)]`: pixels of an instance prefer the instance's label
//!   `L(iota)` (the label of least depth cost over the instance, re-estimated each round);
//!   `w_i` = instance weight x instance confidence.
//! * `omega_xy = exp(-(alpha |I(x) - I(y)| / mean|dI| + beta b_sem))`, `b_sem = 1` across
//!   instance boundaries and depth discontinuities: cuts are cheap along colour and semantic
//!   edges.

use crate::cues::Work;
use crate::maxflow::Graph;
use crate::slice::cluster_disparity;
use serde::{Deserialize, Serialize};

/// Configuration of the fusion energy.
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields, default)]
pub struct FusionConfig {
    /// Alpha-expansion rounds (each: one expansion per label, then representatives
    /// re-estimated).
    pub rounds: usize,
    /// `sigma` of the robust depth penalty, in normalised inverse depth.
    pub sigma: f32,
    /// Truncation `T` of the robust penalties.
    pub truncation: f32,
    /// Weight of the saliency term.
    pub saliency_weight: f32,
    /// Weight of the instance term.
    pub instance_weight: f32,
    /// `lambda_b`: weight of the pairwise term.
    pub smoothness: f32,
    /// `alpha`: colour-contrast sensitivity of `omega`.
    pub contrast: f32,
    /// `beta`: semantic-edge sensitivity of `omega`.
    pub semantic: f32,
    /// Normalised inverse-depth jump between neighbours that counts as a depth edge.
    pub depth_edge: f32,
    /// Labels are planes in inverse depth (fitted to their pixels between rounds) where the
    /// layers' geometry is not the paper's fronto-parallel plane (`--geometry slanted|mesh`),
    /// so that a floor or a wall seen at an angle can stay one layer; false keeps the paper's
    /// one inverse depth per label with any geometry. (Measured with ground-truth depth,
    /// K = 6: Middlebury mean PSNR +0.83 dB with slanted geometry, +0.10 dB with meshes;
    /// EVALUATION.md.)
    pub slanted_labels: bool,
}

impl Default for FusionConfig {
    fn default() -> Self {
        Self {
            rounds: 2,
            sigma: 0.04,
            truncation: 9.0,
            saliency_weight: 1.0,
            instance_weight: 3.0,
            smoothness: 1.5,
            contrast: 1.0,
            semantic: 2.0,
            depth_edge: 0.04,
            slanted_labels: true,
        }
    }
}

/// The result of fusion.
#[derive(Debug, Clone, PartialEq)]
pub struct Fusion {
    /// Label per working pixel, indexing `representatives`.
    pub labels: Vec<u8>,
    /// Representative normalised inverse depth of each label, nearest (largest) first.
    pub representatives: Vec<f32>,
    /// Energy after each round.
    pub energy: Vec<f64>,
    /// Whether the labels were planes in inverse depth (slanted labels): promotion and
    /// merging then weigh the depth-fit error of a plane per layer.
    pub slanted: bool,
}

struct Problem<'a> {
    work: &'a Work,
    cfg: FusionConfig,
    /// Pairwise weights to the right and down neighbours (`lambda_b omega`).
    right: Vec<f32>,
    down: Vec<f32>,
    w_d: Vec<f32>,
    w_s: Vec<f32>,
    /// Each pixel's [`centred`] position, where the labels' planes are evaluated (computed
    /// once: the divisions cost the energy's every term more than the term itself).
    uv: Vec<(f32, f32)>,
}

impl Problem<'_> {
    fn rho(&self, r: f32) -> f32 {
        ((r / self.cfg.sigma).powi(2)).min(self.cfg.truncation)
    }

    /// `plane`'s inverse depth at pixel `p`.
    fn at(&self, plane: &Plane, p: usize) -> f32 {
        let (u, v) = self.uv[p];
        plane.at_uv(u, v)
    }

    fn unary(&self, p: usize, plane: &Plane, label: usize, inst_label: &[usize]) -> f32 {
        let w = self.work;
        let d = w.disparity[p];
        let rep = self.at(plane, p);
        let mut e = self.w_d[p] * self.rho(d - rep);
        if self.w_s[p] > 0.0 {
            e += self.cfg.saliency_weight
                * self.w_s[p]
                * ((d - rep).max(0.0) / self.cfg.sigma).min(self.cfg.truncation);
        }
        let id = w.instances.ids[p] as usize;
        if id > 0 && inst_label[id - 1] != label {
            e += self.cfg.instance_weight * w.instances.confidence[id - 1];
        }
        e
    }
}

/// A label's inverse depth over the image: `c + a u + b v`, with `u` and `v` the pixel's
/// position in image widths and heights from the centre (`a = b = 0`: the paper's
/// fronto-parallel representative).
#[derive(Debug, Clone, Copy, PartialEq)]
struct Plane {
    a: f32,
    b: f32,
    c: f32,
}

impl Plane {
    fn flat(c: f32) -> Self {
        Self { a: 0.0, b: 0.0, c }
    }

    fn at_uv(&self, u: f32, v: f32) -> f32 {
        self.c + self.a * u + self.b * v
    }
}

/// Pixel `p`'s position `(u, v)` in image widths and heights from the centre of a `w` x `h`
/// image: the coordinates of the labels' planes and of promotion's plane fit.
pub(crate) fn centred(p: usize, w: usize, h: usize) -> (f32, f32) {
    (
        (p % w) as f32 / w as f32 - 0.5,
        (p / w) as f32 / h as f32 - 0.5,
    )
}

/// The confidence-weighted median of `values` over `pixels`.
fn weighted_median(pixels: &[usize], values: &[f32], weights: &[f32]) -> f32 {
    let mut v: Vec<(f32, f32)> = pixels.iter().map(|&p| (values[p], weights[p])).collect();
    v.sort_by(|a, b| a.0.total_cmp(&b.0));
    let half = v.iter().map(|e| e.1).sum::<f32>() / 2.0;
    let mut acc = 0.0;
    let m = v.iter().find(|e| {
        acc += e.1;
        acc >= half
    });
    m.map_or(v[v.len() / 2].0, |e| e.0)
}

/// Rounds of reweighting in [`fit_plane`].
const PLANE_ROUNDS: usize = 3;

/// Largest `|a| + |b|` of a fitted plane (normalised inverse depth across the image).
const MAX_TILT: f64 = 4.0;

/// A plane fitted to the inverse depth of `pixels` by iteratively reweighted least squares
/// (confidence times a Cauchy weight of the residual at the depth term's `sigma`), starting
/// from `start`; `None` when the pixels do not fix one (too few, or on a line: singular, or
/// tilted beyond [`MAX_TILT`]).
fn fit_plane(pixels: &[usize], prob: &Problem, start: Plane) -> Option<Plane> {
    if pixels.len() < 16 {
        return None;
    }
    let sigma = prob.cfg.sigma as f64;
    let mut plane = start;
    for _ in 0..PLANE_ROUNDS {
        // Normal equations of (u, v, 1) . (a, b, c) = d.
        let mut m = [[0f64; 3]; 3];
        let mut r = [0f64; 3];
        for &p in pixels {
            let (u, v) = prob.uv[p];
            let d = prob.work.disparity[p] as f64;
            let e = d - plane.at_uv(u, v) as f64;
            let wt = prob.w_d[p] as f64 / (1.0 + (e / sigma).powi(2));
            let f = [u as f64, v as f64, 1.0];
            for i in 0..3 {
                r[i] += wt * f[i] * d;
                for j in 0..3 {
                    m[i][j] += wt * f[i] * f[j];
                }
            }
        }
        let inv = cpsl_core::Mat3(m).inverse()?;
        let s = inv * cpsl_core::Vec3(r);
        // Normalised inverse depth lies in [0, 1]: a plane that changes by more than
        // MAX_TILT across the image is an ill-conditioned fit (pixels nearly on a line).
        if !s.is_finite() || s.x().abs() + s.y().abs() > MAX_TILT {
            return None;
        }
        plane = Plane {
            a: s.x() as f32,
            b: s.y() as f32,
            c: s.z() as f32,
        };
    }
    Some(plane)
}

/// Minimises the fusion energy over `labels` candidate layers; with `slanted`, each label's
/// representative is a plane in inverse depth (fitted to its pixels between rounds) instead of
/// one inverse depth, so that a floor or a wall seen at an angle can stay one label (the
/// pipeline passes [`FusionConfig::slanted_labels`] where the geometry is not `plane`).
pub fn fuse(work: &Work, labels: usize, cfg: &FusionConfig, slanted: bool) -> Fusion {
    let (w, h) = (work.width, work.height);
    let n = w * h;
    let labels = labels.clamp(1, 255);
    let mut reps: Vec<Plane> = cluster_disparity(&work.disparity, labels, 30)
        .into_iter()
        .map(|c| Plane::flat(c as f32))
        .collect();

    // Pairwise weights.
    let diff = |p: usize, q: usize| {
        let (a, b) = (&work.rgb[p * 3..p * 3 + 3], &work.rgb[q * 3..q * 3 + 3]);
        ((a[0] - b[0]).powi(2) + (a[1] - b[1]).powi(2) + (a[2] - b[2]).powi(2)).sqrt()
    };
    let mut mean = 0f64;
    let mut count = 0usize;
    for y in 0..h {
        for x in 0..w {
            let p = y * w + x;
            if x + 1 < w {
                mean += diff(p, p + 1) as f64;
                count += 1;
            }
            if y + 1 < h {
                mean += diff(p, p + w) as f64;
                count += 1;
            }
        }
    }
    let mean = ((mean / count.max(1) as f64) as f32).max(1e-3);
    let ids = &work.instances.ids;
    let omega = |p: usize, q: usize| {
        let sem = ((ids[p] != ids[q]) as u8 as f32)
            .max(((work.disparity[p] - work.disparity[q]).abs() > cfg.depth_edge) as u8 as f32);
        cfg.smoothness * (-(cfg.contrast * diff(p, q) / mean + cfg.semantic * sem)).exp()
    };
    let mut right = vec![0f32; n];
    let mut down = vec![0f32; n];
    for y in 0..h {
        for x in 0..w {
            let p = y * w + x;
            if x + 1 < w {
                right[p] = omega(p, p + 1);
            }
            if y + 1 < h {
                down[p] = omega(p, p + w);
            }
        }
    }
    let prob = Problem {
        work,
        cfg: *cfg,
        right,
        down,
        w_d: work.confidence.iter().map(|c| 0.1 + 0.9 * c).collect(),
        w_s: work
            .saliency
            .iter()
            .map(|s| 1.0 / (1.0 + (-10.0 * (s - 0.5)).exp()))
            .collect(),
        uv: (0..n).map(|p| centred(p, w, h)).collect(),
    };

    // Initial labelling: nearest representative.
    let nearest = |d: f32, reps: &[Plane]| {
        (0..reps.len())
            .min_by(|&a, &b| (d - reps[a].c).abs().total_cmp(&(d - reps[b].c).abs()))
            .unwrap_or(0)
    };
    let mut lab: Vec<u8> = work
        .disparity
        .iter()
        .map(|&d| nearest(d, &reps) as u8)
        .collect();
    let n_inst = work.instances.confidence.len();
    let mut energies = Vec::new();
    for _ in 0..cfg.rounds.max(1) {
        let inst_label = instance_labels(&prob, &reps, n_inst);
        let mut energy = total_energy(&prob, &lab, &reps, &inst_label);
        for alpha in 0..reps.len() {
            let (next, e) = expand(&prob, &lab, alpha, &reps, &inst_label);
            if e < energy - 1e-6 {
                lab = next;
                energy = e;
            }
        }
        energies.push(energy);
        // Re-estimate representatives: confidence-weighted median of each label's pixels, or
        // with `slanted` a robust plane fitted to them; drop empty labels.
        let mut per: Vec<Vec<usize>> = vec![Vec::new(); reps.len()];
        for p in 0..n {
            per[lab[p] as usize].push(p);
        }
        let mut remap = vec![0u8; reps.len()];
        let mut next = Vec::new();
        for (l, v) in per.iter().enumerate() {
            if v.is_empty() {
                continue;
            }
            remap[l] = next.len() as u8;
            let flat = Plane::flat(weighted_median(v, &work.disparity, &prob.w_d));
            next.push(if slanted {
                fit_plane(v, &prob, flat).unwrap_or(flat)
            } else {
                flat
            });
        }
        lab.iter_mut().for_each(|l| *l = remap[*l as usize]);
        reps = next;
    }
    // Nearest first: sort representatives (a slanted one's inverse depth at the centroid of
    // its pixels) by decreasing inverse depth.
    let mut centroid = vec![(0f64, 0f64, 0f64); reps.len()];
    for (p, &l) in lab.iter().enumerate() {
        let (u, v) = prob.uv[p];
        let c = &mut centroid[l as usize];
        *c = (c.0 + u as f64, c.1 + v as f64, c.2 + 1.0);
    }
    let reps: Vec<f32> = reps
        .iter()
        .zip(&centroid)
        .map(|(r, &(u, v, k))| r.at_uv((u / k.max(1.0)) as f32, (v / k.max(1.0)) as f32))
        .collect();
    let mut order: Vec<usize> = (0..reps.len()).collect();
    order.sort_by(|&a, &b| reps[b].total_cmp(&reps[a]));
    let mut rank = vec![0u8; reps.len()];
    for (r, &l) in order.iter().enumerate() {
        rank[l] = r as u8;
    }
    Fusion {
        labels: lab.iter().map(|&l| rank[l as usize]).collect(),
        representatives: order.iter().map(|&l| reps[l]).collect(),
        energy: energies,
        slanted,
    }
}

/// The label of least depth cost over each instance.
fn instance_labels(prob: &Problem, reps: &[Plane], n_inst: usize) -> Vec<usize> {
    let mut cost = vec![0f64; n_inst * reps.len()];
    for (p, &id) in prob.work.instances.ids.iter().enumerate() {
        if id > 0 {
            for (l, r) in reps.iter().enumerate() {
                cost[(id as usize - 1) * reps.len() + l] +=
                    (prob.w_d[p] * prob.rho(prob.work.disparity[p] - prob.at(r, p))) as f64;
            }
        }
    }
    (0..n_inst)
        .map(|i| {
            (0..reps.len())
                .min_by(|&a, &b| cost[i * reps.len() + a].total_cmp(&cost[i * reps.len() + b]))
                .unwrap_or(0)
        })
        .collect()
}

fn total_energy(prob: &Problem, lab: &[u8], reps: &[Plane], inst_label: &[usize]) -> f64 {
    let w = prob.work.width;
    let mut e = 0f64;
    // Row by row, so that the right neighbour needs no division to exist.
    for (y, row) in lab.chunks_exact(w).enumerate() {
        for (x, &l) in row.iter().enumerate() {
            let p = y * w + x;
            e += prob.unary(p, &reps[l as usize], l as usize, inst_label) as f64;
            if x + 1 < w && row[x + 1] != l {
                e += prob.right[p] as f64;
            }
            if p + w < lab.len() && lab[p + w] != l {
                e += prob.down[p] as f64;
            }
        }
    }
    e
}

/// One alpha-expansion move: every pixel keeps its label or switches to `alpha`, whichever
/// set of switches minimises the energy (an exact binary graph cut, Potts being a metric).
fn expand(
    prob: &Problem,
    lab: &[u8],
    alpha: usize,
    reps: &[Plane],
    inst_label: &[usize],
) -> (Vec<u8>, f64) {
    let (w, n) = (prob.work.width, lab.len());
    let mut g = Graph::new(n, 2 * n);
    // Unary energies for x = 0 (keep) and x = 1 (switch), plus pairwise decompositions.
    let mut e1 = vec![0f32; n];
    let mut e0 = vec![0f32; n];
    for p in 0..n {
        let l = lab[p] as usize;
        e0[p] = prob.unary(p, &reps[l], l, inst_label);
        e1[p] = if l == alpha {
            e0[p]
        } else {
            prob.unary(p, &reps[alpha], alpha, inst_label)
        };
    }
    let a8 = alpha as u8;
    let add_pair = |g: &mut Graph, e1: &mut [f32], p: usize, q: usize, wt: f32| {
        if wt <= 0.0 {
            return;
        }
        let v = |a: u8, b: u8| if a != b { wt } else { 0.0 };
        let (a, b, c, d) = (v(lab[p], lab[q]), v(lab[p], a8), v(a8, lab[q]), 0.0);
        // E(x_p, x_q) = A + (C - A) x_p + (D - C) x_q + (B + C - A - D) (1 - x_p) x_q; the
        // constant A does not change the cut. With x = 1 on the sink side, the edge p -> q
        // is cut exactly when x_p = 0 and x_q = 1.
        e1[p] += c - a;
        e1[q] += d - c;
        g.add_edge(p, q, (b + c - a - d).max(0.0), 0.0);
    };
    for y in 0..n / w {
        for x in 0..w {
            let p = y * w + x;
            if x + 1 < w {
                add_pair(&mut g, &mut e1, p, p + 1, prob.right[p]);
            }
            if p + w < n {
                add_pair(&mut g, &mut e1, p, p + w, prob.down[p]);
            }
        }
    }
    for p in 0..n {
        // The source link is cut when x = 1, the sink link when x = 0.
        g.add_tweights(p, e1[p], e0[p]);
    }
    g.maxflow();
    let next: Vec<u8> = (0..n)
        .map(|p| if g.sink_side(p) { a8 } else { lab[p] })
        .collect();
    let e = total_energy(prob, &next, reps, inst_label);
    (next, e)
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::cues::{InstanceSource, Instances};

    fn work(w: usize, h: usize, seed: u64) -> Work {
        let mut lcg = crate::lcg::Lcg(seed);
        let mut rnd = move || lcg.unit();
        let n = w * h;
        Work {
            width: w,
            height: h,
            rgb: (0..n * 3).map(|_| rnd()).collect(),
            disparity: (0..n).map(|_| rnd()).collect(),
            confidence: (0..n).map(|_| rnd()).collect(),
            saliency: (0..n).map(|_| rnd()).collect(),
            instances: Instances {
                ids: (0..n).map(|_| (rnd() * 3.0) as u32).collect(),
                confidence: vec![0.9, 0.5],
                source: InstanceSource::DepthComponents,
            },
        }
    }

    fn problem(work: &Work) -> Problem<'_> {
        let n = work.width * work.height;
        Problem {
            work,
            cfg: FusionConfig::default(),
            right: (0..n).map(|p| 0.3 + (p % 5) as f32 * 0.4).collect(),
            down: (0..n).map(|p| 0.2 + (p % 3) as f32 * 0.7).collect(),
            w_d: work.confidence.clone(),
            w_s: work.saliency.clone(),
            uv: (0..n)
                .map(|p| centred(p, work.width, work.height))
                .collect(),
        }
    }

    #[test]
    fn expansion_move_is_the_best_binary_move() {
        for seed in 0..20 {
            let wk = work(4, 3, seed);
            let prob = problem(&wk);
            // Flat and slanted representatives.
            let reps = [
                Plane::flat(0.8),
                Plane {
                    a: 0.3,
                    b: -0.2,
                    c: 0.5,
                },
                Plane::flat(0.1),
            ];
            let inst = [0usize, 2];
            let lab: Vec<u8> = (0..12)
                .map(|p| ((p * 7 + seed as usize) % 3) as u8)
                .collect();
            for alpha in 0..3 {
                let (_, e) = expand(&prob, &lab, alpha, &reps, &inst);
                let mut best = f64::INFINITY;
                for m in 0..1u32 << 12 {
                    let cand: Vec<u8> = (0..12)
                        .map(|p| if m >> p & 1 == 1 { alpha as u8 } else { lab[p] })
                        .collect();
                    best = best.min(total_energy(&prob, &cand, &reps, &inst));
                }
                assert!(
                    (e - best).abs() < 1e-3,
                    "seed {seed} alpha {alpha}: {e} vs {best}"
                );
            }
        }
    }

    #[test]
    fn fusion_lowers_energy_and_orders_labels() {
        let wk = work(24, 16, 3);
        let f = fuse(&wk, 4, &FusionConfig::default(), false);
        assert!(f.representatives.windows(2).all(|r| r[0] > r[1]));
        assert!(f
            .labels
            .iter()
            .all(|&l| (l as usize) < f.representatives.len()));
        assert!(f.energy.iter().all(|e| e.is_finite()));
        let g = fuse(&wk, 4, &FusionConfig::default(), true);
        assert!(g.representatives.windows(2).all(|r| r[0] > r[1]));
        assert!(g.energy.iter().all(|e| e.is_finite()));
    }

    /// A floor whose inverse depth falls from 0.9 at the bottom to 0.1 at the top, with a box
    /// standing on it (inverse depth 0.7, nearer than the floor around it), in two labels:
    /// flat representatives cut the floor into two slabs (one shared with the box), slanted
    /// ones give the floor one label and the box the other.
    #[test]
    fn slanted_labels_keep_a_floor_whole() {
        let (w, h) = (40, 30);
        let n = w * h;
        let inside = |p: usize| (14..26).contains(&(p % w)) && (4..12).contains(&(p / w));
        let floor = |p: usize| 0.1 + 0.8 * (p / w) as f32 / (h - 1) as f32;
        let wk = Work {
            width: w,
            height: h,
            rgb: (0..n)
                .flat_map(|p| if inside(p) { [0.9f32; 3] } else { [0.3; 3] })
                .collect(),
            disparity: (0..n)
                .map(|p| if inside(p) { 0.7 } else { floor(p) })
                .collect(),
            confidence: vec![1.0; n],
            saliency: vec![0.0; n],
            instances: Instances {
                ids: vec![0; n],
                confidence: vec![],
                source: InstanceSource::DepthComponents,
            },
        };
        let labels_of_floor = |f: &Fusion| {
            let mut seen: Vec<u8> = (0..n)
                .filter(|&p| !inside(p))
                .map(|p| f.labels[p])
                .collect();
            seen.sort_unstable();
            seen.dedup();
            seen
        };
        let flat = fuse(&wk, 2, &FusionConfig::default(), false);
        assert_eq!(labels_of_floor(&flat).len(), 2);
        let slanted = fuse(&wk, 2, &FusionConfig::default(), true);
        let on_floor = labels_of_floor(&slanted);
        assert_eq!(on_floor.len(), 1, "the floor in labels {on_floor:?}");
        assert!((0..n)
            .filter(|&p| inside(p))
            .all(|p| slanted.labels[p] != on_floor[0]));
        // The box is nearer than the floor at its centroid, so it comes first.
        assert_eq!(on_floor[0], 1);
    }
}
