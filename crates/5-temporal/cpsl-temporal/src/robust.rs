//! A layer's motion from the flow of its interior, made robust. Flow measured near a motion
//! boundary mixes the motions of both sides, and such vectors, carried frame after frame,
//! make a layer's boundary drift. So each vector is compared with the median vector of its
//! neighbourhood among the layer's own vectors and loses its weight when it disagrees
//! ([`local_inliers`]); the layer's motion outside its interior follows an affine model of the
//! vectors kept ([`Affine::fit`]) plus their filled-in residual.

/// `u = a[0] + a[1] x + a[2] y`, `v = a[3] + a[4] x + a[5] y`, with `x, y` grid coordinates
/// relative to the grid's centre, divided by its width.
#[derive(Debug, Clone, Copy, PartialEq)]
pub(crate) struct Affine {
    a: [f64; 6],
    centre: (f64, f64),
    scale: f64,
}

/// Smallest robust scale of the distances to the local median, in grid pixels.
const MIN_SIGMA: f32 = 0.05;
/// Vectors further than this many robust standard deviations from their neighbourhood's
/// median get no weight (Tukey's biweight).
const REJECT: f32 = 2.5;
/// Fewest samples for the affine terms; below it the model is the translation.
const MIN_AFFINE: f64 = 32.0;

impl Affine {
    /// The weighted least-squares affine model of the vectors of `flow` (2 interleaved values
    /// per pixel of a `gw x gh` grid) with positive `weight`; a translation where they are
    /// too few or collinear. `None` without any.
    pub(crate) fn fit(flow: &[f32], weight: &[f32], gw: usize, gh: usize) -> Option<Self> {
        let mut model = Self {
            a: [0.0; 6],
            centre: (gw as f64 / 2.0, gh as f64 / 2.0),
            scale: 1.0 / gw as f64,
        };
        // Weighted sums of 1, x, y, xx, xy, yy and of u, v times 1, x, y (per row, in f32).
        let mut sums = [0f64; 12];
        for (y, (wr, fr)) in weight.chunks(gw).zip(flow.chunks(gw * 2)).enumerate() {
            let mut row = [0f32; 12];
            let (_, yn) = model.coords(0, y);
            let yn = yn as f32;
            for (x, (&w, uv)) in wr.iter().zip(fr.chunks_exact(2)).enumerate() {
                if w <= 0.0 {
                    continue;
                }
                let xn = (x as f64 - model.centre.0) as f32 * model.scale as f32;
                let (wx, wy) = (w * xn, w * yn);
                let terms = [w, wx, wy, wx * xn, wx * yn, wy * yn];
                for (r, t) in row.iter_mut().zip(terms) {
                    *r += t;
                }
                for (c, v) in [uv[0], uv[1]].into_iter().enumerate() {
                    row[6 + c * 3] += w * v;
                    row[7 + c * 3] += wx * v;
                    row[8 + c * 3] += wy * v;
                }
            }
            for (s, r) in sums.iter_mut().zip(row) {
                *s += r as f64;
            }
        }
        let m = [
            [sums[0], sums[1], sums[2]],
            [sums[1], sums[3], sums[4]],
            [sums[2], sums[4], sums[5]],
        ];
        let (bu, bv) = ([sums[6], sums[7], sums[8]], [sums[9], sums[10], sums[11]]);
        if m[0][0] <= 0.0 {
            return None;
        }
        model.a = match (m[0][0] >= MIN_AFFINE, solve3(m, bu), solve3(m, bv)) {
            (true, Some(u), Some(v)) => [u[0], u[1], u[2], v[0], v[1], v[2]],
            _ => [bu[0] / m[0][0], 0.0, 0.0, bv[0] / m[0][0], 0.0, 0.0],
        };
        Some(model)
    }

    /// Normalised coordinates of grid pixel `(x, y)`.
    #[inline]
    fn coords(&self, x: usize, y: usize) -> (f64, f64) {
        (
            (x as f64 - self.centre.0) * self.scale,
            (y as f64 - self.centre.1) * self.scale,
        )
    }

    /// Adds `sign` times the model's vector to every vector of a `gw`-wide grid flow.
    pub(crate) fn add_to(&self, flow: &mut [f32], gw: usize, sign: f32) {
        for (y, row) in flow.chunks_mut(gw * 2).enumerate() {
            let [u0, v0] = self.at(0, y);
            let [u1, v1] = self.at(1, y);
            let (du, dv) = (u1 - u0, v1 - v0);
            for (x, d) in row.chunks_exact_mut(2).enumerate() {
                d[0] += sign * (u0 + du * x as f32);
                d[1] += sign * (v0 + dv * x as f32);
            }
        }
    }

    /// The model's vector at grid pixel `(x, y)`.
    #[inline]
    pub(crate) fn at(&self, x: usize, y: usize) -> [f32; 2] {
        let (x, y) = self.coords(x, y);
        let a = &self.a;
        [
            (a[0] + a[1] * x + a[2] * y) as f32,
            (a[3] + a[4] * x + a[5] * y) as f32,
        ]
    }
}

/// Solves `m x = b` by Cramer's rule; `None` when `m` is (nearly) singular.
fn solve3(m: [[f64; 3]; 3], b: [f64; 3]) -> Option<[f64; 3]> {
    let det = |m: [[f64; 3]; 3]| {
        m[0][0] * (m[1][1] * m[2][2] - m[1][2] * m[2][1])
            - m[0][1] * (m[1][0] * m[2][2] - m[1][2] * m[2][0])
            + m[0][2] * (m[1][0] * m[2][1] - m[1][1] * m[2][0])
    };
    let d = det(m);
    // Relative to the product of the diagonal (the determinant of uncorrelated terms; the
    // sums are accumulated in f32 along rows).
    if d.abs() <= 1e-5 * (m[0][0] * m[1][1] * m[2][2]).abs() || !d.is_finite() {
        return None;
    }
    let mut x = [0f64; 3];
    for (c, xc) in x.iter_mut().enumerate() {
        let mut mc = m;
        for (row, &bv) in mc.iter_mut().zip(&b) {
            row[c] = bv;
        }
        *xc = det(mc) / d;
    }
    Some(x)
}

/// `weight` times Tukey's weight of each vector's distance to the median vector of its block
/// (`block x block` grid pixels, among the pixels with positive `weight`), with the robust
/// scale of those distances over the whole grid. Blocks with fewer than 3 vectors keep
/// their weights.
pub(crate) fn local_inliers(
    flow: &[f32],
    weight: &[f32],
    gw: usize,
    gh: usize,
    block: usize,
) -> Vec<f32> {
    let mut dist = vec![f32::NAN; gw * gh];
    let (mut us, mut vs, mut idx) = (Vec::new(), Vec::new(), Vec::new());
    for by in (0..gh).step_by(block) {
        for bx in (0..gw).step_by(block) {
            idx.clear();
            for y in by..(by + block).min(gh) {
                let row = y * gw..y * gw + (bx + block).min(gw);
                idx.extend(row.skip(bx).filter(|&p| weight[p] > 0.0));
            }
            if idx.len() < 3 {
                continue;
            }
            us.clear();
            vs.clear();
            us.extend(idx.iter().map(|&p| flow[p * 2]));
            vs.extend(idx.iter().map(|&p| flow[p * 2 + 1]));
            let mid = idx.len() / 2;
            let mu = *us.select_nth_unstable_by(mid, f32::total_cmp).1;
            let mv = *vs.select_nth_unstable_by(mid, f32::total_cmp).1;
            for &p in &idx {
                dist[p] = (flow[p * 2] - mu).hypot(flow[p * 2 + 1] - mv);
            }
        }
    }
    let mut known: Vec<f32> = dist.iter().copied().filter(|d| d.is_finite()).collect();
    if known.is_empty() {
        return weight.to_vec();
    }
    let mid = known.len() / 2;
    let mad = *known.select_nth_unstable_by(mid, f32::total_cmp).1;
    let c = REJECT * (1.4826 * mad).max(MIN_SIGMA);
    weight
        .iter()
        .zip(&dist)
        .map(|(&w, &d)| {
            let t = d / c;
            match t {
                t if t.is_nan() => w,
                t if t < 1.0 => w * (1.0 - t * t) * (1.0 - t * t),
                _ => 0.0,
            }
        })
        .collect()
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn vectors_of_the_neighbours_motion_lose_their_weight() {
        // A layer covering columns 0..23 moves by (2, -1); its neighbour (columns 20..) is
        // still, and the layer's last columns measured the neighbour's motion.
        let (gw, gh) = (40, 30);
        let mut flow = vec![0f32; gw * gh * 2];
        let mut weight = vec![0f32; gw * gh];
        for p in 0..gw * gh {
            if p % gw < 20 {
                flow[p * 2..p * 2 + 2].copy_from_slice(&[2.0, -1.0]);
            }
            weight[p] = (p % gw < 23) as u8 as f32;
        }
        for block in [8, 16, 48] {
            let w = local_inliers(&flow, &weight, gw, gh, block);
            for (p, &got) in w.iter().enumerate() {
                let want = (p % gw < 20) as u8 as f32;
                assert_eq!(got, want, "block {block}, pixel {p}");
            }
        }
        // The model of the vectors kept is their motion everywhere.
        let w = local_inliers(&flow, &weight, gw, gh, 16);
        let model = Affine::fit(&flow, &w, gw, gh).expect("samples");
        for (x, y) in [(0, 0), (39, 29), (30, 5)] {
            let m = model.at(x, y);
            assert!(
                (m[0] - 2.0).abs() < 1e-4 && (m[1] + 1.0).abs() < 1e-4,
                "{m:?}"
            );
        }
        assert!(Affine::fit(&flow, &vec![0.0; gw * gh], gw, gh).is_none());
    }

    #[test]
    fn the_model_is_exact_on_affine_motion() {
        let (gw, gh) = (40, 30);
        let truth = |x: usize, y: usize| {
            let (x, y) = (x as f32, y as f32);
            [1.5 + 0.02 * x - 0.01 * y, -0.5 + 0.005 * x + 0.03 * y]
        };
        let flow: Vec<f32> = (0..gw * gh).flat_map(|p| truth(p % gw, p / gw)).collect();
        // Samples in the left half only: the model extrapolates to the right.
        let weight: Vec<f32> = (0..gw * gh).map(|p| (p % gw < 20) as u8 as f32).collect();
        let model = Affine::fit(&flow, &weight, gw, gh).expect("samples");
        for (x, y) in [(0, 0), (39, 29), (25, 3)] {
            let (m, t) = (model.at(x, y), truth(x, y));
            assert!((m[0] - t[0]).abs() < 1e-4 && (m[1] - t[1]).abs() < 1e-4);
        }
    }

    #[test]
    fn few_or_collinear_samples_give_a_translation() {
        let (gw, gh) = (40, 10);
        let flow: Vec<f32> = (0..gw * gh)
            .flat_map(|p| [2.0 + (p % gw) as f32 * 0.1, -1.0])
            .collect();
        // One row (40 samples: the y terms are undetermined), then 10 samples.
        for n in [gw, 10] {
            let weight: Vec<f32> = (0..gw * gh)
                .map(|p| (p / gw == 4 && p % gw < n) as u8 as f32)
                .collect();
            let model = Affine::fit(&flow, &weight, gw, gh).expect("samples");
            let mean = 2.0 + (n - 1) as f32 * 0.05;
            for (x, y) in [(0, 0), (39, 9), (7, 4)] {
                let m = model.at(x, y);
                assert!(
                    (m[0] - mean).abs() < 1e-4 && (m[1] + 1.0).abs() < 1e-4,
                    "{n}: {m:?}"
                );
            }
        }
    }
}
