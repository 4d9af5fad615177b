//! The pipelines end to end on a short ray-cast clip with exact depth: layered frames with
//! their `video.json`, one layering pass coded into bitrate variants, and a stop request that
//! leaves nothing behind.

use cpsl_codec::RateControl;
use cpsl_core::{NoProgress, Pose};
use cpsl_io::pfm::{write_pfm, FloatImage};
use cpsl_package::{Codec, Package, VariantSet, VARIANTS_FILE};
use cpsl_pipeline::encode::{encode, EncodeJob, EncodeTarget};
use cpsl_pipeline::sources::{CameraChoice, VideoDepth};
use cpsl_pipeline::video::{write_layered_video, MotionSource, VideoJob, VIDEO_FILE};
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
        depth_every_frame: false,
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
