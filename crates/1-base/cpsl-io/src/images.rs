//! Image files: decoding with limits checked before allocation, PNG encoding.

use crate::error::IoError;
use cpsl_core::Limits;
use image::{ImageEncoder, ImageReader};
use std::fs;
use std::io::BufReader;
use std::path::Path;

/// A decoded 8-bit image with `channels` interleaved channels.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct Image8 {
    /// Width in pixels.
    pub width: u32,
    /// Height in pixels.
    pub height: u32,
    /// Interleaved samples, row-major.
    pub data: Vec<u8>,
}

fn open_reader(path: &Path, limits: &Limits) -> Result<ImageReader<BufReader<fs::File>>, IoError> {
    let meta = fs::metadata(path).map_err(|e| IoError::io(path, e))?;
    if meta.len() > limits.max_file_bytes {
        return Err(IoError::FileTooLarge {
            path: path.into(),
            size: meta.len(),
            max: limits.max_file_bytes,
        });
    }
    let mut r = ImageReader::open(path)
        .map_err(|e| IoError::io(path, e))?
        .with_guessed_format()
        .map_err(|e| IoError::io(path, e))?;
    let mut il = image::Limits::default();
    il.max_image_width = Some(limits.max_side);
    il.max_image_height = Some(limits.max_side);
    il.max_alloc = Some(limits.max_pixels.saturating_mul(16));
    r.limits(il);
    Ok(r)
}

/// Reads only the dimensions of an image file (cheap: the header).
pub fn dimensions(path: &Path, limits: &Limits) -> Result<(u32, u32), IoError> {
    open_reader(path, limits)?
        .into_dimensions()
        .map_err(|e| IoError::Image {
            path: path.into(),
            message: e.to_string(),
        })
}

fn checked_decode(path: &Path, limits: &Limits) -> Result<image::DynamicImage, IoError> {
    let (w, h) = dimensions(path, limits)?;
    limits
        .check_size(&path.display().to_string(), w, h)
        .map_err(|e| IoError::Invalid {
            path: path.into(),
            cause: e,
        })?;
    open_reader(path, limits)?
        .decode()
        .map_err(|e| IoError::Image {
            path: path.into(),
            message: e.to_string(),
        })
}

/// Decodes any supported image (PNG, JPEG) as 8-bit RGB.
pub fn read_rgb8(path: &Path, limits: &Limits) -> Result<Image8, IoError> {
    let img = checked_decode(path, limits)?.into_rgb8();
    Ok(Image8 {
        width: img.width(),
        height: img.height(),
        data: img.into_raw(),
    })
}

/// Decodes any supported image as 8-bit straight-alpha RGBA.
pub fn read_rgba8(path: &Path, limits: &Limits) -> Result<Image8, IoError> {
    let img = checked_decode(path, limits)?.into_rgba8();
    Ok(Image8 {
        width: img.width(),
        height: img.height(),
        data: img.into_raw(),
    })
}

/// Encodes 8-bit samples (`channels` = 1, 3 or 4) as PNG bytes.
pub fn encode_png(width: u32, height: u32, channels: u8, data: &[u8]) -> Result<Vec<u8>, String> {
    let ct = match channels {
        1 => image::ExtendedColorType::L8,
        3 => image::ExtendedColorType::Rgb8,
        4 => image::ExtendedColorType::Rgba8,
        c => return Err(format!("unsupported channel count {c}")),
    };
    let mut out = Vec::new();
    image::codecs::png::PngEncoder::new_with_quality(
        &mut out,
        image::codecs::png::CompressionType::Fast,
        image::codecs::png::FilterType::Paeth,
    )
    .write_image(data, width, height, ct)
    .map_err(|e| e.to_string())?;
    Ok(out)
}

/// Writes 8-bit samples as a PNG file (written to a temporary name, then renamed).
pub fn write_png(
    path: &Path,
    width: u32,
    height: u32,
    channels: u8,
    data: &[u8],
) -> Result<(), IoError> {
    let bytes = encode_png(width, height, channels, data).map_err(|message| IoError::Image {
        path: path.into(),
        message,
    })?;
    crate::atomic::write_file_atomic(path, &bytes)
}
