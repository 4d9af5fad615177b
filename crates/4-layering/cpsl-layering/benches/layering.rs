//! Criterion benchmarks of the layering stages at 1280x720 (ray-cast scene, exact depth). The
//! end-to-end per-stage figures in BENCHMARKS.md come from `cpsl bench layer`.
#![allow(missing_docs)] // criterion_group! generates undocumented items

use cpsl_core::{NoProgress, Pose};
use cpsl_layering::fuse::fuse;
use cpsl_layering::geometry::{fit_geometry, LayerDepth, FINEST_MESH_STEP};
use cpsl_layering::{layer_cues, Cues, GeometryMode, LayeringConfig};
use cpsl_synth::Scene;
use criterion::{criterion_group, criterion_main, Criterion};

fn bench(c: &mut Criterion) {
    let scene = Scene::default_scene(1280, 720);
    let view = scene.render(&scene.camera, &Pose::IDENTITY, 0.0, 1);
    let cfg = LayeringConfig::default();
    c.bench_function("cues_720p", |b| {
        b.iter(|| Cues::compute(&view.rgb, &view.depth, 1280, 720, &cfg.cues).unwrap())
    });
    let cues = Cues::compute(&view.rgb, &view.depth, 1280, 720, &cfg.cues).unwrap();
    c.bench_function("fusion_720p_k6", |b| {
        b.iter(|| fuse(&cues.work, cfg.layers, &cfg.fusion, false))
    });
    // A layer's region as the distance transforms of the matting see it: the pixels nearer
    // than the median depth, in the whole frame.
    let mut sorted = view.depth.clone();
    sorted.sort_by(f32::total_cmp);
    let median = sorted[sorted.len() / 2];
    let inside: Vec<bool> = view.depth.iter().map(|&z| z < median).collect();
    c.bench_function("distance_720p", |b| {
        b.iter(|| cpsl_layering::grid::distance(&inside, 1280, 720))
    });
    // A layer's surface as a mesh (auto step, refined down to the finest where that helps):
    // the pixels between the 60th and 80th percentiles of depth (the floor and walls across
    // the frame), looked for in their box and in the whole frame.
    let (near, far) = (sorted[sorted.len() * 3 / 5], sorted[sorted.len() * 4 / 5]);
    let owner: Vec<u8> = view
        .depth
        .iter()
        .map(|z| u8::from((near..=far).contains(z)))
        .collect();
    let own = |p: usize| owner[p] == 1;
    let (xs, ys): (Vec<usize>, Vec<usize>) = (0..1280 * 720)
        .filter(|&p| own(p))
        .map(|p| (p % 1280, p / 1280))
        .unzip();
    let extent = [
        *xs.iter().min().unwrap(),
        *ys.iter().min().unwrap(),
        *xs.iter().max().unwrap(),
        *ys.iter().max().unwrap(),
    ];
    let step = cpsl_layering::geometry::auto_mesh_step(1280, 720);
    for (name, bounds) in [
        ("mesh_fit_720p", Some(extent)),
        ("mesh_fit_720p_unbounded", None),
    ] {
        let px = LayerDepth {
            width: 1280,
            height: 720,
            depth: &view.depth,
            confidence: None,
            owner: &owner,
            label: 1,
            covered: &own,
            bounds,
        };
        c.bench_function(name, |b| {
            b.iter(|| {
                let g = fit_geometry(
                    GeometryMode::Mesh,
                    &scene.camera,
                    &px,
                    near as f64,
                    Some(extent),
                    step,
                    FINEST_MESH_STEP,
                );
                assert!(matches!(g, cpsl_core::Geometry::Mesh(_)));
            })
        });
    }
    c.bench_function("layer_cues_720p_k6", |b| {
        b.iter(|| layer_cues(&cues, &view.rgb, scene.camera, &cfg, &NoProgress).unwrap())
    });
}

criterion_group! {
    name = benches;
    config = Criterion::default().sample_size(10);
    targets = bench
}
criterion_main!(benches);
