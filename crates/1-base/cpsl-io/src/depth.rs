//! Depth maps from files: PFM (float), 16-bit greyscale PNG (integer units scaled to scene
//! units) and NumPy `.npy` (2-D `float32`, `float64` or `uint16`, either byte order, C or
//! Fortran order). The format is chosen by extension. Sizes are checked against [`Limits`]
//! before any allocation.
//!
//! Integer formats (PNG, `uint16` `.npy`) store depth in units of `scale` scene units (for
//! example millimetres with `scale = 0.001`); the value 0 means "unknown" and becomes NaN.

use crate::error::IoError;
use crate::pfm::{read_pfm, FloatImage};
use cpsl_core::Limits;
use std::path::Path;

/// How integer depth files are converted to scene units.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct DepthUnits {
    /// Scene units per integer step (default 0.001: millimetres to metres).
    pub scale: f32,
}

impl Default for DepthUnits {
    fn default() -> Self {
        Self { scale: 0.001 }
    }
}

/// A depth file as a [`cpsl_core::DepthSource`]: read when depth is asked for, checked
/// against the frame's size.
#[derive(Debug, Clone)]
pub struct DepthFile {
    /// The file.
    pub path: std::path::PathBuf,
    /// Units of integer formats.
    pub units: DepthUnits,
    /// Size limits.
    pub limits: Limits,
}

impl cpsl_core::DepthSource for DepthFile {
    fn name(&self) -> String {
        format!("file {}", self.path.display())
    }

    fn depth(
        &mut self,
        _rgb: &[u8],
        width: u32,
        height: u32,
    ) -> Result<Vec<f32>, cpsl_core::DepthSourceError> {
        let fail = |cause: Box<dyn std::error::Error + Send + Sync>| cpsl_core::DepthSourceError {
            source_name: self.name(),
            cause,
        };
        let d = read_depth(&self.path, self.units, &self.limits).map_err(|e| fail(Box::new(e)))?;
        if (d.width, d.height) != (width, height) {
            return Err(fail(
                format!(
                    "depth is {}x{} but the image is {width}x{height}",
                    d.width, d.height
                )
                .into(),
            ));
        }
        Ok(d.data)
    }
}

/// A folder of depth maps for a frame sequence, one per frame in file-name order (`.pfm`,
/// 16-bit `.png`, `.npy`; other files are ignored).
#[derive(Debug, Clone)]
pub struct DepthSequence {
    /// The folder.
    pub dir: std::path::PathBuf,
    /// The maps, sorted by file name.
    pub files: Vec<std::path::PathBuf>,
    /// Units of integer formats.
    pub units: DepthUnits,
    /// Size limits.
    pub limits: Limits,
}

impl DepthSequence {
    /// Lists the depth maps of `dir`; an error when it has none.
    pub fn open(dir: &Path, units: DepthUnits, limits: Limits) -> Result<Self, IoError> {
        let mut files: Vec<std::path::PathBuf> = std::fs::read_dir(dir)
            .map_err(|e| IoError::io(dir, e))?
            .filter_map(|e| e.ok().map(|e| e.path()))
            .filter(|p| {
                p.is_file()
                    && p.extension().is_some_and(|e| {
                        matches!(
                            e.to_string_lossy().to_ascii_lowercase().as_str(),
                            "pfm" | "png" | "npy"
                        )
                    })
            })
            .collect();
        if files.is_empty() {
            return Err(IoError::Depth {
                path: dir.into(),
                reason: "no depth maps (.pfm, .png, .npy) in this folder".into(),
            });
        }
        files.sort();
        Ok(Self {
            dir: dir.into(),
            files,
            units,
            limits,
        })
    }

    /// The depth of frame `index`, checked against the frame's size.
    pub fn depth_at(&self, index: usize, width: u32, height: u32) -> Result<Vec<f32>, IoError> {
        let path = self.files.get(index).ok_or_else(|| IoError::Depth {
            path: self.dir.clone(),
            reason: format!(
                "frame {index} has no depth map: the folder holds {} maps",
                self.files.len()
            ),
        })?;
        let d = read_depth(path, self.units, &self.limits)?;
        if (d.width, d.height) != (width, height) {
            return Err(IoError::Depth {
                path: path.clone(),
                reason: format!(
                    "depth is {}x{} but the frame is {width}x{height}",
                    d.width, d.height
                ),
            });
        }
        Ok(d.data)
    }
}

/// Reads a depth map (`.pfm`, `.png`, `.npy`).
pub fn read_depth(path: &Path, units: DepthUnits, limits: &Limits) -> Result<FloatImage, IoError> {
    let ext = path
        .extension()
        .map(|e| e.to_string_lossy().to_ascii_lowercase())
        .unwrap_or_default();
    let bad = |reason: String| IoError::Depth {
        path: path.into(),
        reason,
    };
    match ext.as_str() {
        "pfm" => read_pfm(path, limits),
        "png" => {
            let (w, h) = crate::images::dimensions(path, limits)?;
            limits
                .check_size(&path.display().to_string(), w, h)
                .map_err(|e| bad(e.to_string()))?;
            let file = std::fs::File::open(path).map_err(|e| IoError::io(path, e))?;
            let dec = image::codecs::png::PngDecoder::new(std::io::BufReader::new(file))
                .map_err(|e| bad(e.to_string()))?;
            let ct = image::ImageDecoder::color_type(&dec);
            if ct != image::ColorType::L16 {
                return Err(bad(format!(
                    "expected a 16-bit greyscale PNG, found {ct:?}"
                )));
            }
            let img = image::DynamicImage::from_decoder(dec)
                .map_err(|e| bad(e.to_string()))?
                .into_luma16();
            Ok(FloatImage {
                width: w,
                height: h,
                data: img
                    .into_raw()
                    .into_iter()
                    .map(|v| from_int(v, units))
                    .collect(),
            })
        }
        "npy" => {
            let meta = std::fs::metadata(path).map_err(|e| IoError::io(path, e))?;
            if meta.len() > limits.max_file_bytes {
                return Err(IoError::FileTooLarge {
                    path: path.into(),
                    size: meta.len(),
                    max: limits.max_file_bytes,
                });
            }
            let bytes = std::fs::read(path).map_err(|e| IoError::io(path, e))?;
            parse_npy(&bytes, units, limits).map_err(bad)
        }
        other => Err(bad(format!(
            "unknown depth format '.{other}': expected .pfm, .png (16-bit) or .npy"
        ))),
    }
}

fn from_int(v: u16, units: DepthUnits) -> f32 {
    if v == 0 {
        f32::NAN
    } else {
        v as f32 * units.scale
    }
}

/// Parses a NumPy `.npy` file holding a 2-D depth array (a leading or trailing axis of size 1
/// is accepted).
pub fn parse_npy(bytes: &[u8], units: DepthUnits, limits: &Limits) -> Result<FloatImage, String> {
    if bytes.len() < 10 || &bytes[..6] != b"\x93NUMPY" {
        return Err("not a .npy file (bad magic)".into());
    }
    let (header_len, start) = match bytes[6] {
        1 => (u16::from_le_bytes([bytes[8], bytes[9]]) as usize, 10),
        2 | 3 => {
            let b = bytes.get(8..12).ok_or("truncated header")?;
            (u32::from_le_bytes([b[0], b[1], b[2], b[3]]) as usize, 12)
        }
        v => return Err(format!("unsupported .npy version {v}")),
    };
    let header = bytes
        .get(start..start + header_len)
        .ok_or("truncated header")?;
    let header = std::str::from_utf8(header).map_err(|_| "header is not text")?;
    let field = |key: &str| -> Result<&str, String> {
        let k = format!("'{key}':");
        let i = header.find(&k).ok_or(format!("header lacks '{key}'"))? + k.len();
        Ok(header[i..].trim_start())
    };
    let descr = field("descr")?;
    let descr = descr
        .strip_prefix('\'')
        .and_then(|d| d.split('\'').next())
        .ok_or("bad 'descr'")?;
    let fortran = field("fortran_order")?.starts_with("True");
    let shape_txt = field("shape")?;
    let shape_txt = shape_txt
        .strip_prefix('(')
        .and_then(|s| s.split(')').next())
        .ok_or("bad 'shape'")?;
    let dims: Vec<u64> = shape_txt
        .split(',')
        .map(str::trim)
        .filter(|s| !s.is_empty())
        .map(|s| {
            s.parse::<u64>()
                .map_err(|_| format!("bad shape entry '{s}'"))
        })
        .collect::<Result<_, _>>()?;
    let dims: Vec<u64> = match dims.as_slice() {
        [h, w] => vec![*h, *w],
        [1, h, w] | [h, w, 1] => vec![*h, *w],
        other => {
            return Err(format!(
                "expected a 2-D array (H, W), found shape {other:?}"
            ))
        }
    };
    let (h, w) = (dims[0], dims[1]);
    if w > u32::MAX as u64 || h > u32::MAX as u64 {
        return Err(format!("array of {h}x{w} is too large"));
    }
    let (w, h) = (w as u32, h as u32);
    limits
        .check_size("depth array", w, h)
        .map_err(|e| e.to_string())?;
    let (little, kind) = match descr.as_bytes() {
        [b'<' | b'|', k @ ..] => (true, k),
        [b'>', k @ ..] => (false, k),
        _ => return Err(format!("unsupported dtype '{descr}'")),
    };
    let size = match kind {
        b"f4" => 4,
        b"f8" => 8,
        b"u2" => 2,
        _ => {
            return Err(format!(
                "unsupported dtype '{descr}': expected float32, float64 or uint16"
            ))
        }
    };
    let n = w as usize * h as usize;
    let body = &bytes[start + header_len..];
    if body.len() < n * size {
        return Err(format!(
            "truncated data: {} bytes, {} expected for {w}x{h} {descr}",
            body.len(),
            n * size
        ));
    }
    let value = |i: usize| -> f32 {
        let b = &body[i * size..(i + 1) * size];
        match (kind, little) {
            (b"f4", true) => f32::from_le_bytes(b.try_into().unwrap()),
            (b"f4", false) => f32::from_be_bytes(b.try_into().unwrap()),
            (b"f8", true) => f64::from_le_bytes(b.try_into().unwrap()) as f32,
            (b"f8", false) => f64::from_be_bytes(b.try_into().unwrap()) as f32,
            (_, true) => from_int(u16::from_le_bytes([b[0], b[1]]), units),
            (_, false) => from_int(u16::from_be_bytes([b[0], b[1]]), units),
        }
    };
    let (wu, hu) = (w as usize, h as usize);
    let data = (0..n)
        .map(|i| {
            if fortran {
                let (y, x) = (i / wu, i % wu);
                value(x * hu + y)
            } else {
                value(i)
            }
        })
        .collect();
    Ok(FloatImage {
        width: w,
        height: h,
        data,
    })
}

#[cfg(test)]
mod tests {
    use super::*;

    fn npy(descr: &str, fortran: bool, shape: &str, body: &[u8]) -> Vec<u8> {
        let mut header = format!(
            "{{'descr': '{descr}', 'fortran_order': {}, 'shape': {shape}, }}",
            if fortran { "True" } else { "False" }
        );
        while (10 + header.len() + 1) % 64 != 0 {
            header.push(' ');
        }
        header.push('\n');
        let mut out = b"\x93NUMPY\x01\x00".to_vec();
        out.extend_from_slice(&(header.len() as u16).to_le_bytes());
        out.extend_from_slice(header.as_bytes());
        out.extend_from_slice(body);
        out
    }

    #[test]
    fn npy_dtypes_orders_and_shapes() {
        let l = Limits::default();
        let u = DepthUnits::default();
        let f4: Vec<u8> = [1.0f32, 2.0, 3.0, 4.0, 5.0, 6.0]
            .iter()
            .flat_map(|v| v.to_le_bytes())
            .collect();
        let img = parse_npy(&npy("<f4", false, "(2, 3)", &f4), u, &l).unwrap();
        assert_eq!((img.width, img.height), (3, 2));
        assert_eq!(img.data, vec![1.0, 2.0, 3.0, 4.0, 5.0, 6.0]);
        // Fortran order: columns stored first.
        let img = parse_npy(&npy("<f4", true, "(2, 3)", &f4), u, &l).unwrap();
        assert_eq!(img.data, vec![1.0, 3.0, 5.0, 2.0, 4.0, 6.0]);
        let f8: Vec<u8> = [1.5f64, 2.5].iter().flat_map(|v| v.to_be_bytes()).collect();
        let img = parse_npy(&npy(">f8", false, "(1, 1, 2)", &f8), u, &l).unwrap();
        assert_eq!(img.data, vec![1.5, 2.5]);
        let u2: Vec<u8> = [0u16, 1500].iter().flat_map(|v| v.to_le_bytes()).collect();
        let img = parse_npy(&npy("<u2", false, "(2, 1)", &u2), u, &l).unwrap();
        assert!(img.data[0].is_nan() && (img.data[1] - 1.5).abs() < 1e-6);
    }

    #[test]
    fn npy_rejections() {
        let l = Limits::default();
        let u = DepthUnits::default();
        let f4 = [0u8; 24];
        assert!(parse_npy(b"garbage", u, &l).unwrap_err().contains("magic"));
        assert!(parse_npy(&npy("<f4", false, "(2, 3)", &f4[..20]), u, &l)
            .unwrap_err()
            .contains("truncated"));
        assert!(parse_npy(&npy("<i8", false, "(2, 3)", &f4), u, &l)
            .unwrap_err()
            .contains("dtype"));
        assert!(parse_npy(&npy("<f4", false, "(2, 3, 3)", &f4), u, &l)
            .unwrap_err()
            .contains("2-D"));
        assert!(parse_npy(&npy("<f4", false, "(99999, 99999)", &f4), u, &l)
            .unwrap_err()
            .contains("limit"));
        let v = npy("<f4", false, "(2, 3)", &f4);
        for cut in 0..v.len() {
            let _ = parse_npy(&v[..cut], u, &l);
        }
    }

    #[test]
    fn png16_and_extension_dispatch() {
        let d = tempfile::tempdir().unwrap();
        let p = d.path().join("d.png");
        let raw: Vec<u16> = vec![0, 1000, 2000, 65535];
        image::ImageBuffer::<image::Luma<u16>, _>::from_raw(2, 2, raw)
            .unwrap()
            .save(&p)
            .unwrap();
        let img = read_depth(&p, DepthUnits { scale: 0.01 }, &Limits::default()).unwrap();
        assert!(img.data[0].is_nan());
        assert_eq!(&img.data[1..], &[10.0, 20.0, 655.35]);
        // 8-bit PNGs are ambiguous as depth and refused.
        let p8 = d.path().join("d8.png");
        crate::images::write_png(&p8, 2, 2, 1, &[1, 2, 3, 4]).unwrap();
        let e = read_depth(&p8, DepthUnits::default(), &Limits::default())
            .unwrap_err()
            .to_string();
        assert!(e.contains("16-bit") && e.contains("d8.png"), "{e}");
        let e = read_depth(
            &d.path().join("x.tiff"),
            DepthUnits::default(),
            &Limits::default(),
        )
        .unwrap_err()
        .to_string();
        assert!(e.contains("unknown depth format"), "{e}");
    }

    #[test]
    fn depth_sequence_in_name_order_with_clear_errors() {
        let d = tempfile::tempdir().unwrap();
        let err = DepthSequence::open(d.path(), DepthUnits::default(), Limits::default());
        assert!(err.unwrap_err().to_string().contains("no depth maps"));
        for (name, v) in [("b_0001.pfm", 2.0), ("a_0000.pfm", 1.0)] {
            let img = FloatImage {
                width: 3,
                height: 2,
                data: vec![v; 6],
            };
            crate::pfm::write_pfm(&d.path().join(name), &img).unwrap();
        }
        std::fs::write(d.path().join("notes.txt"), "not depth").unwrap();
        let seq = DepthSequence::open(d.path(), DepthUnits::default(), Limits::default()).unwrap();
        assert_eq!(seq.files.len(), 2);
        assert_eq!(seq.depth_at(0, 3, 2).unwrap(), vec![1.0; 6]);
        assert_eq!(seq.depth_at(1, 3, 2).unwrap(), vec![2.0; 6]);
        let e = seq.depth_at(2, 3, 2).unwrap_err().to_string();
        assert!(e.contains("frame 2 has no depth map"), "{e}");
        let e = seq.depth_at(0, 4, 2).unwrap_err().to_string();
        assert!(e.contains("3x2 but the frame is 4x2"), "{e}");
    }
}
