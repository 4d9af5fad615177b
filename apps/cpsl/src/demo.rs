//! `cpsl demo`: the main job end to end on the built-in synthetic scene.

use crate::layer::{layer_image, write_output, InstanceMode};
use crate::progress::Bars;
use crate::render::{render_sweep, Source, Sweep};
use crate::synth::{depth_list, estimate_depth, synthesise, SynthArgs};
use crate::util::{self, Output};
use anyhow::{Context, Result};
use clap::Args;
use cpsl_core::FixedDepth;
use cpsl_eval::metrics::psnr;
use cpsl_layering::LayeringConfig;
use cpsl_render::PreparedLayers;
use serde::Serialize;
use std::path::PathBuf;

/// Arguments of `cpsl demo`.
#[derive(Args)]
pub struct DemoArgs {
    /// Output folder.
    #[arg(short, long, default_value = "out/demo")]
    pub output: PathBuf,
    /// Image width.
    #[arg(long, default_value_t = 640)]
    pub width: u32,
    /// Image height.
    #[arg(long, default_value_t = 480)]
    pub height: u32,
    /// Number of layers K.
    #[arg(long, default_value_t = 6, value_parser = clap::value_parser!(u32).range(2..=16))]
    pub layers: u32,
    /// Layering configuration as JSON (as for `cpsl layer --config`).
    #[arg(long)]
    pub config: Option<PathBuf>,
    /// Instance masks for layering.
    #[arg(long, value_enum, default_value_t = InstanceMode::Components)]
    pub instances: InstanceMode,
    /// Layer from a monocular depth model (`fastdepth` or an .onnx path) instead of the
    /// ground-truth depth. Monocular depth has no absolute scale, so it is scaled to match
    /// the median of the ground truth before slicing.
    #[arg(long)]
    pub depth_model: Option<String>,
}

#[derive(Serialize)]
struct Score {
    view: String,
    pose: String,
    identity: bool,
    /// PSNR against the ray-cast ground truth; `null` when the render is identical.
    psnr_db: Option<f64>,
}

/// Runs `cpsl demo`.
pub fn run(a: DemoArgs) -> Result<()> {
    let bars = Bars::default();
    let synth_dir = a.output.join("scene");
    let synth = synthesise(
        &SynthArgs {
            output: synth_dir.clone(),
            width: a.width,
            height: a.height,
            time: 0.0,
            supersample: 3,
        },
        &bars,
    )?;
    println!(
        "1/3 synthesised scene, depth and {} ground-truth views in {}",
        synth.views.len(),
        synth_dir.display()
    );

    let layer_dir = a.output.join("layers");
    let config = LayeringConfig {
        layers: a.layers as usize,
        ..match &a.config {
            Some(p) => crate::layer::read_config(p)?,
            None => LayeringConfig::default(),
        }
    };
    let (depth, source) = match &a.depth_model {
        None => (synth.depth.clone(), "ray-cast ground truth".to_string()),
        Some(model) => {
            let cam = synth.scene.camera;
            let (est, source) = estimate_depth(model, None, &synth.rgb, cam.width, cam.height)?;
            let (aligned, s) = cpsl_eval::datasets::align_median(&est, &synth.depth)
                .with_context(|| format!("{source}: no valid depth to align"))?;
            (
                aligned,
                format!("{source}, median-scaled by {s:.3} to the ground truth"),
            )
        }
    };
    let cam = synth.scene.camera;
    let mut fixed = FixedDepth {
        name: source.clone(),
        width: cam.width,
        height: cam.height,
        depth,
    };
    let run = layer_image(
        &synth.rgb,
        cam,
        &mut fixed,
        true,
        &config,
        a.instances,
        &bars,
    )?;
    write_output(&layer_dir, &run, &config, &source, true)?;
    let set = run.layered.set;
    println!(
        "2/3 layered into {} layers at depths [{}] ({} promoted) in {} (depth: {source})",
        set.len(),
        depth_list(&set),
        set.layers()
            .iter()
            .filter(|l| l.meta.role == Some(cpsl_core::LayerRole::Instance))
            .count(),
        layer_dir.display()
    );

    let mut source = Source::Still(Box::new(
        PreparedLayers::new(&set).with_edc(&run.layered.edc),
    ));
    let sweep_dir = a.output.join("sweep");
    let sweep = Sweep::parse("tx:-0.3:0.3:61").expect("valid sweep");
    render_sweep(
        &mut source,
        true,
        &sweep.poses(),
        &sweep_dir,
        Output::Over([0, 0, 0]),
        30,
        &bars,
    )?;
    let video = sweep_dir.join("sweep.mp4");
    println!(
        "3/3 rendered a 61-frame sweep in {}{}",
        sweep_dir.display(),
        if video.exists() {
            " (sweep.mp4, sheet.png)"
        } else {
            " (sheet.png)"
        }
    );

    let prepared = source.at(0)?;
    let mut scores = Vec::new();
    for (entry, truth) in &synth.views {
        let mut img = cpsl_core::PremulImage::new(set.camera().width, set.camera().height);
        crate::render::render_pose(prepared, true, &entry.pose_matrix, set.camera(), &mut img);
        scores.push(Score {
            view: entry.name.clone(),
            pose: entry.pose.clone(),
            identity: entry.pose_matrix == cpsl_core::Pose::IDENTITY,
            psnr_db: Some(psnr(&img.over_background([0, 0, 0]), truth)).filter(|p| p.is_finite()),
        });
    }
    // The reference view reproduces the input; average the novel views.
    let novel: Vec<f64> = scores
        .iter()
        .filter(|s| !s.identity)
        .map(|s| s.psnr_db.unwrap_or(f64::INFINITY))
        .collect();
    let mean = novel.iter().sum::<f64>() / novel.len().max(1) as f64;
    println!(
        "novel views vs ray-cast ground truth: mean PSNR {mean:.2} dB over {} novel views",
        novel.len(),
    );
    for s in &scores {
        let note = if s.identity { "  (reference view)" } else { "" };
        match s.psnr_db {
            Some(p) => println!("  {:<12} {p:>6.2} dB{note}", s.view),
            None => println!("  {:<12}  exact{note}", s.view),
        }
    }
    util::write_json(&a.output.join("scores.json"), &scores)?;
    Ok(())
}
