//! Criterion benchmark of stacking a phone-size layer (1080x1920) into its colour-over-alpha
//! picture, as every encode of a full-size stream does for every picture (trial encodes
//! included).
#![allow(missing_docs)] // criterion_group! generates undocumented items

use cpsl_codec::yuv::stack;
use cpsl_core::PremulImage;
use criterion::{criterion_group, criterion_main, Criterion};

fn bench(c: &mut Criterion) {
    let (w, h) = (1080u32, 1920u32);
    let data: Vec<u8> = (0..w * h)
        .flat_map(|i| {
            let (x, y) = (i % w, i / w);
            let a = if (x / 64 + y / 64) % 3 == 0 { 0 } else { 255 };
            [(x % 256) as u8 & a, (y % 256) as u8 & a, 128 & a, a]
        })
        .collect();
    let layer = PremulImage::from_premul(w, h, data).expect("premultiplied");
    c.bench_function("stack_1080x1920", |b| b.iter(|| stack(&layer)));
}

criterion_group!(benches, bench);
criterion_main!(benches);
