//! Criterion benchmarks of the CPU renderer kernels. The end-to-end figures in BENCHMARKS.md
//! come from `cpsl bench render`; these track the kernel per change.
#![allow(missing_docs)] // criterion_group! generates undocumented items

use cpsl_core::{Pose, PremulImage, Vec3};
use cpsl_render::{Filter, PreparedLayers};
use cpsl_synth::layers::{synthetic_layer_set, Coverage};
use criterion::{criterion_group, criterion_main, Criterion};

fn bench(c: &mut Criterion) {
    let pose = Pose::from_euler_deg(Vec3::new(0.05, -0.02, 0.03), 0.4, -0.8, 0.2);
    for (name, coverage) in [("typical", Coverage::Typical), ("dense", Coverage::Dense)] {
        let set = synthetic_layer_set(1280, 720, 6, coverage, 7);
        let prepared = PreparedLayers::new(&set);
        let cam = *set.camera();
        let mut out = PremulImage::new(cam.width, cam.height);
        c.bench_function(&format!("render_720p_k6_{name}"), |b| {
            b.iter(|| prepared.render_into(&pose, &cam, &mut out))
        });
    }
    // The Catmull-Rom filter on the typical layers.
    let set = synthetic_layer_set(1280, 720, 6, Coverage::Typical, 7);
    let prepared = PreparedLayers::new(&set).with_filter(Filter::Cubic);
    let cam = *set.camera();
    let mut out = PremulImage::new(cam.width, cam.height);
    c.bench_function("render_720p_k6_typical_cubic", |b| {
        b.iter(|| prepared.render_into(&pose, &cam, &mut out))
    });
    let set = synthetic_layer_set(1280, 720, 6, Coverage::Typical, 7);
    c.bench_function("prepare_720p_k6", |b| b.iter(|| PreparedLayers::new(&set)));
    // The Dynamic Pixel Strip pass on top of the render (typical layers, the same pose).
    let prepared = PreparedLayers::new(&set);
    let cam = *set.camera();
    let mut out = PremulImage::new(cam.width, cam.height);
    c.bench_function("render_dps_720p_k6_typical", |b| {
        b.iter(|| {
            prepared.render_dps_into(&pose, &cam, &mut out, &cpsl_render::DpsConfig::default())
        })
    });
    // Filling what that view leaves uncovered (the frame's edge the pose looks past).
    c.bench_function("over_fill_720p", |b| b.iter(|| out.over_fill()));
}

criterion_group! {
    name = benches;
    config = Criterion::default().sample_size(20);
    targets = bench
}
criterion_main!(benches);
