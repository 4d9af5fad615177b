//! `cpsl synth` (synthetic ground truth) and `cpsl slice` (depth slicing).

use crate::layer::{CameraArgs, DepthArgs};
use crate::progress::Bars;
use anyhow::{Context, Result};
use clap::Args;
use cpsl_core::{Camera, DepthSource, Limits, Progress, ProgressEvent};
use cpsl_layering::{slice_by_depth, SliceConfig};
use cpsl_pipeline::sources::open_depth_model;
use cpsl_pipeline::synthetic::{synthesise, SynthOptions};
use std::path::{Path, PathBuf};

/// Arguments of `cpsl synth`.
#[derive(Args)]
pub struct SynthArgs {
    /// Output folder.
    #[arg(short, long)]
    pub output: PathBuf,
    /// Image width.
    #[arg(long, default_value_t = 640)]
    pub width: u32,
    /// Image height.
    #[arg(long, default_value_t = 480)]
    pub height: u32,
    /// Scene time in seconds (objects move with their velocities).
    #[arg(long, default_value_t = 0.0)]
    pub time: f64,
    /// Supersamples per pixel side for colour (anti-aliasing).
    #[arg(long, default_value_t = 3)]
    pub supersample: u32,
}

impl SynthArgs {
    /// The library's options.
    pub fn options(&self) -> SynthOptions {
        SynthOptions {
            output: self.output.clone(),
            width: self.width,
            height: self.height,
            time: self.time,
            supersample: self.supersample,
        }
    }
}

/// Runs `cpsl synth`.
pub fn run_synth(a: SynthArgs) -> Result<()> {
    let out = synthesise(&a.options(), &Bars::default())?;
    println!(
        "wrote {}: input.png, depth.pfm, depth.png, objects.png, camera.json, scene.json, {} views",
        a.output.display(),
        out.views.len()
    );
    Ok(())
}

/// Arguments of `cpsl slice`.
#[derive(Args)]
pub struct SliceArgs {
    /// Input image (PNG or JPEG).
    pub image: PathBuf,
    #[command(flatten)]
    pub depth: DepthArgs,
    /// Output layer-set folder.
    #[arg(short, long)]
    pub output: PathBuf,
    /// Number of layers K.
    #[arg(long, default_value_t = 6, value_parser = clap::value_parser!(u32).range(1..=64))]
    pub layers: u32,
    #[command(flatten)]
    pub camera: CameraArgs,
}

/// Slices an image + depth and writes the layer set with its resolved config (stage, depth
/// source, camera, slicing parameters) as `config.json`.
pub fn slice_to(
    rgb: &[u8],
    depth: &[f32],
    depth_source: &str,
    cam: Camera,
    config: &SliceConfig,
    out: &Path,
) -> Result<cpsl_core::LayerSet> {
    let set = slice_by_depth(rgb, depth, cam, config)?;
    let cfg = serde_json::to_vec_pretty(&serde_json::json!({
        "stage": "depth-slice",
        "depth": depth_source,
        "camera": cam,
        "config": config,
    }))?;
    cpsl_io::write_layer_set(out, &set, &[("config.json", &cfg)])
        .with_context(|| format!("writing layer set {}", out.display()))?;
    Ok(set)
}

/// The layer depths of `set`, comma separated, to three decimals.
pub fn depth_list(set: &cpsl_core::LayerSet) -> String {
    let d: Vec<String> = set
        .layers()
        .iter()
        .map(|l| format!("{:.3}", l.depth))
        .collect();
    d.join(", ")
}

/// Runs a monocular depth model on an RGB image: `model` is `fastdepth` (the cached default)
/// or an .onnx path, described by `desc` or `<model>.json`. Returns the depth and a
/// description of its source.
pub fn estimate_depth(
    model: &str,
    desc: Option<&Path>,
    rgb: &[u8],
    width: u32,
    height: u32,
) -> Result<(Vec<f32>, String)> {
    let mut m = open_depth_model(model, desc)?;
    Ok((m.depth(rgb, width, height)?, m.name()))
}

/// Runs `cpsl slice`.
pub fn run_slice(a: SliceArgs) -> Result<()> {
    let img = cpsl_io::images::read_rgb8(&a.image, &Limits::default())
        .with_context(|| format!("reading image {}", a.image.display()))?;
    let (mut source, _) = a.depth.source()?;
    let depth = source.depth(&img.data, img.width, img.height)?;
    let cam = a.camera.camera(img.width, img.height)?;
    let invalid = depth
        .iter()
        .filter(|z| !(z.is_finite() && **z > 0.0))
        .count();
    if invalid > 0 {
        Bars::default().event(ProgressEvent::Warning {
            message: format!(
                "{}: {invalid} of {} pixels have no valid depth (NaN, infinite, zero or negative); they go to the back layer",
                source.name(),
                depth.len()
            ),
        });
    }
    let config = SliceConfig {
        layers: a.layers as usize,
        ..SliceConfig::default()
    };
    let set = slice_to(&img.data, &depth, &source.name(), cam, &config, &a.output)?;
    println!(
        "wrote {} layers to {} (depths {})",
        set.len(),
        a.output.display(),
        depth_list(&set)
    );
    Ok(())
}
