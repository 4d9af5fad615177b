//! The index of a layered video folder (`video.json`, written by `cpsl layer-video`): the part
//! that a reader needs to play it, the frame rate and each frame's layer-set folder. The whole
//! file, with every frame's timings and depth notes, is `cpsl_pipeline::video::VideoManifest`.

use crate::error::IoError;
use serde::Deserialize;
use std::path::Path;

/// The index file inside a layered video folder.
pub const VIDEO_FILE: &str = "video.json";
/// The format name of [`VIDEO_FILE`].
pub const VIDEO_FORMAT: &str = "cpsl-video-layers";
/// The newest version of [`VIDEO_FILE`] this build reads.
pub const VIDEO_VERSION: u32 = 1;

/// What a player needs of a layered video's index.
#[derive(Debug, Clone, PartialEq)]
pub struct VideoIndex {
    /// Frames per second.
    pub fps: f64,
    /// Each frame's layer-set folder, in display order (plain names inside the video's folder).
    pub frames: Vec<String>,
}

/// Reads the index of the layered video in `dir` with its size (at most the default
/// [`cpsl_core::Limits`]' file size), format and version checked, for a reader that parses the
/// rest (this build reads version 1).
pub fn read_video_file(dir: &Path) -> Result<Vec<u8>, IoError> {
    let path = dir.join(VIDEO_FILE);
    let bytes = crate::layerset::read_limited(&path, &cpsl_core::Limits::default())?;
    let cause = match cpsl_core::check_head(&bytes, VIDEO_FORMAT, VIDEO_VERSION) {
        Ok(()) => return Ok(bytes),
        Err(cpsl_core::HeadError::Json(m)) => format!("invalid JSON: {m}"),
        Err(cpsl_core::HeadError::Format(f)) => {
            format!("field `format`: expected \"{VIDEO_FORMAT}\", found \"{f}\"")
        }
        Err(cpsl_core::HeadError::Version(v)) => {
            format!("field `version`: this build reads versions 1..={VIDEO_VERSION}, found {v}")
        }
    };
    Err(IoError::Video { path, cause })
}

impl VideoIndex {
    /// The index of the layered video in `dir` with frame rate `fps` and the frames' folders
    /// `frames`, checked: a frame rate above zero, at least one frame, and plain folder names.
    /// The error names `dir`'s index file and the field.
    pub fn new(dir: &Path, fps: f64, frames: Vec<String>) -> Result<Self, IoError> {
        let bad = |cause: String| IoError::Video {
            path: dir.join(VIDEO_FILE),
            cause,
        };
        if !(fps.is_finite() && fps > 0.0) {
            return Err(bad(format!("field `fps`: {fps} is not a frame rate")));
        }
        if frames.is_empty() {
            return Err(bad("field `frames`: no frames".into()));
        }
        for (i, f) in frames.iter().enumerate() {
            if let Some(reason) = cpsl_core::manifest::unsafe_file_name(f) {
                return Err(bad(format!(
                    "field `frames[{i}].dir`: {reason}, found \"{f}\""
                )));
            }
        }
        Ok(Self { fps, frames })
    }
}

/// Reads and checks the index of the layered video in `dir`: format and version, then
/// [`VideoIndex::new`]'s checks.
pub fn read_video_index(dir: &Path) -> Result<VideoIndex, IoError> {
    #[derive(Deserialize)]
    struct Frame {
        dir: String,
    }
    #[derive(Deserialize)]
    struct Index {
        fps: f64,
        frames: Vec<Frame>,
    }
    let bytes = read_video_file(dir)?;
    let index: Index = serde_json::from_slice(&bytes).map_err(|e| IoError::Video {
        path: dir.join(VIDEO_FILE),
        cause: format!("invalid JSON: {e}"),
    })?;
    let frames = index.frames.into_iter().map(|f| f.dir).collect();
    VideoIndex::new(dir, index.fps, frames)
}

#[cfg(test)]
mod tests {
    use super::*;

    fn index(dir: &Path, body: &str) -> Result<VideoIndex, IoError> {
        std::fs::write(dir.join(VIDEO_FILE), body).unwrap();
        read_video_index(dir)
    }

    #[test]
    fn reads_the_frames_and_names_what_is_wrong() {
        let d = tempfile::tempdir().unwrap();
        let head = r#""format": "cpsl-video-layers", "version": 1"#;
        let ok = index(
            d.path(),
            &format!(r#"{{{head}, "fps": 30, "width": 8, "frames": [{{"dir": "frame_000000", "kind": "I"}}]}}"#),
        )
        .unwrap();
        assert_eq!(ok.frames, ["frame_000000"]);
        for (body, fragment) in [
            (
                format!(r#"{{{head}, "fps": 0, "frames": [{{"dir": "a"}}]}}"#),
                "fps",
            ),
            (
                format!(r#"{{{head}, "fps": 30, "frames": []}}"#),
                "no frames",
            ),
            (
                format!(r#"{{{head}, "fps": 30, "frames": [{{"dir": "../a"}}]}}"#),
                "frames[0].dir",
            ),
            (
                r#"{"format": "cpsl-video-layers", "version": 2}"#.to_string(),
                "found 2",
            ),
            (
                r#"{"format": "cpsl-layerset", "version": 1}"#.to_string(),
                "expected",
            ),
            ("not json".to_string(), "invalid JSON"),
        ] {
            let e = index(d.path(), &body).unwrap_err().to_string();
            assert!(e.contains(fragment) && e.contains("video.json"), "{e}");
        }
        std::fs::remove_file(d.path().join(VIDEO_FILE)).unwrap();
        assert!(read_video_index(d.path()).is_err());
    }
}
