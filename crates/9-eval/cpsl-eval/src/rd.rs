//! Rate-distortion curves (`cpsl eval-rd`) of coded CPSL against two baselines coded with the
//! same codec (paper §4.2-4.3), on a synthetic moving clip with ray-cast ground truth, or on
//! the fox video, whose poses make its neighbouring frames the truth at novel views:
//!
//! * **CPSL**: the video layered with I/P propagation (the clip's depth on I-frames), coded as a
//!   package under a total budget (per-layer allocation), decoded and rendered with the
//!   Dynamic Pixel Strip.
//! * **DIBR streaming**: colour over quantised inverse depth in one stream, rendered by forward
//!   warping with push-pull hole filling; twice: 8-bit depth in an 8-bit stream (`dibr`) and
//!   16-bit depth in a 10-bit stream (`dibr-16`, the 877 levels of 10-bit limited range).
//! * **MPI**: a uniform multiplane image (planes fixed over the clip, uniform in inverse depth,
//!   hard alpha), every plane a colour-over-alpha stream at one quality.
//!
//! Every method is also scored uncompressed; the proxy distortion of the allocator is compared
//! with LPIPS over the coded layered points.

use crate::baselines::dibr;
use crate::error::{Context, EvalError};
use crate::metrics::{blacken, psnr, psnr_masked};
use cpsl_codec::yuv::Yuv420;
use cpsl_codec::{CodingOptions, Container, PackageWriter, RateControl};
use cpsl_core::{
    Camera, Edc, Layer, LayerSet, LayeredFrame, Limits, Pose, PremulImage, Progress, ProgressEvent,
    RefreshReason,
};
use cpsl_layering::GeometryMode;
use cpsl_package::Codec;
use cpsl_pipeline::video::PFrameDepth;
use cpsl_render::{CpuRenderer, DpsConfig, Filter, FrameLayers};
use cpsl_temporal::{GopConfig, VideoLayerer};
use serde::Serialize;
use std::path::{Path, PathBuf};

type Result<T> = std::result::Result<T, EvalError>;

/// The clips.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum RdClip {
    /// The built-in scene moving, ray cast with exact depth; novel views at tx = +-0.12.
    Synthetic,
    /// The fox phone video at half size (540x960, up to 50 frames), FastDepth scaled by the
    /// poses; a scored frame is rendered at each neighbouring frame's camera that is 2 to 30
    /// degrees away and scored against that frame.
    Fox,
}

/// What CPSL's layering is given of the clip's pictures.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Default)]
pub enum RdInput {
    /// The pictures themselves; P-frames' motion from optical flow.
    #[default]
    Pictures,
    /// The pictures coded as H.264 by the `ffmpeg` tool at libx264's defaults (preset medium:
    /// three B-frames, three references) at CRF 12, as a camera's or a download's file is, and
    /// decoded; P-frames' motion from its motion vectors where they cover the frame (as
    /// `cpsl layer-video --motion auto`), from optical flow otherwise.
    H264Vectors,
    /// The same decoded pictures, every P-frame's motion from optical flow (`--motion flow`).
    H264Flow,
}

impl RdInput {
    /// The name in the report.
    pub fn name(self) -> &'static str {
        match self {
            RdInput::Pictures => "pictures",
            RdInput::H264Vectors => "h264",
            RdInput::H264Flow => "h264-flow",
        }
    }
}

/// What to evaluate, and how.
#[derive(Debug, Clone)]
pub struct RdOptions {
    /// Clip.
    pub clip: RdClip,
    /// Folder holding the datasets (for the fox).
    pub data: PathBuf,
    /// Width of the synthetic clip.
    pub width: u32,
    /// Height of the synthetic clip.
    pub height: u32,
    /// Frames of the clip.
    pub frames: u32,
    /// Number of CPSL layers K.
    pub layers: u32,
    /// Layer surfaces for CPSL (`None`: the configuration's, by default the best).
    pub geometry: Option<GeometryMode>,
    /// Planes of the MPI baseline.
    pub mpi_planes: u32,
    /// Codec of every method's streams.
    pub codec: Codec,
    /// How the layer streams are stored.
    pub container: Container,
    /// Where CPSL's segments start (the MPI's start every GOP either way).
    pub segments: cpsl_codec::Segments,
    /// CPSL layered for each budget with the refresh threshold it sets
    /// (`GopConfig::for_budget`); off: one layering for every budget.
    pub rate_aware_refresh: bool,
    /// CPSL budgets (total bits per second).
    pub bitrates: Vec<f64>,
    /// Qualities (CRF) of the baselines; five points spread over the codec's range if `None`.
    pub qualities: Option<Vec<f32>>,
    /// Score every N-th frame (at two novel viewpoints each).
    pub score_every: u32,
    /// Score LPIPS.
    pub lpips: bool,
    /// How the CPU renderer resamples the layered methods' layers.
    pub filter: Filter,
    /// The fox's depth from the video itself (camera tracking, multi-view depth fused with
    /// FastDepth; [`crate::tracking::video_depth`]) instead of FastDepth alone.
    pub video_depth: bool,
    /// Where CPSL's P-frames take their depth: carried along the motion, carried from the
    /// I-frame by the tracked poses (the fox with depth from the video; along the motion
    /// otherwise), or the clip's own depth of every frame.
    pub p_depth: PFrameDepth,
    /// What CPSL's layering is given of the pictures (the baselines always take them as they
    /// are).
    pub input: RdInput,
}

/// Everything a run measured (the JSON of `cpsl eval-rd --json`).
#[derive(Serialize)]
pub struct RdReport {
    /// What the clip is, its size, the frames scored and the novel viewpoints.
    pub clip: serde_json::Value,
    /// The codec's name.
    pub codec: &'static str,
    /// CPSL's K.
    pub layers: u32,
    /// The MPI's planes.
    pub mpi_planes: u32,
    /// Every method's curve.
    pub curves: Vec<Curve>,
    /// The headline numbers.
    pub summary: Summary,
}

/// Frame rate of the clip.
const FPS: f64 = 30.0;
/// The novel viewpoints scored (scene units; the nearest object is at depth 2.5).
const NOVEL: [[f64; 3]; 2] = [[0.12, 0.0, 0.0], [-0.12, 0.0, 0.0]];

/// One point of a curve.
#[derive(Debug, Serialize, Clone)]
pub struct Point {
    /// The rate control asked for: a budget (`3M`) or a quality (`crf 23`); `uncompressed`.
    pub setting: String,
    /// Bits per second actually spent (`null` uncompressed).
    pub bitrate: Option<f64>,
    /// Mean novel-view PSNR (dB) over the scored frames and viewpoints.
    pub psnr: f64,
    /// Mean novel-view LPIPS.
    pub lpips: Option<f64>,
    /// The allocator's proxy distortion of the decoded layers (layered methods).
    pub proxy: Option<f64>,
    /// Under a budget, each segment's frames, budget and spending (kbit).
    #[serde(skip_serializing_if = "Vec::is_empty")]
    pub segments: Vec<SegmentSpend>,
}

/// What one segment of a coded point was given and spent.
#[derive(Debug, Serialize, Clone, PartialEq)]
pub struct SegmentSpend {
    /// Its frames.
    pub frames: u32,
    /// Its budget in kbit.
    pub budget_kbit: f64,
    /// What its streams took, in kbit.
    pub spent_kbit: f64,
    /// Streams fitted by trial encodes (the others' models came from the segment before).
    pub fitted: usize,
}

/// One method's curve.
#[derive(Debug, Serialize)]
pub struct Curve {
    /// The method.
    pub method: &'static str,
    /// Its uncoded point.
    pub uncompressed: Point,
    /// Its coded points.
    pub points: Vec<Point>,
}

/// A baseline's bitrate at the PSNR of a CPSL point, divided by CPSL's.
#[derive(Serialize, Clone, Copy, Debug, PartialEq)]
#[serde(rename_all = "snake_case")]
pub enum Ratio {
    /// Interpolated on the baseline's curve.
    Equal(f64),
    /// The baseline's cheapest point already does better: the ratio is at most this.
    AtMost(f64),
    /// The baseline does worse at every rate measured.
    Never,
}

impl std::fmt::Display for Ratio {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        match self {
            Ratio::Equal(r) => write!(f, "{r:.2}"),
            Ratio::AtMost(r) => write!(f, "< {r:.2}"),
            Ratio::Never => write!(f, "never reached"),
        }
    }
}

/// The ratio of `base`'s bitrate to `rate` at `psnr`.
fn ratio(base: &[Point], psnr: f64, rate: f64) -> Ratio {
    if let Some(r) = rate_at(base, psnr) {
        return Ratio::Equal(r / rate);
    }
    let coded = || base.iter().filter_map(|p| Some((p.bitrate?, p.psnr)));
    let cheapest = coded().min_by(|a, b| a.0.total_cmp(&b.0));
    match cheapest {
        Some((r, p)) if p >= psnr => Ratio::AtMost(r / rate),
        _ => Ratio::Never,
    }
}

/// The headline numbers.
#[derive(Debug, Serialize)]
pub struct Summary {
    /// Per CPSL point: DIBR's bitrate at the same PSNR divided by CPSL's.
    pub dibr_rate_ratio: Vec<Ratio>,
    /// The same for DIBR with 16-bit depth.
    pub dibr16_rate_ratio: Vec<Ratio>,
    /// The same for the MPI.
    pub mpi_rate_ratio: Vec<Ratio>,
    /// Uncompressed CPSL PSNR minus the best CPSL PSNR at no more than 3 Mbit/s.
    pub cpsl_gap_at_3m_db: Option<f64>,
    /// Spearman rank correlation of the proxy distortion with LPIPS over the coded CPSL and
    /// MPI points.
    pub proxy_lpips_spearman: Option<f64>,
}

/// A clip: frames with depth, and the truth at the novel viewpoints of the scored frames.
struct Clip {
    /// What the clip is and where its views are, for the report.
    description: String,
    camera: Camera,
    rgb: Vec<Vec<u8>>,
    depth: Vec<Vec<f32>>,
    views: Vec<View>,
    /// What carries an I-frame's depth to a P-frame by the camera's poses, where known.
    carrier: Option<crate::video::DepthCarrier>,
}

/// A scored novel view.
struct View {
    /// The frame rendered.
    frame: usize,
    /// The viewpoint, relative to that frame's camera.
    pose: Pose,
    /// The true image there (black outside `scored`).
    truth: Vec<u8>,
    /// The pixels scored, where not all: those of the truth that the frame sees.
    scored: Option<Vec<bool>>,
}

fn ray_cast(a: &RdOptions, bars: &dyn Progress) -> Clip {
    let scene = cpsl_synth::Scene::default_scene(a.width, a.height);
    let cam = scene.camera;
    let poses: Vec<Pose> = NOVEL
        .iter()
        .map(|t| Pose::from_translation(cpsl_core::Vec3::new(t[0], t[1], t[2])))
        .collect();
    let n = a.frames as usize;
    let stage = "ray cast clip";
    bars.event(ProgressEvent::Start {
        stage,
        total: Some(n as u64),
    });
    let (mut rgb, mut depth, mut views) = (vec![], vec![], vec![]);
    for i in 0..n {
        let time = i as f64 / FPS;
        let v = scene.render(&cam, &Pose::IDENTITY, time, 2);
        rgb.push(v.rgb);
        depth.push(v.depth);
        if i % a.score_every as usize == 0 {
            for pose in &poses {
                views.push(View {
                    frame: i,
                    pose: *pose,
                    truth: scene.render(&cam, pose, time, 2).rgb,
                    scored: None,
                });
            }
        }
        bars.event(ProgressEvent::Advance {
            stage,
            done: i as u64 + 1,
        });
    }
    bars.event(ProgressEvent::Finish { stage });
    Clip {
        description: format!(
            "synthetic {}x{} clip (exact depth), {n} frames at {FPS} fps; novel views at tx +-{} every {} frames",
            a.width, a.height, NOVEL[0][0], a.score_every
        ),
        camera: cam,
        rgb,
        depth,
        views,
        carrier: None,
    }
}

/// Rotation angle of a pose in degrees.
fn rotation_deg(p: &Pose) -> f64 {
    let r = &p.rotation.0;
    ((r[0][0] + r[1][1] + r[2][2] - 1.0) / 2.0)
        .clamp(-1.0, 1.0)
        .acos()
        .to_degrees()
}

/// The fox at half size: every `score_every`-th frame is rendered at the cameras of its
/// neighbouring frames that are 2 to 30 degrees away (the data's README: pairs closer than
/// that barely move, farther ones mostly leave the frame) and scored against them.
fn fox_clip(a: &RdOptions) -> Result<Clip> {
    let mut f = crate::video::load_fox(&a.data, 2, a.video_depth)?;
    let n = f.frames.len().min(a.frames as usize);
    f.frames.truncate(n);
    f.depth.truncate(n);
    let mut views = Vec::new();
    for i in (0..n).step_by(a.score_every as usize) {
        for j in [i.wrapping_sub(1), i + 1] {
            if j < n {
                let pose = f.video.relative(i, j);
                if (2.0..=30.0).contains(&rotation_deg(&pose)) {
                    let scored = seen_from(&f.depth[j], &f.camera, &pose);
                    let mut t = f.frames[j].clone();
                    blacken(&mut t, &scored);
                    views.push(View {
                        frame: i,
                        pose,
                        truth: t,
                        scored: Some(scored),
                    });
                }
            }
        }
    }
    if views.is_empty() {
        return Err(EvalError::Invalid(
            "fox: no scored view (lower --score-every)".into(),
        ));
    }
    Ok(Clip {
        description: format!(
            "fox {}x{}, {n} frames at {FPS} fps, {}; {} novel views (the neighbouring frames 2 to 30 degrees away of every {}-th frame, scored where the frame sees them)",
            f.camera.width,
            f.camera.height,
            f.depth_name,
            views.len(),
            a.score_every
        ),
        camera: f.camera,
        rgb: f.frames,
        depth: f.depth,
        views,
        carrier: f.carrier,
    })
}

/// The pixels of a view, with depth `depth` and at `pose` relative to a frame with the same
/// camera, whose scene point the frame sees (in its image, in front of it). Only these can be
/// scored against the view: the rest is outside what the frame holds, and each method would
/// be scored on how it fills it.
fn seen_from(depth: &[f32], cam: &Camera, pose: &Pose) -> Vec<bool> {
    let (w, h) = (cam.width as usize, cam.height as usize);
    (0..w * h)
        .map(|p| {
            let z = depth[p] as f64;
            if !(z.is_finite() && z > 0.0) {
                return false;
            }
            let x = cam.unproject((p % w) as f64, (p / w) as f64, z);
            cam.project(pose.view_to_ref(x)).is_some_and(|(u, v)| {
                (-0.5..w as f64 - 0.5).contains(&u) && (-0.5..h as f64 - 0.5).contains(&v)
            })
        })
        .collect()
}

/// Scores views rendered by `render(frame, pose)` against the truth: mean PSNR and LPIPS.
fn score(
    clip: &Clip,
    lpips: &mut Option<cpsl_models::Lpips>,
    mut render: impl FnMut(usize, &Pose) -> Result<Vec<u8>>,
) -> Result<(f64, Option<f64>)> {
    let (w, h) = (clip.camera.width, clip.camera.height);
    let (mut p, mut l) = (0.0, 0.0);
    for v in &clip.views {
        let mut img = render(v.frame, &v.pose)?;
        p += match &v.scored {
            Some(s) => {
                blacken(&mut img, s);
                psnr_masked(&img, &v.truth, s)
                    .ok_or_else(|| EvalError::Invalid("a view with no pixel to score".into()))?
            }
            None => psnr(&img, &v.truth),
        };
        if let Some(m) = lpips {
            l += m.distance(&img, &v.truth, w, h)? as f64;
        }
    }
    let n = clip.views.len() as f64;
    Ok((p / n, lpips.as_ref().map(|_| l / n)))
}

/// The view of `frame` at `pose`, with or without the Dynamic Pixel Strip, what it leaves
/// uncovered filled as a viewer fills it ([`cpsl_core::PremulImage::over_fill`]; DIBR fills its holes
/// the same way).
fn render_layers(frame: &FrameLayers, dps: bool, pose: &Pose, filter: Filter) -> Vec<u8> {
    let cam = frame.set.camera();
    let img = CpuRenderer::new(filter).view(frame, pose, cam, dps.then_some(&DpsConfig::DEFAULT));
    img.over_fill()
}

/// A picture of the clip after H.264, and the decoder's motion to the one before.
type DecodedPicture = (Vec<u8>, Option<cpsl_core::Flow>);

/// The clip's pictures through H.264 ([`RdInput::H264Vectors`]), coded into `dir`; the
/// decoder's motion only where `vectors` asks for it.
fn through_h264(dir: &Path, clip: &Clip, vectors: bool) -> Result<Vec<DecodedPicture>> {
    use std::io::Write;
    let (w, h) = (clip.camera.width, clip.camera.height);
    let path = dir.join("input.mp4");
    let tool = |e: std::io::Error| {
        EvalError::Invalid(format!("running the ffmpeg tool (apt install ffmpeg): {e}"))
    };
    let mut child = std::process::Command::new("ffmpeg")
        .args([
            "-v", "error", "-y", "-f", "rawvideo", "-pix_fmt", "rgb24", "-s",
        ])
        .arg(format!("{w}x{h}"))
        .args([
            "-r",
            &FPS.to_string(),
            "-i",
            "pipe:0",
            "-vf",
            "scale=out_color_matrix=bt709",
        ])
        .args(["-c:v", "libx264", "-crf", "12", "-pix_fmt", "yuv420p"])
        .args([
            "-colorspace",
            "bt709",
            "-color_primaries",
            "bt709",
            "-color_trc",
            "bt709",
        ])
        .arg(&path)
        .stdin(std::process::Stdio::piped())
        .spawn()
        .map_err(tool)?;
    let mut stdin = child.stdin.take().expect("piped");
    for f in &clip.rgb {
        stdin.write_all(f).map_err(tool)?;
    }
    drop(stdin);
    if !child.wait().map_err(tool)?.success() {
        return Err(EvalError::Invalid(
            "the ffmpeg tool failed to code the clip as H.264".into(),
        ));
    }
    let media = |e: cpsl_media::MediaError| EvalError::Invalid(format!("{}: {e}", path.display()));
    let mut src = cpsl_media::open_with(&path, vectors).map_err(media)?;
    let mut out = Vec::with_capacity(clip.rgb.len());
    while let Some(f) = src.next_frame().map_err(media)? {
        out.push((f.rgb, f.motion));
    }
    if out.len() != clip.rgb.len() {
        return Err(EvalError::Invalid(format!(
            "{}: {} of {} pictures decoded",
            path.display(),
            out.len(),
            clip.rgb.len()
        )));
    }
    Ok(out)
}

/// CPSL: I/P propagation with the clip's depth on I-frames (P-frames as `a.p_depth` says).
fn cpsl_layers(
    clip: &Clip,
    a: &RdOptions,
    gop: GopConfig,
    decoded: Option<&[DecodedPicture]>,
    bars: &dyn Progress,
) -> Result<Vec<LayeredFrame>> {
    let mut cfg = cpsl_layering::LayeringConfig {
        layers: a.layers as usize,
        ..Default::default()
    };
    cfg.matte.geometry = a.geometry.unwrap_or(GeometryMode::VIDEO_DEFAULT);
    let mut layerer = VideoLayerer::new(clip.camera, cfg, gop)?;
    let stage = "layer clip";
    bars.event(ProgressEvent::Start {
        stage,
        total: Some(clip.rgb.len() as u64),
    });
    let mut frames = Vec::with_capacity(clip.rgb.len());
    let mut intra = 0;
    for (i, (rgb, depth)) in clip.rgb.iter().zip(&clip.depth).enumerate() {
        let (rgb, motion) = match decoded {
            Some(d) => (&d[i].0, d[i].1.clone()),
            None => (rgb, None),
        };
        layerer.set_frames_left(Some(clip.rgb.len() - i));
        let is_intra = layerer.next_is_intra();
        if is_intra {
            intra = i;
        }
        let carried = match (&clip.carrier, a.p_depth) {
            (Some(c), PFrameDepth::Poses) if !is_intra => {
                c.carry(intra, &clip.depth[intra], i, rgb)?
            }
            _ => None,
        };
        let z = match a.p_depth {
            _ if is_intra => Some(depth.as_slice()),
            PFrameDepth::Estimated => Some(depth.as_slice()),
            PFrameDepth::Poses | PFrameDepth::Motion => carried.as_deref(),
        };
        let frame = layerer.push_with_motion(rgb, z, motion);
        frames.push(frame.context_with(|| format!("frame {i}"))?);
        bars.event(ProgressEvent::Advance {
            stage,
            done: i as u64 + 1,
        });
    }
    bars.event(ProgressEvent::Finish { stage });
    Ok(frames)
}

/// Inverse-depth range of the clip (`1/far`, `1/near`): its 0.1% and 99.9% quantiles, so that
/// a few stray values of an estimated depth map (the fox's FastDepth) do not stretch the
/// range that the MPI's planes and DIBR's 8-bit depth spread over; values outside it are
/// clamped to its ends.
fn inverse_range(clip: &Clip) -> (f64, f64) {
    let mut v: Vec<f64> = clip
        .depth
        .iter()
        .flatten()
        .step_by(16)
        .filter(|d| d.is_finite() && **d > 0.0)
        .map(|d| 1.0 / *d as f64)
        .collect();
    if v.is_empty() {
        return (1.0, 1.0 + 1e-6);
    }
    let q = |v: &mut Vec<f64>, t: f64| {
        let i = ((v.len() - 1) as f64 * t).round() as usize;
        *v.select_nth_unstable_by(i, f64::total_cmp).1
    };
    let lo = q(&mut v, 0.001);
    let hi = q(&mut v, 0.999);
    (lo, hi.max(lo * (1.0 + 1e-6)))
}

/// MPI: `planes` planes uniform in inverse depth over the clip's range, fixed for every frame,
/// each pixel fully in the plane of its depth; an I-frame every GOP.
fn mpi_layers(clip: &Clip, planes: usize, gop: usize) -> Result<Vec<LayeredFrame>> {
    let (lo, hi) = inverse_range(clip);
    let step = (hi - lo) / planes as f64;
    let cam = clip.camera;
    let (w, h) = (cam.width as usize, cam.height as usize);
    let mut frames = Vec::with_capacity(clip.rgb.len());
    for (i, (rgb, depth)) in clip.rgb.iter().zip(&clip.depth).enumerate() {
        let mut data = vec![vec![0u8; w * h * 4]; planes];
        for p in 0..w * h {
            let d = depth[p];
            if !(d.is_finite() && d > 0.0) {
                continue;
            }
            // Plane 0 is the nearest (largest inverse depth); the cast saturates, so depths
            // outside the range land in the end planes.
            let k = (((hi - 1.0 / d as f64) / step) as usize).min(planes - 1);
            data[k][p * 4..p * 4 + 3].copy_from_slice(&rgb[p * 3..p * 3 + 3]);
            data[k][p * 4 + 3] = 255;
        }
        let layers = data
            .into_iter()
            .enumerate()
            .map(|(k, d)| {
                let z = 1.0 / (hi - (k as f64 + 0.5) * step);
                Ok(Layer::new(
                    PremulImage::from_premul(cam.width, cam.height, d)?,
                    z,
                ))
            })
            .collect::<Result<Vec<_>>>()?;
        let set = LayerSet::new(cam, layers, &Limits::default())?;
        let refresh = match i {
            0 => Some(RefreshReason::First),
            _ => (i % gop == 0).then_some(RefreshReason::Gop),
        };
        frames.push(LayeredFrame::new(
            i as u32,
            refresh,
            set,
            Edc::empty(cam.width, cam.height, planes as u16, 1.0 / 64.0),
        ));
    }
    Ok(frames)
}

/// The source and decoded layers of a scored frame.
struct Coded {
    bitrate: f64,
    segments: Vec<SegmentSpend>,
    /// Per frame index: the decoded layers and their Edge-Depth Cache.
    frames: std::collections::HashMap<usize, FrameLayers>,
}

/// Codes `frames` as a package in `dir` with `rate`, and decodes the scored frames.
fn code(
    dir: &Path,
    frames: &[LayeredFrame],
    k: u32,
    (codec, container, segments): (Codec, Container, cpsl_codec::Segments),
    rate: RateControl,
    wanted: &[usize],
) -> Result<Coded> {
    let path = dir.join("rd.cpsl");
    let cam = *frames[0].set.camera();
    let opts = CodingOptions {
        codec,
        rate,
        fps: FPS,
        gop: GopConfig::default().gop as u32,
        container,
        segments,
    };
    let mut writer = PackageWriter::create(&path, cam, k, opts)?;
    let mut reports = Vec::new();
    // As `cpsl encode` does: frame by frame, the writer told how many are left.
    for (i, f) in frames.iter().enumerate() {
        writer.set_frames_left(Some((frames.len() - i) as u32));
        reports.extend(writer.push(f.clone())?);
    }
    reports.extend(writer.flush()?);
    let spend = reports
        .iter()
        .filter_map(|r| {
            Some(SegmentSpend {
                frames: r.frames,
                budget_kbit: r.budget_bits? / 1e3,
                spent_kbit: r.bits / 1e3,
                fitted: r.fitted,
            })
        })
        .collect();
    let m = writer.finish()?;
    // Only the frames scored are decoded and kept (a 32-plane MPI segment at 1080p would
    // not fit in memory whole), in order, so that the player decodes each segment once.
    let mut player = cpsl_player::Player::open(&path)?;
    let mut scored: Vec<u32> = wanted.iter().map(|&f| f as u32).collect();
    scored.sort_unstable();
    scored.dedup();
    let decoded = scored
        .into_iter()
        .filter(|&f| f < m.frames)
        .map(|f| Ok((f as usize, player.decode(f)?)))
        .collect::<Result<_>>()?;
    std::fs::remove_dir_all(&path).map_err(|e| EvalError::file(&path, e))?;
    // Every byte a viewer fetches but the manifest: the init segments too, spread over the
    // clip (the baselines' MP4 files carry theirs in every file).
    let init_bits: u64 = m.inits.iter().map(|f| f.bytes * 8).sum();
    Ok(Coded {
        bitrate: m.bitrate() + init_bits as f64 * m.frame_rate / m.frames as f64,
        segments: spend,
        frames: decoded,
    })
}

/// The allocator's proxy distortion (visibility-weighted squared error of the premultiplied
/// RGBA, summed over layers, per sample) of decoded frames against their sources.
fn proxy(frames: &[LayeredFrame], coded: &Coded) -> f64 {
    let (mut e, mut n) = (0.0, 0.0);
    for f in frames {
        let Some(dec) = coded.frames.get(&(f.index as usize)).map(|d| &d.set) else {
            continue;
        };
        let cam = f.set.camera();
        let src = f.set.layers();
        for (k, (s, d)) in src.iter().zip(dec.layers()).enumerate() {
            let front: Vec<&PremulImage> = src[..k].iter().map(|l| &l.image).collect();
            let vis = cpsl_codec::alloc::visibility(&front, cam.width, cam.height);
            e += cpsl_codec::alloc::distortion(&s.image, &d.image, &vis);
        }
        n += 4.0 * (cam.width * cam.height) as f64;
    }
    e / n.max(1.0)
}

/// Bitrate of `curve` at `target` PSNR, interpolated linearly in log-rate between the two
/// points that bracket it (`None` outside the curve).
fn rate_at(curve: &[Point], target: f64) -> Option<f64> {
    let mut pts: Vec<(f64, f64)> = curve
        .iter()
        .filter_map(|p| Some((p.bitrate?.ln(), p.psnr)))
        .collect();
    pts.sort_by(|a, b| a.0.total_cmp(&b.0));
    pts.windows(2).find_map(|w| {
        let ((r0, p0), (r1, p1)) = (w[0], w[1]);
        let (lo, hi) = (p0.min(p1), p0.max(p1));
        if !(lo..=hi).contains(&target) || (p1 - p0).abs() < 1e-9 {
            return None;
        }
        Some((r0 + (target - p0) / (p1 - p0) * (r1 - r0)).exp())
    })
}

/// Spearman rank correlation.
fn spearman(x: &[f64], y: &[f64]) -> Option<f64> {
    if x.len() < 3 {
        return None;
    }
    let rank = |v: &[f64]| {
        let mut idx: Vec<usize> = (0..v.len()).collect();
        idx.sort_by(|&a, &b| v[a].total_cmp(&v[b]));
        let mut r = vec![0.0; v.len()];
        for (i, &j) in idx.iter().enumerate() {
            r[j] = i as f64;
        }
        r
    };
    let (rx, ry) = (rank(x), rank(y));
    let n = x.len() as f64;
    let mean = (n - 1.0) / 2.0;
    let cov: f64 = rx
        .iter()
        .zip(&ry)
        .map(|(a, b)| (a - mean) * (b - mean))
        .sum();
    let var: f64 = rx.iter().map(|a| (a - mean).powi(2)).sum();
    Some(cov / var)
}

/// LPIPS, which the curves need once asked for.
fn open_lpips() -> Result<cpsl_models::Lpips> {
    cpsl_models::Lpips::open(&cpsl_models::lpips::default_path())
        .context_with(|| "LPIPS (scripts/setup-models.sh, or --no-lpips)".into())
}

/// The baselines' qualities: `given`, or five points spread over the codec's range.
fn baseline_qualities(codec: Codec, given: Option<&[f32]>) -> Result<Vec<f32>> {
    let (q_min, q_max, _) = cpsl_codec::quality_range(codec);
    let qualities = match given {
        Some(q) => q.to_vec(),
        None => [0.2, 0.35, 0.5, 0.65, 0.8]
            .iter()
            .map(|t| (q_min + t * (q_max - q_min)).round())
            .collect(),
    };
    if let Some(q) = qualities.iter().find(|q| !(q_min..=q_max).contains(*q)) {
        return Err(EvalError::Invalid(format!(
            "--qualities {q}: {} takes {q_min} to {q_max}",
            codec.name()
        )));
    }
    Ok(qualities)
}

/// How DIBR's colour-over-depth stream is coded.
struct DibrStream<'a> {
    /// 16-bit depth in a 10-bit stream, else 8-bit in 8-bit.
    deep: bool,
    codec: Codec,
    /// Where the stream is written.
    path: &'a Path,
    /// Depth to `[0, 1]`.
    to_unit: &'a dyn Fn(f32) -> f64,
    /// Back to depth.
    from_unit: &'a dyn Fn(f64) -> f32,
}

/// DIBR streaming's curve: the clip coded at every quality, decoded, warped and scored;
/// `on_point` sees each point as it is measured.
fn dibr_curve(
    clip: &Clip,
    stream: &DibrStream<'_>,
    qualities: &[f32],
    uncompressed: &Point,
    lpips: &mut Option<cpsl_models::Lpips>,
    on_point: &mut dyn FnMut(&str, &Point),
) -> Result<Curve> {
    let cam = clip.camera;
    let mut curve = Curve {
        method: if stream.deep { "dibr-16" } else { "dibr" },
        uncompressed: uncompressed.clone(),
        points: Vec::new(),
    };
    for &q in qualities {
        let (path, codec, to, from) = (stream.path, stream.codec, stream.to_unit, stream.from_unit);
        let (bytes, decoded) = if stream.deep {
            dibr_stream::<u16>(path, clip, codec, q, &to, &from)?
        } else {
            dibr_stream::<u8>(path, clip, codec, q, &to, &from)?
        };
        if decoded.len() != clip.rgb.len() {
            return Err(EvalError::Invalid("DIBR stream lost frames".into()));
        }
        let (p, l) = score(clip, lpips, |f, pose| {
            let (rgb, depth) = &decoded[f];
            Ok(dibr(rgb, depth, &cam, pose, &cam, true).rgb)
        })?;
        curve.points.push(Point {
            setting: format!("crf {q}"),
            bitrate: Some(bytes as f64 * 8.0 * FPS / clip.rgb.len() as f64),
            psnr: p,
            lpips: l,
            proxy: None,
            segments: Vec::new(),
        });
        on_point(curve.method, curve.points.last().expect("pushed"));
    }
    Ok(curve)
}

/// Measures every method's curve; `on_point(method, point)` sees each coded point as it is
/// measured.
pub fn evaluate_rd(
    a: &RdOptions,
    progress: &dyn Progress,
    mut on_point: impl FnMut(&str, &Point),
) -> Result<RdReport> {
    let codec = a.codec;
    cpsl_pipeline::encode::require_encoder(codec)?;
    let qualities = baseline_qualities(codec, a.qualities.as_deref())?;
    let bars = progress;
    let mut lpips = a.lpips.then(open_lpips).transpose()?;
    let clip = match a.clip {
        RdClip::Synthetic => ray_cast(a, bars),
        RdClip::Fox => fox_clip(a)?,
    };
    let wanted: Vec<usize> = (0..clip.rgb.len())
        .step_by(a.score_every as usize)
        .collect();
    let tmp = tempfile::tempdir()
        .map_err(|e| EvalError::file(std::env::temp_dir(), e))
        .context_with(|| "creating a temporary folder".into())?;
    let mut curves = Vec::new();

    // CPSL: uncompressed with the default layering; under each budget layered for it, as
    // `cpsl encode --bitrate` does (`GopConfig::for_budget`), again only where that changes.
    let base = GopConfig {
        rate_aware_refresh: a.rate_aware_refresh,
        ..GopConfig::default()
    };
    let decoded = match a.input {
        RdInput::Pictures => None,
        RdInput::H264Vectors | RdInput::H264Flow => Some(through_h264(
            tmp.path(),
            &clip,
            a.input == RdInput::H264Vectors,
        )?),
    };
    let decoded = decoded.as_deref();
    let mut frames = cpsl_layers(&clip, a, base, decoded, bars)?;
    let mut layered_for = base;
    let (p, l) = score(&clip, &mut lpips, |f, pose| {
        let (set, edc) = (frames[f].set.clone(), frames[f].edc.clone());
        Ok(render_layers(
            &FrameLayers::new(set, Some(edc)),
            true,
            pose,
            a.filter,
        ))
    })?;
    let mut cpsl = Curve {
        method: "cpsl",
        uncompressed: uncompressed(p, l),
        points: Vec::new(),
    };
    let pixels_per_second = f64::from(clip.camera.width) * f64::from(clip.camera.height) * FPS;
    for &b in &a.bitrates {
        let gop = base.for_budget(b / pixels_per_second);
        if gop != layered_for {
            drop(std::mem::take(&mut frames));
            frames = cpsl_layers(&clip, a, gop, decoded, bars)?;
            layered_for = gop;
        }
        let coded = code(
            tmp.path(),
            &frames,
            a.layers,
            (codec, a.container, a.segments),
            RateControl::Budget(b),
            &wanted,
        )?;
        let (p, l) = score(&clip, &mut lpips, |f, pose| {
            Ok(render_layers(&coded.frames[&f], true, pose, a.filter))
        })?;
        cpsl.points.push(Point {
            setting: format!("{:.2}M", b / 1e6),
            bitrate: Some(coded.bitrate),
            psnr: p,
            lpips: l,
            proxy: Some(proxy(&frames, &coded)),
            segments: coded.segments.clone(),
        });
        on_point(cpsl.method, cpsl.points.last().expect("pushed"));
    }
    drop(frames);
    curves.push(cpsl);

    // DIBR streaming: colour over quantised inverse depth, 8-bit in an 8-bit stream and
    // 16-bit in a 10-bit stream.
    let (lo, hi) = inverse_range(&clip);
    let to_unit = |d: f32| ((1.0 / d as f64 - lo) / (hi - lo)).clamp(0.0, 1.0);
    let from_unit = |c: f64| (1.0 / (lo + c * (hi - lo))) as f32;
    let cam = clip.camera;
    let (p, l) = score(&clip, &mut lpips, |f, pose| {
        Ok(dibr(&clip.rgb[f], &clip.depth[f], &cam, pose, &cam, true).rgb)
    })?;
    let dibr_uncompressed = uncompressed(p, l);
    for deep in [false, true] {
        let stream = DibrStream {
            deep,
            codec,
            path: &tmp.path().join("dibr.mp4"),
            to_unit: &to_unit,
            from_unit: &from_unit,
        };
        let uncompressed = &dibr_uncompressed;
        let curve = dibr_curve(
            &clip,
            &stream,
            &qualities,
            uncompressed,
            &mut lpips,
            &mut on_point,
        )?;
        curves.push(curve);
    }

    // MPI.
    let planes = a.mpi_planes as usize;
    // The MPI is segmented like CPSL's fixed GOP (CPSL may also refresh earlier).
    let frames = mpi_layers(&clip, planes, GopConfig::default().gop)?;
    let (p, l) = score(&clip, &mut lpips, |f, pose| {
        let set = frames[f].set.clone();
        Ok(render_layers(
            &FrameLayers::new(set, None),
            false,
            pose,
            a.filter,
        ))
    })?;
    let mut mpi = Curve {
        method: "mpi",
        uncompressed: uncompressed(p, l),
        points: Vec::new(),
    };
    for &q in &qualities {
        let coded = code(
            tmp.path(),
            &frames,
            a.mpi_planes,
            (codec, a.container, cpsl_codec::Segments::Gop),
            RateControl::Quality(q),
            &wanted,
        )?;
        let (p, l) = score(&clip, &mut lpips, |f, pose| {
            Ok(render_layers(&coded.frames[&f], false, pose, a.filter))
        })?;
        mpi.points.push(Point {
            setting: format!("crf {q}"),
            bitrate: Some(coded.bitrate),
            psnr: p,
            lpips: l,
            proxy: Some(proxy(&frames, &coded)),
            segments: coded.segments.clone(),
        });
        on_point(mpi.method, mpi.points.last().expect("pushed"));
    }
    curves.push(mpi);

    let summary = summarise(&curves);
    let views: Vec<_> = clip
        .views
        .iter()
        .map(|v| (v.frame, v.pose.translation.0, rotation_deg(&v.pose)))
        .collect();
    Ok(RdReport {
        clip: serde_json::json!({
            "description": clip.description, "input": a.input.name(), "width": clip.camera.width,
            "height": clip.camera.height, "frames": clip.rgb.len(), "fps": FPS,
            "scored_frames": wanted, "novel_viewpoints": views,
        }),
        codec: codec.name(),
        layers: a.layers,
        mpi_planes: a.mpi_planes,
        curves,
        summary,
    })
}

fn uncompressed(psnr: f64, lpips: Option<f64>) -> Point {
    Point {
        setting: "uncompressed".into(),
        bitrate: None,
        psnr,
        lpips,
        proxy: None,
        segments: Vec::new(),
    }
}

/// A grey sample of DIBR's depth: 8-bit in an 8-bit stream, 16-bit in a 10-bit one.
trait DepthSample: cpsl_codec::Sample + Into<f64> {
    /// The largest value.
    const TOP: f64;
    /// The sample nearest `v * TOP`.
    fn from_unit(v: f64) -> Self;
    /// Colour over grey in one picture.
    fn stack(rgb: &[u8], grey: &[Self], width: u32, height: u32) -> Yuv420<Self>;
    /// The colour and grey of a picture made by [`DepthSample::stack`].
    fn unstack(p: &Yuv420<Self>, width: u32, height: u32) -> (Vec<u8>, Vec<Self>);
}

impl DepthSample for u8 {
    const TOP: f64 = 255.0;
    fn from_unit(v: f64) -> Self {
        (v * Self::TOP).round() as u8
    }
    fn stack(rgb: &[u8], grey: &[u8], width: u32, height: u32) -> Yuv420 {
        cpsl_codec::yuv::stack_colour_grey(rgb, grey, width, height)
    }
    fn unstack(p: &Yuv420, width: u32, height: u32) -> (Vec<u8>, Vec<u8>) {
        cpsl_codec::yuv::unstack_colour_grey(p, width, height)
    }
}

impl DepthSample for u16 {
    const TOP: f64 = 65535.0;
    fn from_unit(v: f64) -> Self {
        (v * Self::TOP).round() as u16
    }
    fn stack(rgb: &[u8], grey: &[u16], width: u32, height: u32) -> Yuv420<u16> {
        cpsl_codec::yuv::stack_colour_grey16(rgb, grey, width, height)
    }
    fn unstack(p: &Yuv420<u16>, width: u32, height: u32) -> (Vec<u8>, Vec<u16>) {
        cpsl_codec::yuv::unstack_colour_grey16(p, width, height)
    }
}

/// Colour over depth per frame.
type ColourDepth = Vec<(Vec<u8>, Vec<f32>)>;

/// DIBR's stream at quality `q`: the clip's colour over its depth coded (`to_unit`: depth to
/// `[0, 1]`) in grey samples `T`, written to `path` and decoded (`from_unit`: back to depth).
/// Returns the file size and the decoded frames.
fn dibr_stream<T: DepthSample>(
    path: &Path,
    clip: &Clip,
    codec: Codec,
    q: f32,
    to_unit: &dyn Fn(f32) -> f64,
    from_unit: &dyn Fn(f64) -> f32,
) -> Result<(u64, ColourDepth)> {
    let (w, h) = (clip.camera.width, clip.camera.height);
    let grey: Vec<Vec<T>> = clip
        .depth
        .iter()
        .map(|d| d.iter().map(|&z| T::from_unit(to_unit(z))).collect())
        .collect();
    let picture = |i: usize| T::stack(&clip.rgb[i], &grey[i], w, h);
    let bytes = cpsl_codec::encode_pictures(path, clip.rgb.len(), &picture, codec, q, FPS)?;
    let decoded = cpsl_codec::decode_pictures::<T>(path, w, h)?
        .iter()
        .map(|p| {
            let (rgb, g) = T::unstack(p, w, h);
            let depth = g
                .into_iter()
                .map(|g| from_unit(g.into() / T::TOP))
                .collect();
            (rgb, depth)
        })
        .collect();
    Ok((bytes, decoded))
}

fn summarise(curves: &[Curve]) -> Summary {
    let by = |m: &str| {
        curves
            .iter()
            .find(|c| c.method == m)
            .expect("every method runs")
    };
    let (cpsl, dibr, dibr16, mpi) = (by("cpsl"), by("dibr"), by("dibr-16"), by("mpi"));
    let ratios = |base: &Curve| -> Vec<Ratio> {
        cpsl.points
            .iter()
            .filter_map(|p| Some(ratio(&base.points, p.psnr, p.bitrate?)))
            .collect()
    };
    let best_3m = cpsl
        .points
        .iter()
        .filter(|p| p.bitrate.is_some_and(|b| b <= 3e6))
        .map(|p| p.psnr)
        .max_by(f64::total_cmp);
    let (proxies, lpips): (Vec<f64>, Vec<f64>) = cpsl
        .points
        .iter()
        .chain(&mpi.points)
        .filter_map(|p| Some((p.proxy?, p.lpips?)))
        .unzip();
    Summary {
        dibr_rate_ratio: ratios(dibr),
        dibr16_rate_ratio: ratios(dibr16),
        mpi_rate_ratio: ratios(mpi),
        cpsl_gap_at_3m_db: best_3m.map(|b| cpsl.uncompressed.psnr - b),
        proxy_lpips_spearman: spearman(&proxies, &lpips),
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn pt(bitrate: f64, psnr: f64) -> Point {
        Point {
            setting: String::new(),
            bitrate: Some(bitrate),
            psnr,
            lpips: None,
            proxy: None,
            segments: Vec::new(),
        }
    }

    #[test]
    fn rate_at_interpolates_in_log_rate() {
        let curve = [pt(4e6, 30.0), pt(1e6, 26.0), pt(2e6, 28.0)];
        assert!((rate_at(&curve, 28.0).unwrap() - 2e6).abs() < 1.0);
        // Halfway in dB between 1 and 2 Mbit/s is their geometric mean.
        assert!((rate_at(&curve, 27.0).unwrap() - 2f64.sqrt() * 1e6).abs() < 1.0);
        assert!(rate_at(&curve, 31.0).is_none() && rate_at(&curve, 25.0).is_none());
    }

    #[test]
    fn ratio_interpolates_or_bounds() {
        let base = [pt(1e6, 26.0), pt(2e6, 28.0)];
        let Ratio::Equal(r) = ratio(&base, 28.0, 4e6) else {
            panic!("28 dB is on the curve")
        };
        assert!((r - 0.5).abs() < 1e-9, "{r}");
        assert_eq!(ratio(&base, 25.0, 4e6), Ratio::AtMost(0.25));
        assert_eq!(ratio(&base, 29.0, 4e6), Ratio::Never);
    }

    #[test]
    fn spearman_of_monotone_and_reversed() {
        let x = [1.0, 2.0, 3.0, 4.0];
        assert!((spearman(&x, &[10.0, 20.0, 25.0, 90.0]).unwrap() - 1.0).abs() < 1e-12);
        assert!((spearman(&x, &[4.0, 3.0, 2.0, 1.0]).unwrap() + 1.0).abs() < 1e-12);
        assert!(spearman(&x[..2], &x[..2]).is_none());
    }
}
