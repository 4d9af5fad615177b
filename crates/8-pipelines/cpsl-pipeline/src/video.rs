//! A video (or an image sequence) to layered frames: the driver loop of temporal layering
//! (frames decoded one at a time, depth on I-frames or every frame, motion from the decoder's
//! vectors or optical flow), and its output folder: one layer set per frame and a typed
//! `video.json`.

use crate::error::{Context, PipelineError};
use crate::sources::{CameraChoice, VideoDepth};
use cpsl_core::{LayerSet, LayeredFrame, Progress, ProgressEvent, RefreshReason};
use cpsl_layering::LayeringConfig;
use cpsl_media::FrameSource;
use cpsl_stereo::StereoLayout;
use cpsl_temporal::{GopConfig, VideoLayerer};
use serde::{Deserialize, Serialize};
use std::path::{Path, PathBuf};
use std::sync::mpsc::sync_channel;
use std::time::Instant;

/// Where P-frame motion comes from.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum MotionSource {
    /// The decoder's motion vectors where the input is 8-bit 4:2:0 H.264 and they cover the
    /// frame (each divided by the distance of its reference, found from the pictures), optical
    /// flow otherwise.
    Auto,
    /// Always optical flow: slower (a 720p P-frame's motion about 40 ms against 5-7), closer to the
    /// pictures than block vectors (EVALUATION.md, "The decoder's motion vectors").
    Flow,
}

/// Where a P-frame's depth comes from.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default)]
pub enum PFrameDepth {
    /// Carried along the motion with the layers (the paper's: depth on I-frames only).
    Motion,
    /// Where the depth source tracks the camera (depth from the video), the last I-frame's
    /// depth carried to the frame by the two cameras' poses, what it does not reach taken
    /// from the monocular prior fitted to it; along the motion otherwise. Tens of
    /// milliseconds and one run of the prior instead of a multi-view pass, and each layer's
    /// slanted plane or mesh then follows the camera.
    #[default]
    Poses,
    /// Estimated on every frame, as on I-frames.
    Estimated,
}

/// How a video is layered.
#[derive(Debug, Clone)]
pub struct VideoJob {
    /// A video file (any container and codec FFmpeg reads) or a folder of frames.
    pub input: PathBuf,
    /// The reference camera.
    pub camera: CameraChoice,
    /// Layering of one frame (its `layers` is K).
    pub layering: LayeringConfig,
    /// Groups of pictures, propagation and refresh.
    pub gop: GopConfig,
    /// Where P-frame motion comes from.
    pub motion: MotionSource,
    /// Where P-frames' depth comes from.
    pub p_depth: PFrameDepth,
    /// Stop after this many frames.
    pub max_frames: Option<usize>,
    /// The frames hold two views (side by side or top and bottom): the left one is layered,
    /// and stereo depth sources see both. Motion then always comes from optical flow (the
    /// decoder's vectors describe the packed frame).
    pub stereo: Option<StereoLayout>,
}

/// One layered frame, as the driver hands it on.
pub struct FrameRecord {
    /// The layered frame.
    pub frame: LayeredFrame,
    /// Whether the decoder's motion vectors were used.
    pub decoder_motion: bool,
    /// Milliseconds for this frame, depth included.
    pub ms: f64,
    /// Where this frame's depth came from, when the source says (stereo and its fallbacks).
    pub depth_note: Option<String>,
    /// The frame's depth was carried from its I-frame's by the camera's poses
    /// ([`PFrameDepth::Poses`]).
    pub depth_carried: bool,
    /// Frames still to come, this one included, when the input says how many it has.
    pub frames_left: Option<usize>,
}

/// How many frames a run will read: the input's count (when it says) capped by `max_frames`.
pub(crate) fn frames_to_read(input: Option<usize>, max_frames: Option<usize>) -> Option<usize> {
    match (input, max_frames) {
        (Some(n), Some(m)) => Some(n.min(m)),
        (n, m) => n.or(m),
    }
}

/// The progress stage of layering a video.
pub const LAYERING: &str = "layering";

/// Refuses an input that is cpsl's own output rather than a video or a folder of frames (a
/// folder of layer PNGs would otherwise be read as frames).
pub(crate) fn refuse_layers(input: &Path) -> Result<(), PipelineError> {
    let what = if is_layered_video(input) {
        "a layered video (video.json): `cpsl encode` codes it as it was layered, `cpsl view` plays it"
    } else if input.join(cpsl_io::MANIFEST_FILE).is_file() {
        "a layer set (manifest.json): `cpsl render` and `cpsl view` show it"
    } else {
        return Ok(());
    };
    Err(PipelineError::Invalid(format!(
        "{} is {what}; layering takes a video file or a folder of frames",
        input.display()
    )))
}

/// Layers every frame of the job's input with `depth`, handing each frame to `sink` as soon as
/// it is layered. Returns what the input is.
pub fn layer_video(
    job: &VideoJob,
    depth: &mut VideoDepth,
    progress: &dyn Progress,
    mut sink: impl FnMut(FrameRecord) -> Result<(), PipelineError>,
) -> Result<cpsl_media::Info, PipelineError> {
    let input = &job.input;
    refuse_layers(input)?;
    // Decoding overlaps the layering of the frame before.
    let mut src = cpsl_media::open_ahead(input, true, 1)
        .context_with(|| format!("opening {}", input.display()))?;
    let mut info = src.info().clone();
    if let Some(layout) = job.stereo {
        (info.width, info.height) = layout
            .view_size(info.width, info.height)
            .context_with(|| format!("{} as stereo", input.display()))?;
    }
    let cam = job.camera.camera(info.width, info.height)?;
    let full = (src.info().width, src.info().height);
    if let VideoDepth::Tracked(t) = depth {
        if job.stereo.is_some() {
            return Err(PipelineError::Invalid(
                "depth from the video takes monocular input; stereo input has its own depth".into(),
            ));
        }
        t.prepare(input, &job.camera, job.max_frames, progress)?;
    }
    let mut cfg = job.layering;
    cfg.cues.allow_missing_depth = true;
    let mut layerer = VideoLayerer::new(cam, cfg, job.gop)?;
    let total = frames_to_read(info.frames, job.max_frames);
    progress.event(ProgressEvent::Start {
        stage: LAYERING,
        total: total.map(|n| n as u64),
    });
    let mut count = 0;
    // The last I-frame's depth, for P-frames that carry it by the camera's poses.
    let mut intra_depth: Option<(usize, Vec<f32>)> = None;
    // What of a frame's depth is worked out while the frame before is layered (which decides
    // whether it is an I-frame).
    let early = match job.p_depth {
        PFrameDepth::Estimated => Some(Early::Depth),
        PFrameDepth::Poses if depth.carries() => Some(Early::Carried),
        _ => None,
    };
    let mut read = |count: usize| -> Result<Option<Picture>, PipelineError> {
        if job.max_frames.is_some_and(|m| count >= m) {
            return Ok(None);
        }
        let Some(frame) = src
            .next_frame()
            .context_with(|| format!("decoding {}", input.display()))?
        else {
            return Ok(None);
        };
        let (rgb, right) = match job.stereo {
            Some(layout) => {
                let (l, r, ..) = cpsl_stereo::split(&frame.rgb, full.0, full.1, layout)
                    .context_with(|| format!("frame {}", frame.index))?;
                (l, Some(r))
            }
            None => (frame.rgb, None),
        };
        Ok(Some(Picture {
            index: frame.index,
            rgb,
            right,
            motion: frame.motion,
        }))
    };
    // A failure to read the next frame is reported once the frame before is handed on.
    let mut next = read(count);
    let mut ahead: Option<Result<Ahead, PipelineError>> = None;
    while let Some(frame) = next? {
        let t = Instant::now();
        layerer.set_frames_left(total.map(|n| n.saturating_sub(count)));
        let intra = layerer.next_is_intra();
        let (z, depth_note) = match ahead.take().transpose()? {
            Some(Ahead::Depth(z, note)) => (Some(z), note),
            Some(Ahead::Carried { carried, .. }) if !intra => (carried, None),
            model @ (Some(Ahead::Carried { .. }) | None)
                if intra || job.p_depth == PFrameDepth::Estimated =>
            {
                let model = model.and_then(Ahead::into_model);
                let z = depth
                    .depth(frame.index, &frame.rgb, frame.right.as_deref(), &cam, model)
                    .context_with(|| format!("depth of frame {}", frame.index))?;
                (Some(z), depth.note().map(String::from))
            }
            // Carried depth has no note of its own: a P-frame belongs to its I-frame's run
            // of depth notes ([`depth_runs`]); `video.json` says `carried`.
            _ => (
                carry(depth, &intra_depth, job.p_depth, &frame, &cam, None)
                    .context_with(|| format!("depth of frame {}", frame.index))?,
                None,
            ),
        };
        if intra && job.p_depth == PFrameDepth::Poses {
            intra_depth = z.clone().map(|z| (frame.index, z));
        }
        let depth_carried = !intra && job.p_depth == PFrameDepth::Poses && z.is_some();
        let given = match job.motion {
            MotionSource::Auto if job.stereo.is_none() => frame.motion,
            _ => None,
        };
        let decoder_motion = given.is_some() && !intra;
        next = read(count + 1);
        // The next frame's depth (or what of it does not wait for the layering) beside this
        // frame's layering.
        let (out, early_work) = std::thread::scope(|s| {
            let work = match (&next, early) {
                (Ok(Some(f)), Some(kind)) => {
                    let (depth, intra_depth, cam) = (&mut *depth, &intra_depth, &cam);
                    Some(s.spawn(move || {
                        ahead_of(kind, depth, intra_depth, job.p_depth, f, cam)
                            .context_with(|| format!("depth of frame {}", f.index))
                    }))
                }
                _ => None,
            };
            let out = layerer.push_with_motion(&frame.rgb, z.as_deref(), given);
            let work = work.map(|w| w.join().unwrap_or_else(|p| std::panic::resume_unwind(p)));
            (out, work)
        });
        ahead = early_work;
        let out = out.context_with(|| format!("frame {}", frame.index))?;
        sink(FrameRecord {
            frame: out,
            decoder_motion,
            ms: t.elapsed().as_secs_f64() * 1e3,
            depth_note,
            depth_carried,
            frames_left: total.map(|n| n.saturating_sub(count)),
        })?;
        count += 1;
        progress.event(ProgressEvent::Advance {
            stage: LAYERING,
            done: count as u64,
        });
    }
    progress.event(ProgressEvent::Finish { stage: LAYERING });
    if count == 0 {
        return Err(PipelineError::Invalid(format!(
            "{}: no frames",
            input.display()
        )));
    }
    info.damaged = src.info().damaged;
    Ok(info)
}

/// A decoded frame: the (left) view that is layered, the right view of stereo input, the
/// decoder's motion.
struct Picture {
    index: usize,
    rgb: Vec<u8>,
    right: Option<Vec<u8>>,
    motion: Option<cpsl_core::Flow>,
}

/// Which of a frame's depth [`ahead_of`] works out.
#[derive(Clone, Copy)]
enum Early {
    /// All of it: every frame's depth is estimated.
    Depth,
    /// The model's, and the last I-frame's depth carried by the poses (what a P-frame takes).
    Carried,
}

/// A frame's depth worked out while the frame before it was layered.
enum Ahead {
    /// Its depth and where it came from.
    Depth(Vec<f32>, Option<String>),
    /// The source's model run on it, and the carried depth a P-frame takes.
    Carried {
        model: Option<Vec<f32>>,
        carried: Option<Vec<f32>>,
    },
}

impl Ahead {
    /// The model's depth, for a frame that turned out to be an I-frame.
    fn into_model(self) -> Option<Vec<f32>> {
        match self {
            Ahead::Carried { model, .. } => model,
            Ahead::Depth(..) => None,
        }
    }
}

/// Works out frame `f`'s depth, or the part of it that does not wait for whether it is an
/// I-frame.
fn ahead_of(
    kind: Early,
    depth: &mut VideoDepth,
    intra_depth: &Option<(usize, Vec<f32>)>,
    p_depth: PFrameDepth,
    f: &Picture,
    cam: &cpsl_core::Camera,
) -> Result<Ahead, PipelineError> {
    Ok(match kind {
        Early::Depth => {
            let z = depth.depth(f.index, &f.rgb, f.right.as_deref(), cam, None)?;
            Ahead::Depth(z, depth.note().map(String::from))
        }
        Early::Carried => {
            let model = depth.model_depth(&f.rgb, cam).transpose()?;
            let carried = carry(depth, intra_depth, p_depth, f, cam, model.as_deref())?;
            Ahead::Carried { model, carried }
        }
    })
}

/// A P-frame's depth: the last I-frame's carried by the camera's poses where the job and the
/// source do that (`model`: the source's model already run on the frame), else `None` (the
/// layering carries depth along the motion).
fn carry(
    depth: &mut VideoDepth,
    intra_depth: &Option<(usize, Vec<f32>)>,
    p_depth: PFrameDepth,
    f: &Picture,
    cam: &cpsl_core::Camera,
    model: Option<&[f32]>,
) -> Result<Option<Vec<f32>>, PipelineError> {
    match (intra_depth, p_depth) {
        (Some((from, z)), PFrameDepth::Poses) => {
            depth.carried(*from, z, f.index, &f.rgb, cam, model)
        }
        _ => Ok(None),
    }
}

fn is_zero(n: &usize) -> bool {
    *n == 0
}

pub use cpsl_io::video::{VIDEO_FILE, VIDEO_FORMAT, VIDEO_VERSION};

/// `video.json`: what was layered, how, and every frame.
#[derive(Debug, Clone, Serialize, Deserialize)]
pub struct VideoManifest {
    /// Always [`VIDEO_FORMAT`].
    pub format: String,
    /// Format version (1).
    pub version: u32,
    /// The input, as given.
    pub input: String,
    /// The input's codec (`images` for a folder).
    pub codec: String,
    /// Frames per second.
    pub fps: f64,
    /// Width of the layered view (half a side-by-side frame).
    pub width: u32,
    /// Height of the layered view.
    pub height: u32,
    /// `sbs` or `tab` for stereo input.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub stereo: Option<String>,
    /// Clockwise rotation applied to make the pictures upright, in degrees.
    pub rotation: u32,
    /// The HDR transfer mapped to SDR, if any.
    pub hdr: Option<String>,
    /// The depth source.
    pub depth: String,
    /// Damaged packets of the input that were skipped (their frames are missing).
    #[serde(default, skip_serializing_if = "is_zero")]
    pub damaged_packets: usize,
    /// Groups of pictures.
    pub gop: GopConfig,
    /// Layering of one frame.
    pub layering: LayeringConfig,
    /// Every frame.
    pub frames: Vec<VideoFrameEntry>,
}

/// One frame of `video.json`.
#[derive(Debug, Clone, Serialize, Deserialize)]
pub struct VideoFrameEntry {
    /// Frame index.
    pub index: u32,
    /// Its layer-set folder.
    pub dir: String,
    /// `I` or `P`.
    pub kind: String,
    /// Why an I-frame is one.
    pub refresh: Option<RefreshReason>,
    /// Each layer's track.
    pub tracks: Vec<Option<u32>>,
    /// Temporal confidence per layer.
    pub confidence: Vec<f32>,
    /// Crack rate above the last I-frame's.
    pub crack: f32,
    /// `estimated`, `carried` (from the I-frame's by the camera's poses) or `propagated`
    /// (along the motion).
    pub depth: String,
    /// Where an estimated depth came from, when the source says: stereo with its share of
    /// matched pixels, or the fallback taken and why.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub depth_note: Option<String>,
    /// `none` (I-frames), `decoder` or `flow`.
    pub motion: String,
    /// Milliseconds for the frame.
    pub ms: f64,
    /// Milliseconds per stage.
    pub timings_ms: Vec<StageTime>,
}

/// Time spent in one stage.
#[derive(Debug, Clone, Serialize, Deserialize)]
pub struct StageTime {
    /// Stage name.
    pub stage: String,
    /// Milliseconds.
    pub ms: f64,
}

impl VideoFrameEntry {
    fn new(r: &FrameRecord, dir: String) -> Self {
        let f = &r.frame;
        Self {
            index: f.index,
            dir,
            kind: if f.refresh.is_some() { "I" } else { "P" }.into(),
            refresh: f.refresh,
            tracks: f.set.layers().iter().map(|l| l.meta.track).collect(),
            confidence: f.confidence.clone(),
            crack: f.crack,
            depth: match (f.depth_propagated, r.depth_carried) {
                (true, _) => "propagated",
                (false, true) => "carried",
                (false, false) => "estimated",
            }
            .into(),
            depth_note: r.depth_note.clone(),
            motion: match (f.refresh.is_some(), r.decoder_motion) {
                (true, _) => "none",
                (false, true) => "decoder",
                (false, false) => "flow",
            }
            .into(),
            ms: r.ms,
            timings_ms: f
                .timings
                .iter()
                .map(|(s, t)| StageTime {
                    stage: s.to_string(),
                    ms: *t,
                })
                .collect(),
        }
    }
}

pub use cpsl_package::DepthRun;

/// The frames' depth notes (`(frame, note)` in frame order) as runs of equal notes: a frame
/// without a note (its depth carried along the motion) joins the run before it. Empty where
/// no frame has a note (the depth model on every frame).
pub fn depth_runs<'a>(frames: impl IntoIterator<Item = (u32, Option<&'a str>)>) -> Vec<DepthRun> {
    let mut runs: Vec<DepthRun> = Vec::new();
    for (frame, note) in frames {
        match (runs.last_mut(), note) {
            (Some(r), Some(n)) if r.note == n => r.last = frame,
            (_, Some(n)) => runs.push(DepthRun {
                first: frame,
                last: frame,
                note: n.to_string(),
            }),
            (Some(r), None) => r.last = frame,
            (None, None) => {}
        }
    }
    runs
}

/// Reads the `video.json` of the layered video in `dir`: format and version checked first,
/// then what a player needs of it ([`cpsl_io::video::VideoIndex::new`]: a frame rate, at least
/// one frame, each frame's folder a plain name inside `dir`).
pub fn read_manifest(dir: &Path) -> Result<VideoManifest, PipelineError> {
    let bytes = cpsl_io::video::read_video_file(dir)?;
    let m: VideoManifest =
        serde_json::from_slice(&bytes).map_err(|source| PipelineError::Json {
            path: dir.join(VIDEO_FILE),
            source,
        })?;
    let frames = m.frames.iter().map(|f| f.dir.clone()).collect();
    cpsl_io::video::VideoIndex::new(dir, m.fps, frames)?;
    Ok(m)
}

/// Whether a folder is the output of [`write_layered_video`] (and so may be replaced).
pub fn is_layered_video(dir: &Path) -> bool {
    dir.join(VIDEO_FILE).is_file()
}

/// Layers the job's video into `output`: one layer set per frame (`frame_NNNNNN/`) and
/// `video.json`, written beside it and moved into place when complete. An existing output of
/// this function is replaced; any other folder is refused.
pub fn write_layered_video(
    job: &VideoJob,
    depth: &mut VideoDepth,
    output: &Path,
    progress: &dyn Progress,
) -> Result<VideoManifest, PipelineError> {
    if output.exists() && !is_layered_video(output) {
        return Err(PipelineError::Invalid(format!(
            "{} exists and is not the output of cpsl layer-video; not replacing it",
            output.display()
        )));
    }
    // On an error the staged folder is removed when `staged` is dropped.
    let staged = cpsl_io::Staged::folder(output, is_layered_video)?;
    let mut frames = Vec::new();
    // Each frame's layer set is written on a thread of its own while the next is layered.
    let (to_writer, written) = sync_channel::<(String, LayerSet, Vec<u8>)>(1);
    let info = std::thread::scope(|s| {
        let writer = s.spawn(|| -> Result<(), PipelineError> {
            for (dir, set, edc) in written {
                let files = [(cpsl_io::EDC_FILE, edc.as_slice())];
                cpsl_io::write_layer_set(&staged.path().join(&dir), &set, &files)?;
            }
            Ok(())
        });
        let layered = layer_video(job, depth, progress, |r| {
            let dir = format!("frame_{:06}", r.frame.index);
            frames.push(VideoFrameEntry::new(&r, dir.clone()));
            let edc = r.frame.edc.encode();
            // A failed send means the writer stopped on an error, which it returns below.
            to_writer
                .send((dir, r.frame.set, edc))
                .map_err(|_| PipelineError::Invalid("writing the layer sets stopped".into()))
        });
        drop(to_writer);
        match writer.join() {
            Err(panic) => std::panic::resume_unwind(panic),
            Ok(Err(e)) => Err(e),
            Ok(Ok(())) => layered,
        }
    })?;
    let manifest = VideoManifest {
        format: VIDEO_FORMAT.into(),
        version: VIDEO_VERSION,
        input: job.input.display().to_string(),
        codec: info.codec,
        fps: info.fps,
        width: info.width,
        height: info.height,
        stereo: job.stereo.map(|l| l.name().to_string()),
        rotation: info.rotation,
        hdr: info.hdr.map(String::from),
        damaged_packets: info.damaged,
        depth: depth.name(),
        gop: job.gop,
        layering: job.layering,
        frames,
    };
    let json = serde_json::to_vec_pretty(&manifest).expect("video.json serialises");
    staged.write_file(VIDEO_FILE, &json)?;
    staged.commit(is_layered_video)?;
    Ok(manifest)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn depth_runs_group_equal_notes_and_carry_propagated_frames() {
        let fused = Some("video: fused with fastdepth");
        let turns = Some("fallback: the camera only turns; fastdepth");
        let notes = [
            (0, fused),
            (1, None),
            (2, fused),
            (3, turns),
            (4, None),
            (5, None),
            (6, fused),
        ];
        let runs = depth_runs(notes);
        let spans: Vec<(u32, u32, bool)> = runs
            .iter()
            .map(|r| (r.first, r.last, r.is_fallback()))
            .collect();
        assert_eq!(spans, [(0, 2, false), (3, 5, true), (6, 6, false)]);
        assert!(depth_runs([(0, None), (1, None)]).is_empty());
    }
}
