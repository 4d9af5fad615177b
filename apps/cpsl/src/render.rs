//! `cpsl render`: one pose or a sweep of poses.

use crate::progress::Bars;
use crate::util::FilterArg;
use anyhow::{bail, Result};
use clap::Args;
use cpsl_core::{Pose, PremulImage};
use cpsl_player::sweep::{render_sweep, write_render, Output, Sweep};
use cpsl_player::Source;
use cpsl_render::DpsConfig;
use std::path::PathBuf;

/// Arguments of `cpsl render`.
#[derive(Args)]
pub struct RenderArgs {
    /// A layer-set folder (from `cpsl layer`), a layered video (from `cpsl layer-video`) or a
    /// package (from `cpsl encode`, decoded first).
    pub layerset: PathBuf,
    /// Frame of a package or layered video to render with --pose (a --sweep plays its frames,
    /// one per step, looping).
    #[arg(long, default_value_t = 0)]
    pub frame: u32,
    /// Viewer pose `tx,ty,tz,rx,ry,rz`: the viewer's position in the reference camera frame
    /// (x right, y down, z forward, scene units) and yaw/pitch/roll in degrees
    /// (R = Ry(ry) Rx(rx) Rz(rz); +ry looks right, +rx looks up).
    #[arg(long, allow_hyphen_values = true, conflicts_with = "sweep", value_parser = Pose::parse)]
    pub pose: Option<Pose>,
    /// Sweep `axis:from:to:steps` with axis one of tx, ty, tz (scene units) or rx, ry, rz
    /// (degrees); writes numbered frames, a contact sheet and (with FFmpeg) sweep.mp4.
    #[arg(long, allow_hyphen_values = true, value_parser = Sweep::parse)]
    pub sweep: Option<Sweep>,
    /// Output PNG (with --pose) or folder (with --sweep).
    #[arg(short, long)]
    pub output: PathBuf,
    /// What shows where the layers leave the view uncovered (beyond the frame's edge when the
    /// viewpoint looks past it): `fill` (extended from the covered pixels around it, as DIBR
    /// fills its holes) or a colour `R,G,B`.
    #[arg(long, default_value = "fill", value_parser = parse_background)]
    pub background: Output,
    /// Keep transparency: write straight-alpha RGBA instead of filling or compositing over
    /// --background.
    #[arg(long)]
    pub alpha: bool,
    /// Frames per second of the sweep video.
    #[arg(long, default_value_t = 30)]
    pub fps: u32,
    /// Render without the Dynamic Pixel Strip (ablation).
    #[arg(long)]
    pub no_dps: bool,
    /// Render on the GPU (wgpu: Vulkan, Metal or GL; lavapipe on machines without one);
    /// falls back to the CPU renderer, saying so, when no adapter exists.
    #[arg(long)]
    pub gpu: bool,
    /// How the renderer resamples the layers: `cubic` (Catmull-Rom: sharper where the view
    /// shifts layers by fractions of a pixel; 4x the texel reads, about 3x the CPU's render
    /// time; the players draw it with `filter=cubic` or key C) or `bilinear` (the players'
    /// real-time default, so that a render matches what they show by default).
    #[arg(long, value_enum, default_value_t = FilterArg::Cubic)]
    pub filter: FilterArg,
}

/// `fill` or `R,G,B`.
fn parse_background(s: &str) -> Result<Output, String> {
    if s == "fill" {
        return Ok(Output::Fill);
    }
    crate::util::parse_rgb(s)
        .map(Output::Over)
        .map_err(|e| format!("{e}, or `fill`"))
}

/// Runs `cpsl render`.
pub fn run(a: RenderArgs) -> Result<()> {
    let mut source = Source::open(&a.layerset)?;
    let progress = Bars::default();
    let renderer = cpsl_player::choose_renderer(a.gpu, a.filter.into(), &progress);
    if a.gpu {
        eprintln!("rendering on {}", renderer.name());
    }
    let dps = !a.no_dps;
    let how = if a.alpha { Output::Alpha } else { a.background };
    match (a.pose, a.sweep) {
        (Some(pose), None) => {
            let frame = source.frame(a.frame)?;
            let cam = *frame.set.camera();
            let mut img = PremulImage::new(cam.width, cam.height);
            renderer.render(
                frame,
                &pose,
                &cam,
                dps.then_some(&DpsConfig::DEFAULT),
                &mut img,
            )?;
            write_render(&a.output, &img, how)?;
            println!("wrote {}", a.output.display());
        }
        (None, Some(sweep)) => {
            let poses = sweep.poses();
            render_sweep(
                &mut source,
                &*renderer,
                dps,
                &poses,
                &a.output,
                how,
                a.fps,
                &progress,
            )?;
            println!("wrote {} frames to {}", poses.len(), a.output.display());
        }
        _ => bail!("give either --pose tx,ty,tz,rx,ry,rz or --sweep axis:from:to:steps"),
    }
    Ok(())
}
