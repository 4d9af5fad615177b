//! Where a pipeline's depth, camera and layering configuration come from.

use crate::error::{Context, PipelineError};
use cpsl_core::{Camera, DepthSource, Limits};
use cpsl_layering::{GeometryMode, LayeringConfig};
use std::path::{Path, PathBuf};

/// Where an image's depth comes from.
#[derive(Debug, Clone, PartialEq)]
pub enum DepthChoice {
    /// A depth map: PFM (scene units), 16-bit PNG or `.npy` (integers times `scale`).
    File {
        /// The map.
        path: PathBuf,
        /// Scene units per integer step.
        scale: f32,
    },
    /// A monocular depth model: `fastdepth` or an `.onnx` file, described by `desc` or
    /// `<model>.json`.
    Model {
        /// The model.
        model: String,
        /// Its description.
        desc: Option<PathBuf>,
    },
}

fn check_scale(scale: f32) -> Result<(), PipelineError> {
    if scale.is_finite() && scale > 0.0 {
        Ok(())
    } else {
        Err(PipelineError::Invalid(format!(
            "--depth-scale must be finite and > 0, found {scale}"
        )))
    }
}

impl DepthChoice {
    /// The depth source, and whether it may leave values missing (models may; files must be
    /// complete).
    pub fn open(&self) -> Result<(Box<dyn DepthSource>, bool), PipelineError> {
        Ok(match self {
            DepthChoice::File { path, scale } => {
                check_scale(*scale)?;
                let file = cpsl_io::depth::DepthFile {
                    path: path.clone(),
                    units: cpsl_io::depth::DepthUnits { scale: *scale },
                    limits: Limits::default(),
                };
                (Box::new(file), false)
            }
            DepthChoice::Model { model, desc } => {
                (Box::new(open_depth_model(model, desc.as_deref())?), true)
            }
        })
    }
}

/// Opens a monocular depth model: `fastdepth` (the cached default) or an .onnx path,
/// described by `desc` or `<model>.json`.
pub fn open_depth_model(
    model: &str,
    desc: Option<&Path>,
) -> Result<cpsl_models::OnnxDepth, PipelineError> {
    let path = match model {
        "fastdepth" => cpsl_models::runtime::cache_dir().join("models/fastdepth_7.onnx"),
        other => PathBuf::from(other),
    };
    let desc = desc.map(cpsl_models::DepthModelDesc::load).transpose()?;
    cpsl_models::OnnxDepth::open(&path, desc)
        .context_with(|| format!("loading depth model {}", path.display()))
}

/// Where a video's depth comes from.
pub enum VideoDepth {
    /// A monocular depth model run on the frames.
    Model(Box<dyn DepthSource>),
    /// One depth map per frame.
    Frames(cpsl_io::depth::DepthSequence),
}

impl VideoDepth {
    /// A model (`fastdepth` or an `.onnx` file with its description).
    pub fn model(model: &str, desc: Option<&Path>) -> Result<Self, PipelineError> {
        Ok(VideoDepth::Model(Box::new(open_depth_model(model, desc)?)))
    }

    /// A folder with one depth map per frame in file-name order (PFM in scene units; 16-bit
    /// PNG or `.npy` integers times `scale`).
    pub fn frames(dir: &Path, scale: f32) -> Result<Self, PipelineError> {
        check_scale(scale)?;
        let units = cpsl_io::depth::DepthUnits { scale };
        Ok(VideoDepth::Frames(cpsl_io::depth::DepthSequence::open(
            dir,
            units,
            Limits::default(),
        )?))
    }

    /// Depth of frame `index`.
    pub fn depth(
        &mut self,
        index: usize,
        rgb: &[u8],
        width: u32,
        height: u32,
    ) -> Result<Vec<f32>, PipelineError> {
        Ok(match self {
            VideoDepth::Model(m) => m.depth(rgb, width, height)?,
            VideoDepth::Frames(s) => s.depth_at(index, width, height)?,
        })
    }

    /// A short description, saved with the output.
    pub fn name(&self) -> String {
        match self {
            VideoDepth::Model(m) => m.name(),
            VideoDepth::Frames(s) => format!("depth maps in {}", s.dir.display()),
        }
    }
}

/// The reference camera: intrinsics from a JSON file (as `cpsl synth` writes), or a pinhole
/// of horizontal field of view `fov` degrees.
#[derive(Debug, Clone, PartialEq)]
pub enum CameraChoice {
    /// Intrinsics from a file; the image must have its size.
    File(PathBuf),
    /// A centred pinhole with this horizontal field of view in degrees.
    Fov(f64),
}

impl CameraChoice {
    /// The camera for a `width x height` image.
    pub fn camera(&self, width: u32, height: u32) -> Result<Camera, PipelineError> {
        let cam = match self {
            CameraChoice::File(p) => {
                let bytes = std::fs::read(p).map_err(|source| PipelineError::File {
                    path: p.clone(),
                    source,
                })?;
                let c: Camera = serde_json::from_slice(&bytes)
                    .map_err(|source| PipelineError::Json {
                        path: p.clone(),
                        source,
                    })
                    .context_with(|| format!("{}: not a camera JSON", p.display()))?;
                if (c.width, c.height) != (width, height) {
                    return Err(PipelineError::Invalid(format!(
                        "{}: camera is {}x{} but the image is {width}x{height}",
                        p.display(),
                        c.width,
                        c.height,
                    )));
                }
                c
            }
            CameraChoice::Fov(fov) => Camera::from_fov(width, height, *fov),
        };
        cam.validate().context_with(|| "camera".into())?;
        Ok(cam)
    }
}

/// Reads a layering configuration: a bare configuration (missing fields take their
/// defaults) or a layer set's `config.json`.
pub fn read_config(path: &Path) -> Result<LayeringConfig, PipelineError> {
    let bad = || format!("{}: not a layering configuration", path.display());
    let json = |source| PipelineError::Json {
        path: path.to_path_buf(),
        source,
    };
    let bytes = std::fs::read(path).map_err(|source| PipelineError::File {
        path: path.to_path_buf(),
        source,
    })?;
    let mut v: serde_json::Value = serde_json::from_slice(&bytes)
        .map_err(json)
        .context_with(bad)?;
    if v.get("stage").is_some() {
        v = v["config"].take();
    }
    serde_json::from_value(v).map_err(json).context_with(bad)
}

/// A layering configuration: `config` read with [`read_config`] (or the default), with `K`
/// set to `layers` and the layers' surfaces to `geometry` where given.
pub fn layering_config(
    config: Option<&Path>,
    layers: u32,
    geometry: Option<GeometryMode>,
) -> Result<LayeringConfig, PipelineError> {
    let mut cfg = match config {
        Some(p) => read_config(p)?,
        None => LayeringConfig::default(),
    };
    cfg.layers = layers as usize;
    if let Some(g) = geometry {
        cfg.matte.geometry = g;
    }
    Ok(cfg)
}
