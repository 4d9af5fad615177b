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
    assert_eq!(data.len(), width * height * channels);
    assert_eq!(weight.len(), width * height);
    if !weight.iter().any(|&w| w > 0.0) {
        return false;
    }
    // Level 0 premultiplied by weight.
    let mut levels: Vec<(usize, usize, Vec<f32>, Vec<f32>)> = Vec::new();
    let mut c: Vec<f32> = data
        .chunks_exact(channels)
        .zip(weight)
        .flat_map(|(p, &w)| p.iter().map(move |v| v * w))
        .collect();
    let mut w = weight.to_vec();
    let (mut lw, mut lh) = (width, height);
    while lw > 1 || lh > 1 {
        let (nw, nh) = (lw.div_ceil(2), lh.div_ceil(2));
        let mut nc = vec![0f32; nw * nh * channels];
        let mut nwt = vec![0f32; nw * nh];
        for y in 0..lh {
            for x in 0..lw {
                let (i, j) = (y * lw + x, (y / 2) * nw + x / 2);
                nwt[j] += w[i];
                for k in 0..channels {
                    nc[j * channels + k] += c[i * channels + k];
                }
            }
        }
        // Normalise to weight <= 1, keeping colour premultiplied by the clamped weight.
        for j in 0..nw * nh {
            if nwt[j] > 1.0 {
                let s = 1.0 / nwt[j];
                for k in 0..channels {
                    nc[j * channels + k] *= s;
                }
                nwt[j] = 1.0;
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
        .chunks_exact(channels)
        .zip(&w)
        .flat_map(|(p, &wt)| p.iter().map(move |v| if wt > 0.0 { v / wt } else { 0.0 }))
        .collect();
    let (mut cw, mut ch) = (lw, lh);
    for (fw, fh, fc, fwt) in levels.into_iter().rev() {
        let mut out = vec![0f32; fw * fh * channels];
        for y in 0..fh {
            // Bilinear sample of the coarse level at the fine pixel centre.
            let sy = ((y as f32 + 0.5) / 2.0 - 0.5).clamp(0.0, (ch - 1) as f32);
            let y0 = sy as usize; // non-negative: truncation is the floor (no libm call)
            let y1 = (y0 + 1).min(ch - 1);
            let fy = sy - y0 as f32;
            for x in 0..fw {
                let sx = ((x as f32 + 0.5) / 2.0 - 0.5).clamp(0.0, (cw - 1) as f32);
                let x0 = sx as usize;
                let x1 = (x0 + 1).min(cw - 1);
                let fx = sx - x0 as f32;
                let i = y * fw + x;
                let wt = fwt[i];
                for k in 0..channels {
                    let s = |yy: usize, xx: usize| coarse[(yy * cw + xx) * channels + k];
                    let up = (s(y0, x0) * (1.0 - fx) + s(y0, x1) * fx) * (1.0 - fy)
                        + (s(y1, x0) * (1.0 - fx) + s(y1, x1) * fx) * fy;
                    // fc is premultiplied by wt: known part plus the missing share from above.
                    out[i * channels + k] = fc[i * channels + k] + (1.0 - wt) * up;
                }
            }
        }
        coarse = out;
        cw = fw;
        ch = fh;
    }
    for (i, wt) in weight.iter().enumerate() {
        if *wt < 1.0 {
            data[i * channels..(i + 1) * channels]
                .copy_from_slice(&coarse[i * channels..(i + 1) * channels]);
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
