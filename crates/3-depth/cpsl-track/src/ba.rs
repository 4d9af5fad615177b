//! Bundle adjustment: the placed frames' poses and the triangulated points refined together
//! by minimising the reprojection error of every observation (Cauchy loss, half a pixel),
//! with tiny-solver's Levenberg-Marquardt on a sparse Cholesky factorisation.
//!
//! A frame is six numbers, the world-to-camera rotation as an axis-angle vector and the
//! translation (`X_cam = R X_world + t`); a point is three. The gauge is fixed by holding the
//! first frame and one coordinate of the first baseline's far frame; over a long clip the
//! frames before the adjusted window are held as they are.

use crate::{from_extrinsics, Obs, Result, TrackError};
use cpsl_core::{Camera, Mat3, Pose, Vec3};
use std::collections::{HashMap, HashSet};
use tiny_solver::factors::Factor;
use tiny_solver::loss_functions::CauchyLoss;
use tiny_solver::na::{DVector, RealField};
use tiny_solver::optimizer::{Optimizer, OptimizerOptions};
use tiny_solver::{LevenbergMarquardtOptimizer, Problem};

/// Scale of the Cauchy loss on the reprojection residual (working pixels): tracks that drift
/// weigh little. (Measured on the fox: Huber at 1 px left 0.51 degrees of rotation error,
/// at 0.5 px 0.41, Cauchy at 0.5 px 0.30.)
const CAUCHY_PX: f64 = 0.5;

/// One observation's reprojection residual.
struct Reprojection {
    cam: Camera,
    u: f64,
    v: f64,
}

/// `R(w) p`, Rodrigues' formula, with the first-order form near zero.
fn rotate<T: RealField>(w: [T; 3], p: [T; 3]) -> [T; 3] {
    let [wx, wy, wz] = w;
    let [px, py, pz] = p;
    let th2 = wx.clone() * wx.clone() + wy.clone() * wy.clone() + wz.clone() * wz.clone();
    let cross = |a: [T; 3], b: [T; 3]| {
        [
            a[1].clone() * b[2].clone() - a[2].clone() * b[1].clone(),
            a[2].clone() * b[0].clone() - a[0].clone() * b[2].clone(),
            a[0].clone() * b[1].clone() - a[1].clone() * b[0].clone(),
        ]
    };
    let p = [px, py, pz];
    if th2 < T::from_f64(1e-16).expect("a constant") {
        let c = cross([wx, wy, wz], p.clone());
        return [
            p[0].clone() + c[0].clone(),
            p[1].clone() + c[1].clone(),
            p[2].clone() + c[2].clone(),
        ];
    }
    let th = th2.sqrt();
    let k = [wx / th.clone(), wy / th.clone(), wz / th.clone()];
    let (c, s) = (th.clone().cos(), th.sin());
    let kxp = cross(k.clone(), p.clone());
    let kdp =
        k[0].clone() * p[0].clone() + k[1].clone() * p[1].clone() + k[2].clone() * p[2].clone();
    let one_c = T::one() - c.clone();
    let term = |i: usize| {
        p[i].clone() * c.clone()
            + kxp[i].clone() * s.clone()
            + k[i].clone() * kdp.clone() * one_c.clone()
    };
    [term(0), term(1), term(2)]
}

impl<T: RealField> Factor<T> for Reprojection {
    fn residual_func(&self, params: &[DVector<T>]) -> DVector<T> {
        let (c, x) = (&params[0], &params[1]);
        let k = |v: f64| T::from_f64(v).expect("a finite constant");
        let p = rotate(
            [c[0].clone(), c[1].clone(), c[2].clone()],
            [x[0].clone(), x[1].clone(), x[2].clone()],
        );
        // Points that fall behind the camera during a step are kept in front by the depth's
        // floor; the step then raises the cost and is rejected.
        let z = (p[2].clone() + c[5].clone()).max(k(1e-6));
        let u = k(self.cam.fx) * (p[0].clone() + c[3].clone()) / z.clone() + k(self.cam.cx);
        let v = k(self.cam.fy) * (p[1].clone() + c[4].clone()) / z + k(self.cam.cy);
        DVector::from_vec(vec![u - k(self.u), v - k(self.v)])
    }
}

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
    let free: HashSet<usize> = window
        .free
        .iter()
        .copied()
        .filter(|&f| f != fixed && poses.get(f).copied().flatten().is_some())
        .collect();
    if free.is_empty() {
        return Ok(());
    }
    let mut seen: HashSet<usize> = free.iter().chain(window.held).copied().collect();
    seen.insert(fixed);
    let mut problem = Problem::new();
    let mut init: HashMap<String, DVector<f64>> = HashMap::new();
    let mut used_frames: HashSet<usize> = HashSet::new();
    let mut used_points = Vec::new();
    // In id order, so that the problem (and its rounding) is the same on every run.
    let mut ids: Vec<usize> = points.keys().copied().collect();
    ids.sort_unstable();
    for id in ids {
        let x = points[&id];
        let obs: Vec<&Obs> = tracks[id]
            .iter()
            .filter(|o| seen.contains(&(o.0 as usize)) && poses[o.0 as usize].is_some())
            .collect();
        if obs.len() < 2 || !obs.iter().any(|o| free.contains(&(o.0 as usize))) {
            continue;
        }
        let pname = format!("p{id}");
        for &&(f, u, v) in &obs {
            let cname = format!("c{f}");
            problem.add_residual_block(
                2,
                &[&cname, &pname],
                Box::new(Reprojection {
                    cam: *cam,
                    u: u as f64,
                    v: v as f64,
                }),
                Some(Box::new(CauchyLoss::new(CAUCHY_PX))),
            );
            used_frames.insert(f as usize);
        }
        init.insert(pname, DVector::from_vec(vec![x.x(), x.y(), x.z()]));
        used_points.push(id);
    }
    if used_points.is_empty() {
        return Ok(());
    }
    for &f in &used_frames {
        let Pose {
            rotation: r,
            translation: t,
        } = poses[f].expect("a placed frame").inverse();
        let w = r.log();
        let name = format!("c{f}");
        init.insert(
            name.clone(),
            DVector::from_vec(vec![w.x(), w.y(), w.z(), t.x(), t.y(), t.z()]),
        );
        if !free.contains(&f) {
            for i in 0..6 {
                problem.fix_variable(&name, i);
            }
        }
    }
    if free.contains(&window.scale) {
        let s = window.scale;
        // The translation coordinate of largest size carries the scale.
        let t = &init[&format!("c{s}")];
        let i = (3..6)
            .max_by(|&a, &b| t[a].abs().total_cmp(&t[b].abs()))
            .expect("three entries");
        problem.fix_variable(&format!("c{s}"), i);
    }
    let options = OptimizerOptions {
        max_iteration: window.iterations,
        // Stop once a step lowers the cost by less than 0.1 %: on the fox, 1e-5 (tiny-solver's
        // default) took twice as long for the same poses (0.185 against 0.186 degrees).
        min_rel_error_decrease_threshold: 1e-3,
        ..Default::default()
    };
    let solved = LevenbergMarquardtOptimizer::default()
        .optimize(&problem, &init, Some(options))
        .ok_or_else(|| TrackError::Input("bundle adjustment found no solution".into()))?;
    for &f in &free {
        let Some(c) = solved.get(&format!("c{f}")) else {
            continue;
        };
        let r = Mat3::exp(Vec3::new(c[0], c[1], c[2]));
        let pose = from_extrinsics(r, Vec3::new(c[3], c[4], c[5]));
        if pose.is_finite() {
            poses[f] = Some(pose);
        }
    }
    for &id in &used_points {
        let p = &solved[&format!("p{id}")];
        let x = Vec3::new(p[0], p[1], p[2]);
        if x.is_finite() {
            points.insert(id, x);
        }
    }
    Ok(())
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn rotate_matches_the_matrix() {
        let axis = Vec3::new(1.0, -2.0, 0.5).normalized();
        let r = Mat3::axis_angle(axis, 0.7);
        let p = Vec3::new(0.3, -1.2, 2.0);
        let w = axis * 0.7;
        let q = rotate([w.x(), w.y(), w.z()], [p.x(), p.y(), p.z()]);
        let e = r * p;
        assert!((q[0] - e.x()).abs() + (q[1] - e.y()).abs() + (q[2] - e.z()).abs() < 1e-12);
    }
}
