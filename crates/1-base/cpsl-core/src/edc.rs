//! The Edge-Depth Cache (EDC): sparse, quantised depth offsets sampled along layer boundaries,
//! so that boundary-aware rendering (the Dynamic Pixel Strip) knows the true depths on both
//! sides of a silhouette without a dense depth map.
//!
//! Each sample sits on a boundary pixel of the front layer `front` where it touches the back
//! layer `back` (`front < back`, nearest first). It stores the log-depth offsets of the true
//! scene depth from each layer's plane: `ln(z / z_front)` at the front-side pixel and
//! `ln(z / z_back)` at the adjacent back-side pixel, quantised in steps of `step`.
//!
//! Binary layout (`edc.bin`, little endian, 32-byte header then 8 bytes per sample):
//!
//! | offset | type | field |
//! |---|---|---|
//! | 0 | `[u8; 8]` | magic `CPSLEDC\0` |
//! | 8 | `u16` | version (1) |
//! | 10 | `u16` | flags (0) |
//! | 12 | `u32` | width |
//! | 16 | `u32` | height |
//! | 20 | `u16` | layer count |
//! | 22 | `u16` | reserved (0) |
//! | 24 | `f32` | `step`: log-depth per quantum |
//! | 28 | `u32` | sample count `n` |
//! | 32 + 8i | `u16, u16, u8, u8, i8, i8` | `x, y, front, back, front_offset, back_offset` |

use thiserror::Error;

/// Magic bytes at the start of an EDC file.
pub const EDC_MAGIC: &[u8; 8] = b"CPSLEDC\0";
/// Newest EDC version this build reads and writes.
pub const EDC_VERSION: u16 = 1;
const HEADER: usize = 32;
const SAMPLE: usize = 8;

/// One boundary sample.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct EdcSample {
    /// Pixel column of the front-side boundary pixel.
    pub x: u16,
    /// Pixel row of the front-side boundary pixel.
    pub y: u16,
    /// Index of the nearer layer.
    pub front: u8,
    /// Index of the farther layer.
    pub back: u8,
    /// Quantised `ln(z / z_front)` at the front-side pixel.
    pub front_offset: i8,
    /// Quantised `ln(z / z_back)` at the adjacent back-side pixel.
    pub back_offset: i8,
}

/// An Edge-Depth Cache for one layer set.
#[derive(Debug, Clone, PartialEq)]
pub struct Edc {
    /// Width of the layer set's camera.
    pub width: u32,
    /// Height of the layer set's camera.
    pub height: u32,
    /// Number of layers of the layer set.
    pub layers: u16,
    /// Log-depth per quantisation step.
    pub step: f32,
    /// Samples in row-major order of their position.
    pub samples: Vec<EdcSample>,
}

/// Why EDC bytes were rejected.
#[derive(Debug, Error, Clone, PartialEq)]
pub enum EdcError {
    /// The header is short, has the wrong magic or an unknown version.
    #[error("edge-depth cache header: {0}")]
    Header(String),
    /// The sample count does not match the data length.
    #[error("edge-depth cache: {count} samples need {expected} bytes, found {found}")]
    Length {
        /// Declared sample count.
        count: u32,
        /// Bytes the samples need.
        expected: usize,
        /// Bytes present.
        found: usize,
    },
    /// A sample lies outside the image or names invalid layers.
    #[error("edge-depth cache sample {index}: {message}")]
    Sample {
        /// Sample index.
        index: usize,
        /// What is wrong.
        message: String,
    },
}

impl Edc {
    /// A cache without samples for a layer set of `layers` layers on a `width x height`
    /// camera, quantised in steps of `step`.
    pub fn empty(width: u32, height: u32, layers: u16, step: f32) -> Self {
        Self {
            width,
            height,
            layers,
            step,
            samples: Vec::new(),
        }
    }

    /// Quantises a log-depth offset, saturating at the representable range.
    pub fn quantise(&self, offset: f64) -> i8 {
        (offset / self.step as f64).round().clamp(-127.0, 127.0) as i8
    }

    /// The log-depth offset a quantised value stands for.
    pub fn dequantise(&self, q: i8) -> f64 {
        q as f64 * self.step as f64
    }

    /// Serialises to the binary layout above.
    pub fn encode(&self) -> Vec<u8> {
        let mut out = Vec::with_capacity(HEADER + SAMPLE * self.samples.len());
        out.extend_from_slice(EDC_MAGIC);
        out.extend_from_slice(&EDC_VERSION.to_le_bytes());
        out.extend_from_slice(&0u16.to_le_bytes());
        out.extend_from_slice(&self.width.to_le_bytes());
        out.extend_from_slice(&self.height.to_le_bytes());
        out.extend_from_slice(&self.layers.to_le_bytes());
        out.extend_from_slice(&0u16.to_le_bytes());
        out.extend_from_slice(&self.step.to_le_bytes());
        out.extend_from_slice(&(self.samples.len() as u32).to_le_bytes());
        for s in &self.samples {
            out.extend_from_slice(&s.x.to_le_bytes());
            out.extend_from_slice(&s.y.to_le_bytes());
            out.extend_from_slice(&[s.front, s.back, s.front_offset as u8, s.back_offset as u8]);
        }
        out
    }

    /// Parses and validates the binary layout: header, length, every sample inside the image
    /// with `front < back < layers`.
    pub fn decode(bytes: &[u8]) -> Result<Self, EdcError> {
        if bytes.len() < HEADER {
            return Err(EdcError::Header(format!(
                "{} bytes, at least {HEADER} expected",
                bytes.len()
            )));
        }
        if &bytes[..8] != EDC_MAGIC {
            return Err(EdcError::Header(
                "not an edge-depth cache (bad magic)".into(),
            ));
        }
        let u16_at = |o: usize| u16::from_le_bytes([bytes[o], bytes[o + 1]]);
        let u32_at = |o: usize| u32::from_le_bytes(bytes[o..o + 4].try_into().unwrap());
        let version = u16_at(8);
        if version == 0 || version > EDC_VERSION {
            return Err(EdcError::Header(format!(
                "version {version} (this build reads 1..={EDC_VERSION})"
            )));
        }
        let (width, height, layers) = (u32_at(12), u32_at(16), u16_at(20));
        let step = f32::from_le_bytes(bytes[24..28].try_into().unwrap());
        if !(step.is_finite() && step > 0.0) {
            return Err(EdcError::Header(format!(
                "step must be finite and > 0, found {step}"
            )));
        }
        let count = u32_at(28);
        let expected = count as usize * SAMPLE;
        if bytes.len() - HEADER != expected {
            return Err(EdcError::Length {
                count,
                expected,
                found: bytes.len() - HEADER,
            });
        }
        let samples = bytes[HEADER..]
            .chunks_exact(SAMPLE)
            .enumerate()
            .map(|(index, c)| {
                let s = EdcSample {
                    x: u16::from_le_bytes([c[0], c[1]]),
                    y: u16::from_le_bytes([c[2], c[3]]),
                    front: c[4],
                    back: c[5],
                    front_offset: c[6] as i8,
                    back_offset: c[7] as i8,
                };
                if s.x as u32 >= width || s.y as u32 >= height {
                    return Err(EdcError::Sample {
                        index,
                        message: format!("({}, {}) outside {width}x{height}", s.x, s.y),
                    });
                }
                if s.front >= s.back || s.back as u16 >= layers {
                    return Err(EdcError::Sample {
                        index,
                        message: format!(
                            "layers {} / {} (front < back < {layers} required)",
                            s.front, s.back
                        ),
                    });
                }
                Ok(s)
            })
            .collect::<Result<_, _>>()?;
        Ok(Self {
            width,
            height,
            layers,
            step,
            samples,
        })
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn edc() -> Edc {
        Edc {
            width: 10,
            height: 5,
            layers: 3,
            step: 1.0 / 128.0,
            samples: vec![
                EdcSample {
                    x: 9,
                    y: 0,
                    front: 0,
                    back: 2,
                    front_offset: -127,
                    back_offset: 5,
                },
                EdcSample {
                    x: 3,
                    y: 4,
                    front: 1,
                    back: 2,
                    front_offset: 0,
                    back_offset: 127,
                },
            ],
        }
    }

    #[test]
    fn roundtrip_and_size() {
        let b = edc().encode();
        assert_eq!(b.len(), 32 + 2 * 8);
        assert_eq!(Edc::decode(&b).unwrap(), edc());
        let e = edc();
        assert_eq!(e.quantise(0.5), 64);
        assert_eq!(e.quantise(-9.0), -127);
        assert!((e.dequantise(64) - 0.5).abs() < 1e-12);
    }

    #[test]
    fn rejects_corruption() {
        let b = edc().encode();
        assert!(matches!(Edc::decode(&b[..20]), Err(EdcError::Header(_))));
        assert!(matches!(
            Edc::decode(&b[..b.len() - 1]),
            Err(EdcError::Length { .. })
        ));
        let mut bad = b.clone();
        bad[0] = b'X';
        assert!(matches!(Edc::decode(&bad), Err(EdcError::Header(_))));
        let mut bad = b.clone();
        bad[32] = 10; // x = 10 in a 10 px wide image
        assert!(matches!(
            Edc::decode(&bad),
            Err(EdcError::Sample { index: 0, .. })
        ));
        let mut bad = b.clone();
        bad[36] = 2; // front == back
        assert!(matches!(
            Edc::decode(&bad),
            Err(EdcError::Sample { index: 0, .. })
        ));
        let mut bad = b;
        bad[8] = 9;
        assert!(matches!(Edc::decode(&bad), Err(EdcError::Header(_))));
        // Arbitrary bytes never panic.
        for n in 0..200u32 {
            let junk: Vec<u8> = (0..n)
                .map(|i| (i.wrapping_mul(2654435761) >> 13) as u8)
                .collect();
            let _ = Edc::decode(&junk);
        }
    }
}
