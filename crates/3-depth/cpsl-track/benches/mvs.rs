//! Criterion benchmark of a frame's multi-view depth at the size frames are tracked at
//! (480x270): the built-in scene seen from an orbit with exact poses, frame 6 against frames
//! 2, 4, 8 and 10 (what `TrackedDepth` does for an I-frame): the eight optical flows, the
//! triangulation from them, and the fusion with a prior. The flows one after the other and
//! in parallel (as `TrackedDepth` runs them).
#![allow(missing_docs)] // criterion_group! generates undocumented items

use cpsl_synth::Scene;
use cpsl_track::mvs::{depth_from_flows, flow, fuse, MvsConfig, Neighbour};
use cpsl_track::{work_grey, work_rgb};
use criterion::{criterion_group, criterion_main, Criterion};
use rayon::prelude::*;

fn bench(c: &mut Criterion) {
    let (w, h) = (480, 270);
    let scene = Scene::default_scene(w, h);
    let cam = scene.camera;
    // Around a point 4 units ahead: turn left while moving right, 1.5 degrees a frame.
    let path = Scene::orbit_path(11, 1.5, 4.0);
    let rgb: Vec<Vec<u8>> = path
        .iter()
        .map(|p| scene.render(&cam, p, 0.0, 1).rgb)
        .collect();
    let grey: Vec<_> = rgb
        .iter()
        .map(|f| work_grey(f, w, h, (w, h)).unwrap())
        .collect();
    let near = [2usize, 4, 8, 10];
    let pairs: Vec<(usize, usize)> = near.iter().flat_map(|&j| [(6, j), (j, 6)]).collect();
    c.bench_function("mvs_eight_flows_480x270", |b| {
        b.iter(|| {
            pairs
                .iter()
                .map(|&(a, b)| flow(&grey[a], &grey[b]).unwrap())
                .collect::<Vec<_>>()
        })
    });
    c.bench_function("mvs_eight_flows_in_parallel_480x270", |b| {
        b.iter(|| {
            pairs
                .par_iter()
                .map(|&(a, b)| flow(&grey[a], &grey[b]).unwrap())
                .collect::<Vec<_>>()
        })
    });
    let flows: Vec<_> = pairs
        .iter()
        .map(|&(a, b)| flow(&grey[a], &grey[b]).unwrap())
        .collect();
    let neighbours: Vec<Neighbour> = near
        .iter()
        .zip(flows.chunks(2))
        .map(|(&j, f)| Neighbour {
            pose: &path[j],
            forward: &f[0],
            backward: &f[1],
            plane: None,
        })
        .collect();
    let cfg = MvsConfig::default();
    c.bench_function("mvs_triangulate_4_neighbours_480x270", |b| {
        b.iter(|| depth_from_flows(&cam, &path[6], &neighbours, &cfg).unwrap())
    });
    let views = depth_from_flows(&cam, &path[6], &neighbours, &cfg).unwrap();
    // A prior in other units and bent: the exact depth squared.
    let prior: Vec<f32> = scene
        .render(&cam, &path[6], 0.0, 1)
        .depth
        .iter()
        .map(|z| z * z)
        .collect();
    let guide = work_rgb(&rgb[6], w, h, (w, h)).unwrap();
    c.bench_function("mvs_fuse_with_prior_480x270", |b| {
        b.iter(|| fuse(&views, &prior, &guide, 0.5).unwrap())
    });
}

criterion_group! {
    name = benches;
    config = Criterion::default().sample_size(20);
    targets = bench
}
criterion_main!(benches);
