//! Timed playback (`cpsl bench play`, `cpsl-gpu-play`): a package decoded frame after frame
//! in lock step with rendering, on the CPU reference or on the GPU, with per-stage times.

use crate::{Player, PlayerError};
use cpsl_core::run::{peak_rss_kib, RunInfo, Timing};
use cpsl_core::{Pose, PremulImage};
use cpsl_render::{CpuRenderer, DpsConfig, Renderer};
use cpsl_render_gpu::GpuRenderer;
use serde::Serialize;
use std::path::PathBuf;
use std::time::Instant;

/// What [`bench_play`] plays.
#[derive(Debug, Clone)]
pub struct PlayBench {
    /// The package (folder or single file).
    pub package: PathBuf,
    /// Frames to play (from the first, looping); every frame once when `None`.
    pub frames: Option<u32>,
    /// The pose every frame is rendered at.
    pub pose: Pose,
    /// Render with the Dynamic Pixel Strip.
    pub dps: bool,
}

/// Playback timings (the JSON of `cpsl bench play` and `cpsl-gpu-play`).
#[derive(Debug, Serialize)]
pub struct PlayReport {
    /// Where and when it was measured.
    #[serde(flatten)]
    pub run: RunInfo,
    /// The package.
    pub package: String,
    /// Frame width.
    pub width: u32,
    /// Frame height.
    pub height: u32,
    /// Layers.
    pub layers: usize,
    /// The codec.
    pub codec: String,
    /// The package's bitrate in kbit/s.
    pub kbit_per_s: f64,
    /// The package's frame rate.
    pub package_fps: f64,
    /// Frames timed.
    pub frames: u32,
    /// Whether the Dynamic Pixel Strip ran.
    pub dps: bool,
    /// The renderer: "cpu" or the GPU adapter's name.
    pub renderer: String,
    /// Decoding every layer stream's picture (on the CPU) and building the layer set.
    pub decode: Timing,
    /// Preparing the layers for the renderer (on the GPU: creating the texture and queueing
    /// its upload, which the render's submission carries out).
    pub prepare: Timing,
    /// Rendering, from the host: on the GPU from submission (upload included) to completion.
    pub render: Timing,
    /// On the GPU, its timestamps of the render passes alone.
    pub gpu_render: Option<Timing>,
    /// A whole frame: decode, prepare and render, one after another.
    pub frame: Timing,
    /// Frames over the whole wall time, stages one after another on this thread (a player
    /// that decodes ahead on another thread overlaps them only where cores are free).
    pub fps: f64,
    /// The process's peak resident memory.
    pub peak_rss_mib: f64,
}

/// Plays a package, timing decoding, preparation and rendering per frame: on `gpu` where
/// given, else on the CPU reference.
pub fn bench_play(a: &PlayBench, gpu: Option<&GpuRenderer>) -> Result<PlayReport, PlayerError> {
    let mut player = Player::open(&a.package)?;
    let m = player.package().manifest().clone();
    let frames = a.frames.unwrap_or(m.frames).max(1);
    let cam = m.camera;
    let mut img = PremulImage::new(cam.width, cam.height);
    let mut decode = Vec::with_capacity(frames as usize);
    let (mut prepare, mut render, mut whole) = (decode.clone(), decode.clone(), decode.clone());
    let mut gpu_render = gpu.map(|_| Vec::with_capacity(frames as usize));
    let mut layers = 0;
    let ms = |t: Instant| t.elapsed().as_secs_f64() * 1e3;
    let started = Instant::now();
    let dps = a.dps.then_some(&DpsConfig::DEFAULT);
    for i in 0..frames {
        let t0 = Instant::now();
        // Frame after frame, looping at the end.
        let frame = player.decode(i % m.frames)?;
        decode.push(ms(t0));
        layers = layers.max(frame.set.len());
        let t = Instant::now();
        match gpu {
            Some(g) => {
                let up = g.prepare(&frame.set, frame.edc.as_ref())?;
                prepare.push(ms(t));
                let times = g.time_renders(&up, &a.pose, &cam, dps, 1)?;
                render.push(times.wall[0] * 1e3);
                if let (Some(v), Some(s)) = (&mut gpu_render, times.gpu) {
                    v.push(s[0] * 1e3);
                }
            }
            None => {
                frame.prepared();
                prepare.push(ms(t));
                let t = Instant::now();
                CpuRenderer::default().render(&frame, &a.pose, &cam, dps, &mut img)?;
                render.push(ms(t));
            }
        }
        whole.push(ms(t0));
    }
    let wall = started.elapsed().as_secs_f64();
    Ok(PlayReport {
        run: RunInfo::now(),
        package: a.package.display().to_string(),
        width: cam.width,
        height: cam.height,
        layers,
        codec: m.codec.name().to_string(),
        kbit_per_s: m.bitrate() / 1e3,
        package_fps: m.frame_rate,
        frames,
        dps: a.dps,
        renderer: gpu.map_or("cpu".into(), |g| g.adapter().to_string()),
        decode: Timing::of(decode),
        prepare: Timing::of(prepare),
        render: Timing::of(render),
        gpu_render: gpu_render.filter(|v| !v.is_empty()).map(Timing::of),
        frame: Timing::of(whole),
        fps: frames as f64 / wall,
        peak_rss_mib: peak_rss_kib() as f64 / 1024.0,
    })
}
