//! Criterion benchmark of a P-frame at 1280x720 (motion given, as from the decoder's motion
//! vectors; depth carried, as when depth inference is skipped on P-frames, or given, as
//! carried by the camera's poses). The end-to-end
//! figures in BENCHMARKS.md come from `cpsl layer-video`; this tracks the P-frame per change,
//! with the video default (slanted planes) and with mesh layers.
#![allow(missing_docs)] // criterion_group! generates undocumented items

use cpsl_core::Pose;
use cpsl_flow::Flow;
use cpsl_layering::{GeometryMode, LayeringConfig};
use cpsl_synth::Scene;
use cpsl_temporal::{GopConfig, VideoLayerer};
use criterion::{criterion_group, criterion_main, Criterion};

fn bench(c: &mut Criterion) {
    let (w, h, dt) = (1280u32, 720u32, 0.1);
    let scene = Scene::default_scene(w, h);
    let views = [0.0, dt].map(|t| scene.render(&scene.camera, &Pose::IDENTITY, t, 1));
    let flow = |data: Vec<f32>| Flow {
        width: w as usize,
        height: h as usize,
        data,
    };
    // The motion from each frame to the other, so that alternating them stays in place.
    let there = flow(scene.backward_motion(&views[0], &views[1], dt).0);
    let back = flow(there.data.iter().map(|v| -v).collect());
    let gop = GopConfig {
        gop: usize::MAX,
        adaptive_refresh: false,
        ..GopConfig::default()
    };
    // With depth given on P-frames as well (`--p-depth poses`, the default with depth from
    // the video): layer depths and surfaces refitted to it.
    for (name, geometry, with_depth) in [
        ("p_frame_720p_k6_pair", GeometryMode::VIDEO_DEFAULT, false),
        ("p_frame_720p_k6_pair_mesh", GeometryMode::Mesh, false),
        (
            "p_frame_720p_k6_pair_depth",
            GeometryMode::VIDEO_DEFAULT,
            true,
        ),
        ("p_frame_720p_k6_pair_mesh_depth", GeometryMode::Mesh, true),
    ] {
        let mut cfg = LayeringConfig::default();
        cfg.matte.geometry = geometry;
        let mut layerer = VideoLayerer::new(scene.camera, cfg, gop).expect("valid configuration");
        layerer
            .push(&views[0].rgb, Some(&views[0].depth))
            .expect("I-frame");
        c.bench_function(name, |b| {
            b.iter(|| {
                for (view, motion) in [(&views[1], &there), (&views[0], &back)] {
                    let depth = with_depth.then_some(view.depth.as_slice());
                    layerer
                        .push_with_motion(&view.rgb, depth, Some(motion.clone()))
                        .expect("P-frame");
                }
            })
        });
    }
}

criterion_group! {
    name = benches;
    config = Criterion::default().sample_size(20);
    targets = bench
}
criterion_main!(benches);
