//! A video's camera path ([`cpsl_track`]) as a library call, and its files: `poses.json`
//! (per frame: camera-to-world pose, PnP inliers, whether it was placed; the camera motion
//! found) and a NeRF-style `transforms.json` (OpenGL camera axes, as instant-ngp, nerfstudio
//! and 3-D Gaussian splatting tools read it); and depth from the video itself
//! ([`VideoTrackedDepth`]).

use crate::error::{Context, PipelineError};
use crate::sources::CameraChoice;
use cpsl_core::{Camera, DepthSource, Progress, ProgressEvent};
use cpsl_media::FrameSource;
use cpsl_track::{DepthFrom, Mat, TrackedDepth, Tracker, Trajectory};

pub use cpsl_track::TrackConfig;
use serde::Serialize;
use std::path::Path;

/// The progress stage of tracking.
pub const TRACKING: &str = "tracking";

/// Tracks every frame of `input` (a video file or a folder of frames) seen by `camera`, with
/// `cfg` ([`TrackConfig::default`] unless a user asks otherwise). Returns the trajectory (at tracking resolution), the camera at the input's size and a name
/// per frame (its file for a folder, `frame_NNNNNN` for a video).
pub fn track_video(
    input: &Path,
    camera: &CameraChoice,
    cfg: TrackConfig,
    max_frames: Option<usize>,
    progress: &dyn Progress,
) -> Result<(Trajectory, Camera, Vec<String>), PipelineError> {
    let (t, cam, names, _) = track_frames(input, camera, cfg, max_frames, progress, None)?;
    if names.len() < 2 {
        return Err(PipelineError::Invalid(format!(
            "{}: {} frame(s); tracking needs at least two",
            input.display(),
            names.len()
        )));
    }
    Ok((t, cam, names))
}

/// [`track_video`] for any number of frames, also returning every frame's working grey image
/// when `keep` allows that many frames (an error names the limit otherwise).
fn track_frames(
    input: &Path,
    camera: &CameraChoice,
    cfg: TrackConfig,
    max_frames: Option<usize>,
    progress: &dyn Progress,
    keep: Option<usize>,
) -> Result<(Trajectory, Camera, Vec<String>, Vec<Mat>), PipelineError> {
    // Tracking needs the pictures alone, not the decoder's motion vectors.
    let mut src = cpsl_media::open_ahead(input, false, 1)
        .context_with(|| format!("opening {}", input.display()))?;
    let info = src.info().clone();
    let cam = camera.camera(info.width, info.height)?;
    let mut tracker = Tracker::new(cam, cfg)?;
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
    let mut greys = Vec::new();
    while max_frames.is_none_or(|m| names.len() < m) {
        let Some(frame) = src
            .next_frame()
            .context_with(|| format!("decoding {}", input.display()))?
        else {
            break;
        };
        let grey = tracker
            .grey(&frame.rgb, info.width, info.height)
            .context_with(|| format!("frame {}", frame.index))?;
        if let Some(most) = keep {
            if greys.len() == most {
                return Err(PipelineError::Invalid(format!(
                    "{}: depth from the video holds at most {most} frames; \
                     layer a part (--max-frames) or use a depth model",
                    input.display()
                )));
            }
            greys.push(grey.clone());
        }
        tracker
            .push_grey(grey)
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
    Ok((tracker.finish()?, cam, names, greys))
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
    /// The segment the pose belongs to: 0, or a later one where tracking broke off (a jump or
    /// a cut).
    pub segment: u32,
    /// The world the pose is in: 0 (the first frame's camera, unit the first baseline), or a
    /// later segment's own (its first frame's camera and its own unit) when it could not be
    /// tied to an earlier one by relocalisation.
    pub world: u32,
    /// Triangulated tracks the pose agrees with.
    pub inliers: usize,
}

/// `poses.json`.
#[derive(Debug, Serialize)]
pub struct PosesFile {
    /// Always `cpsl-poses`.
    pub format: &'static str,
    /// Format version (2: with segments; 3: with worlds).
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

/// The files of a tracked clip: `poses.json` and `transforms.json` (the placed frames of the
/// world with the most of them ([`Trajectory::largest_world`]); each
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
                segment: t.segment[i],
                world: t.world[i],
            }
        })
        .collect();
    let keep = t.largest_world();
    let transforms: Vec<serde_json::Value> = frames
        .iter()
        .filter(|f| f.world == keep)
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
        version: 3,
        camera,
        motion: t.motion.name(),
        points: t.points,
        reprojection_px: t.reprojection_px.is_finite().then_some(t.reprojection_px),
        frames,
    };
    (poses, nerf)
}

/// Depth from the video itself: a first pass tracks the camera through the whole input
/// ([`VideoTrackedDepth::prepare`]), then each frame asked for runs the monocular `prior` and
/// fuses it with multi-view depth ([`TrackedDepth`]); every frame says where its depth came
/// from (in `video.json`).
pub struct VideoTrackedDepth {
    prior: Box<dyn DepthSource>,
    /// How the first pass tracks.
    cfg: TrackConfig,
    /// Once prepared: the tracked clip, or why every frame takes the prior.
    tracked: Option<Result<TrackedDepth, String>>,
    note: String,
}

impl VideoTrackedDepth {
    /// Most frames the first pass holds (their working grey images: about 130 kB each at the
    /// default tracking size, 480x270 for 16:9, so at most about 390 MB).
    pub const MAX_FRAMES: usize = 3000;

    /// Depth from the video with `prior` for what the views cannot see; [`Self::prepare`]
    /// must run before the first frame.
    pub fn new(prior: Box<dyn DepthSource>) -> Self {
        Self {
            prior,
            cfg: TrackConfig::default(),
            tracked: None,
            note: String::new(),
        }
    }

    /// The same, tracking with `cfg` instead of [`TrackConfig::default`].
    pub fn with_config(self, cfg: TrackConfig) -> Self {
        Self { cfg, ..self }
    }

    /// The first pass: tracks every frame of `input` (at most `max_frames`) seen by `camera`.
    pub fn prepare(
        &mut self,
        input: &Path,
        camera: &CameraChoice,
        max_frames: Option<usize>,
        progress: &dyn Progress,
    ) -> Result<(), PipelineError> {
        let keep = Some(Self::MAX_FRAMES);
        let (t, _, _, greys) = track_frames(input, camera, self.cfg, max_frames, progress, keep)?;
        self.tracked = Some(match greys.len() {
            0 | 1 => Err("one frame: nothing to track".into()),
            _ => Ok(TrackedDepth::new(t, greys)?),
        });
        Ok(())
    }

    /// What the last frame's depth came from.
    pub fn note(&self) -> Option<&str> {
        (!self.note.is_empty()).then_some(self.note.as_str())
    }

    /// A short description, saved with the output.
    pub fn name(&self) -> String {
        format!(
            "the video (tracking, multi-view depth fused with {}{})",
            self.prior.name(),
            match &self.tracked {
                Some(Ok(t)) => format!("; {}", t.summary()),
                Some(Err(why)) => format!("; {why}"),
                None => String::new(),
            }
        )
    }

    /// Depth of frame `index` (picture `rgb`, seen by `cam`) without a multi-view pass:
    /// `from_depth`, what [`Self::depth`] gave frame `from`, carried to it by the two frames'
    /// poses, the rest the prior fitted to it ([`TrackedDepth::carry_depth`]). `None` where
    /// the poses cannot carry it (a frame not placed, another world, a camera that does not
    /// translate). `prior` is the prior already run on `rgb`, if it was.
    pub fn carried(
        &mut self,
        from: usize,
        from_depth: &[f32],
        index: usize,
        rgb: &[u8],
        cam: &Camera,
        prior: Option<&[f32]>,
    ) -> Result<Option<Vec<f32>>, PipelineError> {
        let Some(Ok(tracked)) = &self.tracked else {
            return Ok(None);
        };
        if !self.carries() {
            return Ok(None);
        }
        let (w, h) = (cam.width, cam.height);
        let run;
        let prior = match prior {
            Some(p) => p,
            None => {
                run = self.prior.depth(rgb, w, h)?;
                &run
            }
        };
        Ok(tracked.carry_depth(from, from_depth, index, rgb, prior, (w, h))?)
    }

    /// Whether [`Self::carried`] carries depth: the clip was tracked and the camera translates.
    pub fn carries(&self) -> bool {
        matches!(&self.tracked, Some(Ok(t))
            if t.trajectory().motion == cpsl_track::CameraMotion::Translating)
    }

    /// The monocular prior.
    pub fn prior_mut(&mut self) -> &mut dyn DepthSource {
        &mut *self.prior
    }

    /// Depth of frame `index`, whose picture is `rgb` seen by `cam` (the input's size);
    /// `prior` is the prior already run on `rgb`, if it was.
    pub fn depth(
        &mut self,
        index: usize,
        rgb: &[u8],
        cam: &Camera,
        prior: Option<Vec<f32>>,
    ) -> Result<Vec<f32>, PipelineError> {
        let tracked = self.tracked.as_mut().ok_or_else(|| {
            PipelineError::Invalid("depth from the video: the clip was not tracked first".into())
        })?;
        let (w, h) = (cam.width, cam.height);
        let prior = match prior {
            Some(p) => p,
            None => self.prior.depth(rgb, w, h)?,
        };
        let (z, from) = match tracked {
            Ok(t) => t.depth(index, rgb, &prior, (w, h))?,
            Err(why) => (prior, DepthFrom::Fallback(why.clone())),
        };
        let name = self.prior.name();
        self.note = match from {
            DepthFrom::Views {
                share,
                views,
                prior: true,
            } => format!(
                "video: {:.0} % of pixels from {views} views, the rest {name} fitted to them",
                100.0 * share
            ),
            DepthFrom::Views {
                share,
                views,
                prior: false,
            } => format!(
                "video: {:.0} % of pixels from {views} views, the rest filled from them ({name}'s depth order disagrees)",
                100.0 * share
            ),
            DepthFrom::Carried { from, share } => format!(
                "video: the views too seldom confident, {:.0} % of pixels carried from frame {from}'s depth, the rest {name} fitted to them",
                100.0 * share
            ),
            DepthFrom::Fallback(why) => format!("fallback: {why}; {name}"),
        };
        Ok(z)
    }
}
