//! Y'CbCr to 8-bit RGB in fixed point: the conversion of every decoded picture (the layer
//! streams' BT.709 limited range, and input video in whatever matrix and range it declares).

/// The luma coefficients `K_R`, `K_B` of a Y'CbCr matrix (`K_G = 1 - K_R - K_B`).
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Matrix {
    /// Red's weight in luma.
    pub kr: f64,
    /// Blue's weight in luma.
    pub kb: f64,
}

impl Matrix {
    /// ITU-R BT.709 (HD).
    pub const BT709: Self = Self::new(0.2126, 0.0722);
    /// ITU-R BT.601 (SD; also BT.470 BG and SMPTE 170M).
    pub const BT601: Self = Self::new(0.299, 0.114);
    /// ITU-R BT.2020 (non-constant luminance).
    pub const BT2020: Self = Self::new(0.2627, 0.0593);
    /// SMPTE 240M.
    pub const SMPTE240M: Self = Self::new(0.212, 0.087);
    /// FCC (US, 1953).
    pub const FCC: Self = Self::new(0.30, 0.11);

    /// A matrix of luma weights `kr` and `kb`.
    pub const fn new(kr: f64, kb: f64) -> Self {
        Self { kr, kb }
    }

    /// The inverse matrix's chroma weights `[cr_r, cb_g, cr_g, cb_b]`, per unit of centred
    /// chroma: `R = Y + cr_r Cr`, `G = Y + cb_g Cb + cr_g Cr`, `B = Y + cb_b Cb`.
    pub fn chroma_weights(self) -> [f64; 4] {
        let Self { kr, kb } = self;
        let kg = 1.0 - kr - kb;
        let (r, b) = (2.0 * (1.0 - kr), 2.0 * (1.0 - kb));
        [r, -kb / kg * b, -kr / kg * r, b]
    }
}

/// The conversion back to 8-bit RGB as tables, in 0..255 units with 16 fractional bits:
/// `R = Y + Cr_r`, `G = Y + Cb_g + Cr_g`, `B = Y + Cb_b`. Integer sums and one rounding per
/// channel (the float formula costs a libm `roundf` per channel: the baseline x86-64 target
/// has no rounding instruction).
#[derive(Debug, Clone)]
pub struct ToRgb {
    y: [i32; 256],
    cr_r: [i32; 256],
    cb_g: [i32; 256],
    cr_g: [i32; 256],
    cb_b: [i32; 256],
}

impl ToRgb {
    /// Tables for `matrix`; `full` range (0..255) or limited (luma 16..235, chroma 16..240).
    pub fn new(matrix: Matrix, full: bool) -> Self {
        let [cr_r, cb_g, cr_g, cb_b] = matrix.chroma_weights();
        let (y0, ys, cs) = if full {
            (0.0, 255.0, 255.0)
        } else {
            (16.0, 219.0, 224.0)
        };
        let fixed = |v: f64| (v * 255.0 * 65536.0).round() as i32;
        let mut t = Self {
            y: [0; 256],
            cr_r: [0; 256],
            cb_g: [0; 256],
            cr_g: [0; 256],
            cb_b: [0; 256],
        };
        for v in 0..256 {
            let c = (v as f64 - 128.0) / cs;
            t.y[v] = fixed((v as f64 - y0) / ys);
            t.cr_r[v] = fixed(cr_r * c);
            t.cb_g[v] = fixed(cb_g * c);
            t.cr_g[v] = fixed(cr_g * c);
            t.cb_b[v] = fixed(cb_b * c);
        }
        t
    }

    /// The chroma terms of R, G and B for one (Cb, Cr) sample.
    #[inline]
    pub fn chroma(&self, cb: u8, cr: u8) -> [i32; 3] {
        let (cb, cr) = (cb as usize, cr as usize);
        [self.cr_r[cr], self.cb_g[cb] + self.cr_g[cr], self.cb_b[cb]]
    }

    /// The 8-bit RGB of a luma sample with its chroma terms.
    #[inline]
    pub fn rgb_with(&self, y: u8, chroma: [i32; 3]) -> [u8; 3] {
        let l = self.y[y as usize];
        chroma.map(|c| ((l + c + 32768) >> 16).clamp(0, 255) as u8)
    }

    /// The 8-bit RGB of one Y'CbCr sample.
    #[inline]
    pub fn rgb(&self, y: u8, cb: u8, cr: u8) -> [u8; 3] {
        self.rgb_with(y, self.chroma(cb, cr))
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn tables_invert_the_forward_matrix() {
        for (m, full) in [
            (Matrix::BT709, false),
            (Matrix::BT601, true),
            (Matrix::BT2020, false),
        ] {
            let t = ToRgb::new(m, full);
            let (y0, ys, cs) = if full {
                (0.0, 255.0, 255.0)
            } else {
                (16.0, 219.0, 224.0)
            };
            for rgb in [[200u8, 50, 20], [0, 0, 0], [255, 255, 255], [30, 140, 250]] {
                let [r, g, b] = rgb.map(|v| v as f64 / 255.0);
                let l = m.kr * r + (1.0 - m.kr - m.kb) * g + m.kb * b;
                let q = |v: f64| v.round().clamp(0.0, 255.0) as u8;
                let y = q(y0 + ys * l);
                let cb = q(128.0 + cs * (b - l) / (2.0 * (1.0 - m.kb)));
                let cr = q(128.0 + cs * (r - l) / (2.0 * (1.0 - m.kr)));
                let back = t.rgb(y, cb, cr);
                for (a, b) in back.iter().zip(rgb) {
                    assert!(
                        a.abs_diff(b) <= 2,
                        "{m:?} full={full}: {back:?} for {rgb:?}"
                    );
                }
            }
        }
    }
}
