//! Decoding real files written by the `ffmpeg` command line tool, and image sequences.

use cpsl_media::{open, FrameSource, MediaError};
use std::path::Path;
use std::process::Command;

/// Writes `frames` frames of FFmpeg's moving test pattern with the given encoder arguments.
fn encode(dir: &Path, name: &str, frames: usize, args: &[&str]) -> std::path::PathBuf {
    let out = dir.join(name);
    let status = Command::new("ffmpeg")
        .args([
            "-v",
            "error",
            "-y",
            "-f",
            "lavfi",
            "-i",
            "testsrc2=size=160x120:rate=10",
        ])
        .args(["-frames:v", &frames.to_string()])
        .args(args)
        .arg(&out)
        .status()
        .expect("the ffmpeg tool (apt install ffmpeg; .ci/run installs it)");
    assert!(status.success());
    out
}

fn drain(src: &mut dyn FrameSource) -> Result<Vec<cpsl_media::Frame>, MediaError> {
    let mut v = Vec::new();
    while let Some(f) = src.next_frame()? {
        v.push(f);
    }
    Ok(v)
}

#[test]
fn decodes_h264_with_motion_vectors_and_vp9() {
    let dir = tempfile::tempdir().unwrap();
    let h264 = encode(
        dir.path(),
        "clip.mp4",
        12,
        &[
            "-c:v", "libx264", "-bf", "0", "-refs", "1", "-pix_fmt", "yuv420p",
        ],
    );
    let mut src = open(&h264).unwrap();
    assert_eq!((src.info().width, src.info().height), (160, 120));
    assert!((src.info().fps - 10.0).abs() < 1e-6);
    let frames = drain(src.as_mut()).unwrap();
    assert_eq!(frames.len(), 12);
    assert!(frames.iter().all(|f| f.rgb.len() == 160 * 120 * 3));
    assert!(frames[0].motion.is_none(), "the first frame is intra");
    let with = frames.iter().filter(|f| f.motion.is_some()).count();
    assert!(with >= 8, "{with} P-frames carry motion vectors");
    // The pattern scrolls: some vectors are not zero.
    let m = frames.iter().find_map(|f| f.motion.as_ref()).unwrap();
    assert!(m.data.iter().any(|&v| v.abs() >= 1.0));

    let vp9 = encode(
        dir.path(),
        "clip.webm",
        5,
        &["-c:v", "libvpx-vp9", "-deadline", "realtime"],
    );
    let mut src = open(&vp9).unwrap();
    let frames = drain(src.as_mut()).unwrap();
    assert_eq!(frames.len(), 5);
    assert!(frames.iter().all(|f| f.motion.is_none()));
}

#[test]
fn bad_files_give_clear_errors() {
    let dir = tempfile::tempdir().unwrap();
    assert!(matches!(
        open(&dir.path().join("missing.mp4")),
        Err(MediaError::Unreadable { .. })
    ));
    let junk = dir.path().join("junk.mp4");
    std::fs::write(&junk, b"this is not a video").unwrap();
    assert!(matches!(open(&junk), Err(MediaError::Unreadable { .. })));
    // Audio only: no video stream.
    let audio = dir.path().join("tone.wav");
    let status = Command::new("ffmpeg")
        .args([
            "-v",
            "error",
            "-y",
            "-f",
            "lavfi",
            "-i",
            "sine=duration=0.2",
        ])
        .arg(&audio)
        .status()
        .unwrap();
    assert!(status.success());
    assert!(matches!(open(&audio), Err(MediaError::NoVideo(_))));
    // Truncated: whatever decodes comes out, then a clean end or a clear error; no panic.
    let clip = encode(
        dir.path(),
        "whole.mkv",
        20,
        &["-c:v", "libx264", "-pix_fmt", "yuv420p"],
    );
    let bytes = std::fs::read(&clip).unwrap();
    let cut = dir.path().join("cut.mkv");
    std::fs::write(&cut, &bytes[..bytes.len() / 2]).unwrap();
    match open(&cut) {
        Ok(mut src) => match drain(src.as_mut()) {
            Ok(frames) => assert!(
                frames.len() < 20,
                "{} frames from half a file",
                frames.len()
            ),
            Err(e) => assert!(matches!(e, MediaError::Decode { .. }), "{e}"),
        },
        Err(e) => assert!(matches!(e, MediaError::Unreadable { .. }), "{e}"),
    }
}

#[test]
fn image_sequences_in_name_order_with_size_checks() {
    let dir = tempfile::tempdir().unwrap();
    assert!(matches!(open(dir.path()), Err(MediaError::Empty(_))));
    let png = |name: &str, w: u32, h: u32, v: u8| {
        let data = vec![v; (w * h * 3) as usize];
        cpsl_io::images::write_png(&dir.path().join(name), w, h, 3, &data).unwrap();
    };
    png("b_002.png", 8, 6, 20);
    png("a_001.png", 8, 6, 10);
    std::fs::write(dir.path().join("notes.txt"), "ignored").unwrap();
    let mut src = open(dir.path()).unwrap();
    assert_eq!(src.info().frames, Some(2));
    let frames = drain(src.as_mut()).unwrap();
    assert_eq!(frames[0].rgb[0], 10);
    assert_eq!(frames[1].rgb[0], 20);
    png("c_003.png", 4, 4, 30);
    let mut src = open(dir.path()).unwrap();
    assert!(matches!(
        drain(src.as_mut()),
        Err(MediaError::FrameSize { .. })
    ));
}
