//! AVX2 kernels: linear row spans, eight pixels per step, and the output stage's packing of
//! accumulators into 8-bit RGBA.
//!
//! Both compute exactly what the scalar paths compute (the spans: the same fixed-point
//! positions, the same 8-bit two-stage bilinear filter in 16-bit lanes, the same `f32`
//! multiply-then-add compositing and `1 - a / 255` transmittance; the packing: the same
//! rounding and saturation), so renders are bit-identical with or without them; tests check
//! that.
#![allow(unsafe_code)]

pub(crate) use cpsl_core::resample::avx2::available;
use cpsl_core::resample::avx2::{bilerp8, gather_taps};
use std::arch::x86_64::*;

/// Composites the `n = trans.len()` pixels of a linear span whose positions (16.16 fixed
/// point, with half a 1/256 step pre-added) start at `x`, `y` and advance by `dx`, `dy`:
/// groups of eight, the last one masked to the pixels left (so that the short spans of mesh
/// triangles run here too). Returns the number of pixels that became opaque through
/// `opaqued`.
///
/// Positions must stay within `i32` for the whole span and seven steps beyond it (the caller
/// checks).
#[allow(clippy::too_many_arguments)]
pub(crate) fn draw_linear(
    texels: &[u32],
    pitch: usize,
    sw: u32,
    sh: u32,
    xy: [i32; 2],
    dxy: [i32; 2],
    acc: &mut [[f32; 4]],
    trans: &mut [f32],
    opaqued: &mut u32,
) {
    assert!(texels.len() >= pitch * (sh as usize + 2) && pitch == sw as usize + 2);
    assert_eq!(acc.len(), trans.len());
    assert!(available());
    // SAFETY: AVX2 is present (checked above); the kernel only reads texels at indices that
    // the range masks prove to be inside the padded texture (see `draw_linear_avx2`), and
    // only touches `acc`/`trans` within their (equal) length: whole groups of eight, then the
    // last group's pixels through masked loads and stores.
    unsafe { draw_linear_avx2(texels, pitch, sw, sh, xy, dxy, acc, trans, opaqued) }
}

#[allow(clippy::too_many_arguments)]
#[target_feature(enable = "avx2")]
unsafe fn draw_linear_avx2(
    texels: &[u32],
    pitch: usize,
    sw: u32,
    sh: u32,
    xy: [i32; 2],
    dxy: [i32; 2],
    acc: &mut [[f32; 4]],
    trans: &mut [f32],
    opaqued: &mut u32,
) {
    let n = trans.len();
    let lane = _mm256_setr_epi32(0, 1, 2, 3, 4, 5, 6, 7);
    let k = Kernel {
        texels,
        pitch,
        minus_one: _mm256_set1_epi32(-1),
        sw1: _mm256_set1_epi32(sw as i32 + 1),
        sh1: _mm256_set1_epi32(sh as i32 + 1),
        pitch_v: _mm256_set1_epi32(pitch as i32),
    };
    let mut xs = _mm256_add_epi32(
        _mm256_set1_epi32(xy[0]),
        _mm256_mullo_epi32(lane, _mm256_set1_epi32(dxy[0])),
    );
    let mut ys = _mm256_add_epi32(
        _mm256_set1_epi32(xy[1]),
        _mm256_mullo_epi32(lane, _mm256_set1_epi32(dxy[1])),
    );
    let (step_x, step_y) = (
        _mm256_set1_epi32(dxy[0].wrapping_mul(8)),
        _mm256_set1_epi32(dxy[1].wrapping_mul(8)),
    );
    let mut count = 0u32;
    let mut o = 0;
    while o + 8 <= n {
        // SAFETY: pixels o..o + 8 lie inside `acc` and `trans`.
        count += k.group::<false>(
            xs,
            ys,
            k.minus_one,
            acc.as_mut_ptr().add(o),
            trans.as_mut_ptr().add(o),
        );
        xs = _mm256_add_epi32(xs, step_x);
        ys = _mm256_add_epi32(ys, step_y);
        o += 8;
    }
    if o < n {
        // The pixels left: lanes below their count.
        let live = _mm256_cmpgt_epi32(_mm256_set1_epi32((n - o) as i32), lane);
        // SAFETY: the masked loads and stores touch only the live lanes, pixels o..n.
        count += k.group::<true>(
            xs,
            ys,
            live,
            acc.as_mut_ptr().add(o),
            trans.as_mut_ptr().add(o),
        );
    }
    *opaqued += count;
}

/// What every group of eight pixels of a span shares.
struct Kernel<'a> {
    texels: &'a [u32],
    pitch: usize,
    minus_one: __m256i,
    sw1: __m256i,
    sh1: __m256i,
    pitch_v: __m256i,
}

impl Kernel<'_> {
    /// Composites the eight pixels at positions `xs`, `ys` (the `live` lanes when `MASKED`:
    /// all bits set or none per lane) into the accumulators at `ap` and transmittances at
    /// `tp`; returns how many became opaque.
    ///
    /// # Safety
    /// AVX2 must be present; `ap` and `tp` must point at eight pixels' accumulators and
    /// transmittances, or at as many as there are live lanes (the first ones) when `MASKED`.
    #[inline]
    #[target_feature(enable = "avx2")]
    unsafe fn group<const MASKED: bool>(
        &self,
        xs: __m256i,
        ys: __m256i,
        live: __m256i,
        ap: *mut [f32; 4],
        tp: *mut f32,
    ) -> u32 {
        let one_i = _mm256_set1_epi32(1);
        let byte = _mm256_set1_epi32(255);
        // 1/256 px positions, integer texel and 8-bit fractions.
        let xi = _mm256_srai_epi32(xs, 8);
        let yi = _mm256_srai_epi32(ys, 8);
        let x1 = _mm256_add_epi32(_mm256_srai_epi32(xi, 8), one_i); // x0 + 1, padded column
        let y1 = _mm256_add_epi32(_mm256_srai_epi32(yi, 8), one_i);
        let fx = _mm256_and_si256(xi, byte);
        let fy = _mm256_and_si256(yi, byte);
        // 0 <= x0 + 1 <= sw and 0 <= y0 + 1 <= sh: all four taps inside the padded texture,
        // whose last index is (sh + 1) * pitch + sw + 1 = (y0+1)*pitch + (x0+1) + pitch + 1
        // at most.
        let mut valid = _mm256_and_si256(
            _mm256_and_si256(
                _mm256_cmpgt_epi32(x1, self.minus_one),
                _mm256_cmpgt_epi32(self.sw1, x1),
            ),
            _mm256_and_si256(
                _mm256_cmpgt_epi32(y1, self.minus_one),
                _mm256_cmpgt_epi32(self.sh1, y1),
            ),
        );
        if MASKED {
            valid = _mm256_and_si256(valid, live);
        }
        let idx = _mm256_add_epi32(_mm256_mullo_epi32(y1, self.pitch_v), x1);
        // SAFETY: valid lanes' taps are inside the padded texture (above), and so are texel
        // 0's (the texture has at least two rows of `pitch` texels).
        let taps = gather_taps(self.texels, self.pitch, idx, valid);
        let [p00, p01, p10, p11] = taps;
        if _mm256_testz_si256(
            _mm256_or_si256(_mm256_or_si256(p00, p01), _mm256_or_si256(p10, p11)),
            self.minus_one,
        ) == 1
        {
            return 0;
        }
        let (v_rb, v_ga) = bilerp8(taps, fx, fy);
        let low16 = _mm256_set1_epi32(0xFFFF);
        let a_i = _mm256_srli_epi32(v_ga, 16);
        let r = _mm256_cvtepi32_ps(_mm256_and_si256(v_rb, low16));
        let b = _mm256_cvtepi32_ps(_mm256_srli_epi32(v_rb, 16));
        let gr = _mm256_cvtepi32_ps(_mm256_and_si256(v_ga, low16));
        let a = _mm256_cvtepi32_ps(a_i);

        // Masked-off lanes load a transmittance of 0, so they neither count nor contribute.
        let t = match MASKED {
            true => _mm256_maskload_ps(tp, live),
            false => _mm256_loadu_ps(tp),
        };
        // Pixels whose transmittance drops to zero now (alive and fully opaque sample).
        let alive = _mm256_castps_si256(_mm256_cmp_ps::<_CMP_GT_OQ>(t, _mm256_setzero_ps()));
        let newly = _mm256_and_si256(alive, _mm256_cmpeq_epi32(a_i, byte));
        let count = (_mm256_movemask_ps(_mm256_castsi256_ps(newly)) as u32).count_ones();
        let t_new = _mm256_mul_ps(
            t,
            _mm256_sub_ps(_mm256_set1_ps(1.0), _mm256_div_ps(a, _mm256_set1_ps(255.0))),
        );
        match MASKED {
            true => _mm256_maskstore_ps(tp, live, t_new),
            false => _mm256_storeu_ps(tp, t_new),
        }

        // Contributions T * sample in lane order R, B, G, A, transposed to per-pixel order.
        let (cr, cb, cg, ca) = (
            _mm256_mul_ps(t, r),
            _mm256_mul_ps(t, b),
            _mm256_mul_ps(t, gr),
            _mm256_mul_ps(t, a),
        );
        let t0 = _mm256_unpacklo_ps(cr, cb);
        let t1 = _mm256_unpackhi_ps(cr, cb);
        let t2 = _mm256_unpacklo_ps(cg, ca);
        let t3 = _mm256_unpackhi_ps(cg, ca);
        let u0 = _mm256_shuffle_ps::<0x44>(t0, t2);
        let u1 = _mm256_shuffle_ps::<0xEE>(t0, t2);
        let u2 = _mm256_shuffle_ps::<0x44>(t1, t3);
        let u3 = _mm256_shuffle_ps::<0xEE>(t1, t3);
        // Pixels (0, 1), (2, 3), (4, 5) and (6, 7).
        let px = [
            _mm256_permute2f128_ps::<0x20>(u0, u1),
            _mm256_permute2f128_ps::<0x20>(u2, u3),
            _mm256_permute2f128_ps::<0x31>(u0, u1),
            _mm256_permute2f128_ps::<0x31>(u2, u3),
        ];
        let ap = ap as *mut f32;
        for (k, c) in px.iter().enumerate() {
            let p = ap.add(k * 8);
            if MASKED {
                // Each pixel's four lanes take its live flag: lanes 2k and 2k + 1, each twice
                // over four lanes.
                let pair = _mm256_permutevar8x32_epi32(
                    live,
                    _mm256_setr_epi32(
                        2 * k as i32,
                        2 * k as i32,
                        2 * k as i32,
                        2 * k as i32,
                        2 * k as i32 + 1,
                        2 * k as i32 + 1,
                        2 * k as i32 + 1,
                        2 * k as i32 + 1,
                    ),
                );
                if _mm256_testz_si256(pair, pair) == 1 {
                    break;
                }
                let sum = _mm256_add_ps(_mm256_maskload_ps(p, pair), *c);
                _mm256_maskstore_ps(p, pair, sum);
            } else {
                _mm256_storeu_ps(p, _mm256_add_ps(_mm256_loadu_ps(p), *c));
            }
        }
        count
    }
}

/// Packs accumulators (lanes R, B, G, A on a 0..255 scale) into 8-bit RGBA exactly as
/// [`crate::raster::pack_pixel`] does (round half up, saturating; colour at most alpha),
/// eight pixels per step. `dst` holds four bytes per accumulator.
pub(crate) fn pack_rgba8(acc: &[[f32; 4]], dst: &mut [u8]) {
    assert_eq!(dst.len(), acc.len() * 4);
    assert!(available());
    // SAFETY: AVX2 is present (checked above); whole groups of eight accumulators are read
    // and 32 bytes written per group, within the two slices (equal in pixels, checked).
    unsafe { pack_rgba8_avx2(acc, dst) }
}

#[target_feature(enable = "avx2")]
unsafe fn pack_rgba8_avx2(acc: &[[f32; 4]], dst: &mut [u8]) {
    let n = acc.len() / 8 * 8;
    let half = _mm256_set1_ps(0.5);
    // `as u8` saturates at 255, where the conversion to i32 would overflow: values beyond
    // 2^20 are brought down first; `min` takes its second operand when either is NaN, so
    // NaN stays NaN and converts to i32::MIN, which packs to 0 as `as u8` gives.
    let big = _mm256_set1_ps((1 << 20) as f32);
    // Per pixel: R, B, G, A to R, G, B, A, and its alpha in all four bytes.
    let order = _mm256_setr_epi8(
        0, 2, 1, 3, 4, 6, 5, 7, 8, 10, 9, 11, 12, 14, 13, 15, 0, 2, 1, 3, 4, 6, 5, 7, 8, 10, 9, 11,
        12, 14, 13, 15,
    );
    let alpha = _mm256_setr_epi8(
        3, 3, 3, 3, 7, 7, 7, 7, 11, 11, 11, 11, 15, 15, 15, 15, 3, 3, 3, 3, 7, 7, 7, 7, 11, 11, 11,
        11, 15, 15, 15, 15,
    );
    // The packs interleave the 128-bit lanes: pixels 0, 2, 4, 6 | 1, 3, 5, 7.
    let unzip = _mm256_setr_epi32(0, 4, 1, 5, 2, 6, 3, 7);
    for i in (0..n).step_by(8) {
        let p = acc.as_ptr().add(i) as *const f32;
        let q = |k: usize| {
            let v = _mm256_add_ps(_mm256_loadu_ps(p.add(8 * k)), half);
            _mm256_cvttps_epi32(_mm256_min_ps(big, v))
        };
        let words = (
            _mm256_packs_epi32(q(0), q(1)),
            _mm256_packs_epi32(q(2), q(3)),
        );
        let bytes = _mm256_packus_epi16(words.0, words.1);
        let rgba = _mm256_min_epu8(
            _mm256_shuffle_epi8(bytes, order),
            _mm256_shuffle_epi8(bytes, alpha),
        );
        let out = _mm256_permutevar8x32_epi32(rgba, unzip);
        _mm256_storeu_si256(dst.as_mut_ptr().add(i * 4) as *mut __m256i, out);
    }
    for (d, s) in dst[n * 4..].chunks_exact_mut(4).zip(&acc[n..]) {
        d.copy_from_slice(&crate::raster::pack_pixel(s));
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn packing_matches_the_scalar_rounding() {
        if !available() {
            return;
        }
        // Every edge of the conversion: halves, saturation, negatives, NaN, huge values,
        // colour above alpha; 8 groups and a tail.
        let edge = [
            0.0,
            0.49,
            0.5,
            1.5,
            127.5,
            254.49,
            254.5,
            255.0,
            255.49,
            255.5,
            256.0,
            300.0,
            -0.3,
            -0.5,
            -1.0,
            -300.0,
            f32::NAN,
            1e7,
            3e9,
            f32::INFINITY,
            f32::NEG_INFINITY,
        ];
        let acc: Vec<[f32; 4]> = (0..67u32)
            .map(|i| {
                std::array::from_fn(|c| {
                    edge[(i as usize * 7 + c * 5 + i as usize / 3) % edge.len()]
                })
            })
            .collect();
        let mut fast = vec![0u8; acc.len() * 4];
        pack_rgba8(&acc, &mut fast);
        for (i, s) in acc.iter().enumerate() {
            assert_eq!(
                fast[i * 4..i * 4 + 4],
                crate::raster::pack_pixel(s),
                "pixel {i}: {s:?}"
            );
        }
    }

    #[test]
    fn spans_of_every_length_touch_only_their_pixels() {
        if !available() {
            return;
        }
        // A 6x4 layer, opaque grey, padded by one transparent texel all round.
        let (sw, sh) = (6u32, 4u32);
        let pitch = sw as usize + 2;
        let mut texels = vec![0u32; pitch * (sh as usize + 2)];
        for y in 1..=sh as usize {
            for x in 1..=sw as usize {
                texels[y * pitch + x] = 0xFF80_8080;
            }
        }
        for n in 1..=20 {
            // Sentinels after the span: -0.0 turns into +0.0 under any store of a sum with 0,
            // and 0.5 into 0 under a store of a masked lane's transmittance.
            let mut acc = vec![[-0.0f32; 4]; n + 8];
            let mut trans = vec![0.5f32; n + 8];
            trans[..n].fill(1.0);
            acc[..n].fill([0.0; 4]);
            let mut opaqued = 0;
            // From the first column along the second row and a half, a quarter pixel a step.
            let (x, y) = (128, 128 + (1 << 16) + (1 << 15));
            draw_linear(
                &texels,
                pitch,
                sw,
                sh,
                [x, y],
                [1 << 14, 0],
                &mut acc[..n],
                &mut trans[..n],
                &mut opaqued,
            );
            for (i, (a, t)) in acc.iter().zip(&trans).enumerate().skip(n) {
                assert!(
                    a.iter().all(|v| v.to_bits() == (-0.0f32).to_bits()),
                    "n {n}: acc {i}"
                );
                assert_eq!(*t, 0.5, "n {n}: trans {i}");
            }
            // Every pixel of the span is over the layer and opaque.
            assert_eq!(opaqued as usize, n, "n {n}");
            assert!(trans[..n].iter().all(|&t| t == 0.0), "n {n}");
            assert!(acc[..n].iter().all(|a| a[3] == 255.0), "n {n}");
        }
    }
}
