//! Camera tracking and depth from the video itself ([`cpsl_track`]) scored on the fox: its
//! frames (undistorted, a quarter of full size) are tracked without reading its poses, and
//! the solved poses are compared with its COLMAP poses relative to frame 0's camera (where
//! the solved path starts): rotations directly, translations by direction, so that the
//! monocular scale does not enter.

use crate::datasets::PosedVideo;
use crate::error::EvalError;
use cpsl_core::{Camera, Mat3, Pose, Vec3};
use cpsl_track::{DepthFrom, TrackConfig, TrackedDepth, Tracker, Trajectory};
use serde::Serialize;
use std::collections::HashMap;
use std::path::Path;
use std::time::Instant;

type Result<T> = std::result::Result<T, EvalError>;

/// Tracking scored against reference poses.
#[derive(Debug, Clone, Serialize)]
pub struct TrackScore {
    /// The clip.
    pub clip: String,
    /// Frames.
    pub frames: usize,
    /// Frames placed.
    pub placed: usize,
    /// Segments the placed frames fall in (tracking broke off between them).
    pub segments: usize,
    /// Worlds the segments fall in (those relocalisation tied share one).
    pub worlds: usize,
    /// The camera motion found.
    pub motion: String,
    /// Triangulated points.
    pub points: usize,
    /// Median reprojection error (working pixels).
    pub reprojection_px: f64,
    /// Median rotation error against the reference, degrees, both paths starting at frame 0's
    /// camera.
    pub rotation_deg: f64,
    /// Median rotation error after the rotation that best aligns the two paths (the mean of
    /// the per-frame differences), degrees: frame 0's own error no longer enters every frame.
    pub rotation_aligned_deg: f64,
    /// Median translation-direction error, degrees (frames at least a tenth of the farthest
    /// camera distance from frame 0).
    pub translation_dir_deg: f64,
    /// Milliseconds per frame for tracking and solving.
    pub ms_per_frame: f64,
    /// A reference reconstruction's own camera path scored the same way (when given): how
    /// far two reconstructions of the same frames can disagree.
    #[serde(skip_serializing_if = "Option::is_none")]
    pub reference: Option<PathScore>,
}

/// A camera path's rotation and translation-direction errors against the fox's poses (as
/// [`score`] computes them), degrees.
#[derive(Debug, Clone, Copy, Serialize)]
pub struct PathScore {
    /// Frames the path places.
    pub placed: usize,
    /// Median rotation error, both paths starting at the first placed frame's camera.
    pub rotation_deg: f64,
    /// Median rotation error after the best aligning rotation.
    pub rotation_aligned_deg: f64,
    /// Median translation-direction error.
    pub translation_dir_deg: f64,
}

use cpsl_track::rotation_deg as angle;

/// Scores `est` (camera-to-world; per world, the origin is its first frame's camera) against
/// `truth`'s poses: median rotation error, median rotation error after aligning each
/// segment's rotations with the truth's, and median translation-direction error, degrees,
/// over every placed frame; each world is compared with the truth relative to its first
/// frame.
pub fn score(est: &Trajectory, truth: &PosedVideo) -> (f64, f64, f64) {
    let (mut rot, mut aligned, mut dir) = (Vec::new(), Vec::new(), Vec::new());
    for (world, _) in est.world_sizes() {
        let frames: Vec<usize> = (0..est.poses.len())
            .filter(|&i| est.poses[i].is_some() && est.world[i] == world)
            .collect();
        let Some(&first) = frames.first() else {
            continue;
        };
        let origin = est.poses[first].expect("placed");
        let rel = |i: usize| truth.relative(first, i);
        let far = (first..truth.poses.len())
            .map(|i| rel(i).translation.norm())
            .fold(0.0, f64::max);
        let mut pairs = Vec::new();
        for &i in &frames {
            let p = origin.relative_to(&est.poses[i].expect("placed"));
            let g = rel(i);
            rot.push(angle(&(p.rotation.transpose() * g.rotation)));
            pairs.push((p.rotation, g.rotation));
            if g.translation.norm() >= 0.1 * far && p.translation.norm() > 0.0 {
                let c = p
                    .translation
                    .normalized()
                    .dot(g.translation.normalized())
                    .clamp(-1.0, 1.0);
                dir.push(c.acos().to_degrees());
            }
        }
        // The aligning rotation A (truth = A est): the Karcher mean of G_i E_i^T.
        let mut a = Mat3::IDENTITY;
        for _ in 0..10 {
            let mut step = Vec3::ZERO;
            for (e, g) in &pairs {
                step = step + (a.transpose() * *g * e.transpose()).log();
            }
            a = a * Mat3::exp(step * (1.0 / pairs.len() as f64));
        }
        aligned.extend(
            pairs
                .iter()
                .map(|(e, g)| angle(&((a * *e).transpose() * *g))),
        );
    }
    let med = |mut v: Vec<f64>| {
        if v.is_empty() {
            return f64::NAN;
        }
        median(&mut v)
    };
    (med(rot), med(aligned), med(dir))
}

/// The fox's frames undistorted at `1/scale` of full size, and that camera.
pub fn fox_frames(data: &Path, scale: u32) -> Result<(PosedVideo, Camera, Vec<Vec<u8>>)> {
    let video = crate::datasets::fox(data)?;
    let camera = video.camera.scaled(1.0 / scale as f64);
    let frames =
        crate::video::read_frames(&video.files, camera, scale as usize, Some(&video.lens))?;
    Ok((video, camera, frames))
}

/// Tracks frames seen by `camera`.
pub fn track(frames: &[Vec<u8>], camera: Camera, cfg: TrackConfig) -> Result<Trajectory> {
    let mut t = Tracker::new(camera, cfg)?;
    for f in frames {
        t.push(f, camera.width, camera.height)?;
    }
    Ok(t.finish()?)
}

/// Tracks the fox and scores its poses, and `reference`'s path (by file name) when given:
/// the score, the solved path and the frames' file names.
pub fn fox(
    data: &Path,
    reference: Option<&HashMap<String, Pose>>,
) -> Result<(TrackScore, Trajectory, Vec<String>)> {
    let (video, camera, frames) = fox_frames(data, 4)?;
    let t0 = Instant::now();
    let est = track(&frames, camera, TrackConfig::default())?;
    let ms = t0.elapsed().as_secs_f64() * 1e3 / frames.len() as f64;
    let (rotation_deg, rotation_aligned_deg, translation_dir_deg) = score(&est, &video);
    let mut result = TrackScore {
        clip: "fox".into(),
        frames: frames.len(),
        placed: est.poses.iter().filter(|p| p.is_some()).count(),
        segments: est.segments(),
        worlds: est.worlds(),
        motion: est.motion.name().into(),
        points: est.points,
        reprojection_px: est.reprojection_px,
        rotation_deg,
        rotation_aligned_deg,
        translation_dir_deg,
        ms_per_frame: ms,
        reference: None,
    };
    let names: Vec<String> = video
        .files
        .iter()
        .map(|f| {
            f.file_name()
                .map_or(String::new(), |n| n.to_string_lossy().into_owned())
        })
        .collect();
    result.reference = reference.map(|r| {
        // The reference's path as a trajectory of one world over the same frames.
        let poses: Vec<Option<Pose>> = names.iter().map(|n| r.get(n).copied()).collect();
        let n = poses.len();
        let path = Trajectory {
            camera,
            inliers: vec![0; n],
            motion: est.motion,
            points: 0,
            reprojection_px: f64::NAN,
            initial_pair: None,
            segment: vec![0; n],
            world: vec![0; n],
            poses,
        };
        let (rotation_deg, rotation_aligned_deg, translation_dir_deg) = score(&path, &video);
        PathScore {
            placed: path.poses.iter().flatten().count(),
            rotation_deg,
            rotation_aligned_deg,
            translation_dir_deg,
        }
    });
    Ok((result, est, names))
}

/// Depth of every frame from the video itself ([`TrackedDepth`]): tracked poses, multi-view
/// depth from up to four placed neighbours chosen by ray angle, fused with `prior` (per frame, any scale).
/// Returns the depths, a description and the camera centres in the depth's units.
pub fn video_depth(frames: &[Vec<u8>], camera: Camera, prior: &[Vec<f32>]) -> Result<VideoDepth> {
    let (w, h) = (camera.width, camera.height);
    let mut t = Tracker::new(camera, TrackConfig::default())?;
    let mut greys = Vec::with_capacity(frames.len());
    for f in frames {
        let g = t.grey(f, w, h)?;
        greys.push(g.clone());
        t.push_grey(g)?;
    }
    let mut tracked = TrackedDepth::new(t.finish()?, greys)?;
    let (mut shares, mut alone, mut carried) = (Vec::new(), 0, 0);
    let depths = prior
        .iter()
        .zip(frames)
        .enumerate()
        .map(|(i, (p, rgb))| {
            let (z, from) = tracked.depth(i, rgb, p, (w, h))?;
            match from {
                DepthFrom::Views { share, prior, .. } => {
                    shares.push(share);
                    alone += usize::from(!prior);
                }
                DepthFrom::Carried { .. } => carried += 1,
                DepthFrom::Fallback(_) => {}
            }
            Ok(z)
        })
        .collect::<Result<Vec<_>>>()?;
    shares.sort_by(f64::total_cmp);
    let share = shares.get(shares.len() / 2).copied().unwrap_or(0.0);
    // The camera centres of the largest world, in the depth's units (none for unplaced
    // frames).
    let t = tracked.trajectory();
    let keep = t.largest_world();
    let centres = (0..frames.len())
        .map(|i| {
            (t.world[i] == keep)
                .then(|| tracked.centre_in_depth_units(i))
                .flatten()
        })
        .collect();
    Ok(VideoDepth {
        depth: depths,
        how: format!(
            "video ({}, {} fused, {carried} carried from a neighbour; median {:.0} % of pixels from the views, the rest FastDepth fitted to them or, on {alone} frames where its order disagrees, filled from the views)",
            tracked.summary(),
            shares.len(),
            100.0 * share
        ),
        centres,
        tracked,
    })
}

/// Depth of a clip's frames from the video itself ([`video_depth`]).
pub struct VideoDepth {
    /// Per frame, the depth (the prior's size).
    pub depth: Vec<Vec<f32>>,
    /// Where it came from, in words.
    pub how: String,
    /// Per frame of the trajectory's largest world, its camera centre in the depth's units.
    pub centres: Vec<Option<cpsl_core::Vec3>>,
    /// The tracked clip, which carries a frame's depth to another by their poses.
    pub tracked: TrackedDepth,
}

/// Depth of the fox's frames scored at the 3-D points of an independent reconstruction.
#[derive(Debug, Clone, Serialize)]
pub struct PointDepthScore {
    /// Where the depth came from.
    pub depth: String,
    /// Frames with points in view.
    pub frames: usize,
    /// Points scored (one per frame that sees it).
    pub points: usize,
    /// AbsRel (mean of |z - z_ref| / z_ref) with one scale for the whole clip: the median
    /// ratio over every point.
    pub abs_rel: f64,
    /// Median relative error with that scale.
    pub median_rel: f64,
    /// AbsRel with each frame scaled on its own (the depth's shape alone).
    pub abs_rel_per_frame: f64,
    /// Per frame, its own scale over the clip's (NaN without points): how far the depth's
    /// units drift.
    pub frame_scales: Vec<f64>,
}

/// Camera coordinates `(x/z, y/z, z)` of the points each frame (by file name) sees, as
/// `scripts/fox_sfm_points.py` writes them (`{"frames": {"0004.jpg": [[x, y, z], ...]}}`).
pub type FramePoints = HashMap<String, Vec<[f64; 3]>>;

/// An independent reconstruction of the fox's frames, as `scripts/fox_sfm_points.py` writes
/// it: the points each frame sees and, when the file has them, the reconstruction's own
/// camera path.
#[derive(Debug, Clone, Default)]
pub struct Reconstruction {
    /// The points each frame sees.
    pub points: FramePoints,
    /// Per frame (by file name), its camera-to-world pose (OpenCV axes).
    pub poses: HashMap<String, Pose>,
}

/// Reads a [`Reconstruction`] from a JSON file (`{"frames": {...}, "poses": {"0004.jpg":
/// {"rotation": [[..]; 3], "centre": [x, y, z]}}}`; `poses` may be left out).
pub fn read_reconstruction(path: &Path) -> Result<Reconstruction> {
    #[derive(serde::Deserialize)]
    struct FilePose {
        rotation: [[f64; 3]; 3],
        centre: [f64; 3],
    }
    #[derive(serde::Deserialize)]
    struct File {
        frames: FramePoints,
        #[serde(default)]
        poses: HashMap<String, FilePose>,
    }
    let bad = |what: String| EvalError::Invalid(format!("{}: {what}", path.display()));
    let text = std::fs::read_to_string(path).map_err(|e| bad(e.to_string()))?;
    let f: File = serde_json::from_str(&text).map_err(|e| bad(e.to_string()))?;
    if f.frames
        .values()
        .flatten()
        .any(|p| !(p.iter().all(|v| v.is_finite()) && p[2] > 0.0))
    {
        return Err(bad(
            "a point with a non-finite coordinate or a depth <= 0".into()
        ));
    }
    let mut poses = HashMap::new();
    for (name, p) in f.poses {
        let pose = Pose {
            rotation: Mat3(p.rotation),
            translation: Vec3(p.centre),
        };
        let r = pose.rotation;
        let off = r.transpose() * r;
        let orthonormal = (0..3)
            .all(|i| (0..3).all(|j| (off.0[i][j] - if i == j { 1.0 } else { 0.0 }).abs() < 1e-6));
        if !(pose.is_finite() && orthonormal && r.det() > 0.0) {
            return Err(bad(format!(
                "poses.{name}: not a rotation and a finite centre"
            )));
        }
        poses.insert(name, pose);
    }
    Ok(Reconstruction {
        points: f.frames,
        poses,
    })
}

/// Scores `depth` (one map per frame, `camera`'s size, in any units) at `points`, the
/// frames named by `files`: each point is projected with `camera` and the depth read at the
/// nearest pixel. `None` when no point lands on a known depth.
pub fn depth_at_points(
    name: &str,
    depth: &[Vec<f32>],
    camera: Camera,
    files: &[std::path::PathBuf],
    points: &FramePoints,
) -> Option<PointDepthScore> {
    let (w, h) = (camera.width as usize, camera.height as usize);
    // Per frame, (estimate, reference) pairs.
    let pairs: Vec<Vec<(f64, f64)>> = files
        .iter()
        .zip(depth)
        .map(|(file, z)| {
            let name = file.file_name().and_then(|n| n.to_str()).unwrap_or("");
            points
                .get(name)
                .into_iter()
                .flatten()
                .filter_map(|&[x, y, zr]| {
                    let (u, v) = (camera.fx * x + camera.cx, camera.fy * y + camera.cy);
                    let (u, v) = (u.round(), v.round());
                    if !(u >= 0.0 && v >= 0.0 && (u as usize) < w && (v as usize) < h) {
                        return None;
                    }
                    let e = z[v as usize * w + u as usize] as f64;
                    (e.is_finite() && e > 0.0).then_some((e, zr))
                })
                .collect()
        })
        .collect();
    let ratio = |p: &[(f64, f64)]| {
        let mut r: Vec<f64> = p.iter().map(|(e, zr)| zr / e).collect();
        (!r.is_empty()).then(|| median(&mut r))
    };
    let all: Vec<(f64, f64)> = pairs.iter().flatten().copied().collect();
    let k = ratio(&all)?;
    let rel = |p: &[(f64, f64)], k: f64| -> Vec<f64> {
        p.iter().map(|(e, zr)| (k * e - zr).abs() / zr).collect()
    };
    let mut whole = rel(&all, k);
    let abs_rel = whole.iter().sum::<f64>() / whole.len() as f64;
    let own: Vec<Option<f64>> = pairs.iter().map(|p| ratio(p)).collect();
    let per_frame: Vec<f64> = pairs
        .iter()
        .zip(&own)
        .filter_map(|(p, r)| Some(rel(p, (*r)?)))
        .flatten()
        .collect();
    let frame_scales = own.iter().map(|r| r.map_or(f64::NAN, |r| r / k)).collect();
    Some(PointDepthScore {
        depth: name.to_string(),
        frames: pairs.iter().filter(|p| !p.is_empty()).count(),
        points: all.len(),
        abs_rel,
        median_rel: median(&mut whole),
        abs_rel_per_frame: per_frame.iter().sum::<f64>() / per_frame.len() as f64,
        frame_scales,
    })
}

/// The median of `v` (not empty), sorting it.
fn median(v: &mut [f64]) -> f64 {
    v.sort_by(f64::total_cmp);
    v[v.len() / 2]
}

#[cfg(test)]
mod tests {
    use super::{depth_at_points, read_reconstruction, FramePoints};
    use cpsl_core::Camera;
    use std::path::PathBuf;

    #[test]
    fn depth_is_scored_at_the_points_in_its_own_units() {
        let cam = Camera::from_fov(8, 6, 60.0);
        let files = vec![PathBuf::from("a/0001.jpg"), PathBuf::from("a/0002.jpg")];
        // Frame 1 at depth 2 (its reference 4: the clip's scale 2); frame 2 at depth 1, its
        // reference 4 (a scale of its own, 4), except one pixel at depth 3.
        let mut second = vec![1.0f32; 48];
        let p = |u: f64, v: f64, z: f64| [(u - cam.cx) / cam.fx, (v - cam.cy) / cam.fy, z];
        second[2 * 8 + 3] = 3.0;
        let depth = vec![vec![2.0f32; 48], second];
        let mut points = FramePoints::new();
        points.insert(
            "0001.jpg".into(),
            vec![p(1.0, 1.0, 4.0), p(5.0, 4.0, 4.0), p(20.0, 1.0, 4.0)],
        );
        points.insert(
            "0002.jpg".into(),
            vec![p(0.0, 0.0, 4.0), p(3.0, 2.0, 4.0), p(7.0, 5.0, 4.0)],
        );
        let s = depth_at_points("test", &depth, cam, &files, &points).unwrap();
        // The point off the frame is left out; the clip's scale is the median ratio, 2.
        assert_eq!((s.frames, s.points), (2, 5));
        // With the clip's scale frame 2 is off by half at its three points: |2 - 4| / 4
        // twice and |6 - 4| / 4 once.
        assert!((s.abs_rel - 3.0 * 0.5 / 5.0).abs() < 1e-9, "{}", s.abs_rel);
        // Its own scale (4) fits two of its three points; the third is off by |12 - 4| / 4.
        assert!(
            (s.abs_rel_per_frame - 2.0 / 5.0).abs() < 1e-9,
            "{}",
            s.abs_rel_per_frame
        );
        assert_eq!(s.frame_scales, vec![1.0, 2.0]);
        assert!(depth_at_points("none", &depth, cam, &files, &FramePoints::new()).is_none());
    }

    #[test]
    fn bad_reconstruction_files_are_refused() {
        let dir = tempfile::tempdir().unwrap();
        let path = dir.path().join("points.json");
        let write = |text: &str| std::fs::write(&path, text).unwrap();
        write(r#"{"frames": {"0001.jpg": [[0.1, 0.2, 3.0]]}}"#);
        let r = read_reconstruction(&path).unwrap();
        assert_eq!((r.points["0001.jpg"].len(), r.poses.len()), (1, 0));
        // A quarter turn about y, at (1, 2, 3).
        write(
            r#"{"frames": {}, "poses": {"0001.jpg": {"rotation": [[0, 0, 1], [0, 1, 0], [-1, 0, 0]], "centre": [1, 2, 3]}}}"#,
        );
        let p = read_reconstruction(&path).unwrap().poses["0001.jpg"];
        assert_eq!(p.translation.0, [1.0, 2.0, 3.0]);
        assert_eq!(p.rotation.0[2], [-1.0, 0.0, 0.0]);
        write(r#"{"frames": {"0001.jpg": [[0.1, 0.2, -3.0]]}}"#);
        let e = read_reconstruction(&path).unwrap_err().to_string();
        assert!(e.contains("points.json") && e.contains("depth"), "{e}");
        // A matrix that is not a rotation: scaled, or a mirror.
        for pose in [
            r#"{"rotation": [[2, 0, 0], [0, 1, 0], [0, 0, 1]], "centre": [0, 0, 0]}"#,
            r#"{"rotation": [[-1, 0, 0], [0, 1, 0], [0, 0, 1]], "centre": [0, 0, 0]}"#,
        ] {
            write(&format!(
                r#"{{"frames": {{}}, "poses": {{"0007.jpg": {pose}}}}}"#
            ));
            let e = read_reconstruction(&path).unwrap_err().to_string();
            assert!(e.contains("poses.0007.jpg"), "{e}");
        }
        write("{");
        assert!(read_reconstruction(&path).is_err());
    }
}
