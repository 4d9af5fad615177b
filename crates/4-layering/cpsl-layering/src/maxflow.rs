//! Boykov-Kolmogorov max-flow / min-cut (Boykov & Kolmogorov, PAMI 2004): two search trees
//! grown from the terminals, augmenting along the paths where they meet, and adoption of
//! orphaned nodes. Fast on the sparse grid graphs of alpha-expansion.

use std::collections::VecDeque;

const NONE: u32 = u32::MAX;
const TERMINAL: u32 = u32::MAX - 1;
const ORPHAN: u32 = u32::MAX - 2;
const FREE: u8 = 0;
const SOURCE: u8 = 1;
const SINK: u8 = 2;

/// A graph with non-negative edge capacities and terminal links. Node `p`'s terminal
/// capacity is kept as one signed residual: positive from the source, negative to the sink.
#[derive(Debug, Clone)]
pub struct Graph {
    tr_cap: Vec<f32>,
    first: Vec<u32>,
    parent: Vec<u32>,
    tree: Vec<u8>,
    ts: Vec<u32>,
    dist: Vec<u32>,
    active: Vec<bool>,
    // Arcs in sister pairs (2i, 2i + 1).
    head: Vec<u32>,
    next: Vec<u32>,
    r_cap: Vec<f32>,
    flow: f64,
}

impl Graph {
    /// A graph of `nodes` nodes without edges; `edges_hint` reserves space for that many edges.
    pub fn new(nodes: usize, edges_hint: usize) -> Self {
        Self {
            tr_cap: vec![0.0; nodes],
            first: vec![NONE; nodes],
            parent: vec![NONE; nodes],
            tree: vec![FREE; nodes],
            ts: vec![0; nodes],
            dist: vec![0; nodes],
            active: vec![false; nodes],
            head: Vec::with_capacity(2 * edges_hint),
            next: Vec::with_capacity(2 * edges_hint),
            r_cap: Vec::with_capacity(2 * edges_hint),
            flow: 0.0,
        }
    }

    /// Adds the cost `source_cost` for `p` ending on the sink side and `sink_cost` for it
    /// ending on the source side (either may be negative: only the difference matters, the
    /// rest is a constant added to the flow).
    pub fn add_tweights(&mut self, p: usize, source_cost: f32, sink_cost: f32) {
        let (mut cs, mut ct) = (source_cost, sink_cost);
        let d = self.tr_cap[p];
        if d > 0.0 {
            cs += d;
        } else {
            ct -= d;
        }
        self.flow += cs.min(ct) as f64;
        self.tr_cap[p] = cs - ct;
    }

    /// Adds an edge `p -> q` with capacity `cap` and `q -> p` with `rev_cap` (both >= 0).
    pub fn add_edge(&mut self, p: usize, q: usize, cap: f32, rev_cap: f32) {
        debug_assert!(cap >= 0.0 && rev_cap >= 0.0 && p != q);
        let a = self.head.len() as u32;
        self.head.extend([q as u32, p as u32]);
        self.next.extend([self.first[p], self.first[q]]);
        self.r_cap.extend([cap, rev_cap]);
        self.first[p] = a;
        self.first[q] = a + 1;
    }

    /// Computes the maximum flow (= the minimum cut's cost plus the constants of
    /// [`Graph::add_tweights`]). Afterwards [`Graph::sink_side`] gives the cut.
    pub fn maxflow(&mut self) -> f64 {
        let n = self.tr_cap.len();
        let mut queue = VecDeque::new();
        for p in 0..n {
            let c = self.tr_cap[p];
            if c != 0.0 {
                self.tree[p] = if c > 0.0 { SOURCE } else { SINK };
                self.parent[p] = TERMINAL;
                self.dist[p] = 1;
                self.active[p] = true;
                queue.push_back(p as u32);
            }
        }
        let mut time = 0u32;
        let mut orphans: VecDeque<u32> = VecDeque::new();
        while let Some(p) = queue.pop_front() {
            let p = p as usize;
            self.active[p] = false;
            if self.parent[p] == NONE {
                continue;
            }
            // Grow the tree of p; stop at an arc into the other tree.
            let mut meet = NONE;
            let mut a = self.first[p];
            while a != NONE {
                let ai = a as usize;
                let q = self.head[ai] as usize;
                let (open, into) = if self.tree[p] == SOURCE {
                    (self.r_cap[ai] > 0.0, SINK)
                } else {
                    (self.r_cap[ai ^ 1] > 0.0, SOURCE)
                };
                if open {
                    if self.parent[q] == NONE {
                        self.tree[q] = self.tree[p];
                        self.parent[q] = a ^ 1;
                        self.ts[q] = self.ts[p];
                        self.dist[q] = self.dist[p] + 1;
                        if !self.active[q] {
                            self.active[q] = true;
                            queue.push_back(q as u32);
                        }
                    } else if self.tree[q] == into {
                        meet = if self.tree[p] == SOURCE { a } else { a ^ 1 };
                        break;
                    } else if self.ts[q] <= self.ts[p] && self.dist[q] > self.dist[p] {
                        // A shorter path to the terminal through p.
                        self.parent[q] = a ^ 1;
                        self.ts[q] = self.ts[p];
                        self.dist[q] = self.dist[p] + 1;
                    }
                }
                a = self.next[ai];
            }
            if meet == NONE {
                continue;
            }
            // p may have more arcs into the other tree.
            self.active[p] = true;
            queue.push_front(p as u32);
            time += 1;
            self.augment(meet as usize, &mut orphans);
            while let Some(o) = orphans.pop_front() {
                self.adopt(o as usize, time, &mut queue, &mut orphans);
            }
        }
        self.flow
    }

    fn augment(&mut self, middle: usize, orphans: &mut VecDeque<u32>) {
        let mut b = self.r_cap[middle];
        // Source side: from the arc's tail up to the source.
        let mut x = self.head[middle ^ 1] as usize;
        while self.parent[x] != TERMINAL {
            let pa = self.parent[x] as usize;
            b = b.min(self.r_cap[pa ^ 1]);
            x = self.head[pa] as usize;
        }
        b = b.min(self.tr_cap[x]);
        // Sink side.
        let mut x = self.head[middle] as usize;
        while self.parent[x] != TERMINAL {
            let pa = self.parent[x] as usize;
            b = b.min(self.r_cap[pa]);
            x = self.head[pa] as usize;
        }
        b = b.min(-self.tr_cap[x]);

        self.r_cap[middle] -= b;
        self.r_cap[middle ^ 1] += b;
        let mut x = self.head[middle ^ 1] as usize;
        while self.parent[x] != TERMINAL {
            let pa = self.parent[x] as usize;
            self.r_cap[pa] += b;
            self.r_cap[pa ^ 1] -= b;
            if self.r_cap[pa ^ 1] <= 0.0 {
                self.parent[x] = ORPHAN;
                orphans.push_front(x as u32);
            }
            x = self.head[pa] as usize;
        }
        self.tr_cap[x] -= b;
        if self.tr_cap[x] <= 0.0 {
            self.parent[x] = ORPHAN;
            orphans.push_front(x as u32);
        }
        let mut x = self.head[middle] as usize;
        while self.parent[x] != TERMINAL {
            let pa = self.parent[x] as usize;
            self.r_cap[pa ^ 1] += b;
            self.r_cap[pa] -= b;
            if self.r_cap[pa] <= 0.0 {
                self.parent[x] = ORPHAN;
                orphans.push_front(x as u32);
            }
            x = self.head[pa] as usize;
        }
        self.tr_cap[x] += b;
        if self.tr_cap[x] >= 0.0 {
            self.parent[x] = ORPHAN;
            orphans.push_front(x as u32);
        }
        self.flow += b as f64;
    }

    fn adopt(
        &mut self,
        p: usize,
        time: u32,
        queue: &mut VecDeque<u32>,
        orphans: &mut VecDeque<u32>,
    ) {
        let source = self.tree[p] == SOURCE;
        let mut best = NONE;
        let mut dmin = u32::MAX;
        let mut a = self.first[p];
        while a != NONE {
            let ai = a as usize;
            let q = self.head[ai] as usize;
            let open = if source {
                self.r_cap[ai ^ 1] > 0.0
            } else {
                self.r_cap[ai] > 0.0
            };
            if open && self.tree[q] == self.tree[p] && self.parent[q] != NONE {
                // Does q's path reach the terminal?
                let mut d = 0u32;
                let mut j = q;
                let reaches = loop {
                    if self.ts[j] == time {
                        d += self.dist[j];
                        break true;
                    }
                    let pj = self.parent[j];
                    d += 1;
                    if pj == TERMINAL {
                        self.ts[j] = time;
                        self.dist[j] = 1;
                        break true;
                    }
                    if pj == ORPHAN {
                        break false;
                    }
                    j = self.head[pj as usize] as usize;
                };
                if reaches {
                    if d < dmin {
                        best = a;
                        dmin = d;
                    }
                    // Mark the path with distances for later searches.
                    let mut j = q;
                    while self.ts[j] != time {
                        self.ts[j] = time;
                        self.dist[j] = d;
                        d -= 1;
                        j = self.head[self.parent[j] as usize] as usize;
                    }
                }
            }
            a = self.next[ai];
        }
        if best != NONE {
            self.parent[p] = best;
            self.ts[p] = time;
            self.dist[p] = dmin + 1;
            return;
        }
        // No parent: p becomes free; its children become orphans, its neighbours active.
        let mut a = self.first[p];
        while a != NONE {
            let ai = a as usize;
            let q = self.head[ai] as usize;
            let pq = self.parent[q];
            if self.tree[q] == self.tree[p] && pq != NONE {
                let open = if source {
                    self.r_cap[ai ^ 1] > 0.0
                } else {
                    self.r_cap[ai] > 0.0
                };
                if open && !self.active[q] {
                    self.active[q] = true;
                    queue.push_back(q as u32);
                }
                if pq != TERMINAL && pq != ORPHAN && self.head[pq as usize] as usize == p {
                    self.parent[q] = ORPHAN;
                    orphans.push_back(q as u32);
                }
            }
            a = self.next[ai];
        }
        self.parent[p] = NONE;
        self.tree[p] = FREE;
    }

    /// After [`Graph::maxflow`]: whether `p` is on the sink side of the minimum cut (free
    /// nodes count as source side).
    pub fn sink_side(&self, p: usize) -> bool {
        self.tree[p] == SINK && self.parent[p] != NONE
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    use crate::lcg::Lcg;

    #[test]
    fn matches_brute_force_min_cut_on_random_graphs() {
        let mut r = Lcg(7);
        for case in 0..300 {
            let n = 2 + case % 9;
            let mut g = Graph::new(n, 16);
            let mut tw = vec![(0f32, 0f32); n];
            for (p, t) in tw.iter_mut().enumerate() {
                // Integer-valued costs keep float sums exact; some negative.
                *t = (
                    (r.unit() * 10.0).floor() - 3.0,
                    (r.unit() * 10.0).floor() - 3.0,
                );
                g.add_tweights(p, t.0, t.1);
            }
            let mut edges = Vec::new();
            for _ in 0..(n * 2) {
                let p = (r.unit() * n as f32) as usize % n;
                let q = (r.unit() * n as f32) as usize % n;
                if p == q {
                    continue;
                }
                let (c, rc) = ((r.unit() * 6.0).floor(), (r.unit() * 6.0).floor());
                g.add_edge(p, q, c, rc);
                edges.push((p, q, c, rc));
            }
            let flow = g.maxflow();
            // Brute force: x_p = 1 means sink side.
            let cost = |x: &dyn Fn(usize) -> bool| -> f64 {
                let mut e = 0.0;
                for (p, &(cs, ct)) in tw.iter().enumerate() {
                    e += if x(p) { cs } else { ct } as f64;
                }
                for &(p, q, c, rc) in &edges {
                    if !x(p) && x(q) {
                        e += c as f64;
                    }
                    if x(p) && !x(q) {
                        e += rc as f64;
                    }
                }
                e
            };
            let best = (0..1u32 << n)
                .map(|m| cost(&|p| m >> p & 1 == 1))
                .fold(f64::INFINITY, f64::min);
            assert!(
                (flow - best).abs() < 1e-6,
                "case {case}: flow {flow}, min cut {best}"
            );
            let found = cost(&|p| g.sink_side(p));
            assert!(
                (found - best).abs() < 1e-6,
                "case {case}: cut {found}, min {best}"
            );
        }
    }
}
