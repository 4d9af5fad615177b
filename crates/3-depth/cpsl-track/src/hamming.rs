//! Brute-force matching of ORB descriptors (256 bits) by Hamming distance, as OpenCV's
//! `BFMatcher` with `NORM_HAMMING` matches them (the same neighbours, ties to the lower
//! index; its cross check is [`mutual`]), eight train descriptors at a time by AVX-512's
//! `vpopcntq` where the CPU has it, else one at a time by `popcnt`. OpenCV's matcher (its
//! thread pool's waiting included) took about 40 % of `cpsl track`'s cycles on the fox,
//! mostly relocalisation's; the `popcnt` path takes a ninth of its time (`cargo bench -p
//! cpsl-track --bench matching`: 0.78 against 7.05 ms for 1000 against 1000 descriptors on two
//! cores), the AVX-512 one a further third to half (0.28-0.44 against 1.00 ms on an AMD EPYC
//! with AVX-512, 2026-12-03).
#![allow(unsafe_code)]

use crate::Result;
use opencv::core::Mat;
use opencv::prelude::*;
use rayon::prelude::*;

/// One descriptor: 256 bits.
pub type Descriptor = [u64; 4];

/// The rows of an OpenCV descriptor matrix (32 bytes each, ORB's).
///
/// # Panics
/// If the rows are not 32 bytes long (not ORB descriptors).
pub fn descriptors(m: &Mat) -> Result<Vec<Descriptor>> {
    if m.rows() == 0 {
        return Ok(Vec::new());
    }
    let bytes = m.data_typed::<u8>()?;
    let cols = m.cols() as usize;
    assert_eq!(cols, 32, "ORB descriptors are 32 bytes");
    Ok(bytes
        .chunks_exact(cols)
        .map(|row| {
            std::array::from_fn(|k| {
                u64::from_le_bytes(row[k * 8..k * 8 + 8].try_into().expect("8 bytes"))
            })
        })
        .collect())
}

#[inline(always)]
pub(crate) fn distance(a: &Descriptor, b: &Descriptor) -> u32 {
    (a[0] ^ b[0]).count_ones()
        + (a[1] ^ b[1]).count_ones()
        + (a[2] ^ b[2]).count_ones()
        + (a[3] ^ b[3]).count_ones()
}

/// No neighbour (fewer descriptors than asked for).
pub const NONE: (u32, u32) = (u32::MAX, u32::MAX);

/// The two nearest of `train` to `q` as (distance, index), nearest first, ties to the lower
/// index; [`NONE`] where `train` has fewer.
#[inline(always)]
fn nearest_two_of(q: &Descriptor, train: &[Descriptor]) -> [(u32, u32); 2] {
    let mut best = [NONE; 2];
    for (j, t) in train.iter().enumerate() {
        let d = distance(q, t);
        if d < best[1].0 {
            if d < best[0].0 {
                best[1] = best[0];
                best[0] = (d, j as u32);
            } else {
                best[1] = (d, j as u32);
            }
        }
    }
    best
}

/// `nearest` of every query, the queries in parallel.
fn per_query(
    query: &[Descriptor],
    nearest: impl Fn(&Descriptor) -> [(u32, u32); 2] + Sync + Send,
) -> Vec<[(u32, u32); 2]> {
    query.par_iter().with_min_len(32).map(nearest).collect()
}

fn nearest_two_portable(query: &[Descriptor], train: &[Descriptor]) -> Vec<[(u32, u32); 2]> {
    per_query(query, |q| nearest_two_of(q, train))
}

/// [`nearest_two_of`] compiled with `popcnt`.
///
/// # Safety
/// The CPU must have `popcnt`.
#[cfg(target_arch = "x86_64")]
#[target_feature(enable = "popcnt")]
unsafe fn nearest_two_of_popcnt(q: &Descriptor, train: &[Descriptor]) -> [(u32, u32); 2] {
    nearest_two_of(q, train)
}

/// `train` word by word (structure of arrays), padded to a multiple of 8 descriptors, for
/// [`nearest_two_of_avx512`].
#[cfg(target_arch = "x86_64")]
fn by_word(train: &[Descriptor]) -> [Vec<u64>; 4] {
    let n = train.len().div_ceil(8) * 8;
    std::array::from_fn(|k| {
        let mut w: Vec<u64> = train.iter().map(|d| d[k]).collect();
        w.resize(n, 0);
        w
    })
}

/// [`nearest_two_of`] eight train descriptors at a time: the words of `words` ([`by_word`] of
/// `n` descriptors) XORed with the query's, counted by `vpopcntq` and summed; each of the eight
/// lanes keeps its own two nearest (a later index replaces only a strictly nearer one, so
/// ties stay with the lower index), and the sixteen are merged at the end.
///
/// # Safety
/// The CPU must have AVX-512F and AVX-512 VPOPCNTDQ.
#[cfg(target_arch = "x86_64")]
#[target_feature(enable = "avx512f,avx512vpopcntdq")]
unsafe fn nearest_two_of_avx512(
    q: &Descriptor,
    words: &[Vec<u64>; 4],
    n: usize,
) -> [(u32, u32); 2] {
    use std::arch::x86_64::*;
    let qs: [__m512i; 4] = std::array::from_fn(|k| _mm512_set1_epi64(q[k] as i64));
    let far = _mm512_set1_epi64(i64::MAX);
    let (mut best, mut best_at) = (far, _mm512_setzero_si512());
    let (mut second, mut second_at) = (far, _mm512_setzero_si512());
    let mut at = _mm512_setr_epi64(0, 1, 2, 3, 4, 5, 6, 7);
    let eight = _mm512_set1_epi64(8);
    for j in (0..n).step_by(8) {
        let mut d = _mm512_setzero_si512();
        for k in 0..4 {
            // SAFETY: `words[k]` holds a multiple of 8 words, at least `j + 8`.
            let w = unsafe { _mm512_loadu_si512(words[k].as_ptr().add(j).cast()) };
            d = _mm512_add_epi64(d, _mm512_popcnt_epi64(_mm512_xor_si512(w, qs[k])));
        }
        // Lanes past the last descriptor never win.
        let valid = if n - j >= 8 {
            0xff
        } else {
            (1u8 << (n - j)) - 1
        };
        d = _mm512_mask_blend_epi64(valid, far, d);
        let nearer = _mm512_cmplt_epi64_mask(d, best);
        let second_nearer = _mm512_cmplt_epi64_mask(d, second);
        // Where nearer than the best, the best moves to second; else where nearer than the
        // second, `d` takes its place.
        second = _mm512_mask_blend_epi64(second_nearer, second, d);
        second_at = _mm512_mask_blend_epi64(second_nearer, second_at, at);
        second = _mm512_mask_blend_epi64(nearer, second, best);
        second_at = _mm512_mask_blend_epi64(nearer, second_at, best_at);
        best = _mm512_mask_blend_epi64(nearer, best, d);
        best_at = _mm512_mask_blend_epi64(nearer, best_at, at);
        at = _mm512_add_epi64(at, eight);
    }
    let lanes = |v: __m512i| -> [i64; 8] {
        let mut out = [0i64; 8];
        // SAFETY: `out` is 64 bytes.
        unsafe { _mm512_storeu_si512(out.as_mut_ptr().cast(), v) };
        out
    };
    let (b, ba, s, sa) = (lanes(best), lanes(best_at), lanes(second), lanes(second_at));
    let mut out = [NONE; 2];
    for (d, i) in b.into_iter().zip(ba).chain(s.into_iter().zip(sa)) {
        if d == i64::MAX {
            continue;
        }
        let c = (d as u32, i as u32);
        if c < out[0] {
            out[1] = out[0];
            out[0] = c;
        } else if c < out[1] {
            out[1] = c;
        }
    }
    out
}

/// For each of `query`, the two nearest of `train` as (distance, index), nearest first, ties
/// to the lower index; [`NONE`] where `train` has fewer than two.
pub fn nearest_two(query: &[Descriptor], train: &[Descriptor]) -> Vec<[(u32, u32); 2]> {
    #[cfg(target_arch = "x86_64")]
    if std::arch::is_x86_feature_detected!("avx512f")
        && std::arch::is_x86_feature_detected!("avx512vpopcntdq")
    {
        let words = by_word(train);
        // SAFETY: the CPU has AVX-512F and VPOPCNTDQ.
        return per_query(query, |q| unsafe {
            nearest_two_of_avx512(q, &words, train.len())
        });
    }
    #[cfg(target_arch = "x86_64")]
    if std::arch::is_x86_feature_detected!("popcnt") {
        return nearest_two_popcnt(query, train);
    }
    nearest_two_portable(query, train)
}

/// [`nearest_two`] by [`nearest_two_of_popcnt`].
///
/// # Panics
/// If the CPU lacks `popcnt`.
#[cfg(target_arch = "x86_64")]
fn nearest_two_popcnt(query: &[Descriptor], train: &[Descriptor]) -> Vec<[(u32, u32); 2]> {
    assert!(std::arch::is_x86_feature_detected!("popcnt"));
    // SAFETY: the CPU has `popcnt`.
    per_query(query, |q| unsafe { nearest_two_of_popcnt(q, train) })
}

/// Mutual nearest neighbours (OpenCV's cross check): `(i, j, distance)` where `train[j]` is
/// the nearest of `train` to `query[i]` and `query[i]` the nearest of `query` to `train[j]`,
/// in the order of `query`.
pub fn mutual(query: &[Descriptor], train: &[Descriptor]) -> Vec<(usize, usize, u32)> {
    let forward = nearest_two(query, train);
    let back = nearest_two(train, query);
    forward
        .iter()
        .enumerate()
        .filter_map(|(i, [(d, j), _])| {
            (*j != u32::MAX && back[*j as usize][0].1 == i as u32).then_some((i, *j as usize, *d))
        })
        .collect()
}

#[cfg(test)]
mod tests {
    use super::*;
    use opencv::core::{self, DMatch, Vector};
    use opencv::features2d;

    /// Descriptors with many exact ties: random bits, then copies and near copies.
    fn sample(n: usize, seed: u64) -> Vec<Descriptor> {
        let mut s = seed;
        let mut next = move || {
            s ^= s << 13;
            s ^= s >> 7;
            s ^= s << 17;
            s
        };
        let mut out: Vec<Descriptor> = (0..n).map(|_| std::array::from_fn(|_| next())).collect();
        for i in (0..n).step_by(7).skip(1) {
            out[i] = out[i / 2];
            out[i][i % 4] ^= 1 << (next() % 64);
        }
        out
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

    #[test]
    fn rows_come_back_as_they_went_in() {
        let d = sample(50, 3);
        assert_eq!(descriptors(&to_mat(&d)).unwrap(), d);
        assert!(descriptors(&Mat::default()).unwrap().is_empty());
    }

    #[test]
    fn the_portable_popcnt_and_avx512_paths_agree_with_opencv() {
        // Train sets of every length modulo 8 (the AVX-512 path's lanes).
        for (nq, nt, seed) in [
            (300, 200, 1),
            (64, 500, 2),
            (1, 1, 3),
            (5, 1, 4),
            (40, 9, 5),
            (40, 15, 6),
            (40, 2, 7),
            (33, 1003, 8),
            (40, 13, 9),
            (40, 6, 10),
        ] {
            let (q, t) = (sample(nq, seed), sample(nt, seed + 100));
            // Make some queries copies of train rows, so that exact and tied matches occur.
            let q: Vec<Descriptor> = q
                .iter()
                .enumerate()
                .map(|(i, r)| if i % 3 == 0 { t[i % nt] } else { *r })
                .collect();
            let matcher = features2d::BFMatcher::create(core::NORM_HAMMING, false).unwrap();
            let mut knn = Vector::<Vector<DMatch>>::new();
            matcher
                .knn_train_match(
                    &to_mat(&q),
                    &to_mat(&t),
                    &mut knn,
                    2,
                    &core::no_array(),
                    false,
                )
                .unwrap();
            let ours = nearest_two(&q, &t);
            assert_eq!(ours, nearest_two_portable(&q, &t));
            #[cfg(target_arch = "x86_64")]
            if std::arch::is_x86_feature_detected!("popcnt") {
                assert_eq!(ours, nearest_two_popcnt(&q, &t));
            }
            for (i, m) in knn.iter().enumerate() {
                let want: Vec<(u32, u32)> = m
                    .iter()
                    .map(|d| (d.distance as u32, d.train_idx as u32))
                    .collect();
                let got: Vec<(u32, u32)> = ours[i].iter().copied().filter(|&x| x != NONE).collect();
                assert_eq!(got, want, "query {i} of {nq} x {nt}");
            }
            let cross = features2d::BFMatcher::create(core::NORM_HAMMING, true).unwrap();
            let mut m = Vector::<DMatch>::new();
            cross
                .train_match(&to_mat(&q), &to_mat(&t), &mut m, &core::no_array())
                .unwrap();
            let want: Vec<(usize, usize, u32)> = m
                .iter()
                .map(|d| {
                    (
                        d.query_idx as usize,
                        d.train_idx as usize,
                        d.distance as u32,
                    )
                })
                .collect();
            assert_eq!(mutual(&q, &t), want, "{nq} x {nt}");
        }
    }
}
