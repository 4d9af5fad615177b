//! Video layering on the synthetic scene with moving objects, where the true motion and object
//! partition are known.

use cpsl_core::Pose;
use cpsl_core::{LayeredFrame, RefreshReason};
use cpsl_eval::temporal::{alpha_owner, boundary_variance, ClipMotion};
use cpsl_flow::Flow;
use cpsl_layering::LayeringConfig;
use cpsl_synth::{Scene, View};
use cpsl_temporal::{GopConfig, VideoError, VideoLayerer};

const W: u32 = 320;
const H: u32 = 240;
/// Seconds between frames.
const DT: f64 = 0.1;

struct Clip {
    scene: Scene,
    views: Vec<View>,
    rgb: Vec<Vec<u8>>,
    depth: Vec<Vec<f32>>,
    object: Vec<Vec<u16>>,
}

fn clip(frames: usize) -> Clip {
    let scene = Scene::default_scene(W, H);
    let views: Vec<View> = (0..frames)
        .map(|t| scene.render(&scene.camera, &Pose::IDENTITY, t as f64 * DT, 2))
        .collect();
    Clip {
        rgb: views.iter().map(|v| v.rgb.clone()).collect(),
        depth: views.iter().map(|v| v.depth.clone()).collect(),
        object: views.iter().map(|v| v.object.clone()).collect(),
        scene,
        views,
    }
}

/// The true motion of the clip (see `Scene::backward_motion`).
fn true_motion(c: &Clip) -> ClipMotion {
    let (w, h) = (W as usize, H as usize);
    let (back, valid) = c
        .views
        .windows(2)
        .map(|v| {
            let (data, seen) = c.scene.backward_motion(&v[0], &v[1], DT);
            (
                Flow {
                    width: w,
                    height: h,
                    data,
                },
                seen,
            )
        })
        .unzip();
    ClipMotion {
        width: w,
        height: h,
        back,
        valid,
    }
}

/// The layers composited front to back at the reference view, over black.
fn composite(set: &cpsl_core::LayerSet) -> Vec<u8> {
    let n = (set.camera().width * set.camera().height) as usize;
    let mut out = vec![0f32; n * 3];
    let mut through = vec![1f32; n];
    for layer in set.layers() {
        for (p, px) in layer.image.as_bytes().chunks_exact(4).enumerate() {
            for c in 0..3 {
                out[p * 3 + c] += through[p] * px[c] as f32;
            }
            through[p] *= 1.0 - px[3] as f32 / 255.0;
        }
    }
    out.iter()
        .map(|v| v.round().clamp(0.0, 255.0) as u8)
        .collect()
}

fn run(c: &Clip, gop: GopConfig) -> Vec<LayeredFrame> {
    let mut v = VideoLayerer::new(c.scene.camera, LayeringConfig::default(), gop).unwrap();
    (0..c.rgb.len())
        .map(|t| v.push(&c.rgb[t], Some(&c.depth[t])).unwrap())
        .collect()
}

#[test]
fn propagation_steadies_boundaries_and_keeps_tracks() {
    let c = clip(10);
    let motion = true_motion(&c);
    let estimated = ClipMotion::estimate(&c.rgb, W as usize, H as usize);
    let mut scores = Vec::new();
    for (name, gop) in [
        ("frame-wise", GopConfig::frame_wise()),
        ("I/P", GopConfig::propagation_only()),
        ("I/P + refinement + hysteresis", GopConfig::default()),
    ] {
        let frames = run(&c, gop);
        let owners: Vec<Vec<u8>> = frames.iter().map(|f| alpha_owner(&f.set)).collect();
        let bv = boundary_variance(&owners, &motion);
        let bve = boundary_variance(&owners, &estimated);
        let kinds: String = frames
            .iter()
            .map(|f| if f.refresh.is_some() { 'I' } else { 'P' })
            .collect();
        eprintln!("{name}: boundary variance {bv:.3} (estimated motion {bve:.3}), frames {kinds}");
        scores.push(bv);
        // The layers composited at the reference view against the input, on the last frame
        // (where carried layers have drifted most).
        let last = frames.last().expect("frames");
        let psnr = cpsl_eval::metrics::psnr(&composite(&last.set), c.rgb.last().expect("frames"));
        eprintln!("{name}: reference view of the last frame {psnr:.2} dB");
        // Carried along imperfect flow, boundaries drift unless the layers' motion rejects
        // vectors measured across a motion boundary (26.5 / 32.6 dB; 24.0 / 29.3 before).
        match name {
            "I/P" => assert!(psnr > 25.5, "{name}: {psnr}"),
            "I/P + refinement + hysteresis" => assert!(psnr > 31.0, "{name}: {psnr}"),
            _ => {}
        }
        if name != "frame-wise" {
            assert_eq!(&kinds, "IPPPPPPPPP", "{name}");
            // The board (object 2) stays on one track.
            let board: Vec<u32> = frames
                .iter()
                .zip(&c.object)
                .map(|(f, obj)| {
                    let mut count = vec![0usize; f.set.len()];
                    for (&o, &l) in obj.iter().zip(&f.owner) {
                        if o == 2 {
                            count[l as usize] += 1;
                        }
                    }
                    let l = (0..count.len()).max_by_key(|&l| count[l]).unwrap();
                    f.set.layers()[l].meta.track.unwrap()
                })
                .collect();
            assert!(board.windows(2).all(|p| p[0] == p[1]), "{name}: {board:?}");
        }
    }
    // With exact depth, frame-wise layering is stable here too: both stay well below a
    // pixel (0.05 and 0.08 px^2).
    assert!(scores[1] < 0.15, "contours move with the content");
    assert!(scores[2] <= scores[1] * 1.05, "refinement does not undo it");
}

#[test]
fn a_scene_cut_triggers_a_refresh_once_with_hysteresis() {
    let c = clip(4);
    let scene = &c.scene;
    // The same scene mirrored left to right: nothing lines up with the layers any more.
    let mirror = |v: &[u8]| -> Vec<u8> {
        (0..(W * H) as usize)
            .flat_map(|p| {
                let (x, y) = (p % W as usize, p / W as usize);
                let q = y * W as usize + (W as usize - 1 - x);
                v[q * 3..q * 3 + 3].to_vec()
            })
            .collect()
    };
    let mirror_depth = |v: &[f32]| -> Vec<f32> {
        (0..(W * H) as usize)
            .map(|p| {
                let (x, y) = (p % W as usize, p / W as usize);
                v[y * W as usize + (W as usize - 1 - x)]
            })
            .collect()
    };
    let (cut_rgb, cut_depth) = (mirror(&c.rgb[3]), mirror_depth(&c.depth[3]));
    let cfg = GopConfig {
        min_gap: 2,
        ..GopConfig::default()
    };
    let mut v = VideoLayerer::new(scene.camera, LayeringConfig::default(), cfg).unwrap();
    let mut kinds = Vec::new();
    for t in 0..3 {
        kinds.push(v.push(&c.rgb[t], Some(&c.depth[t])).unwrap().refresh);
    }
    for _ in 0..5 {
        kinds.push(v.push(&cut_rgb, Some(&cut_depth)).unwrap().refresh);
    }
    eprintln!("{kinds:?}");
    assert_eq!(kinds[0], Some(RefreshReason::First));
    let adaptive: Vec<usize> = (1..kinds.len())
        .filter(|&i| {
            matches!(
                kinds[i],
                Some(RefreshReason::Confidence | RefreshReason::Crack)
            )
        })
        .collect();
    // Two low-confidence frames after the cut (hysteresis 2), then one refresh.
    assert_eq!(adaptive.len(), 1, "{kinds:?}");
    assert!(adaptive[0] >= 5, "{kinds:?}");
}

#[test]
fn no_short_group_at_the_end_of_a_clip_of_known_length() {
    let c = clip(9);
    let n = c.rgb.len();
    let intra = |gop: usize, left: &dyn Fn(usize) -> Option<usize>| -> Vec<usize> {
        let cfg = GopConfig {
            gop,
            min_gap: 2,
            adaptive_refresh: false,
            ..GopConfig::default()
        };
        let mut v = VideoLayerer::new(c.scene.camera, LayeringConfig::default(), cfg).unwrap();
        (0..n)
            .filter(|&t| {
                v.set_frames_left(left(t));
                let told = v.next_is_intra();
                let z = told.then_some(c.depth[t].as_slice());
                let f = v.push(&c.rgb[t], z).unwrap();
                assert_eq!(told, f.refresh.is_some(), "frame {t}");
                told
            })
            .collect()
    };
    let known = |t: usize| Some(n - t);
    // GOP 4 over 9 frames: the last group would be frame 8 alone.
    assert_eq!(intra(4, &|_| None), [0, 4, 8]);
    assert_eq!(intra(4, &known), [0, 4], "frame 8 joins the group before");
    // A tail of half a GOP is long enough; every frame an I-frame stays so.
    assert_eq!(intra(3, &known), [0, 3, 6]);
    assert_eq!(intra(1, &known), (0..n).collect::<Vec<_>>());
    // Four frames more than announced: the refresh that the count held back comes as soon
    // as the count is spent.
    assert_eq!(intra(4, &|t| Some((n - t).saturating_sub(4))), [0, 5]);
}

#[test]
fn clear_errors() {
    let c = clip(1);
    let mut v = VideoLayerer::new(
        c.scene.camera,
        LayeringConfig::default(),
        GopConfig::default(),
    )
    .unwrap();
    assert!(v.next_is_intra());
    assert!(matches!(
        v.push(&c.rgb[0], None),
        Err(VideoError::NeedDepth { frame: 0 })
    ));
    assert!(matches!(
        v.push(&c.rgb[0][..300], Some(&c.depth[0])),
        Err(VideoError::FrameSize { frame: 0, .. })
    ));
    let bad = GopConfig {
        gop: 0,
        ..GopConfig::default()
    };
    assert!(VideoLayerer::new(c.scene.camera, LayeringConfig::default(), bad).is_err());
    // P-frames may skip depth: it is carried along the flow.
    v.push(&c.rgb[0], Some(&c.depth[0])).unwrap();
    assert!(!v.next_is_intra());
    let p = v.push(&c.rgb[0], None).unwrap();
    assert!(p.refresh.is_none() && p.depth_propagated);
}

#[test]
fn a_still_clip_keeps_its_layers() {
    let c = clip(1);
    let mut v = VideoLayerer::new(
        c.scene.camera,
        LayeringConfig::default(),
        GopConfig::default(),
    )
    .unwrap();
    let first = v.push(&c.rgb[0], Some(&c.depth[0])).unwrap();
    for _ in 0..3 {
        let p = v.push(&c.rgb[0], Some(&c.depth[0])).unwrap();
        assert!(p.refresh.is_none());
        for (a, b) in first.set.layers().iter().zip(p.set.layers()) {
            let diff = a
                .image
                .as_bytes()
                .iter()
                .zip(b.image.as_bytes())
                .filter(|(x, y)| x.abs_diff(**y) > 2)
                .count();
            assert!(diff < 100, "{diff} bytes changed");
        }
    }
}

#[test]
fn layers_follow_a_known_translation() {
    // The scene's first frame shifted right by 3 px per frame, with that motion given.
    let c = clip(1);
    let (w, h) = (W as usize, H as usize);
    let shift = |v: &[u8], d: usize| -> Vec<u8> {
        (0..w * h)
            .flat_map(|p| {
                let (x, y) = (p % w, p / w);
                let q = y * w + x.saturating_sub(d);
                v[q * 3..q * 3 + 3].to_vec()
            })
            .collect()
    };
    let shift_z = |v: &[f32], d: usize| -> Vec<f32> {
        (0..w * h)
            .map(|p| v[(p / w) * w + (p % w).saturating_sub(d)])
            .collect()
    };
    let back = Flow {
        width: w,
        height: h,
        data: (0..w * h).flat_map(|_| [-3.0f32, 0.0]).collect(),
    };
    let mut v = VideoLayerer::new(
        c.scene.camera,
        LayeringConfig::default(),
        GopConfig::default(),
    )
    .unwrap();
    let first = v.push(&c.rgb[0], Some(&c.depth[0])).unwrap();
    for t in 1..4 {
        let d = 3 * t;
        let p = v
            .push_with_motion(
                &shift(&c.rgb[0], d),
                Some(&shift_z(&c.depth[0], d)),
                Some(back.clone()),
            )
            .unwrap();
        assert!(p.refresh.is_none());
        // Every layer is the first frame's layer shifted by d (away from the left border).
        for (a, b) in first.set.layers().iter().zip(p.set.layers()) {
            let (a, b) = (a.image.as_bytes(), b.image.as_bytes());
            let mut bad = 0;
            for y in 0..h {
                for x in d + 2..w - 2 {
                    let (pa, pb) = ((y * w + x - d) * 4 + 3, (y * w + x) * 4 + 3);
                    bad += (a[pa].abs_diff(b[pb]) > 8) as usize;
                }
            }
            assert!(bad < 50, "frame {t}: {bad} alpha values off");
        }
    }
}
