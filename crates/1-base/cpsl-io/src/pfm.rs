//! Portable Float Map (PFM) files: greyscale `Pf` (one float per pixel) and colour `PF`.
//!
//! Layout: `Pf\n<width> <height>\n<scale>\n` then little-endian (scale < 0) or big-endian
//! (scale > 0) `f32` samples, rows stored **bottom to top**. [`read_pfm`] returns rows top to
//! bottom; colour files are reduced to their first channel.

use crate::error::IoError;
use cpsl_core::Limits;
use std::path::Path;

/// A single-channel float image, rows top to bottom.
#[derive(Debug, Clone, PartialEq)]
pub struct FloatImage {
    /// Width in pixels.
    pub width: u32,
    /// Height in pixels.
    pub height: u32,
    /// Samples, row-major, top row first.
    pub data: Vec<f32>,
}

/// Reads a PFM file.
pub fn read_pfm(path: &Path, limits: &Limits) -> Result<FloatImage, IoError> {
    let bytes = std::fs::read(path).map_err(|e| IoError::io(path, e))?;
    parse_pfm(&bytes, limits).map_err(|reason| IoError::Pfm {
        path: path.into(),
        reason,
    })
}

/// Parses PFM bytes.
pub fn parse_pfm(bytes: &[u8], limits: &Limits) -> Result<FloatImage, String> {
    // Header: three whitespace-separated tokens after the magic, then one whitespace byte.
    let mut pos = 0usize;
    let mut token = || -> Result<String, String> {
        while pos < bytes.len() && bytes[pos].is_ascii_whitespace() {
            pos += 1;
        }
        let start = pos;
        while pos < bytes.len() && !bytes[pos].is_ascii_whitespace() {
            pos += 1;
            if pos - start > 32 {
                return Err("header token too long".into());
            }
        }
        if start == pos {
            return Err("truncated header".into());
        }
        Ok(String::from_utf8_lossy(&bytes[start..pos]).into_owned())
    };
    let magic = token()?;
    let channels = match magic.as_str() {
        "Pf" => 1usize,
        "PF" => 3,
        other => return Err(format!("bad magic {other:?}, expected \"Pf\" or \"PF\"")),
    };
    let w: u32 = token()?.parse().map_err(|e| format!("bad width: {e}"))?;
    let h: u32 = token()?.parse().map_err(|e| format!("bad height: {e}"))?;
    let scale: f32 = token()?.parse().map_err(|e| format!("bad scale: {e}"))?;
    if scale == 0.0 || !scale.is_finite() {
        return Err(format!("bad scale {scale}"));
    }
    limits
        .check_size("PFM image", w, h)
        .map_err(|e| e.to_string())?;
    pos += 1; // the single whitespace byte after the scale
    let n = w as usize * h as usize;
    let need = n * channels * 4;
    let body = bytes.get(pos..).unwrap_or(&[]);
    if body.len() < need {
        return Err(format!(
            "truncated data: {} bytes, {need} expected for {w}x{h}",
            body.len()
        ));
    }
    let little = scale < 0.0;
    let mut data = vec![0f32; n];
    for y in 0..h as usize {
        let src_row = h as usize - 1 - y;
        for x in 0..w as usize {
            let o = (src_row * w as usize + x) * channels * 4;
            let b = [body[o], body[o + 1], body[o + 2], body[o + 3]];
            data[y * w as usize + x] = if little {
                f32::from_le_bytes(b)
            } else {
                f32::from_be_bytes(b)
            };
        }
    }
    Ok(FloatImage {
        width: w,
        height: h,
        data,
    })
}

/// Encodes a greyscale little-endian PFM.
pub fn encode_pfm(img: &FloatImage) -> Vec<u8> {
    let mut out = format!("Pf\n{} {}\n-1.0\n", img.width, img.height).into_bytes();
    let w = img.width as usize;
    for y in (0..img.height as usize).rev() {
        for v in &img.data[y * w..(y + 1) * w] {
            out.extend_from_slice(&v.to_le_bytes());
        }
    }
    out
}

/// Writes a greyscale little-endian PFM file atomically.
pub fn write_pfm(path: &Path, img: &FloatImage) -> Result<(), IoError> {
    crate::atomic::write_file_atomic(path, &encode_pfm(img))
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn roundtrip_and_orientation() {
        let img = FloatImage {
            width: 3,
            height: 2,
            data: vec![1.0, 2.0, 3.0, 4.0, 5.0, 6.0],
        };
        let bytes = encode_pfm(&img);
        assert_eq!(parse_pfm(&bytes, &Limits::default()).unwrap(), img);
        // First stored row is the bottom row.
        let body = &bytes[bytes.len() - 24..];
        assert_eq!(f32::from_le_bytes(body[0..4].try_into().unwrap()), 4.0);
    }

    #[test]
    fn arbitrary_bytes_never_panic() {
        // Deterministic pseudo-random inputs, plus every truncation of a valid file.
        let valid = encode_pfm(&FloatImage {
            width: 3,
            height: 2,
            data: vec![1.5; 6],
        });
        for cut in 0..valid.len() {
            let _ = parse_pfm(&valid[..cut], &Limits::default());
        }
        let mut s = 0x9E37_79B9_7F4A_7C15u64;
        for n in 0..2000usize {
            let mut bytes = valid.clone();
            for _ in 0..(n % 5) + 1 {
                s ^= s << 13;
                s ^= s >> 7;
                s ^= s << 17;
                let i = (s as usize) % bytes.len();
                bytes[i] = (s >> 32) as u8;
            }
            let _ = parse_pfm(&bytes, &Limits::default());
        }
    }

    #[test]
    fn rejects_truncated_and_bad_headers() {
        let l = Limits::default();
        let img = FloatImage {
            width: 2,
            height: 2,
            data: vec![0.0; 4],
        };
        let bytes = encode_pfm(&img);
        assert!(parse_pfm(&bytes[..bytes.len() - 1], &l)
            .unwrap_err()
            .contains("truncated"));
        assert!(parse_pfm(b"P6\n1 1\n255\n", &l).is_err());
        assert!(parse_pfm(b"Pf\n99999999 99999999\n-1\n", &l).is_err());
        assert!(parse_pfm(b"Pf\n", &l).is_err());
    }
}
