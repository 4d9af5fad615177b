//! A video's camera path ([`cpsl_track`]) as a library call, and its files: `poses.json`
//! (per frame: camera-to-world pose, PnP inliers, whether it was placed; the camera motion
//! found) and a NeRF-style `transforms.json` (OpenGL camera axes, as instant-ngp, nerfstudio
//! and 3-D Gaussian splatting tools read it).

use crate::error::{Context, PipelineError};
use crate::sources::CameraChoice;
use cpsl_core::{Camera, Progress, ProgressEvent};
use cpsl_track::{TrackConfig, Tracker, Trajectory};
use serde::Serialize;
use std::path::Path;

/// The progress stage of tracking.
pub const TRACKING: &str = "tracking";

/// Tracks every frame of `input` (a video file or a folder of frames) seen by `camera`.
/// Returns the trajectory (at tracking resolution), the camera at the input's size and a name
/// per frame (its file for a folder, `frame_NNNNNN` for a video).
pub fn track_video(
    input: &Path,
    camera: &CameraChoice,
    max_frames: Option<usize>,
    progress: &dyn Progress,
) -> Result<(Trajectory, Camera, Vec<String>), PipelineError> {
    let mut src =
        cpsl_media::open(input).context_with(|| format!("opening {}", input.display()))?;
    let info = src.info().clone();
    let cam = camera.camera(info.width, info.height)?;
    let mut tracker = Tracker::new(cam, TrackConfig::default())?;
    let total = crate::video::frames_to_read(info.frames, max_frames);
    progress.event(ProgressEvent::Start {
        stage: TRACKING,
        total: total.map(|n| n as u64),
    });
    let files = match input.is_dir() {
        true => Some(cpsl_media::ImageSequence::open(input)?.files().to_vec()),
        false => None,
    };
    let mut names = Vec::new();
    while max_frames.is_none_or(|m| names.len() < m) {
        let Some(frame) = src
            .next_frame()
            .context_with(|| format!("decoding {}", input.display()))?
        else {
            break;
        };
        tracker
            .push(&frame.rgb, info.width, info.height)
            .context_with(|| format!("frame {}", frame.index))?;
        names.push(match &files {
            Some(f) => f[frame.index]
                .file_name()
                .map_or_else(String::new, |n| n.to_string_lossy().into_owned()),
            None => format!("frame_{:06}", frame.index),
        });
        progress.event(ProgressEvent::Advance {
            stage: TRACKING,
            done: names.len() as u64,
        });
    }
    progress.event(ProgressEvent::Finish { stage: TRACKING });
    if names.len() < 2 {
        return Err(PipelineError::Invalid(format!(
            "{}: {} frame(s); tracking needs at least two",
            input.display(),
            names.len()
        )));
    }
    Ok((tracker.finish()?, cam, names))
}

/// One frame of `poses.json`.
#[derive(Debug, Serialize)]
pub struct PoseEntry {
    /// The frame (file name, or `frame_NNNNNN` for a video).
    pub frame: String,
    /// Whether the frame was placed.
    pub placed: bool,
    /// Camera-to-world rotation (OpenCV axes: x right, y down, z forward), rows.
    pub rotation: Option<[[f64; 3]; 3]>,
    /// Camera position in the world (the first frame's camera; unit: the first baseline).
    pub translation: Option<[f64; 3]>,
    /// Triangulated tracks the pose agrees with.
    pub inliers: usize,
}

/// `poses.json`.
#[derive(Debug, Serialize)]
pub struct PosesFile {
    /// Always `cpsl-poses`.
    pub format: &'static str,
    /// Format version (1).
    pub version: u32,
    /// The camera at the input's size.
    pub camera: Camera,
    /// `translating`, `rotating`, `static` or `untracked`.
    pub motion: &'static str,
    /// Triangulated points.
    pub points: usize,
    /// Median reprojection error in tracking pixels.
    pub reprojection_px: Option<f64>,
    /// Every frame.
    pub frames: Vec<PoseEntry>,
}

/// The files of a tracked clip: `poses.json` and `transforms.json` (placed frames only; each
/// `file_path` is the frame's file in `dir`, absolute where it can be resolved, when the
/// input was a folder of frames).
pub fn pose_files(
    t: &Trajectory,
    camera: Camera,
    names: &[String],
    dir: Option<&Path>,
) -> (PosesFile, serde_json::Value) {
    let dir = dir.map(|d| d.canonicalize().unwrap_or_else(|_| d.to_path_buf()));
    let frames: Vec<PoseEntry> = names
        .iter()
        .enumerate()
        .map(|(i, n)| {
            let p = t.poses[i];
            PoseEntry {
                frame: n.clone(),
                placed: p.is_some(),
                rotation: p.map(|p| p.rotation.0),
                translation: p.map(|p| [p.translation.x(), p.translation.y(), p.translation.z()]),
                inliers: t.inliers[i],
            }
        })
        .collect();
    let transforms: Vec<serde_json::Value> = frames
        .iter()
        .filter_map(|f| {
            let (r, t) = (f.rotation?, f.translation?);
            // OpenCV camera axes to OpenGL's (y up, looking down -z): negate columns 1, 2.
            let row = |i: usize| [r[i][0], -r[i][1], -r[i][2], t[i]];
            let file = match &dir {
                Some(d) => d.join(&f.frame).display().to_string(),
                None => f.frame.clone(),
            };
            Some(serde_json::json!({
                "file_path": file,
                "transform_matrix": [row(0), row(1), row(2), [0.0, 0.0, 0.0, 1.0]],
            }))
        })
        .collect();
    let nerf = serde_json::json!({
        "camera_angle_x": 2.0 * (camera.width as f64 / (2.0 * camera.fx)).atan(),
        "fl_x": camera.fx,
        "fl_y": camera.fy,
        "cx": camera.cx + 0.5,
        "cy": camera.cy + 0.5,
        "w": camera.width,
        "h": camera.height,
        "frames": transforms,
    });
    let poses = PosesFile {
        format: "cpsl-poses",
        version: 1,
        camera,
        motion: t.motion.name(),
        points: t.points,
        reprojection_px: t.reprojection_px.is_finite().then_some(t.reprojection_px),
        frames,
    };
    (poses, nerf)
}
