//! AVX2 kernel for linear row spans: eight pixels per step.
//!
//! It computes exactly what the scalar path computes (same fixed-point positions, the same
//! 8-bit two-stage bilinear filter in 16-bit lanes, the same `f32` multiply-then-add
//! compositing and `1 - a / 255` transmittance), so renders are bit-identical with or without
//! it; a test checks that.
#![allow(unsafe_code)]

pub(crate) use cpsl_core::resample::avx2::available;
use cpsl_core::resample::avx2::{bilerp8, gather_taps};
use std::arch::x86_64::*;

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
    let low16 = _mm256_set1_epi32(0xFFFF);
    let zero_f = _mm256_setzero_ps();
    let one_f = _mm256_set1_ps(1.0);
    let f255 = _mm256_set1_ps(255.0);
    let opaque_a = _mm256_set1_epi32(255);
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
        // SAFETY: valid lanes' taps are inside the padded texture (above), and so are texel
        // 0's (the texture has at least two rows of `pitch` texels).
        let taps = gather_taps(texels, pitch, idx, valid);
        let [p00, p01, p10, p11] = taps;
        if _mm256_testz_si256(
            _mm256_or_si256(_mm256_or_si256(p00, p01), _mm256_or_si256(p10, p11)),
            minus_one,
        ) == 1
        {
            xs = _mm256_add_epi32(xs, step_x);
            ys = _mm256_add_epi32(ys, step_y);
            continue;
        }
        let (v_rb, v_ga) = bilerp8(taps, fx, fy);
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
