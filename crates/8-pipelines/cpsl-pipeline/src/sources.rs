//! Where a pipeline's depth, camera and layering configuration come from.

use crate::error::{Context, PipelineError};
use cpsl_core::{median_depth, Camera, DepthSource, Limits};
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
    /// Stereo matching of each frame's two views.
    Stereo(StereoDepth),
    /// The video itself: camera tracking and multi-view depth, fused with a monocular prior.
    Tracked(Box<crate::track::VideoTrackedDepth>),
}

/// Depth from a stereo pair per frame: z-depth `f b / (d + offset)` from the left view's
/// disparity `d` (see [`cpsl_stereo`]), with `offset` chosen once, on the first frame: zero
/// when every matched disparity is at least 1 px (a parallel rig: metric depth), else
/// `1 - d_1` px for the 1st percentile `d_1` (converged or shifted pairs, as in 3-D films,
/// whose far content has zero or negative disparity: the farthest content then sits at
/// 1 px). Frames where less than [`StereoDepth::MIN_MATCHED`] of the pixels match (black,
/// blank or broken frames) fall back to the monocular prior when one is given, scaled to the
/// last good frame's median depth, else to the last good depth (or a flat plane); each
/// fallback is reported.
pub struct StereoDepth {
    /// Rig baseline in scene units (metres by default).
    pub baseline: f64,
    /// Matching settings.
    pub config: cpsl_stereo::StereoConfig,
    /// The monocular prior for frames stereo cannot see.
    pub prior: Option<Box<dyn DepthSource>>,
    offset: Option<f64>,
    last: Option<Vec<f32>>,
    note: String,
}

impl StereoDepth {
    /// Least share of matched pixels for a frame's stereo depth to count.
    pub const MIN_MATCHED: f64 = 0.05;
    /// The default baseline: a human interocular distance, 65 mm (stereo films and VR180
    /// cameras are built around it).
    pub const DEFAULT_BASELINE: f64 = 0.065;

    /// Stereo depth with `baseline` (scene units) and an optional prior.
    pub fn new(baseline: f64, prior: Option<Box<dyn DepthSource>>) -> Result<Self, PipelineError> {
        if !(baseline.is_finite() && baseline > 0.0) {
            return Err(PipelineError::Invalid(format!(
                "--baseline must be finite and > 0, found {baseline}"
            )));
        }
        Ok(Self {
            baseline,
            config: cpsl_stereo::StereoConfig::default(),
            prior,
            offset: None,
            last: None,
            note: String::new(),
        })
    }

    /// What the last frame's depth came from: stereo with its share of matched pixels, or the
    /// fallback taken and why.
    pub fn note(&self) -> Option<&str> {
        (!self.note.is_empty()).then_some(self.note.as_str())
    }

    /// Depth of the left view from the pair, for a camera of focal length `focal` px.
    pub fn depth(
        &mut self,
        left: &[u8],
        right: &[u8],
        width: u32,
        height: u32,
        focal: f64,
    ) -> Result<Vec<f32>, PipelineError> {
        let d = cpsl_stereo::match_pair(left, right, width, height, &self.config)?;
        let matched = d.density();
        if matched >= Self::MIN_MATCHED {
            let offset = *self.offset.get_or_insert_with(|| {
                let mut v: Vec<f32> = d
                    .values
                    .iter()
                    .zip(&d.valid)
                    .filter(|(_, &ok)| ok)
                    .map(|(&x, _)| x)
                    .collect();
                v.sort_by(f32::total_cmp);
                let d1 = v[(v.len() - 1) / 100] as f64;
                (1.0 - d1).max(0.0)
            });
            let z = d.depth(focal, self.baseline, offset);
            self.note = format!("stereo, {:.0} % matched", 100.0 * matched);
            self.last = Some(z.clone());
            return Ok(z);
        }
        let why = format!(
            "too little texture for stereo ({:.1} % matched)",
            100.0 * matched
        );
        let reference = self.last.as_deref().and_then(median_depth);
        let z = match &mut self.prior {
            Some(p) => {
                let mut z = p.depth(left, width, height)?;
                if let (Some(r), Some(m)) = (reference, median_depth(&z)) {
                    z.iter_mut().for_each(|v| *v *= r / m);
                }
                self.note = format!("fallback: {why}; {}", p.name());
                z
            }
            None => match &self.last {
                Some(z) => {
                    self.note = format!("fallback: {why}; the last stereo depth");
                    z.clone()
                }
                None => {
                    self.note = format!("fallback: {why}; a flat plane");
                    let far = focal * self.baseline;
                    vec![far as f32; (width * height) as usize]
                }
            },
        };
        Ok(z)
    }
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

    /// Depth of frame `index`, whose (left) view is `rgb` seen by `cam`; `right` is its
    /// right view for stereo input; `model` is the source's monocular model already run on `rgb` ([`Self::model_depth`]),
    /// which a model or the video's depth then take instead of running it again.
    pub fn depth(
        &mut self,
        index: usize,
        rgb: &[u8],
        right: Option<&[u8]>,
        cam: &Camera,
        model: Option<Vec<f32>>,
    ) -> Result<Vec<f32>, PipelineError> {
        let (width, height) = (cam.width, cam.height);
        Ok(match self {
            VideoDepth::Model(m) => match model {
                Some(z) => z,
                None => m.depth(rgb, width, height)?,
            },
            VideoDepth::Frames(s) => s.depth_at(index, width, height)?,
            VideoDepth::Stereo(s) => {
                let right = right.ok_or_else(|| {
                    PipelineError::Invalid(
                        "stereo depth needs stereo input (--stereo sbs|tab)".into(),
                    )
                })?;
                s.depth(rgb, right, width, height, cam.fx)?
            }
            VideoDepth::Tracked(t) => t.depth(index, rgb, cam, model)?,
        })
    }

    /// The source's monocular model (a model, or the prior of the video's depth) run on `rgb`,
    /// seen by `cam`; `None` for sources without one. For work done ahead: [`Self::depth`]
    /// and [`Self::carried`] take it.
    pub fn model_depth(
        &mut self,
        rgb: &[u8],
        cam: &Camera,
    ) -> Option<Result<Vec<f32>, PipelineError>> {
        let m: &mut dyn DepthSource = match self {
            VideoDepth::Model(m) => &mut **m,
            VideoDepth::Tracked(t) => t.prior_mut(),
            VideoDepth::Frames(_) | VideoDepth::Stereo(_) => return None,
        };
        Some(m.depth(rgb, cam.width, cam.height).map_err(Into::into))
    }

    /// Whether [`Self::carried`] carries depth (the video's depth of a translating camera),
    /// so that every P-frame runs the model.
    pub fn carries(&self) -> bool {
        matches!(self, VideoDepth::Tracked(t) if t.carries())
    }

    /// Depth of frame `index` (picture `rgb`, seen by `cam`) carried from frame `from`'s depth
    /// `from_depth` by the camera's motion, where the source knows it (the video itself,
    /// [`crate::track::VideoTrackedDepth::carried`]); `None` otherwise.
    pub fn carried(
        &mut self,
        from: usize,
        from_depth: &[f32],
        index: usize,
        rgb: &[u8],
        cam: &Camera,
        model: Option<&[f32]>,
    ) -> Result<Option<Vec<f32>>, PipelineError> {
        match self {
            VideoDepth::Tracked(t) => t.carried(from, from_depth, index, rgb, cam, model),
            _ => Ok(None),
        }
    }

    /// What the last frame's depth came from, where it is worth saying per frame (stereo,
    /// the video itself, and their fallbacks).
    pub fn note(&self) -> Option<&str> {
        match self {
            VideoDepth::Stereo(s) => s.note(),
            VideoDepth::Tracked(t) => t.note(),
            _ => None,
        }
    }

    /// A short description, saved with the output.
    pub fn name(&self) -> String {
        match self {
            VideoDepth::Model(m) => m.name(),
            VideoDepth::Frames(s) => format!("depth maps in {}", s.dir.display()),
            VideoDepth::Stereo(s) => format!(
                "stereo (SGBM, baseline {} scene units{})",
                s.baseline,
                s.prior
                    .as_ref()
                    .map_or(String::new(), |p| format!("; prior {}", p.name()))
            ),
            VideoDepth::Tracked(t) => t.name(),
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
