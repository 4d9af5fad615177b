//! Criterion benchmark of dense flow at the working resolution of a 1280x720 frame, by both
//! methods.
#![allow(missing_docs)] // criterion_group! generates undocumented items

use cpsl_flow::{flow, FlowConfig, FlowMethod, Grey};
use criterion::{criterion_group, criterion_main, Criterion};

fn bench(c: &mut Criterion) {
    let (w, h) = (320, 180);
    let img = |s: f32| Grey {
        width: w,
        height: h,
        data: (0..w * h)
            .map(|p| {
                let (x, y) = ((p % w) as f32 - s, (p / w) as f32);
                0.5 + 0.2 * (x * 0.11 + y * 0.07).sin() + 0.2 * (x * -0.05 + y * 0.13).sin()
            })
            .collect(),
    };
    let (a, b) = (img(0.0), img(3.0));
    // DIS (the default) and Lucas-Kanade side by side.
    for (name, method) in [
        ("flow_320x180", FlowMethod::Dis),
        ("flow_320x180_lucas_kanade", FlowMethod::LucasKanade),
    ] {
        let cfg = FlowConfig {
            method,
            ..FlowConfig::default()
        };
        c.bench_function(name, |bch| bch.iter(|| flow(&a, &b, &cfg).unwrap()));
    }
}

criterion_group!(benches, bench);
criterion_main!(benches);
