//! The GPU render benchmark (`cpsl-gpu-bench`): synthetic layer sets of every size, layer
//! count, geometry and coverage asked for, each rendered by the wgpu renderer and timed
//! (GPU timestamps per view, submission to completion per view, and views submitted back to
//! back), and each image checked against the CPU reference renderer's.
//!
//! It links neither FFmpeg nor ONNX Runtime, so that the binary runs on a machine that has a
//! Vulkan driver and nothing else of cpsl's dependencies.

use cpsl_core::image::psnr;
use cpsl_core::run::{RunInfo, Timing};
use cpsl_core::{LayerSet, Pose, PremulImage};
use cpsl_layering::GeometryMode;
use cpsl_render::{CpuRenderer, DpsConfig, FrameLayers, Renderer};
use cpsl_render_gpu::{Fill, GpuRenderer, Passes};
use cpsl_synth::layers::{synthetic_layer_set, Coverage};
use serde::Serialize;
use std::time::Instant;

/// What [`bench()`] runs: every combination of the lists.
#[derive(Debug, Clone)]
pub struct GpuBench {
    /// Frame sizes, width x height.
    pub sizes: Vec<(u32, u32)>,
    /// Layer counts K.
    pub layers: Vec<usize>,
    /// Layer geometries.
    pub geometries: Vec<GeometryMode>,
    /// Layer contents.
    pub coverages: Vec<Coverage>,
    /// How the composite and strip passes run (each case once per entry).
    pub passes: Vec<Passes>,
    /// Seconds of views rendered before each case is timed (a GPU left idle while the CPU
    /// built the case slows its clocks down).
    pub warm_up_s: f64,
    /// Views timed one at a time (each waited for), after the warm-up.
    pub frames: usize,
    /// Views submitted back to back for the sustained rate.
    pub throughput_frames: usize,
    /// The viewer pose.
    pub pose: Pose,
    /// The least PSNR of the GPU image against the CPU reference's that passes.
    pub min_psnr_db: f64,
}

/// The adapter, as wgpu reports it.
#[derive(Debug, Clone, Serialize)]
pub struct Adapter {
    /// Its name.
    pub name: String,
    /// The graphics API.
    pub backend: String,
    /// Discrete, integrated, CPU...
    pub device_type: String,
    /// The driver.
    pub driver: String,
    /// The driver's version.
    pub driver_info: String,
    /// Whether it has GPU timestamp queries.
    pub timestamps: bool,
}

impl Adapter {
    /// The adapter `gpu` runs on.
    pub fn of(gpu: &GpuRenderer) -> Self {
        let i = gpu.adapter_handle().get_info();
        Self {
            name: i.name,
            backend: format!("{:?}", i.backend),
            device_type: format!("{:?}", i.device_type),
            driver: i.driver,
            driver_info: i.driver_info,
            timestamps: gpu
                .device()
                .features()
                .contains(cpsl_render_gpu::wgpu::Features::TIMESTAMP_QUERY),
        }
    }
}

/// One case: a layer set rendered with or without the Dynamic Pixel Strip.
#[derive(Debug, Clone, Serialize)]
pub struct CaseReport {
    /// Frame width.
    pub width: u32,
    /// Frame height.
    pub height: u32,
    /// Layers.
    pub layers: usize,
    /// Their geometry.
    pub geometry: &'static str,
    /// Their content (`typical` or `dense`).
    pub coverage: &'static str,
    /// Whether the strip pass ran after compositing.
    pub dps: bool,
    /// `compute` or `fragment` passes.
    pub passes: &'static str,
    /// GPU timestamps from the first pass's start to the last's end, per view (where the
    /// adapter has them).
    pub gpu: Option<Timing>,
    /// Per view, from submission to completion as the host sees it.
    pub wall: Timing,
    /// Views per second at the GPU timestamps' median (else the wall clock's).
    pub fps: f64,
    /// Views per second submitted back to back (recording overlaps the GPU's work).
    pub sustained_fps: f64,
    /// PSNR of the GPU image against the CPU reference's, over black (99 = identical).
    pub psnr_vs_cpu_db: f64,
    /// Whether that PSNR reaches the bench's minimum.
    pub matches_cpu: bool,
    /// One CPU reference render of the same view, for scale.
    pub cpu_ms: f64,
    /// Per view, the fill of what it leaves uncovered as the players show it
    /// (`cpsl_render_gpu::Fill`), from submission to completion.
    pub fill: Timing,
}

/// The report of [`bench()`] (`cpsl-gpu-bench --json`).
#[derive(Debug, Clone, Serialize)]
pub struct GpuReport {
    /// Where and when it ran.
    #[serde(flatten)]
    pub run: RunInfo,
    /// The adapter.
    pub adapter: Adapter,
    /// The viewer pose, `tx,ty,tz,rx,ry,rz` (rotations in degrees).
    pub pose: [f64; 6],
    /// Views timed per case.
    pub frames: usize,
    /// Views submitted back to back per case.
    pub throughput_frames: usize,
    /// The least PSNR against the CPU reference that passes.
    pub min_psnr_db: f64,
    /// Every case.
    pub cases: Vec<CaseReport>,
    /// Whether every case matched the CPU reference.
    pub all_match: bool,
}

/// The name of a coverage.
pub fn coverage_name(c: Coverage) -> &'static str {
    match c {
        Coverage::Typical => "typical",
        Coverage::Dense => "dense",
    }
}

/// The synthetic layer set of a case (deterministic).
pub fn case_set(w: u32, h: u32, k: usize, g: GeometryMode, c: Coverage) -> LayerSet {
    let set = synthetic_layer_set(w, h, k, c, 7);
    match g {
        GeometryMode::Plane => set,
        GeometryMode::Slanted => cpsl_synth::layers::slanted(set),
        GeometryMode::Mesh => {
            cpsl_synth::layers::meshed(set, cpsl_layering::geometry::auto_mesh_step(w, h))
        }
    }
}

/// The name of a way to run the passes.
pub fn passes_name(p: Passes) -> &'static str {
    match p {
        Passes::Compute => "compute",
        Passes::Fragment => "fragment",
    }
}

/// Runs every case on `gpu`, calling `each` with the report so far after each case (so that
/// a run cut short still leaves its figures).
pub fn bench(
    gpu: &mut GpuRenderer,
    a: &GpuBench,
    mut each: impl FnMut(&GpuReport),
) -> Result<GpuReport, cpsl_render_gpu::GpuError> {
    let (rx, ry, rz) = a.pose.euler_deg();
    let t = a.pose.translation;
    let mut report = GpuReport {
        run: RunInfo::now(),
        adapter: Adapter::of(gpu),
        pose: [t.x(), t.y(), t.z(), rx, ry, rz],
        frames: a.frames,
        throughput_frames: a.throughput_frames,
        min_psnr_db: a.min_psnr_db,
        cases: Vec::new(),
        all_match: true,
    };
    let ms = |v: Vec<f64>| Timing::of(v.into_iter().map(|s| s * 1e3).collect());
    let mut fill = Fill::new(gpu.device(), gpu.adapter_handle());
    for &(w, h) in &a.sizes {
        for &k in &a.layers {
            for &g in &a.geometries {
                for &c in &a.coverages {
                    let frame = FrameLayers::new(case_set(w, h, k, g, c), None);
                    let cam = *frame.set.camera();
                    let up = gpu.prepare(&frame.set, None)?;
                    // The CPU reference of the view, without and with the strip: rendered
                    // once, whichever way the GPU's passes run.
                    let mut reference = Vec::new();
                    for dps in [None, Some(&DpsConfig::DEFAULT)] {
                        let mut cpu = PremulImage::new(w, h);
                        let t = Instant::now();
                        CpuRenderer::default()
                            .render(&frame, &a.pose, &cam, dps, &mut cpu)
                            .map_err(|e| cpsl_render_gpu::GpuError::Layers(e.to_string()))?;
                        let cpu_ms = t.elapsed().as_secs_f64() * 1e3;
                        reference.push((dps, cpu.over_background([0, 0, 0]), cpu_ms));
                    }
                    let runs = a
                        .passes
                        .iter()
                        .flat_map(|&p| reference.iter().map(move |r| (p, r)));
                    for (passes, (dps, cpu, cpu_ms)) in runs {
                        let (dps, cpu_ms) = (*dps, *cpu_ms);
                        gpu.set_passes(passes)?;
                        let img = gpu.render(&up, &a.pose, &cam, dps)?;
                        let p = psnr(cpu, &img.over_background([0, 0, 0])).min(99.0);
                        let warm = Instant::now();
                        while warm.elapsed().as_secs_f64() < a.warm_up_s {
                            gpu.throughput(&up, &a.pose, &cam, dps, 10)?;
                        }
                        let times = gpu.time_renders(&up, &a.pose, &cam, dps, a.frames.max(1))?;
                        let fills =
                            gpu.time_fills(&mut fill, &up, &a.pose, &cam, dps, a.frames.max(1))?;
                        let sustained =
                            gpu.throughput(&up, &a.pose, &cam, dps, a.throughput_frames.max(1))?;
                        let gpu_t = times.gpu.filter(|v| !v.is_empty()).map(ms);
                        let wall = ms(times.wall);
                        let median = gpu_t.as_ref().unwrap_or(&wall).median_ms;
                        let case = CaseReport {
                            width: w,
                            height: h,
                            layers: k,
                            geometry: g.name(),
                            coverage: coverage_name(c),
                            dps: dps.is_some(),
                            passes: passes_name(passes),
                            gpu: gpu_t,
                            wall,
                            fps: 1e3 / median,
                            sustained_fps: 1.0 / sustained,
                            psnr_vs_cpu_db: p,
                            matches_cpu: p >= a.min_psnr_db,
                            cpu_ms,
                            fill: ms(fills),
                        };
                        report.all_match &= case.matches_cpu;
                        report.cases.push(case);
                        each(&report);
                    }
                }
            }
        }
    }
    Ok(report)
}
