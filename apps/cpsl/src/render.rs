//! `cpsl render`: one pose or a sweep of poses.

use crate::progress::Bars;
use crate::util::{self, Output};
use anyhow::{bail, Context, Result};
use clap::Args;
use cpsl_core::{Camera, Edc, LayerSet, Pose, PremulImage, Progress, ProgressEvent, Vec3};
use cpsl_render::PreparedLayers;
use cpsl_render_gpu::GpuRenderer;
use std::path::{Path, PathBuf};

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

/// One frame's layers: the layer set and its cache, and their CPU preparation.
pub struct Frame {
    /// The layers.
    pub set: LayerSet,
    /// Their Edge-Depth Cache, when there is one.
    pub edc: Option<Edc>,
    /// Prepared for the CPU renderer, on its first use (the GPU renderer and the viewer
    /// upload the layers themselves).
    prepared: std::sync::OnceLock<PreparedLayers>,
}

impl Frame {
    /// A frame of `set` (with `edc`) to render.
    pub fn new(set: LayerSet, edc: Option<Edc>) -> Self {
        Self {
            set,
            edc,
            prepared: std::sync::OnceLock::new(),
        }
    }

    /// The layers prepared for the CPU renderer.
    pub fn prepared(&self) -> &PreparedLayers {
        self.prepared.get_or_init(|| {
            let prepared = PreparedLayers::new(&self.set);
            match &self.edc {
                Some(e) => prepared.with_edc(e),
                None => prepared,
            }
        })
    }
}

/// Which renderer draws.
pub enum Backend {
    /// The CPU reference.
    Cpu,
    /// wgpu.
    Gpu(Box<GpuRenderer>),
}

impl Backend {
    /// The GPU when asked for and present, else the CPU (with a message saying why).
    pub fn choose(gpu: bool) -> Self {
        if !gpu {
            return Backend::Cpu;
        }
        match GpuRenderer::new() {
            Ok(g) => {
                eprintln!("rendering on {}", g.adapter());
                Backend::Gpu(Box::new(g))
            }
            Err(e) => {
                eprintln!("--gpu: {e}; rendering on the CPU instead");
                Backend::Cpu
            }
        }
    }

    /// Renders `frame` at `pose` for camera `target` into `img`, with or without the Dynamic
    /// Pixel Strip.
    pub fn render(
        &self,
        frame: &Frame,
        dps: bool,
        pose: &Pose,
        target: &Camera,
        img: &mut PremulImage,
    ) -> Result<()> {
        match self {
            Backend::Cpu => render_pose(frame.prepared(), dps, pose, target, img),
            Backend::Gpu(g) => {
                let cfg = cpsl_render::DpsConfig::default();
                let layers = g.prepare(&frame.set, frame.edc.as_ref())?;
                *img = g.render(&layers, pose, target, dps.then_some(&cfg))?;
            }
        }
        Ok(())
    }
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

/// What is rendered: one layer set, or the frames of a package.
pub enum Source {
    /// A layer set, prepared.
    Still(Box<Frame>),
    /// A package, decoded one segment at a time.
    Package(Box<PackagePlayer>),
}

impl Source {
    /// Opens a layer-set folder or a package.
    pub fn open(path: &Path) -> Result<Self> {
        if cpsl_package::is_package(path) {
            return Ok(Source::Package(Box::new(PackagePlayer::open(path)?)));
        }
        anyhow::ensure!(
            !path.is_file(),
            "{} is a file, not a layer-set folder or a package (`cpsl layer` makes layers \
             from an image, `cpsl encode` a package from a video)",
            path.display()
        );
        let set = util::load_layer_set(path)?;
        let edc = cpsl_io::read_edc(path, &set, &cpsl_core::Limits::default())?;
        Ok(Source::Still(Box::new(Frame::new(set, edc))))
    }

    /// The layers to show at step `i` (a package's frame `i` modulo its length).
    pub fn at(&mut self, i: usize) -> Result<&Frame> {
        match self {
            Source::Still(p) => Ok(p),
            Source::Package(p) => {
                let n = p.frames() as usize;
                p.frame((i % n) as u32)
            }
        }
    }
}

/// Plays a package: decodes frame after frame of the segment holding the requested one,
/// keeping only the current frame (a seek backwards or into another segment reopens the
/// segment at its key frame).
pub struct PackagePlayer {
    pkg: cpsl_package::Package,
    /// The open segment and its reader.
    reader: Option<(usize, cpsl_codec::SegmentReader)>,
    current: Option<(u32, Frame)>,
}

impl PackagePlayer {
    /// Opens a package (its manifest checked; files are checked as they are decoded).
    pub fn open(path: &Path) -> Result<Self> {
        let pkg = cpsl_package::Package::open(path)
            .with_context(|| format!("opening the package {}", path.display()))?;
        Ok(Self {
            pkg,
            reader: None,
            current: None,
        })
    }

    /// Number of frames.
    pub fn frames(&self) -> u32 {
        self.pkg.manifest().frames
    }

    /// Frame `f`, decoded and prepared for rendering with its Edge-Depth Cache.
    pub fn frame(&mut self, f: u32) -> Result<&Frame> {
        if self.current.as_ref().is_some_and(|c| c.0 == f) {
            return Ok(&self.current.as_ref().unwrap().1);
        }
        let m = self.pkg.manifest();
        let seg = m
            .segment_of(f)
            .with_context(|| format!("frame {f}: the package has {} frames", m.frames))?;
        let start = m.segments[seg].start;
        let ahead =
            |(s, r): &(usize, cpsl_codec::SegmentReader)| *s == seg && start + r.given() <= f;
        if !self.reader.as_ref().is_some_and(ahead) {
            let r = cpsl_codec::SegmentReader::open(&self.pkg, seg).with_context(|| {
                format!("opening segment {seg} of {}", self.pkg.opened().display())
            })?;
            self.reader = Some((seg, r));
        }
        let (_, reader) = self.reader.as_mut().expect("opened above");
        loop {
            let decoded = match reader.next() {
                Some(Ok(d)) => d,
                failed => {
                    // A failed reader is not reused: the next request reopens the segment.
                    self.reader = None;
                    let e = match failed {
                        Some(Err(e)) => anyhow::Error::new(e),
                        _ => anyhow::anyhow!("segment {seg} ended before frame {f}"),
                    };
                    return Err(e.context(format!(
                        "decoding segment {seg} of {}",
                        self.pkg.opened().display()
                    )));
                }
            };
            if decoded.side.index == f {
                self.current = Some((f, Frame::new(decoded.set, Some(decoded.side.edc))));
                return Ok(&self.current.as_ref().unwrap().1);
            }
        }
    }
}

/// Renders `poses` into `dir` as `frame_NNN.png`, plus `sheet.png` (five frames side by side)
/// and, when FFmpeg is present, `sweep.mp4`. A package plays along the sweep, one frame per
/// pose.
#[allow(clippy::too_many_arguments)]
pub fn render_sweep(
    source: &mut Source,
    backend: &Backend,
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
        backend.render(source.at(i)?, dps, pose, &cam, &mut img)?;
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

/// Renders the view of camera `target` at `pose` into `img` on the CPU, with or without the
/// Dynamic Pixel Strip.
pub fn render_pose(
    prepared: &PreparedLayers,
    dps: bool,
    pose: &Pose,
    target: &Camera,
    img: &mut PremulImage,
) {
    if dps {
        prepared.render_dps_into(pose, target, img, &cpsl_render::DpsConfig::default());
    } else {
        prepared.render_into(pose, target, img);
    }
}

/// Runs `cpsl render`.
pub fn run(a: RenderArgs) -> Result<()> {
    let mut source = Source::open(&a.layerset)?;
    let backend = Backend::choose(a.gpu);
    let dps = !a.no_dps;
    let how = if a.alpha {
        Output::Alpha
    } else {
        Output::Over(a.background)
    };
    match (a.pose, a.sweep) {
        (Some(pose), None) => {
            let frame = match &mut source {
                Source::Still(p) => &**p,
                Source::Package(p) => p.frame(a.frame)?,
            };
            let cam = *frame.set.camera();
            let mut img = PremulImage::new(cam.width, cam.height);
            backend.render(frame, dps, &pose, &cam, &mut img)?;
            util::write_render(&a.output, &img, how)?;
            println!("wrote {}", a.output.display());
        }
        (None, Some(sweep)) => {
            render_sweep(
                &mut source,
                &backend,
                dps,
                &sweep.poses(),
                &a.output,
                how,
                a.fps,
                &Bars::default(),
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
