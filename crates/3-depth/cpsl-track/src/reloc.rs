//! Relocalisation: ties the segments of a clip into one world and places the frames tracking
//! left out, by descriptor matches against the 3-D points of other frames.
//!
//! Every frame keeps its ORB features ([`Features`], found while tracking). A placed frame's
//! *map points* are its features triangulated with up to [`MAP_PARTNERS`] placed frames of
//! its segment (the widest baselines within [`MAP_REACH`] frames and [`MAP_TURN_DEG`] of
//! turn; their poses are known, so a match is kept only where its rays meet). Then:
//!
//! - *Tying* ([`tie_segments`]). The map points of each later segment's frames are matched
//!   with those of every earlier segment's (at most [`TIE_FRAMES`] frames a side), and a
//!   similarity (rotation, translation and scale) is fitted to the matched 3-D pairs:
//!   RANSAC on three pairs, then least squares (Umeyama) on the inliers. With at least
//!   [`TIE_MIN`] inliers the segment's poses move into the earlier world
//!   ([`Trajectory::world`]): across a jump of the camera the depth keeps its units.
//! - *Placing* ([`place_frames`]). A frame left unplaced is matched with the map points of
//!   the nearest placed frames and placed by PnP (RANSAC) in their world.

use crate::hamming::{self, Descriptor};
use crate::{camera_matrix, mat3, pnp, rotation_deg, triangulate, vec3, Result, Trajectory};
use cpsl_core::{Camera, Mat3, Pose, Vec3};
use opencv::core::{self, Point2f, Vector};
use opencv::features2d;
use opencv::prelude::*;
use std::collections::HashMap;

/// ORB features of a frame: positions (working pixels) and descriptors, one each.
pub(crate) struct Features {
    pub(crate) points: Vec<Point2f>,
    pub(crate) desc: Vec<Descriptor>,
}

/// Most ORB features kept per frame for relocalisation (40 KB a frame).
pub(crate) const KEPT_FEATURES: i32 = 1000;

/// ORB's patch (and edge) size, pixels.
const PATCH: i32 = 31;

/// An ORB of up to `count` features over `levels` pyramid levels 1.2 apart, Harris-scored
/// FAST corners, [`PATCH`]-pixel patches: the one setting every ORB of the crate uses.
fn orb(count: i32, levels: i32) -> Result<core::Ptr<features2d::ORB>> {
    Ok(features2d::ORB::create(
        count,
        1.2,
        levels,
        PATCH,
        0,
        2,
        features2d::ORB_ScoreType::HARRIS_SCORE,
        PATCH,
        10,
    )?)
}

/// Up to `count` ORB features of a frame (Harris-scored FAST corners over 8 levels, 1.2
/// apart).
pub(crate) fn features(grey: &Mat, count: i32) -> Result<Features> {
    let mut orb = orb(count, 8)?;
    let mut kp = Vector::<core::KeyPoint>::new();
    let mut desc = Mat::default();
    orb.detect_and_compute(grey, &core::no_array(), &mut kp, &mut desc, false)?;
    Ok(Features {
        points: kp.iter().map(|k| k.pt()).collect(),
        desc: hamming::descriptors(&desc)?,
    })
}

/// ORB descriptors of `grey` at `points` (level 0, oriented as ORB orients its own); `None`
/// for a point too near the border for ORB's patch.
pub(crate) fn descriptors_at(grey: &Mat, points: &[Point2f]) -> Result<Vec<Option<Descriptor>>> {
    let mut out = vec![None; points.len()];
    if points.is_empty() {
        return Ok(out);
    }
    let mut orb = orb(points.len() as i32, 1)?;
    let mut kp: Vector<core::KeyPoint> = points
        .iter()
        .enumerate()
        .map(|(i, p)| core::KeyPoint::new_point(*p, PATCH as f32, -1.0, 0.0, 0, i as i32))
        .collect::<std::result::Result<_, _>>()?;
    let mut desc = Mat::default();
    orb.detect_and_compute(grey, &core::no_array(), &mut kp, &mut desc, true)?;
    for (k, d) in kp.iter().zip(hamming::descriptors(&desc)?) {
        out[k.class_id() as usize] = Some(d);
    }
    Ok(out)
}

/// Nearest-neighbour matches from the descriptors `a` to those of `b` that pass the ratio
/// test (the second nearest at least 1/0.8 as far) and are at most 64 bits apart.
pub(crate) fn matches(a: &[Descriptor], b: &[Descriptor]) -> Vec<(usize, usize)> {
    if a.len() < 2 || b.len() < 2 {
        return Vec::new();
    }
    hamming::nearest_two(a, b)
        .iter()
        .enumerate()
        .filter(|(_, [x, y])| x.0 <= 64 && (x.0 as f32) < 0.8 * y.0 as f32)
        .map(|(i, [x, _])| (i, x.1 as usize))
        .collect()
}

/// Partner frames a frame's map points are triangulated with, each giving at least
/// [`MAP_GOOD`] of them.
const MAP_PARTNERS: usize = 2;
/// Least angle between the two rays of a map point, degrees.
const MAP_ANGLE_DEG: f64 = 3.0;
/// Least points a partner must give to count.
const MAP_GOOD: usize = 20;
/// Most partners tried.
const MAP_TRIES: usize = 4;
/// Farthest partner, in frames.
const MAP_REACH: usize = 8;
/// Largest turn to a partner, degrees (descriptors match less well beyond).
const MAP_TURN_DEG: f64 = 20.0;

/// A placed frame's features with 3-D points (its world's).
struct MapPoints {
    points: Vec<Vec3>,
    /// Their descriptors, one each.
    desc: Vec<Descriptor>,
}

/// Map points of the placed frames, built when first asked for.
struct Maps<'a> {
    cam: Camera,
    min_angle_deg: f64,
    features: &'a [Features],
    built: HashMap<usize, MapPoints>,
}

impl<'a> Maps<'a> {
    fn new(t: &Trajectory, features: &'a [Features], min_angle_deg: f64) -> Self {
        Self {
            cam: t.camera,
            min_angle_deg,
            features,
            built: HashMap::new(),
        }
    }

    fn get(&mut self, t: &Trajectory, f: usize) -> Result<&MapPoints> {
        if !self.built.contains_key(&f) {
            let m = self.build(t, f)?;
            self.built.insert(f, m);
        }
        Ok(&self.built[&f])
    }

    fn build(&self, t: &Trajectory, f: usize) -> Result<MapPoints> {
        let mut feature = Vec::new();
        let mut points = Vec::new();
        let ff = &self.features[f];
        if let Some(pose) = t.poses[f] {
            // Partners: placed frames of the segment, within reach and turn,
            // nearest first; one that gives too few points (too short a baseline, too little
            // overlap) does not count.
            let lo = f.saturating_sub(MAP_REACH);
            let hi = (f + MAP_REACH).min(t.poses.len() - 1);
            let mut partners: Vec<(usize, Pose)> = (lo..=hi)
                .filter(|&g| g != f && t.segment[g] == t.segment[f])
                .filter_map(|g| Some((g, t.poses[g]?)))
                .filter(|(_, p)| {
                    rotation_deg(&(p.rotation.transpose() * pose.rotation)) <= MAP_TURN_DEG
                })
                .collect();
            partners.sort_by_key(|&(g, _)| g.abs_diff(f));
            let mut taken = vec![false; ff.points.len()];
            let mut good = 0;
            for &(g, pg) in partners.iter().take(MAP_TRIES) {
                let fg = &self.features[g];
                let before = points.len();
                for (i, j) in matches(&ff.desc, &fg.desc) {
                    if taken[i] {
                        continue;
                    }
                    let obs = [(pose, ff.points[i]), (pg, fg.points[j])];
                    if let Some(x) =
                        triangulate(&self.cam, self.min_angle_deg.max(MAP_ANGLE_DEG), &obs)
                    {
                        taken[i] = true;
                        feature.push(i);
                        points.push(x);
                    }
                }
                good += usize::from(points.len() - before >= MAP_GOOD);
                if good == MAP_PARTNERS {
                    break;
                }
            }
        }
        let desc = feature.iter().map(|&i| ff.desc[i]).collect();
        Ok(MapPoints { points, desc })
    }
}

/// Most frames a side whose map points are matched when tying two segments (evenly spaced).
const TIE_FRAMES: usize = 16;
/// Least matched 3-D pairs that agree with one similarity for a tie.
const TIE_MIN: usize = 40;
/// A matched pair agrees with a similarity when it maps within this share of the point's
/// depth (in the earlier frame) of its partner.
const TIE_TOLERANCE: f64 = 0.05;
/// RANSAC samples for a tie.
const TIE_SAMPLES: usize = 500;

/// A similarity `x -> scale * rotation * x + translation`.
#[derive(Debug, Clone, Copy)]
pub(crate) struct Similarity {
    pub(crate) rotation: Mat3,
    pub(crate) translation: Vec3,
    pub(crate) scale: f64,
}

impl Similarity {
    fn apply(&self, x: Vec3) -> Vec3 {
        self.rotation * x * self.scale + self.translation
    }

    /// A camera-to-world pose of the source world in the target world.
    fn pose(&self, p: &Pose) -> Pose {
        Pose {
            rotation: self.rotation * p.rotation,
            translation: self.apply(p.translation),
        }
    }
}

/// The weighted least-squares similarity taking each `pairs[i].1` to `pairs[i].0`, weighed
/// by `pairs[i].2` (Umeyama, 1991); `None` when degenerate.
pub(crate) fn umeyama(pairs: &[(Vec3, Vec3, f64)]) -> Result<Option<Similarity>> {
    let n: f64 = pairs.iter().map(|p| p.2).sum();
    if pairs.len() < 3 || n <= 0.0 || n.is_nan() {
        return Ok(None);
    }
    let mean = |f: fn(&(Vec3, Vec3, f64)) -> Vec3| {
        pairs
            .iter()
            .map(|p| f(p) * p.2)
            .fold(Vec3::ZERO, |a, b| a + b)
            * (1.0 / n)
    };
    let (ma, mb) = (mean(|p| p.0), mean(|p| p.1));
    let mut cov = Mat3([[0.0; 3]; 3]);
    let mut var = 0.0;
    for &(a, b, w) in pairs {
        let (da, db) = (a - ma, b - mb);
        cov = cov.add(&Mat3::outer(da, db).scale(w));
        var += w * db.dot(db);
    }
    if var <= 1e-12 * n {
        return Ok(None);
    }
    let m = Mat::from_slice_2d(&cov.scale(1.0 / n).0)?;
    let (mut w, mut u, mut vt) = (Mat::default(), Mat::default(), Mat::default());
    core::sv_decomp(&m, &mut w, &mut u, &mut vt, 0)?;
    let (u, vt, w) = (mat3(&u)?, mat3(&vt)?, vec3(&w)?);
    let sign = if (u * vt).det() < 0.0 { -1.0 } else { 1.0 };
    let s = Mat3([[1.0, 0.0, 0.0], [0.0, 1.0, 0.0], [0.0, 0.0, sign]]);
    let rotation = u * s * vt;
    let scale = (w.x() + w.y() + sign * w.z()) / (var / n);
    if !(scale.is_finite() && scale > 0.0) {
        return Ok(None);
    }
    Ok(Some(Similarity {
        rotation,
        translation: ma - rotation * mb * scale,
        scale,
    }))
}

/// A matched 3-D pair: the earlier world's point, the later world's point, and the earlier
/// one's depth in the frame that saw it.
#[derive(Clone, Copy)]
struct Pair {
    a: Vec3,
    b: Vec3,
    z: f64,
}

/// The similarity most `pairs` agree with (RANSAC on three, then refitted on its inliers
/// twice), and its inliers.
fn fit_similarity(pairs: &[Pair]) -> Result<Option<(Similarity, usize)>> {
    let inliers = |s: &Similarity| -> Vec<usize> {
        (0..pairs.len())
            .filter(|&i| {
                let p = &pairs[i];
                (s.apply(p.b) - p.a).norm() <= TIE_TOLERANCE * p.z
            })
            .collect()
    };
    // A point's error grows with the square of its depth: weigh it by the inverse.
    let refit = |idx: &[usize]| -> Result<Option<Similarity>> {
        let sel: Vec<(Vec3, Vec3, f64)> = idx
            .iter()
            .map(|&i| (pairs[i].a, pairs[i].b, pairs[i].z.powi(-2)))
            .collect();
        umeyama(&sel)
    };
    if pairs.len() < TIE_MIN {
        return Ok(None);
    }
    // A fixed-seed generator: the same clip ties the same way every run.
    let mut seed = 0x9e37_79b9_7f4a_7c15u64;
    let mut next = |n: usize| {
        seed = seed
            .wrapping_mul(6_364_136_223_846_793_005)
            .wrapping_add(1_442_695_040_888_963_407);
        ((seed >> 33) % n as u64) as usize
    };
    let mut best: Vec<usize> = Vec::new();
    for _ in 0..TIE_SAMPLES {
        let idx = [next(pairs.len()), next(pairs.len()), next(pairs.len())];
        if idx[0] == idx[1] || idx[1] == idx[2] || idx[0] == idx[2] {
            continue;
        }
        if let Some(s) = refit(&idx)? {
            let inl = inliers(&s);
            if inl.len() > best.len() {
                best = inl;
            }
        }
    }
    let mut fit = None;
    for _ in 0..2 {
        if best.len() < TIE_MIN {
            return Ok(None);
        }
        let Some(s) = refit(&best)? else {
            return Ok(None);
        };
        best = inliers(&s);
        fit = Some(s);
    }
    Ok(fit
        .filter(|_| best.len() >= TIE_MIN)
        .map(|s| (s, best.len())))
}

/// Up to `n` of `v`, evenly spaced.
fn spread(v: &[usize], n: usize) -> Vec<usize> {
    if v.len() <= n {
        return v.to_vec();
    }
    (0..n).map(|i| v[i * v.len() / n]).collect()
}

/// Ties every segment after the first into an earlier segment's world where their map
/// points agree with one similarity (see the [module docs](self)): its poses are moved into
/// that world and [`Trajectory::world`] says so. Returns how many segments were tied.
pub(crate) fn tie_segments(
    t: &mut Trajectory,
    features: &[Features],
    min_angle_deg: f64,
) -> Result<usize> {
    let mut maps = Maps::new(t, features, min_angle_deg);
    let n = t.poses.len();
    let last = t.segment.iter().copied().max().unwrap_or(0);
    let mut tied = 0;
    for s in 1..=last {
        let placed = |f: usize| t.poses[f].is_some();
        let new: Vec<usize> = (0..n).filter(|&f| placed(f) && t.segment[f] == s).collect();
        let old: Vec<usize> = (0..n).filter(|&f| placed(f) && t.segment[f] < s).collect();
        // Matched pairs, by the earlier world.
        let mut pairs: HashMap<u32, Vec<Pair>> = HashMap::new();
        for &b in &spread(&new, TIE_FRAMES) {
            for &a in &spread(&old, TIE_FRAMES) {
                maps.get(t, a)?;
                maps.get(t, b)?;
                let (ma, mb) = (&maps.built[&a], &maps.built[&b]);
                let m = matches(&ma.desc, &mb.desc);
                if m.is_empty() {
                    continue;
                }
                let to_a = t.poses[a].expect("placed").inverse();
                let list = pairs.entry(t.world[a]).or_default();
                for (i, j) in m {
                    list.push(Pair {
                        a: ma.points[i],
                        b: mb.points[j],
                        z: to_a.view_to_ref(ma.points[i]).z(),
                    });
                }
            }
        }
        let mut worlds: Vec<(u32, Vec<Pair>)> = pairs.into_iter().collect();
        worlds.sort_by_key(|(w, p)| (std::cmp::Reverse(p.len()), *w));
        for (w, list) in worlds {
            if let Some((sim, _)) = fit_similarity(&list)? {
                for f in 0..n {
                    if t.segment[f] == s {
                        if let Some(p) = &mut t.poses[f] {
                            *p = sim.pose(p);
                            t.world[f] = w;
                        }
                    }
                }
                // The map points of the segment moved with it.
                for (&f, m) in maps.built.iter_mut() {
                    if t.segment[f] == s {
                        m.points.iter_mut().for_each(|x| *x = sim.apply(*x));
                    }
                }
                tied += 1;
                break;
            }
        }
    }
    Ok(tied)
}

/// A feature of an unplaced frame matched with a map point: the map point's frame, the
/// feature's position and the map point.
type Sighting = (usize, Point2f, Vec3);

/// Nearest placed frames whose map points an unplaced frame is matched with.
const PLACE_FROM: usize = 4;
/// Least PnP inliers that place a frame by relocalisation.
const PLACE_MIN: usize = 30;

/// Places the frames left unplaced, by PnP on the map points of the nearest placed frames
/// (see the [module docs](self)), nearest to a placed frame first. Returns how many were
/// placed.
pub(crate) fn place_frames(
    t: &mut Trajectory,
    features: &[Features],
    min_angle_deg: f64,
    max_turn_deg: f64,
) -> Result<usize> {
    let mut maps = Maps::new(t, features, min_angle_deg);
    let n = t.poses.len();
    let k = camera_matrix(&t.camera)?;
    let mut placed = 0;
    loop {
        let mut progress = false;
        for (f, ff) in features.iter().enumerate() {
            if t.poses[f].is_some() {
                continue;
            }
            let mut near: Vec<usize> = (0..n).filter(|&g| t.poses[g].is_some()).collect();
            near.sort_by_key(|&g| g.abs_diff(f));
            near.truncate(PLACE_FROM);
            // 2-D to 3-D matches by world, each feature of f once.
            let mut by_world: HashMap<u32, (Vec<bool>, Vec<Sighting>)> = HashMap::new();
            for &g in &near {
                let m = maps.get(t, g)?;
                let list = by_world
                    .entry(t.world[g])
                    .or_insert_with(|| (vec![false; ff.points.len()], Vec::new()));
                for (i, j) in matches(&ff.desc, &m.desc) {
                    if !list.0[i] {
                        list.0[i] = true;
                        list.1.push((g, ff.points[i], m.points[j]));
                    }
                }
            }
            let Some((w, (_, list))) = by_world.into_iter().max_by_key(|(w, l)| (l.1.len(), *w))
            else {
                continue;
            };
            if list.len() < PLACE_MIN {
                continue;
            }
            let obj: Vector<core::Point3f> = list
                .iter()
                .map(|(_, _, x)| core::Point3f::new(x.x() as f32, x.y() as f32, x.z() as f32))
                .collect();
            let img: Vector<Point2f> = list.iter().map(|l| l.1).collect();
            let Some((pose, inl)) = pnp(&k, &obj, &img, None, 300)? else {
                continue;
            };
            if inl.len() < PLACE_MIN {
                continue;
            }
            // No more turn to the nearest placed frame of the world than neighbouring frames
            // take.
            let turn_ok = near.iter().filter(|&&g| t.world[g] == w).all(|&g| {
                let q = t.poses[g].expect("placed");
                rotation_deg(&(q.rotation.transpose() * pose.rotation))
                    <= max_turn_deg * g.abs_diff(f) as f64
            });
            if !turn_ok {
                continue;
            }
            // The segment of the frame most inliers came from.
            let mut votes: HashMap<usize, usize> = HashMap::new();
            for i in inl.iter() {
                *votes.entry(list[i as usize].0).or_default() += 1;
            }
            let from = votes
                .into_iter()
                .max_by_key(|&(g, v)| (v, std::cmp::Reverse(g)))
                .map(|(g, _)| g)
                .expect("inliers");
            t.poses[f] = Some(pose);
            t.inliers[f] = inl.len();
            t.segment[f] = t.segment[from];
            t.world[f] = w;
            placed += 1;
            progress = true;
        }
        if !progress {
            return Ok(placed);
        }
    }
}
