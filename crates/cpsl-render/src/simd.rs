//! AVX2 kernel for linear row spans: eight pixels per step.
//!
//! It computes exactly what the scalar path computes (same fixed-point positions, the same
//! 8-bit two-stage bilinear filter in 16-bit lanes, the same `f32` multiply-then-add
//! compositing and `1 - a / 255` transmittance), so renders are bit-identical with or without
//! it; a test checks that.
#![allow(unsafe_code)]

use std::arch::x86_64::*;

/// Whether the running CPU has AVX2.
pub(crate) fn available() -> bool {
    std::arch::is_x86_feature_detected!("avx2")
}

/// Composites `n = trans.len()` pixels of a linear span whose positions (16.16 fixed point,
/// with half a 1/256 step pre-added) start at `x`, `y` and advance by `dx`, `dy`. Processes
/// whole groups of eight and returns how many pixels it handled; the caller finishes the rest.
/// Returns the number of pixels that became opaque through `opaqued`.
///
/// Positions must stay within `i32` for the whole span (the caller checks).
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
) -> usize {
    assert!(texels.len() >= pitch * (sh as usize + 2) && pitch == sw as usize + 2);
    assert_eq!(acc.len(), trans.len());
    assert!(available());
    // SAFETY: AVX2 is present (checked above); the kernel only reads texels at indices that
    // the range masks prove to be inside the padded texture (see `draw_linear_avx2`), and
    // only touches `acc`/`trans` within the groups of eight that fit their (equal) length.
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
) -> usize {
    let groups = trans.len() / 8;
    let lane = _mm256_setr_epi32(0, 1, 2, 3, 4, 5, 6, 7);
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
    let one_i = _mm256_set1_epi32(1);
    let minus_one = _mm256_set1_epi32(-1);
    let sw1 = _mm256_set1_epi32(sw as i32 + 1);
    let sh1 = _mm256_set1_epi32(sh as i32 + 1);
    let pitch_v = _mm256_set1_epi32(pitch as i32);
    let byte = _mm256_set1_epi32(255);
    let lanes16 = _mm256_set1_epi32(0x00FF_00FF);
    let w256 = _mm256_set1_epi32(0x0100_0100);
    let round = _mm256_set1_epi32(0x0080_0080);
    let low16 = _mm256_set1_epi32(0xFFFF);
    let zero_f = _mm256_setzero_ps();
    let one_f = _mm256_set1_ps(1.0);
    let f255 = _mm256_set1_ps(255.0);
    let opaque_a = _mm256_set1_epi32(255);
    let base = texels.as_ptr() as *const i32;
    let mut count = 0u32;
    for g in 0..groups {
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
        let valid = _mm256_and_si256(
            _mm256_and_si256(
                _mm256_cmpgt_epi32(x1, minus_one),
                _mm256_cmpgt_epi32(sw1, x1),
            ),
            _mm256_and_si256(
                _mm256_cmpgt_epi32(y1, minus_one),
                _mm256_cmpgt_epi32(sh1, y1),
            ),
        );
        let idx = _mm256_add_epi32(_mm256_mullo_epi32(y1, pitch_v), x1);
        // Each row's two taps are adjacent: load them as one 64-bit value per pixel. Invalid
        // lanes load from index 0 (always in bounds) and are masked to zero afterwards.
        let mut lane_idx = [0i32; 8];
        _mm256_storeu_si256(
            lane_idx.as_mut_ptr() as *mut __m256i,
            _mm256_and_si256(idx, valid),
        );
        let row = |off: usize| {
            // SAFETY: every index is 0 or a valid lane's index; both rows of taps are in
            // bounds for those (see above).
            let q =
                |k: usize| (base.add(lane_idx[k] as usize + off) as *const i64).read_unaligned();
            let lo = _mm256_setr_epi64x(q(0), q(1), q(2), q(3));
            let hi = _mm256_setr_epi64x(q(4), q(5), q(6), q(7));
            (lo, hi)
        };
        let (t_lo, t_hi) = row(0);
        let (u_lo, u_hi) = row(pitch);
        // Even dwords are left taps, odd dwords right taps; restore pixel order 0..7.
        let split = |lo: __m256i, hi: __m256i| {
            let (a, b) = (_mm256_castsi256_ps(lo), _mm256_castsi256_ps(hi));
            let even = _mm256_castps_si256(_mm256_shuffle_ps::<0x88>(a, b));
            let odd = _mm256_castps_si256(_mm256_shuffle_ps::<0xDD>(a, b));
            (
                _mm256_and_si256(_mm256_permute4x64_epi64::<0xD8>(even), valid),
                _mm256_and_si256(_mm256_permute4x64_epi64::<0xD8>(odd), valid),
            )
        };
        let (p00, p01) = split(t_lo, t_hi);
        let (p10, p11) = split(u_lo, u_hi);
        if _mm256_testz_si256(
            _mm256_or_si256(_mm256_or_si256(p00, p01), _mm256_or_si256(p10, p11)),
            minus_one,
        ) == 1
        {
            xs = _mm256_add_epi32(xs, step_x);
            ys = _mm256_add_epi32(ys, step_y);
            continue;
        }
        // Weights replicated into both 16-bit halves: (256 - f, f).
        let wx1 = _mm256_or_si256(fx, _mm256_slli_epi32(fx, 16));
        let wx0 = _mm256_sub_epi16(w256, wx1);
        let wy1 = _mm256_or_si256(fy, _mm256_slli_epi32(fy, 16));
        let wy0 = _mm256_sub_epi16(w256, wy1);
        let lerp = |a: __m256i, b: __m256i, w0: __m256i, w1: __m256i| {
            _mm256_srli_epi16(
                _mm256_add_epi16(
                    _mm256_add_epi16(_mm256_mullo_epi16(a, w0), _mm256_mullo_epi16(b, w1)),
                    round,
                ),
                8,
            )
        };
        // Even bytes (R, B) and odd bytes (G, A) in 16-bit lanes.
        let rb = |p: __m256i| _mm256_and_si256(p, lanes16);
        let ga = |p: __m256i| _mm256_srli_epi16(p, 8);
        let top_rb = lerp(rb(p00), rb(p01), wx0, wx1);
        let bot_rb = lerp(rb(p10), rb(p11), wx0, wx1);
        let top_ga = lerp(ga(p00), ga(p01), wx0, wx1);
        let bot_ga = lerp(ga(p10), ga(p11), wx0, wx1);
        let v_rb = lerp(top_rb, bot_rb, wy0, wy1);
        let v_ga = lerp(top_ga, bot_ga, wy0, wy1);
        let a_i = _mm256_srli_epi32(v_ga, 16);
        let r = _mm256_cvtepi32_ps(_mm256_and_si256(v_rb, low16));
        let b = _mm256_cvtepi32_ps(_mm256_srli_epi32(v_rb, 16));
        let gr = _mm256_cvtepi32_ps(_mm256_and_si256(v_ga, low16));
        let a = _mm256_cvtepi32_ps(a_i);

        let o = g * 8;
        let tp = trans.as_mut_ptr().add(o);
        let t = _mm256_loadu_ps(tp);
        // Pixels whose transmittance drops to zero now (alive and fully opaque sample).
        let alive = _mm256_castps_si256(_mm256_cmp_ps::<_CMP_GT_OQ>(t, zero_f));
        let newly = _mm256_and_si256(alive, _mm256_cmpeq_epi32(a_i, opaque_a));
        count += (_mm256_movemask_ps(_mm256_castsi256_ps(newly)) as u32).count_ones();
        _mm256_storeu_ps(
            tp,
            _mm256_mul_ps(t, _mm256_sub_ps(one_f, _mm256_div_ps(a, f255))),
        );

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
        let px = [
            _mm256_permute2f128_ps::<0x20>(u0, u1),
            _mm256_permute2f128_ps::<0x20>(u2, u3),
            _mm256_permute2f128_ps::<0x31>(u0, u1),
            _mm256_permute2f128_ps::<0x31>(u2, u3),
        ];
        let ap = acc.as_mut_ptr().add(o) as *mut f32;
        for (k, c) in px.iter().enumerate() {
            let p = ap.add(k * 8);
            _mm256_storeu_ps(p, _mm256_add_ps(_mm256_loadu_ps(p), *c));
        }
        xs = _mm256_add_epi32(xs, step_x);
        ys = _mm256_add_epi32(ys, step_y);
    }
    *opaqued += count;
    groups * 8
}
