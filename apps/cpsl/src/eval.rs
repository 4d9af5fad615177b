//! `cpsl eval`: layer real reference views, render their target views, score against the real
//! images.

use crate::progress::Bars;
use crate::synth::estimate_depth;
use anyhow::{Context, Result};
use clap::{Args, ValueEnum};
use cpsl_core::{PremulImage, Progress, ProgressEvent};
use cpsl_eval::datasets::{self, align_median, Dataset};
use cpsl_eval::metrics::{psnr_masked, ssim};
use cpsl_layering::{slice_by_depth, SliceConfig};
use cpsl_render::PreparedLayers;
use serde::Serialize;
use std::path::PathBuf;

/// Layering methods `cpsl eval` compares.
#[derive(Clone, Copy, PartialEq, Eq, ValueEnum, Serialize)]
#[serde(rename_all = "kebab-case")]
pub enum Method {
    /// Depth slicing into K layers.
    DepthSlice,
    /// One plane at the median depth: the reference image shifted as a whole (no parallax
    /// between objects), the "plain 2D" baseline.
    SinglePlane,
    /// Both.
    All,
}

/// Arguments of `cpsl eval`.
#[derive(Args)]
pub struct EvalArgs {
    /// Dataset name (hci/backgammon, middlebury2005/Art|Books|Dolls,
    /// middlebury2003/Teddy|Cones) or `all`.
    pub dataset: String,
    /// Folder holding the datasets (`../shared/data` beside the checkout).
    #[arg(long, default_value = "../shared/data")]
    pub data: PathBuf,
    /// Layering method.
    #[arg(long, value_enum, default_value_t = Method::All)]
    pub method: Method,
    /// Number of layers K for depth slicing.
    #[arg(long, default_value_t = 6, value_parser = clap::value_parser!(u32).range(1..=64))]
    pub layers: u32,
    /// Depth source: `gt` (the dataset's ground truth) or a model (`fastdepth` or an .onnx
    /// path), median-scaled to the ground truth.
    #[arg(long, default_value = "gt")]
    pub depth: String,
    /// Write the full report (per view) as JSON.
    #[arg(long)]
    pub json: Option<PathBuf>,
}

/// Scores of one rendered view.
#[derive(Serialize)]
struct ViewScore {
    view: String,
    /// PSNR over the pixels the render covers (dB).
    psnr: Option<f64>,
    /// SSIM over the covered pixels.
    ssim: f64,
    /// Fraction of pixels the render covers.
    coverage: f64,
}

#[derive(Serialize)]
struct MethodReport {
    dataset: String,
    method: String,
    layers: usize,
    depth: String,
    mean_psnr: f64,
    mean_ssim: f64,
    mean_coverage: f64,
    views: Vec<ViewScore>,
}

fn score(
    ds: &Dataset,
    prepared: &PreparedLayers,
    progress: &dyn Progress,
    stage: &str,
) -> Vec<ViewScore> {
    progress.event(ProgressEvent::Start {
        stage,
        total: Some(ds.targets.len() as u64),
    });
    let out = ds
        .targets
        .iter()
        .enumerate()
        .map(|(i, t)| {
            let mut img = PremulImage::new(t.camera.width, t.camera.height);
            prepared.render_into(&t.pose, &t.camera, &mut img);
            let covered: Vec<bool> = img
                .as_bytes()
                .chunks_exact(4)
                .map(|p| p[3] == 255)
                .collect();
            let rgb = img.over_background([0, 0, 0]);
            progress.event(ProgressEvent::Advance {
                stage,
                done: i as u64 + 1,
            });
            ViewScore {
                view: t.name.clone(),
                psnr: psnr_masked(&rgb, &t.rgb, &covered),
                ssim: ssim(
                    &rgb,
                    &t.rgb,
                    t.camera.width as usize,
                    t.camera.height as usize,
                    Some(&covered),
                ),
                coverage: covered.iter().filter(|&&c| c).count() as f64 / covered.len() as f64,
            }
        })
        .collect();
    progress.event(ProgressEvent::Finish { stage });
    out
}

fn mean(v: impl Iterator<Item = f64>) -> f64 {
    let (s, n) = v.fold((0.0, 0usize), |(s, n), x| (s + x, n + 1));
    s / n.max(1) as f64
}

/// Runs `cpsl eval`.
pub fn run(a: EvalArgs) -> Result<()> {
    anyhow::ensure!(
        a.data.is_dir(),
        "{}: data folder not found (pass --data with the folder that holds hci_lightfield_4d/ and middlebury_2005_2003_stereo/)",
        a.data.display()
    );
    let names: Vec<&str> = if a.dataset == "all" {
        datasets::NAMES.to_vec()
    } else {
        vec![a.dataset.as_str()]
    };
    let bars = Bars::default();
    let mut reports = Vec::new();
    println!(
        "{:<22} {:<12} {:>3} {:>9} {:>7} {:>9} {:>6}",
        "dataset", "method", "K", "PSNR dB", "SSIM", "coverage", "views"
    );
    for name in names {
        let ds = datasets::load(&a.data, name).with_context(|| format!("loading {name}"))?;
        let (depth, depth_name) = if a.depth == "gt" {
            (ds.depth.clone(), "ground truth".to_string())
        } else {
            let (est, source) =
                estimate_depth(&a.depth, None, &ds.rgb, ds.camera.width, ds.camera.height)?;
            let (aligned, s) = align_median(&est, &ds.depth)
                .with_context(|| format!("{source}: no valid depth to align"))?;
            (aligned, format!("{source}, median-scaled x{s:.3}"))
        };
        let mut methods = Vec::new();
        if a.method != Method::SinglePlane {
            methods.push(("depth-slice", a.layers as usize));
        }
        if a.method != Method::DepthSlice {
            methods.push(("single-plane", 1));
        }
        for (method, k) in methods {
            let config = SliceConfig {
                layers: k,
                ..SliceConfig::default()
            };
            let set = slice_by_depth(&ds.rgb, &depth, ds.camera, &config)
                .with_context(|| format!("layering {name}"))?;
            let prepared = PreparedLayers::new(&set);
            let views = score(&ds, &prepared, &bars, "render views");
            let r = MethodReport {
                dataset: name.into(),
                method: method.into(),
                layers: set.len(),
                depth: depth_name.clone(),
                mean_psnr: mean(
                    views
                        .iter()
                        .filter_map(|v| v.psnr)
                        .filter(|p| p.is_finite()),
                ),
                mean_ssim: mean(views.iter().map(|v| v.ssim)),
                mean_coverage: mean(views.iter().map(|v| v.coverage)),
                views,
            };
            println!(
                "{:<22} {:<12} {:>3} {:>9.2} {:>7.4} {:>8.1}% {:>6}",
                r.dataset,
                r.method,
                r.layers,
                r.mean_psnr,
                r.mean_ssim,
                r.mean_coverage * 100.0,
                r.views.len()
            );
            reports.push(r);
        }
    }
    if let Some(path) = &a.json {
        crate::util::write_json(path, &reports)?;
        println!("wrote {}", path.display());
    }
    Ok(())
}
