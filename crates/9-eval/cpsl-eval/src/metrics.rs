//! Image quality metrics on 8-bit interleaved images.

pub use cpsl_core::image::psnr;

/// Sets the RGB pixels outside `keep` to black.
pub fn blacken(rgb: &mut [u8], keep: &[bool]) {
    for (px, _) in rgb.chunks_exact_mut(3).zip(keep).filter(|(_, k)| !**k) {
        px.fill(0);
    }
}

/// PSNR in dB over the pixels where `mask` is true (RGB, 3 bytes per pixel). `None` when the
/// mask is empty; `f64::INFINITY` when the masked pixels are identical.
pub fn psnr_masked(a: &[u8], b: &[u8], mask: &[bool]) -> Option<f64> {
    assert_eq!(a.len(), b.len(), "psnr_masked: images differ in size");
    assert_eq!(a.len(), mask.len() * 3, "psnr_masked: mask size");
    let (mut se, mut n) = (0u64, 0u64);
    for (i, _) in mask.iter().enumerate().filter(|(_, &m)| m) {
        for c in 0..3 {
            let d = a[i * 3 + c] as i64 - b[i * 3 + c] as i64;
            se += (d * d) as u64;
        }
        n += 3;
    }
    if n == 0 {
        return None;
    }
    if se == 0 {
        return Some(f64::INFINITY);
    }
    Some(10.0 * (255.0f64 * 255.0 / (se as f64 / n as f64)).log10())
}

/// Luma (BT.601) of an RGB image on the 0..255 scale.
fn luma(rgb: &[u8]) -> Vec<f64> {
    rgb.chunks_exact(3)
        .map(|p| 0.299 * p[0] as f64 + 0.587 * p[1] as f64 + 0.114 * p[2] as f64)
        .collect()
}

/// Separable Gaussian blur (σ = 1.5, 11 taps, edges clamped).
fn gauss(v: &[f64], w: usize, h: usize) -> Vec<f64> {
    let k: Vec<f64> = (-5i32..=5)
        .map(|i| (-(i * i) as f64 / (2.0 * 1.5 * 1.5)).exp())
        .collect();
    let s: f64 = k.iter().sum();
    let k: Vec<f64> = k.iter().map(|x| x / s).collect();
    let mut tmp = vec![0.0; v.len()];
    for y in 0..h {
        for x in 0..w {
            tmp[y * w + x] = (0..11)
                .map(|j| {
                    k[j] * v[y * w + (x as i64 + j as i64 - 5).clamp(0, w as i64 - 1) as usize]
                })
                .sum();
        }
    }
    let mut out = vec![0.0; v.len()];
    for y in 0..h {
        for x in 0..w {
            out[y * w + x] = (0..11)
                .map(|j| {
                    k[j] * tmp[(y as i64 + j as i64 - 5).clamp(0, h as i64 - 1) as usize * w + x]
                })
                .sum();
        }
    }
    out
}

/// SSIM (Wang et al. 2004) on BT.601 luma with an 11x11 Gaussian window (σ = 1.5),
/// K1 = 0.01, K2 = 0.03, L = 255, averaged over the pixels where `mask` is true (all pixels
/// when `mask` is `None`). Identical images give 1.
pub fn ssim(a: &[u8], b: &[u8], width: usize, height: usize, mask: Option<&[bool]>) -> f64 {
    assert_eq!(a.len(), width * height * 3, "ssim: image size");
    assert_eq!(a.len(), b.len(), "ssim: images differ in size");
    let (x, y) = (luma(a), luma(b));
    let xx: Vec<f64> = x.iter().map(|v| v * v).collect();
    let yy: Vec<f64> = y.iter().map(|v| v * v).collect();
    let xy: Vec<f64> = x.iter().zip(&y).map(|(p, q)| p * q).collect();
    let (mx, my) = (gauss(&x, width, height), gauss(&y, width, height));
    let (sxx, syy, sxy) = (
        gauss(&xx, width, height),
        gauss(&yy, width, height),
        gauss(&xy, width, height),
    );
    let (c1, c2) = ((0.01 * 255.0f64).powi(2), (0.03 * 255.0f64).powi(2));
    let (mut sum, mut n) = (0.0, 0usize);
    for i in 0..width * height {
        if mask.is_some_and(|m| !m[i]) {
            continue;
        }
        let (vx, vy, cxy) = (
            sxx[i] - mx[i] * mx[i],
            syy[i] - my[i] * my[i],
            sxy[i] - mx[i] * my[i],
        );
        sum += ((2.0 * mx[i] * my[i] + c1) * (2.0 * cxy + c2))
            / ((mx[i] * mx[i] + my[i] * my[i] + c1) * (vx + vy + c2));
        n += 1;
    }
    if n == 0 {
        f64::NAN
    } else {
        sum / n as f64
    }
}

#[cfg(test)]
mod ssim_tests {
    use super::*;

    fn noise(w: usize, h: usize, seed: u64) -> Vec<u8> {
        let mut s = seed;
        (0..w * h * 3)
            .map(|_| {
                s ^= s << 13;
                s ^= s >> 7;
                s ^= s << 17;
                (s >> 24) as u8
            })
            .collect()
    }

    #[test]
    fn ssim_known_cases() {
        let a = noise(32, 24, 1);
        assert!((ssim(&a, &a, 32, 24, None) - 1.0).abs() < 1e-12);
        // Independent noise images are nearly uncorrelated: SSIM close to 0.
        let b = noise(32, 24, 2);
        assert!(ssim(&a, &b, 32, 24, None).abs() < 0.1);
        // A constant offset of 10 on flat grey: structure and contrast terms are 1 and the
        // luminance term is (2*100*110 + C1) / (100^2 + 110^2 + C1), computed independently.
        let g1 = vec![100u8; 16 * 16 * 3];
        let g2 = vec![110u8; 16 * 16 * 3];
        let c1 = (0.01f64 * 255.0).powi(2);
        let expect = (2.0 * 100.0 * 110.0 + c1) / (100.0f64.powi(2) + 110.0f64.powi(2) + c1);
        assert!((ssim(&g1, &g2, 16, 16, None) - expect).abs() < 1e-9);
    }

    #[test]
    fn masked_psnr() {
        let a = [10u8, 10, 10, 50, 50, 50];
        let b = [11u8, 9, 10, 0, 0, 0];
        // Only the first pixel counts: squared errors 1, 1, 0 over 3 samples.
        let p = psnr_masked(&a, &b, &[true, false]).unwrap();
        assert!((p - 10.0 * (255.0f64 * 255.0 / (2.0 / 3.0)).log10()).abs() < 1e-9);
        assert_eq!(psnr_masked(&a, &b, &[false, false]), None);
    }
}
