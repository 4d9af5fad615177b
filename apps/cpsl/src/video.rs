//! `cpsl layer-video`: a video (or an image sequence) to a sequence of layer sets, organised
//! in groups of pictures with motion-guided propagation.

use crate::layer::{CameraArgs, StereoArgs};
use crate::progress::Bars;
use anyhow::Result;
use clap::{Args, ValueEnum};
use cpsl_flow::FlowMethod;
use cpsl_layering::GeometryMode;
use cpsl_pipeline::sources::{layering_config, open_depth_model, StereoDepth, VideoDepth};
use cpsl_pipeline::track::VideoTrackedDepth;
use cpsl_pipeline::video::{write_layered_video, MotionSource, PFrameDepth, VideoJob};
use cpsl_temporal::GopConfig;
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
pub enum MotionArg {
    /// The decoder's motion vectors where the input is 8-bit 4:2:0 H.264 and they cover the
    /// frame (each divided by the distance of its reference, found from the pictures), optical
    /// flow otherwise.
    Auto,
    /// Always optical flow: slower (a 720p P-frame's motion about 40 ms against 5-7), closer to the
    /// pictures than block vectors (EVALUATION.md, "The decoder's motion vectors").
    Flow,
}

impl From<MotionArg> for MotionSource {
    fn from(a: MotionArg) -> Self {
        match a {
            MotionArg::Auto => MotionSource::Auto,
            MotionArg::Flow => MotionSource::Flow,
        }
    }
}

/// The optical flow of P-frames.
#[derive(ValueEnum, Clone, Copy, Debug, PartialEq, Eq)]
pub enum FlowArg {
    /// OpenCV's Dense Inverse Search, polished by two Lucas-Kanade steps.
    Dis,
    /// The Lucas-Kanade of `cpsl-flow` (the flow before 2026-11-29).
    LucasKanade,
}

impl From<FlowArg> for FlowMethod {
    fn from(a: FlowArg) -> Self {
        match a {
            FlowArg::Dis => FlowMethod::Dis,
            FlowArg::LucasKanade => FlowMethod::LucasKanade,
        }
    }
}

/// Where P-frames' depth comes from.
#[derive(ValueEnum, Clone, Copy, Debug, PartialEq, Eq)]
pub enum PDepthArg {
    /// The last I-frame's depth carried by the camera's poses, the rest the depth model
    /// fitted to it (with `--depth video`; along the motion with other depth sources).
    Poses,
    /// Carried along the motion with the layers (the paper's: depth on I-frames only).
    Motion,
    /// Estimated on every frame, as on I-frames (with `--depth video` a multi-view pass per
    /// frame: about twice the time).
    Estimated,
}

impl From<PDepthArg> for PFrameDepth {
    fn from(a: PDepthArg) -> Self {
        match a {
            PDepthArg::Poses => PFrameDepth::Poses,
            PDepthArg::Motion => PFrameDepth::Motion,
            PDepthArg::Estimated => PFrameDepth::Estimated,
        }
    }
}

/// Where a video's depth comes from (without --depth-frames or --stereo).
#[derive(ValueEnum, Clone, Copy, Debug, PartialEq, Eq)]
pub enum DepthArg {
    /// The monocular depth model on each frame.
    Model,
    /// Camera tracking and multi-view depth, fused with the depth model.
    Video,
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
    pub layering: VideoLayeringArgs,
}

/// How a video is layered (shared by `cpsl layer-video` and `cpsl encode`).
#[derive(Args)]
pub struct VideoLayeringArgs {
    /// Most frames per group of pictures (an I-frame at least this often).
    #[arg(long, default_value_t = 30, value_parser = clap::value_parser!(u32).range(1..=600))]
    pub gop: u32,
    /// Target number of layers K.
    #[arg(long, default_value_t = 6, value_parser = clap::value_parser!(u32).range(2..=16))]
    pub layers: u32,
    /// Layer surfaces: `plane`, `slanted` (video's default) or `mesh` (single images').
    #[arg(long, long_help = crate::util::GEOMETRY_HELP)]
    pub geometry: Option<GeometryMode>,
    /// Where depth comes from: `video` (the default: the video itself; the camera is tracked
    /// through the whole input first, then each frame's depth is triangulated from up to four
    /// neighbouring frames (chosen so that they see the scene under a wide enough angle) and
    /// fused with the --depth-model, which fills what the views cannot see;
    /// where the camera does not translate (static, only turning, too little texture) or a
    /// frame could not be placed, that frame takes the model's depth and `video.json` says
    /// why) or `model` (the --depth-model on each frame, without the tracking pass).
    #[arg(long, value_enum, default_value_t = DepthArg::Video, conflicts_with_all = ["depth_frames", "stereo"])]
    pub depth: DepthArg,
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
    /// Where P-frames' depth comes from: `poses` (the default: with `--depth video`, the
    /// last I-frame's depth carried by the tracked camera's poses, what it does not reach
    /// from the depth model fitted to it, so that slanted planes and meshes follow the
    /// camera; along the motion with other depth sources), `motion` (carried along the
    /// motion with the layers: the paper's) or `estimated` (as on I-frames: with `--depth
    /// video` a multi-view pass per frame).
    #[arg(long, value_enum, default_value_t = PDepthArg::Poses)]
    pub p_depth: PDepthArg,
    #[command(flatten)]
    pub stereo: StereoArgs,
    #[command(flatten)]
    pub camera: CameraArgs,
    #[command(flatten)]
    pub tracking: crate::layer::TrackingArgs,
    /// Temporal organisation.
    #[arg(long, value_enum, default_value_t = Temporal::Full)]
    pub temporal: Temporal,
    /// Motion source for P-frames.
    #[arg(long, value_enum, default_value_t = MotionArg::Auto)]
    pub motion: MotionArg,
    /// The optical flow P-frames take where the decoder gives no motion.
    #[arg(long, value_enum, default_value_t = FlowArg::Dis)]
    pub flow: FlowArg,
    /// Stop after this many frames.
    #[arg(long)]
    pub max_frames: Option<usize>,
    /// Layering configuration as JSON (as for `cpsl layer`); --layers overrides its K.
    #[arg(long)]
    pub config: Option<PathBuf>,
}

impl VideoLayeringArgs {
    /// The job these arguments describe for `input`, and its depth source.
    pub fn job(&self, input: &Path) -> Result<(VideoJob, VideoDepth)> {
        let depth = self.depth()?;
        Ok((self.video_job(input)?, depth))
    }

    /// The depth source the options give (models are opened here).
    fn depth(&self) -> Result<VideoDepth> {
        let depth = match (&self.depth_frames, self.stereo.stereo) {
            (Some(dir), _) => VideoDepth::frames(dir, self.depth_scale)?,
            (None, Some(_)) => {
                // The monocular model is the prior for frames stereo cannot see; without it
                // (not installed) those frames keep the last stereo depth.
                let prior = open_depth_model(&self.depth_model, self.model_desc.as_deref())
                    .map(|m| Box::new(m) as Box<dyn cpsl_core::DepthSource>);
                if let Err(e) = &prior {
                    eprintln!("warning: no monocular prior for stereo fallbacks: {e}");
                }
                VideoDepth::Stereo(StereoDepth::new(self.stereo.baseline, prior.ok())?)
            }
            (None, None) => match self.depth {
                DepthArg::Model => {
                    VideoDepth::model(&self.depth_model, self.model_desc.as_deref())?
                }
                DepthArg::Video => VideoDepth::Tracked(Box::new(
                    VideoTrackedDepth::new(Box::new(open_depth_model(
                        &self.depth_model,
                        self.model_desc.as_deref(),
                    )?))
                    .with_config(self.tracking.config()),
                )),
            },
        };
        Ok(depth)
    }

    /// The layering job the options give for `input`.
    pub fn video_job(&self, input: &Path) -> Result<VideoJob> {
        Ok(VideoJob {
            input: input.to_path_buf(),
            camera: self.camera.choice(),
            layering: layering_config(
                self.config.as_deref(),
                self.layers,
                Some(self.geometry.unwrap_or(GeometryMode::VIDEO_DEFAULT)),
            )?,
            gop: GopConfig {
                flow: self.flow.into(),
                ..self.temporal.config(self.gop as usize)
            },
            motion: self.motion.into(),
            p_depth: self.p_depth.into(),
            max_frames: self.max_frames,
            stereo: self.stereo.stereo,
        })
    }
}

/// Runs `cpsl layer-video`.
pub fn run(a: LayerVideoArgs) -> Result<()> {
    let (job, mut depth) = a.layering.job(&a.input)?;
    let t = Instant::now();
    let m = write_layered_video(&job, &mut depth, &a.output, &Bars::default())?;
    let seconds = t.elapsed().as_secs_f64();
    let n = m.frames.len();
    let intra = m.frames.iter().filter(|f| f.kind == "I").count();
    println!(
        "wrote {n} frames ({intra} I-frames) to {} in {seconds:.1} s ({:.1} frames/s)",
        a.output.display(),
        n as f64 / seconds
    );
    let notes = m.frames.iter().map(|f| (f.index, f.depth_note.as_deref()));
    crate::util::print_depth_runs(&cpsl_pipeline::video::depth_runs(notes));
    crate::util::warn_damaged(&a.input, m.damaged_packets);
    Ok(())
}
