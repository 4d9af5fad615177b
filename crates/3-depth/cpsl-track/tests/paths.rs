//! Tracking on ray-cast clips with exact poses (the built-in scene, objects held still):
//! sideways and orbiting cameras are solved (sideways within 0.1 degrees of rotation and 1
//! degree of translation direction); a static camera and a pure rotation are told apart; a
//! black clip is untracked, without a panic; after a cut the clip is solved again as a new
//! segment, also after a blank frame, and relocalisation does not tie another scene to the
//! first. Multi-view depth on the sideways clip with exact poses matches the exact depth,
//! alone and fused with a prior (exact, or bent and blurred as a network's), and is measured
//! on the orbit and walking forward; objects that
//! move on their own take the prior; and fused over a tracked clip it is in the prior's
//! units.

use cpsl_core::{Camera, Pose, Vec3};
use cpsl_synth::{Scene, Texture};
use cpsl_track::mvs::{carry, depth_from_views, fuse, MvsConfig, ViewDepth};
use cpsl_track::{
    rotation_deg, work_grey, work_rgb, CameraMotion, DepthFrom, TrackConfig, TrackedDepth, Tracker,
    Trajectory,
};
use opencv::core::{Mat, Size};
use opencv::imgproc;
use opencv::prelude::*;

const W: u32 = 320;
const H: u32 = 240;

fn clip(poses: &[Pose]) -> (Scene, Vec<Vec<u8>>) {
    clip_sized(poses, W, H)
}

fn clip_sized(poses: &[Pose], width: u32, height: u32) -> (Scene, Vec<Vec<u8>>) {
    let scene = Scene::default_scene(width, height);
    let frames = poses
        .iter()
        .map(|p| scene.render(&scene.camera, p, 0.0, 1).rgb)
        .collect();
    (scene, frames)
}

fn track(cam: Camera, frames: &[Vec<u8>]) -> Trajectory {
    track_with(cam, frames, TrackConfig::default())
}

fn track_with(cam: Camera, frames: &[Vec<u8>], cfg: TrackConfig) -> Trajectory {
    let mut t = Tracker::new(cam, cfg).unwrap();
    for f in frames {
        t.push(f, cam.width, cam.height).unwrap();
    }
    t.finish().unwrap()
}

/// The trajectory of `frames` and their working grey images, for [`TrackedDepth`].
fn track_keeping_greys(cam: Camera, frames: &[Vec<u8>]) -> (Trajectory, Vec<Mat>) {
    let mut t = Tracker::new(cam, TrackConfig::default()).unwrap();
    let mut greys = Vec::new();
    for f in frames {
        let g = t.grey(f, cam.width, cam.height).unwrap();
        greys.push(g.clone());
        t.push_grey(g).unwrap();
    }
    (t.finish().unwrap(), greys)
}

/// The ratios `z / prior` where both are known, in increasing order.
fn sorted_ratios(z: &[f32], prior: &[f32]) -> Vec<f64> {
    let mut rel: Vec<f64> = z
        .iter()
        .zip(prior)
        .filter(|(z, p)| z.is_finite() && p.is_finite())
        .map(|(z, p)| (z / p) as f64)
        .collect();
    rel.sort_by(f64::total_cmp);
    rel
}

/// Median rotation error and translation-direction error (degrees) against `truth`
/// (camera-to-world with frame 0 at the origin).
fn errors(est: &Trajectory, truth: &[Pose]) -> (f64, f64, usize) {
    let (mut rot, mut dir, mut placed) = (vec![], vec![], 0);
    for (p, g) in est.poses.iter().zip(truth) {
        let Some(p) = p else { continue };
        placed += 1;
        rot.push(rotation_deg(&(p.rotation.transpose() * g.rotation)));
        if g.translation.norm() > 1e-6 {
            let c = p.translation.normalized().dot(g.translation.normalized());
            dir.push(c.clamp(-1.0, 1.0).acos().to_degrees());
        }
    }
    let med = |mut v: Vec<f64>| {
        v.sort_by(f64::total_cmp);
        v[v.len() / 2]
    };
    (med(rot), med(dir), placed)
}

fn sideways() -> Vec<Pose> {
    sideways_of(12)
}

/// `n` frames moving right, 0.05 a frame.
fn sideways_of(n: usize) -> Vec<Pose> {
    (0..n)
        .map(|i| Pose::from_translation(Vec3::new(0.05 * i as f64, 0.0, 0.0)))
        .collect()
}

/// Around a point 4 units ahead: turn left while moving right, 1.5 degrees a frame.
fn orbit() -> Vec<Pose> {
    orbit_of(12)
}

/// [`orbit`] over `n` frames.
fn orbit_of(n: usize) -> Vec<Pose> {
    Scene::orbit_path(n, 1.5, 4.0)
}

/// The clip along `path` at the size frames are tracked at (480x270), frame 6's depth from
/// frames 2, 4, 8 and 10 with exact poses (the dense triangulation alone), its exact depth
/// and the camera.
fn views_of_frame_6(path: &[Pose]) -> (Vec<Vec<u8>>, ViewDepth, Vec<f32>, Camera) {
    views_of_frame_6_with(path, &MvsConfig::default())
}

/// [`views_of_frame_6`] with the multi-view settings `cfg`.
fn views_of_frame_6_with(
    path: &[Pose],
    cfg: &MvsConfig,
) -> (Vec<Vec<u8>>, ViewDepth, Vec<f32>, Camera) {
    let (w, h) = (480, 270);
    let (scene, frames) = clip_sized(path, w, h);
    let cam = scene.camera;
    let grey: Vec<_> = frames
        .iter()
        .map(|f| work_grey(f, w, h, (w, h)).unwrap())
        .collect();
    let nb: Vec<_> = [2usize, 4, 8, 10]
        .iter()
        .map(|&j| (&grey[j], &path[j]))
        .collect();
    let d = depth_from_views(&cam, (&grey[6], &path[6]), &nb, cfg).unwrap();
    let truth = scene.render(&cam, &path[6], 0.0, 1).depth;
    (frames, d, truth, cam)
}

#[test]
fn sideways_and_orbit_are_solved() {
    let orbit = orbit();
    // Limits: (rotation, translation direction) in degrees. With the bundle adjustment,
    // sideways measures 0.037 / 0.21 and the orbit 0.105 / 0.23 (before it: 0.02 / 0.24 and
    // 0.69 / 1.11; the orbit's scene is dominated by one wall, which leaves the first
    // baseline's rotation and translation poorly separated).
    for (name, path, limits) in [
        ("sideways", sideways(), (0.1, 1.0)),
        ("orbit", orbit.clone(), (0.2, 0.5)),
    ] {
        let (scene, frames) = clip(&path);
        let est = track(scene.camera, &frames);
        assert_eq!(est.motion, CameraMotion::Translating, "{name}");
        let (rot, dir, placed) = errors(&est, &path);
        eprintln!("{name}: rotation {rot:.3} deg, translation direction {dir:.3} deg, reprojection {:.3} px", est.reprojection_px);
        assert_eq!(placed, path.len(), "{name}: every frame placed");
        assert!(rot < limits.0, "{name}: rotation error {rot} deg");
        assert!(
            dir < limits.1,
            "{name}: translation direction error {dir} deg"
        );
        assert!(est.reprojection_px < 0.5, "{name}: {}", est.reprojection_px);
    }
    // Bundle adjustment in overlapping windows of five frames (as on clips longer than the
    // window), each held to the frames before it: measured 0.28 / 0.31, between no bundle
    // adjustment and one over the whole clip.
    let cfg = TrackConfig {
        ba_window: 5,
        ..TrackConfig::default()
    };
    let (scene, frames) = clip(&orbit);
    let (rot, dir, placed) = errors(&track_with(scene.camera, &frames, cfg), &orbit);
    eprintln!("orbit, windows of 5: rotation {rot:.3} deg, translation direction {dir:.3} deg");
    assert_eq!(placed, orbit.len());
    assert!(rot < 0.4 && dir < 0.5, "{rot} {dir}");
}

#[test]
fn a_cut_starts_a_new_segment() {
    // Eight frames sideways, a cut, then the same motion in the same geometry painted
    // otherwise, which no track crosses and no descriptor matches.
    let path = &sideways()[..8];
    let (scene, mut frames) = clip(path);
    let mut other = scene.clone();
    for (i, o) in other.objects.iter_mut().enumerate() {
        o.texture = Texture::Noise {
            a: [30, 60, 20],
            b: [220, 200, 240],
            scale: 0.15,
            seed: 1000 + i as u32,
        };
    }
    frames.extend(
        path.iter()
            .map(|p| other.render(&other.camera, p, 0.0, 1).rgb),
    );
    let est = track(scene.camera, &frames);
    assert_eq!(est.motion, CameraMotion::Translating);
    assert_eq!(est.segments(), 2);
    // Nothing ties the other scene to the first: two worlds.
    assert_eq!(est.worlds(), 2);
    for (f, p) in est.poses.iter().enumerate() {
        assert!(p.is_some(), "frame {f} placed");
        assert_eq!(est.segment[f], (f >= 8) as u32, "frame {f}");
        assert_eq!(est.world[f], est.segment[f], "frame {f}");
    }
    // Each segment's world is its first frame's camera.
    let (rot, dir, _) = errors(&est, path);
    assert!(rot < 0.1 && dir < 1.0, "first segment: {rot} {dir}");
    let mut second = est.clone();
    second.poses = est.poses[8..].to_vec();
    let (rot, dir, _) = errors(&second, path);
    eprintln!("after the cut: rotation {rot:.3} deg, translation direction {dir:.3} deg");
    assert!(rot < 0.1 && dir < 1.0, "second segment: {rot} {dir}");
}

#[test]
fn frames_after_a_blank_frame_are_placed() {
    // Sixteen frames sideways with frame 8 black (a corrupt frame, or a fade): no track
    // crosses it and no segment can start at it, so the next frame starts one, which
    // relocalisation may tie to the first (not measured here: on this scene's repeated
    // textures and 1-degree rays, its map points do not pin the scale to 1 %).
    let path: Vec<Pose> = (0..16)
        .map(|i| Pose::from_translation(Vec3::new(0.1 * i as f64, 0.0, 0.0)))
        .collect();
    let (scene, mut frames) = clip(&path);
    frames[8].iter_mut().for_each(|v| *v = 0);
    let est = track(scene.camera, &frames);
    for (f, p) in est.poses.iter().enumerate() {
        assert_eq!(p.is_some(), f != 8, "frame {f}");
    }
    assert_eq!(est.segments(), 2);
    for f in 9..16 {
        assert_eq!(est.segment[f], 1, "frame {f}");
    }
}

#[test]
fn static_rotation_and_black_are_detected() {
    let still = vec![Pose::IDENTITY; 8];
    let (scene, frames) = clip(&still);
    assert_eq!(track(scene.camera, &frames).motion, CameraMotion::Static);
    let turn: Vec<Pose> = (0..10)
        .map(|i| Pose::from_euler_deg(Vec3::ZERO, 0.0, 1.0 * i as f64, 0.0))
        .collect();
    let (scene, frames) = clip(&turn);
    let est = track(scene.camera, &frames);
    assert_eq!(est.motion, CameraMotion::Rotating);
    assert!(est.poses.iter().all(|p| p.is_none()));
    let black = vec![vec![0u8; (W * H * 3) as usize]; 4];
    assert_eq!(track(scene.camera, &black).motion, CameraMotion::Untracked);
    // Two frames, or one: no panic, nothing placed.
    assert!(track(scene.camera, &frames[..1])
        .poses
        .iter()
        .all(|p| p.is_none()));
    // A frame of the wrong size is an error.
    let mut t = Tracker::new(scene.camera, TrackConfig::default()).unwrap();
    assert!(t.push(&frames[0][3..], W, H).is_err());
}

#[test]
fn multi_view_depth_matches_the_scene() {
    // At the size frames are tracked at, exact poses: the dense triangulation alone.
    let (frames, d, truth, cam) = views_of_frame_6(&sideways());
    let (w, h, i) = (cam.width, cam.height, 6);
    let (confident, abs_rel, median) = score(&d, &truth, 0.5);
    eprintln!(
        "views: {:.0} % triangulated, {:.0} % confident, AbsRel {abs_rel:.4}, median {median:.4}",
        100.0 * d.density(),
        100.0 * confident
    );
    // Measured: 98 % triangulated, 68 % confident, AbsRel 0.78 %, median 0.29 % (0.93 % and
    // 0.44 % with the median of the neighbours' depths instead of their mean weighted by the
    // ray angle squared; before 2026-11-27, DIS's medium preset at half resolution, 1 degree,
    // no band around depth jumps, at 320x240: 59 % at 4.3 %).
    assert!(d.density() > 0.9, "density {}", d.density());
    assert!(confident > 0.6, "confident share {confident}");
    assert!(median < 0.008, "median relative error {median}");
    assert!(abs_rel < 0.015, "AbsRel {abs_rel}");

    // Fused with a prior: the exact depth in other units, and one as a monocular network
    // gives it (inverse depth to the power 0.6, blurred over 8 pixels, other units).
    // Measured: AbsRel over every pixel 0.61 % and 3.05 %, over the 90 % most confident
    // 0.55 % and 0.84 % (0.81 %, 3.14 %, 0.78 % and 0.94 % before the confident views were
    // weighed against their surroundings by variance; issue 29: at most 2 % over at least 90 %; 1.56 %, 2.83 %, 1.27 % and
    // 1.41 % before the fusion dropped the views' outliers against the fitted prior; 0.97 %,
    // 3.02 %, 0.92 % and 1.12 % before the prior was mapped by a curve and the neighbours'
    // depths weighted by their ray angles).
    let exact: Vec<f32> = truth.iter().map(|z| 3.0 * z).collect();
    let blurred = network_like(&truth, w, h);
    let guide = work_rgb(&frames[i], w, h, (w, h)).unwrap();
    for (name, prior, limits) in [
        ("exact", exact, (0.012, 0.011)),
        ("blurred", blurred, (0.035, 0.018)),
    ] {
        let (f, _) = fuse(&d, &prior, &guide, 0.5).unwrap().unwrap();
        let (all, abs_all, _) = score(&f, &truth, -1.0);
        let (_, abs_90, _) = score_best(&f, &truth, 0.9);
        eprintln!("fused with the {name} prior: AbsRel {abs_all:.4} over {:.0} %, {abs_90:.4} over the 90 % most confident", 100.0 * all);
        assert!(all > 0.999, "{name}: {all}");
        assert!(abs_all < limits.0, "{name}: AbsRel {abs_all}");
        assert!(abs_90 < limits.1, "{name}: AbsRel {abs_90} over 90 %");
    }
}

#[test]
fn moving_objects_take_the_prior_bent_to_their_surroundings() {
    // Sideways with the board moving along with the camera (it would look infinitely far)
    // and the disc
    // moving up, across the epipolar lines; the prior is the exact depth in other units.
    let (w, h) = (480, 270);
    let path = sideways();
    let scene = Scene::default_scene(w, h);
    let views: Vec<_> = path
        .iter()
        .enumerate()
        .map(|(i, p)| scene.render(&scene.camera, p, 0.2 * i as f64, 1))
        .collect();
    let grey: Vec<_> = views
        .iter()
        .map(|v| work_grey(&v.rgb, w, h, (w, h)).unwrap())
        .collect();
    let i = 6;
    let (truth, object) = (&views[i].depth, &views[i].object);
    let prior: Vec<f32> = truth.iter().map(|z| 3.0 * z).collect();
    let guide = work_rgb(&views[i].rgb, w, h, (w, h)).unwrap();
    let nb: Vec<_> = [2usize, 4, 8, 10]
        .iter()
        .map(|&j| (&grey[j], &path[j]))
        .collect();
    let id = |name: &str| scene.objects.iter().position(|o| o.name == name).unwrap() as u16;
    let (board, disc) = (id("board"), id("disc"));
    let errors = |cfg: MvsConfig| {
        let d = depth_from_views(&scene.camera, (&grey[i], &path[i]), &nb, &cfg).unwrap();
        let (f, _) = fuse(&d, &prior, &guide, 0.5).unwrap().unwrap();
        let abs_rel = |keep: &dyn Fn(u16) -> bool| {
            let r: Vec<f64> = (0..truth.len())
                .filter(|&k| keep(object[k]) && f.depth[k].is_finite())
                .map(|k| ((f.depth[k] - truth[k]) / truth[k]).abs() as f64)
                .collect();
            r.iter().sum::<f64>() / r.len() as f64
        };
        [
            abs_rel(&|o| o != board && o != disc),
            abs_rel(&|o| o == board),
            abs_rel(&|o| o == disc),
        ]
    };
    let [still, b, d] = errors(MvsConfig::default());
    eprintln!("AbsRel: static {still:.4}, board {b:.4}, disc {d:.4}");
    // Measured: 3.2 %, 0.3 %, 0.03 %; without the epipolar check (the board's and the
    // disc's motion taken for parallax) 4.8 %, 37 % and more.
    assert!(still < 0.04 && b < 0.01 && d < 0.01, "{still} {b} {d}");
    let [_, b, _] = errors(MvsConfig {
        max_epipolar: f64::INFINITY,
        ..MvsConfig::default()
    });
    assert!(b > 0.1, "without the check: {b}");
}

/// Share of the pixels with a depth and a confidence above `min_conf`, their AbsRel and
/// median relative error against `truth`.
fn score(d: &ViewDepth, truth: &[f32], min_conf: f32) -> (f64, f64, f64) {
    let mut rel: Vec<f64> = d
        .depth
        .iter()
        .zip(&d.confidence)
        .zip(truth)
        .filter(|((z, &c), t)| z.is_finite() && c > min_conf && t.is_finite())
        .map(|((z, _), t)| ((z - t) / t).abs() as f64)
        .collect();
    let share = rel.len() as f64 / truth.len() as f64;
    rel.sort_by(f64::total_cmp);
    let abs_rel = rel.iter().sum::<f64>() / rel.len().max(1) as f64;
    (
        share,
        abs_rel,
        rel.get(rel.len() / 2).copied().unwrap_or(f64::NAN),
    )
}

/// AbsRel over the `share` of the pixels with the highest confidence (unknown ones last).
fn score_best(d: &ViewDepth, truth: &[f32], share: f64) -> (f64, f64, f64) {
    let mut order: Vec<usize> = (0..truth.len()).collect();
    let key = |k: usize| {
        if d.depth[k].is_finite() {
            d.confidence[k]
        } else {
            -1.0
        }
    };
    order.sort_by(|&a, &b| key(b).total_cmp(&key(a)));
    order.truncate((share * truth.len() as f64) as usize);
    let best = ViewDepth {
        width: d.width,
        height: d.height,
        depth: order.iter().map(|&k| d.depth[k]).collect(),
        confidence: order.iter().map(|&k| d.confidence[k]).collect(),
        variance: Vec::new(),
    };
    let t: Vec<f32> = order.iter().map(|&k| truth[k]).collect();
    let (s, a, m) = score(&best, &t, -1.0);
    (s * share, a, m)
}

#[test]
fn tracked_depth_fuses_views_with_the_prior_in_its_units() {
    // Sideways and around a point: every frame fused; the prior (three times the exact depth)
    // sets the units. On the orbit the neighbours are warped by the median plane of the
    // frame fused before (its keystone is several pixels).
    for (name, path) in [("sideways", sideways()), ("orbit", orbit())] {
        let (scene, frames) = clip(&path);
        let cam = scene.camera;
        let (est, greys) = track_keeping_greys(cam, &frames);
        assert!(TrackedDepth::new(est.clone(), greys[1..].to_vec()).is_err());
        let mut tracked = TrackedDepth::new(est, greys).unwrap();
        let (mut ratios, mut offs) = (Vec::new(), Vec::new());
        for (i, p) in path.iter().enumerate() {
            let truth = scene.render(&cam, p, 0.0, 1).depth;
            let prior: Vec<f32> = truth.iter().map(|z| 3.0 * z).collect();
            let (z, from) = tracked.depth(i, &frames[i], &prior, (W, H)).unwrap();
            assert!(
                matches!(from, DepthFrom::Views { share, .. } if share > 0.3),
                "{name}, frame {i}: {from:?}"
            );
            let rel = sorted_ratios(&z, &prior);
            ratios.push(rel[rel.len() / 2]);
            let off = rel.iter().filter(|r| (*r - 1.0).abs() > 0.05).count();
            offs.push(off as f64 / rel.len() as f64);
        }
        // Measured 2026-11-28: per-frame median ratios sideways 0.993-1.002, orbit
        // 0.992-1.000; 1.6-6.0 % (median 4.4 %) and 2.3-6.4 % (median 3.9 %) of pixels off
        // by more than 5 % (sideways before the flow at full resolution, the band around
        // depth jumps and the edge-aware spread of the views: 0.978-1.026 and 2-43 %, median
        // 4 %; 0.985-1.007 and 3.5-10.6 %, median 7 %, before the prior was mapped by a curve
        // and the views weighed by variance).
        offs.sort_by(f64::total_cmp);
        eprintln!("{name}: median ratios {ratios:.3?}, shares more than 5 % off {offs:.3?}");
        assert!(
            ratios.iter().all(|r| (r - 1.0).abs() < 0.02),
            "{name}: {ratios:?}"
        );
        assert!(offs[offs.len() - 1] < 0.1, "{name}: {offs:?}");
        assert!(offs[offs.len() / 2] < 0.06, "{name}: {offs:?}");
    }

    // A static camera: every frame takes its prior as it is, and says why.
    let still = vec![Pose::IDENTITY; 6];
    let (scene, frames) = clip(&still);
    let cam = scene.camera;
    let mut t = Tracker::new(cam, TrackConfig::default()).unwrap();
    let greys: Vec<_> = frames.iter().map(|f| t.grey(f, W, H).unwrap()).collect();
    for g in &greys {
        t.push_grey(g.clone()).unwrap();
    }
    let mut tracked = TrackedDepth::new(t.finish().unwrap(), greys).unwrap();
    let prior = scene.render(&cam, &still[0], 0.0, 1).depth;
    let (z, from) = tracked.depth(2, &frames[2], &prior, (W, H)).unwrap();
    assert_eq!(from, DepthFrom::Fallback("the camera is static".into()));
    assert_eq!(z, prior);
}

#[test]
fn p_frames_carry_the_fused_depth_by_the_poses() {
    // On the orbit, frame 0 fused from its views; the frames after it (as P-frames of a
    // video) take that depth carried by the tracked poses, the rest from their prior
    // (three times the exact depth) fitted to it.
    let path = orbit();
    let (scene, frames) = clip(&path);
    let cam = scene.camera;
    let (est, greys) = track_keeping_greys(cam, &frames);
    let mut tracked = TrackedDepth::new(est, greys).unwrap();
    let prior_of = |p: &Pose| -> Vec<f32> {
        let truth = scene.render(&cam, p, 0.0, 1).depth;
        truth.iter().map(|z| 3.0 * z).collect()
    };
    let prior = prior_of(&path[0]);
    // Before any frame of the world is fused there are no units to carry in.
    let none = tracked.carry_depth(0, &prior, 3, &frames[3], &prior, (W, H));
    assert!(none.unwrap().is_none());
    let (z0, _) = tracked.depth(0, &frames[0], &prior, (W, H)).unwrap();
    let mut offs = Vec::new();
    for (i, p) in path.iter().enumerate().skip(1) {
        let prior = prior_of(p);
        let z = tracked
            .carry_depth(0, &z0, i, &frames[i], &prior, (W, H))
            .unwrap()
            .expect("placed in the same world");
        let rel = sorted_ratios(&z, &prior);
        assert!(rel.len() as f64 > 0.99 * z.len() as f64, "frame {i}");
        let median = rel[rel.len() / 2];
        let off = rel.iter().filter(|r| (*r - 1.0).abs() > 0.05).count();
        offs.push((median, off as f64 / rel.len() as f64));
    }
    // Measured 2026-11-29: median ratios 0.999-1.002, 5.1-6.4 % of pixels off by more than
    // 5 % (frame 0's own fused depth on the orbit: 2.3-6.4 % for the frames fused from their
    // views, test above).
    eprintln!("carried from frame 0: (median ratio, share more than 5 % off) {offs:.3?}");
    assert!(offs.iter().all(|(m, _)| (m - 1.0).abs() < 0.02), "{offs:?}");
    assert!(offs.iter().all(|(_, o)| *o < 0.15), "{offs:?}");
    // A depth map of the wrong size is an error, not a panic.
    assert!(tracked
        .carry_depth(0, &z0[1..], 2, &frames[2], &prior, (W, H))
        .is_err());
}

#[test]
fn carried_depth_is_the_scene_seen_from_the_other_pose() {
    // Depth rendered at one pose, carried to another (moved and turned), against the depth
    // rendered there.
    let (a, b) = (
        Pose::IDENTITY,
        Pose {
            rotation: Pose::from_euler_deg(Vec3::ZERO, 1.0, -3.0, 0.5).rotation,
            translation: Vec3::new(0.15, -0.03, 0.1),
        },
    );
    let scene = Scene::default_scene(W, H);
    let cam = scene.camera;
    let depth = |p: &Pose| scene.render(&cam, p, 0.0, 1).depth;
    let from = ViewDepth {
        width: W,
        height: H,
        depth: depth(&a),
        confidence: vec![0.8; (W * H) as usize],
        variance: Vec::new(),
    };
    let moved = carry(&cam, &a, &from, &b).unwrap();
    let truth = depth(&b);
    let mut rel: Vec<f64> = moved
        .depth
        .iter()
        .zip(&truth)
        .filter(|(z, _)| z.is_finite())
        .map(|(z, t)| ((z - t) / t).abs() as f64)
        .collect();
    let covered = rel.len() as f64 / truth.len() as f64;
    rel.sort_by(f64::total_cmp);
    let within = rel.iter().filter(|&&r| r < 0.01).count() as f64 / rel.len() as f64;
    // Measured: 86 % of the pixels reached (the rest outside the first view, or behind
    // nearer surfaces there), 99.5 % of those within 1 %.
    eprintln!("covered {covered:.3}, within 1 % {within:.3}");
    assert!(covered > 0.8, "{covered}");
    assert!(within > 0.98, "{within}");
    assert!(moved
        .confidence
        .iter()
        .zip(&moved.depth)
        .all(|(c, z)| if z.is_finite() { *c == 0.8 } else { *c == 0.0 }));
}

#[test]
fn frames_the_views_cannot_serve_take_a_neighbours_depth() {
    // Sideways, then still for longer than a neighbour is looked for: the first still frames
    // still reach moving ones under enough angle; the last see nothing but frames that stand
    // where they stand, and take the depth of the last frame fused from its views.
    let mut path = sideways()[..8].to_vec();
    path.extend(std::iter::repeat_n(path[7], TrackedDepth::REACH + 3));
    let (scene, frames) = clip(&path);
    let cam = scene.camera;
    let (est, greys) = track_keeping_greys(cam, &frames);
    assert_eq!(est.motion, CameraMotion::Translating);
    let mut tracked = TrackedDepth::new(est, greys).unwrap();
    let (mut ratios, mut fused, mut carried) = (Vec::new(), Vec::new(), Vec::new());
    for (i, p) in path.iter().enumerate() {
        let truth = scene.render(&cam, p, 0.0, 1).depth;
        let prior: Vec<f32> = truth.iter().map(|z| 3.0 * z).collect();
        let (z, from) = tracked.depth(i, &frames[i], &prior, (W, H)).unwrap();
        let rel = sorted_ratios(&z, &prior);
        ratios.push(rel[rel.len() / 2]);
        match from {
            DepthFrom::Views { .. } => fused.push(i),
            DepthFrom::Carried { from, share } => carried.push((i, from, share)),
            DepthFrom::Fallback(why) => panic!("frame {i}: {why}"),
        }
    }
    // Measured 2026-11-29: frames 0-20 (moving, and the still ones whose neighbours, chosen
    // by ray angle, reach back to moving frames) fused from their views, median ratios
    // 0.990-1.005; frames 21-25 carried from frame 20, within 0.9 % of its ratio (fused with
    // the prior again, which fills what the carried depth does not reach). With the nearest
    // frames as neighbours every still frame was carried (within 0.6 %).
    eprintln!("median ratios {ratios:.4?}, fused {fused:?}, carried {carried:?}");
    assert!(ratios.iter().all(|r| (r - 1.0).abs() < 0.05), "{ratios:?}");
    assert!(fused.starts_with(&[0, 1, 2, 3, 4, 5, 6, 7, 8]), "{fused:?}");
    assert!(carried.len() >= 3, "{carried:?}");
    let last = path.len() - 1;
    assert!(carried.iter().any(|c| c.0 == last), "{carried:?}");
    for &(i, from, share) in &carried {
        assert!(from >= 7 && from < i && share > 0.2, "{carried:?}");
        assert!((ratios[i] / ratios[from] - 1.0).abs() < 0.01, "{ratios:?}");
    }
}

#[test]
fn multi_view_depth_on_the_orbit_and_forward_paths() {
    // As `multi_view_depth_matches_the_scene` (frame 6 from frames 2, 4, 8 and 10, exact
    // poses, 480x270) on the orbit of `sideways_and_orbit_are_solved` and a camera walking
    // forward. Limits: (views alone over the confident pixels; fused with the exact prior over
    // every pixel and over the 90 % most confident; the same with the blurred prior). Measured
    // 2026-11-28, the neighbours warped by the median plane before the flow where it moves
    // more than a shift (both paths, every neighbour): orbit 0.94 %; 0.45 %, 0.49 %; 5.6 %,
    // 4.75 %. Forward 0.92 %; 1.39 %, 1.50 %; 8.3 %, 8.15 % (the blurred prior's remainder is
    // its own shape around the focus of expansion, where the rays meet at too small an angle).
    // Before the warp: orbit 0.89 %; 0.52 %, 0.56 %; 5.6 %, 5.0 %; forward 1.60 %; 2.20 %,
    // 2.31 %; 8.2 %, 7.8 % (DIS's patches, which assume a shift, match off under the zoom of
    // forward motion, and the prior's fit inherited the bias). Before the prior was mapped by
    // a curve: orbit with the blurred prior 9.9 %, 8.4 % (the views see little of the brick
    // wall, which takes the mapped prior). Before the confident views were weighed against
    // their surroundings by variance: orbit 0.59 %, 0.64 %; forward 2.27 %, 2.39 %. Before the
    // neighbours' depths were weighted by their ray angles: orbit 0.98 %; 0.67 %, 0.73 %;
    // forward 1.79 %; 2.96 %, 3.06 %; 8.4 %, 8.0 %. Before the fusion dropped the views'
    // outliers against the fitted prior, the orbit fused to 12.8 % (exact prior) and 14.2 %
    // (blurred), forward to 4.1 %: the orbit's brick wall is confident only where the flow
    // fattened the objects over it or matched a brick off, and the spread carried those depths
    // over the wall.
    let forward: Vec<Pose> = (0..12)
        .map(|i| Pose::from_translation(Vec3::new(0.0, 0.0, 0.05 * i as f64)))
        .collect();
    // Without the warp the views walking forward are biased.
    let plain = MvsConfig {
        warp_px: f64::INFINITY,
        ..MvsConfig::default()
    };
    let (_, d, truth, _) = views_of_frame_6_with(&forward, &plain);
    let (_, unwarped, _) = score(&d, &truth, 0.5);
    eprintln!("forward without the warp: views' AbsRel {unwarped:.4}");
    assert!(unwarped > 0.013, "forward without the warp: {unwarped}");
    for (name, path, limits) in [
        ("orbit", orbit(), [0.012, 0.007, 0.007, 0.065, 0.055]),
        ("forward", forward, [0.013, 0.02, 0.02, 0.09, 0.09]),
    ] {
        let (frames, d, truth, cam) = views_of_frame_6(&path);
        let (w, h) = (cam.width, cam.height);
        let (confident, abs_rel, _) = score(&d, &truth, 0.5);
        eprintln!(
            "{name}: views {:.0} % confident, AbsRel {abs_rel:.4}",
            100.0 * confident
        );
        assert!(confident > 0.3, "{name}: confident share {confident}");
        assert!(abs_rel < limits[0], "{name}: views' AbsRel {abs_rel}");
        let guide = work_rgb(&frames[6], w, h, (w, h)).unwrap();
        let priors = [
            truth.iter().map(|z| 3.0 * z).collect(),
            network_like(&truth, w, h),
        ];
        for (k, prior) in priors.iter().enumerate() {
            let (f, _) = fuse(&d, prior, &guide, 0.5).unwrap().unwrap();
            let (all, abs_all, _) = score(&f, &truth, -1.0);
            let (_, abs_90, _) = score_best(&f, &truth, 0.9);
            eprintln!(
                "{name}, prior {k}: AbsRel {abs_all:.4} over {:.0} %, {abs_90:.4} over 90 %",
                100.0 * all
            );
            assert!(all > 0.999, "{name}, prior {k}: {all}");
            assert!(abs_all < limits[1 + 2 * k], "{name}, prior {k}: {abs_all}");
            assert!(
                abs_90 < limits[2 + 2 * k],
                "{name}, prior {k}: {abs_90} over 90 %"
            );
        }
    }
}

/// `path` as a trajectory solved exactly (every frame placed, one segment, translating), at
/// the size of `cam`.
fn exact_trajectory(cam: Camera, path: &[Pose]) -> Trajectory {
    let n = path.len();
    Trajectory {
        camera: cam,
        poses: path.iter().map(|p| Some(*p)).collect(),
        inliers: vec![0; n],
        motion: CameraMotion::Translating,
        points: 0,
        reprojection_px: 0.0,
        initial_pair: Some((0, 1)),
        segment: vec![0; n],
        world: vec![0; n],
    }
}

/// AbsRel of `z` against `truth` over the pixels where both are known, after scaling `z` by
/// the median ratio, and the share of pixels known.
fn aligned_abs_rel(z: &[f32], truth: &[f32]) -> (f64, f64) {
    let ratios = sorted_ratios(truth, z);
    let s = ratios[ratios.len() / 2];
    let rel: Vec<f64> = z
        .iter()
        .zip(truth)
        .filter(|(z, t)| z.is_finite() && t.is_finite())
        .map(|(z, t)| ((s * *z as f64 - *t as f64) / *t as f64).abs())
        .collect();
    (
        rel.iter().sum::<f64>() / rel.len() as f64,
        rel.len() as f64 / z.len() as f64,
    )
}

#[test]
fn tracked_depth_chooses_neighbours_by_ray_angle() {
    // 25 frames with exact poses at 480x270; frame 10 fused first (its neighbours chosen at
    // the median depth its nearest frames see), then frame 12 (chosen at frame 10's). AbsRel
    // over every pixel after a median scale. Measured 2026-11-29 (the nearest four frames
    // before), frame 12: walking forward 0.65 % with the exact prior (6.8 %) and 5.2 % with
    // the network-like one (27 %), neighbours 5, 18, 0, 22; the orbit 0.50 % (0.84 %),
    // sideways 0.44 % (0.57 %), both exact. Frame 10: forward 1.28 % and 11 % (1.49 and 19 %
    // from its nearest frames), the orbit 0.46 % (0.79 %), sideways 0.59 % (0.57 %).
    let (w, h) = (480, 270);
    let forward: Vec<Pose> = (0..25)
        .map(|i| Pose::from_translation(Vec3::new(0.0, 0.0, 0.05 * i as f64)))
        .collect();
    for (name, path, limits) in [
        ("forward", forward, [0.015, 0.09]),
        ("orbit", orbit_of(25), [0.007, f64::INFINITY]),
        ("sideways", sideways_of(25), [0.005, f64::INFINITY]),
    ] {
        let (scene, frames) = clip_sized(&path, w, h);
        let cam = scene.camera;
        let greys: Vec<Mat> = frames
            .iter()
            .map(|f| work_grey(f, w, h, (w, h)).unwrap())
            .collect();
        for (k, limit) in limits.into_iter().enumerate() {
            if limit.is_infinite() {
                continue;
            }
            let mut tracked =
                TrackedDepth::new(exact_trajectory(cam, &path), greys.clone()).unwrap();
            for i in [10, 12] {
                let truth = scene.render(&cam, &path[i], 0.0, 1).depth;
                let prior: Vec<f32> = match k {
                    0 => truth.iter().map(|z| 3.0 * z).collect(),
                    _ => network_like(&truth, w, h),
                };
                let (z, from) = tracked.depth(i, &frames[i], &prior, (w, h)).unwrap();
                assert!(matches!(from, DepthFrom::Views { .. }), "{name}: {from:?}");
                let (abs_rel, known) = aligned_abs_rel(&z, &truth);
                eprintln!("{name}, prior {k}, frame {i}: AbsRel {abs_rel:.4} over {known:.3}");
                assert!(known > 0.999, "{name}, prior {k}, frame {i}: {known}");
                if i == 12 {
                    assert!(abs_rel < limit, "{name}, prior {k}: {abs_rel}");
                }
            }
        }
    }
}

/// A prior as a monocular network gives it: inverse depth to the power 0.6, blurred over 8
/// pixels, in other units.
fn network_like(truth: &[f32], w: u32, h: u32) -> Vec<f32> {
    let inv: Vec<f32> = truth.iter().map(|z| (1.0 / z).powf(0.6)).collect();
    let m = Mat::new_rows_cols_with_data(h as i32, w as i32, &inv).unwrap();
    let mut o = Mat::default();
    imgproc::gaussian_blur_def(&m, &mut o, Size::new(0, 0), 8.0).unwrap();
    o.data_typed::<f32>()
        .unwrap()
        .iter()
        .map(|v| 0.2 / v)
        .collect()
}
