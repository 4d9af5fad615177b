//! `cpsl-gpu-play`: a package played on the GPU (decoding on the CPU through FFmpeg, the
//! layers uploaded and rendered each frame, in lock step), with per-stage frame times;
//! optionally the same on the CPU reference for comparison.

use anyhow::{Context, Result};
use clap::Parser;
use cpsl_core::Pose;
use cpsl_player::bench::{bench_play, PlayBench, PlayReport};
use cpsl_render_gpu::GpuRenderer;
use std::path::PathBuf;

/// Plays a package on the GPU and times it.
#[derive(Parser)]
#[command(version)]
struct Args {
    /// The package (folder or single file).
    package: PathBuf,
    /// Frames to play (from the first, looping); default every frame once.
    #[arg(long, value_parser = clap::value_parser!(u32).range(1..))]
    frames: Option<u32>,
    /// Viewer pose `tx,ty,tz,rx,ry,rz` every frame is rendered at (rotations in degrees).
    #[arg(long, allow_hyphen_values = true, default_value = "0.05,-0.02,0,0,0,0", value_parser = Pose::parse)]
    pose: Pose,
    /// Render without the Dynamic Pixel Strip.
    #[arg(long)]
    no_dps: bool,
    /// Also play it on the CPU reference renderer, after the GPU.
    #[arg(long)]
    cpu: bool,
    /// Write the JSON report (a list: the GPU's, then the CPU's) here.
    #[arg(long)]
    json: Option<PathBuf>,
}

fn print(r: &PlayReport) {
    println!(
        "{} ({}x{}, {} layers, {} at {:.0} kbit/s, {} fps): {} frames on {}",
        r.package,
        r.width,
        r.height,
        r.layers,
        r.codec,
        r.kbit_per_s,
        r.package_fps,
        r.frames,
        r.renderer
    );
    let stages = [
        ("decode", &r.decode),
        ("prepare", &r.prepare),
        ("render", &r.render),
        ("frame", &r.frame),
    ];
    for (name, t) in stages
        .into_iter()
        .chain(r.gpu_render.as_ref().map(|t| ("gpu", t)))
    {
        println!(
            "  {name:<8} median {:>7.2} ms  p90 {:>7.2} ms  p99 {:>7.2} ms  max {:>7.2} ms",
            t.median_ms, t.p90_ms, t.p99_ms, t.max_ms
        );
    }
    println!(
        "  {:.1} frames/s end to end, peak memory {:.0} MiB",
        r.fps, r.peak_rss_mib
    );
}

fn main() -> Result<()> {
    let a = Args::parse();
    let gpu = GpuRenderer::new().context("opening the GPU")?;
    let opts = PlayBench {
        package: a.package,
        frames: a.frames,
        pose: a.pose,
        dps: !a.no_dps,
    };
    let mut reports = vec![bench_play(&opts, Some(&gpu))?];
    print(&reports[0]);
    if a.cpu {
        reports.push(bench_play(&opts, None)?);
        print(&reports[1]);
    }
    if let Some(p) = &a.json {
        std::fs::write(p, serde_json::to_vec_pretty(&reports)?)
            .with_context(|| format!("writing {}", p.display()))?;
    }
    Ok(())
}
