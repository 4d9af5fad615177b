//! Push-pull hole filling (Gortler et al. 1996): known pixels are averaged down a pyramid and
//! unknown pixels are filled from coarser levels with bilinear upsampling, giving smooth,
//! plausible colour behind occluders.

/// Fills the pixels of `data` (`channels` interleaved `f32` values per pixel) whose `weight`
/// is below 1, from pixels with weight 1 (weights in `[0, 1]` blend partially known pixels).
/// Returns `false` when no pixel is known (nothing is changed then).
pub fn push_pull(
    data: &mut [f32],
    weight: &[f32],
    width: usize,
    height: usize,
    channels: usize,
) -> bool {
    // The common channel counts get their own copy of the loops, with constant strides.
    match channels {
        1 => fill(data, weight, width, height, 1),
        2 => fill(data, weight, width, height, 2),
        3 => fill(data, weight, width, height, 3),
        c => fill(data, weight, width, height, c),
    }
}

#[inline(always)]
fn fill(data: &mut [f32], weight: &[f32], width: usize, height: usize, ch: usize) -> bool {
    assert_eq!(data.len(), width * height * ch);
    assert_eq!(weight.len(), width * height);
    if !weight.iter().any(|&w| w > 0.0) {
        return false;
    }
    // Level 0 premultiplied by weight.
    let mut levels: Vec<(usize, usize, Vec<f32>, Vec<f32>)> = Vec::new();
    let mut c: Vec<f32> = data
        .chunks_exact(ch)
        .zip(weight)
        .flat_map(|(p, &w)| p.iter().map(move |v| v * w))
        .collect();
    let mut w = weight.to_vec();
    let (mut lw, mut lh) = (width, height);
    while lw > 1 || lh > 1 {
        let (nw, nh) = (lw.div_ceil(2), lh.div_ceil(2));
        let mut nc = vec![0f32; nw * nh * ch];
        let mut nwt = vec![0f32; nw * nh];
        // Each coarse pixel sums its 2x2 block, row by row.
        for y in 0..lh {
            let j = (y / 2) * nw;
            let (dst_c, dst_w) = (&mut nc[j * ch..(j + nw) * ch], &mut nwt[j..j + nw]);
            let (src_c, src_w) = (&c[y * lw * ch..(y + 1) * lw * ch], &w[y * lw..(y + 1) * lw]);
            for (x, (p, &wt)) in src_c.chunks_exact(ch).zip(src_w).enumerate() {
                dst_w[x / 2] += wt;
                for (d, v) in dst_c[(x / 2) * ch..(x / 2 + 1) * ch].iter_mut().zip(p) {
                    *d += v;
                }
            }
        }
        // Normalise to weight <= 1, keeping colour premultiplied by the clamped weight.
        for (p, wt) in nc.chunks_exact_mut(ch).zip(&mut nwt) {
            if *wt > 1.0 {
                let s = 1.0 / *wt;
                p.iter_mut().for_each(|v| *v *= s);
                *wt = 1.0;
            }
        }
        levels.push((
            lw,
            lh,
            std::mem::replace(&mut c, nc),
            std::mem::replace(&mut w, nwt),
        ));
        lw = nw;
        lh = nh;
    }
    // Top level: normalise (weight > 0 guaranteed since some pixel is known).
    let mut coarse: Vec<f32> = c
        .chunks_exact(ch)
        .zip(&w)
        .flat_map(|(p, &wt)| p.iter().map(move |v| if wt > 0.0 { v / wt } else { 0.0 }))
        .collect();
    let (mut cw, mut chh) = (lw, lh);
    // Where a fine pixel centre falls on the coarse level: the two taps and the weight of
    // the second (non-negative after the clamp: truncation is the floor, no libm call).
    let taps = |i: usize, n: usize| {
        let s = ((i as f32 + 0.5) / 2.0 - 0.5).clamp(0.0, (n - 1) as f32);
        let i0 = s as usize;
        (i0, (i0 + 1).min(n - 1), s - i0 as f32)
    };
    for (fw, fh, fc, fwt) in levels.into_iter().rev() {
        let mut out = vec![0f32; fw * fh * ch];
        let cols: Vec<(usize, usize, f32)> = (0..fw).map(|x| taps(x, cw)).collect();
        for y in 0..fh {
            // Bilinear sample of the coarse level at the fine pixel centre.
            let (y0, y1, fy) = taps(y, chh);
            let (r0, r1) = (
                &coarse[y0 * cw * ch..][..cw * ch],
                &coarse[y1 * cw * ch..][..cw * ch],
            );
            let row = y * fw;
            let (out_row, fc_row) = (&mut out[row * ch..][..fw * ch], &fc[row * ch..][..fw * ch]);
            for (x, &(x0, x1, fx)) in cols.iter().enumerate() {
                let wt = fwt[row + x];
                for k in 0..ch {
                    let up = (r0[x0 * ch + k] * (1.0 - fx) + r0[x1 * ch + k] * fx) * (1.0 - fy)
                        + (r1[x0 * ch + k] * (1.0 - fx) + r1[x1 * ch + k] * fx) * fy;
                    // fc is premultiplied by wt: known part plus the missing share from above.
                    out_row[x * ch + k] = fc_row[x * ch + k] + (1.0 - wt) * up;
                }
            }
        }
        coarse = out;
        cw = fw;
        chh = fh;
    }
    for ((d, p), wt) in data
        .chunks_exact_mut(ch)
        .zip(coarse.chunks_exact(ch))
        .zip(weight)
    {
        if *wt < 1.0 {
            d.copy_from_slice(p);
        }
    }
    true
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn keeps_known_and_fills_unknown_smoothly() {
        let (w, h) = (9, 7);
        let mut data = vec![0f32; w * h];
        let mut wt = vec![0f32; w * h];
        for y in 0..h {
            for x in 0..w {
                if x < 3 {
                    data[y * w + x] = 10.0;
                    wt[y * w + x] = 1.0;
                } else if x > 6 {
                    data[y * w + x] = 50.0;
                    wt[y * w + x] = 1.0;
                }
            }
        }
        assert!(push_pull(&mut data, &wt, w, h, 1));
        for y in 0..h {
            assert_eq!(data[y * w], 10.0);
            assert_eq!(data[y * w + 8], 50.0);
            for x in 3..7 {
                let v = data[y * w + x];
                assert!(
                    (10.0..=50.0).contains(&v),
                    "filled value {v} within the known range"
                );
            }
        }
        let mut none = vec![1f32; 4];
        assert!(!push_pull(&mut none, &[0.0; 4], 2, 2, 1));
    }
}
