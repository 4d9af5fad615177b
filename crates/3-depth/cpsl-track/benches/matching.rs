//! Criterion benchmark of brute-force ORB descriptor matching (the two nearest of 1000
//! against 1000, as relocalisation matches a frame's features), ours against OpenCV's
//! `BFMatcher` in the same run.
#![allow(missing_docs)] // criterion_group! generates undocumented items

use cpsl_track::hamming::{nearest_two, Descriptor};
use criterion::{criterion_group, criterion_main, Criterion};
use opencv::core::{self, DMatch, Mat, Vector};
use opencv::features2d;
use opencv::prelude::*;

fn sample(n: usize, mut s: u64) -> Vec<Descriptor> {
    let mut next = move || {
        s ^= s << 13;
        s ^= s >> 7;
        s ^= s << 17;
        s
    };
    (0..n).map(|_| std::array::from_fn(|_| next())).collect()
}

fn to_mat(d: &[Descriptor]) -> Mat {
    let bytes: Vec<u8> = d
        .iter()
        .flat_map(|r| r.iter().flat_map(|w| w.to_le_bytes()))
        .collect();
    Mat::new_rows_cols_with_data(d.len() as i32, 32, &bytes)
        .expect("a matrix")
        .try_clone()
        .expect("a copy")
}

fn bench(c: &mut Criterion) {
    let (q, t) = (sample(1000, 1), sample(1000, 2));
    c.bench_function("nearest_two_1000x1000", |b| b.iter(|| nearest_two(&q, &t)));
    let (qm, tm) = (to_mat(&q), to_mat(&t));
    let matcher = features2d::BFMatcher::create(core::NORM_HAMMING, false).expect("a matcher");
    c.bench_function("opencv_bfmatcher_knn2_1000x1000", |b| {
        b.iter(|| {
            let mut knn = Vector::<Vector<DMatch>>::new();
            matcher
                .knn_train_match(&qm, &tm, &mut knn, 2, &core::no_array(), false)
                .expect("matches");
            knn
        })
    });
}

criterion_group!(benches, bench);
criterion_main!(benches);
