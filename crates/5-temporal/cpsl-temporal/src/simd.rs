//! AVX2 kernel of the P-frame warp: eight samples per step.
//!
//! It computes exactly what the scalar kernel (`kernels::sample_scalar`) computes: the same
//! range test, the same taps from the edge-padded texels, the same two-stage 8-bit bilinear
//! filter in 16-bit lanes. A test checks bit-identity on random layers and positions.
#![allow(unsafe_code)]

pub(crate) use cpsl_core::resample::avx2::available;
use cpsl_core::resample::avx2::{bilerp8, gather_taps};
use std::arch::x86_64::*;

/// Samples whole groups of eight of the positions `xs`, `ys` (1/256 px) from `texels` (a
/// `w x h` layer with a one-pixel edge-repeating border, pitch `w + 2`) into `out` (RGBA,
/// four bytes per position); where a sample has content, `hid` says whether `owner` at the
/// nearest pixel is below `l`. Returns how many positions it handled; the caller finishes
/// the rest.
#[allow(clippy::too_many_arguments)]
pub(crate) fn sample_span(
    texels: &[u32],
    w: usize,
    h: usize,
    xs: &[i32],
    ys: &[i32],
    out: &mut [u8],
    hid: &mut [bool],
    owner: &[u8],
    l: usize,
) -> usize {
    assert_eq!(owner.len(), w * h);
    assert!(texels.len() >= (w + 2) * (h + 2) && w >= 1 && h >= 1);
    assert!((w + 2) * (h + 2) < i32::MAX as usize && w * 256 < i32::MAX as usize / 2);
    assert!(h * 256 < i32::MAX as usize / 2);
    let n = xs.len().min(ys.len()).min(out.len() / 4).min(hid.len());
    assert!(available());
    // SAFETY: AVX2 is present (checked above); the kernel reads `xs`, `ys` and writes `out`
    // only within the first `n / 8` groups of eight, which fit all three; it reads texels
    // only at indices that the range test proves to be inside the padded texture (invalid
    // lanes read index 0).
    unsafe { sample_avx2(texels, w, h, &xs[..n], &ys[..n], out, hid, owner, l) }
}

#[allow(clippy::too_many_arguments)]
#[target_feature(enable = "avx2")]
unsafe fn sample_avx2(
    texels: &[u32],
    w: usize,
    h: usize,
    xs: &[i32],
    ys: &[i32],
    out: &mut [u8],
    hid: &mut [bool],
    owner: &[u8],
    l: usize,
) -> usize {
    let groups = xs.len() / 8;
    let pitch = w + 2;
    let one = _mm256_set1_epi32(1);
    let below = _mm256_set1_epi32(-129);
    let lim_x = _mm256_set1_epi32((w * 256) as i32 - 127);
    let lim_y = _mm256_set1_epi32((h * 256) as i32 - 127);
    let pitch_v = _mm256_set1_epi32(pitch as i32);
    let byte = _mm256_set1_epi32(255);
    let zero = _mm256_setzero_si256();
    let seven = _mm256_set1_epi32(7);
    let eight = _mm256_set1_epi32(8);
    let base = texels.as_ptr() as *const i32;
    for g in 0..groups {
        let o = g * 8;
        let xi = _mm256_loadu_si256(xs.as_ptr().add(o) as *const __m256i);
        let yi = _mm256_loadu_si256(ys.as_ptr().add(o) as *const __m256i);
        // -128 <= xi <= 256 w - 128 and the same for y: within half a pixel of the image.
        let valid = _mm256_and_si256(
            _mm256_and_si256(_mm256_cmpgt_epi32(xi, below), _mm256_cmpgt_epi32(lim_x, xi)),
            _mm256_and_si256(_mm256_cmpgt_epi32(yi, below), _mm256_cmpgt_epi32(lim_y, yi)),
        );
        let tx = _mm256_add_epi32(_mm256_srai_epi32(xi, 8), one);
        let ty = _mm256_add_epi32(_mm256_srai_epi32(yi, 8), one);
        let idx = _mm256_and_si256(_mm256_add_epi32(_mm256_mullo_epi32(ty, pitch_v), tx), valid);
        // Where all eight positions are inside, on one texel row, and their left taps lie
        // within eight texels of the first (a near-unit step, the usual case), all taps come
        // from sixteen consecutive texels of each row: four loads and lane permutes instead
        // of sixteen scalar loads.
        let i0 = _mm256_cvtsi256_si32(idx);
        let d = _mm256_sub_epi32(idx, _mm256_set1_epi32(i0));
        // Left taps i0 .. i0 + 8 (right taps up to i0 + 9, still among the sixteen).
        let spread = _mm256_or_si256(_mm256_cmpgt_epi32(zero, d), _mm256_cmpgt_epi32(d, eight));
        let contiguous = _mm256_movemask_ps(_mm256_castsi256_ps(valid)) == 0xFF
            && _mm256_testz_si256(spread, spread) == 1
            && i0 as usize + pitch + 16 <= texels.len();
        let (p00, p01, p10, p11) = if contiguous {
            // SAFETY: i0 is a valid lane's index, and the last texel read, i0 + pitch + 15,
            // is inside the texture (checked just above).
            let load = |i: usize| _mm256_loadu_si256(base.add(i) as *const __m256i);
            let (a0, a1) = (load(i0 as usize), load(i0 as usize + 8));
            let (b0, b1) = (load(i0 as usize + pitch), load(i0 as usize + pitch + 8));
            let d1 = _mm256_add_epi32(d, one);
            // Texel i0 + d from the pair (lo: 0..8, hi: 8..16).
            let pick = |lo: __m256i, hi: __m256i, d: __m256i| {
                let high = _mm256_cmpgt_epi32(d, seven);
                _mm256_blendv_epi8(
                    _mm256_permutevar8x32_epi32(lo, d),
                    _mm256_permutevar8x32_epi32(hi, d),
                    high,
                )
            };
            (
                pick(a0, a1, d),
                pick(a0, a1, d1),
                pick(b0, b1, d),
                pick(b0, b1, d1),
            )
        } else {
            // SAFETY: valid lanes' taps lie inside the padded texture, and so do texel 0's.
            let [p00, p01, p10, p11] = gather_taps(texels, pitch, idx, valid);
            (p00, p01, p10, p11)
        };
        let any = _mm256_or_si256(_mm256_or_si256(p00, p01), _mm256_or_si256(p10, p11));
        let content = _mm256_xor_si256(_mm256_cmpeq_epi32(any, zero), _mm256_set1_epi32(-1));
        let mask = _mm256_movemask_ps(_mm256_castsi256_ps(content)) as u32;
        if mask == 0 {
            continue;
        }
        let fx = _mm256_and_si256(xi, byte);
        let fy = _mm256_and_si256(yi, byte);
        let (v_rb, v_ga) = bilerp8([p00, p01, p10, p11], fx, fy);
        let v = _mm256_or_si256(v_rb, _mm256_slli_epi32(v_ga, 8));
        // Lanes without content are zero, as the output already is.
        _mm256_storeu_si256(out.as_mut_ptr().add(o * 4) as *mut __m256i, v);
        if l == 0 {
            // No layer is nearer than the first.
            continue;
        }
        // The owner at the nearest pixel, clamped to the image.
        let half = _mm256_set1_epi32(128);
        let near = |v: __m256i, n: usize| {
            let p = _mm256_srai_epi32(_mm256_add_epi32(v, half), 8);
            _mm256_min_epi32(_mm256_max_epi32(p, zero), _mm256_set1_epi32(n as i32 - 1))
        };
        let at = _mm256_add_epi32(
            _mm256_mullo_epi32(near(yi, h), _mm256_set1_epi32(w as i32)),
            near(xi, w),
        );
        let mut at_idx = [0i32; 8];
        _mm256_storeu_si256(at_idx.as_mut_ptr() as *mut __m256i, at);
        // All eight lanes without branches (the content mask is irregular); lanes without
        // content stay false, as they already are.
        for (k, (hid, &at)) in hid[o..o + 8].iter_mut().zip(&at_idx).enumerate() {
            *hid = ((mask >> k) & 1 == 1) & ((owner[at as usize] as usize) < l);
        }
    }
    groups * 8
}
