//! H.264 motion vectors (FFmpeg's `AVMotionVector` side data) as a dense backward motion field.
//!
//! A vector points into one of the block's reference pictures, which need not be the previous
//! frame: a P-frame after three B-frames refers four frames back, a B-frame to a later frame
//! too, and any block may take an older reference. FFmpeg says only the direction (`source`
//! -1 or +1), so each vector's distance is found here from the pictures: of the distances 1 to
//! [`MAX_DISTANCE`], the one whose vector, divided by it (constant motion), carries the block
//! best from the previous frame (least mean absolute difference of luma). The frame's own
//! most common distance is preferred where it carries a block about as well; a block that no
//! distance carries ([`MAX_DIFFERENCE`]) is left to the median vector like an intra block.

use cpsl_core::Flow;

/// Size in bytes of FFmpeg's `AVMotionVector`: `int32 source; uint8 w, h; int16 src_x, src_y,
/// dst_x, dst_y; uint64 flags; int32 motion_x, motion_y; uint16 motion_scale` (dst is the block
/// centre, `src = dst + motion / motion_scale`).
const MV_SIZE: usize = 40;

/// Farthest reference, in frames, a vector is taken to span (x264's default three B-frames
/// put a P-frame's reference four frames back).
pub const MAX_DISTANCE: usize = 4;

/// Mean absolute luma difference above which no distance carries a block (8-bit levels).
const MAX_DIFFERENCE: f32 = 16.0;

/// A block's vectors are taken at the frame's most common distance unless another carries
/// it clearly better: by this factor and [`PREFER_SLACK`] levels.
const PREFER_FACTOR: f32 = 1.25;
const PREFER_SLACK: f32 = 1.0;

/// One vector of the side data.
struct Vector {
    /// -1: into an earlier frame, +1: into a later one.
    dir: f32,
    /// Block centre and size.
    dst: (i32, i32),
    size: (i32, i32),
    /// Motion to the reference, in pixels.
    m: (f32, f32),
}

impl Vector {
    /// The pixel rows and columns of the block inside a `w` x `h` frame.
    fn span(&self, w: usize, h: usize) -> (std::ops::Range<i32>, std::ops::Range<i32>) {
        let (x, y) = self.dst;
        let (bw, bh) = self.size;
        (
            (x - bw / 2).max(0)..(x + bw / 2).min(w as i32),
            (y - bh / 2).max(0)..(y + bh / 2).min(h as i32),
        )
    }

    /// The motion from this frame to the previous one if the reference is `s` frames away
    /// and the motion constant.
    fn per_frame(&self, s: usize) -> (f32, f32) {
        let k = -self.dir / s as f32;
        (self.m.0 * k, self.m.1 * k)
    }
}

/// Mean absolute difference between the block of `v` in `cur` and where `u` takes it in
/// `prev` (nearest pixel, clamped to the frame; at most 4x4 samples a block).
fn difference(v: &Vector, u: (f32, f32), cur: &[u8], prev: &[u8], w: usize, h: usize) -> f32 {
    let (xs, ys) = v.span(w, h);
    let step = |n: i32| (n / 4).max(1) as usize;
    let (sx, sy) = (step(v.size.0), step(v.size.1));
    let (ox, oy) = (u.0.round() as i32, u.1.round() as i32);
    let (mut sum, mut n) = (0u32, 0u32);
    for y in ys.step_by(sy) {
        let py = (y + oy).clamp(0, h as i32 - 1) as usize;
        let (row, ref_row) = (&cur[y as usize * w..][..w], &prev[py * w..][..w]);
        for x in xs.clone().step_by(sx) {
            let px = (x + ox).clamp(0, w as i32 - 1) as usize;
            sum += row[x as usize].abs_diff(ref_row[px]) as u32;
            n += 1;
        }
    }
    if n == 0 {
        f32::INFINITY
    } else {
        sum as f32 / n as f32
    }
}

/// The index of the least of `costs` (distance index: 0 is one frame).
fn least(costs: &[f64; MAX_DISTANCE]) -> usize {
    (0..MAX_DISTANCE)
        .min_by(|&a, &b| costs[a].total_cmp(&costs[b]))
        .unwrap_or(0)
}

/// A dense backward motion field (this frame to the previous one) from `AVMotionVector`
/// records, each vector's reference distance found from the pictures (see the module), if the
/// blocks carried cover at least half of the frame. `cur` and `prev` are this frame's and the
/// previous frame's luma, `w` x `h` bytes. Uncovered pixels (intra blocks, blocks no distance
/// carries) get the median vector.
pub fn motion_from_vectors(
    raw: &[u8],
    w: usize,
    h: usize,
    cur: &[u8],
    prev: &[u8],
) -> Option<Flow> {
    if w == 0 || h == 0 || cur.len() < w * h || prev.len() < w * h {
        return None;
    }
    let i16_at = |b: &[u8], o: usize| i16::from_ne_bytes([b[o], b[o + 1]]) as i32;
    let i32_at = |b: &[u8], o: usize| i32::from_ne_bytes([b[o], b[o + 1], b[o + 2], b[o + 3]]);
    let vectors: Vec<Vector> = raw
        .chunks_exact(MV_SIZE)
        .filter_map(|r| {
            let source = i32_at(r, 0);
            let scale = u16::from_ne_bytes([r[32], r[33]]).max(1) as f32;
            (source != 0).then(|| Vector {
                dir: source.signum() as f32,
                dst: (i16_at(r, 10), i16_at(r, 12)),
                size: (r[4] as i32, r[5] as i32),
                m: (i32_at(r, 24) as f32 / scale, i32_at(r, 28) as f32 / scale),
            })
        })
        .collect();
    // Each vector's difference at every distance, and the frame's best distance per
    // direction (least summed difference).
    let costs: Vec<[f32; MAX_DISTANCE]> = vectors
        .iter()
        .map(|v| std::array::from_fn(|i| difference(v, v.per_frame(i + 1), cur, prev, w, h)))
        .collect();
    let common = |dir: f32| -> usize {
        let mut sums = [0f64; MAX_DISTANCE];
        for (_, c) in vectors.iter().zip(&costs).filter(|(v, _)| v.dir == dir) {
            for (s, &d) in sums.iter_mut().zip(c) {
                *s += d.min(255.0) as f64;
            }
        }
        least(&sums)
    };
    let (past, future) = (common(-1.0), common(1.0));
    let mut data = vec![0f32; w * h * 2];
    let mut best = vec![f32::INFINITY; w * h];
    let mut kept = Vec::new();
    for (v, c) in vectors.iter().zip(&costs) {
        let own = least(&c.map(f64::from));
        let frame = if v.dir < 0.0 { past } else { future };
        let s = if c[frame] <= c[own] * PREFER_FACTOR + PREFER_SLACK {
            frame
        } else {
            own
        };
        if c[s] > MAX_DIFFERENCE {
            continue;
        }
        let u = v.per_frame(s + 1);
        kept.push(u);
        let (xs, ys) = v.span(w, h);
        let (x0, x1) = (xs.start as usize, xs.end.max(xs.start) as usize);
        for y in ys {
            let row = y as usize * w;
            let pixels = best[row + x0..row + x1].iter_mut();
            // Of a bi-predicted block's two vectors, the one that carries it better.
            for (b, d) in pixels.zip(data[2 * (row + x0)..2 * (row + x1)].chunks_exact_mut(2)) {
                if c[s] < *b {
                    *b = c[s];
                    d.copy_from_slice(&[u.0, u.1]);
                }
            }
        }
    }
    let n = best.iter().filter(|b| b.is_finite()).count();
    if n * 2 < w * h {
        return None;
    }
    let median = |mut v: Vec<f32>| {
        let m = v.len() / 2;
        *v.select_nth_unstable_by(m, f32::total_cmp).1
    };
    let mu = median(kept.iter().map(|v| v.0).collect());
    let mv = median(kept.iter().map(|v| v.1).collect());
    for p in (0..w * h).filter(|&p| !best[p].is_finite()) {
        data[p * 2] = mu;
        data[p * 2 + 1] = mv;
    }
    Some(Flow {
        width: w,
        height: h,
        data,
    })
}

#[cfg(test)]
mod tests {
    use super::*;

    const W: usize = 64;

    /// A textured picture whose content sits `shift` pixels to the right.
    fn picture(shift: i32) -> Vec<u8> {
        (0..W * W)
            .map(|p| {
                let (x, y) = ((p % W) as i32 - shift, (p / W) as i32);
                let v = (x * 37 + y * 91).wrapping_mul(2_654_435_761u32 as i32) >> 11;
                (v & 0xff) as u8
            })
            .collect()
    }

    /// An `AVMotionVector` record of a 16x16 block centred at `(x, y)`.
    fn record(source: i32, x: i16, y: i16, motion: (i32, i32)) -> Vec<u8> {
        let mut r = vec![0u8; MV_SIZE];
        r[0..4].copy_from_slice(&source.to_ne_bytes());
        (r[4], r[5]) = (16, 16);
        r[10..12].copy_from_slice(&x.to_ne_bytes());
        r[12..14].copy_from_slice(&y.to_ne_bytes());
        r[24..28].copy_from_slice(&(motion.0 * 4).to_ne_bytes());
        r[28..32].copy_from_slice(&(motion.1 * 4).to_ne_bytes());
        r[32..34].copy_from_slice(&4u16.to_ne_bytes());
        r
    }

    #[test]
    fn each_vector_is_divided_by_the_distance_of_its_reference() {
        // The content moves 2 pixels right a frame: this frame to the previous one is -2.
        let (prev, cur) = (picture(0), picture(2));
        let mut raw = Vec::new();
        for (i, (by, bx)) in (0..4).flat_map(|y| (0..4).map(move |x| (y, x))).enumerate() {
            let (x, y) = (8 + 16 * bx as i16, 8 + 16 * by as i16);
            raw.extend(match i % 4 {
                // A P-frame's reference three frames back, another's one frame back.
                0 => record(-1, x, y, (-6, 0)),
                1 => record(-1, x, y, (-2, 0)),
                // A B-frame's later reference two frames ahead.
                2 => record(1, x, y, (4, 0)),
                // Ten frames back: no distance up to MAX_DISTANCE carries it.
                _ => record(-1, x, y, (-20, 0)),
            });
        }
        let f = motion_from_vectors(&raw, W, W, &cur, &prev).expect("three quarters covered");
        for (i, (by, bx)) in (0..4).flat_map(|y| (0..4).map(move |x| (y, x))).enumerate() {
            let (u, v) = f.at(8 + 16 * bx, 8 + 16 * by);
            // The uncarried block takes the median of the others.
            assert_eq!((u, v), (-2.0, 0.0), "block {i}");
        }
        // Less than half of the frame carried (7 blocks of 16): no field.
        let raw: Vec<u8> = (0..16)
            .flat_map(|b: i16| {
                let m = if b < 7 { (-2, 0) } else { (-20, 0) };
                record(-1, 8 + 16 * (b % 4), 8 + 16 * (b / 4), m)
            })
            .collect();
        assert!(motion_from_vectors(&raw, W, W, &cur, &prev).is_none());
        assert!(motion_from_vectors(&raw, W, W, &cur, &prev[..10]).is_none());
    }
}
