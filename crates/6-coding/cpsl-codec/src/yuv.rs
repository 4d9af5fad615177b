//! The colour-over-alpha picture of one layer: premultiplied colour converted to Y'CbCr
//! (BT.709, limited range, 4:2:0) in the top half, alpha as limited-range luma with neutral
//! chroma in the bottom half. Any 8-bit 4:2:0 decoder (browsers included) reproduces both
//! halves; the player reads alpha from the bottom half's luma.

use cpsl_core::ycbcr::{Matrix, ToRgb};
use cpsl_core::PremulImage;
use rayon::prelude::*;

/// A planar 4:2:0 picture: `width x height` luma, `width/2 x height/2` chroma, no padding.
/// Samples are 8-bit (`u8`) or 10-bit (`u16`, values up to 1023).
#[derive(Debug, Clone, PartialEq)]
pub struct Yuv420<T = u8> {
    /// Luma width (even).
    pub width: usize,
    /// Luma height (even).
    pub height: usize,
    /// Luma plane.
    pub y: Vec<T>,
    /// Cb plane.
    pub u: Vec<T>,
    /// Cr plane.
    pub v: Vec<T>,
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
    let w = img.width() as usize;
    let px = img.as_bytes();
    stack_with(img.width(), img.height(), |y, row| {
        let src = &px[y * w * 4..(y + 1) * w * 4];
        for (d, s) in row.iter_mut().zip(src.chunks_exact(4)) {
            *d = [s[0], s[1], s[2], s[3]];
        }
    })
}

/// Stacks any colour image (3 bytes per pixel) over any 8-bit grey image of the same size, in
/// the layout of [`stack`] (the DIBR baseline codes colour over quantised inverse depth).
pub fn stack_colour_grey(rgb: &[u8], grey: &[u8], width: u32, height: u32) -> Yuv420 {
    let (w, h) = (width as usize, height as usize);
    assert!(
        rgb.len() == w * h * 3 && grey.len() == w * h,
        "stack: plane sizes"
    );
    stack_with(width, height, |y, row| {
        let (rgb, grey) = (&rgb[y * w * 3..(y + 1) * w * 3], &grey[y * w..(y + 1) * w]);
        for ((d, c), &g) in row.iter_mut().zip(rgb.chunks_exact(3)).zip(grey) {
            *d = [c[0], c[1], c[2], g];
        }
    })
}

/// The colour (RGB) and grey planes of a picture made by [`stack_colour_grey`].
pub fn unstack_colour_grey(p: &Yuv420, width: u32, height: u32) -> (Vec<u8>, Vec<u8>) {
    let (w, h) = (width as usize, height as usize);
    let mut rgb = vec![0u8; w * h * 3];
    let mut grey = vec![0u8; w * h];
    let t = tables();
    for y in 0..h {
        let (luma, g, u, v) = rows_of(p, y, w);
        for x in 0..w {
            let i = y * w + x;
            grey[i] = t.grey[g[x] as usize];
            rgb[i * 3..i * 3 + 3].copy_from_slice(&t.rgb.rgb(luma[x], u[x / 2], v[x / 2]));
        }
    }
    (rgb, grey)
}

/// Limited-range 10-bit luma: the 16-bit grey code 0 is luma 64, 65535 is luma 940.
const DEEP_LUMA: (f64, f64) = (64.0, 876.0);

/// Stacks a colour image (3 bytes per pixel) over a 16-bit grey image into a 10-bit picture in
/// the layout of [`stack`]: the colour as [`stack_colour_grey`] makes it, scaled to 10 bits,
/// and the grey with the 877 luma levels of 10-bit limited range (the DIBR baseline's deep
/// depth: a 16-bit depth map coded by a 10-bit video stream).
pub fn stack_colour_grey16(rgb: &[u8], grey: &[u16], width: u32, height: u32) -> Yuv420<u16> {
    let (w, h) = (width as usize, height as usize);
    assert!(grey.len() == w * h, "stack: plane sizes");
    let colour = stack_colour_grey(rgb, &vec![0; w * h], width, height);
    let up = |v: &[u8]| v.iter().map(|&s| u16::from(s) << 2).collect::<Vec<u16>>();
    let mut p = Yuv420 {
        width: colour.width,
        height: colour.height,
        y: up(&colour.y),
        u: up(&colour.u),
        v: up(&colour.v),
    };
    let ch = p.height / 2;
    let (base, span) = DEEP_LUMA;
    for yy in 0..ch {
        for xx in 0..p.width {
            let g = grey[yy.min(h - 1) * w + xx.min(w - 1)] as f64 / 65535.0;
            p.y[(yy + ch) * p.width + xx] = (base + span * g).round() as u16;
        }
    }
    p
}

/// The colour (RGB) and 16-bit grey planes of a picture made by [`stack_colour_grey16`].
pub fn unstack_colour_grey16(p: &Yuv420<u16>, width: u32, height: u32) -> (Vec<u8>, Vec<u16>) {
    let (w, h) = (width as usize, height as usize);
    let down = |v: &[u16]| {
        v.iter()
            .map(|&s| ((s + 2) >> 2).min(255) as u8)
            .collect::<Vec<u8>>()
    };
    let colour = Yuv420 {
        width: p.width,
        height: p.height,
        y: down(&p.y),
        u: down(&p.u),
        v: down(&p.v),
    };
    let (rgb, _) = unstack_colour_grey(&colour, width, height);
    let ch = p.height / 2;
    let (base, span) = DEEP_LUMA;
    let grey = (0..w * h)
        .map(|i| {
            let l = p.y[(i / w + ch) * p.width + i % w] as f64;
            (((l - base) / span).clamp(0.0, 1.0) * 65535.0).round() as u16
        })
        .collect();
    (rgb, grey)
}

/// The forward BT.709 limited-range conversion in fixed point (16 fractional bits): luma from
/// one pixel's RGB, chroma from the sums of a 2x2 block's RGB (4:2:0, the block's mean). One
/// rounding per sample, where the float formula cost a libm `roundf` each.
struct Forward {
    y: [i32; 3],
    cb: [i32; 3],
    cr: [i32; 3],
}

impl Forward {
    const fn fixed(v: f64) -> i32 {
        let v = v * 65536.0;
        (if v < 0.0 { v - 0.5 } else { v + 0.5 }) as i32
    }

    const fn new() -> Self {
        let Matrix { kr, kb } = Matrix::BT709;
        let kg = 1.0 - kr - kb;
        // Per unit of an 8-bit sample, and per unit of a sum of four for chroma.
        let (ys, cbs, crs) = (
            219.0 / 255.0,
            224.0 / (2.0 * (1.0 - kb)) / 1020.0,
            224.0 / (2.0 * (1.0 - kr)) / 1020.0,
        );
        let f = Self::fixed;
        Self {
            y: [f(ys * kr), f(ys * kg), f(ys * kb)],
            cb: [f(-cbs * kr), f(-cbs * kg), f(cbs * (1.0 - kb))],
            cr: [f(crs * (1.0 - kr)), f(-crs * kg), f(-crs * kb)],
        }
    }

    #[inline]
    fn dot(c: &[i32; 3], p: [i32; 3], offset: i32) -> u8 {
        ((c[0] * p[0] + c[1] * p[1] + c[2] * p[2] + (offset << 16) + 32768) >> 16).clamp(0, 255)
            as u8
    }

    #[inline]
    fn luma(&self, p: [u8; 4]) -> u8 {
        Self::dot(&self.y, [p[0], p[1], p[2]].map(i32::from), 16)
    }

    /// Cb and Cr of the sums of a block's four pixels.
    #[inline]
    fn chroma(&self, sum: [i32; 3]) -> (u8, u8) {
        (Self::dot(&self.cb, sum, 128), Self::dot(&self.cr, sum, 128))
    }
}

const FORWARD: Forward = Forward::new();

/// An 8-bit grey value as limited-range luma (`16 + 219 g / 255`, rounded; never a tie).
#[inline]
fn grey_luma(g: u8) -> u8 {
    (16 + (219 * u32::from(g) + 127) / 255) as u8
}

/// Luma of black and of zero grey (limited range).
const ZERO_LUMA: u8 = 16;

/// The stacking of [`stack`] with row `y` of the image read as `[r, g, b, grey]` pixels by
/// `row` (into the first `width` of a row of the coded width; the last pixel is then
/// replicated where that is odd, as is the last row), rows of 2x2 blocks in parallel.
fn stack_with(width: u32, height: u32, row: impl Fn(usize, &mut [[u8; 4]]) + Sync) -> Yuv420 {
    let (cw, ch) = coded_size(width, height);
    let (w, h) = (width as usize, height as usize);
    let (pw, ph) = (cw, 2 * ch);
    let mut y_plane = vec![0u8; pw * ph];
    let mut u = vec![128u8; pw / 2 * ph / 2];
    let mut v = vec![128u8; pw / 2 * ph / 2];
    let (colour, grey) = y_plane.split_at_mut(pw * ch);
    let f = &FORWARD;
    colour
        .par_chunks_mut(2 * pw)
        .zip(grey.par_chunks_mut(2 * pw))
        .zip(u.par_chunks_mut(pw / 2).zip(v.par_chunks_mut(pw / 2)))
        .enumerate()
        .for_each_init(
            || vec![[0u8; 4]; 2 * cw],
            |rows, (by, ((colour, grey), (u, v)))| {
                let (r0, r1) = rows.split_at_mut(cw);
                for (r, y) in [(&mut *r0, 2 * by), (&mut *r1, (2 * by + 1).min(h - 1))] {
                    row(y, &mut r[..w]);
                    if w < cw {
                        r[w] = r[w - 1];
                    }
                }
                let (c0, c1) = colour.split_at_mut(pw);
                let (g0, g1) = grey.split_at_mut(pw);
                let blocks = r0.chunks_exact(2).zip(r1.chunks_exact(2));
                let luma = c0.chunks_exact_mut(2).zip(c1.chunks_exact_mut(2));
                let alpha = g0.chunks_exact_mut(2).zip(g1.chunks_exact_mut(2));
                let chroma = u.iter_mut().zip(v.iter_mut());
                for ((((a, b), (la, lb)), (ga, gb)), (cu, cv)) in
                    blocks.zip(luma).zip(alpha).zip(chroma)
                {
                    // A block that is all zero (transparent, most of a layer) keeps the
                    // conversion of zero: the planes' initial values but for luma.
                    if a == [[0; 4]; 2] && b == [[0; 4]; 2] {
                        for l in [la, lb, ga, gb] {
                            l.fill(ZERO_LUMA);
                        }
                        continue;
                    }
                    let mut sum = [0i32; 3];
                    for (src, (l, g)) in [a, b].into_iter().zip([(la, ga), (lb, gb)]) {
                        for (p, (l, g)) in src.iter().zip(l.iter_mut().zip(g.iter_mut())) {
                            *l = f.luma(*p);
                            *g = grey_luma(p[3]);
                            for c in 0..3 {
                                sum[c] += i32::from(p[c]);
                            }
                        }
                    }
                    (*cu, *cv) = f.chroma(sum);
                }
            },
        );
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
    let w = width as usize;
    let mut img = PremulImage::new(width, height);
    let t = tables();
    img.as_bytes_mut()
        .par_chunks_exact_mut(w * 4)
        .enumerate()
        .for_each(|(y, out)| {
            let (luma, grey, u, v) = rows_of(p, y, w);
            // Two pixels share a chroma sample (the last one alone where the width is odd).
            let pairs = out.chunks_mut(8).zip(luma.chunks(2)).zip(grey.chunks(2));
            for (((px, l), g), (&cb, &cr)) in pairs.zip(u.iter().zip(v)) {
                // A transparent pair stays zero (most of a layer).
                if g.iter().all(|&g| t.grey[g as usize] == 0) {
                    continue;
                }
                let chroma = t.rgb.chroma(cb, cr);
                for ((px, &l), &g) in px.chunks_exact_mut(4).zip(l).zip(g) {
                    let (c, a) = (t.rgb.rgb_with(l, chroma), t.grey[g as usize]);
                    px.copy_from_slice(&[c[0].min(a), c[1].min(a), c[2].min(a), a]);
                }
            }
        });
    img
}

/// Row `y` of a stacked picture: colour luma, grey, and the chroma rows (`w` wide).
fn rows_of(p: &Yuv420, y: usize, w: usize) -> (&[u8], &[u8], &[u8], &[u8]) {
    let (ch, cw) = (p.height / 2, p.width / 2);
    (
        &p.y[y * p.width..][..w],
        &p.y[(y + ch) * p.width..][..w],
        &p.u[(y / 2) * cw..][..cw],
        &p.v[(y / 2) * cw..][..cw],
    )
}

/// The BT.709 limited-range conversion back to 8-bit RGB, and the alpha half's luma back to
/// an 8-bit value.
struct Tables {
    rgb: ToRgb,
    /// Limited-range luma as an 8-bit full-range value (the alpha half).
    grey: [u8; 256],
}

fn tables() -> &'static Tables {
    static TABLES: std::sync::OnceLock<Tables> = std::sync::OnceLock::new();
    TABLES.get_or_init(|| {
        let mut grey = [0; 256];
        for (v, g) in grey.iter_mut().enumerate() {
            *g = q((v as f32 - 16.0) * 255.0 / 219.0);
        }
        Tables {
            rgb: ToRgb::new(Matrix::BT709, false),
            grey,
        }
    })
}

#[cfg(test)]
mod tests {
    use super::*;

    const KR: f32 = Matrix::BT709.kr as f32;
    const KB: f32 = Matrix::BT709.kb as f32;
    const KG: f32 = 1.0 - KR - KB;

    #[test]
    fn fixed_point_stacking_matches_the_float_formula() {
        // The forward formula in f64, rounded once per sample: the fixed point gives the same
        // samples.
        let r = |v: f64| v.round().clamp(0.0, 255.0) as u8;
        let Matrix { kr, kb } = Matrix::BT709;
        let kg = 1.0 - kr - kb;
        let luma = |p: [f64; 3]| (kr * p[0] + kg * p[1] + kb * p[2]) / 255.0;
        // Odd size: the last column and row are replicated.
        let (w, h) = (37u32, 23u32);
        let mut seed = 0x2545_f491_u32;
        let mut next = || {
            seed ^= seed << 13;
            seed ^= seed >> 17;
            seed ^= seed << 5;
            seed
        };
        let data: Vec<u8> = (0..w * h)
            .flat_map(|_| {
                let a = (next() % 256) as u8;
                let c = next().to_le_bytes();
                [0, 1, 2]
                    .map(|i| cpsl_core::image::premultiply(c[i], a))
                    .into_iter()
                    .chain([a])
            })
            .collect();
        let img = PremulImage::from_premul(w, h, data).unwrap();
        let p = stack(&img);
        let (cw, ch) = coded_size(w, h);
        let at = |x: usize, y: usize| img.pixel((x as u32).min(w - 1), (y as u32).min(h - 1));
        let check = |got: u8, want: u8| assert_eq!(got, want);
        for y in 0..ch {
            for x in 0..cw {
                let q = at(x, y).map(f64::from);
                check(p.y[y * cw + x], r(16.0 + 219.0 * luma([q[0], q[1], q[2]])));
                check(p.y[(y + ch) * cw + x], r(16.0 + 219.0 * q[3] / 255.0));
            }
        }
        for by in 0..ch / 2 {
            for bx in 0..cw / 2 {
                let mut s = [0.0; 3];
                for (dx, dy) in [(0, 0), (1, 0), (0, 1), (1, 1)] {
                    let q = at(2 * bx + dx, 2 * by + dy);
                    for c in 0..3 {
                        s[c] += f64::from(q[c]) / 4.0;
                    }
                }
                let l = luma(s);
                let i = by * cw / 2 + bx;
                check(
                    p.u[i],
                    r(128.0 + 224.0 * (s[2] / 255.0 - l) / (2.0 * (1.0 - kb))),
                );
                check(
                    p.v[i],
                    r(128.0 + 224.0 * (s[0] / 255.0 - l) / (2.0 * (1.0 - kr))),
                );
            }
        }
    }

    #[test]
    fn the_tables_match_the_float_conversion() {
        // The BT.709 limited-range formula in floating point, rounded once per channel.
        let float = |y: u8, u: u8, v: u8| {
            let luma = (y as f32 - 16.0) / 219.0;
            let (cb, cr) = ((u as f32 - 128.0) / 224.0, (v as f32 - 128.0) / 224.0);
            let r = luma + 2.0 * (1.0 - KR) * cr;
            let b = luma + 2.0 * (1.0 - KB) * cb;
            let g = (luma - KR * r - KB * b) / KG;
            [r, g, b].map(|c| q(c * 255.0))
        };
        let mut worst = 0;
        for y in (0..=255u8).step_by(3) {
            for u in (0..=255u8).step_by(5) {
                for v in (0..=255u8).step_by(5) {
                    // A 2x2 opaque layer of one colour.
                    let p = Yuv420 {
                        width: 2,
                        height: 4,
                        y: [[y; 4], [235; 4]].concat(),
                        u: vec![u],
                        v: vec![v],
                    };
                    let (rgb, alpha) = unstack_colour_grey(&p, 2, 2);
                    assert_eq!(alpha, [255; 4]);
                    // The layer path (opaque: colour as it is) agrees.
                    assert_eq!(&unstack(&p, 2, 2).as_bytes()[..3], &rgb[..3]);
                    for (a, b) in rgb[..3].iter().zip(float(y, u, v)) {
                        worst = worst.max((*a as i32 - b as i32).abs());
                    }
                }
            }
        }
        assert!(worst <= 1, "{worst} levels off");
    }

    #[test]
    fn transparent_blocks_take_the_conversion_of_zero() {
        // 2x2 blocks all transparent, one pixel transparent, none; the picture is the same as
        // the conversion of each pixel gives.
        let (w, h) = (6u32, 4u32);
        let data: Vec<u8> = (0..w * h)
            .flat_map(|i| {
                let (x, y) = (i % w, i / w);
                let clear = match x / 2 {
                    0 => true,
                    1 => (x, y) == (2, 0),
                    _ => false,
                };
                if clear {
                    [0; 4]
                } else {
                    [40, 90, 200, 255]
                }
            })
            .collect();
        let p = stack(&PremulImage::from_premul(w, h, data.clone()).unwrap());
        let f = &FORWARD;
        let px = |x: usize, y: usize| {
            let o = (y * w as usize + x) * 4;
            [data[o], data[o + 1], data[o + 2], data[o + 3]]
        };
        let ch = p.height / 2;
        for y in 0..ch {
            for x in 0..p.width {
                assert_eq!(p.y[y * p.width + x], f.luma(px(x, y)));
                assert_eq!(p.y[(y + ch) * p.width + x], grey_luma(px(x, y)[3]));
            }
        }
        for by in 0..ch / 2 {
            for bx in 0..p.width / 2 {
                let mut sum = [0i32; 3];
                for (dx, dy) in [(0, 0), (1, 0), (0, 1), (1, 1)] {
                    let q = px(2 * bx + dx, 2 * by + dy);
                    (0..3).for_each(|c| sum[c] += i32::from(q[c]));
                }
                let i = by * p.width / 2 + bx;
                assert_eq!((p.u[i], p.v[i]), f.chroma(sum));
            }
        }
        assert_eq!(p.y[0], ZERO_LUMA);
    }

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

    #[test]
    fn colour_over_grey_round_trips() {
        let (w, h) = (6u32, 4u32);
        // Flat colour per 2x2 block so that 4:2:0 keeps chroma; any grey value.
        let rgb: Vec<u8> = (0..w * h)
            .flat_map(|i| {
                let b = ((i % w) / 2 + (i / w) / 2 * 3) as u8;
                [40 + 30 * b, 200 - 20 * b, 90 + 10 * b]
            })
            .collect();
        let grey: Vec<u8> = (0..w * h).map(|i| (i * 11 % 256) as u8).collect();
        let (r2, g2) = unstack_colour_grey(&stack_colour_grey(&rgb, &grey, w, h), w, h);
        for (a, b) in rgb.iter().zip(&r2) {
            assert!((*a as i32 - *b as i32).abs() <= 2, "colour {a} vs {b}");
        }
        for (a, b) in grey.iter().zip(&g2) {
            // 219 luma levels for 256 grey values.
            assert!((*a as i32 - *b as i32).abs() <= 1, "grey {a} vs {b}");
        }
        // 16-bit grey in 10 bits: 877 levels, so within 65535 / 876 / 2 (37.4).
        let deep: Vec<u16> = (0..w * h).map(|i| (i * 2851 % 65536) as u16).collect();
        let (r3, g3) = unstack_colour_grey16(&stack_colour_grey16(&rgb, &deep, w, h), w, h);
        assert_eq!(r3, r2, "the same colour as 8 bits");
        for (a, b) in deep.iter().zip(&g3) {
            assert!((*a as i32 - *b as i32).abs() <= 38, "grey {a} vs {b}");
        }
        assert!(g3.iter().any(|&g| g % 256 != 0), "finer than 8 bits");
    }
}
