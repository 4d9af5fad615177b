//! Camera tracking and depth from the video itself ([`cpsl_track`]) scored on the fox: its
//! frames (undistorted, a quarter of full size) are tracked without reading its poses, and
//! the solved poses are compared with its COLMAP poses relative to frame 0's camera (where
//! the solved path starts): rotations directly, translations by direction, so that the
//! monocular scale does not enter.

use crate::datasets::PosedVideo;
use crate::error::EvalError;
use cpsl_core::{Camera, Mat3, Vec3};
use cpsl_track::{DepthFrom, TrackConfig, TrackedDepth, Tracker, Trajectory};
use serde::Serialize;
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
}

use cpsl_track::rotation_deg as angle;

/// Scores `est` (camera-to-world; per segment, the world is its first frame's camera) against
/// `truth`'s poses: median rotation error, median rotation error after aligning each
/// segment's rotations with the truth's, and median translation-direction error, degrees,
/// over every placed frame; each segment is compared with the truth relative to its first
/// frame.
pub fn score(est: &Trajectory, truth: &PosedVideo) -> (f64, f64, f64) {
    let (mut rot, mut aligned, mut dir) = (Vec::new(), Vec::new(), Vec::new());
    for (seg, _) in est.segment_sizes() {
        let frames: Vec<usize> = (0..est.poses.len())
            .filter(|&i| est.poses[i].is_some() && est.segment[i] == seg)
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
        v.sort_by(f64::total_cmp);
        v[v.len() / 2]
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

/// Tracks the fox and scores its poses.
pub fn fox(data: &Path) -> Result<TrackScore> {
    let (video, camera, frames) = fox_frames(data, 4)?;
    let t0 = Instant::now();
    let est = track(&frames, camera, TrackConfig::default())?;
    let ms = t0.elapsed().as_secs_f64() * 1e3 / frames.len() as f64;
    let (rotation_deg, rotation_aligned_deg, translation_dir_deg) = score(&est, &video);
    Ok(TrackScore {
        clip: "fox".into(),
        frames: frames.len(),
        placed: est.poses.iter().filter(|p| p.is_some()).count(),
        segments: est.segments(),
        motion: est.motion.name().into(),
        points: est.points,
        reprojection_px: est.reprojection_px,
        rotation_deg,
        rotation_aligned_deg,
        translation_dir_deg,
        ms_per_frame: ms,
    })
}

/// Depth of every frame from the video itself ([`TrackedDepth`]): tracked poses, multi-view
/// depth from up to four nearest placed frames, fused with `prior` (per frame, any scale).
/// Returns the depths and a description.
pub fn video_depth(
    frames: &[Vec<u8>],
    camera: Camera,
    prior: &[Vec<f32>],
) -> Result<(Vec<Vec<f32>>, String)> {
    let (w, h) = (camera.width, camera.height);
    let mut t = Tracker::new(camera, TrackConfig::default())?;
    let mut greys = Vec::with_capacity(frames.len());
    for f in frames {
        let g = t.grey(f, w, h)?;
        greys.push(g.clone());
        t.push_grey(g)?;
    }
    let mut tracked = TrackedDepth::new(t.finish()?, greys)?;
    let (mut shares, mut alone) = (Vec::new(), 0);
    let depths = prior
        .iter()
        .zip(frames)
        .enumerate()
        .map(|(i, (p, rgb))| {
            let (z, from) = tracked.depth(i, rgb, p, (w, h))?;
            if let DepthFrom::Views { share, prior, .. } = from {
                shares.push(share);
                alone += usize::from(!prior);
            }
            Ok(z)
        })
        .collect::<Result<Vec<_>>>()?;
    shares.sort_by(f64::total_cmp);
    let share = shares.get(shares.len() / 2).copied().unwrap_or(0.0);
    Ok((
        depths,
        format!(
            "video ({}, {} fused; median {:.0} % of pixels from the views, the rest FastDepth fitted to them or, on {alone} frames where its order disagrees, filled from the views)",
            tracked.summary(),
            shares.len(),
            100.0 * share
        ),
    ))
}
