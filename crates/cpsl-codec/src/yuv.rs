//! The colour-over-alpha picture of one layer: premultiplied colour converted to Y'CbCr
//! (BT.709, limited range, 4:2:0) in the top half, alpha as limited-range luma with neutral
//! chroma in the bottom half. Any 8-bit 4:2:0 decoder (browsers included) reproduces both
//! halves; the player reads alpha from the bottom half's luma.

use cpsl_core::PremulImage;

const KR: f32 = 0.2126;
const KB: f32 = 0.0722;
const KG: f32 = 1.0 - KR - KB;

/// A planar 4:2:0 picture: `width x height` luma, `width/2 x height/2` chroma, no padding.
#[derive(Debug, Clone, PartialEq)]
pub struct Yuv420 {
    /// Luma width (even).
    pub width: usize,
    /// Luma height (even).
    pub height: usize,
    /// Luma plane.
    pub y: Vec<u8>,
    /// Cb plane.
    pub u: Vec<u8>,
    /// Cr plane.
    pub v: Vec<u8>,
}

#[inline]
fn q(v: f32) -> u8 {
    v.round().clamp(0.0, 255.0) as u8
}

/// The even size a `width x height` layer is coded at (one half of the stacked picture).
pub fn coded_size(width: u32, height: u32) -> (usize, usize) {
    (
        width.next_multiple_of(2) as usize,
        height.next_multiple_of(2) as usize,
    )
}

/// Stacks a layer into its colour-over-alpha picture (`cw x 2ch`), replicating the last
/// column/row where the layer size is odd.
pub fn stack(img: &PremulImage) -> Yuv420 {
    let (w, h) = (img.width() as usize, img.height() as usize);
    let (cw, ch) = coded_size(img.width(), img.height());
    let (pw, ph) = (cw, 2 * ch);
    let px = img.as_bytes();
    let at = |x: usize, y: usize| {
        let o = (y.min(h - 1) * w + x.min(w - 1)) * 4;
        [px[o], px[o + 1], px[o + 2], px[o + 3]]
    };
    let mut y_plane = vec![0u8; pw * ph];
    let mut u = vec![128u8; pw / 2 * ph / 2];
    let mut v = vec![128u8; pw / 2 * ph / 2];
    for yy in 0..ch {
        for xx in 0..cw {
            let p = at(xx, yy);
            let luma = (KR * p[0] as f32 + KG * p[1] as f32 + KB * p[2] as f32) / 255.0;
            y_plane[yy * pw + xx] = q(16.0 + 219.0 * luma);
            y_plane[(yy + ch) * pw + xx] = q(16.0 + 219.0 * p[3] as f32 / 255.0);
        }
    }
    for by in 0..ch / 2 {
        for bx in 0..cw / 2 {
            let mut s = [0f32; 3];
            for (dx, dy) in [(0, 0), (1, 0), (0, 1), (1, 1)] {
                let p = at(2 * bx + dx, 2 * by + dy);
                for c in 0..3 {
                    s[c] += p[c] as f32 / (4.0 * 255.0);
                }
            }
            let luma = KR * s[0] + KG * s[1] + KB * s[2];
            u[by * pw / 2 + bx] = q(128.0 + 224.0 * (s[2] - luma) / (2.0 * (1.0 - KB)));
            v[by * pw / 2 + bx] = q(128.0 + 224.0 * (s[0] - luma) / (2.0 * (1.0 - KR)));
        }
    }
    Yuv420 {
        width: pw,
        height: ph,
        y: y_plane,
        u,
        v,
    }
}

/// Reads a `width x height` layer back from its colour-over-alpha picture. Colour is clamped
/// to alpha so that the result is a valid premultiplied image.
pub fn unstack(p: &Yuv420, width: u32, height: u32) -> PremulImage {
    let (w, h) = (width as usize, height as usize);
    let ch = p.height / 2;
    let mut out = vec![0u8; w * h * 4];
    for y in 0..h {
        for x in 0..w {
            let a = q((p.y[(y + ch) * p.width + x] as f32 - 16.0) * 255.0 / 219.0);
            let o = (y * w + x) * 4;
            out[o + 3] = a;
            if a == 0 {
                continue;
            }
            let luma = (p.y[y * p.width + x] as f32 - 16.0) / 219.0;
            let ci = (y / 2) * (p.width / 2) + x / 2;
            let cb = (p.u[ci] as f32 - 128.0) / 224.0;
            let cr = (p.v[ci] as f32 - 128.0) / 224.0;
            let r = luma + 2.0 * (1.0 - KR) * cr;
            let b = luma + 2.0 * (1.0 - KB) * cb;
            let g = (luma - KR * r - KB * b) / KG;
            for (c, val) in [r, g, b].into_iter().enumerate() {
                out[o + c] = q(val * 255.0).min(a);
            }
        }
    }
    PremulImage::from_premul(width, height, out).expect("colour clamped to alpha")
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn stack_then_unstack_is_close() {
        let (w, h) = (7u32, 5u32);
        let mut data = Vec::new();
        for i in 0..(w * h) as usize {
            let a = [0u8, 80, 255, 255, 200][i % 5];
            let c = [200u8, 30, 120];
            data.extend(c.iter().map(|&c| cpsl_core::image::premultiply(c, a)));
            data.push(a);
        }
        // Uniform 2x2 blocks keep chroma exact up to rounding: use a flat colour per pixel
        // family and compare with a tolerance that covers the 4:2:0 averaging.
        let img = PremulImage::from_premul(w, h, data).unwrap();
        let s = stack(&img);
        assert_eq!((s.width, s.height), (8, 12));
        let back = unstack(&s, w, h);
        for (i, (a, b)) in img.as_bytes().iter().zip(back.as_bytes()).enumerate() {
            if i % 4 == 3 {
                assert!((*a as i32 - *b as i32).abs() <= 1, "alpha {a} vs {b}");
            }
        }
        // A flat opaque image survives with every channel within 2 levels.
        let flat = PremulImage::from_rgb(6, 4, &[90u8, 160, 30].repeat(24)).unwrap();
        let back = unstack(&stack(&flat), 6, 4);
        for (a, b) in flat.as_bytes().iter().zip(back.as_bytes()) {
            assert!((*a as i32 - *b as i32).abs() <= 2, "{a} vs {b}");
        }
    }
}
