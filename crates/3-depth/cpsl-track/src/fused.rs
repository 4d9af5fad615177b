//! Depth of a tracked clip's frames: multi-view depth from the nearest placed frames fused
//! with a monocular prior, in the prior's units, with a fallback to the prior (and why) where
//! the views cannot serve.

use crate::mvs::{self, MvsConfig, Neighbour, ViewDepth};
use crate::{CameraMotion, Mat, Result, TrackError, Trajectory};
use cpsl_core::Pose;
use opencv::prelude::*;
use rayon::prelude::*;
use std::collections::HashMap;

/// Where a frame's depth came from.
#[derive(Debug, Clone, PartialEq)]
pub enum DepthFrom {
    /// Fused: `share` of the pixels from `views` neighbouring frames, the rest from the
    /// prior fitted to them and bent to them, or, when the prior's depth order disagrees with
    /// the views' (`prior` false), spread from the views alone and unknown (NaN) far from
    /// them ([`mvs::fuse`]).
    Views {
        /// Share of pixels from the views.
        share: f64,
        /// Neighbouring frames used.
        views: usize,
        /// Whether the prior filled the pixels the views did not see.
        prior: bool,
    },
    /// The views were too seldom confident, so the depth of frame `from` (fused from its own
    /// views, in the same world) was carried here by the two frames' poses and fused with
    /// the prior like views: `share` of the pixels from it.
    Carried {
        /// The frame whose depth was carried.
        from: usize,
        /// Share of pixels from it.
        share: f64,
    },
    /// The prior (scaled to the clip), and why.
    Fallback(String),
}

/// Depth from a tracked clip: each frame asked for gets multi-view depth from up to
/// [`TrackedDepth::NEIGHBOURS`] placed frames around it, chosen by how wide an angle they see
/// the scene under ([`TrackedDepth::RUNG_DEG`]; [`mvs::depth_from_views`]; each
/// neighbour warped by the plane at the median depth of the frame fused last in its world
/// where that plane moves more than a shift, [`mvs::warped_flows`]), fused with
/// its monocular prior ([`mvs::fuse`]) at the tracking resolution and brought back to the
/// prior's. The clip is put in the prior's units: the scale of each world of the trajectory
/// (its first baseline is 1; segments tied into one world share it) is fixed by its first
/// fused frame's median per-pixel ratio of prior to fused depth (times the median
/// fused-to-prior ratio of the frames fused before, for a later world); only frames of the
/// same segment serve as views. Each fused frame is then averaged with the frame fused before
/// it, carried to it, where both are confident and agree within [`TrackedDepth::FILTER_AGREE`]
/// (a per-pixel inverse-depth filter over time; moving points disagree and keep their own
/// depth). A placed frame whose views are too seldom confident (at the end of a segment, or
/// after a jump) takes the depth of the nearest frame fused before it in its world, carried
/// to it by their poses ([`mvs::carry`]) and fused with its prior in the same way. A frame
/// the views cannot serve otherwise takes its prior, scaled by the median fused-to-prior
/// ratio of the frames fused so far, and says why: the camera does not translate (rotating, static,
/// untracked), the frame was not placed, or its views saw too little. The flows between two
/// frames serve both; they are kept until the frames asked for have passed them.
pub struct TrackedDepth {
    trajectory: Trajectory,
    greys: Vec<Mat>,
    /// Per world of the trajectory, prior units per trajectory unit, once one of its frames
    /// has been fused.
    scale: HashMap<u32, f64>,
    /// Fused-to-prior median ratios of the fused frames (prior units).
    ratios: Vec<f64>,
    /// Flows between frames (from, to), kept while a later frame may use them: each flow
    /// serves both frames of its pair.
    flows: HashMap<(usize, usize), Mat>,
    /// The last frames fused from their own views, with their depth (working resolution,
    /// trajectory units), for frames after them that the views cannot serve.
    recent: Vec<(usize, ViewDepth)>,
}

impl TrackedDepth {
    /// Most placed frames a frame's depth is triangulated from.
    pub const NEIGHBOURS: usize = 4;
    /// The rungs of median ray angle (degrees) a frame's neighbours are chosen by: on each
    /// side of the frame, the nearest frame reaching one rung, then the nearest beyond it
    /// reaching two, and so on.
    pub const RUNG_DEG: f64 = 1.5;
    /// Farthest (in frames) a neighbour is looked for.
    pub const REACH: usize = 15;
    /// Least confidence of a multi-view pixel kept over the prior.
    pub const MIN_CONFIDENCE: f32 = 0.5;
    /// Frames back the temporal filter reaches for an earlier fused frame.
    pub const FILTER_REACH: usize = 2;
    /// Largest disagreement of two inverse depths the temporal filter averages (a share):
    /// beyond it the point moved or one of them is wrong, and the frame keeps its own.
    /// Measured on the fox: the depth at pycolmap's points AbsRel 1.54 % (1.57 % without the
    /// filter; 10 % the same), its novel views' boundary variance 27.7 against 28.2 px^2.
    pub const FILTER_AGREE: f32 = 0.05;

    /// Depth for the clip solved as `trajectory`, whose frames' working grey images
    /// ([`crate::Tracker::grey`]) are `greys`, one per frame.
    pub fn new(trajectory: Trajectory, greys: Vec<Mat>) -> Result<Self> {
        let cam = trajectory.camera;
        if greys.len() != trajectory.poses.len() {
            return Err(TrackError::Input(format!(
                "{} grey frames for a trajectory of {}",
                greys.len(),
                trajectory.poses.len()
            )));
        }
        for g in &greys {
            let s = g.size()?;
            if (s.width as u32, s.height as u32) != (cam.width, cam.height) {
                return Err(TrackError::Input(format!(
                    "a {}x{} grey frame for tracking at {}x{}",
                    s.width, s.height, cam.width, cam.height
                )));
            }
        }
        Ok(Self {
            trajectory,
            greys,
            scale: HashMap::new(),
            ratios: Vec::new(),
            flows: HashMap::new(),
            recent: Vec::new(),
        })
    }

    /// Where frame `index`'s camera is in the units of its depth: its position in the
    /// trajectory's world times that world's scale, once a frame of the world has been fused
    /// (`None` before, and for unplaced frames).
    pub fn centre_in_depth_units(&self, index: usize) -> Option<cpsl_core::Vec3> {
        let t = &self.trajectory;
        let pose = t.poses.get(index).copied().flatten()?;
        let scale = self.scale.get(t.world.get(index)?)?;
        Some(pose.translation * *scale)
    }

    /// The trajectory the depth comes from.
    pub fn trajectory(&self) -> &Trajectory {
        &self.trajectory
    }

    /// How the camera moves and how many frames were placed.
    pub fn summary(&self) -> String {
        let t = &self.trajectory;
        let placed = t.poses.iter().filter(|p| p.is_some()).count();
        let (segments, worlds) = (t.segments(), t.worlds());
        format!(
            "camera {}, {placed} of {} frames placed{}",
            t.motion.name(),
            t.poses.len(),
            match (segments, worlds) {
                (1, _) => String::new(),
                (s, 1) => format!(" in {s} segments tied into one world"),
                (s, w) => format!(" in {s} segments, {w} worlds"),
            }
        )
    }

    /// Depth of frame `index`, whose picture is `rgb`, from its `prior` (both `width x
    /// height`; the prior in any scale, NaN where unknown), at that size.
    pub fn depth(
        &mut self,
        index: usize,
        rgb: &[u8],
        prior: &[f32],
        (width, height): (u32, u32),
    ) -> Result<(Vec<f32>, DepthFrom)> {
        let t = &self.trajectory;
        let work = t.camera;
        let size = (work.width, work.height);
        let why = match (t.motion, t.poses.get(index).copied().flatten()) {
            (CameraMotion::Translating, Some(pose)) => {
                // The plane the neighbours are warped by where it moves more than a shift,
                // and at whose depth they are chosen: the median depth of the frame fused
                // last in this world (the same units); for the first, the median depth of
                // its unwarped views from the nearest frames.
                let last = self
                    .recent
                    .iter()
                    .rev()
                    .find(|(j, _)| t.world[*j] == t.world[index])
                    .and_then(|(_, z)| mvs::median_depth(z));
                let plane = match last {
                    Some(p) => Some(p),
                    None => self.nearest_median_depth(index, &pose)?,
                };
                let t = &self.trajectory;
                let near = self.neighbours(index, &pose, plane);
                let poses: Vec<Pose> = near.iter().map(|&j| t.poses[j].expect("placed")).collect();
                let cfg = MvsConfig::default();
                let reference = (&self.greys[index], &pose);
                // The neighbours in parallel (OpenCV's DIS flow keeps two cores only partly busy).
                let warped = near
                    .par_iter()
                    .zip(&poses)
                    .map(|(&j, nb_pose)| match plane {
                        Some(p) => {
                            mvs::warped_flows(&work, reference, (&self.greys[j], nb_pose), p, &cfg)
                        }
                        None => Ok(None),
                    })
                    .collect::<Result<Vec<_>>>()?;
                let unwarped: Vec<usize> = near
                    .iter()
                    .zip(&warped)
                    .filter(|(_, w)| w.is_none())
                    .map(|(&j, _)| j)
                    .collect();
                Self::compute_flows(&self.greys, &mut self.flows, index, &unwarped)?;
                let nb: Vec<Neighbour> = near
                    .iter()
                    .zip(&poses)
                    .zip(&warped)
                    .map(|((&j, pose), w)| match w {
                        Some((forward, backward)) => Neighbour {
                            pose,
                            forward,
                            backward,
                            plane,
                        },
                        None => unwarped_neighbour(&self.flows, index, j, pose),
                    })
                    .collect();
                // Without a plane (the nearest frames' views saw too little for a median
                // depth) the unwarped views are all there is.
                let views = mvs::depth_from_flows(&work, &pose, &nb, &cfg)?;
                // Frames are mostly asked for in order: pairs below every neighbour of this
                // frame are seldom needed again.
                let low = near.iter().copied().min().unwrap_or(index).min(index);
                self.flows.retain(|&(a, b), _| a.max(b) >= low);
                let small = mvs::resize_depth(prior, (width, height), size)?;
                let guide = crate::work_rgb(rgb, width, height, size)?;
                let fused = mvs::fuse(&views, &small, &guide, Self::MIN_CONFIDENCE)?
                    .and_then(|(z, f)| Some((median_ratio(&small, &z.depth)?, z, f)));
                if let Some((ratio, mut z, fusion)) = fused {
                    self.filter(index, &pose, &mut z)?;
                    // A later world starts at the fused-to-prior ratio typical so far, not at
                    // its first frame's prior alone.
                    let typical = self.typical_ratio();
                    let scale = *self.scale.entry(t.world[index]).or_insert(ratio * typical);
                    self.ratios.push(scale / ratio);
                    let out = scaled(&z.depth, size, (width, height), scale)?;
                    self.recent.push((index, z));
                    if self.recent.len() > Self::NEIGHBOURS {
                        self.recent.remove(0);
                    }
                    let from = DepthFrom::Views {
                        share: fusion.from_views,
                        views: near.len(),
                        prior: fusion.prior.is_some(),
                    };
                    return Ok((out, from));
                }
                if let Some((from, z, share)) = self.carried(index, &pose, &small, &guide)? {
                    let scale = self.scale[&t.world[index]];
                    let out = scaled(&z, size, (width, height), scale)?;
                    return Ok((out, DepthFrom::Carried { from, share }));
                }
                if views.density() < 0.01 {
                    format!(
                        "the views saw too little ({:.1} % triangulated)",
                        100.0 * views.density()
                    )
                } else {
                    "the views were too seldom confident".to_string()
                }
            }
            (CameraMotion::Translating, None) => "the frame was not placed".to_string(),
            (CameraMotion::Rotating, _) => {
                "the camera only turns (no baseline to triangulate)".to_string()
            }
            (CameraMotion::Static, _) => "the camera is static".to_string(),
            (CameraMotion::Untracked, _) => "too little texture to track the camera".to_string(),
        };
        let k = self.typical_ratio() as f32;
        Ok((
            prior.iter().map(|v| v * k).collect(),
            DepthFrom::Fallback(why),
        ))
    }

    /// Depth of frame `index` (whose picture is `rgb` and monocular depth `prior`, both
    /// `width x height`) without views of its own: `from_depth`, the depth [`Self::depth`]
    /// gave frame `from` (same size and units), carried to it by the two frames' poses
    /// ([`mvs::carry`], at the working resolution), what it does not reach (disoccluded, or
    /// outside `from`'s view) taken from the prior fitted to it ([`mvs::fuse`]). The carried
    /// pixels count as confident. Tens of milliseconds against the hundreds of a multi-view
    /// pass: what a P-frame of a video gets, whose layers move with the picture. `None` when
    /// either frame is not placed, they lie in different worlds, the world has no scale yet
    /// (none of its frames fused) or too little lands.
    pub fn carry_depth(
        &self,
        from: usize,
        from_depth: &[f32],
        index: usize,
        rgb: &[u8],
        prior: &[f32],
        (width, height): (u32, u32),
    ) -> Result<Option<Vec<f32>>> {
        let t = &self.trajectory;
        let pose = |i: usize| t.poses.get(i).copied().flatten();
        let (Some(from_pose), Some(to_pose)) = (pose(from), pose(index)) else {
            return Ok(None);
        };
        if t.world[from] != t.world[index] {
            return Ok(None);
        }
        let Some(&scale) = self.scale.get(&t.world[index]) else {
            return Ok(None);
        };
        let size = (t.camera.width, t.camera.height);
        let mut z = mvs::resize_depth(from_depth, (width, height), size)?;
        z.iter_mut().for_each(|v| *v /= scale as f32);
        let confidence = z
            .iter()
            .map(|v| f32::from(u8::from(v.is_finite())))
            .collect();
        let depth = ViewDepth {
            width: size.0,
            height: size.1,
            depth: z,
            confidence,
            variance: Vec::new(),
        };
        let moved = mvs::carry(&t.camera, &from_pose, &depth, &to_pose)?;
        let small = mvs::resize_depth(prior, (width, height), size)?;
        let guide = crate::work_rgb(rgb, width, height, size)?;
        match mvs::fuse(&moved, &small, &guide, Self::MIN_CONFIDENCE)? {
            Some((z, _)) => Ok(Some(scaled(&z.depth, size, (width, height), scale)?)),
            None => Ok(None),
        }
    }

    /// The neighbours frame `index` (placed at `pose`) is triangulated from: up to
    /// [`Self::NEIGHBOURS`] placed frames of its segment, alternately before and after it.
    /// Once the world's depth is known (`plane`, the median depth of the frame fused last),
    /// each side is walked outwards, at most [`Self::REACH`] frames, and a frame is taken
    /// when its median ray angle at that depth ([`mvs::ray_angle`]) reaches the next rung of
    /// [`Self::RUNG_DEG`], twice it, and so on; where the camera moves too little for that,
    /// the side's farthest frames serve. Without a depth, the nearest frames.
    fn neighbours(&self, index: usize, pose: &Pose, plane: Option<f64>) -> Vec<usize> {
        let t = &self.trajectory;
        let usable = |j: &usize| t.poses[*j].is_some() && t.segment[*j] == t.segment[index];
        let mut near: Vec<usize> = (0..t.poses.len())
            .filter(|&j| j != index && usable(&j))
            .collect();
        near.sort_by_key(|&j| j.abs_diff(index));
        let Some(depth) = plane else {
            near.truncate(Self::NEIGHBOURS);
            return near;
        };
        let end = (index + Self::REACH).min(t.poses.len() - 1);
        let sides = [
            (index.saturating_sub(Self::REACH)..index)
                .rev()
                .filter(usable)
                .collect::<Vec<_>>(),
            (index + 1..=end).filter(usable).collect(),
        ];
        let [mut before, mut after] = sides.map(|side| {
            let mut picks = Vec::new();
            let mut rung = Self::RUNG_DEG;
            for &j in &side {
                if picks.len() == Self::NEIGHBOURS {
                    break;
                }
                let other = t.poses[j].expect("placed");
                if mvs::ray_angle(&t.camera, pose, &other, depth) >= rung {
                    picks.push(j);
                    rung += Self::RUNG_DEG;
                }
            }
            for &j in side.iter().rev() {
                if picks.len() >= Self::NEIGHBOURS / 2 {
                    break;
                }
                if !picks.contains(&j) {
                    picks.push(j);
                }
            }
            picks.into_iter()
        });
        let mut chosen = Vec::new();
        loop {
            match (before.next(), after.next()) {
                (None, None) => break,
                (b, a) => chosen.extend(b.into_iter().chain(a)),
            }
        }
        chosen.truncate(Self::NEIGHBOURS);
        // Near the clip's ends or gaps, the nearest frames make up the number.
        for j in near {
            if chosen.len() >= Self::NEIGHBOURS {
                break;
            }
            if !chosen.contains(&j) {
                chosen.push(j);
            }
        }
        chosen
    }

    /// The median depth of frame `index` (placed at `pose`) seen from its nearest frames
    /// through unwarped flows (kept for the frames after it): how far away the scene is
    /// before any frame of its world has been fused, to choose its neighbours by.
    fn nearest_median_depth(&mut self, index: usize, pose: &Pose) -> Result<Option<f64>> {
        let near = self.neighbours(index, pose, None);
        Self::compute_flows(&self.greys, &mut self.flows, index, &near)?;
        let t = &self.trajectory;
        let nb: Vec<Neighbour> = near
            .iter()
            .map(|&j| {
                unwarped_neighbour(&self.flows, index, j, t.poses[j].as_ref().expect("placed"))
            })
            .collect();
        let views = mvs::depth_from_flows(&t.camera, pose, &nb, &MvsConfig::default())?;
        Ok(mvs::median_depth(&views))
    }

    /// The flows between frame `index` and each of `others` (both ways) that `flows` does
    /// not hold yet: computed in parallel and kept there (eight flows at 480x270: 177 ms one
    /// after the other, 141 in parallel; `cargo bench -p cpsl-track --bench mvs`).
    fn compute_flows(
        greys: &[Mat],
        flows: &mut HashMap<(usize, usize), Mat>,
        index: usize,
        others: &[usize],
    ) -> Result<()> {
        let missing: Vec<(usize, usize)> = others
            .iter()
            .flat_map(|&j| [(index, j), (j, index)])
            .filter(|pair| !flows.contains_key(pair))
            .collect();
        let computed = missing
            .par_iter()
            .map(|&(a, b)| mvs::flow(&greys[a], &greys[b]))
            .collect::<Result<Vec<_>>>()?;
        flows.extend(missing.into_iter().zip(computed));
        Ok(())
    }

    /// The depth of the frame nearest to `index` among those fused from their own views in
    /// its world, carried to it and fused with its `small` prior (guided by `guide`): the
    /// frame, the fused depth (working resolution, trajectory units) and the share of pixels
    /// from the carried depth; `None` when no such frame is at hand or too little of it lands.
    fn carried(
        &self,
        index: usize,
        pose: &Pose,
        small: &[f32],
        guide: &Mat,
    ) -> Result<Option<(usize, Vec<f32>, f64)>> {
        let t = &self.trajectory;
        let Some((from, depth)) = self
            .recent
            .iter()
            .filter(|(j, _)| t.world[*j] == t.world[index])
            .min_by_key(|(j, _)| j.abs_diff(index))
        else {
            return Ok(None);
        };
        let moved = self.carry(*from, depth, pose)?;
        Ok(mvs::fuse(&moved, small, guide, Self::MIN_CONFIDENCE)?
            .map(|(z, f)| (*from, z.depth, f.from_views)))
    }

    /// Frame `index`'s fused depth `z` averaged, where both are confident and agree, with the
    /// depth of the frame fused before it (at most [`Self::FILTER_REACH`] frames back in its
    /// segment) carried to it ([`mvs::blend`]).
    fn filter(&self, index: usize, pose: &Pose, z: &mut ViewDepth) -> Result<()> {
        let t = &self.trajectory;
        let Some((from, depth)) = self.recent.iter().rev().find(|(j, _)| {
            t.segment[*j] == t.segment[index] && j.abs_diff(index) <= Self::FILTER_REACH
        }) else {
            return Ok(());
        };
        let moved = self.carry(*from, depth, pose)?;
        mvs::blend(z, &moved, Self::MIN_CONFIDENCE, Self::FILTER_AGREE);
        Ok(())
    }

    /// `depth`, that of frame `from` (one of [`TrackedDepth::recent`], so placed), carried to
    /// the frame at `pose` ([`mvs::carry`]).
    fn carry(&self, from: usize, depth: &ViewDepth, pose: &Pose) -> Result<ViewDepth> {
        let t = &self.trajectory;
        let from_pose = t.poses[from].expect("a frame fused from its views is placed");
        mvs::carry(&t.camera, &from_pose, depth, pose)
    }

    /// The median fused-to-prior ratio of the frames fused so far (1 before the first).
    fn typical_ratio(&self) -> f64 {
        if self.ratios.is_empty() {
            return 1.0;
        }
        crate::median(&mut self.ratios.clone())
    }
}

/// Neighbour `j` of frame `index`, at `pose`, by its kept unwarped flows
/// ([`TrackedDepth::compute_flows`]).
fn unwarped_neighbour<'a>(
    flows: &'a HashMap<(usize, usize), Mat>,
    index: usize,
    j: usize,
    pose: &'a Pose,
) -> Neighbour<'a> {
    Neighbour {
        pose,
        forward: &flows[&(index, j)],
        backward: &flows[&(j, index)],
        plane: None,
    }
}

/// Depth `z` at working size `size` brought to `to` and multiplied by `scale`.
fn scaled(z: &[f32], size: (u32, u32), to: (u32, u32), scale: f64) -> Result<Vec<f32>> {
    let mut z = mvs::resize_depth(z, size, to)?;
    z.iter_mut().for_each(|v| *v *= scale as f32);
    Ok(z)
}

/// Median over the pixels of `a / b` (both finite and positive).
fn median_ratio(a: &[f32], b: &[f32]) -> Option<f64> {
    let mut r: Vec<f64> = a
        .iter()
        .zip(b)
        .filter(|(x, y)| x.is_finite() && y.is_finite() && **x > 0.0 && **y > 0.0)
        .map(|(x, y)| (x / y) as f64)
        .collect();
    if r.is_empty() {
        return None;
    }
    let m = r.len() / 2;
    Some(*r.select_nth_unstable_by(m, f64::total_cmp).1)
}
