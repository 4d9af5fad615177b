//! The resolution ladder of layer streams: under a tight budget a layer may be coded at a
//! half, a quarter or an eighth of the frame size (box-filtered), and is brought back to the frame size
//! after decoding by bilinear interpolation of its premultiplied RGBA. The browser player
//! (`web/src/render.ts`) upsamples with the same rule.

use cpsl_core::PremulImage;
use rayon::prelude::*;

/// The downscale factors a stream may be coded at, full size first.
pub const LADDER: [u32; 4] = [1, 2, 4, 8];

/// Smallest coded layer side a rung may have (SVT-AV1 refuses pictures under 64 pixels).
const MIN_SIDE: u32 = 64;

/// The size of a `width x height` layer coded at downscale `factor`.
pub fn scaled_size(width: u32, height: u32, factor: u32) -> (u32, u32) {
    (width.div_ceil(factor), height.div_ceil(factor))
}

/// The rungs of [`LADDER`] a `width x height` layer can be coded at (at least full size).
pub fn rungs(width: u32, height: u32) -> Vec<u32> {
    LADDER
        .into_iter()
        .filter(|&f| {
            let (w, h) = scaled_size(width, height, f);
            f == 1 || (w >= MIN_SIDE && h >= MIN_SIDE)
        })
        .collect()
}

/// Box-filters `img` down by `factor` (each output pixel the mean of its `factor x factor`
/// block, clipped at the border). Premultiplied averaging keeps colour within alpha.
pub fn downscale(img: &PremulImage, factor: u32) -> PremulImage {
    if factor == 1 {
        return img.clone();
    }
    let (w, h) = (img.width() as usize, img.height() as usize);
    let (sw, sh) = scaled_size(img.width(), img.height(), factor);
    let f = factor as usize;
    let src = img.as_bytes();
    let mut out = vec![0u8; sw as usize * sh as usize * 4];
    out.par_chunks_mut(sw as usize * 4)
        .enumerate()
        .for_each(|(oy, dst)| {
            // The block sums of the output row, its source rows added in turn.
            let ys = oy * f..((oy + 1) * f).min(h);
            let mut acc = vec![0u32; dst.len()];
            for y in ys.clone() {
                let row = &src[y * w * 4..][..w * 4];
                for (a, block) in acc.chunks_exact_mut(4).zip(row.chunks(4 * f)) {
                    for px in block.chunks_exact(4) {
                        for c in 0..4 {
                            a[c] += px[c] as u32;
                        }
                    }
                }
            }
            for (ox, (d, a)) in dst.chunks_exact_mut(4).zip(acc.chunks_exact(4)).enumerate() {
                let n = (ys.len() * (((ox + 1) * f).min(w) - ox * f)) as u32;
                // Whole blocks hold a power of two of pixels: a shift, not a division.
                let shift = n.is_power_of_two().then(|| n.trailing_zeros());
                for c in 0..4 {
                    let v = a[c] + n / 2;
                    d[c] = shift.map_or(v / n, |s| v >> s) as u8;
                }
            }
        });
    PremulImage::from_premul(sw, sh, out).expect("means of premultiplied pixels")
}

/// Bilinear upsampling of a layer coded at downscale `factor` back to `width x height`:
/// output pixel `x` reads the coded layer at `(x + 0.5) / factor - 0.5`, clamped to its edge.
/// A layer already at that size comes back as it is.
///
/// Separable and in fixed point: the weights are in 1/256 steps, every coded row is first
/// interpolated across (kept at 16 bits), and each output row blends two of those, rounding
/// once. Every channel of a pixel gets the same weights, so colour stays within alpha.
pub fn upscale(img: PremulImage, width: u32, height: u32, factor: u32) -> PremulImage {
    if factor == 1 && (img.width(), img.height()) == (width, height) {
        return img;
    }
    let (sw, sh) = (img.width() as usize, img.height() as usize);
    let src = img.as_bytes();
    // Per output coordinate: the two coded neighbours and the second's weight in 1/256.
    let taps = |n: u32, size: usize| -> Vec<(usize, usize, u32)> {
        (0..n)
            .map(|x| {
                let u = ((x as f32 + 0.5) / factor as f32 - 0.5).max(0.0);
                let x0 = (u.floor() as usize).min(size - 1);
                let x1 = (x0 + 1).min(size - 1);
                (x0, x1, ((u - u.floor()) * 256.0).round() as u32)
            })
            .collect()
    };
    let (tx, ty) = (taps(width, sw), taps(height, sh));
    let row = width as usize * 4;
    // Coded rows interpolated across, x256.
    let mut across = vec![0u16; sh * row];
    across
        .par_chunks_mut(row)
        .zip(src.par_chunks(sw * 4))
        .for_each(|(dst, s)| {
            for (d, &(x0, x1, w)) in dst.chunks_exact_mut(4).zip(&tx) {
                for c in 0..4 {
                    let (a, b) = (s[x0 * 4 + c] as u32, s[x1 * 4 + c] as u32);
                    d[c] = (a * (256 - w) + b * w) as u16;
                }
            }
        });
    let mut out = vec![0u8; height as usize * row];
    out.par_chunks_mut(row)
        .zip(&ty)
        .for_each(|(dst, &(y0, y1, w))| {
            let top = &across[y0 * row..][..row];
            let bottom = &across[y1 * row..][..row];
            for ((d, &t), &b) in dst.iter_mut().zip(top).zip(bottom) {
                *d = ((t as u32 * (256 - w) + b as u32 * w + (1 << 15)) >> 16) as u8;
            }
        });
    PremulImage::from_premul(width, height, out).expect("blends of premultiplied pixels")
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn downscaling_takes_the_rounded_mean_of_each_clipped_block() {
        let (w, h) = (75u32, 41u32);
        let data: Vec<u8> = (0..w * h)
            .flat_map(|i| {
                let a = ((i * 53) % 256) as u8;
                [a / 2, ((i * 13) % 256) as u8 % (a / 2 + 1), a / 5, a]
            })
            .collect();
        let img = PremulImage::from_premul(w, h, data).unwrap();
        for f in [2u32, 3, 4, 8] {
            let small = downscale(&img, f);
            assert_eq!((small.width(), small.height()), scaled_size(w, h, f));
            for (i, px) in small.as_bytes().chunks_exact(4).enumerate() {
                let (ox, oy) = (i as u32 % small.width(), i as u32 / small.width());
                let xs = ox * f..((ox + 1) * f).min(w);
                let ys = oy * f..((oy + 1) * f).min(h);
                let n = xs.len() * ys.len();
                for (c, &v) in px.iter().enumerate() {
                    let sum: usize = ys
                        .clone()
                        .flat_map(|y| xs.clone().map(move |x| (x, y)))
                        .map(|(x, y)| img.as_bytes()[((y * w + x) * 4) as usize + c] as usize)
                        .sum();
                    assert_eq!(v as usize, (sum + n / 2) / n, "factor {f} at {ox},{oy}");
                }
            }
        }
    }

    #[test]
    fn fixed_point_upscaling_matches_the_float_formula() {
        // Varied content at every rung: the float bilinear formula of the doc comment.
        let (w, h) = (75u32, 41u32);
        let data: Vec<u8> = (0..w * h)
            .flat_map(|i| {
                let a = ((i * 37) % 256) as u8;
                [a / 2, ((i * 11) % 256) as u8 % (a / 2 + 1), a / 3, a]
            })
            .collect();
        let img = PremulImage::from_premul(w, h, data).unwrap();
        for f in [2u32, 4, 8] {
            let small = downscale(&img, f);
            let (sw, sh) = (small.width() as usize, small.height() as usize);
            let up = upscale(small.clone(), w, h, f);
            let s = small.as_bytes();
            let pos = |x: u32, n: usize| {
                let u = ((x as f32 + 0.5) / f as f32 - 0.5).max(0.0);
                let x0 = (u.floor() as usize).min(n - 1);
                (x0, (x0 + 1).min(n - 1), u - u.floor())
            };
            for y in 0..h {
                let (y0, y1, fy) = pos(y, sh);
                for x in 0..w {
                    let (x0, x1, fx) = pos(x, sw);
                    for c in 0..4 {
                        let at = |xx: usize, yy: usize| s[(yy * sw + xx) * 4 + c] as f32;
                        let top = at(x0, y0) * (1.0 - fx) + at(x1, y0) * fx;
                        let bottom = at(x0, y1) * (1.0 - fx) + at(x1, y1) * fx;
                        let want = top * (1.0 - fy) + bottom * fy;
                        let got = up.as_bytes()[((y * w + x) * 4) as usize + c] as f32;
                        assert!(
                            (got - want).abs() <= 1.0,
                            "x{f} ({x}, {y}) {c}: {got} {want}"
                        );
                    }
                }
            }
        }
    }

    #[test]
    fn rungs_keep_coded_sides_of_64() {
        assert_eq!(rungs(1920, 1080), vec![1, 2, 4, 8]);
        assert_eq!(rungs(640, 480), vec![1, 2, 4]);
        assert_eq!(rungs(320, 240), vec![1, 2]);
        assert_eq!(rungs(100, 60), vec![1]);
        assert_eq!(scaled_size(541, 961, 2), (271, 481));
    }

    #[test]
    fn down_then_up_keeps_smooth_content_and_premultiplication() {
        let (w, h) = (37u32, 23u32);
        let mut data = Vec::new();
        for y in 0..h {
            for x in 0..w {
                let a = (x * 255 / (w - 1)) as u8;
                let c = (y * 200 / (h - 1)) as u8;
                data.extend([c.min(a), (c / 2).min(a), 0, a]);
            }
        }
        let img = PremulImage::from_premul(w, h, data).unwrap();
        for f in LADDER {
            let small = downscale(&img, f);
            assert_eq!((small.width(), small.height()), scaled_size(w, h, f));
            let back = upscale(small, w, h, f);
            // A linear ramp survives up to the clipped border blocks.
            for y in f..h - f {
                for x in f..w - f {
                    let o = ((y * w + x) * 4 + 3) as usize;
                    let (a, b) = (img.as_bytes()[o], back.as_bytes()[o]);
                    assert!(
                        (a as i32 - b as i32).abs() <= 2,
                        "factor {f} ({x}, {y}): {a} {b}"
                    );
                }
            }
        }
        // A constant image stays constant at every rung, edges included.
        let flat =
            PremulImage::from_premul(w, h, [60u8, 20, 5, 90].repeat((w * h) as usize)).unwrap();
        for f in LADDER {
            assert_eq!(upscale(downscale(&flat, f), w, h, f), flat);
        }
    }
}
