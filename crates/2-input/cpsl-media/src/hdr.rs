//! HDR video (PQ or HLG with BT.2020 primaries) mapped to SDR BT.709: linear light relative
//! to reference white (203 cd/m2; HLG through the reference display's system gamma), primaries
//! converted, highlights rolled off above 0.75 of white.

use cpsl_core::ycbcr::Matrix;
use rayon::prelude::*;

/// The transfer function of an HDR video.
#[derive(Debug, Clone, Copy, PartialEq)]
pub(crate) enum Transfer {
    /// SMPTE ST 2084 (perceptual quantiser): absolute display light up to 10 000 cd/m2.
    Pq,
    /// ARIB STD-B67 (hybrid log-gamma): relative scene light.
    Hlg,
}

/// Display light of HDR reference white (ITU-R BT.2408), which SDR white is mapped to.
const HDR_WHITE_NITS: f32 = 203.0;
/// Peak of the HLG reference display (ITU-R BT.2100).
const HLG_PEAK_NITS: f32 = 1000.0;
/// Highlights above this share of SDR white are rolled off towards white.
const KNEE: f32 = 0.75;

/// Entries of [`ToSdr`]'s table of the transfer function, over the signal's [0, 1]: finer
/// than 10- and 12-bit video.
const SIGNAL_STEPS: usize = 1 << 14;

/// 16-bit Y'CbCr samples (the scaler's `yuv444p16le`: 8-bit values times 256 in limited range)
/// to R'G'B' signal in [0, 1], in floating point.
pub(crate) struct Signal {
    y0: f32,
    /// Reciprocals of the luma and chroma scales.
    ys: f32,
    cs: f32,
    /// The matrix's [`Matrix::chroma_weights`].
    weights: [f32; 4],
}

impl Signal {
    pub(crate) fn new(matrix: Matrix, full: bool) -> Self {
        let (y0, ys, cs) = if full {
            (0.0, 65535.0, 65535.0)
        } else {
            (16.0 * 256.0, 219.0 * 256.0, 224.0 * 256.0)
        };
        Self {
            y0,
            ys: 1.0 / ys,
            cs: 1.0 / cs,
            weights: matrix.chroma_weights().map(|v| v as f32),
        }
    }

    #[inline]
    pub(crate) fn rgb(&self, y: f32, cb: f32, cr: f32) -> [f32; 3] {
        let l = (y - self.y0) * self.ys;
        let (cb, cr) = ((cb - 32768.0) * self.cs, (cr - 32768.0) * self.cs);
        let [cr_r, cb_g, cr_g, cb_b] = self.weights;
        [l + cr_r * cr, l + cb_g * cb + cr_g * cr, l + cb_b * cb]
    }
}

/// HDR (BT.2100: BT.2020 primaries, PQ or HLG) to SDR BT.709 R'G'B' for a display with
/// gamma 2.4: linear display light relative to reference white (HLG through the reference
/// display's system gamma, 1.2 at 1000 cd/m2), BT.2020 to BT.709 primaries, highlights above
/// 0.75 of white compressed smoothly towards it (by the largest channel, so hues keep their
/// ratios), colours outside BT.709 clipped.
pub(crate) struct ToSdr {
    transfer: Transfer,
    /// R'G'B' signal (in [`SIGNAL_STEPS`]) to linear light (PQ: relative to reference white;
    /// HLG: scene light).
    linear: Vec<f32>,
    /// Linear SDR light in [0, 1] to 8-bit code, over its square root (4096 steps: 8-bit
    /// codes near black are as close as 1 / 4095 in linear light, a step of the square root
    /// moves them by at most a quarter).
    encode: Vec<u8>,
    /// HLG: the reference display's gain `Lw / white * Ys^(gamma - 1)` over `sqrt(Ys)` in
    /// [0, 1] (4096 steps: fine near black, where `Ys^0.2` is steep).
    ootf: Vec<f32>,
}

impl ToSdr {
    pub(crate) fn new(transfer: Transfer) -> Self {
        let linear = (0..SIGNAL_STEPS)
            .map(|i| {
                let e = i as f64 / (SIGNAL_STEPS - 1) as f64;
                (match transfer {
                    Transfer::Pq => {
                        let (m1, m2) = (0.1593017578125, 78.84375);
                        let (c1, c2, c3) = (0.8359375, 18.8515625, 18.6875);
                        let n = e.powf(1.0 / m2);
                        let nits = 10000.0 * ((n - c1).max(0.0) / (c2 - c3 * n)).powf(1.0 / m1);
                        nits / HDR_WHITE_NITS as f64
                    }
                    Transfer::Hlg => {
                        let (a, b, c) = (0.17883277, 0.28466892, 0.55991073);
                        if e <= 0.5 {
                            e * e / 3.0
                        } else {
                            (((e - c) / a).exp() + b) / 12.0
                        }
                    }
                }) as f32
            })
            .collect();
        let encode = (0..4096)
            .map(|i| ((i as f64 / 4095.0).powf(2.0 / 2.4) * 255.0).round() as u8)
            .collect();
        let gain = HLG_PEAK_NITS / HDR_WHITE_NITS;
        let ootf = (0..4096)
            .map(|i| gain * (i as f32 / 4095.0).powf(0.4))
            .collect();
        Self {
            transfer,
            linear,
            encode,
            ootf,
        }
    }

    /// Fills 8-bit RGB pictures `w` pixels wide, rows in parallel: `signal(y, row)` writes row
    /// `y`'s BT.2020 R'G'B' signal as three planes.
    pub(crate) fn apply(
        &self,
        rgb: &mut [u8],
        w: usize,
        signal: impl Fn(usize, &mut [Vec<f32>; 3]) + Sync,
    ) {
        rgb.par_chunks_mut(w * 3).enumerate().for_each_init(
            || [vec![0f32; w], vec![0f32; w], vec![0f32; w]],
            |planes, (y, row)| {
                signal(y, planes);
                self.map_row(planes, row);
            },
        );
    }

    /// One row, in stages over the planes: the lookups stay scalar, the arithmetic between
    /// them vectorises.
    pub(crate) fn map_row(&self, planes: &mut [Vec<f32>; 3], out: &mut [u8]) {
        let top = (SIGNAL_STEPS - 1) as f32;
        for v in planes.iter_mut().flatten() {
            *v = self.linear[(v.clamp(0.0, 1.0) * top + 0.5) as usize];
        }
        let [r, g, b] = planes;
        if self.transfer == Transfer::Hlg {
            // The reference display's OOTF: Fd = Lw * Ys^(gamma - 1) * E, gamma 1.2.
            for ((r, g), b) in r.iter_mut().zip(g.iter_mut()).zip(b.iter_mut()) {
                let ys = 0.2627 * *r + 0.6780 * *g + 0.0593 * *b;
                let k = self.ootf[(ys.clamp(0.0, 1.0).sqrt() * 4095.0 + 0.5) as usize];
                (*r, *g, *b) = (*r * k, *g * k, *b * k);
            }
        }
        for ((r, g), b) in r.iter_mut().zip(g.iter_mut()).zip(b.iter_mut()) {
            // BT.2020 to BT.709 primaries.
            let r709 = (1.6605 * *r - 0.5876 * *g - 0.0728 * *b).max(0.0);
            let g709 = (-0.1246 * *r + 1.1329 * *g - 0.0083 * *b).max(0.0);
            let b709 = (-0.0182 * *r - 0.1006 * *g + 1.1187 * *b).max(0.0);
            // Slope 1 at the knee, approaching 1 (white) for ever brighter highlights.
            let m = r709.max(g709).max(b709);
            let t = (m - KNEE) / (1.0 - KNEE);
            let scale = if m > KNEE {
                (KNEE * (1.0 + t) + (1.0 - KNEE) * t) / ((1.0 + t) * m)
            } else {
                1.0
            };
            // Indices into `encode`, over the square root of linear light.
            let index = |v: f32| (v * scale).min(1.0).sqrt() * 4095.0 + 0.5;
            (*r, *g, *b) = (index(r709), index(g709), index(b709));
        }
        for (px, ((r, g), b)) in out
            .chunks_exact_mut(3)
            .zip(r.iter().zip(g.iter()).zip(b.iter()))
        {
            px[0] = self.encode[*r as usize];
            px[1] = self.encode[*g as usize];
            px[2] = self.encode[*b as usize];
        }
    }
}
