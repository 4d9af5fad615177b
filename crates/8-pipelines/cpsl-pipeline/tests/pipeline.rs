//! The pipelines end to end on a short ray-cast clip with exact depth: layered frames with
//! their `video.json`, one layering pass coded into bitrate variants, and a stop request that
//! leaves nothing behind.

use cpsl_codec::RateControl;
use cpsl_core::{NoProgress, Pose};
use cpsl_io::pfm::{write_pfm, FloatImage};
use cpsl_package::{Codec, Package, VariantSet, VARIANTS_FILE};
use cpsl_pipeline::encode::{encode, EncodeJob, EncodeTarget};
use cpsl_pipeline::sources::{CameraChoice, VideoDepth};
use cpsl_pipeline::video::{write_layered_video, MotionSource, PFrameDepth, VideoJob, VIDEO_FILE};
use cpsl_pipeline::PipelineError;
use cpsl_synth::Scene;
use cpsl_temporal::GopConfig;
use std::path::Path;
use std::sync::atomic::AtomicBool;

const FRAMES: usize = 7;

/// Frames and exact depth of the built-in scene in `dir/frames` and `dir/depth`.
fn clip(dir: &Path) -> VideoJob {
    let scene = Scene::default_scene(128, 96);
    let cam = scene.camera;
    for i in 0..FRAMES {
        let v = scene.render(&cam, &Pose::IDENTITY, i as f64 / 10.0, 1);
        let name = format!("{i:04}");
        cpsl_io::images::write_png(
            &dir.join(format!("frames/{name}.png")),
            cam.width,
            cam.height,
            3,
            &v.rgb,
        )
        .unwrap();
        let depth = FloatImage {
            width: cam.width,
            height: cam.height,
            data: v.depth,
        };
        write_pfm(&dir.join(format!("depth/{name}.pfm")), &depth).unwrap();
    }
    let camera = dir.join("camera.json");
    std::fs::write(&camera, serde_json::to_vec(&cam).unwrap()).unwrap();
    VideoJob {
        input: dir.join("frames"),
        camera: CameraChoice::File(camera),
        layering: cpsl_pipeline::sources::layering_config(None, 4, None).unwrap(),
        gop: GopConfig {
            gop: 4,
            ..GopConfig::default()
        },
        motion: MotionSource::Auto,
        p_depth: PFrameDepth::default(),
        max_frames: None,
        stereo: None,
    }
}

#[test]
fn layered_frames_variants_and_interruption() {
    let dir = tempfile::tempdir().unwrap();
    let video = clip(dir.path());
    let depth = || VideoDepth::frames(&dir.path().join("depth"), 0.001).unwrap();

    // Layered frames: a layer set per frame and a typed video.json that reads back.
    let out = dir.path().join("layers");
    let m = write_layered_video(&video, &mut depth(), &out, &NoProgress).unwrap();
    assert_eq!(m.frames.len(), FRAMES);
    assert_eq!(m.frames[0].kind, "I");
    let read: cpsl_pipeline::video::VideoManifest =
        serde_json::from_slice(&std::fs::read(out.join(VIDEO_FILE)).unwrap()).unwrap();
    assert_eq!(read.frames.len(), FRAMES);
    assert!(out.join("frame_000006/manifest.json").is_file());
    // Anything else at the output is refused, and left alone.
    let other = dir.path().join("other");
    std::fs::create_dir(&other).unwrap();
    let e = write_layered_video(&video, &mut depth(), &other, &NoProgress).unwrap_err();
    assert!(e.to_string().contains("not replacing"), "{e}");

    // One layering pass, two budgets: two packages and their variant set.
    let variants = dir.path().join("variants");
    let job = EncodeJob {
        video: video.clone(),
        codec: Codec::H264,
        container: cpsl_codec::Container::Fragment,
        segments: cpsl_codec::Segments::default(),
        fps: Some(10.0),
        target: EncodeTarget::Variants(variants.clone(), vec![400e3, 150e3]),
    };
    let done = encode(&job, &mut depth(), &NoProgress, &AtomicBool::new(false)).unwrap();
    assert_eq!(done.packages.len(), 2);
    let set: VariantSet =
        serde_json::from_slice(&std::fs::read(variants.join(VARIANTS_FILE)).unwrap()).unwrap();
    assert_eq!(set.variants, ["150k.cpsl", "400k.cpsl"], "cheapest first");
    let rates: Vec<f64> = set
        .variants
        .iter()
        .map(|v| {
            let pkg = Package::open(&variants.join(v)).unwrap();
            assert!(pkg.verify().is_empty());
            assert_eq!(pkg.manifest().frames as usize, FRAMES);
            assert!(pkg.manifest().segments.len() >= 2, "GOP 4 over 7 frames");
            pkg.manifest().bitrate()
        })
        .collect();
    assert!(rates[0] < rates[1], "{rates:?}");

    // A stop request ends the run with nothing written.
    let archive = dir.path().join("clip.cpsl");
    let job = EncodeJob {
        target: EncodeTarget::Archive(archive.clone(), RateControl::Quality(30.0)),
        ..job
    };
    let e = encode(&job, &mut depth(), &NoProgress, &AtomicBool::new(true)).unwrap_err();
    assert!(matches!(e, PipelineError::Interrupted(_)), "{e}");
    let left: Vec<_> = std::fs::read_dir(dir.path())
        .unwrap()
        .map(|e| e.unwrap().file_name().to_string_lossy().into_owned())
        .filter(|n| n.starts_with('.') || n == "clip.cpsl")
        .collect();
    assert!(left.is_empty(), "{left:?}");
}

/// A depth "model" that knows each frame by its picture and hands out its exact depth times
/// three (other units, as a network's), noting which frames it was asked for; it fails on
/// frame `fail`.
struct ByPicture {
    frames: Vec<(Vec<u8>, Vec<f32>)>,
    asked: std::sync::Arc<std::sync::Mutex<Vec<usize>>>,
    fail: Option<usize>,
}

impl cpsl_core::DepthSource for ByPicture {
    fn name(&self) -> String {
        "exact depth by picture".into()
    }

    fn depth(
        &mut self,
        rgb: &[u8],
        _width: u32,
        _height: u32,
    ) -> Result<Vec<f32>, cpsl_core::DepthSourceError> {
        let i = self
            .frames
            .iter()
            .position(|(p, _)| p == rgb)
            .expect("a frame of the clip");
        self.asked.lock().unwrap().push(i);
        if self.fail == Some(i) {
            return Err(cpsl_core::DepthSourceError {
                source_name: self.name(),
                cause: "broken on purpose".into(),
            });
        }
        Ok(self.frames[i].1.clone())
    }
}

#[test]
fn p_frames_take_the_i_frames_depth_carried_by_the_tracked_poses() {
    // A camera moving sideways over the still scene: with depth from the video, P-frames
    // take the I-frame's depth carried by the poses (`carried`), or with the paper's
    // setting, along the motion (`propagated`).
    let dir = tempfile::tempdir().unwrap();
    let scene = Scene::default_scene(320, 240);
    let cam = scene.camera;
    let n = 12;
    let mut frames = Vec::new();
    for i in 0..n {
        let pose = Pose::from_translation(cpsl_core::Vec3::new(0.05 * i as f64, 0.0, 0.0));
        let v = scene.render(&cam, &pose, 0.0, 1);
        let file = dir.path().join(format!("frames/{i:04}.png"));
        cpsl_io::images::write_png(&file, cam.width, cam.height, 3, &v.rgb).unwrap();
        frames.push((v.rgb, v.depth.iter().map(|z| 3.0 * z).collect::<Vec<f32>>()));
    }
    let camera = dir.path().join("camera.json");
    std::fs::write(&camera, serde_json::to_vec(&cam).unwrap()).unwrap();
    let job = VideoJob {
        input: dir.path().join("frames"),
        camera: CameraChoice::File(camera),
        layering: cpsl_pipeline::sources::layering_config(None, 4, None).unwrap(),
        gop: GopConfig {
            gop: 5,
            adaptive_refresh: false,
            ..GopConfig::default()
        },
        motion: MotionSource::Flow,
        p_depth: PFrameDepth::Poses,
        max_frames: None,
        stereo: None,
    };
    let source = |fail| {
        let asked = std::sync::Arc::default();
        let prior = ByPicture {
            frames: frames.clone(),
            asked: std::sync::Arc::clone(&asked),
            fail,
        };
        let depth = VideoDepth::Tracked(Box::new(cpsl_pipeline::track::VideoTrackedDepth::new(
            Box::new(prior),
        )));
        (depth, asked)
    };
    let intra = [0, 5, 10];
    for (p_depth, kind, runs) in [
        // Every frame runs the prior, the next one's beside the layering of the one before
        // (also where the next turns out to be an I-frame): once each, in order.
        (PFrameDepth::Poses, "carried", (0..n).collect::<Vec<_>>()),
        (PFrameDepth::Motion, "propagated", intra.to_vec()),
    ] {
        let (mut depth, asked) = source(None);
        let out = dir.path().join(format!("layers-{kind}"));
        let job = VideoJob {
            p_depth,
            ..job.clone()
        };
        let m = write_layered_video(&job, &mut depth, &out, &NoProgress).unwrap();
        assert_eq!(*asked.lock().unwrap(), runs);
        for (i, f) in m.frames.iter().enumerate() {
            let i_frame = intra.contains(&i);
            assert_eq!(f.kind, if i_frame { "I" } else { "P" }, "frame {i}");
            assert_eq!(
                f.depth,
                if i_frame { "estimated" } else { kind },
                "frame {i}"
            );
            // The I-frame's note covers its P-frames.
            assert_eq!(f.depth_note.is_some(), i_frame, "frame {i}");
        }
    }
    // A model failing on a frame is reported as that frame's, whether it ran ahead (a
    // P-frame) or in turn (the first frame).
    for fail in [7, 0] {
        let (mut depth, _) = source(Some(fail));
        let out = dir.path().join(format!("layers-failing-{fail}"));
        let e = write_layered_video(&job, &mut depth, &out, &NoProgress).unwrap_err();
        let text = error_chain(&e);
        let frame = format!("depth of frame {fail}");
        assert_eq!(text.matches(&frame).count(), 1, "{text}");
        assert!(text.contains("broken on purpose"), "{text}");
        assert!(!out.exists(), "nothing left at {}", out.display());
    }
}

/// An error and its causes, one line.
fn error_chain(e: &dyn std::error::Error) -> String {
    let mut text = e.to_string();
    let mut cause = e.source();
    while let Some(c) = cause {
        text += &format!(": {c}");
        cause = c.source();
    }
    text
}
