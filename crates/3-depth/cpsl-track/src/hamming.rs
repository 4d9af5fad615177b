//! Brute-force matching of ORB descriptors (256 bits) by Hamming distance, as OpenCV's
//! `BFMatcher` with `NORM_HAMMING` matches them (the same neighbours, ties to the lower
//! index; its cross check is [`mutual`]), with the distance taken by the CPU's `popcnt` where
//! it has one. OpenCV's matcher (its thread pool's waiting included) took about 40 % of `cpsl
//! track`'s cycles on the fox, mostly relocalisation's; this one takes a ninth of its time
//! (`cargo bench -p cpsl-track --bench matching`: 0.78 against 7.05 ms for 1000 against 1000
//! descriptors on two cores).
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
fn distance(a: &Descriptor, b: &Descriptor) -> u32 {
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

fn nearest_two_portable(query: &[Descriptor], train: &[Descriptor]) -> Vec<[(u32, u32); 2]> {
    query
        .par_iter()
        .with_min_len(32)
        .map(|q| nearest_two_of(q, train))
        .collect()
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

/// For each of `query`, the two nearest of `train` as (distance, index), nearest first, ties
/// to the lower index; [`NONE`] where `train` has fewer than two.
pub fn nearest_two(query: &[Descriptor], train: &[Descriptor]) -> Vec<[(u32, u32); 2]> {
    #[cfg(target_arch = "x86_64")]
    if std::arch::is_x86_feature_detected!("popcnt") {
        return query
            .par_iter()
            .with_min_len(32)
            // SAFETY: the CPU has `popcnt`.
            .map(|q| unsafe { nearest_two_of_popcnt(q, train) })
            .collect();
    }
    nearest_two_portable(query, train)
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
    fn the_portable_and_popcnt_paths_agree_with_opencv() {
        for (nq, nt, seed) in [(300, 200, 1), (64, 500, 2), (1, 1, 3), (5, 1, 4)] {
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
