//! Criterion benchmarks of the picture work around the codec on a phone-size layer
//! (1080x1920, the fox): stacking it into its colour-over-alpha picture, as every encode of a
//! full-size stream does for every picture (trial encodes included), reading it back, as
//! playback and every trial encode's scoring do for every decoded picture, and bringing a layer
//! coded at an eighth of that size back to it, as every trial encode of a smaller rung and
//! every decoded frame of such a stream does.
#![allow(missing_docs)] // criterion_group! generates undocumented items

use cpsl_codec::scale::{downscale, upscale};
use cpsl_codec::yuv::{stack, unstack};
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
    let frame = PremulImage::from_premul(w, h, data).expect("premultiplied");
    c.bench_function("stack_1080x1920", |b| b.iter(|| stack(&frame)));
    let picture = stack(&frame);
    c.bench_function("unstack_1080x1920", |b| b.iter(|| unstack(&picture, w, h)));
    let small = downscale(&frame, 8);
    c.bench_function("upscale_1080x1920_from_eighth", |b| {
        b.iter(|| upscale(small.clone(), w, h, 8))
    });
}

criterion_group!(benches, bench);
criterion_main!(benches);
