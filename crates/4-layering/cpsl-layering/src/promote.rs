//! Instance promotion and background merging: the fused label map becomes at most `K`
//! depth-ordered layers. Salient regions that stand in front of their surroundings get
//! dedicated layers, as long as each promotion raises the plan's inverse-depth error by at most
//! a tolerance (a promoted region takes a layer from the background); the rest is grouped by
//! label and neighbouring groups (in depth order) are merged by depth and texture statistics
//! until the target count is met.

use crate::cues::{luma, Work};
use crate::fuse::{centred, Fusion};
use crate::grid::components;
use serde::{Deserialize, Serialize};

/// Configuration of promotion and merging.
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields, default)]
pub struct PromoteConfig {
    /// Most promoted instances (at most `K - 1` in any case).
    pub max_promoted: usize,
    /// Smallest promoted region, as a fraction of the image.
    pub min_area: f32,
    /// Largest promoted region, as a fraction of the image.
    pub max_area: f32,
    /// Promotion score threshold (mean saliency x instance support x size).
    pub threshold: f32,
    /// How much nearer (normalised inverse depth) than its surrounding ring a promoted
    /// region must be.
    pub min_standout: f32,
    /// Largest inverse-depth spread (10th to 90th percentile, normalised) of a promoted
    /// region: one plane must represent it well.
    pub max_spread: f32,
    /// How much more depth-fit error (relative) a promotion may cost. A promoted region takes
    /// a layer from the background, so candidates (best score first) are promoted only if the
    /// squared inverse-depth error of the whole plan grows by at most this fraction; 0
    /// promotes only where that improves the depth fit, a large value (1e9) always promotes.
    pub cost_tolerance: f32,
}

impl Default for PromoteConfig {
    fn default() -> Self {
        Self {
            max_promoted: 3,
            min_area: 0.002,
            max_area: 0.35,
            threshold: 0.25,
            min_standout: 0.03,
            max_spread: 0.05,
            cost_tolerance: 0.15,
        }
    }
}

/// What a final layer is.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Kind {
    /// A promoted region.
    Promoted,
    /// A (possibly merged) background group.
    Background,
}

/// One final layer at working resolution.
#[derive(Debug, Clone, PartialEq)]
pub struct Planned {
    /// Kind.
    pub kind: Kind,
    /// Representative normalised inverse depth.
    pub disparity: f32,
    /// Mean saliency of its pixels.
    pub saliency: f32,
    /// Its promotion score (0 for background groups).
    pub score: f32,
}

/// The plan: a final layer per working pixel, layers nearest first.
#[derive(Debug, Clone, PartialEq)]
pub struct Plan {
    /// Final layer index per working pixel.
    pub owner: Vec<u8>,
    /// The layers, nearest first.
    pub layers: Vec<Planned>,
}

#[derive(Debug, Clone, Default)]
struct Stats {
    n: f64,
    disp: f64,
    disp2: f64,
    sal: f64,
    luma: f64,
    luma2: f64,
    /// Moments of the position (`u`, `v`: [`centred`]) for the plane fit: sums of u, v, u^2,
    /// uv, v^2, u d and v d.
    plane: [f64; 7],
}

impl Stats {
    fn add(&mut self, o: &Stats) {
        self.n += o.n;
        self.disp += o.disp;
        self.disp2 += o.disp2;
        self.sal += o.sal;
        self.luma += o.luma;
        self.luma2 += o.luma2;
        for (a, b) in self.plane.iter_mut().zip(o.plane) {
            *a += b;
        }
    }
    fn mean(&self, v: f64) -> f64 {
        v / self.n.max(1.0)
    }
    /// Sum of squared inverse-depth deviations from the mean.
    fn sse(&self) -> f64 {
        (self.disp2 - self.disp * self.disp / self.n.max(1.0)).max(0.0)
    }
    /// Sum of squared inverse-depth deviations from the least-squares plane (`c + a u + b
    /// v`); the flat [`Stats::sse`] where the pixels fix no plane.
    fn sse_plane(&self) -> f64 {
        let [u, v, uu, uv, vv, ud, vd] = self.plane;
        let m = cpsl_core::Mat3([[uu, uv, u], [uv, vv, v], [u, v, self.n]]);
        let r = cpsl_core::Vec3([ud, vd, self.disp]);
        match m.inverse().map(|i| i * r) {
            Some(beta) if self.n >= 3.0 && beta.is_finite() => {
                (self.disp2 - beta.dot(r)).clamp(0.0, self.sse())
            }
            _ => self.sse(),
        }
    }

    /// The depth-fit error: [`Stats::sse_plane`] with slanted labels, else [`Stats::sse`].
    fn error(&self, slanted: bool) -> f64 {
        if slanted {
            self.sse_plane()
        } else {
            self.sse()
        }
    }

    fn luma_sd(&self) -> f64 {
        (self.mean(self.luma2) - self.mean(self.luma).powi(2))
            .max(0.0)
            .sqrt()
    }
}

/// Promotion candidates, best score first: regions (per region its statistics, its ring of
/// neighbouring pixels and its summed instance confidence) of moderate area that stand out
/// in front of their surroundings, are compact in depth and salient enough; at most
/// `cfg.max_promoted`, and at most half of the `k` layers.
fn candidates(
    disparity: &[f32],
    region: &[u32],
    (rs, ring, inst): (&[Stats], &[Stats], &[f64]),
    k: usize,
    cfg: &PromoteConfig,
) -> Vec<(usize, f32)> {
    let n = region.len();
    let mut cand: Vec<(usize, f32)> = Vec::new();
    for r in 0..rs.len() {
        let area = (rs[r].n / n as f64) as f32;
        if area < cfg.min_area || area > cfg.max_area || ring[r].n == 0.0 {
            continue;
        }
        let standout = (rs[r].mean(rs[r].disp) - ring[r].mean(ring[r].disp)) as f32;
        if standout < cfg.min_standout {
            continue;
        }
        let mut d: Vec<f32> = (0..n)
            .filter(|&p| region[p] as usize == r)
            .map(|p| disparity[p])
            .collect();
        d.sort_by(f32::total_cmp);
        if d[d.len() * 9 / 10] - d[d.len() / 10] > cfg.max_spread {
            continue;
        }
        let support = (inst[r] / rs[r].n) as f32;
        let size = (area / 0.02).min(1.0).sqrt();
        let score = rs[r].mean(rs[r].sal) as f32 * (0.5 + 0.5 * support) * size;
        if score >= cfg.threshold {
            cand.push((r, score));
        }
    }
    cand.sort_by(|a, b| b.1.total_cmp(&a.1));
    // At least half the layers stay for the background depth range.
    cand.truncate(cfg.max_promoted.min(k.saturating_sub(1) / 2));
    cand
}

/// Promotes salient regions and merges the background to at most `k` layers.
pub fn promote(work: &Work, fusion: &Fusion, k: usize, cfg: &PromoteConfig) -> Plan {
    let (w, h) = (work.width, work.height);
    let n = w * h;
    let lab = &fusion.labels;
    let y = luma(&work.rgb);
    let slanted = fusion.slanted;
    let px = |p: usize| {
        let d = work.disparity[p] as f64;
        let (u, v) = centred(p, w, h);
        let (u, v) = (u as f64, v as f64);
        Stats {
            n: 1.0,
            disp: d,
            disp2: d * d,
            sal: work.saliency[p] as f64,
            luma: y[p] as f64,
            luma2: (y[p] * y[p]) as f64,
            plane: [u, v, u * u, u * v, v * v, u * d, v * d],
        }
    };

    // Regions: connected components of equal label and instance (instance boundaries split
    // regions even where depth is continuous, e.g. a pole standing on the floor).
    let ids = &work.instances.ids;
    let (region, nr) = components(w, h, |p, q| lab[p] == lab[q] && ids[p] == ids[q]);
    let mut rs = vec![Stats::default(); nr];
    let mut ring = vec![Stats::default(); nr];
    let mut inst = vec![0f64; nr];
    for p in 0..n {
        let r = region[p] as usize;
        rs[r].add(&px(p));
        let id = ids[p] as usize;
        if id > 0 {
            inst[r] += work.instances.confidence[id - 1] as f64;
        }
        // The ring: neighbours in other regions.
        let (x, yy) = (p % w, p / w);
        for q in [
            (x > 0).then(|| p - 1),
            (x + 1 < w).then(|| p + 1),
            (yy > 0).then(|| p - w),
            (yy + 1 < h).then(|| p + w),
        ]
        .into_iter()
        .flatten()
        {
            if region[q] as usize != r {
                ring[r].add(&px(q));
            }
        }
    }

    let cand = candidates(&work.disparity, &region, (&rs, &ring, &inst), k, cfg);

    // Candidates are taken best score first; each is promoted only if the plan's depth-fit
    // error stays within the tolerance of the plan without it.
    let nl = fusion.representatives.len();
    let plan_for = |chosen: &[(usize, f32)]| -> (Vec<(Vec<usize>, Stats)>, f64) {
        let mut promoted = vec![false; nr];
        for &(r, _) in chosen {
            promoted[r] = true;
        }
        let mut gs = vec![Stats::default(); nl];
        for p in 0..n {
            if !promoted[region[p] as usize] {
                gs[lab[p] as usize].add(&px(p));
            }
        }
        let groups = merge(gs, k.saturating_sub(chosen.len()).max(1), slanted);
        let sse = groups.iter().map(|g| g.1.error(slanted)).sum::<f64>()
            + chosen
                .iter()
                .map(|&(r, _)| rs[r].error(slanted))
                .sum::<f64>();
        (groups, sse)
    };
    let mut chosen = Vec::new();
    let (mut groups, mut sse) = plan_for(&chosen);
    for &c in &cand {
        chosen.push(c);
        let (g, s) = plan_for(&chosen);
        if s <= sse * (1.0 + cfg.cost_tolerance as f64) {
            (groups, sse) = (g, s);
        } else {
            chosen.pop();
        }
    }
    let cand = chosen;
    let mut promoted_of = vec![usize::MAX; nr];
    for (i, &(r, _)) in cand.iter().enumerate() {
        promoted_of[r] = i;
    }
    let mut group_of = vec![0usize; nl];
    for (g, (labels, _)) in groups.iter().enumerate() {
        for &l in labels {
            group_of[l] = g;
        }
    }

    // Final layers: promoted regions at their median inverse depth, groups at the weighted
    // median of their pixels.
    let median = |mut v: Vec<f32>| -> f32 {
        if v.is_empty() {
            return 0.0;
        }
        let m = v.len() / 2;
        *v.select_nth_unstable_by(m, f32::total_cmp).1
    };
    let mut pix: Vec<Vec<f32>> = vec![Vec::new(); cand.len() + groups.len()];
    let slot = |p: usize| {
        let r = region[p] as usize;
        if promoted_of[r] != usize::MAX {
            promoted_of[r]
        } else {
            cand.len() + group_of[lab[p] as usize]
        }
    };
    for p in 0..n {
        pix[slot(p)].push(work.disparity[p]);
    }
    let mut planned: Vec<Planned> = Vec::new();
    for (i, &(r, score)) in cand.iter().enumerate() {
        planned.push(Planned {
            kind: Kind::Promoted,
            disparity: median(std::mem::take(&mut pix[i])),
            saliency: rs[r].mean(rs[r].sal) as f32,
            score,
        });
    }
    for (g, (_, st)) in groups.iter().enumerate() {
        planned.push(Planned {
            kind: Kind::Background,
            disparity: median(std::mem::take(&mut pix[cand.len() + g])),
            saliency: st.mean(st.sal) as f32,
            score: 0.0,
        });
    }
    let mut order: Vec<usize> = (0..planned.len()).collect();
    order.sort_by(|&a, &b| planned[b].disparity.total_cmp(&planned[a].disparity));
    let mut rank = vec![0u8; planned.len()];
    for (r, &i) in order.iter().enumerate() {
        rank[i] = r as u8;
    }
    Plan {
        owner: (0..n).map(|p| rank[slot(p)]).collect(),
        layers: order.iter().map(|&i| planned[i].clone()).collect(),
    }
}

/// Groups the labels' statistics (nearest first; empty labels dropped) into at most `target`
/// runs of neighbouring labels, merging the cheapest neighbouring pair first: Ward cost in
/// inverse depth (with `slanted`, the growth of the plane fit's error instead), scaled by
/// texture dissimilarity.
fn merge(gs: Vec<Stats>, target: usize, slanted: bool) -> Vec<(Vec<usize>, Stats)> {
    let mut groups: Vec<(Vec<usize>, Stats)> = gs
        .into_iter()
        .enumerate()
        .filter(|(_, g)| g.n > 0.0)
        .map(|(l, g)| (vec![l], g))
        .collect();
    let cost = |a: &Stats, b: &Stats| {
        let tex = (a.mean(a.luma) - b.mean(b.luma)).abs() + (a.luma_sd() - b.luma_sd()).abs();
        let growth = if slanted {
            let mut both = a.clone();
            both.add(b);
            (both.sse_plane() - a.sse_plane() - b.sse_plane()).max(0.0)
        } else {
            let dd = a.mean(a.disp) - b.mean(b.disp);
            dd * dd * a.n * b.n / (a.n + b.n)
        };
        growth * (1.0 + 2.0 * tex)
    };
    while groups.len() > target {
        let i = (0..groups.len() - 1)
            .min_by(|&i, &j| {
                cost(&groups[i].1, &groups[i + 1].1)
                    .total_cmp(&cost(&groups[j].1, &groups[j + 1].1))
            })
            .unwrap_or(0);
        let (labels, stats) = groups.remove(i + 1);
        groups[i].0.extend(labels);
        groups[i].1.add(&stats);
    }
    groups
}

#[cfg(test)]
mod tests {
    use super::{merge, Stats};

    /// The statistics of pixels `(u, v, d)` of one grey.
    fn stats(pixels: impl Iterator<Item = (f64, f64, f64)>) -> Stats {
        let mut s = Stats::default();
        for (u, v, d) in pixels {
            s.add(&Stats {
                n: 1.0,
                disp: d,
                disp2: d * d,
                sal: 0.0,
                luma: 0.5,
                luma2: 0.25,
                plane: [u, v, u * u, u * v, v * v, u * d, v * d],
            });
        }
        s
    }

    /// A floor (inverse depth 0.5 + 0.8 v) in two labels, its near and its far half, and a
    /// small far wall: merged to two layers, the flat cost joins the floor's far half to the
    /// wall (the nearer means), the plane fit's cost joins the floor's halves (one plane
    /// holds both exactly).
    #[test]
    fn slanted_merging_keeps_a_floor_together() {
        let grid = |v0: f64, v1: f64| {
            (0..20).flat_map(move |i| {
                (0..10).map(move |j| (i as f64 / 20.0 - 0.5, v0 + (v1 - v0) * j as f64 / 10.0))
            })
        };
        let near = stats(grid(0.0, 0.5).map(|(u, v)| (u, v, 0.5 + 0.8 * v)));
        let far = stats(grid(-0.5, 0.0).map(|(u, v)| (u, v, 0.5 + 0.8 * v)));
        let wall = stats(grid(-0.5, -0.45).map(|(u, v)| (u, v, 0.05)));
        assert!(near.sse_plane() < 1e-9 && far.sse_plane() < 1e-9);
        let labels = |slanted| -> Vec<Vec<usize>> {
            merge(vec![near.clone(), far.clone(), wall.clone()], 2, slanted)
                .into_iter()
                .map(|g| g.0)
                .collect()
        };
        assert_eq!(labels(false), vec![vec![0], vec![1, 2]]);
        assert_eq!(labels(true), vec![vec![0, 1], vec![2]]);
    }
}
