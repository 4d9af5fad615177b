//! Image quality metrics on 8-bit interleaved images.

/// Peak signal-to-noise ratio in dB between two equally sized 8-bit images (any channel
/// count), over all samples. Identical images give `f64::INFINITY`.
///
/// # Panics
/// When the buffers differ in length or are empty.
pub fn psnr(a: &[u8], b: &[u8]) -> f64 {
    assert_eq!(a.len(), b.len(), "psnr: images differ in size");
    assert!(!a.is_empty(), "psnr: empty images");
    let se: u64 = a
        .iter()
        .zip(b)
        .map(|(&x, &y)| {
            let d = x as i64 - y as i64;
            (d * d) as u64
        })
        .sum();
    if se == 0 {
        return f64::INFINITY;
    }
    let mse = se as f64 / a.len() as f64;
    10.0 * (255.0f64 * 255.0 / mse).log10()
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn known_values() {
        assert_eq!(psnr(&[1, 2, 3], &[1, 2, 3]), f64::INFINITY);
        // MSE 1 -> 20 log10(255) = 48.1308 dB.
        let p = psnr(&[10, 10], &[11, 9]);
        assert!((p - 20.0 * 255f64.log10()).abs() < 1e-12, "{p}");
    }
}
