//! Image resampling shared by every stage: the 8-bit fixed-point bilinear filter of
//! premultiplied RGBA texels (scalar here, eight pixels at a time in [`avx2`]) that the
//! renderer and the P-frame warp sample with, and the pixel-centre bilinear resize of `f32`
//! maps (depth, cues, motion) between working grids.
//!
//! Pixel centres are at integer coordinates (see the crate's conventions): resizing maps the
//! centre of output pixel `i` to `(i + 0.5) * from / to - 0.5` in the input.

#[cfg(target_arch = "x86_64")]
pub mod avx2;

use rayon::prelude::*;

/// The four 16-bit lanes of a spread texel, ordered R, B, G, A.
pub const LANES: u64 = 0x00FF_00FF_00FF_00FF;
/// Half a step of the 8-bit weights, in every lane.
const ROUND: u64 = 0x0080_0080_0080_0080;

/// Spreads RGBA8 (R in the low byte) into four 16-bit lanes ordered R, B, G, A.
#[inline(always)]
pub fn spread(p: u32) -> u64 {
    let p = p as u64;
    (p | (p << 24)) & LANES
}

/// Packs spread lanes (R, B, G, A) back into RGBA8.
#[inline(always)]
pub fn pack(v: u64) -> u32 {
    (v | (v >> 24)) as u32
}

/// The bilinear blend of four RGBA8 texels (top left, top right, bottom left, bottom right)
/// with 8-bit weights `fx`, `fy` in `0..=256`: horizontally, then vertically, each step
/// rounded, all four channels at once in the 16-bit lanes of a `u64` (R, B, G, A; each stays
/// below 2^16). Every channel goes through the same operations, so premultiplied colour never
/// exceeds alpha.
#[inline(always)]
pub fn bilerp(p00: u32, p01: u32, p10: u32, p11: u32, fx: u64, fy: u64) -> u64 {
    let top = ((spread(p00) * (256 - fx) + spread(p01) * fx + ROUND) >> 8) & LANES;
    let bot = ((spread(p10) * (256 - fx) + spread(p11) * fx + ROUND) >> 8) & LANES;
    ((top * (256 - fy) + bot * fy + ROUND) >> 8) & LANES
}

/// Where the centre of pixel `i` of `to` pixels falls among `from` pixels, clamped to the
/// outermost centres.
#[inline]
pub fn source_coord(i: usize, to: usize, from: usize) -> f64 {
    ((i as f64 + 0.5) * from as f64 / to as f64 - 0.5).clamp(0.0, (from - 1) as f64)
}

/// Bilinear resize of an interleaved `f32` image of `ch` channels from `sw x sh` to
/// `dw x dh`, pixel centres aligned, edges clamped; rows in parallel.
///
/// # Panics
/// If `src` does not hold `sw * sh * ch` values or a size is zero.
pub fn resize_bilinear(
    src: &[f32],
    sw: usize,
    sh: usize,
    ch: usize,
    dw: usize,
    dh: usize,
) -> Vec<f32> {
    resize_bilinear_of(src, (sw, sh, ch), (dw, dh), |v| v)
}

/// [`resize_bilinear`] of 8-bit samples read as values in [0, 1] (`v / 255`): the same result
/// as converting the whole image first, converting only the samples the output reads (a
/// network's input is a few hundred pixels on a side).
///
/// # Panics
/// If `src` does not hold `sw * sh * ch` values or a size is zero.
pub fn resize_bilinear_unit(
    src: &[u8],
    sw: usize,
    sh: usize,
    ch: usize,
    dw: usize,
    dh: usize,
) -> Vec<f32> {
    resize_bilinear_of(src, (sw, sh, ch), (dw, dh), |v| v as f32 / 255.0)
}

fn resize_bilinear_of<T: Copy + Sync>(
    src: &[T],
    (sw, sh, ch): (usize, usize, usize),
    (dw, dh): (usize, usize),
    value: impl Fn(T) -> f32 + Sync,
) -> Vec<f32> {
    assert_eq!(src.len(), sw * sh * ch, "resize_bilinear: source size");
    assert!(
        sw > 0 && sh > 0 && dw > 0 && dh > 0,
        "resize_bilinear: empty image"
    );
    let mut out = vec![0f32; dw * dh * ch];
    let axis = |d: usize, dn: usize, sn: usize| {
        let s = source_coord(d, dn, sn);
        let i0 = s.floor() as usize;
        (i0, (i0 + 1).min(sn - 1), (s - i0 as f64) as f32)
    };
    let xs: Vec<_> = (0..dw).map(|x| axis(x, dw, sw)).collect();
    out.par_chunks_mut(dw * ch)
        .enumerate()
        .for_each(|(y, row)| {
            let (y0, y1, fy) = axis(y, dh, sh);
            for (o, &(x0, x1, fx)) in row.chunks_exact_mut(ch).zip(&xs) {
                for (c, o) in o.iter_mut().enumerate() {
                    let p = |yy: usize, xx: usize| value(src[(yy * sw + xx) * ch + c]);
                    let top = p(y0, x0) * (1.0 - fx) + p(y0, x1) * fx;
                    let bot = p(y1, x0) * (1.0 - fx) + p(y1, x1) * fx;
                    *o = top * (1.0 - fy) + bot * fy;
                }
            }
        });
    out
}

/// Box-downscales interleaved RGB by the whole factor `f` that brings the width to at most
/// `max_w` (each output pixel the mean of an `f x f` block, rounded down); returns the pixels
/// and their size.
pub fn downscale_rgb(rgb: &[u8], w: usize, h: usize, max_w: usize) -> (Vec<u8>, usize, usize) {
    let f = w.div_ceil(max_w.max(1)).max(1);
    let (nw, nh) = (w / f, h / f);
    let mut out = vec![0u8; nw * nh * 3];
    for y in 0..nh {
        for x in 0..nw {
            for c in 0..3 {
                let mut s = 0u32;
                for dy in 0..f {
                    for dx in 0..f {
                        s += rgb[((y * f + dy) * w + x * f + dx) * 3 + c] as u32;
                    }
                }
                out[(y * nw + x) * 3 + c] = (s / (f * f) as u32) as u8;
            }
        }
    }
    (out, nw, nh)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn resizing_8_bit_samples_equals_resizing_them_converted() {
        let (w, h) = (37, 23);
        let rgb: Vec<u8> = (0..w * h * 3).map(|i| (i * 97 % 251) as u8).collect();
        let converted: Vec<f32> = rgb.iter().map(|&v| v as f32 / 255.0).collect();
        for (dw, dh) in [(11, 7), (37, 23), (80, 50)] {
            let a = resize_bilinear_unit(&rgb, w, h, 3, dw, dh);
            let b = resize_bilinear(&converted, w, h, 3, dw, dh);
            assert!(a.iter().zip(&b).all(|(x, y)| x.to_bits() == y.to_bits()));
            assert_eq!(a.len(), dw * dh * 3);
        }
    }

    #[test]
    fn bilerp_exact_at_integer_positions_and_midpoint() {
        let p = u32::from_le_bytes([10, 20, 30, 40]);
        let q = u32::from_le_bytes([30, 40, 50, 60]);
        assert_eq!(pack(bilerp(p, q, q, q, 0, 0)), p);
        let m = bilerp(p, q, p, q, 128, 0);
        assert_eq!([m & 0xFFFF, m >> 48], [20, 50]);
        let full = u32::MAX;
        let f = bilerp(full, full, full, full, 77, 200);
        assert_eq!(f >> 48, 255, "no lane overflow at maximum values");
        assert_eq!(pack(f), full);
    }

    #[test]
    fn bilerp_is_within_one_level_of_exact_and_keeps_colour_below_alpha() {
        let mut state = 1u64;
        let mut next = || {
            state = state
                .wrapping_mul(6364136223846793005)
                .wrapping_add(1442695040888963407);
            (state >> 33) as u32
        };
        for _ in 0..20000 {
            let taps: [[u8; 4]; 4] = std::array::from_fn(|_| {
                let a = (next() % 256) as u8;
                let mut c = |_| (next() % (a as u32 + 1)) as u8;
                [c(0), c(1), c(2), a]
            });
            let (fx, fy) = (next() % 256, next() % 256);
            let t = taps.map(u32::from_le_bytes);
            let got = pack(bilerp(t[0], t[1], t[2], t[3], fx as u64, fy as u64)).to_le_bytes();
            let (wx, wy) = (fx as f32 / 256.0, fy as f32 / 256.0);
            for c in 0..4 {
                let v = |t: usize| taps[t][c] as f32;
                let want = (v(0) * (1.0 - wx) + v(1) * wx) * (1.0 - wy)
                    + (v(2) * (1.0 - wx) + v(3) * wx) * wy;
                assert!(
                    (got[c] as f32 - want).abs() <= 1.0,
                    "{taps:?} {fx} {fy}: {got:?}"
                );
            }
            assert!(got[..3].iter().all(|&c| c <= got[3]), "{got:?}");
        }
    }

    #[test]
    fn downscaling_averages_blocks() {
        // 4x2 RGB: two 2x2 blocks, one all 10/20/30, one mixing 0 and 255 in red.
        let mut rgb = vec![0u8; 4 * 2 * 3];
        for y in 0..2 {
            for x in 0..4 {
                let p = (y * 4 + x) * 3;
                let px = if x < 2 {
                    [10, 20, 30]
                } else {
                    [255 * (x % 2) as u8, 0, 0]
                };
                rgb[p..p + 3].copy_from_slice(&px);
            }
        }
        let (out, w, h) = downscale_rgb(&rgb, 4, 2, 2);
        assert_eq!((w, h), (2, 1));
        assert_eq!(out, [10, 20, 30, 127, 0, 0]);
        assert_eq!(downscale_rgb(&rgb, 4, 2, 4).0, rgb, "no reduction needed");
    }

    #[test]
    fn resizing_keeps_constants_and_ramps_and_aligns_centres() {
        // A two-channel ramp: linear in x (channel 0) and y (channel 1).
        let (sw, sh) = (8, 6);
        let src: Vec<f32> = (0..sw * sh)
            .flat_map(|p| [(p % sw) as f32, (p / sw) as f32])
            .collect();
        let up = resize_bilinear(&src, sw, sh, 2, 16, 12);
        // Interior output centres map to (i + 0.5) / 2 - 0.5 in the input.
        for (i, want) in [(5, 2.25), (10, 4.75)] {
            assert!((up[(3 * 16 + i) * 2] - want).abs() < 1e-5);
        }
        // Clamped at the edges.
        assert_eq!(up[0], 0.0);
        assert_eq!(up[15 * 2], (sw - 1) as f32);
        let down = resize_bilinear(&up, 16, 12, 2, sw, sh);
        for (a, b) in down.iter().zip(&src) {
            assert!((a - b).abs() < 0.26, "{a} {b}");
        }
        let flat = resize_bilinear(&[0.5; 12], 4, 3, 1, 7, 5);
        assert!(flat.iter().all(|&v| v == 0.5));
    }
}
