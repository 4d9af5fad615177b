//! The temporal-stability ablation (paper Table 2, `cpsl eval-video`) on moving clips:
//! frame-wise depth slicing (the normalising baseline), frame-wise CPSL, I/P propagation, and
//! I/P with refinement and adaptive refresh with hysteresis.

use crate::datasets::Distortion;
use crate::error::{Context, EvalError};
use crate::metrics::{blacken, psnr_masked};
use crate::temporal::{alpha_owner, boundary_variance, f_ssim, flicker, warping_error, ClipMotion};
use cpsl_core::resample::downscale_rgb;
use cpsl_core::{Camera, DepthSource, Flow, LayerSet, Limits, Pose, Vec3};
use cpsl_layering::GeometryMode;
use cpsl_layering::{slice_by_depth, LayeringConfig, SliceConfig};
use cpsl_pipeline::sources::open_depth_model;
use cpsl_render::{CpuRenderer, DpsConfig, Filter, FrameLayers};
use cpsl_temporal::{GopConfig, VideoLayerer};
use serde::Serialize;
use std::path::{Path, PathBuf};

type Result<T> = std::result::Result<T, EvalError>;

/// The clips.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum Clip {
    /// The built-in scene with its moving board, pole and disc (exact depth, true motion and
    /// ray-cast novel views).
    Synthetic,
    /// HCI backgammon, the centre row of the 9x9 grid as a camera sweep (ground-truth depth
    /// warped to each view; the row above as novel views).
    HciRow,
    /// The fox handheld phone video (50 frames, a quarter of full size, FastDepth scaled by the
    /// poses; each frame rendered at the next frame's camera and scored against it).
    Fox,
    /// KITTI odometry 06 colour frames 12, 13, 14, 17 (FastDepth).
    Kitti,
    /// All of the above.
    All,
}

/// What to evaluate, and how.
#[derive(Debug, Clone)]
pub struct VideoOptions {
    /// Clip (`All` for every one).
    pub clip: Clip,
    /// Folder holding the datasets.
    pub data: PathBuf,
    /// Frames per group of pictures for the I/P methods.
    pub gop: usize,
    /// Number of layers K.
    pub layers: usize,
    /// Layer surfaces for CPSL (`None`: the configuration's, by default the best).
    pub geometry: Option<GeometryMode>,
    /// Score flicker (it needs the LPIPS model).
    pub lpips: bool,
    /// Give the I/P methods the clip's true motion (only the synthetic clip has one).
    pub true_motion: bool,
    /// Depth of the fox from the video itself (tracking, multi-view depth fused with
    /// FastDepth; [`crate::tracking::video_depth`]) instead of FastDepth alone.
    pub video_depth: bool,
    /// How the layers are resampled for the novel views.
    pub filter: Filter,
}

/// What a run reports as it goes.
pub enum VideoRow<'a> {
    /// A method scored on a clip.
    Scored(&'a StabilityScore),
    /// The boundary variance of the clip's exact object partition moving with the true
    /// motion (where known).
    ObjectPartition {
        /// The clip.
        clip: &'a str,
        /// Its boundary variance in px^2.
        boundary_variance_px2: f64,
    },
}

/// A clip ready to layer.
struct ClipData {
    name: &'static str,
    camera: Camera,
    frames: Vec<Vec<u8>>,
    depth: Vec<Vec<f32>>,
    depth_name: String,
    /// Per frame: the novel viewpoint and its camera.
    novel: Vec<(Pose, Camera)>,
    /// Ground truth at the novel viewpoint, where known.
    truth: Option<Vec<Vec<u8>>>,
    /// The true motion of the input, where known.
    motion: Option<ClipMotion>,
    /// The true object partition of every frame, where known.
    objects: Option<Vec<Vec<u8>>>,
}

/// One method on one clip.
#[derive(Debug, Clone, Serialize)]
pub struct StabilityScore {
    /// The clip.
    pub clip: String,
    /// The method.
    pub method: String,
    /// The depth used.
    pub depth: String,
    /// Frames.
    pub frames: usize,
    /// I-frames.
    pub i_frames: usize,
    /// Boundary variance in px^2.
    pub boundary_variance_px2: f64,
    /// Relative to frame-wise depth slicing (the paper's normalisation).
    pub boundary_variance: f64,
    /// Relative to frame-wise CPSL.
    pub boundary_variance_vs_frame_wise: f64,
    /// Flow-compensated SSIM between consecutive output frames.
    pub f_ssim: f64,
    /// Warping error.
    pub warping_error: f64,
    /// Flicker (LPIPS), when scored.
    pub flicker: Option<f64>,
    /// Novel-view PSNR against the truth, where known.
    pub psnr: Option<f64>,
    /// Each frame's novel-view PSNR with whether it is an I-frame, where known: where the
    /// P-frames lose, and how far from their I-frame.
    #[serde(skip_serializing_if = "Vec::is_empty")]
    pub psnr_per_frame: Vec<(bool, Option<f64>)>,
    /// Novel-view LPIPS against the truth, where known and scored (pixels the view does not
    /// cover black in both).
    pub lpips: Option<f64>,
}

const METHODS: [&str; 4] = [
    "depth-slice (frame-wise)",
    "cpsl frame-wise",
    "cpsl I/P",
    "cpsl I/P + refinement + hysteresis",
];

fn fastdepth() -> Result<Box<dyn DepthSource>> {
    Ok(Box::new(open_depth_model("fastdepth", None)?))
}

fn synthetic() -> ClipData {
    let scene = cpsl_synth::Scene::default_scene(480, 360);
    let dt = 0.1;
    let novel = Pose::from_translation(Vec3::new(0.15, 0.0, 0.0));
    let (mut views, mut truth) = (vec![], vec![]);
    for t in 0..16 {
        views.push(scene.render(&scene.camera, &Pose::IDENTITY, t as f64 * dt, 2));
        truth.push(scene.render(&scene.camera, &novel, t as f64 * dt, 2).rgb);
    }
    let cam = scene.camera;
    let (w, h) = (cam.width as usize, cam.height as usize);
    let (back, valid): (Vec<Flow>, Vec<Vec<bool>>) = views
        .windows(2)
        .map(|v| {
            let (data, seen) = scene.backward_motion(&v[0], &v[1], dt);
            (
                Flow {
                    width: w,
                    height: h,
                    data,
                },
                seen,
            )
        })
        .unzip();
    let objects = views
        .iter()
        .map(|v| v.object.iter().map(|&o| o.min(255) as u8).collect())
        .collect();
    let (frames, depth): (Vec<Vec<u8>>, Vec<Vec<f32>>) =
        views.into_iter().map(|v| (v.rgb, v.depth)).unzip();
    ClipData {
        name: "synthetic",
        camera: cam,
        novel: vec![(novel, cam); frames.len()],
        frames,
        depth,
        depth_name: "exact".into(),
        truth: Some(truth),
        motion: Some(ClipMotion {
            width: w,
            height: h,
            back,
            valid,
        }),
        objects: Some(objects),
    }
}

fn hci_row(data: &Path) -> Result<ClipData> {
    let ds = crate::datasets::load(data, "hci/backgammon")?;
    let (w, h) = (ds.camera.width as usize, ds.camera.height as usize);
    let f = ds.camera.fx;
    let view = |row: i32, col: i32| -> Option<&crate::datasets::Target> {
        let name = format!("input_Cam{:03}", 9 * row + col);
        ds.targets.iter().find(|t| t.name == name)
    };
    let (mut frames, mut depth, mut truth, mut novel) = (vec![], vec![], vec![], vec![]);
    for col in 0..9 {
        let (rgb, pose, cam) = match view(4, col) {
            Some(t) => (t.rgb.clone(), t.pose, t.camera),
            None => (ds.rgb.clone(), Pose::IDENTITY, ds.camera),
        };
        // Ground-truth depth carried from the centre view (z-buffered, holes from the row).
        let shift = |z: f32| (pose.translation.x() * f / z as f64) as f32;
        let mut z = vec![f32::INFINITY; w * h];
        for p in 0..w * h {
            let zc = ds.depth[p];
            if !zc.is_finite() {
                continue;
            }
            let x = (p % w) as f32 - shift(zc) + (cam.cx - ds.camera.cx) as f32;
            let xi = x.round();
            if xi >= 0.0 && (xi as usize) < w {
                let q = (p / w) * w + xi as usize;
                z[q] = z[q].min(zc);
            }
        }
        for y in 0..h {
            let row = &mut z[y * w..(y + 1) * w];
            // Fill holes with the farther neighbour (disocclusions show background).
            for x in 0..w {
                if !row[x].is_finite() {
                    let l = (0..x).rev().map(|i| row[i]).find(|v| v.is_finite());
                    let r = (x + 1..w).map(|i| row[i]).find(|v| v.is_finite());
                    row[x] = match (l, r) {
                        (Some(a), Some(b)) => a.max(b),
                        (Some(a), None) | (None, Some(a)) => a,
                        (None, None) => 1.0,
                    };
                }
            }
        }
        let above = view(3, col)
            .ok_or_else(|| EvalError::Invalid("HCI backgammon: the row above is missing".into()))?;
        frames.push(rgb);
        depth.push(z);
        truth.push(above.rgb.clone());
        // The view above relative to this one.
        novel.push((
            Pose::from_translation(above.pose.translation - pose.translation),
            above.camera,
        ));
        let _ = cam;
    }
    Ok(ClipData {
        name: "hci-row",
        camera: ds.camera,
        frames,
        depth,
        depth_name: "ground truth".into(),
        novel,
        truth: Some(truth),
        motion: None,
        objects: None,
    })
}

/// Frames (RGB), their depth maps and the depth's source.
type Estimated = (Vec<Vec<u8>>, Vec<Vec<f32>>, String);

/// The frames of `files` downscaled by `scale` and undistorted with `lens`, if any, to
/// `camera`.
pub fn read_frames(
    files: &[PathBuf],
    camera: Camera,
    scale: usize,
    lens: Option<&Distortion>,
) -> Result<Vec<Vec<u8>>> {
    files
        .iter()
        .map(|f| {
            let img = cpsl_io::images::read_rgb8(f, &Limits::default())
                .context_with(|| format!("reading {}", f.display()))?;
            let (rgb, _, _) = downscale_rgb(
                &img.data,
                img.width as usize,
                img.height as usize,
                img.width as usize / scale,
            );
            Ok(match lens {
                Some(l) => l.undistort_rgb(&rgb, &camera),
                None => rgb,
            })
        })
        .collect()
}

/// [`read_frames`] and their FastDepth depth.
fn estimate_frames(
    files: &[PathBuf],
    camera: Camera,
    scale: usize,
    lens: Option<&Distortion>,
) -> Result<Estimated> {
    let mut model = fastdepth()?;
    let frames = read_frames(files, camera, scale, lens)?;
    let depth = frames
        .iter()
        .map(|rgb| Ok(model.depth(rgb, camera.width, camera.height)?))
        .collect::<Result<_>>()?;
    Ok((frames, depth, model.name()))
}

/// A clip without truth at a novel view: a lateral step of 3 % of the first frame's median
/// depth, scored against the input.
fn estimated(
    name: &'static str,
    files: Vec<PathBuf>,
    camera: Camera,
    scale: usize,
) -> Result<ClipData> {
    let (frames, depth, depth_name) = estimate_frames(&files, camera, scale, None)?;
    let median = crate::datasets::median(&depth[0]).unwrap_or(1.0) as f64;
    let pose = Pose::from_translation(Vec3::new(0.03 * median, 0.0, 0.0));
    Ok(ClipData {
        name,
        camera,
        novel: vec![(pose, camera); frames.len()],
        frames,
        depth,
        depth_name,
        truth: None,
        motion: None,
        objects: None,
    })
}

/// The fox downscaled by `scale` and undistorted: frames, FastDepth depth with one scale for
/// the clip (the median over the frames of the poses' scene-centre depth over the estimate's
/// median, so that depth is in the poses' unit; missing values filled) and the poses.
pub struct Fox {
    /// The video, its poses and lens.
    pub video: crate::datasets::PosedVideo,
    /// The camera at this scale.
    pub camera: Camera,
    /// Undistorted frames.
    pub frames: Vec<Vec<u8>>,
    /// Their depth.
    pub depth: Vec<Vec<f32>>,
    /// Where the depth comes from.
    pub depth_name: String,
    /// With depth from the video: what carries a frame's depth to another frame by the
    /// tracked camera's poses, as `cpsl layer-video` gives its P-frames depth.
    pub carrier: Option<DepthCarrier>,
}

/// Carries a fox frame's depth to another frame by the tracked camera's poses, the rest its
/// FastDepth fitted to it ([`cpsl_track::TrackedDepth::carry_depth`]), as a P-frame of
/// `cpsl layer-video` gets it ([`cpsl_pipeline::video::PFrameDepth::Poses`]): in the
/// clip's units, unknown pixels filled as [`load_fox`] fills them.
pub struct DepthCarrier {
    tracked: cpsl_track::TrackedDepth,
    /// Each frame's FastDepth.
    prior: Vec<Vec<f32>>,
    /// Clip units per unit of the tracked depth.
    scale: f32,
    camera: Camera,
}

impl DepthCarrier {
    /// Frame `to`'s depth carried from frame `from`'s, `from_depth` (the clip's units);
    /// `None` where the poses cannot carry it.
    pub fn carry(
        &self,
        from: usize,
        from_depth: &[f32],
        to: usize,
        rgb: &[u8],
    ) -> Result<Option<Vec<f32>>> {
        let size = (self.camera.width, self.camera.height);
        let z: Vec<f32> = from_depth.iter().map(|v| v / self.scale).collect();
        let Some(mut out) = self
            .tracked
            .carry_depth(from, &z, to, rgb, &self.prior[to], size)?
        else {
            return Ok(None);
        };
        fill_depth(&mut out, self.scale, size)?;
        Ok(Some(out))
    }
}

/// `z` times `k`, pixels without a positive depth given one from their neighbours (push-pull
/// in inverse depth, as the layering fills them), so that every method sees the same depth.
fn fill_depth(z: &mut [f32], k: f32, (w, h): (u32, u32)) -> Result<()> {
    let known: Vec<f32> = z
        .iter()
        .map(|v| f32::from(u8::from(v.is_finite() && *v > 0.0)))
        .collect();
    let mut inv: Vec<f32> = z
        .iter()
        .zip(&known)
        .map(|(v, &m)| if m > 0.0 { 1.0 / (v * k) } else { 0.0 })
        .collect();
    if !cpsl_core::fill::push_pull(&mut inv, &known, w as usize, h as usize, 1) {
        return Err(EvalError::Invalid("fox: a frame without depth".into()));
    }
    z.iter_mut().zip(&inv).for_each(|(v, i)| *v = 1.0 / i);
    Ok(())
}

/// The fox at `1/scale` of full size ([`Fox`]).
pub fn load_fox(data: &Path, scale: u32, from_video: bool) -> Result<Fox> {
    let video = crate::datasets::fox(data)?;
    let camera = video.camera.scaled(1.0 / scale as f64);
    let (frames, mut depth, mut name) =
        estimate_frames(&video.files, camera, scale as usize, Some(&video.lens))?;
    let (mut path_scale, mut tracked) = (None, None);
    if from_video {
        let v = crate::tracking::video_depth(&frames, camera, &depth)?;
        path_scale = spread_ratio(&video.poses, &v.centres);
        tracked = Some((v.tracked, std::mem::replace(&mut depth, v.depth)));
        name = v.how;
    }
    // Depth from the video is in the units of its own camera path: the path's size against
    // the poses' scales it. Other depth (and a path of fewer than three frames) is scaled by
    // the depth of the filmed object, a rougher proxy: its per-frame ratios spread by a
    // fifth, so their median moves with which frames it is taken over.
    let (k, how) = match path_scale {
        Some(k) => (k, "camera path"),
        None => {
            let ratios: Vec<f32> = depth
                .iter()
                .zip(&video.centre_depth)
                .filter_map(|(z, c)| crate::datasets::median(z).map(|m| c / m))
                .collect();
            let k = crate::datasets::median(&ratios)
                .ok_or_else(|| EvalError::Invalid("fox: no depth to scale".into()))?;
            (k, "object depth")
        }
    };
    for z in &mut depth {
        fill_depth(z, k, (camera.width, camera.height))?;
    }
    Ok(Fox {
        video,
        camera,
        frames,
        depth,
        depth_name: format!("{name}, pose-scaled x{k:.3} ({how})"),
        carrier: tracked.map(|(tracked, prior)| DepthCarrier {
            tracked,
            prior,
            scale: k,
            camera,
        }),
    })
}

/// How many times larger the camera path of `poses` is than `centres` (where known, at least
/// three): the ratio of their root-mean-square distances from their centroids.
fn spread_ratio(poses: &[cpsl_core::Pose], centres: &[Option<cpsl_core::Vec3>]) -> Option<f32> {
    let pairs: Vec<(cpsl_core::Vec3, cpsl_core::Vec3)> = poses
        .iter()
        .zip(centres)
        .filter_map(|(p, c)| Some((p.translation, (*c)?)))
        .collect();
    if pairs.len() < 3 {
        return None;
    }
    let n = pairs.len() as f64;
    let spread = |f: &dyn Fn(&(cpsl_core::Vec3, cpsl_core::Vec3)) -> cpsl_core::Vec3| {
        let m = pairs
            .iter()
            .map(f)
            .fold(cpsl_core::Vec3::ZERO, |a, b| a + b)
            * (1.0 / n);
        (pairs.iter().map(|p| (f(p) - m).dot(f(p) - m)).sum::<f64>() / n).sqrt()
    };
    let (truth, est) = (spread(&|p| p.0), spread(&|p| p.1));
    let k = truth / est;
    (k.is_finite() && k > 0.0).then_some(k as f32)
}

/// The fox at a quarter of full size. Its poses give every frame a real novel view: frame t is
/// rendered at frame t+1's camera (the last frame at frame t-1's) and scored against that
/// frame.
fn fox(data: &Path, from_video: bool) -> Result<ClipData> {
    let f = load_fox(data, 4, from_video)?;
    let n = f.frames.len();
    let target = |t: usize| {
        if t + 1 < n {
            t + 1
        } else {
            t.saturating_sub(1)
        }
    };
    Ok(ClipData {
        name: "fox",
        camera: f.camera,
        novel: (0..n)
            .map(|t| (f.video.relative(t, target(t)), f.camera))
            .collect(),
        truth: Some((0..n).map(|t| f.frames[target(t)].clone()).collect()),
        frames: f.frames,
        depth: f.depth,
        depth_name: f.depth_name,
        motion: None,
        objects: None,
    })
}

fn kitti(data: &Path) -> Result<ClipData> {
    let dir = data.join("kitti_odometry06_stereo_snippet/image_2_left_color");
    let files: Vec<PathBuf> = ["000012", "000013", "000014", "000017"]
        .iter()
        .map(|n| dir.join(format!("{n}.png")))
        .collect();
    let (w, h) = cpsl_io::images::dimensions(&files[0], &Limits::default())?;
    let camera = Camera {
        width: w,
        height: h,
        fx: 707.0912,
        fy: 707.0912,
        cx: 601.8873,
        cy: 183.1104,
    };
    estimated("kitti", files, camera, 1)
}

/// Per-frame layer sets of one method (with the Edge-Depth Cache where it has one).
fn layer_clip(
    c: &ClipData,
    method: &str,
    cfg: &LayeringConfig,
    gop: usize,
    true_motion: Option<&ClipMotion>,
) -> Result<Vec<(LayerSet, Option<cpsl_core::Edc>, bool)>> {
    if method.starts_with("depth-slice") {
        let sc = SliceConfig {
            layers: cfg.layers,
            ..SliceConfig::default()
        };
        return c
            .frames
            .iter()
            .zip(&c.depth)
            .map(|(rgb, z)| Ok((slice_by_depth(rgb, z, c.camera, &sc)?, None, true)))
            .collect();
    }
    let g = match method {
        "cpsl frame-wise" => GopConfig::frame_wise(),
        "cpsl I/P" => GopConfig {
            gop,
            ..GopConfig::propagation_only()
        },
        _ => GopConfig {
            gop,
            ..GopConfig::default()
        },
    };
    let mut cfg = *cfg;
    cfg.cues.allow_missing_depth = true;
    let mut v = VideoLayerer::new(c.camera, cfg, g)?;
    let n = c.frames.len();
    c.frames
        .iter()
        .zip(&c.depth)
        .enumerate()
        .map(|(i, (rgb, z))| {
            v.set_frames_left(Some(n - i));
            let given = true_motion.filter(|_| i > 0).map(|m| m.back[i - 1].clone());
            let f = v.push_with_motion(rgb, Some(z), given)?;
            Ok((f.set, Some(f.edc), f.refresh.is_some()))
        })
        .collect()
}

/// Scores every method on the clips `a` names, handing each row to `rows` once its clip is
/// done; returns every score.
pub fn evaluate_video(
    a: &VideoOptions,
    mut rows_out: impl FnMut(VideoRow<'_>),
) -> Result<Vec<StabilityScore>> {
    let clips = match a.clip {
        Clip::All => vec![Clip::Synthetic, Clip::HciRow, Clip::Fox, Clip::Kitti],
        c => vec![c],
    };
    if a.true_motion && clips != [Clip::Synthetic] {
        return Err(EvalError::Invalid(
            "--true-motion needs the synthetic clip: no other clip has a true motion".into(),
        ));
    }
    let mut lpips = if !a.lpips {
        None
    } else {
        Some(
            cpsl_models::Lpips::open(&cpsl_models::lpips::default_path()).context_with(|| {
                "LPIPS for the flicker score (run scripts/setup-models.sh or pass --no-lpips)"
                    .into()
            })?,
        )
    };
    let mut cfg = LayeringConfig {
        layers: a.layers,
        ..LayeringConfig::default()
    };
    cfg.matte.geometry = a.geometry.unwrap_or(GeometryMode::VIDEO_DEFAULT);
    let mut rows: Vec<StabilityScore> = Vec::new();
    for clip in clips {
        let c = match clip {
            Clip::Synthetic => synthetic(),
            Clip::HciRow => hci_row(&a.data)?,
            Clip::Fox => fox(&a.data, a.video_depth)?,
            Clip::Kitti => kitti(&a.data)?,
            Clip::All => unreachable!(),
        };
        let (w, h) = (c.camera.width as usize, c.camera.height as usize);
        let input_motion = match &c.motion {
            Some(m) => m.clone(),
            None => ClipMotion::estimate(&c.frames, w, h),
        };
        let given = c.motion.as_ref().filter(|_| a.true_motion);
        // Output frames live at the novel viewpoint: their motion is the truth's where known.
        let (nw, nh) = (c.novel[0].1.width as usize, c.novel[0].1.height as usize);
        let reference = c.truth.clone().unwrap_or_else(|| c.frames.clone());
        let out_motion = ClipMotion::estimate(&reference, nw, nh);
        let first = rows.len();
        for method in METHODS {
            let sets = layer_clip(&c, method, &cfg, a.gop, given)?;
            let owners: Vec<Vec<u8>> = sets.iter().map(|s| alpha_owner(&s.0)).collect();
            let bv = boundary_variance(&owners, &input_motion);
            let (frames, i_frames) = (sets.len(), sets.iter().filter(|s| s.2).count());
            let intra: Vec<bool> = sets.iter().map(|s| s.2).collect();
            let renders: Vec<(Vec<u8>, Vec<bool>)> = sets
                .into_iter()
                .zip(&c.novel)
                .map(|((set, edc, _), (pose, cam))| {
                    let dps = edc.is_some().then_some(&DpsConfig::DEFAULT);
                    let frame = FrameLayers::new(set, edc);
                    let img = CpuRenderer::new(a.filter).view(&frame, pose, cam, dps);
                    (img.over_background([0, 0, 0]), img.covered(128))
                })
                .collect();
            let outs: Vec<Vec<u8>> = renders.iter().map(|r| r.0.clone()).collect();
            let per_frame: Vec<(bool, Option<f64>)> = match &c.truth {
                Some(truth) => renders
                    .iter()
                    .zip(truth)
                    .zip(&intra)
                    .map(|(((o, m), t), &i)| (i, psnr_masked(o, t, m)))
                    .collect(),
                None => Vec::new(),
            };
            let psnr = c.truth.as_ref().map(|_| {
                let v: Vec<f64> = per_frame.iter().filter_map(|f| f.1).collect();
                v.iter().sum::<f64>() / v.len().max(1) as f64
            });
            let novel_lpips = match (lpips.as_mut(), c.truth.as_ref()) {
                (Some(l), Some(truth)) => {
                    let mut sum = 0.0;
                    for ((o, m), t) in renders.iter().zip(truth) {
                        let mut t = t.clone();
                        blacken(&mut t, m);
                        sum += l.distance(o, &t, nw as u32, nh as u32)? as f64;
                    }
                    Some(sum / renders.len().max(1) as f64)
                }
                _ => None,
            };
            let flick = lpips
                .as_mut()
                .map(|l| -> Result<f64> {
                    let mut err = None;
                    let v = flicker(&outs, &reference, |x, y| {
                        l.distance(x, y, nw as u32, nh as u32)
                            .map(f64::from)
                            .unwrap_or_else(|e| {
                                err = Some(e);
                                0.0
                            })
                    });
                    match err {
                        Some(e) => Err(e.into()),
                        None => Ok(v),
                    }
                })
                .transpose()?;
            let row = StabilityScore {
                clip: c.name.into(),
                method: method.into(),
                depth: c.depth_name.clone(),
                frames,
                i_frames,
                boundary_variance_px2: bv,
                boundary_variance: 0.0,
                boundary_variance_vs_frame_wise: 0.0,
                f_ssim: f_ssim(&outs, &reference, &out_motion),
                warping_error: warping_error(&outs, &out_motion),
                flicker: flick,
                psnr,
                psnr_per_frame: per_frame,
                lpips: novel_lpips,
            };
            rows.push(row);
        }
        // Boundary variance relative to frame-wise slicing (the paper's normalisation) and to
        // frame-wise CPSL.
        let by = |m: &str| {
            rows[first..]
                .iter()
                .find(|r| r.method == m)
                .map(|r| r.boundary_variance_px2)
        };
        let (slice, fw) = (by(METHODS[0]).unwrap_or(0.0), by(METHODS[1]).unwrap_or(0.0));
        for row in &mut rows[first..] {
            let rel = |base: f64| {
                if base > 0.0 {
                    row.boundary_variance_px2 / base
                } else {
                    f64::NAN
                }
            };
            row.boundary_variance = rel(slice);
            row.boundary_variance_vs_frame_wise = rel(fw);
            rows_out(VideoRow::Scored(row));
        }
        if let Some(objects) = &c.objects {
            rows_out(VideoRow::ObjectPartition {
                clip: c.name,
                boundary_variance_px2: boundary_variance(objects, &input_motion),
            });
        }
    }
    Ok(rows)
}
