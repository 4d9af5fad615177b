//! `cpsl layer-video`: a video (or an image sequence) to a sequence of layer sets, organised
//! in groups of pictures with motion-guided propagation.

use crate::layer::{open_depth_model, read_config, CameraArgs};
use anyhow::{Context, Result};
use clap::{Args, ValueEnum};
use cpsl_core::DepthSource;
use cpsl_core::LayeredFrame;
use cpsl_layering::LayeringConfig;
use cpsl_temporal::{GopConfig, VideoLayerer};
use indicatif::{ProgressBar, ProgressStyle};
use std::path::{Path, PathBuf};
use std::time::Instant;

/// Temporal organisation (the ablation of the paper's Table 2).
#[derive(ValueEnum, Clone, Copy, Debug, PartialEq, Eq)]
pub enum Temporal {
    /// Every frame layered on its own.
    FrameWise,
    /// I/P propagation with a fixed GOP, no refinement, no adaptive refresh.
    Propagation,
    /// I/P propagation, boundary-band moving average, adaptive refresh with hysteresis.
    Full,
}

impl Temporal {
    /// The GOP configuration of this mode with GOP length `gop`.
    pub fn config(self, gop: usize) -> GopConfig {
        let base = match self {
            Temporal::FrameWise => return GopConfig::frame_wise(),
            Temporal::Propagation => GopConfig::propagation_only(),
            Temporal::Full => GopConfig::default(),
        };
        GopConfig { gop, ..base }
    }
}

/// Where P-frame motion comes from.
#[derive(ValueEnum, Clone, Copy, Debug, PartialEq, Eq)]
pub enum MotionSource {
    /// The decoder's motion vectors where the input is H.264 and they cover the frame,
    /// optical flow otherwise.
    Auto,
    /// Always optical flow.
    Flow,
}

/// Arguments of `cpsl layer-video`.
#[derive(Args)]
pub struct LayerVideoArgs {
    /// Input: a video file (any container and codec FFmpeg reads) or a folder of PNG/JPEG
    /// frames (in file-name order).
    pub input: PathBuf,
    /// Output folder: one layer set per frame (`frame_000000/`, ...) and `video.json`. Written
    /// beside it first and moved into place when complete; an existing output of this command
    /// is replaced, any other folder is left alone.
    #[arg(short, long)]
    pub output: PathBuf,
    #[command(flatten)]
    pub layering: VideoLayering,
}

/// How a video is layered (shared by `cpsl layer-video` and `cpsl encode`).
#[derive(Args)]
pub struct VideoLayering {
    /// Most frames per group of pictures (an I-frame at least this often).
    #[arg(long, default_value_t = 30, value_parser = clap::value_parser!(u32).range(1..=600))]
    pub gop: u32,
    /// Target number of layers K.
    #[arg(long, default_value_t = 6, value_parser = clap::value_parser!(u32).range(2..=16))]
    pub layers: u32,
    /// Depth model: `fastdepth` (default) or an .onnx file described by `<model>.json`.
    #[arg(long, default_value = "fastdepth")]
    pub depth_model: String,
    /// Description of the --depth-model.
    #[arg(long)]
    pub model_desc: Option<PathBuf>,
    /// Depth maps instead of a model: a folder with one map per frame in file-name order
    /// (PFM in scene units, 16-bit PNG or .npy as for `cpsl layer --depth`).
    #[arg(long, conflicts_with_all = ["depth_model", "model_desc"])]
    pub depth_frames: Option<PathBuf>,
    /// Scene units per integer step of 16-bit PNG / uint16 .npy --depth-frames.
    #[arg(long, default_value_t = 0.001)]
    pub depth_scale: f32,
    /// Estimate depth on P-frames too (by default their depth is carried along the motion).
    #[arg(long)]
    pub depth_every_frame: bool,
    #[command(flatten)]
    pub camera: CameraArgs,
    /// Temporal organisation.
    #[arg(long, value_enum, default_value_t = Temporal::Full)]
    pub temporal: Temporal,
    /// Motion source for P-frames.
    #[arg(long, value_enum, default_value_t = MotionSource::Auto)]
    pub motion: MotionSource,
    /// Stop after this many frames.
    #[arg(long)]
    pub max_frames: Option<usize>,
    /// Layering configuration as JSON (as for `cpsl layer`); --layers overrides its K.
    #[arg(long)]
    pub config: Option<PathBuf>,
}

/// Where a video's depth comes from.
pub enum VideoDepth {
    /// A monocular depth model run on the frames.
    Model(Box<dyn DepthSource>),
    /// One depth map per frame.
    Frames(cpsl_io::depth::DepthSequence),
}

impl VideoDepth {
    /// Depth of frame `index`.
    fn depth(&mut self, index: usize, rgb: &[u8], width: u32, height: u32) -> Result<Vec<f32>> {
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

impl VideoLayering {
    /// The layering configuration, GOP configuration and depth source these arguments name.
    pub fn setup(&self) -> Result<(LayeringConfig, GopConfig, VideoDepth)> {
        let mut cfg = match &self.config {
            Some(p) => read_config(p)?,
            None => LayeringConfig::default(),
        };
        cfg.layers = self.layers as usize;
        let gop = self.temporal.config(self.gop as usize);
        let depth = match &self.depth_frames {
            Some(dir) => {
                anyhow::ensure!(
                    self.depth_scale.is_finite() && self.depth_scale > 0.0,
                    "--depth-scale must be finite and > 0, found {}",
                    self.depth_scale
                );
                let units = cpsl_io::depth::DepthUnits {
                    scale: self.depth_scale,
                };
                VideoDepth::Frames(cpsl_io::depth::DepthSequence::open(
                    dir,
                    units,
                    cpsl_core::Limits::default(),
                )?)
            }
            None => VideoDepth::Model(Box::new(open_depth_model(
                &self.depth_model,
                self.model_desc.as_deref(),
            )?)),
        };
        Ok((cfg, gop, depth))
    }
}

/// What `layer_video` produced, per frame.
pub struct FrameRecord {
    /// The layered frame.
    pub frame: LayeredFrame,
    /// Whether the decoder's motion vectors were used.
    pub decoder_motion: bool,
    /// Milliseconds for this frame, depth included.
    pub ms: f64,
}

/// Layers every frame of `input` as `how` says, with the configurations and depth model of
/// [`VideoLayering::setup`], and hands each result to `sink`.
pub fn layer_video(
    input: &Path,
    how: &VideoLayering,
    cfg: &LayeringConfig,
    gop: GopConfig,
    depth: &mut VideoDepth,
    mut sink: impl FnMut(&FrameRecord) -> Result<()>,
) -> Result<cpsl_media::Info> {
    let mut src =
        cpsl_media::open(input).with_context(|| format!("opening {}", input.display()))?;
    let info = src.info().clone();
    let cam = how.camera.camera(info.width, info.height)?;
    let mut cfg = *cfg;
    cfg.cues.allow_missing_depth = true;
    let mut layerer = VideoLayerer::new(cam, cfg, gop)?;
    let max_frames = how.max_frames;
    let total = match (info.frames, max_frames) {
        (Some(n), Some(m)) => Some(n.min(m)),
        (n, m) => n.or(m),
    };
    let bar = match total {
        Some(n) => ProgressBar::new(n as u64).with_style(
            ProgressStyle::with_template(
                "{msg:>12} [{bar:30}] {pos}/{len} frames {per_sec} elapsed {elapsed} eta {eta}",
            )
            .expect("template")
            .progress_chars("=> "),
        ),
        None => ProgressBar::new_spinner(),
    };
    bar.set_message("layering");
    let mut count = 0;
    while max_frames.is_none_or(|m| count < m) {
        let Some(frame) = src
            .next_frame()
            .with_context(|| format!("decoding {}", input.display()))?
        else {
            break;
        };
        let t = Instant::now();
        layerer.set_frames_left(total.map(|n| n.saturating_sub(count)));
        let intra = layerer.next_is_intra();
        let z = if intra || how.depth_every_frame {
            Some(depth.depth(frame.index, &frame.rgb, info.width, info.height)?)
        } else {
            None
        };
        let given = match how.motion {
            MotionSource::Auto => frame.motion,
            MotionSource::Flow => None,
        };
        let decoder_motion = given.is_some() && !intra;
        let out = layerer
            .push_with_motion(&frame.rgb, z.as_deref(), given)
            .with_context(|| format!("frame {}", frame.index))?;
        let rec = FrameRecord {
            frame: out,
            decoder_motion,
            ms: t.elapsed().as_secs_f64() * 1e3,
        };
        sink(&rec)?;
        count += 1;
        bar.set_message(if rec.frame.refresh.is_some() {
            "I-frame"
        } else {
            "P-frame"
        });
        bar.inc(1);
    }
    bar.finish_and_clear();
    anyhow::ensure!(count > 0, "{}: no frames", input.display());
    Ok(info)
}

/// Runs `cpsl layer-video`.
pub fn run(a: LayerVideoArgs) -> Result<()> {
    let replaceable = |p: &Path| p.join("video.json").is_file();
    if a.output.exists() && !replaceable(&a.output) {
        anyhow::bail!(
            "{} exists and is not the output of cpsl layer-video; not replacing it",
            a.output.display()
        );
    }
    let (cfg, gop, mut depth) = a.layering.setup()?;
    // Written beside the output and moved into place when complete; on an error the staged
    // folder is removed when `staged` is dropped.
    let staged = cpsl_io::Staged::folder(&a.output, replaceable)?;
    let stage = staged.path();
    let mut records = Vec::new();
    let t = Instant::now();
    let info = layer_video(&a.input, &a.layering, &cfg, gop, &mut depth, |r| {
        let f = &r.frame;
        let dir = format!("frame_{:06}", f.index);
        let edc = f.edc.encode();
        cpsl_io::write_layer_set(
            &stage.join(&dir),
            &f.set,
            &[(cpsl_io::EDC_FILE, edc.as_slice())],
        )?;
        records.push(serde_json::json!({
                "index": f.index,
                "dir": dir,
                "kind": if f.refresh.is_some() { "I" } else { "P" },
                "refresh": f.refresh,
                "tracks": f.set.layers().iter().map(|l| l.meta.track).collect::<Vec<_>>(),
                "confidence": f.confidence,
                "crack": f.crack,
                "depth": if f.depth_propagated { "propagated" } else { "estimated" },
                "motion": if f.refresh.is_some() { "none" } else if r.decoder_motion { "decoder" } else { "flow" },
                "ms": r.ms,
                "timings_ms": f.timings.iter().map(|(s, t)| serde_json::json!({"stage": s, "ms": t})).collect::<Vec<_>>(),
            }));
        Ok(())
    })?;
    let seconds = t.elapsed().as_secs_f64();
    let n = records.len();
    let intra = records.iter().filter(|r| r["kind"] == "I").count();
    let manifest = serde_json::json!({
        "format": "cpsl-video-layers",
        "version": 1,
        "input": a.input.display().to_string(),
        "codec": info.codec,
        "fps": info.fps,
        "width": info.width,
        "height": info.height,
        "rotation": info.rotation,
        "hdr": info.hdr,
        "depth": depth.name(),
        "gop": gop,
        "layering": cfg,
        "frames": records,
    });
    staged.write_file("video.json", &serde_json::to_vec_pretty(&manifest)?)?;
    staged.commit(replaceable)?;
    println!(
        "wrote {n} frames ({intra} I-frames) to {} in {seconds:.1} s ({:.1} frames/s)",
        a.output.display(),
        n as f64 / seconds
    );
    Ok(())
}
