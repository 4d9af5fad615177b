//! Stereo depth on the real two-view datasets: the pair's own disparity ([`cpsl_stereo`])
//! scored against ground truth, and turned into the reference view's depth for layering
//! (`cpsl eval --depth stereo`).
//!
//! The score is the Middlebury one: the share of non-occluded pixels with known ground truth
//! whose disparity is off by more than 1 px (and 2 px). A pixel is occluded when the ground
//! truth puts a nearer pixel of its row over it in the other view (a z-buffer along the row),
//! so every dataset is scored the same way from its disparity alone.

use crate::datasets::{Dataset, NAMES};
use crate::error::{Context, EvalError};
use cpsl_core::Mat3;
use cpsl_stereo::{Disparity, StereoConfig};
use serde::Serialize;
use std::path::Path;
use std::time::Instant;

type Result<T> = std::result::Result<T, EvalError>;

/// The rectified pair in a dataset: the target to the right of the reference by a pure
/// sideways translation (the widest when there are several), as `(target, baseline,
/// principal-point offset)`; `None` when the dataset has no such view.
pub fn pair(ds: &Dataset) -> Option<(usize, f64, f64)> {
    ds.targets
        .iter()
        .enumerate()
        .filter(|(_, t)| {
            let tr = t.pose.translation;
            t.pose.rotation == Mat3::IDENTITY
                && tr.x() > 0.0
                && tr.y().abs() <= 1e-9 * tr.x()
                && tr.z().abs() <= 1e-9 * tr.x()
                && t.camera.fx == ds.camera.fx
                && t.camera.fy == ds.camera.fy
                && t.camera.cy == ds.camera.cy
                && (t.camera.width, t.camera.height) == (ds.camera.width, ds.camera.height)
        })
        .max_by(|a, b| {
            a.1.pose
                .translation
                .x()
                .total_cmp(&b.1.pose.translation.x())
        })
        .map(|(i, t)| (i, t.pose.translation.x(), t.camera.cx - ds.camera.cx))
}

/// The reference view's depth from its stereo pair, the disparity it came from and a
/// description.
pub fn stereo_depth(ds: &Dataset, cfg: &StereoConfig) -> Result<(Vec<f32>, Disparity, String)> {
    let Some((t, baseline, offset)) = pair(ds) else {
        return Err(EvalError::Invalid(format!(
            "{}: no view to the right of the reference by a pure sideways step, so no stereo pair",
            ds.name
        )));
    };
    let (w, h) = (ds.camera.width, ds.camera.height);
    let disp = cpsl_stereo::match_pair(&ds.rgb, &ds.targets[t].rgb, w, h, cfg)
        .context_with(|| format!("matching {} against {}", ds.name, ds.targets[t].name))?;
    let depth = disp.depth(ds.camera.fx, baseline, offset);
    let desc = format!(
        "stereo (SGBM against {}, {:.0} % matched)",
        ds.targets[t].name,
        100.0 * disp.density()
    );
    Ok((depth, disp, desc))
}

/// Ground-truth disparity of the pair (NaN where unknown) and, per pixel, whether it is
/// visible in the other view.
pub fn truth(ds: &Dataset, baseline: f64, offset: f64) -> (Vec<f32>, Vec<bool>) {
    let (w, f) = (ds.camera.width as usize, ds.camera.fx);
    let disp: Vec<f32> = ds
        .depth
        .iter()
        .map(|&z| {
            if z.is_finite() && z > 0.0 {
                (f * baseline / z as f64 - offset) as f32
            } else {
                f32::NAN
            }
        })
        .collect();
    let mut visible = vec![false; disp.len()];
    for (row, vis) in disp.chunks_exact(w).zip(visible.chunks_exact_mut(w)) {
        // Scanning right to left, the least landing position of the pixels to the right.
        let mut least = f32::INFINITY;
        for x in (0..w).rev() {
            let d = row[x];
            if !d.is_finite() {
                continue;
            }
            let lands = x as f32 - d;
            vis[x] = lands <= least + 1.0 && lands >= -0.5;
            least = least.min(lands);
        }
    }
    (disp, visible)
}

/// One pair scored.
#[derive(Debug, Clone, Serialize)]
pub struct StereoScore {
    /// Dataset name.
    pub dataset: String,
    /// Width x height.
    pub size: (u32, u32),
    /// Disparity range searched, `(least, count)`.
    pub range: (i32, u32),
    /// Vertical offset found by the rectification check (px).
    pub vertical_offset: Option<f32>,
    /// Share of pixels matched (before the fill).
    pub density: f64,
    /// Non-occluded pixels with ground truth scored.
    pub scored: usize,
    /// Share of those off by more than 1 px (after the fill).
    pub bad1: f64,
    /// Share off by more than 2 px.
    pub bad2: f64,
    /// Mean absolute error over them (px).
    pub mean_abs: f64,
    /// Matching time in milliseconds.
    pub ms: f64,
}

/// Matches and scores dataset `name` (any of [`NAMES`] with a stereo pair and depth).
pub fn score(root: &Path, name: &str, cfg: &StereoConfig) -> Result<StereoScore> {
    let ds = crate::datasets::load(root, name).context_with(|| format!("loading {name}"))?;
    let (_, baseline, offset) =
        pair(&ds).ok_or_else(|| EvalError::Invalid(format!("{name}: no stereo pair")))?;
    let t0 = Instant::now();
    let (_, disp, _) = stereo_depth(&ds, cfg)?;
    let ms = t0.elapsed().as_secs_f64() * 1e3;
    let (gt, visible) = truth(&ds, baseline, offset);
    let (mut n, mut b1, mut b2, mut sum) = (0usize, 0usize, 0usize, 0.0f64);
    for ((&g, &v), &d) in gt.iter().zip(&visible).zip(&disp.values) {
        if !v || !g.is_finite() {
            continue;
        }
        n += 1;
        let e = if d.is_finite() {
            (d - g).abs() as f64
        } else {
            f64::INFINITY
        };
        b1 += (e > 1.0) as usize;
        b2 += (e > 2.0) as usize;
        sum += e.min(1e3);
    }
    if n == 0 {
        return Err(EvalError::Invalid(format!(
            "{name}: no ground-truth disparity to score"
        )));
    }
    Ok(StereoScore {
        dataset: name.to_string(),
        size: (ds.camera.width, ds.camera.height),
        range: disp.range,
        vertical_offset: disp.vertical_offset,
        density: disp.density(),
        scored: n,
        bad1: b1 as f64 / n as f64,
        bad2: b2 as f64 / n as f64,
        mean_abs: sum / n as f64,
        ms,
    })
}

/// The datasets with a stereo pair and ground-truth depth.
pub fn stereo_names() -> Vec<&'static str> {
    NAMES
        .iter()
        .copied()
        .filter(|n| !n.starts_with("middlebury-mview"))
        .collect()
}
