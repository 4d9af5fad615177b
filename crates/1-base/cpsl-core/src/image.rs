//! Premultiplied RGBA images.

use crate::error::CoreError;

/// An 8-bit RGBA image whose colour channels are premultiplied by alpha
/// (`colour <= alpha` for every pixel), stored row-major without padding.
#[derive(Clone, PartialEq, Eq)]
pub struct PremulImage {
    width: u32,
    height: u32,
    data: Vec<u8>,
}

impl std::fmt::Debug for PremulImage {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        write!(f, "PremulImage({}x{})", self.width, self.height)
    }
}

/// Premultiplies one straight-alpha channel value, rounding to nearest.
#[inline]
pub fn premultiply(c: u8, a: u8) -> u8 {
    ((c as u32 * a as u32 + 127) / 255) as u8
}

/// Recovers a straight-alpha channel value from a premultiplied one (0 when alpha is 0).
/// `premultiply(unpremultiply(p, a), a) == p` for every valid `p <= a`.
#[inline]
pub const fn unpremultiply(p: u8, a: u8) -> u8 {
    if a == 0 {
        return 0;
    }
    let v = (p as u32 * 255 + a as u32 / 2) / a as u32;
    if v > 255 {
        255
    } else {
        v as u8
    }
}

/// [`unpremultiply`] of every value (inner index) under every alpha (outer index): a table
/// lookup instead of a division per channel when a layer set is written.
static UNPREMULTIPLIED: [[u8; 256]; 256] = {
    let mut t = [[0u8; 256]; 256];
    let mut a = 0;
    while a < 256 {
        let mut p = 0;
        while p < 256 {
            t[a][p] = unpremultiply(p as u8, a as u8);
            p += 1;
        }
        a += 1;
    }
    t
};

/// `v.round().clamp(0.0, 255.0) as u8` (half away from zero; NaN gives 0) without the
/// library call that `f32::round` is on the baseline x86-64 target: in `[0, 255]` the
/// fraction after truncation is exact.
#[inline]
pub fn round_to_u8(v: f32) -> u8 {
    // Branch-free, so that loops over pixels vectorise (NaN stays NaN through the clamp and
    // truncates to 0).
    let c = v.clamp(0.0, 255.0);
    let t = c as u32;
    (t + u32::from(c - t as f32 >= 0.5)) as u8
}

/// Checks that a buffer holds `width * height * channels` values.
fn check_len(
    what: &str,
    width: u32,
    height: u32,
    channels: usize,
    found: usize,
) -> Result<(), CoreError> {
    let expected = width as usize * height as usize * channels;
    if found == expected {
        Ok(())
    } else {
        Err(CoreError::BufferLength {
            what: what.into(),
            expected,
            found,
        })
    }
}

impl PremulImage {
    /// A fully transparent image.
    pub fn new(width: u32, height: u32) -> Self {
        Self {
            width,
            height,
            data: vec![0; width as usize * height as usize * 4],
        }
    }

    /// Wraps premultiplied RGBA bytes, checking the length and the premultiplied invariant.
    pub fn from_premul(width: u32, height: u32, data: Vec<u8>) -> Result<Self, CoreError> {
        check_len("premultiplied image", width, height, 4, data.len())?;
        let img = Self {
            width,
            height,
            data,
        };
        img.check_premultiplied("premultiplied image")?;
        Ok(img)
    }

    /// Converts straight-alpha RGBA bytes to a premultiplied image.
    pub fn from_straight(width: u32, height: u32, rgba: &[u8]) -> Result<Self, CoreError> {
        check_len("straight RGBA image", width, height, 4, rgba.len())?;
        let mut data = rgba.to_vec();
        for px in data.chunks_exact_mut(4) {
            let a = px[3];
            for c in &mut px[..3] {
                *c = premultiply(*c, a);
            }
        }
        Ok(Self {
            width,
            height,
            data,
        })
    }

    /// An opaque image from RGB bytes.
    pub fn from_rgb(width: u32, height: u32, rgb: &[u8]) -> Result<Self, CoreError> {
        check_len("RGB image", width, height, 3, rgb.len())?;
        let mut data = Vec::with_capacity(rgb.len() / 3 * 4);
        for px in rgb.chunks_exact(3) {
            data.extend_from_slice(&[px[0], px[1], px[2], 255]);
        }
        Ok(Self {
            width,
            height,
            data,
        })
    }

    /// Width in pixels.
    pub fn width(&self) -> u32 {
        self.width
    }
    /// Height in pixels.
    pub fn height(&self) -> u32 {
        self.height
    }
    /// Premultiplied RGBA bytes, row-major.
    pub fn as_bytes(&self) -> &[u8] {
        &self.data
    }
    /// Mutable premultiplied RGBA bytes. Callers keep `colour <= alpha`.
    pub fn as_bytes_mut(&mut self) -> &mut [u8] {
        &mut self.data
    }
    /// Consumes the image, returning its bytes.
    pub fn into_bytes(self) -> Vec<u8> {
        self.data
    }
    /// The pixel at `(x, y)` (premultiplied RGBA).
    pub fn pixel(&self, x: u32, y: u32) -> [u8; 4] {
        let i = (y as usize * self.width as usize + x as usize) * 4;
        [
            self.data[i],
            self.data[i + 1],
            self.data[i + 2],
            self.data[i + 3],
        ]
    }
    /// Sets the pixel at `(x, y)` (premultiplied RGBA).
    pub fn set_pixel(&mut self, x: u32, y: u32, p: [u8; 4]) {
        let i = (y as usize * self.width as usize + x as usize) * 4;
        self.data[i..i + 4].copy_from_slice(&p);
    }

    /// Straight-alpha RGBA bytes (for PNG files).
    pub fn to_straight(&self) -> Vec<u8> {
        let mut out = self.data.clone();
        for px in out.chunks_exact_mut(4) {
            // Opaque pixels stay as they are (`unpremultiply(p, 255) == p`).
            let a = px[3];
            if a != 255 {
                let t = &UNPREMULTIPLIED[a as usize];
                for c in &mut px[..3] {
                    *c = t[*c as usize];
                }
            }
        }
        out
    }

    /// The coverage of a rendered view: per pixel, whether its alpha reaches `min_alpha`.
    pub fn covered(&self, min_alpha: u8) -> Vec<bool> {
        self.data
            .chunks_exact(4)
            .map(|p| p[3] >= min_alpha)
            .collect()
    }

    /// RGB bytes of this image composited over an opaque background colour.
    pub fn over_background(&self, bg: [u8; 3]) -> Vec<u8> {
        let mut out = Vec::with_capacity(self.data.len() / 4 * 3);
        for px in self.data.chunks_exact(4) {
            let t = 255 - px[3] as u32;
            for c in 0..3 {
                out.push((px[c] as u32 + (bg[c] as u32 * t + 127) / 255).min(255) as u8);
            }
        }
        out
    }

    /// RGB bytes of this image with what it leaves uncovered filled from what it covers: each
    /// pixel's remainder `1 - alpha` takes the push-pull fill ([`crate::fill::push_pull`]) of
    /// the image's own colours weighted by their alpha, as DIBR fills its holes. This is what a
    /// viewer shows where a new viewpoint looks past the layers' extent (beyond the frame's
    /// edge) instead of the background colour of [`Self::over_background`]. An image with no
    /// coverage at all comes out black.
    pub fn over_fill(&self) -> Vec<u8> {
        let n = self.data.len() / 4;
        if self.data.chunks_exact(4).all(|p| p[3] == 255) {
            return self.over_background([0, 0, 0]);
        }
        // Straight colour weighted by alpha: push-pull's level 0 multiplies them back to the
        // premultiplied colour.
        let mut colour = Vec::with_capacity(n * 3);
        let mut weight = Vec::with_capacity(n);
        for p in self.data.chunks_exact(4) {
            let a = p[3] as f32 / 255.0;
            let s = if p[3] > 0 { 1.0 / p[3] as f32 } else { 0.0 };
            colour.extend(p[..3].iter().map(|&c| c as f32 * s));
            weight.push(a);
        }
        if !crate::fill::push_pull(
            &mut colour,
            &weight,
            self.width as usize,
            self.height as usize,
            3,
        ) {
            return vec![0; n * 3];
        }
        // The fill already blends: a partly covered pixel holds its premultiplied colour plus
        // its remainder's share of the coarser levels.
        colour.iter().map(|&v| round_to_u8(v * 255.0)).collect()
    }

    /// Checks `colour <= alpha` everywhere.
    pub fn check_premultiplied(&self, what: &str) -> Result<(), CoreError> {
        // A branch-free scan first (on whole pixels as integers, so that it vectorises); the
        // slow one only to name the pixel.
        let bad = |px: &[u8]| {
            let p = u32::from_le_bytes([px[0], px[1], px[2], px[3]]);
            let a = p >> 24;
            ((p & 0xFF) > a) | ((p >> 8 & 0xFF) > a) | ((p >> 16 & 0xFF) > a)
        };
        if !self
            .data
            .chunks_exact(4)
            .fold(false, |any, px| any | bad(px))
        {
            return Ok(());
        }
        for (i, px) in self.data.chunks_exact(4).enumerate() {
            let m = px[0].max(px[1]).max(px[2]);
            if m > px[3] {
                let w = self.width.max(1) as usize;
                return Err(CoreError::NotPremultiplied {
                    what: what.into(),
                    x: (i % w) as u32,
                    y: (i / w) as u32,
                    colour: m,
                    alpha: px[3],
                });
            }
        }
        Ok(())
    }

    /// Fraction of pixels with non-zero alpha.
    pub fn coverage(&self) -> f64 {
        let n = self.data.chunks_exact(4).filter(|p| p[3] > 0).count();
        n as f64 / (self.width as f64 * self.height as f64).max(1.0)
    }
}

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
    fn over_fill_extends_the_covered_colours_into_the_rest() {
        // 16x16: the left six columns opaque (red above, green below), a half-covered blue
        // column, the rest uncovered.
        let mut img = PremulImage::new(16, 16);
        for y in 0..16 {
            for x in 0..6 {
                let p = if y < 8 {
                    [200, 0, 0, 255]
                } else {
                    [0, 200, 0, 255]
                };
                img.set_pixel(x, y, p);
            }
            img.set_pixel(6, y, [0, 0, 100, 128]);
        }
        let out = img.over_fill();
        let px = |x: usize, y: usize| &out[(y * 16 + x) * 3..][..3];
        assert_eq!(px(0, 0), [200, 0, 0], "covered pixels are kept");
        assert_eq!(px(5, 15), [0, 200, 0]);
        // The half-covered pixel keeps its blue and fills its remainder from its surroundings.
        assert!(px(6, 0)[2] >= 100 && px(6, 0)[0] > 20, "{:?}", px(6, 0));
        // Uncovered pixels take the colour of the covered ones nearby.
        let (top, bottom) = (px(7, 0), px(7, 15));
        assert!(
            top[0] > top[1] && bottom[1] > bottom[0],
            "{top:?} {bottom:?}"
        );
        assert!(out
            .chunks_exact(3)
            .all(|p| p.iter().map(|&c| c as u32).sum::<u32>() > 60));
        // Fully covered: as over any background; nothing covered: black.
        let mut full = PremulImage::new(2, 1);
        full.set_pixel(0, 0, [1, 2, 3, 255]);
        full.set_pixel(1, 0, [4, 5, 6, 255]);
        assert_eq!(full.over_fill(), full.over_background([9, 9, 9]));
        assert_eq!(PremulImage::new(2, 2).over_fill(), vec![0; 12]);
    }

    #[test]
    fn rounding_to_bytes_is_the_library_rounding() {
        let library = |v: f32| v.round().clamp(0.0, 255.0) as u8;
        let mut values: Vec<f32> = (-3000..=270_000).map(|i| i as f32 / 1024.0).collect();
        for k in -2..=256 {
            let half = k as f32 + 0.5;
            values.extend([
                half,
                half.next_up(),
                half.next_down(),
                k as f32,
                (k as f32).next_down(),
            ]);
        }
        values.extend([
            f32::NAN,
            f32::INFINITY,
            f32::NEG_INFINITY,
            -0.0,
            1e30,
            f32::MIN_POSITIVE,
        ]);
        for v in values {
            assert_eq!(round_to_u8(v), library(v), "{v:e}");
        }
    }

    #[test]
    fn straight_alpha_follows_the_division_for_every_value_and_alpha() {
        // Every (value, alpha) pair once, in each colour channel at a different place.
        let mut img = PremulImage::new(256, 256);
        for a in 0..=255u32 {
            for p in 0..=255u32 {
                let q = (p + 85) % 256;
                img.set_pixel(p, a, [p as u8, q as u8, (255 - p) as u8, a as u8]);
            }
        }
        let out = img.to_straight();
        let div = |p: u32, a: u32| match a {
            0 => 0,
            _ => ((p * 255 + a / 2) / a).min(255),
        };
        for (i, px) in out.chunks_exact(4).enumerate() {
            let (p, a) = ((i % 256) as u32, (i / 256) as u32);
            let q = (p + 85) % 256;
            let want = [div(p, a), div(q, a), div(255 - p, a), a].map(|v| v as u8);
            assert_eq!(px, want, "p={p} a={a}");
        }
    }

    #[test]
    fn premultiply_roundtrip_is_exact() {
        for a in 0..=255u8 {
            for p in 0..=a {
                assert_eq!(premultiply(unpremultiply(p, a), a), p, "p={p} a={a}");
            }
        }
    }

    #[test]
    fn straight_roundtrip() {
        let img = PremulImage::from_straight(2, 1, &[200, 100, 50, 128, 10, 20, 30, 255]).unwrap();
        let back = PremulImage::from_straight(2, 1, &img.to_straight()).unwrap();
        assert_eq!(img, back);
        assert!(PremulImage::from_premul(1, 1, vec![10, 0, 0, 5]).is_err());
        assert!(PremulImage::from_premul(1, 1, vec![0, 0, 0]).is_err());
    }

    #[test]
    fn psnr_known_values() {
        assert_eq!(psnr(&[1, 2, 3], &[1, 2, 3]), f64::INFINITY);
        // MSE 1 -> 20 log10(255) = 48.1308 dB.
        let p = psnr(&[10, 10], &[11, 9]);
        assert!((p - 20.0 * 255f64.log10()).abs() < 1e-12, "{p}");
    }
}
