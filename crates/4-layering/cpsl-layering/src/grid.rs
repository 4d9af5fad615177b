//! Small raster helpers on row-major `f32` maps: blurs, resampling, distance transforms.

/// Box blur of radius `r` (window `2r + 1`, clamped at the borders), separable.
pub fn box_blur(src: &[f32], w: usize, h: usize, r: usize) -> Vec<f32> {
    if r == 0 {
        return src.to_vec();
    }
    let pass = |src: &[f32], len: usize, lines: usize, at: &dyn Fn(usize, usize) -> usize| {
        let mut out = vec![0f32; src.len()];
        let mut prefix = vec![0f64; len + 1];
        for line in 0..lines {
            for i in 0..len {
                prefix[i + 1] = prefix[i] + src[at(line, i)] as f64;
            }
            for i in 0..len {
                let (a, b) = (i.saturating_sub(r), (i + r + 1).min(len));
                out[at(line, i)] = ((prefix[b] - prefix[a]) / (b - a) as f64) as f32;
            }
        }
        out
    };
    let horizontal = pass(src, w, h, &|y, x| y * w + x);
    pass(&horizontal, h, w, &|x, y| y * w + x)
}

/// Area-averaging downscale of a `channels`-interleaved map to `nw x nh` (output rows in
/// parallel).
pub fn downsample(
    src: &[f32],
    w: usize,
    h: usize,
    channels: usize,
    nw: usize,
    nh: usize,
) -> Vec<f32> {
    use rayon::prelude::*;
    let mut out = vec![0f32; nw * nh * channels];
    if out.is_empty() {
        return out;
    }
    let (sx, sy) = (w as f64 / nw as f64, h as f64 / nh as f64);
    out.par_chunks_mut(nw * channels)
        .enumerate()
        .for_each(|(y, out)| {
            let (y0, y1) = (
                (y as f64 * sy) as usize,
                (((y + 1) as f64 * sy).ceil() as usize).min(h),
            );
            for (x, o) in out.chunks_exact_mut(channels).enumerate() {
                let (x0, x1) = (
                    (x as f64 * sx) as usize,
                    (((x + 1) as f64 * sx).ceil() as usize).min(w),
                );
                for yy in y0..y1 {
                    let row = &src[(yy * w + x0) * channels..(yy * w + x1) * channels];
                    for px in row.chunks_exact(channels) {
                        for (v, &s) in o.iter_mut().zip(px) {
                            *v += s;
                        }
                    }
                }
                let n = ((y1 - y0) * (x1 - x0)) as f32;
                o.iter_mut().for_each(|v| *v /= n);
            }
        });
    out
}

/// Euclidean distance from every pixel to the nearest pixel where `inside` is true (0 on
/// those pixels, infinite when none is), by the exact separable transform of Felzenszwalb
/// and Huttenlocher. Along the columns the input is binary, so the squared distance to the
/// nearest pixel inside is found by one sweep down and one up, row after row (what the lower
/// envelope of parabolas at 0 and "infinity" gives, without its divisions or a transposed
/// copy); along the rows the envelope runs on bands of `BAND` (16) rows in parallel.
pub fn distance(inside: &[bool], w: usize, h: usize) -> Vec<f32> {
    use rayon::prelude::*;
    const INF: f32 = 1e20;
    if w == 0 || h == 0 {
        return Vec::new();
    }
    // Squared distance along each column, row-major: from the nearest pixel inside above
    // (sweeping down), then from the nearest below where that is nearer (sweeping up).
    let mut cols = vec![INF; w * h];
    let mut near = vec![usize::MAX; w];
    for (y, (row, g)) in inside
        .chunks_exact(w)
        .zip(cols.chunks_exact_mut(w))
        .enumerate()
    {
        for ((&b, n), g) in row.iter().zip(&mut near).zip(g) {
            if b {
                *n = y;
            }
            if *n != usize::MAX {
                *g = ((y - *n) * (y - *n)) as f32;
            }
        }
    }
    near.fill(usize::MAX);
    for (y, (row, g)) in inside
        .chunks_exact(w)
        .zip(cols.chunks_exact_mut(w))
        .enumerate()
        .rev()
    {
        for ((&b, n), g) in row.iter().zip(&mut near).zip(g) {
            if b {
                *n = y;
            }
            if *n != usize::MAX {
                *g = g.min(((*n - y) * (*n - y)) as f32);
            }
        }
    }
    let mut out = vec![0f32; w * h];
    out.par_chunks_mut(w * BAND)
        .zip(cols.par_chunks(w * BAND))
        .for_each(|(out, f)| {
            let mut scratch = Lower::new(w);
            for (f, d) in f.chunks_exact(w).zip(out.chunks_exact_mut(w)) {
                scratch.envelope(f, d);
                for s in d.iter_mut() {
                    *s = if *s >= INF * 0.5 {
                        f32::INFINITY
                    } else {
                        s.sqrt()
                    };
                }
            }
        });
    out
}

/// Lines [`distance`] hands to one task.
const BAND: usize = 16;

/// Scratch of the one-dimensional transform: the lower envelope's parabolas (`v`) and their
/// boundaries (`z`).
struct Lower {
    v: Vec<usize>,
    z: Vec<f32>,
}

impl Lower {
    fn new(len: usize) -> Self {
        Self {
            v: vec![0; len.max(1)],
            z: vec![0.0; len + 1],
        }
    }

    /// `d[q] = min_p (q - p)^2 + f[p]`, exactly.
    fn envelope(&mut self, f: &[f32], d: &mut [f32]) {
        let (v, z) = (&mut self.v, &mut self.z);
        let mut k = 0;
        v[0] = 0;
        z[0] = f32::NEG_INFINITY;
        z[1] = f32::INFINITY;
        for q in 1..f.len() {
            loop {
                let p = v[k];
                let s =
                    ((f[q] + (q * q) as f32) - (f[p] + (p * p) as f32)) / (2 * q - 2 * p) as f32;
                if s <= z[k] && k > 0 {
                    k -= 1;
                    continue;
                }
                if s <= z[k] {
                    // k == 0: replace the first parabola.
                    v[0] = q;
                    z[0] = f32::NEG_INFINITY;
                    z[1] = f32::INFINITY;
                } else {
                    k += 1;
                    v[k] = q;
                    z[k] = s;
                    z[k + 1] = f32::INFINITY;
                }
                break;
            }
        }
        k = 0;
        for (q, dq) in d.iter_mut().enumerate() {
            while z[k + 1] < q as f32 {
                k += 1;
            }
            let p = v[k];
            *dq = (q as f32 - p as f32).powi(2) + f[p];
        }
    }
}

/// The runs of equal labels along `row`, left to right: each label and its columns.
pub fn label_runs(row: &[u8]) -> impl Iterator<Item = (u8, std::ops::Range<usize>)> + '_ {
    let mut x = 0;
    std::iter::from_fn(move || {
        let &l = row.get(x)?;
        let end = row[x..]
            .iter()
            .position(|&o| o != l)
            .map_or(row.len(), |n| x + n);
        let run = (l, x..end);
        x = end;
        Some(run)
    })
}

/// Labels 4-connected components of equal `key` where `joinable` allows; returns the
/// component id of every pixel and the number of components.
pub fn components(
    w: usize,
    h: usize,
    joinable: impl Fn(usize, usize) -> bool,
) -> (Vec<u32>, usize) {
    let n = w * h;
    let mut parent: Vec<u32> = (0..n as u32).collect();
    fn find(parent: &mut [u32], mut i: u32) -> u32 {
        while parent[i as usize] != i {
            parent[i as usize] = parent[parent[i as usize] as usize];
            i = parent[i as usize];
        }
        i
    }
    for y in 0..h {
        for x in 0..w {
            let p = y * w + x;
            for q in [(x + 1 < w).then(|| p + 1), (y + 1 < h).then(|| p + w)]
                .into_iter()
                .flatten()
            {
                if joinable(p, q) {
                    let (a, b) = (find(&mut parent, p as u32), find(&mut parent, q as u32));
                    if a != b {
                        parent[a.max(b) as usize] = a.min(b);
                    }
                }
            }
        }
    }
    let mut id = vec![u32::MAX; n];
    let mut count = 0;
    let ids = (0..n)
        .map(|p| {
            let r = find(&mut parent, p as u32) as usize;
            if id[r] == u32::MAX {
                id[r] = count as u32;
                count += 1;
            }
            id[r]
        })
        .collect();
    (ids, count)
}

#[cfg(test)]
mod tests {
    use super::*;

    /// The transform one line at a time in place, columns read with a stride, every line
    /// through the envelope (as it was written before the bands).
    fn reference_distance(inside: &[bool], w: usize, h: usize) -> Vec<f32> {
        const INF: f32 = 1e20;
        let mut g: Vec<f32> = inside.iter().map(|&b| if b { 0.0 } else { INF }).collect();
        let mut d = vec![0f32; w.max(h)];
        let mut lower = Lower::new(w.max(h));
        for x in 0..w {
            let f: Vec<f32> = (0..h).map(|y| g[y * w + x]).collect();
            lower.envelope(&f, &mut d[..h]);
            (0..h).for_each(|y| g[y * w + x] = d[y]);
        }
        for row in g.chunks_exact_mut(w.max(1)) {
            lower.envelope(row, &mut d[..w]);
            row.copy_from_slice(&d[..w]);
        }
        g.iter()
            .map(|&s| {
                if s >= INF * 0.5 {
                    f32::INFINITY
                } else {
                    s.sqrt()
                }
            })
            .collect()
    }

    #[test]
    fn distance_in_bands_is_the_line_by_line_transform() {
        for (w, h, m) in [
            (1, 1, 2),
            (13, 9, 17),
            (40, 33, 5),
            (17, 70, 101),
            (64, 48, 3),
        ] {
            // Every m-th pixel inside, none in the first and last three columns (as in the
            // margins of a grown box), and for (1, 1) none at all.
            let inside: Vec<bool> = (0..w * h)
                .map(|i| (i * 7919 + w) % m == 1 && i % w >= 3 && i % w + 3 < w)
                .collect();
            let (a, b) = (distance(&inside, w, h), reference_distance(&inside, w, h));
            assert!(
                a.iter().zip(&b).all(|(x, y)| x.to_bits() == y.to_bits()),
                "{w}x{h}"
            );
        }
        // Regions as layers have them: discs of pseudo-random centres and radii, over
        // frames as wide and as tall as 4K.
        for (w, h, discs) in [(320, 180, 3), (97, 301, 7), (3840, 24, 5), (24, 2160, 5)] {
            let mut lcg = crate::lcg::Lcg(12345 + w as u64);
            let mut next = |n: usize| lcg.index() % n;
            let discs: Vec<(usize, usize, usize)> = (0..discs)
                .map(|_| (next(w), next(h), 1 + next(w.min(h))))
                .collect();
            let inside: Vec<bool> = (0..w * h)
                .map(|i| {
                    let (x, y) = (i % w, i / w);
                    discs
                        .iter()
                        .any(|&(cx, cy, r)| x.abs_diff(cx).pow(2) + y.abs_diff(cy).pow(2) <= r * r)
                })
                .collect();
            let (a, b) = (distance(&inside, w, h), reference_distance(&inside, w, h));
            assert!(
                a.iter().zip(&b).all(|(x, y)| x.to_bits() == y.to_bits()),
                "{w}x{h}"
            );
        }
    }

    #[test]
    fn distance_matches_brute_force() {
        let (w, h) = (13, 9);
        let inside: Vec<bool> = (0..w * h).map(|i| (i * 7919) % 17 == 3).collect();
        let d = distance(&inside, w, h);
        for y in 0..h {
            for x in 0..w {
                let mut best = f32::INFINITY;
                for yy in 0..h {
                    for xx in 0..w {
                        if inside[yy * w + xx] {
                            let e = ((x as f32 - xx as f32).powi(2)
                                + (y as f32 - yy as f32).powi(2))
                            .sqrt();
                            best = best.min(e);
                        }
                    }
                }
                assert!(
                    (d[y * w + x] - best).abs() < 1e-4,
                    "({x},{y}) {} vs {best}",
                    d[y * w + x]
                );
            }
        }
        assert!(distance(&[false; 6], 3, 2).iter().all(|v| v.is_infinite()));
    }

    #[test]
    fn blur_resample_and_components() {
        let m = vec![1f32, 2.0, 3.0, 4.0, 5.0, 6.0];
        let b = box_blur(&m, 3, 2, 1);
        assert!(
            (b[0] - 3.0).abs() < 1e-6 && (b[4] - 3.5).abs() < 1e-6,
            "{b:?}"
        );
        let d = downsample(&[1.0, 3.0, 5.0, 7.0], 2, 2, 1, 1, 1);
        assert_eq!(d, vec![4.0]);
        let key = [0, 0, 1, 1, 0, 1];
        let (ids, n) = components(3, 2, |p, q| key[p] == key[q]);
        assert_eq!(n, 3);
        assert_eq!(ids[0], ids[1]);
        assert_eq!(ids[0], ids[4]);
        assert_ne!(ids[0], ids[3]);
        assert_eq!(ids[2], ids[5]);
    }
}
