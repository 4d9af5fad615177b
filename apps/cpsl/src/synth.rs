//! `cpsl synth` (synthetic ground truth) and `cpsl slice` (depth slicing).

use crate::layer::{CameraArgs, DepthArgs};
use crate::progress::Bars;
use crate::util;
use anyhow::{Context, Result};
use clap::Args;
use cpsl_core::{Camera, DepthSource, Limits, Pose, Progress, ProgressEvent};
use cpsl_io::images::write_png;
use cpsl_io::pfm::{write_pfm, FloatImage};
use cpsl_layering::{slice_by_depth, SliceConfig};
use cpsl_pipeline::sources::open_depth_model;
use cpsl_synth::Scene;
use serde::Serialize;
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

/// One ground-truth view in `views.json`.
#[derive(Clone, Serialize)]
pub struct ViewEntry {
    /// View name.
    pub name: String,
    /// Image file, relative to the synth folder.
    pub file: String,
    /// Pose as accepted by `cpsl render --pose`.
    pub pose: String,
    /// The full pose.
    pub pose_matrix: Pose,
}

/// `views.json`.
#[derive(Serialize)]
struct ViewsFile<'a> {
    camera: &'a Camera,
    time: f64,
    views: Vec<ViewEntry>,
}

/// A synthetic scene written to disk.
pub struct SynthOutput {
    /// The scene.
    pub scene: Scene,
    /// Input view RGB.
    pub rgb: Vec<u8>,
    /// Input z-depth.
    pub depth: Vec<f32>,
    /// Ground-truth views: entry and RGB.
    pub views: Vec<(ViewEntry, Vec<u8>)>,
}

fn pose_string(p: &Pose) -> String {
    let (rx, ry, rz) = p.euler_deg();
    let t = p.translation;
    // Adding 0.0 turns -0.0 into 0.0; values are rounded to 1e-9 to drop float noise.
    let v = [t.x(), t.y(), t.z(), rx, ry, rz].map(|v| ((v * 1e9).round() / 1e9) + 0.0);
    format!("{},{},{},{},{},{}", v[0], v[1], v[2], v[3], v[4], v[5])
}

/// Renders the default scene and its ground-truth views and writes them to `dir`.
pub fn synthesise(a: &SynthArgs, progress: &dyn Progress) -> Result<SynthOutput> {
    anyhow::ensure!(
        (16..=8192).contains(&a.width) && (16..=8192).contains(&a.height),
        "--width and --height must be in 16..=8192, found {}x{}",
        a.width,
        a.height
    );
    let dir = &a.output;
    std::fs::create_dir_all(dir.join("views"))
        .with_context(|| format!("creating {}", dir.display()))?;
    let scene = Scene::default_scene(a.width, a.height);
    let cam = scene.camera;
    let views = Scene::default_views();
    progress.event(ProgressEvent::Start {
        stage: "ray cast views",
        total: Some(views.len() as u64 + 1),
    });
    let input = scene.render(&cam, &Pose::IDENTITY, a.time, a.supersample);
    progress.event(ProgressEvent::Advance {
        stage: "ray cast views",
        done: 1,
    });
    write_png(&dir.join("input.png"), cam.width, cam.height, 3, &input.rgb)?;
    let depth = FloatImage {
        width: cam.width,
        height: cam.height,
        data: input.depth.clone(),
    };
    write_pfm(&dir.join("depth.pfm"), &depth)?;
    write_png(
        &dir.join("depth.png"),
        cam.width,
        cam.height,
        1,
        &depth_preview(&input.depth),
    )?;
    let ids: Vec<u8> = input.object.iter().map(|&o| o.min(255) as u8).collect();
    write_png(&dir.join("objects.png"), cam.width, cam.height, 1, &ids)?;
    util::write_json(&dir.join("camera.json"), &cam)?;
    util::write_json(&dir.join("scene.json"), &scene)?;
    let mut out_views = Vec::new();
    for (i, (name, pose)) in views.iter().enumerate() {
        let v = scene.render(&cam, pose, a.time, a.supersample);
        let file = format!("views/{name}.png");
        write_png(&dir.join(&file), cam.width, cam.height, 3, &v.rgb)?;
        out_views.push((
            ViewEntry {
                name: name.clone(),
                file,
                pose: pose_string(pose),
                pose_matrix: *pose,
            },
            v.rgb,
        ));
        progress.event(ProgressEvent::Advance {
            stage: "ray cast views",
            done: i as u64 + 2,
        });
    }
    progress.event(ProgressEvent::Finish {
        stage: "ray cast views",
    });
    let file = ViewsFile {
        camera: &cam,
        time: a.time,
        views: out_views.iter().map(|(e, _)| e.clone()).collect(),
    };
    util::write_json(&dir.join("views.json"), &file)?;
    Ok(SynthOutput {
        scene,
        rgb: input.rgb,
        depth: input.depth,
        views: out_views,
    })
}

/// 8-bit preview of a depth map: inverse depth normalised to [0, 255] (near is bright).
fn depth_preview(depth: &[f32]) -> Vec<u8> {
    let inv: Vec<f32> = depth
        .iter()
        .map(|&z| {
            if z.is_finite() && z > 0.0 {
                1.0 / z
            } else {
                0.0
            }
        })
        .collect();
    let (lo, hi) = inv
        .iter()
        .fold((f32::MAX, 0f32), |(a, b), &v| (a.min(v), b.max(v)));
    let span = (hi - lo).max(1e-12);
    inv.iter()
        .map(|&v| ((v - lo) / span * 255.0).round() as u8)
        .collect()
}

/// Runs `cpsl synth`.
pub fn run_synth(a: SynthArgs) -> Result<()> {
    let out = synthesise(&a, &Bars::default())?;
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
