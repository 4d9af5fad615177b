//! Criterion benchmarks of the picture work around the codec on a phone-size layer
//! (1080x1920, the fox): stacking it into its colour-over-alpha picture, as every encode of a
//! full-size stream does for every picture (trial encodes included), reading it back, as
//! playback and every trial encode's scoring do for every decoded picture, and bringing a layer
//! coded at an eighth of that size back to it, as every trial encode of a smaller rung and
//! every decoded frame of such a stream does; and the rest of a trial encode's scoring: the
//! box filter down to a rung, how much of a layer shows behind five in front of it, and the
//! proxy distortion of a decoded layer.
#![allow(missing_docs)] // criterion_group! generates undocumented items

use cpsl_codec::alloc::{distortion, visibility};
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
    c.bench_function("downscale_1080x1920_by_2", |b| {
        b.iter(|| downscale(&frame, 2))
    });
    let front = [&frame; 5];
    c.bench_function("visibility_1080x1920_behind_5", |b| {
        b.iter(|| visibility(&front, w, h))
    });
    let vis = visibility(&front[..1], w, h);
    let decoded = unstack(&picture, w, h);
    c.bench_function("distortion_1080x1920", |b| {
        b.iter(|| distortion(&frame, &decoded, &vis))
    });
}

criterion_group!(benches, bench);
criterion_main!(benches);
