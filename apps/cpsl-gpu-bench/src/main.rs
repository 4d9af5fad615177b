//! `cpsl-gpu-bench`: the wgpu renderer timed on synthetic layers of every size, layer count
//! and geometry asked for, and checked against the CPU reference (see the library). Needs a
//! Vulkan (or GL) driver and nothing else.

use anyhow::{bail, Context, Result};
use clap::Parser;
use cpsl_core::Pose;
use cpsl_gpu_bench::{bench, GpuBench, GpuReport};
use cpsl_layering::GeometryMode;
use cpsl_render_gpu::{GpuRenderer, Passes};
use cpsl_synth::layers::Coverage;
use std::path::PathBuf;

/// Times the GPU renderer and checks it against the CPU reference.
#[derive(Parser)]
#[command(version)]
struct Args {
    /// Frame sizes, comma-separated `WIDTHxHEIGHT`.
    #[arg(long, default_value = "1920x1080,3840x2160", value_delimiter = ',', value_parser = parse_size)]
    sizes: Vec<(u32, u32)>,
    /// Layer counts K (1 to 16), comma-separated.
    #[arg(long, default_value = "6,8,16", value_delimiter = ',', value_parser = clap::value_parser!(u32).range(1..=16))]
    layers: Vec<u32>,
    /// Layer geometries: plane, slanted, mesh.
    #[arg(long, default_value = "plane,slanted,mesh", value_delimiter = ',')]
    geometry: Vec<GeometryMode>,
    /// Layer contents: typical (feathered shapes over a fifth of each front layer) and dense
    /// (every layer semi-transparent everywhere).
    #[arg(long, default_value = "typical,dense", value_delimiter = ',', value_parser = parse_coverage)]
    coverage: Vec<Coverage>,
    /// How the composite and strip passes run: compute, fragment.
    #[arg(long, default_value = "compute,fragment", value_delimiter = ',', value_parser = parse_passes)]
    passes: Vec<Passes>,
    /// Seconds of warm-up views before each case (an idle GPU lowers its clocks).
    #[arg(long, default_value_t = 0.3)]
    warm_up: f64,
    /// Views timed one at a time per case (after the warm-up).
    #[arg(long, default_value_t = 100, value_parser = clap::value_parser!(u32).range(1..))]
    frames: u32,
    /// Views submitted back to back per case for the sustained rate.
    #[arg(long, default_value_t = 200, value_parser = clap::value_parser!(u32).range(1..))]
    throughput_frames: u32,
    /// Viewer pose `tx,ty,tz,rx,ry,rz` (rotations in degrees).
    #[arg(long, allow_hyphen_values = true, default_value = "0.05,-0.02,0.03,0.4,-0.8,0.2", value_parser = Pose::parse)]
    pose: Pose,
    /// The least PSNR (dB) of each GPU image against the CPU reference's.
    #[arg(long, default_value_t = 45.0)]
    min_psnr: f64,
    /// Write the JSON report here.
    #[arg(long)]
    json: Option<PathBuf>,
}

fn parse_size(s: &str) -> Result<(u32, u32), String> {
    let (w, h) = s
        .split_once('x')
        .ok_or_else(|| format!("{s:?}: expected WIDTHxHEIGHT"))?;
    let n = |v: &str| {
        v.parse::<u32>()
            .ok()
            .filter(|&n| (16..=8192).contains(&n))
            .ok_or_else(|| format!("{s:?}: sides are 16 to 8192 pixels"))
    };
    Ok((n(w)?, n(h)?))
}

fn parse_coverage(s: &str) -> Result<Coverage, String> {
    match s {
        "typical" => Ok(Coverage::Typical),
        "dense" => Ok(Coverage::Dense),
        _ => Err(format!("{s:?}: expected typical or dense")),
    }
}

fn parse_passes(s: &str) -> Result<Passes, String> {
    match s {
        "compute" => Ok(Passes::Compute),
        "fragment" => Ok(Passes::Fragment),
        _ => Err(format!("{s:?}: expected compute or fragment")),
    }
}

fn main() -> Result<()> {
    let a = Args::parse();
    let mut gpu = GpuRenderer::new().context("opening the GPU")?;
    eprintln!("cpsl-gpu-bench on {}", gpu.adapter());
    let opts = GpuBench {
        sizes: a.sizes,
        layers: a.layers.iter().map(|&k| k as usize).collect(),
        geometries: a.geometry,
        coverages: a.coverage,
        passes: a.passes,
        warm_up_s: a.warm_up,
        frames: a.frames as usize,
        throughput_frames: a.throughput_frames as usize,
        pose: a.pose,
        min_psnr_db: a.min_psnr,
    };
    println!(
        "{:>9} {:>2} {:>7} {:>7} {:>8} {:>3} | {:>8} {:>8} {:>8} | {:>8} {:>8} | {:>6} {:>8} | {:>8}",
        "size",
        "K",
        "geom",
        "cover",
        "passes",
        "dps",
        "gpu med",
        "gpu p99",
        "wall med",
        "fps",
        "sust fps",
        "dB",
        "cpu ms",
        "fill med"
    );
    let save = |report: &GpuReport| -> Result<()> {
        if let Some(p) = &a.json {
            std::fs::write(p, serde_json::to_vec_pretty(report)?)
                .with_context(|| format!("writing {}", p.display()))?;
        }
        Ok(())
    };
    let mut saved = Ok(());
    let report = bench(&mut gpu, &opts, |r| {
        let c = r.cases.last().expect("called after a case");
        let (med, p99) = c
            .gpu
            .as_ref()
            .map_or((f64::NAN, f64::NAN), |t| (t.median_ms, t.p99_ms));
        println!(
            "{:>9} {:>2} {:>7} {:>7} {:>8} {:>3} | {:>8.3} {:>8.3} {:>8.3} | {:>8.0} {:>8.0} | {:>6.1} {:>8.1} | {:>8.3}{}",
            format!("{}x{}", c.width, c.height),
            c.layers,
            c.geometry,
            c.coverage,
            c.passes,
            if c.dps { "yes" } else { "no" },
            med,
            p99,
            c.wall.median_ms,
            c.fps,
            c.sustained_fps,
            c.psnr_vs_cpu_db,
            c.cpu_ms,
            c.fill.median_ms,
            if c.matches_cpu { "" } else { "  MISMATCH" }
        );
        // Written after every case, so that a run cut short keeps what it measured.
        if saved.is_ok() {
            saved = save(r);
        }
    })?;
    saved?;
    if !report.all_match {
        bail!(
            "the GPU image differs from the CPU reference's by more than {} dB allows in {} case(s)",
            a.min_psnr,
            report.cases.iter().filter(|c| !c.matches_cpu).count()
        );
    }
    Ok(())
}
