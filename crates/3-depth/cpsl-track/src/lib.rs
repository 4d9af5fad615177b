//! Camera tracking and multi-view depth for monocular video, on OpenCV.
//!
//! **Tracking** ([`Tracker`]): corners (`goodFeaturesToTrack`) followed frame to frame by
//! pyramidal Lucas-Kanade with a forward-backward check, topped up where tracks die. At the
//! end ([`Tracker::finish`]) the poses are solved:
//!
//! 1. *Initialisation with model selection.* From the first frame, the first later frame whose
//!    tracks moved enough is tried: an essential matrix and a homography are both fitted
//!    (RANSAC, 1 px); when the homography explains nearly as many tracks, the motion is a
//!    rotation (or the camera is static: tracks barely move) and no depth can be triangulated;
//!    otherwise the essential matrix gives the relative pose (unit baseline) and the common
//!    tracks are triangulated.
//! 2. *Registration.* Every other frame is placed by PnP (RANSAC) on the triangulated tracks
//!    it sees, nearest frames first; each placed frame triangulates the tracks it shares with
//!    the placed frame that sees them under the widest angle (at least `min_angle_deg`).
//!    Where many tracks are born in a placed frame (after a break or a large loss), those that
//!    continue a track lost there up to 12 frames before (its point projects
//!    within a few pixels, their ORB descriptors where one died and the other was born
//!    agree) join it, and the frame is solved again: the frames after a break stay tied to
//!    the points before it.
//! 3. *Refinement.* One round of alternating resection and intersection (every frame
//!    re-solved by PnP, every point re-triangulated from all placed frames), then bundle
//!    adjustment (`ba.rs`: Levenberg-Marquardt with analytic Jacobians, the points eliminated
//!    by the Schur complement, Cauchy loss): poses and points together, the observations
//!    farther than a pixel from their adjusted point dropped, and again. Clips with more
//!    placed frames than [`TrackConfig::ba_window`] are adjusted in overlapping windows, each
//!    held to the frames before it.
//! 4. *Segments.* A frame into which fewer than a fifth of the live tracks survive ends them
//!    all (a cut or a jump); descriptor matches may bridge it when most of them agree with
//!    one relative pose. Where no bridge holds, the frames after the last placed one are
//!    solved again from step 1 as a new segment with its own origin and scale
//!    ([`Trajectory::segment`]).
//! 5. *Relocalisation* (`reloc.rs`). Every frame keeps its ORB features. A later segment
//!    whose features, triangulated with its posed frames, match an earlier segment's points
//!    under one similarity is moved into that segment's world, scale included
//!    ([`Trajectory::world`]); frames still unplaced are placed by PnP on the points of
//!    their nearest placed frames.
//!
//! Poses are camera-to-world ([`cpsl_core::Pose`]: `X_world = R X_cam + t`), the world being
//! the first frame's camera, and the first baseline has length 1 (monocular scale).
//!
//! **Multi-view depth** ([`mvs`]): dense optical flow (DIS) from a frame to posed neighbours,
//! forward-backward checked and triangulated per pixel; [`TrackedDepth`] fuses it with a
//! monocular prior for every frame of a tracked clip.

mod ba;
mod fused;
pub mod hamming;
pub mod mvs;
mod reloc;

pub use fused::{DepthFrom, TrackedDepth};

/// OpenCV's image type, as [`work_grey`] and [`mvs`] take it.
pub use opencv::core::Mat;

use cpsl_core::{Camera, Mat3, Pose, Vec3};
use hamming::Descriptor;
use opencv::core::{self, Point2f, Scalar, Size, TermCriteria, Vector};
use opencv::prelude::*;
use opencv::{calib3d, imgproc, video};
use std::collections::{HashMap, HashSet};
use thiserror::Error;

/// Why tracking failed.
#[derive(Debug, Error)]
pub enum TrackError {
    /// The frames do not fit the camera or each other.
    #[error("{0}")]
    Input(String),
    /// OpenCV failed.
    #[error("OpenCV: {0}")]
    OpenCv(#[from] opencv::Error),
}

type Result<T> = std::result::Result<T, TrackError>;

/// Tracking settings.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct TrackConfig {
    /// Longest side the frames are tracked at (they are downscaled to it). 480 by default:
    /// a 720p clip of 50 frames tracked in 2.0 s instead of 3.5 s at 640 (on the day it was
    /// measured; BENCHMARKS.md has today's figures); the fox at 540x960 then tracks less well
    /// (rotation error 0.69 against 0.40 degrees) and its coded novel views score 0.1 dB lower
    /// (EVALUATION.md). `--track-side` on the command line.
    pub work_side: u32,
    /// Most corners tracked at once.
    pub max_features: usize,
    /// Least distance between corners (working pixels).
    pub min_distance: f64,
    /// Largest forward-backward disagreement of a tracked corner (working pixels).
    pub max_fb_error: f32,
    /// Least angle between the two rays of a triangulated point, in degrees.
    pub min_angle_deg: f64,
    /// Least median track motion (share of the working image's long side) for the first
    /// baseline.
    pub init_motion: f64,
    /// Placed frames per bundle-adjustment window (consecutive windows overlap by a third);
    /// 0 leaves the poses of alternating resection and intersection as they are.
    pub ba_window: usize,
}

impl Default for TrackConfig {
    fn default() -> Self {
        Self {
            work_side: 480,
            max_features: 1500,
            min_distance: 8.0,
            max_fb_error: 1.0,
            min_angle_deg: 1.0,
            init_motion: 0.04,
            ba_window: 120,
        }
    }
}

/// How the camera moves over a clip.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum CameraMotion {
    /// It translates: poses and depth come from the video.
    Translating,
    /// Tracks move, but a homography explains them (a rotation about the centre, or a
    /// planar scene): no baseline to triangulate.
    Rotating,
    /// Tracks barely move.
    Static,
    /// Too few tracks to tell (textureless, black or too short).
    Untracked,
}

impl CameraMotion {
    /// The name reports use.
    pub fn name(self) -> &'static str {
        match self {
            Self::Translating => "translating",
            Self::Rotating => "rotating",
            Self::Static => "static",
            Self::Untracked => "untracked",
        }
    }
}

/// The solved camera path of a clip.
#[derive(Debug, Clone)]
pub struct Trajectory {
    /// The camera at working resolution.
    pub camera: Camera,
    /// Per frame, its camera-to-world pose when it could be placed.
    pub poses: Vec<Option<Pose>>,
    /// Per frame, the triangulated tracks its pose agrees with (PnP inliers).
    pub inliers: Vec<usize>,
    /// How the camera moves.
    pub motion: CameraMotion,
    /// Triangulated points.
    pub points: usize,
    /// Median reprojection error of the points over their observations (working pixels).
    pub reprojection_px: f64,
    /// The two frames of the first baseline.
    pub initial_pair: Option<(usize, usize)>,
    /// Per frame, the segment its pose belongs to: 0 for the first; a later one starts where
    /// tracking broke off (a jump or a cut), with its own origin and scale, so poses of
    /// different segments are not comparable unless tied into one world
    /// ([`Trajectory::world`]). 0 for unplaced frames.
    pub segment: Vec<u32>,
    /// Per frame, the world its pose is in: the first segment's number among the segments
    /// tied together by relocalisation (descriptor matches between their 3-D points; see
    /// `reloc.rs`), whose poses share one origin and scale. A segment that could not be tied
    /// keeps a world of its own (its number). 0 for unplaced frames.
    pub world: Vec<u32>,
}

impl Trajectory {
    /// The segments with placed frames (see [`Trajectory::segment`]), in order, each with
    /// its number of placed frames.
    pub fn segment_sizes(&self) -> Vec<(u32, usize)> {
        self.sizes(&self.segment)
    }

    /// How many segments have placed frames.
    pub fn segments(&self) -> usize {
        self.segment_sizes().len()
    }

    /// The worlds with placed frames (see [`Trajectory::world`]), in order, each with its
    /// number of placed frames.
    pub fn world_sizes(&self) -> Vec<(u32, usize)> {
        self.sizes(&self.world)
    }

    /// How many worlds have placed frames: 1 when every segment was tied to the first.
    pub fn worlds(&self) -> usize {
        self.world_sizes().len()
    }

    /// The world with the most placed frames (the first of equals; 0 when none is placed).
    pub fn largest_world(&self) -> u32 {
        self.world_sizes()
            .into_iter()
            .max_by_key(|&(w, n)| (n, std::cmp::Reverse(w)))
            .map_or(0, |(w, _)| w)
    }

    fn sizes(&self, ids: &[u32]) -> Vec<(u32, usize)> {
        let mut sizes = std::collections::BTreeMap::new();
        for (p, &s) in self.poses.iter().zip(ids) {
            if p.is_some() {
                *sizes.entry(s).or_insert(0) += 1;
            }
        }
        sizes.into_iter().collect()
    }
}

/// One observation of a track: frame and working-pixel position.
pub(crate) type Obs = (u32, f32, f32);

/// Where a track was born and where it died (the frame and its ORB descriptor there, when
/// ORB could describe it).
type Ends = [Option<(u32, Descriptor)>; 2];

/// Follows corners through a clip; see the [crate docs](crate).
pub struct Tracker {
    cfg: TrackConfig,
    camera: Camera,
    size: (u32, u32),
    /// The last frame and its image pyramid (with derivatives) for Lucas-Kanade.
    prev: Option<(Mat, Vector<Mat>)>,
    live: Vec<(usize, Point2f)>,
    tracks: Vec<Vec<Obs>>,
    frames: u32,
    /// Per frame, its ORB features, for relocalisation (`reloc.rs`).
    features: Vec<reloc::Features>,
    /// Per track, its ends.
    ends: Vec<Ends>,
}

impl Tracker {
    /// A tracker for frames of `camera`'s size.
    pub fn new(camera: Camera, cfg: TrackConfig) -> Result<Self> {
        let long = camera.width.max(camera.height);
        if long == 0 || cfg.work_side < 32 {
            return Err(TrackError::Input(format!(
                "cannot track {}x{} frames at a working side of {}",
                camera.width, camera.height, cfg.work_side
            )));
        }
        let scale = (cfg.work_side as f64 / long as f64).min(1.0);
        let size = (
            ((camera.width as f64 * scale).round() as u32).max(1),
            ((camera.height as f64 * scale).round() as u32).max(1),
        );
        let work = Camera {
            width: size.0,
            height: size.1,
            fx: camera.fx * size.0 as f64 / camera.width as f64,
            fy: camera.fy * size.1 as f64 / camera.height as f64,
            cx: (camera.cx + 0.5) * size.0 as f64 / camera.width as f64 - 0.5,
            cy: (camera.cy + 0.5) * size.1 as f64 / camera.height as f64 - 0.5,
        };
        Ok(Self {
            cfg,
            camera: work,
            size,
            prev: None,
            live: Vec::new(),
            tracks: Vec::new(),
            frames: 0,
            features: Vec::new(),
            ends: Vec::new(),
        })
    }

    /// The camera at working resolution.
    pub fn camera(&self) -> Camera {
        self.camera
    }

    /// Working grey image of an RGB frame of the tracker's size.
    pub fn grey(&self, rgb: &[u8], width: u32, height: u32) -> Result<Mat> {
        work_grey(rgb, width, height, self.size)
    }

    /// Tracks into the next frame (RGB, 3 bytes per pixel, of the camera's size).
    pub fn push(&mut self, rgb: &[u8], width: u32, height: u32) -> Result<()> {
        let grey = self.grey(rgb, width, height)?;
        self.push_grey(grey)
    }

    /// Tracks into the next frame, given as its working grey image ([`Tracker::grey`]).
    pub fn push_grey(&mut self, grey: Mat) -> Result<()> {
        let size = grey.size()?;
        if (size.width as u32, size.height as u32) != self.size {
            return Err(TrackError::Input(format!(
                "a {}x{} grey frame for tracking at {}x{}",
                size.width, size.height, self.size.0, self.size.1
            )));
        }
        let f = self.frames;
        let (was_live, known) = (self.live.clone(), self.tracks.len());
        let pyramid = lk_pyramid(&grey)?;
        let features = reloc::features(&grey, reloc::KEPT_FEATURES)?;
        if let Some((prev, prev_pyramid)) = &self.prev {
            if !self.live.is_empty() {
                let p0: Vector<Point2f> = self.live.iter().map(|l| l.1).collect();
                let p1 = lk(prev_pyramid, &pyramid, &p0)?;
                let back = lk(&pyramid, prev_pyramid, &p1.0)?;
                let (w, h) = (self.size.0 as f32, self.size.1 as f32);
                let mut kept = Vec::with_capacity(self.live.len());
                for (i, &(id, a)) in self.live.iter().enumerate() {
                    let (b, c) = (p1.0.get(i)?, back.0.get(i)?);
                    let fb = ((c.x - a.x).powi(2) + (c.y - a.y).powi(2)).sqrt();
                    let inside = b.x >= 0.0 && b.y >= 0.0 && b.x < w - 1.0 && b.y < h - 1.0;
                    if p1.1[i] && back.1[i] && fb < self.cfg.max_fb_error && inside {
                        self.tracks[id].push((f, b.x, b.y));
                        kept.push((id, b));
                    }
                }
                // Most tracks lost at once is a cut or a jump: the few that seem to carry
                // across are more likely chance matches than the same points.
                if kept.len() * CUT_SURVIVAL < self.live.len() {
                    kept.clear();
                }
                self.live = kept;
            }
            if self.live.len() < MIN_LIVE {
                // A break (a jump or a gap in the frames): seed tracks across it from
                // descriptor matches.
                let seeds = matches(
                    &reloc::features(prev, SEED_FEATURES)?,
                    &reloc::features(&grey, SEED_FEATURES)?,
                )?;
                for (a, b) in seeds {
                    let near = self
                        .live
                        .iter()
                        .any(|&(_, p)| (p.x - b.x).hypot(p.y - b.y) < self.cfg.min_distance as f32);
                    if !near {
                        self.tracks.push(vec![(f - 1, a.x, a.y), (f, b.x, b.y)]);
                        self.live.push((self.tracks.len() - 1, b));
                    }
                }
            }
        }
        if self.live.len() < self.cfg.max_features * 7 / 10 {
            self.detect(&grey, f)?;
        }
        self.describe_ends(&grey, &was_live, known)?;
        self.prev = Some((grey, pyramid));
        self.features.push(features);
        self.frames += 1;
        Ok(())
    }

    /// Records the ends of the tracks born into frame `f` (`grey`; those from `known` on)
    /// and of those of `was_live` that died in it, with their descriptors where they were
    /// last or first seen (frame `f` or the one before).
    fn describe_ends(
        &mut self,
        grey: &Mat,
        was_live: &[(usize, Point2f)],
        known: usize,
    ) -> Result<()> {
        let f = self.frames;
        self.ends.resize(self.tracks.len(), [None, None]);
        let alive: HashSet<usize> = self.live.iter().map(|l| l.0).collect();
        // (track, end, observation) per frame: this one and the one before.
        let mut todo: [Vec<(usize, usize, Obs)>; 2] = [Vec::new(), Vec::new()];
        for id in known..self.tracks.len() {
            let o = self.tracks[id][0];
            todo[usize::from(o.0 == f)].push((id, 0, o));
        }
        for &(id, _) in was_live.iter().filter(|l| !alive.contains(&l.0)) {
            let o = *self.tracks[id]
                .last()
                .expect("a live track has an observation");
            todo[usize::from(o.0 == f)].push((id, 1, o));
        }
        for (list, image) in todo
            .iter()
            .zip([self.prev.as_ref().map(|p| &p.0), Some(grey)])
        {
            let Some(image) = image.filter(|_| !list.is_empty()) else {
                continue;
            };
            let points: Vec<Point2f> = list.iter().map(|t| Point2f::new(t.2 .1, t.2 .2)).collect();
            for (&(id, end, o), d) in list.iter().zip(reloc::descriptors_at(image, &points)?) {
                self.ends[id][end] = d.map(|d| (o.0, d));
            }
        }
        Ok(())
    }

    /// The tracks' ends in the frames from `start` on, counted from it.
    fn ends(&self, start: usize) -> Vec<Ends> {
        let mut ends = self.ends.clone();
        // A push that failed after adding tracks left them without ends.
        ends.resize(self.tracks.len(), [None, None]);
        for e in ends.iter_mut().flatten() {
            *e = e.and_then(|(g, d)| Some((g.checked_sub(start as u32)?, d)));
        }
        ends
    }

    fn detect(&mut self, grey: &Mat, f: u32) -> Result<()> {
        let mut mask = Mat::new_rows_cols_with_default(
            self.size.1 as i32,
            self.size.0 as i32,
            core::CV_8U,
            Scalar::all(255.0),
        )?;
        for &(_, p) in &self.live {
            imgproc::circle(
                &mut mask,
                core::Point::new(p.x as i32, p.y as i32),
                self.cfg.min_distance as i32,
                Scalar::all(0.0),
                -1,
                imgproc::LINE_8,
                0,
            )?;
        }
        let mut corners: Vector<Point2f> = Vector::new();
        let want = (self.cfg.max_features - self.live.len()) as i32;
        imgproc::good_features_to_track(
            grey,
            &mut corners,
            want,
            0.01,
            self.cfg.min_distance,
            &mask,
            3,
            false,
            0.04,
        )?;
        for p in corners.iter() {
            self.tracks.push(vec![(f, p.x, p.y)]);
            self.live.push((self.tracks.len() - 1, p));
        }
        Ok(())
    }

    /// Frames pushed so far.
    pub fn frames(&self) -> usize {
        self.frames as usize
    }

    /// Solves the poses of every frame pushed; see the [crate docs](crate).
    ///
    /// Where tracking breaks off after a placed frame (a jump of the camera or a cut: no
    /// tracks with points carry across), the frames after it are solved again as a new
    /// segment, with its own origin and scale ([`Trajectory::segment`]).
    pub fn finish(self) -> Result<Trajectory> {
        let n = self.frames as usize;
        let mut whole =
            Solver::new(self.camera, self.cfg, n, self.tracks.clone(), self.ends(0)).solve()?;
        let mut errors = whole.1;
        let mut start = match whole.0.poses.iter().rposition(|p| p.is_some()) {
            Some(last) => last + 1,
            None => n,
        };
        let mut segment = 0;
        let mut skipped = 0;
        while n - start >= MIN_SEGMENT {
            // The tracks from `start` on, their frames counted from it.
            let tracks: Vec<Vec<Obs>> = self
                .tracks
                .iter()
                .map(|t| {
                    t.iter()
                        .filter(|o| o.0 as usize >= start)
                        .map(|&(f, x, y)| (f - start as u32, x, y))
                        .collect()
                })
                .collect();
            let (part, e) =
                Solver::new(self.camera, self.cfg, n - start, tracks, self.ends(start)).solve()?;
            let Some(last) = part.poses.iter().rposition(|p| p.is_some()) else {
                // Nothing placed from this frame on (it may be blank, as at a fade): try from
                // the next, a few times.
                skipped += 1;
                if skipped > MAX_SKIPS {
                    break;
                }
                start += 1;
                continue;
            };
            skipped = 0;
            segment += 1;
            let t = &mut whole.0;
            for (i, p) in part.poses.iter().enumerate() {
                if p.is_some() {
                    t.poses[start + i] = *p;
                    t.inliers[start + i] = part.inliers[i];
                    t.segment[start + i] = segment;
                    t.world[start + i] = segment;
                }
            }
            t.points += part.points;
            errors.extend(e);
            start += last + 1;
        }
        whole.0.reprojection_px = median(&mut errors);
        let mut t = whole.0;
        if t.motion == CameraMotion::Translating {
            reloc::tie_segments(&mut t, &self.features, self.cfg.min_angle_deg)?;
            reloc::place_frames(&mut t, &self.features, self.cfg.min_angle_deg, MAX_TURN_DEG)?;
        }
        Ok(t)
    }
}

/// Working grey image: RGB to grey, area-downscaled to `size`.
pub fn work_grey(rgb: &[u8], width: u32, height: u32, size: (u32, u32)) -> Result<Mat> {
    let m = rgb_mat(rgb, width, height)?;
    let mut g = Mat::default();
    imgproc::cvt_color(&m, &mut g, imgproc::COLOR_RGB2GRAY, 0)?;
    shrink(g, size)
}

/// Working colour image: RGB area-downscaled to `size` (8-bit, three channels).
pub fn work_rgb(rgb: &[u8], width: u32, height: u32, size: (u32, u32)) -> Result<Mat> {
    shrink(rgb_mat(rgb, width, height)?, size)
}

fn rgb_mat(rgb: &[u8], width: u32, height: u32) -> Result<Mat> {
    let n = width as usize * height as usize * 3;
    if rgb.len() != n || width == 0 || height == 0 {
        return Err(TrackError::Input(format!(
            "a {width}x{height} RGB frame has {n} bytes, found {}",
            rgb.len()
        )));
    }
    Ok(
        Mat::new_rows_cols_with_bytes::<core::Vec3b>(height as i32, width as i32, rgb)?
            .try_clone()?,
    )
}

/// `m` area-resized to `size` (itself when it has that size).
fn shrink(m: Mat, size: (u32, u32)) -> Result<Mat> {
    let s = m.size()?;
    if (s.width as u32, s.height as u32) == size {
        return Ok(m);
    }
    let mut out = Mat::default();
    imgproc::resize(
        &m,
        &mut out,
        Size::new(size.0 as i32, size.1 as i32),
        0.0,
        0.0,
        imgproc::INTER_AREA,
    )?;
    Ok(out)
}

/// Fewest PnP inliers that keep a frame's pose when it is solved again.
const MIN_PNP: usize = 15;

/// Fewest PnP inliers that place a frame the first time. Fewer let wrong solutions in: on the
/// fox, 15 placed frame 43 on 22 of 50 points about 180 degrees off, and the frames placed
/// from it with it; 25 to 35 let others in; 40 to 80 none.
const MIN_PNP_NEW: usize = 50;

/// Least frames after a break in the tracking for a new segment to be tried.
const MIN_SEGMENT: usize = 3;

/// Frames skipped in a row, after a break, when no segment starts at them.
const MAX_SKIPS: usize = 4;

/// Largest turn between neighbouring frames, degrees.
const MAX_TURN_DEG: f64 = 30.0;

/// Angle of a rotation matrix in degrees.
pub fn rotation_deg(r: &Mat3) -> f64 {
    let tr = r.0[0][0] + r.0[1][1] + r.0[2][2];
    ((tr - 1.0) / 2.0).clamp(-1.0, 1.0).acos().to_degrees()
}

/// Rounds of alternating resection and intersection before the bundle adjustment. (On the
/// fox one round leaves 0.19 degrees of rotation error after it, two 0.20, five 0.22.)
const REFINE_ROUNDS: usize = 1;

/// Most Levenberg-Marquardt steps of the first bundle adjustment (the second, after the
/// cull, takes half).
const BA_ITERATIONS: usize = 30;

/// Observations farther than this from their adjusted point are dropped before the second
/// adjustment (working pixels; on the fox 2 px left 0.26 degrees, 1 px 0.22, 0.7 px 0.24).
const CULL_PX: f64 = 1.0;

/// Most frames between a track's loss and its rebirth that [`Solver::merge`] joins over.
const MERGE_GAP: usize = 12;
/// Least tracks born into a frame for [`Solver::merge`] to join them to dead ones (after a
/// break or a large loss; joining in every frame scored worse on the fox, EVALUATION.md).
const MERGE_BORN: usize = 100;
/// Farthest a born track lies from a dead track's projected point to join it (working
/// pixels).
const MERGE_RADIUS_PX: f64 = 4.0;
/// Most bits the descriptors of two joined tracks differ in.
const MERGE_BITS: u32 = 64;

/// Fewer tracks than this surviving into a frame is a break.
const MIN_LIVE: usize = 150;

/// Least tracks that agree with a bridge's relative pose.
const BRIDGE_MIN: usize = 30;

/// A frame into which fewer than one in this many live tracks survive ends them all (a cut or
/// a jump; descriptor matches may then bridge it).
const CUT_SURVIVAL: usize = 5;

/// ORB features per frame that seed tracks across a break.
const SEED_FEATURES: i32 = 3000;

/// Cross-checked ORB matches from `a` to `b` that agree with a fundamental matrix (RANSAC,
/// 1.5 px).
fn matches(a: &reloc::Features, b: &reloc::Features) -> Result<Vec<(Point2f, Point2f)>> {
    if a.points.len() < 8 || b.points.len() < 8 {
        return Ok(Vec::new());
    }
    let (mut pa, mut pb): (Vector<Point2f>, Vector<Point2f>) = (Vector::new(), Vector::new());
    for (i, j, _) in hamming::mutual(&a.desc, &b.desc)
        .into_iter()
        .filter(|m| m.2 <= 64)
    {
        pa.push(a.points[i]);
        pb.push(b.points[j]);
    }
    if pa.len() < 15 {
        return Ok(Vec::new());
    }
    let mut mask = Mat::default();
    let fm =
        calib3d::find_fundamental_mat(&pa, &pb, calib3d::FM_RANSAC, 1.5, 0.999, 2000, &mut mask)?;
    if fm.empty() {
        return Ok(Vec::new());
    }
    let keep = mask.data_typed::<u8>()?;
    (0..pa.len())
        .filter(|&i| keep[i] != 0)
        .map(|i| Ok((pa.get(i)?, pb.get(i)?)))
        .collect()
}

/// Pyramidal Lucas-Kanade from `a` to `b`: new positions and which were found.
/// Lucas-Kanade's window.
const LK_WINDOW: i32 = 15;
/// Lucas-Kanade's pyramid levels above the image.
const LK_LEVELS: i32 = 3;

/// The image pyramid of `grey` for [`lk`], built once per frame (each frame is tracked into
/// and back from, and tracked from into the next: four builds otherwise).
fn lk_pyramid(grey: &Mat) -> Result<Vector<Mat>> {
    let mut pyramid = Vector::new();
    video::build_optical_flow_pyramid(
        grey,
        &mut pyramid,
        Size::new(LK_WINDOW, LK_WINDOW),
        LK_LEVELS,
        true,
        core::BORDER_REFLECT_101,
        core::BORDER_CONSTANT,
        true,
    )?;
    Ok(pyramid)
}

fn lk(
    a: &Vector<Mat>,
    b: &Vector<Mat>,
    p: &Vector<Point2f>,
) -> Result<(Vector<Point2f>, Vec<bool>)> {
    let mut next: Vector<Point2f> = Vector::new();
    let mut status: Vector<u8> = Vector::new();
    let mut err: Vector<f32> = Vector::new();
    video::calc_optical_flow_pyr_lk(
        a,
        b,
        p,
        &mut next,
        &mut status,
        &mut err,
        Size::new(LK_WINDOW, LK_WINDOW),
        LK_LEVELS,
        TermCriteria::new(core::TermCriteria_COUNT + core::TermCriteria_EPS, 30, 0.01)?,
        0,
        1e-4,
    )?;
    Ok((next, status.iter().map(|s| s != 0).collect()))
}

/// How far world point `x` projects, through `cam` at camera-to-world `pose`, from the
/// observation `(u, v)` (working pixels); `None` behind the camera.
fn reprojection_px(cam: &Camera, pose: &Pose, x: Vec3, (u, v): (f32, f32)) -> Option<f64> {
    let (pu, pv) = cam.project(pose.inverse().view_to_ref(x))?;
    Some((pu - u as f64).hypot(pv - v as f64))
}

/// The point nearest to the rays of `obs` (camera-to-world pose and working-pixel position
/// each; midpoint least squares), when it is seen by two of them under at least
/// `min_angle_deg` and reprojects within 2 px in every view.
pub(crate) fn triangulate(
    cam: &Camera,
    min_angle_deg: f64,
    obs: &[(Pose, Point2f)],
) -> Option<Vec3> {
    let ray = |p: &Pose, q: Point2f| {
        let d = Vec3::new(
            (q.x as f64 - cam.cx) / cam.fx,
            (q.y as f64 - cam.cy) / cam.fy,
            1.0,
        );
        (p.translation, (p.rotation * d).normalized())
    };
    let rays: Vec<(Vec3, Vec3)> = obs.iter().map(|(p, q)| ray(p, *q)).collect();
    // Least squares point nearest to all rays: sum (I - d d^T) (x - c) = 0.
    let mut a = Mat3([[0.0; 3]; 3]);
    let mut b = Vec3::ZERO;
    for (c, d) in &rays {
        let m = Mat3::IDENTITY.add(&Mat3::outer(*d, *d).scale(-1.0));
        a = a.add(&m);
        b = b + m * *c;
    }
    let x = a.inverse()? * b;
    let mut widest = 0.0f64;
    for (i, (ci, _)) in rays.iter().enumerate() {
        for (cj, _) in &rays[i + 1..] {
            let (u, v) = ((x - *ci).normalized(), (x - *cj).normalized());
            widest = widest.max(u.dot(v).clamp(-1.0, 1.0).acos().to_degrees());
        }
    }
    if !x.is_finite() || widest < min_angle_deg {
        return None;
    }
    for (p, q) in obs {
        if reprojection_px(cam, p, x, (q.x, q.y))? > 2.0 {
            return None;
        }
    }
    Some(x)
}

/// PnP of the camera that sees the points `obj` at `img` (working pixels; OpenCV's RANSAC
/// over `iterations` samples, 2 px, with its iterative solver), starting from `guess` when
/// given: the camera-to-world pose and the indices of the inliers; `None` when it fails or
/// the pose is not finite.
pub(crate) fn pnp(
    k: &Mat,
    obj: &Vector<core::Point3f>,
    img: &Vector<Point2f>,
    guess: Option<Pose>,
    iterations: i32,
) -> Result<Option<(Pose, Vector<i32>)>> {
    let (mut rvec, mut tvec) = (Mat::default(), Mat::default());
    if let Some(p) = guess {
        let Pose {
            rotation: r,
            translation: t,
        } = p.inverse();
        let rm = Mat::from_slice_2d(&r.0)?;
        calib3d::rodrigues(&rm, &mut rvec, &mut core::no_array())?;
        tvec = Mat::from_slice_2d(&[[t.x()], [t.y()], [t.z()]])?;
    }
    let mut inl: Vector<i32> = Vector::new();
    let ok = calib3d::solve_pnp_ransac(
        obj,
        img,
        k,
        &core::no_array(),
        &mut rvec,
        &mut tvec,
        guess.is_some(),
        iterations,
        2.0,
        0.999,
        &mut inl,
        calib3d::SOLVEPNP_ITERATIVE,
    )?;
    if !ok {
        return Ok(None);
    }
    let mut rm = Mat::default();
    calib3d::rodrigues(&rvec, &mut rm, &mut core::no_array())?;
    let pose = from_extrinsics(mat3(&rm)?, vec3(&tvec)?);
    Ok(pose.is_finite().then_some((pose, inl)))
}

/// OpenCV's 3x3 camera matrix of `cam`.
pub(crate) fn camera_matrix(cam: &Camera) -> Result<Mat> {
    Ok(Mat::from_slice_2d(&[
        [cam.fx, 0.0, cam.cx],
        [0.0, cam.fy, cam.cy],
        [0.0, 0.0, 1.0],
    ])?)
}

/// The camera-to-world pose of world-to-camera extrinsics `x_cam = R x_world + t`.
pub(crate) fn from_extrinsics(r: Mat3, t: Vec3) -> Pose {
    Pose {
        rotation: r,
        translation: t,
    }
    .inverse()
}

struct Solver {
    cam: Camera,
    /// Per track, the frame it was born in and the one it died in, with its ORB
    /// descriptors there (for [`Solver::merge`]).
    ends: Vec<Ends>,
    cfg: TrackConfig,
    frames: usize,
    tracks: Vec<Vec<Obs>>,
    /// Per frame: (track, x, y).
    by_frame: Vec<Vec<(usize, f32, f32)>>,
    poses: Vec<Option<Pose>>,
    inliers: Vec<usize>,
    points: HashMap<usize, Vec3>,
}

impl Solver {
    /// The solver of `frames` frames with `tracks` and their `ends`; each frame's
    /// observations are listed in track order.
    fn new(
        cam: Camera,
        cfg: TrackConfig,
        frames: usize,
        tracks: Vec<Vec<Obs>>,
        ends: Vec<Ends>,
    ) -> Self {
        let mut by_frame = vec![Vec::new(); frames];
        for (id, t) in tracks.iter().enumerate() {
            if t.len() < 2 {
                continue;
            }
            for &(f, x, y) in t {
                by_frame[f as usize].push((id, x, y));
            }
        }
        Self {
            cam,
            ends,
            cfg,
            frames,
            tracks,
            by_frame,
            poses: vec![None; frames],
            inliers: vec![0; frames],
            points: HashMap::new(),
        }
    }

    fn k(&self) -> Result<Mat> {
        camera_matrix(&self.cam)
    }

    /// Tracks seen in both frames, as positions in each, in track order (a frame's
    /// observations are listed by track, [`Solver::new`], so the two lists merge).
    fn common(&self, a: usize, b: usize) -> (Vec<usize>, Vector<Point2f>, Vector<Point2f>) {
        let (mut ids, mut pa, mut pb) = (Vec::new(), Vector::new(), Vector::new());
        let mut at_b = self.by_frame[b].iter().peekable();
        for &(id, x, y) in &self.by_frame[a] {
            while at_b.next_if(|o| o.0 < id).is_some() {}
            if let Some(&&(_, u, v)) = at_b.peek().filter(|o| o.0 == id) {
                ids.push(id);
                pa.push(Point2f::new(x, y));
                pb.push(Point2f::new(u, v));
            }
        }
        (ids, pa, pb)
    }

    fn normalised(&self, p: &Vector<Point2f>) -> Vector<Point2f> {
        p.iter()
            .map(|q| {
                Point2f::new(
                    ((q.x as f64 - self.cam.cx) / self.cam.fx) as f32,
                    ((q.y as f64 - self.cam.cy) / self.cam.fy) as f32,
                )
            })
            .collect()
    }

    /// The trajectory, and the reprojection errors of its points' observations.
    fn solve(mut self) -> Result<(Trajectory, Vec<f64>)> {
        let long = self.cam.width.max(self.cam.height) as f64;
        let mut motion = CameraMotion::Untracked;
        let mut init = None;
        let mut most_motion = 0.0f64;
        let mut enough_tracks = false;
        for k in 1..self.frames {
            let (ids, p0, pk) = self.common(0, k);
            if ids.len() < 30 {
                continue;
            }
            enough_tracks = true;
            let mut d: Vec<f64> = p0
                .iter()
                .zip(pk.iter())
                .map(|(a, b)| (((a.x - b.x).powi(2) + (a.y - b.y).powi(2)) as f64).sqrt())
                .collect();
            d.sort_by(f64::total_cmp);
            let med = d[d.len() / 2];
            most_motion = most_motion.max(med);
            if med < self.cfg.init_motion * long {
                continue;
            }
            match self.initialise(k, &p0, &pk)? {
                Some(true) => {
                    init = Some((0, k));
                    break;
                }
                Some(false) => motion = CameraMotion::Rotating,
                None => {}
            }
        }
        if init.is_none() {
            if enough_tracks && motion != CameraMotion::Rotating {
                motion = if most_motion < 1.0 {
                    CameraMotion::Static
                } else {
                    CameraMotion::Rotating
                };
            }
            return Ok((
                Trajectory {
                    camera: self.cam,
                    poses: vec![None; self.frames],
                    inliers: vec![0; self.frames],
                    motion,
                    points: 0,
                    reprojection_px: f64::NAN,
                    initial_pair: None,
                    segment: vec![0; self.frames],
                    world: vec![0; self.frames],
                },
                Vec::new(),
            ));
        }
        self.register()?;

        for _ in 0..REFINE_ROUNDS {
            self.refine()?;
        }
        if let Some(pair) = init.filter(|_| self.cfg.ba_window > 0) {
            // Adjust, drop the observations the adjusted points disagree with, adjust again.
            self.bundle_adjust(pair, BA_ITERATIONS)?;
            self.cull(CULL_PX);
            self.bundle_adjust(pair, BA_ITERATIONS / 2)?;
        }
        let mut errors = self.reprojection_errors();
        let reprojection_px = median(&mut errors);
        Ok((
            Trajectory {
                camera: self.cam,
                segment: vec![0; self.frames],
                world: vec![0; self.frames],
                poses: self.poses,
                inliers: self.inliers,
                motion: CameraMotion::Translating,
                points: self.points.len(),
                reprojection_px,
                initial_pair: init,
            },
            errors,
        ))
    }

    /// The essential matrix between two frames' track positions (RANSAC, 1 px) and the
    /// relative pose it gives, `x_b = R x_a + t` with unit `t`: `(R, t, inliers of E,
    /// tracks in front of both)`; `None` when no matrix fits.
    fn relative_pose(
        &self,
        pa: &Vector<Point2f>,
        pb: &Vector<Point2f>,
    ) -> Result<Option<(Mat3, Vec3, usize, usize)>> {
        let (na, nb) = (self.normalised(pa), self.normalised(pb));
        let f = 0.5 * (self.cam.fx + self.cam.fy);
        let eye = Mat::from_slice_2d(&[[1.0f64, 0.0, 0.0], [0.0, 1.0, 0.0], [0.0, 0.0, 1.0]])?;
        let mut mask = Mat::default();
        let e = calib3d::find_essential_mat(
            &na,
            &nb,
            &eye,
            calib3d::RANSAC,
            0.999,
            1.0 / f,
            1000,
            &mut mask,
        )?;
        if e.rows() < 3 {
            return Ok(None);
        }
        let inliers = count(&mask)?;
        // Several solutions come stacked: take the first.
        let e3 = Mat::roi(&e, core::Rect::new(0, 0, 3, 3))?.try_clone()?;
        let (mut r, mut t) = (Mat::default(), Mat::default());
        let good = calib3d::recover_pose(
            &e3,
            &na,
            &nb,
            &mut r,
            &mut t,
            1.0,
            core::Point2d::new(0.0, 0.0),
            &mut mask,
        )?;
        Ok(Some((mat3(&r)?, vec3(&t)?, inliers, good as usize)))
    }

    /// Tries frames 0 and `k` as the first baseline: `Some(true)` when the essential matrix
    /// wins and the pair is set up, `Some(false)` when a homography explains the motion,
    /// `None` when neither fits.
    fn initialise(
        &mut self,
        k: usize,
        p0: &Vector<Point2f>,
        pk: &Vector<Point2f>,
    ) -> Result<Option<bool>> {
        let Some((r, t, ie, good)) = self.relative_pose(p0, pk)? else {
            return Ok(None);
        };
        let mut hmask = Mat::default();
        let h = calib3d::find_homography(&p0, &pk, &mut hmask, calib3d::RANSAC, 1.0)?;
        let ih = if h.empty() { 0 } else { count(&hmask)? };
        if ie < 20 {
            return Ok(None);
        }
        if ih as f64 >= 0.9 * ie as f64 {
            return Ok(Some(false));
        }
        if good < 20 {
            return Ok(None);
        }
        // x_k = R x_0 + t (world = camera 0).
        self.poses[0] = Some(Pose::IDENTITY);
        self.poses[k] = Some(from_extrinsics(r, t));
        self.triangulate_between(0, k)?;
        if self.points.len() < 20 {
            self.poses[k] = None;
            self.poses[0] = None;
            self.points.clear();
            return Ok(None);
        }
        Ok(Some(true))
    }

    /// Triangulates the tracks frames `a` and `b` (both placed) share and that have no point
    /// yet, keeping those in front of both, seen under `min_angle_deg` and reprojecting
    /// within 2 px.
    fn triangulate_between(&mut self, a: usize, b: usize) -> Result<usize> {
        let (ids, pa, pb) = self.common(a, b);
        let (pose_a, pose_b) = match (self.poses[a], self.poses[b]) {
            (Some(x), Some(y)) => (x, y),
            _ => return Ok(0),
        };
        let mut added = 0;
        for (i, &id) in ids.iter().enumerate() {
            if self.points.contains_key(&id) {
                continue;
            }
            let (qa, qb) = (pa.get(i)?, pb.get(i)?);
            if let Some(x) = self.triangulate(&[(pose_a, qa), (pose_b, qb)]) {
                self.points.insert(id, x);
                added += 1;
            }
        }
        Ok(added)
    }

    /// Midpoint triangulation of two or more rays with the checks of
    /// [`Solver::triangulate_between`].
    fn triangulate(&self, obs: &[(Pose, Point2f)]) -> Option<Vec3> {
        triangulate(&self.cam, self.cfg.min_angle_deg, obs)
    }

    /// PnP of frame `f` on its triangulated tracks; `refine` starts from its current pose
    /// and uses only the iterative solver.
    fn resect(&mut self, f: usize, refine: bool) -> Result<bool> {
        let (mut obj, mut img): (Vector<core::Point3f>, Vector<Point2f>) =
            (Vector::new(), Vector::new());
        for &(id, x, y) in &self.by_frame[f] {
            if let Some(p) = self.points.get(&id) {
                obj.push(core::Point3f::new(p.x() as f32, p.y() as f32, p.z() as f32));
                img.push(Point2f::new(x, y));
            }
        }
        if obj.len() < MIN_PNP {
            return Ok(false);
        }
        let guess = self.poses[f].filter(|_| refine);
        let Some((pose, inl)) = pnp(&self.k()?, &obj, &img, guess, 200)? else {
            return Ok(false);
        };
        if inl.len() < if refine { MIN_PNP } else { MIN_PNP_NEW } {
            return Ok(false);
        }
        // A camera does not turn by more than MAX_TURN_DEG between neighbouring frames: a
        // pose that does is a wrong PnP solution on too few points.
        for g in [f.wrapping_sub(1), f + 1] {
            if let Some(q) = self.poses.get(g).copied().flatten() {
                if rotation_deg(&(q.rotation.transpose() * pose.rotation)) > MAX_TURN_DEG {
                    return Ok(false);
                }
            }
        }
        self.poses[f] = Some(pose);
        self.inliers[f] = inl.len();
        Ok(true)
    }

    /// Places every frame it can, nearest to a placed frame first, triangulating as it goes.
    fn register(&mut self) -> Result<()> {
        loop {
            let mut progress = false;
            // Unplaced frames, most triangulated tracks first.
            let mut todo: Vec<(usize, usize)> = (0..self.frames)
                .filter(|&f| self.poses[f].is_none())
                .map(|f| {
                    let n = self.by_frame[f]
                        .iter()
                        .filter(|o| self.points.contains_key(&o.0))
                        .count();
                    (n, f)
                })
                .collect();
            todo.sort_by(|a, b| b.cmp(a));
            for (n, f) in todo {
                if n < MIN_PNP_NEW || !self.resect(f, false)? {
                    continue;
                }
                if self.merge(f)? > 0 {
                    self.resect(f, true)?;
                }
                progress = true;
                // New points with every placed frame, farthest in time first (widest
                // angles; a point keeps the first pair that triangulates it).
                let mut others: Vec<usize> = (0..self.frames)
                    .filter(|&g| g != f && self.poses[g].is_some())
                    .collect();
                others.sort_by_key(|&g| std::cmp::Reverse(g.abs_diff(f)));
                for g in others {
                    self.triangulate_between(f, g)?;
                }
            }
            if !progress {
                // Bridge a break (too few tracks with points across it, as after a gap in the
                // frames): an unplaced neighbour of a placed frame by their relative pose.
                let next = (0..self.frames).find_map(|f| {
                    if self.poses[f].is_some() {
                        return None;
                    }
                    [f.wrapping_sub(1), f + 1]
                        .into_iter()
                        .find(|&g| g < self.frames && self.poses[g].is_some())
                        .map(|g| (f, g))
                });
                let Some((f, g)) = next else { return Ok(()) };
                if !self.bridge(f, g)? {
                    return Ok(());
                }
                let mut others: Vec<usize> = (0..self.frames)
                    .filter(|&h| h != f && self.poses[h].is_some())
                    .collect();
                others.sort_by_key(|&h| std::cmp::Reverse(h.abs_diff(f)));
                for h in others {
                    self.triangulate_between(f, h)?;
                }
            }
        }
    }

    /// Joins tracks born in placed frame `c` to tracks with points that died at most
    /// [`MERGE_GAP`] frames before it (the tracker lost a corner and found it again as a new
    /// track): a dead track's point projected into `c` joins the born track nearest in
    /// descriptor within [`MERGE_RADIUS_PX`] of it, when their ORB descriptors (where one
    /// died and the other was born) differ in at most [`MERGE_BITS`] bits and clearly less
    /// than those of the second nearest. The later track's observations move to the
    /// earlier one. Returns how many tracks were joined.
    fn merge(&mut self, c: usize) -> Result<usize> {
        let Some(pose) = self.poses[c] else {
            return Ok(0);
        };
        let born: Vec<(usize, Descriptor, f32, f32)> = self.by_frame[c]
            .iter()
            .filter_map(|&(id, x, y)| {
                let (g, d) = self.ends[id][0]?;
                (g as usize == c).then_some((id, d, x, y))
            })
            .collect();
        if born.len() < MERGE_BORN {
            return Ok(0);
        }
        let to_camera = pose.inverse();
        // (Hamming distance, dead track, born track) of each dead track's best.
        let mut pairs = Vec::new();
        for (&id, &x) in &self.points {
            let Some((g, d)) = self.ends[id][1] else {
                continue;
            };
            let g = g as usize;
            if g >= c || g + MERGE_GAP < c {
                continue;
            }
            let Some((u, v)) = self.cam.project(to_camera.view_to_ref(x)) else {
                continue;
            };
            let (mut best, mut second) = ((u32::MAX, 0), u32::MAX);
            for (j, b) in born.iter().enumerate() {
                if (b.2 as f64 - u).hypot(b.3 as f64 - v) > MERGE_RADIUS_PX {
                    continue;
                }
                let h = hamming::distance(&d, &b.1);
                if h < best.0 {
                    second = best.0;
                    best = (h, j);
                } else {
                    second = second.min(h);
                }
            }
            if best.0 <= MERGE_BITS && (best.0 as f32) < 0.8 * second as f32 {
                pairs.push((best.0, id, best.1));
            }
        }
        pairs.sort_unstable();
        let mut taken = vec![false; born.len()];
        let mut touched = HashSet::new();
        let mut joined = 0;
        for (_, old, j) in pairs {
            if std::mem::replace(&mut taken[j], true) {
                continue;
            }
            let new = born[j].0;
            let moved = std::mem::take(&mut self.tracks[new]);
            for &(f, _, _) in &moved {
                for o in self.by_frame[f as usize].iter_mut().filter(|o| o.0 == new) {
                    o.0 = old;
                }
                touched.insert(f as usize);
            }
            self.tracks[old].extend(moved);
            self.points.remove(&new);
            self.ends[old][1] = self.ends[new][1];
            joined += 1;
        }
        for f in touched {
            self.by_frame[f].sort_unstable_by_key(|o| o.0);
        }
        Ok(joined)
    }

    /// Places frame `f` from placed frame `g` by their essential matrix; the baseline's length
    /// comes from the triangulated tracks both see, or else is the length of `g`'s own step
    /// from its other neighbour (constant speed).
    fn bridge(&mut self, f: usize, g: usize) -> Result<bool> {
        let (ids, pg, pf) = self.common(g, f);
        if ids.len() < 15 {
            return Ok(false);
        }
        let Some((r, t, _, good)) = self.relative_pose(&pg, &pf)? else {
            return Ok(false);
        };
        // Most of the tracks must agree with the motion: across a cut, chance matches fit an
        // essential matrix too, but only a few of them (measured: 23 of 43 on a synthetic
        // cut, 5 of 17 across the fox's jump; 73 to 90 % over the fox's gaps).
        if good < BRIDGE_MIN || (good as f64) < 0.6 * ids.len() as f64 {
            return Ok(false);
        }
        let nf = self.normalised(&pf);
        // x_f = R x_g + s t in camera coordinates.
        let pose_g = self.poses[g].expect("g is placed");
        let Pose {
            rotation: rg,
            translation: tg,
        } = pose_g.inverse();
        let mut scales = Vec::new();
        for (i, id) in ids.iter().enumerate() {
            let Some(&x) = self.points.get(id) else {
                continue;
            };
            let q = r * (rg * x + tg);
            let o = nf.get(i)?;
            let (u, v) = (o.x as f64, o.y as f64);
            for (num, den) in [
                (u * q.z() - q.x(), t.x() - u * t.z()),
                (v * q.z() - q.y(), t.y() - v * t.z()),
            ] {
                if den.abs() > 0.2 {
                    scales.push(num / den);
                }
            }
        }
        scales.sort_by(f64::total_cmp);
        let s = if scales.len() >= 4 && scales[scales.len() / 2] > 0.0 {
            scales[scales.len() / 2]
        } else {
            let h = if g > f { g + 1 } else { g.wrapping_sub(1) };
            match self.poses.get(h).copied().flatten() {
                Some(p) => (p.translation - pose_g.translation).norm(),
                None => return Ok(false),
            }
        };
        if !(s.is_finite() && s > 0.0) {
            return Ok(false);
        }
        // World-to-camera of f: R_f = R Rg, t_f = R tg + s t.
        self.poses[f] = Some(from_extrinsics(r * rg, r * tg + t * s));
        Ok(true)
    }

    /// One round of resection (every placed frame) and intersection (every point from all
    /// placed frames that see it).
    fn refine(&mut self) -> Result<()> {
        for f in 0..self.frames {
            if f != 0 && self.poses[f].is_some() && !self.resect(f, true)? {
                self.poses[f] = None;
            }
        }
        let ids: Vec<usize> = self.points.keys().copied().collect();
        for id in ids {
            let obs: Vec<(Pose, Point2f)> = self.tracks[id]
                .iter()
                .filter_map(|&(f, x, y)| self.poses[f as usize].map(|p| (p, Point2f::new(x, y))))
                .collect();
            match (obs.len() >= 2).then(|| self.triangulate(&obs)).flatten() {
                Some(x) => {
                    self.points.insert(id, x);
                }
                None => {
                    self.points.remove(&id);
                }
            }
        }
        Ok(())
    }

    /// Bundle adjustment (`ba.rs`) over windows of `ba_window` (at least 1) placed frames,
    /// the first baseline `pair` fixing the gauge.
    fn bundle_adjust(&mut self, pair: (usize, usize), iterations: usize) -> Result<()> {
        let w = self.cfg.ba_window;
        let placed: Vec<usize> = (0..self.frames)
            .filter(|&f| self.poses[f].is_some())
            .collect();
        let mut start = 0;
        loop {
            let end = (start + w).min(placed.len());
            ba::adjust(
                &self.cam,
                &mut self.poses,
                &mut self.points,
                &self.tracks,
                &ba::Window {
                    free: &placed[start..end],
                    held: &placed[..start],
                    fixed: pair.0,
                    scale: pair.1,
                    iterations,
                },
            )?;
            if end == placed.len() {
                return Ok(());
            }
            start = end - (w / 3).min(end - start - 1);
        }
    }

    /// Drops the observations that reproject farther than `px` from their point (drifted
    /// tracks), and the points left seen by fewer than two placed frames.
    fn cull(&mut self, px: f64) {
        let ids: Vec<usize> = self.points.keys().copied().collect();
        for id in ids {
            let x = self.points[&id];
            let (cam, poses) = (&self.cam, &self.poses);
            self.tracks[id].retain(|&(f, u, v)| match poses[f as usize] {
                Some(p) => reprojection_px(cam, &p, x, (u, v)).is_some_and(|e| e <= px),
                None => true,
            });
            let seen = self.tracks[id]
                .iter()
                .filter(|o| poses[o.0 as usize].is_some())
                .count();
            if seen < 2 {
                self.points.remove(&id);
            }
        }
    }

    fn reprojection_errors(&self) -> Vec<f64> {
        let mut e = Vec::new();
        for (&id, &x) in &self.points {
            for &(f, u, v) in &self.tracks[id] {
                if let Some(p) = self.poses[f as usize] {
                    e.extend(reprojection_px(&self.cam, &p, x, (u, v)));
                }
            }
        }
        e
    }
}

/// Median (NaN when empty): the element at half the length in sorted order; reorders `v`.
pub(crate) fn median(v: &mut [f64]) -> f64 {
    if v.is_empty() {
        return f64::NAN;
    }
    let m = v.len() / 2;
    *v.select_nth_unstable_by(m, f64::total_cmp).1
}

/// Non-zero entries of an OpenCV mask (0 for an empty one).
fn count(m: &Mat) -> Result<usize> {
    if m.empty() {
        return Ok(0);
    }
    Ok(m.data_typed::<u8>()?.iter().filter(|&&v| v != 0).count())
}

fn mat3(m: &Mat) -> Result<Mat3> {
    let mut out = [[0.0; 3]; 3];
    for (i, row) in out.iter_mut().enumerate() {
        for (j, v) in row.iter_mut().enumerate() {
            *v = *m.at_2d::<f64>(i as i32, j as i32)?;
        }
    }
    Ok(Mat3(out))
}

fn vec3(m: &Mat) -> Result<Vec3> {
    // OpenCV may hand back a view into a larger matrix (solvePnPRansac does on some inputs).
    let copy;
    let m = if m.is_continuous() {
        m
    } else {
        copy = m.try_clone()?;
        &copy
    };
    let v = m.data_typed::<f64>()?;
    if v.len() < 3 {
        return Err(TrackError::Input("OpenCV returned a short vector".into()));
    }
    Ok(Vec3::new(v[0], v[1], v[2]))
}

#[cfg(test)]
mod tests {
    use super::*;

    /// Descriptors from a fixed-seed generator.
    fn descriptor(seed: &mut u64) -> Descriptor {
        std::array::from_fn(|_| {
            *seed = seed
                .wrapping_mul(6_364_136_223_846_793_005)
                .wrapping_add(1_442_695_040_888_963_407);
            *seed
        })
    }

    #[test]
    fn merge_joins_reborn_tracks_to_their_dead_points_only() {
        let cam = Camera {
            width: 480,
            height: 270,
            fx: 400.0,
            fy: 400.0,
            cx: 240.0,
            cy: 135.0,
        };
        let born_n = MERGE_BORN + 20;
        // Tracks 0..born_n died in frame c - 1 with points; two more follow (below); then
        // the tracks born in frame c, 20 px apart on a grid, one for each of the first.
        let mut seed = 7;
        let at = |i: usize| (20.0 + 20.0 * (i % 22) as f32, 20.0 + 20.0 * (i / 22) as f32);
        let (mut tracks, mut ends, mut points) = (Vec::new(), Vec::new(), HashMap::new());
        let born_desc: Vec<Descriptor> = (0..born_n).map(|_| descriptor(&mut seed)).collect();
        let frames = MERGE_GAP + 4;
        let c = MERGE_GAP + 2;
        for (i, d) in born_desc.iter().enumerate() {
            let mut dead = *d;
            dead[0] ^= 0b1011; // 3 bits apart
            let (u, v) = at(i);
            tracks.push(vec![(c as u32 - 2, u, v), (c as u32 - 1, u, v)]);
            ends.push([None, Some((c as u32 - 1, dead))]);
            // Seen in frame c 1.5 px from where the born track is.
            let z = 5.0;
            let x = Vec3::new(
                (u as f64 + 1.5 - cam.cx) / cam.fx * z,
                (v as f64 - cam.cy) / cam.fy * z,
                z,
            );
            points.insert(i, x);
        }
        // Dead too long ago (frame 1, with born track 0's very descriptor), and a stranger
        // (another descriptor) dead in frame c - 1: both seen in frame c 1 px from a born track.
        for (dead, near, desc) in [
            (1, 0, born_desc[0]),
            (c as u32 - 1, 3, descriptor(&mut seed)),
        ] {
            let (u, v) = at(near);
            tracks.push(vec![(dead - 1, u, v), (dead, u, v)]);
            ends.push([None, Some((dead, desc))]);
            let x = Vec3::new(
                (u as f64 - cam.cx) / cam.fx,
                (v as f64 + 1.0 - cam.cy) / cam.fy,
                1.0,
            );
            points.insert(tracks.len() - 1, x);
        }
        let first_born = tracks.len();
        for (i, d) in born_desc.iter().enumerate() {
            let (u, v) = at(i);
            tracks.push(vec![(c as u32, u, v), (c as u32 + 1, u + 0.5, v)]);
            ends.push([Some((c as u32, *d)), Some((c as u32 + 1, *d))]);
        }
        let mut solver = Solver::new(cam, TrackConfig::default(), frames, tracks, ends);
        solver.points = points;
        solver.poses[c] = Some(Pose::IDENTITY);

        assert_eq!(solver.merge(c).unwrap(), born_n);
        for i in 0..born_n {
            let frames: Vec<u32> = solver.tracks[i].iter().map(|o| o.0).collect();
            assert_eq!(frames, [c as u32 - 2, c as u32 - 1, c as u32, c as u32 + 1]);
            assert!(solver.tracks[first_born + i].is_empty());
            assert_eq!(solver.ends[i][1].map(|e| e.0), Some(c as u32 + 1));
        }
        assert_eq!(solver.tracks[born_n].len(), 2);
        assert_eq!(solver.tracks[born_n + 1].len(), 2);
        for f in [c, c + 1] {
            let ids: Vec<usize> = solver.by_frame[f].iter().map(|o| o.0).collect();
            assert_eq!(ids, (0..born_n).collect::<Vec<_>>(), "frame {f}");
        }
        // No born tracks are left in frame c.
        assert_eq!(solver.merge(c).unwrap(), 0);
    }
}
