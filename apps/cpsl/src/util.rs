//! Small helpers shared by the commands.

use anyhow::{Context, Result};
use cpsl_core::{Limits, PremulImage};
use cpsl_io::images::write_png;
use std::path::Path;
use std::process::Command;

/// Parses `R,G,B` (0-255 each).
pub fn parse_rgb(s: &str) -> Result<[u8; 3], String> {
    let v: Vec<u8> = s
        .split(',')
        .map(|p| p.trim().parse::<u8>())
        .collect::<Result<_, _>>()
        .map_err(|e| format!("colour '{s}': {e}; expected R,G,B with values 0-255"))?;
    <[u8; 3]>::try_from(v)
        .map_err(|v| format!("colour '{s}': expected 3 values, found {}", v.len()))
}

/// Reads a layer set folder with default limits.
pub fn load_layer_set(dir: &Path) -> Result<cpsl_core::LayerSet> {
    cpsl_io::read_layer_set(dir, &Limits::default())
        .with_context(|| format!("reading layer set {}", dir.display()))
}

/// How a rendered (premultiplied) image is written to PNG.
#[derive(Debug, Clone, Copy)]
pub enum Output {
    /// Composited over an opaque colour, RGB.
    Over([u8; 3]),
    /// Straight-alpha RGBA, uncovered pixels transparent.
    Alpha,
}

/// Writes a render to PNG.
pub fn write_render(path: &Path, img: &PremulImage, how: Output) -> Result<()> {
    let (w, h) = (img.width(), img.height());
    match how {
        Output::Over(bg) => write_png(path, w, h, 3, &img.over_background(bg)),
        Output::Alpha => write_png(path, w, h, 4, &img.to_straight()),
    }
    .with_context(|| format!("writing {}", path.display()))
}

/// Writes pretty JSON atomically.
pub fn write_json(path: &Path, value: &impl serde::Serialize) -> Result<()> {
    Ok(cpsl_eval::report::write_json(path, value)?)
}

pub use cpsl_core::resample::downscale_rgb;

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
        .context("running ffmpeg")?;
    anyhow::ensure!(status.success(), "ffmpeg failed with {status}");
    Ok(())
}

#[cfg(test)]
mod tests {
    use super::*;

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
