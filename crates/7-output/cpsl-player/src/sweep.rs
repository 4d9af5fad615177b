//! Rendering along a sweep of poses: numbered PNG frames, a contact sheet and an H.264 MP4
//! (through the `ffmpeg` tool, tagged BT.709), a package playing along the sweep.

use crate::{PlayerError, Source};
use cpsl_core::{Pose, PremulImage, Progress, ProgressEvent, Vec3};
use cpsl_io::images::write_png;
use cpsl_render::{DpsConfig, Renderer};
use std::path::Path;
use std::process::Command;

type Result<T> = std::result::Result<T, PlayerError>;

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
    pub fn parse(s: &str) -> std::result::Result<Self, String> {
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

/// How a rendered (premultiplied) image is written to PNG.
#[derive(Debug, Clone, Copy)]
pub enum Output {
    /// RGB, with what the layers leave uncovered (beyond the frame's edge where the viewpoint
    /// looks past it) filled from what they cover ([`PremulImage::over_fill`]).
    Fill,
    /// Composited over an opaque colour, RGB.
    Over([u8; 3]),
    /// Straight-alpha RGBA, uncovered pixels transparent.
    Alpha,
}

/// Writes a render to PNG.
pub fn write_render(path: &Path, img: &PremulImage, how: Output) -> Result<()> {
    let (w, h) = (img.width(), img.height());
    match how {
        Output::Alpha => write_png(path, w, h, 4, &img.to_straight()),
        rgb => write_png(path, w, h, 3, &rgb.rgb(img)),
    }
    .map_err(PlayerError::from)
}

impl Output {
    /// The render as RGB bytes (filled, or over the colour; over black for `Alpha`).
    pub fn rgb(self, img: &PremulImage) -> Vec<u8> {
        match self {
            Self::Fill => img.over_fill(),
            Self::Over(bg) => img.over_background(bg),
            Self::Alpha => img.over_background([0, 0, 0]),
        }
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
    std::fs::create_dir_all(dir).map_err(|source| PlayerError::File {
        path: dir.to_path_buf(),
        source,
    })?;
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
        renderer.render(
            source.at(i)?,
            pose,
            &cam,
            dps.then_some(&DpsConfig::DEFAULT),
            &mut img,
        )?;
        write_render(&dir.join(format!("frame_{i:03}.png")), &img, how)?;
        if picks.contains(&i) {
            let (small, w, h) = cpsl_core::resample::downscale_rgb(
                &how.rgb(&img),
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
    let (rgb, w, h) = contact_sheet(&sheet, sw, sh);
    cpsl_io::images::write_png(&dir.join("sheet.png"), w as u32, h as u32, 3, &rgb)?;
    if have_ffmpeg() {
        encode_mp4(dir, "frame_%03d.png", fps, Path::new("sweep.mp4"))?;
    } else {
        progress.event(ProgressEvent::Warning {
            message: "ffmpeg not found: frames written, sweep.mp4 skipped (apt install ffmpeg)"
                .into(),
        });
    }
    Ok(())
}

/// Lays RGB frames (same size) side by side with a 4 px gap.
pub fn contact_sheet(frames: &[Vec<u8>], w: usize, h: usize) -> (Vec<u8>, usize, usize) {
    let gap = 4;
    let sw = frames.len() * w + (frames.len().saturating_sub(1)) * gap;
    let mut out = vec![255u8; sw * h * 3];
    for (i, f) in frames.iter().enumerate() {
        let x0 = i * (w + gap);
        for y in 0..h {
            out[(y * sw + x0) * 3..(y * sw + x0 + w) * 3]
                .copy_from_slice(&f[y * w * 3..(y + 1) * w * 3]);
        }
    }
    (out, sw, h)
}

/// True when an `ffmpeg` executable is on the PATH.
pub fn have_ffmpeg() -> bool {
    Command::new("ffmpeg")
        .arg("-version")
        .output()
        .map(|o| o.status.success())
        .unwrap_or(false)
}

/// Encodes numbered PNG frames (`pattern` like `frame_%03d.png` in `dir`) to an H.264 MP4,
/// converted with the BT.709 matrix (limited range) it is tagged with.
pub fn encode_mp4(dir: &Path, pattern: &str, fps: u32, out: &Path) -> Result<()> {
    let status = Command::new("ffmpeg")
        .current_dir(dir)
        .args([
            "-y",
            "-loglevel",
            "error",
            "-framerate",
            &fps.to_string(),
            "-i",
            pattern,
        ])
        .args([
            "-vf",
            "pad=ceil(iw/2)*2:ceil(ih/2)*2,scale=out_color_matrix=bt709:out_range=tv",
            "-c:v",
            "libx264",
            "-pix_fmt",
            "yuv420p",
        ])
        .args([
            "-color_primaries",
            "bt709",
            "-color_trc",
            "bt709",
            "-colorspace",
            "bt709",
        ])
        .args(["-movflags", "+faststart"])
        .arg(out)
        .status()
        .map_err(|e| PlayerError::Ffmpeg(format!("running ffmpeg: {e}")))?;
    if !status.success() {
        return Err(PlayerError::Ffmpeg(format!("ffmpeg failed with {status}")));
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

    #[test]
    fn mp4_colours_follow_their_bt709_tag() {
        if !have_ffmpeg() {
            eprintln!("skipped: no ffmpeg");
            return;
        }
        let dir = tempfile::tempdir().unwrap();
        let (w, h) = (33u32, 20u32);
        let rgb = [200u8, 50, 20].repeat((w * h) as usize);
        for i in 0..2 {
            write_png(&dir.path().join(format!("f_{i:03}.png")), w, h, 3, &rgb).unwrap();
        }
        let out = dir.path().join("v.mp4");
        encode_mp4(dir.path(), "f_%03d.png", 10, &out).unwrap();
        let mut src = cpsl_media::open(&out).unwrap();
        assert_eq!(
            (src.info().width, src.info().height),
            (34, 20),
            "padded to even"
        );
        let f = src.next_frame().unwrap().unwrap();
        // Converted with BT.601 but tagged BT.709, this was [214, 63, 16].
        let px = &f.rgb[(10 * 34 + 16) * 3..][..3];
        for (got, want) in px.iter().zip([200u8, 50, 20]) {
            assert!(got.abs_diff(want) <= 3, "{px:?} for [200, 50, 20]");
        }
    }
}
