//! The bilinear filter of [`super::bilerp`] on eight pixels at once (AVX2), for the renderer's
//! spans and the P-frame warp: gathering each pixel's four taps from a padded texture and
//! blending them with the same 8-bit two-stage arithmetic, bit-identical to the scalar filter.
#![allow(unsafe_code)]

use std::arch::x86_64::*;

/// Whether the running CPU has AVX2.
pub fn available() -> bool {
    std::arch::is_x86_feature_detected!("avx2")
}

/// The four taps (top left, top right, bottom left, bottom right) of eight pixels whose top
/// left taps are the texels at `idx` in a texture of row pitch `pitch`. Lanes outside `valid`
/// (all bits set or none per 32-bit lane) read texel 0 and come back zero.
///
/// # Safety
/// AVX2 must be present, and for every lane in `valid`, and for texel 0, the texels at `idx`,
/// `idx + 1`, `idx + pitch` and `idx + pitch + 1` must lie inside `texels`.
#[inline]
#[target_feature(enable = "avx2")]
pub unsafe fn gather_taps(
    texels: &[u32],
    pitch: usize,
    idx: __m256i,
    valid: __m256i,
) -> [__m256i; 4] {
    let base = texels.as_ptr() as *const i32;
    let mut lane_idx = [0i32; 8];
    _mm256_storeu_si256(
        lane_idx.as_mut_ptr() as *mut __m256i,
        _mm256_and_si256(idx, valid),
    );
    // Each row's two taps are adjacent: one 64-bit load per pixel and row.
    let row = |off: usize| {
        // SAFETY: every index is 0 or a valid lane's, whose taps lie inside the texture (the
        // caller's promise).
        let q = |k: usize| unsafe {
            (base.add(lane_idx[k] as usize + off) as *const i64).read_unaligned()
        };
        (
            _mm256_setr_epi64x(q(0), q(1), q(2), q(3)),
            _mm256_setr_epi64x(q(4), q(5), q(6), q(7)),
        )
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
    [p00, p01, p10, p11]
}

/// The bilinear blend of eight pixels' taps ([`gather_taps`]) with 8-bit fractions `fx`,
/// `fy` (one per 32-bit lane, `0..=255`): R and B in the 16-bit halves of each lane of the
/// first result, G and A in those of the second, as [`super::bilerp`] computes them.
///
/// # Safety
/// AVX2 must be present.
#[inline]
#[target_feature(enable = "avx2")]
pub unsafe fn bilerp8(taps: [__m256i; 4], fx: __m256i, fy: __m256i) -> (__m256i, __m256i) {
    let lanes16 = _mm256_set1_epi32(0x00FF_00FF);
    let w256 = _mm256_set1_epi32(0x0100_0100);
    let round = _mm256_set1_epi32(0x0080_0080);
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
    let [p00, p01, p10, p11] = taps;
    let v_rb = lerp(
        lerp(rb(p00), rb(p01), wx0, wx1),
        lerp(rb(p10), rb(p11), wx0, wx1),
        wy0,
        wy1,
    );
    let v_ga = lerp(
        lerp(ga(p00), ga(p01), wx0, wx1),
        lerp(ga(p10), ga(p11), wx0, wx1),
        wy0,
        wy1,
    );
    (v_rb, v_ga)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn eight_at_once_equals_the_scalar_filter() {
        if !available() {
            eprintln!("skipping: no AVX2");
            return;
        }
        let (w, h) = (13usize, 7usize);
        let mut state = 7u64;
        let mut next = || {
            state = state
                .wrapping_mul(6364136223846793005)
                .wrapping_add(1442695040888963407);
            (state >> 33) as u32
        };
        let texels: Vec<u32> = (0..w * h).map(|_| next()).collect();
        for _ in 0..2000 {
            let pos: [(usize, usize, u32, u32); 8] = std::array::from_fn(|_| {
                (
                    next() as usize % (w - 1),
                    next() as usize % (h - 1),
                    next() % 256,
                    next() % 256,
                )
            });
            let valid_bits = next() as u8;
            let lane = |f: &dyn Fn(usize) -> i32| {
                let v: [i32; 8] = std::array::from_fn(f);
                // SAFETY: an unaligned load of eight i32.
                unsafe { _mm256_loadu_si256(v.as_ptr() as *const __m256i) }
            };
            // SAFETY: AVX2 is present; every tap of every lane is inside the texture.
            let (rb, ga) = unsafe {
                let idx = lane(&|k| (pos[k].1 * w + pos[k].0) as i32);
                let valid = lane(&|k| -((valid_bits >> k) as i32 & 1));
                let taps = gather_taps(&texels, w, idx, valid);
                bilerp8(taps, lane(&|k| pos[k].2 as i32), lane(&|k| pos[k].3 as i32))
            };
            let (mut a, mut b) = ([0u32; 8], [0u32; 8]);
            // SAFETY: unaligned stores of eight u32.
            unsafe {
                _mm256_storeu_si256(a.as_mut_ptr() as *mut __m256i, rb);
                _mm256_storeu_si256(b.as_mut_ptr() as *mut __m256i, ga);
            }
            for k in 0..8 {
                let (x, y, fx, fy) = pos[k];
                let t = |dx: usize, dy: usize| texels[(y + dy) * w + x + dx];
                let want = match (valid_bits >> k) & 1 {
                    1 => super::super::bilerp(
                        t(0, 0),
                        t(1, 0),
                        t(0, 1),
                        t(1, 1),
                        fx as u64,
                        fy as u64,
                    ),
                    _ => 0,
                };
                let got = (a[k] & 0xFFFF) as u64
                    | ((a[k] >> 16) as u64) << 16
                    | ((b[k] & 0xFFFF) as u64) << 32
                    | ((b[k] >> 16) as u64) << 48;
                assert_eq!(got, want, "lane {k}");
            }
        }
    }
}
