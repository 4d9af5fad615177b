//! `cpsl render`: one pose or a sweep of poses.

use crate::progress::Bars;
use crate::util::{self, Output};
use anyhow::{bail, Context, Result};
use clap::Args;
use cpsl_core::{Pose, PremulImage, Progress, ProgressEvent, Vec3};
use cpsl_player::Source;
use cpsl_render::{DpsConfig, Renderer};
use std::path::{Path, PathBuf};

/// The Dynamic Pixel Strip as every command renders it.
pub const DPS: DpsConfig = DpsConfig::DEFAULT;

/// Arguments of `cpsl render`.
#[derive(Args)]
pub struct RenderArgs {
    /// A layer-set folder (from `cpsl layer`) or a package (from `cpsl encode`, decoded first).
    pub layerset: PathBuf,
    /// Frame of a package to render with --pose (a --sweep plays the package's frames, one per
    /// step, looping).
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
    /// Colour behind the layers, `R,G,B`.
    #[arg(long, default_value = "0,0,0", value_parser = util::parse_rgb)]
    pub background: [u8; 3],
    /// Keep transparency: write straight-alpha RGBA instead of compositing over --background.
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
}

/// A sweep of poses along one axis.
#[derive(Debug, Clone, Copy)]
pub struct Sweep {
    axis: usize,
    from: f64,
    to: f64,
    steps: usize,
}

impl Sweep {
    /// Parses `axis:from:to:steps`.
    pub fn parse(s: &str) -> Result<Self, String> {
        let parts: Vec<&str> = s.split(':').collect();
        let err =
            |m: &str| format!("sweep '{s}': {m}; expected axis:from:to:steps, e.g. tx:-0.2:0.2:30");
        if parts.len() != 4 {
            return Err(err("needs 4 fields"));
        }
        let axis = match parts[0] {
            "tx" | "x" => 0,
            "ty" | "y" => 1,
            "tz" | "z" => 2,
            "rx" => 3,
            "ry" => 4,
            "rz" => 5,
            _ => return Err(err("axis must be tx, ty, tz, rx, ry or rz")),
        };
        let num = |p: &str| p.parse::<f64>().ok().filter(|v| v.is_finite());
        let (Some(from), Some(to)) = (num(parts[1]), num(parts[2])) else {
            return Err(err("from and to must be finite numbers"));
        };
        let steps: usize = parts[3]
            .parse()
            .map_err(|_| err("steps must be a whole number"))?;
        if !(1..=10_000).contains(&steps) {
            return Err(err("steps must be in 1..=10000"));
        }
        Ok(Self {
            axis,
            from,
            to,
            steps,
        })
    }

    /// The poses of the sweep.
    pub fn poses(&self) -> Vec<Pose> {
        (0..self.steps)
            .map(|i| {
                let t = if self.steps == 1 {
                    0.0
                } else {
                    i as f64 / (self.steps - 1) as f64
                };
                let mut v = [0.0; 6];
                v[self.axis] = self.from + (self.to - self.from) * t;
                Pose::from_euler_deg(Vec3::new(v[0], v[1], v[2]), v[3], v[4], v[5])
            })
            .collect()
    }
}

/// Renders `poses` into `dir` as `frame_NNN.png`, plus `sheet.png` (five frames side by side)
/// and, when FFmpeg is present, `sweep.mp4`. A package plays along the sweep, one frame per
/// pose.
#[allow(clippy::too_many_arguments)]
pub fn render_sweep(
    source: &mut Source,
    renderer: &dyn Renderer,
    dps: bool,
    poses: &[Pose],
    dir: &Path,
    how: Output,
    fps: u32,
    progress: &dyn Progress,
) -> Result<()> {
    std::fs::create_dir_all(dir).with_context(|| format!("creating {}", dir.display()))?;
    let cam = *source.at(0)?.set.camera();
    let mut img = PremulImage::new(cam.width, cam.height);
    let n = poses.len();
    let picks: Vec<usize> = if n <= 5 {
        (0..n).collect()
    } else {
        (0..5).map(|i| i * (n - 1) / 4).collect()
    };
    let mut sheet = Vec::new();
    let (mut sw, mut sh) = (0, 0);
    progress.event(ProgressEvent::Start {
        stage: "render sweep",
        total: Some(poses.len() as u64),
    });
    for (i, pose) in poses.iter().enumerate() {
        renderer.render(source.at(i)?, pose, &cam, dps.then_some(&DPS), &mut img)?;
        util::write_render(&dir.join(format!("frame_{i:03}.png")), &img, how)?;
        if picks.contains(&i) {
            let (small, w, h) = util::downscale_rgb(
                &img.over_background([0, 0, 0]),
                cam.width as usize,
                cam.height as usize,
                320,
            );
            sheet.push(small);
            (sw, sh) = (w, h);
        }
        progress.event(ProgressEvent::Advance {
            stage: "render sweep",
            done: i as u64 + 1,
        });
    }
    progress.event(ProgressEvent::Finish {
        stage: "render sweep",
    });
    let (rgb, w, h) = util::contact_sheet(&sheet, sw, sh);
    cpsl_io::images::write_png(&dir.join("sheet.png"), w as u32, h as u32, 3, &rgb)?;
    if util::have_ffmpeg() {
        util::encode_mp4(dir, "frame_%03d.png", fps, Path::new("sweep.mp4"))?;
    } else {
        progress.event(ProgressEvent::Warning {
            message: "ffmpeg not found: frames written, sweep.mp4 skipped (apt install ffmpeg)"
                .into(),
        });
    }
    Ok(())
}

/// Runs `cpsl render`.
pub fn run(a: RenderArgs) -> Result<()> {
    let mut source = Source::open(&a.layerset)?;
    let progress = Bars::default();
    let renderer = cpsl_player::choose_renderer(a.gpu, &progress);
    if a.gpu {
        eprintln!("rendering on {}", renderer.name());
    }
    let dps = !a.no_dps;
    let how = if a.alpha {
        Output::Alpha
    } else {
        Output::Over(a.background)
    };
    match (a.pose, a.sweep) {
        (Some(pose), None) => {
            let frame = source.frame(a.frame)?;
            let cam = *frame.set.camera();
            let mut img = PremulImage::new(cam.width, cam.height);
            renderer.render(frame, &pose, &cam, dps.then_some(&DPS), &mut img)?;
            util::write_render(&a.output, &img, how)?;
            println!("wrote {}", a.output.display());
        }
        (None, Some(sweep)) => {
            render_sweep(
                &mut source,
                &*renderer,
                dps,
                &sweep.poses(),
                &a.output,
                how,
                a.fps,
                &progress,
            )?;
            println!("wrote {} frames to {}", sweep.steps, a.output.display());
        }
        _ => bail!("give either --pose tx,ty,tz,rx,ry,rz or --sweep axis:from:to:steps"),
    }
    Ok(())
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn sweep_parsing() {
        let s = Sweep::parse("tx:-0.2:0.2:5").unwrap();
        let p = s.poses();
        assert_eq!(p.len(), 5);
        assert!(
            (p[0].translation.x() + 0.2).abs() < 1e-12
                && (p[4].translation.x() - 0.2).abs() < 1e-12
        );
        assert!(Sweep::parse("ry:0:10:3").unwrap().poses()[2].euler_deg().1 - 10.0 < 1e-9);
        for bad in ["tx:0:1", "qq:0:1:3", "tx:a:1:3", "tx:0:1:0", "tx:0:inf:3"] {
            assert!(Sweep::parse(bad).is_err(), "{bad}");
        }
    }
}
