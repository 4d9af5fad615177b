//! Bundle adjustment: the placed frames' poses and the triangulated points refined together
//! by minimising the reprojection error of every observation (Cauchy loss, half a pixel).
//!
//! Levenberg-Marquardt with analytic Jacobians: the points are eliminated by the Schur
//! complement and the reduced frame system is solved by a Cholesky factorisation that skips
//! the zeros before each row's first entry (a video's frames share points only with their
//! neighbours, so the system is close to banded). Written here rather than taken from a
//! solver crate because both measured ones spend about 60 ms per step on the fox's problem
//! (31 frames, 4587 points, ~32,000 observations: tiny-solver 0.18 through per-residual
//! automatic differentiation, apex-solver 1.5 through per-residual blocks); this one takes a
//! few milliseconds (BENCHMARKS.md).
//!
//! A frame is its world-to-camera rotation and translation (`X_cam = R X_world + t`), updated
//! as `R <- exp(w) R`, `t <- t + dt`; a point is three numbers. The gauge is fixed by holding
//! the first frame and one translation coordinate of the first baseline's far frame; over a
//! long clip the frames before the adjusted window are held as they are.

use crate::{from_extrinsics, Obs, Result};
use cpsl_core::{Camera, Mat3, Pose, Vec3};
use std::collections::{HashMap, HashSet};

/// Scale of the Cauchy loss on the reprojection residual (working pixels): tracks that drift
/// weigh little. (Measured on the fox: Huber at 1 px left 0.51 degrees of rotation error,
/// at 0.5 px 0.41, Cauchy at 0.5 px 0.30.)
const CAUCHY_PX: f64 = 0.5;

/// An accepted step that lowers the cost by less than this share ends the adjustment (on the
/// fox, 1e-5 took twice as long for the same poses).
const MIN_REL_DECREASE: f64 = 1e-3;

/// Smallest depth a point is projected at (points pushed behind a camera by a step).
const MIN_Z: f64 = 1e-6;

/// Which frames one adjustment moves and which it holds.
pub(crate) struct Window<'a> {
    /// Frames to adjust (placed ones, other than `fixed`).
    pub free: &'a [usize],
    /// Frames whose observations count but whose poses are kept (adjusted before).
    pub held: &'a [usize],
    /// The frame that fixes the gauge (the world's origin).
    pub fixed: usize,
    /// The frame one of whose coordinates is held to fix the monocular scale.
    pub scale: usize,
    /// Most Levenberg-Marquardt steps.
    pub iterations: usize,
}

/// One frame of the problem.
struct Frame {
    r: Mat3,
    t: Vec3,
    /// Index of its six unknowns in the reduced system; `None` for a held frame.
    var: Option<usize>,
}

/// One point of the problem: its position and its observations' range in `Problem::obs`.
struct Point {
    id: usize,
    x: Vec3,
    obs: std::ops::Range<usize>,
}

/// The problem of one adjustment.
struct Problem {
    cam: Camera,
    frames: Vec<Frame>,
    points: Vec<Point>,
    /// (frame slot, u, v), grouped by point.
    obs: Vec<(usize, f64, f64)>,
    /// Free frames (unknowns `6 k .. 6 k + 6`).
    vars: usize,
    /// The unknown held to fix the scale, if the scale frame is free.
    scale_var: Option<usize>,
}

/// The cost's linearisation at the current estimate: the frames' blocks of the normal
/// equations (dense, `6 vars` square), and per point its 3x3 block, its gradient and one
/// 6x3 frame-point block per observation from a free frame.
struct Linear {
    cost: f64,
    h_cc: Vec<f64>,
    g_c: Vec<f64>,
    h_xx: Vec<[f64; 9]>,
    g_x: Vec<[f64; 3]>,
    /// Per observation (indexed like `Problem::obs`); zero for held frames.
    h_cx: Vec<[f64; 18]>,
}

/// The Cauchy loss of a squared residual and its derivative (the observation's weight).
fn cauchy(s: f64) -> (f64, f64) {
    let c2 = CAUCHY_PX * CAUCHY_PX;
    (0.5 * c2 * (s / c2).ln_1p(), 1.0 / (1.0 + s / c2))
}

impl Problem {
    /// Residual of one observation, and the camera-frame point (`None` behind the camera).
    fn residual(&self, f: &Frame, x: Vec3, u: f64, v: f64) -> ([f64; 2], Option<Vec3>) {
        let p = f.r * x + f.t;
        let z = p.z().max(MIN_Z);
        let r = [
            self.cam.fx * p.x() / z + self.cam.cx - u,
            self.cam.fy * p.y() / z + self.cam.cy - v,
        ];
        (r, (p.z() > MIN_Z).then_some(p))
    }

    fn cost(&self) -> f64 {
        self.points
            .iter()
            .flat_map(|pt| {
                self.obs[pt.obs.clone()].iter().map(|&(f, u, v)| {
                    let (r, _) = self.residual(&self.frames[f], pt.x, u, v);
                    cauchy(r[0] * r[0] + r[1] * r[1]).0
                })
            })
            .sum()
    }

    fn linearize(&self) -> Linear {
        let n = 6 * self.vars;
        let mut lin = Linear {
            cost: 0.0,
            h_cc: vec![0.0; n * n],
            g_c: vec![0.0; n],
            h_xx: vec![[0.0; 9]; self.points.len()],
            g_x: vec![[0.0; 3]; self.points.len()],
            h_cx: vec![[0.0; 18]; self.obs.len()],
        };
        let (fx, fy) = (self.cam.fx, self.cam.fy);
        for (j, pt) in self.points.iter().enumerate() {
            for o in pt.obs.clone() {
                let (fi, u, v) = self.obs[o];
                let f = &self.frames[fi];
                let (r, p) = self.residual(f, pt.x, u, v);
                let (rho, w) = cauchy(r[0] * r[0] + r[1] * r[1]);
                lin.cost += rho;
                let Some(p) = p else { continue };
                let z = p.z();
                // d(residual)/d(camera point), 2x3.
                let jp = [
                    [fx / z, 0.0, -fx * p.x() / (z * z)],
                    [0.0, fy / z, -fy * p.y() / (z * z)],
                ];
                // Point: J_p R.
                let jx: [[f64; 3]; 2] = std::array::from_fn(|a| {
                    std::array::from_fn(|b| (0..3).map(|k| jp[a][k] * f.r.0[k][b]).sum())
                });
                let hx = &mut lin.h_xx[j];
                let gx = &mut lin.g_x[j];
                for a in 0..3 {
                    gx[a] += w * (jx[0][a] * r[0] + jx[1][a] * r[1]);
                    for b in 0..3 {
                        hx[3 * a + b] += w * (jx[0][a] * jx[0][b] + jx[1][a] * jx[1][b]);
                    }
                }
                let Some(k) = f.var else { continue };
                // Frame: rotation J_p (-[q]x) with q = R X, translation J_p.
                let q = p - f.t;
                let (qx, qy, qz) = (q.x(), q.y(), q.z());
                let skew_neg = [[0.0, qz, -qy], [-qz, 0.0, qx], [qy, -qx, 0.0]];
                let jc: [[f64; 6]; 2] = std::array::from_fn(|a| {
                    std::array::from_fn(|b| match b {
                        0..3 => (0..3).map(|m| jp[a][m] * skew_neg[m][b]).sum(),
                        _ => jp[a][b - 3],
                    })
                });
                let base = 6 * k;
                for a in 0..6 {
                    lin.g_c[base + a] += w * (jc[0][a] * r[0] + jc[1][a] * r[1]);
                    for b in 0..6 {
                        lin.h_cc[(base + a) * n + base + b] +=
                            w * (jc[0][a] * jc[0][b] + jc[1][a] * jc[1][b]);
                    }
                    for (b, (x0, x1)) in jx[0].iter().zip(&jx[1]).enumerate() {
                        lin.h_cx[o][3 * a + b] = w * (jc[0][a] * x0 + jc[1][a] * x1);
                    }
                }
            }
        }
        lin
    }

    /// The damped Gauss-Newton step (frames, points) and the cost decrease it predicts, or
    /// `None` when the damped system is not positive definite.
    fn step(&self, lin: &Linear, lambda: f64) -> Option<(Vec<f64>, Vec<Vec3>, f64)> {
        let n = 6 * self.vars;
        let damp = |d: f64| lambda * d.clamp(1e-6, 1e32);
        let mut s = lin.h_cc.clone();
        let mut b: Vec<f64> = lin.g_c.iter().map(|g| -g).collect();
        let mut pred = 0.0;
        for i in 0..n {
            let d = damp(s[i * n + i]);
            s[i * n + i] += d;
        }
        // Eliminate each point: S -= W V^-1 W^T, b -= W V^-1 (-g_x).
        let mut v_inv = Vec::with_capacity(self.points.len());
        let mut y = Vec::new();
        for (j, pt) in self.points.iter().enumerate() {
            let mut v = lin.h_xx[j];
            for a in 0..3 {
                v[4 * a] += damp(v[4 * a]);
            }
            let vi = inverse3(&v)?;
            let gx = lin.g_x[j];
            let vg: [f64; 3] = std::array::from_fn(|a| {
                -(vi[3 * a] * gx[0] + vi[3 * a + 1] * gx[1] + vi[3 * a + 2] * gx[2])
            });
            y.clear();
            for o in pt.obs.clone() {
                let Some(k) = self.frames[self.obs[o].0].var else {
                    continue;
                };
                let w = &lin.h_cx[o];
                // Y = W V^-1 (6x3).
                let yo: [f64; 18] = std::array::from_fn(|e| {
                    let (a, c) = (e / 3, e % 3);
                    (0..3).map(|m| w[3 * a + m] * vi[3 * m + c]).sum()
                });
                for a in 0..6 {
                    b[6 * k + a] -= (0..3).map(|m| w[3 * a + m] * vg[m]).sum::<f64>();
                }
                y.push((k, o, yo));
            }
            for &(ka, _, ref ya) in &y {
                for &(kb, ob, _) in &y {
                    if kb < ka {
                        continue;
                    }
                    let wb = &lin.h_cx[ob];
                    for a in 0..6 {
                        let row = (6 * ka + a) * n + 6 * kb;
                        for c in 0..6 {
                            s[row + c] -=
                                (0..3).map(|m| ya[3 * a + m] * wb[3 * c + m]).sum::<f64>();
                        }
                    }
                }
            }
            v_inv.push(vi);
        }
        // Fill the lower blocks from the upper ones, then hold the scale unknown.
        for i in 0..n {
            for c in 0..i {
                s[i * n + c] = s[c * n + i];
            }
        }
        if let Some(i) = self.scale_var {
            for c in 0..n {
                s[i * n + c] = 0.0;
                s[c * n + i] = 0.0;
            }
            s[i * n + i] = 1.0;
            b[i] = 0.0;
        }
        let dc = cholesky_solve(&mut s, n, b)?;
        for (i, d) in dc.iter().enumerate() {
            pred += damp(lin.h_cc[i * n + i]) * d * d - lin.g_c[i] * d;
        }
        // Back-substitute the points: dx = V^-1 (-g_x - W^T dc).
        let mut dx = Vec::with_capacity(self.points.len());
        for (j, pt) in self.points.iter().enumerate() {
            let mut rhs = lin.g_x[j].map(|g| -g);
            for o in pt.obs.clone() {
                if let Some(k) = self.frames[self.obs[o].0].var {
                    let w = &lin.h_cx[o];
                    for m in 0..3 {
                        rhs[m] -= (0..6).map(|a| w[3 * a + m] * dc[6 * k + a]).sum::<f64>();
                    }
                }
            }
            let vi = &v_inv[j];
            let d: [f64; 3] = std::array::from_fn(|a| (0..3).map(|m| vi[3 * a + m] * rhs[m]).sum());
            let v = &lin.h_xx[j];
            for a in 0..3 {
                pred += damp(v[4 * a]) * d[a] * d[a] - lin.g_x[j][a] * d[a];
            }
            dx.push(Vec3(d));
        }
        Some((dc, dx, 0.5 * pred))
    }

    /// Applies a step; returns the state before it.
    fn apply(&mut self, dc: &[f64], dx: &[Vec3]) -> (Vec<(Mat3, Vec3)>, Vec<Vec3>) {
        let frames = self.frames.iter().map(|f| (f.r, f.t)).collect();
        let points = self.points.iter().map(|p| p.x).collect();
        for f in &mut self.frames {
            if let Some(k) = f.var {
                let d = &dc[6 * k..6 * k + 6];
                f.r = Mat3::exp(Vec3::new(d[0], d[1], d[2])) * f.r;
                f.t = f.t + Vec3::new(d[3], d[4], d[5]);
            }
        }
        for (p, d) in self.points.iter_mut().zip(dx) {
            p.x = p.x + *d;
        }
        (frames, points)
    }

    fn restore(&mut self, (frames, points): (Vec<(Mat3, Vec3)>, Vec<Vec3>)) {
        for (f, (r, t)) in self.frames.iter_mut().zip(frames) {
            (f.r, f.t) = (r, t);
        }
        for (p, x) in self.points.iter_mut().zip(points) {
            p.x = x;
        }
    }

    /// Levenberg-Marquardt with Nielsen's damping update; at most `iterations` steps.
    fn solve(&mut self, iterations: usize) {
        let (mut lambda, mut nu) = (1e-4, 2.0);
        let mut lin = self.linearize();
        for _ in 0..iterations {
            let Some((dc, dx, pred)) = self.step(&lin, lambda) else {
                lambda *= nu;
                nu *= 2.0;
                continue;
            };
            let before = self.apply(&dc, &dx);
            let cost = self.cost();
            let gain = (lin.cost - cost) / pred;
            if pred > 0.0 && cost.is_finite() && gain > 0.0 {
                lambda *= (1.0 - (2.0 * gain - 1.0).powi(3)).max(1.0 / 3.0);
                nu = 2.0;
                let done = lin.cost - cost < MIN_REL_DECREASE * lin.cost;
                if done {
                    return;
                }
                lin = self.linearize();
            } else {
                self.restore(before);
                lambda *= nu;
                nu *= 2.0;
                if lambda > 1e16 {
                    return;
                }
            }
        }
    }
}

/// Inverse of a symmetric positive definite 3x3 matrix (row-major), `None` if singular.
fn inverse3(m: &[f64; 9]) -> Option<[f64; 9]> {
    let inv = Mat3([[m[0], m[1], m[2]], [m[3], m[4], m[5]], [m[6], m[7], m[8]]]).inverse()?;
    let i = inv.0;
    let out = [
        i[0][0], i[0][1], i[0][2], i[1][0], i[1][1], i[1][2], i[2][0], i[2][1], i[2][2],
    ];
    out.iter().all(|v| v.is_finite()).then_some(out)
}

/// Solves `A x = b` for a symmetric positive definite `A` (row-major, overwritten by its
/// Cholesky factor), skipping the zeros before each row's first entry; `None` if `A` is not
/// positive definite.
pub(crate) fn cholesky_solve(a: &mut [f64], n: usize, mut b: Vec<f64>) -> Option<Vec<f64>> {
    let first: Vec<usize> = (0..n)
        .map(|i| (0..i).find(|&c| a[i * n + c] != 0.0).unwrap_or(i))
        .collect();
    for i in 0..n {
        for j in first[i]..=i {
            let k0 = first[i].max(first[j]);
            let dot: f64 = (k0..j).map(|k| a[i * n + k] * a[j * n + k]).sum();
            let v = a[i * n + j] - dot;
            if i == j {
                if v <= 0.0 || !v.is_finite() {
                    return None;
                }
                a[i * n + i] = v.sqrt();
            } else {
                a[i * n + j] = v / a[j * n + j];
            }
        }
    }
    for i in 0..n {
        let dot: f64 = (first[i]..i).map(|k| a[i * n + k] * b[k]).sum();
        b[i] = (b[i] - dot) / a[i * n + i];
    }
    for i in (0..n).rev() {
        // Column i of L below the diagonal, where rows reach back to i.
        let dot: f64 = (i + 1..n)
            .filter(|&r| first[r] <= i)
            .map(|r| a[r * n + i] * b[r])
            .sum();
        b[i] = (b[i] - dot) / a[i * n + i];
    }
    Some(b)
}

/// Adjusts the window's free frames and every point one of them sees, from their observations
/// and those of the held and fixed frames.
pub(crate) fn adjust(
    cam: &Camera,
    poses: &mut [Option<Pose>],
    points: &mut HashMap<usize, Vec3>,
    tracks: &[Vec<Obs>],
    window: &Window,
) -> Result<()> {
    let fixed = window.fixed;
    let mut free: Vec<usize> = window
        .free
        .iter()
        .copied()
        .filter(|&f| f != fixed && poses.get(f).copied().flatten().is_some())
        .collect();
    free.sort_unstable();
    free.dedup();
    if free.is_empty() {
        return Ok(());
    }
    let free_set: HashSet<usize> = free.iter().copied().collect();
    let mut seen: HashSet<usize> = free.iter().chain(window.held).copied().collect();
    seen.insert(fixed);
    let mut problem = Problem {
        cam: *cam,
        frames: Vec::new(),
        points: Vec::new(),
        obs: Vec::new(),
        vars: free.len(),
        scale_var: None,
    };
    // Frame slots: free frames first, in frame order (their unknowns' order), then held ones.
    let mut slot: HashMap<usize, usize> = HashMap::new();
    let mut add_frame = |problem: &mut Problem, f: usize, var: Option<usize>| {
        *slot.entry(f).or_insert_with(|| {
            let Pose {
                rotation: r,
                translation: t,
            } = poses[f].expect("a placed frame").inverse();
            problem.frames.push(Frame { r, t, var });
            problem.frames.len() - 1
        })
    };
    for (k, &f) in free.iter().enumerate() {
        add_frame(&mut problem, f, Some(k));
    }
    // In id order, so that the problem (and its rounding) is the same on every run.
    let mut ids: Vec<usize> = points.keys().copied().collect();
    ids.sort_unstable();
    for id in ids {
        let obs: Vec<&Obs> = tracks[id]
            .iter()
            .filter(|o| seen.contains(&(o.0 as usize)) && poses[o.0 as usize].is_some())
            .collect();
        if obs.len() < 2 || !obs.iter().any(|o| free_set.contains(&(o.0 as usize))) {
            continue;
        }
        let start = problem.obs.len();
        for &&(f, u, v) in &obs {
            let s = add_frame(&mut problem, f as usize, None);
            problem.obs.push((s, u as f64, v as f64));
        }
        problem.points.push(Point {
            id,
            x: points[&id],
            obs: start..problem.obs.len(),
        });
    }
    if problem.points.is_empty() {
        return Ok(());
    }
    if let Some(k) = free.iter().position(|&f| f == window.scale) {
        // The translation coordinate of largest size carries the scale.
        let t = problem.frames[k].t;
        let i = (0..3)
            .max_by(|&a, &b| t.0[a].abs().total_cmp(&t.0[b].abs()))
            .expect("three entries");
        problem.scale_var = Some(6 * k + 3 + i);
    }
    problem.solve(window.iterations);
    for (k, &f) in free.iter().enumerate() {
        let fr = &problem.frames[k];
        let pose = from_extrinsics(fr.r, fr.t);
        if pose.is_finite() {
            poses[f] = Some(pose);
        }
    }
    for p in &problem.points {
        if p.x.is_finite() {
            points.insert(p.id, p.x);
        }
    }
    Ok(())
}

#[cfg(test)]
mod tests {
    use super::*;

    /// A small problem: three frames along x looking at points in front of them.
    fn problem() -> Problem {
        let cam = Camera::from_fov(320, 240, 60.0);
        let frames = (0..3)
            .map(|i: usize| Frame {
                r: Mat3::exp(Vec3::new(0.01 * i as f64, -0.02 * i as f64, 0.005)),
                t: Vec3::new(-0.3 * i as f64, 0.02, 0.0),
                var: i.checked_sub(1),
            })
            .collect();
        let mut points = Vec::new();
        let mut obs = Vec::new();
        for j in 0..12 {
            let x = Vec3::new(
                0.2 * (j % 4) as f64 - 0.3,
                0.15 * (j / 4) as f64 - 0.15,
                3.0 + 0.1 * j as f64,
            );
            let start = obs.len();
            for f in 0..3 {
                // Observations off by up to a pixel, so that the residuals are not zero.
                obs.push((
                    f,
                    160.0 + 40.0 * x.x() - 10.0 * f as f64 + (j as f64 * 0.7).sin(),
                    120.0 + 40.0 * x.y() + (f as f64).cos(),
                ));
            }
            points.push(Point {
                id: j,
                x,
                obs: start..obs.len(),
            });
        }
        Problem {
            cam,
            frames,
            points,
            obs,
            vars: 2,
            scale_var: Some(3),
        }
    }

    #[test]
    fn gradient_matches_finite_differences() {
        let mut p = problem();
        let lin = p.linearize();
        assert!((lin.cost - p.cost()).abs() < 1e-12);
        let h = 1e-6;
        for k in 0..12 {
            let mut dc = vec![0.0; 12];
            dc[k] = h;
            let dx = vec![Vec3::default(); p.points.len()];
            let before = p.apply(&dc, &dx);
            let up = p.cost();
            p.restore(before);
            dc[k] = -h;
            let before = p.apply(&dc, &dx);
            let down = p.cost();
            p.restore(before);
            let num = (up - down) / (2.0 * h);
            assert!(
                (num - lin.g_c[k]).abs() < 1e-4 * (1.0 + num.abs()),
                "frame unknown {k}: {num} vs {}",
                lin.g_c[k]
            );
        }
        for j in [0, 5, 11] {
            for a in 0..3 {
                let mut dx = vec![Vec3::default(); p.points.len()];
                dx[j].0[a] = h;
                let before = p.apply(&[0.0; 12], &dx);
                let up = p.cost();
                p.restore(before);
                dx[j].0[a] = -h;
                let before = p.apply(&[0.0; 12], &dx);
                let down = p.cost();
                p.restore(before);
                let num = (up - down) / (2.0 * h);
                assert!(
                    (num - lin.g_x[j][a]).abs() < 1e-4 * (1.0 + num.abs()),
                    "point {j}/{a}"
                );
            }
        }
    }

    #[test]
    fn the_step_lowers_the_cost_and_holds_the_scale() {
        let mut p = problem();
        let start = p.cost();
        let t = p.frames[1].t;
        p.solve(20);
        assert!(p.cost() < 0.5 * start, "{} -> {}", start, p.cost());
        // Unknown 3 is frame 1's x translation.
        assert_eq!(p.frames[1].t.x(), t.x());
        assert_ne!(p.frames[1].t.y(), t.y());
    }

    #[test]
    fn cholesky_solves_a_banded_system() {
        let n = 5;
        let mut a = vec![0.0; n * n];
        for i in 0..n {
            a[i * n + i] = 4.0;
            if i + 1 < n {
                a[i * n + i + 1] = 1.0;
                a[(i + 1) * n + i] = 1.0;
            }
        }
        let x = [1.0, -2.0, 0.5, 3.0, -1.0];
        let b: Vec<f64> = (0..n)
            .map(|i| (0..n).map(|j| a[i * n + j] * x[j]).sum())
            .collect();
        let got = cholesky_solve(&mut a.clone(), n, b).expect("positive definite");
        for i in 0..n {
            assert!((got[i] - x[i]).abs() < 1e-12);
        }
        a[0] = -1.0;
        assert!(cholesky_solve(&mut a, n, vec![0.0; n]).is_none());
    }
}
