//! Image sequences: a folder of PNG or JPEG frames in file-name order.

use crate::{FrameSource, Info, InputFrame, MediaError};
use std::path::{Path, PathBuf};

/// A folder of PNG or JPEG images, in file-name order.
pub struct ImageSequence {
    files: Vec<PathBuf>,
    next: usize,
    info: Info,
}

impl ImageSequence {
    /// The frame files in the order they are read.
    pub fn files(&self) -> &[PathBuf] {
        &self.files
    }

    /// Lists the folder's images (`.png`, `.jpg`, `.jpeg`, any case).
    pub fn open(dir: &Path) -> Result<Self, MediaError> {
        let unreadable = |e: std::io::Error| MediaError::Unreadable {
            path: dir.to_path_buf(),
            reason: e.to_string(),
        };
        let mut files: Vec<PathBuf> = std::fs::read_dir(dir)
            .map_err(unreadable)?
            .filter_map(|e| e.ok().map(|e| e.path()))
            .filter(|p| {
                p.extension().and_then(|e| e.to_str()).is_some_and(|e| {
                    ["png", "jpg", "jpeg"].contains(&e.to_ascii_lowercase().as_str())
                })
            })
            .collect();
        files.sort();
        let first = files
            .first()
            .ok_or_else(|| MediaError::Empty(dir.to_path_buf()))?;
        let (width, height) = cpsl_io::images::dimensions(first, &cpsl_core_limits())?;
        Ok(Self {
            info: Info {
                width,
                height,
                fps: 30.0,
                frames: Some(files.len()),
                codec: "image".into(),
                rotation: 0,
                hdr: None,
                damaged: 0,
            },
            files,
            next: 0,
        })
    }
}

fn cpsl_core_limits() -> cpsl_core::Limits {
    cpsl_core::Limits::default()
}

impl FrameSource for ImageSequence {
    fn info(&self) -> &Info {
        &self.info
    }

    fn next_frame(&mut self) -> Result<Option<InputFrame>, MediaError> {
        let Some(path) = self.files.get(self.next) else {
            return Ok(None);
        };
        let img = cpsl_io::images::read_rgb8(path, &cpsl_core_limits())?;
        if (img.width, img.height) != (self.info.width, self.info.height) {
            return Err(MediaError::FrameSize {
                path: path.clone(),
                found: (img.width, img.height),
                expected: (self.info.width, self.info.height),
            });
        }
        self.next += 1;
        Ok(Some(InputFrame {
            index: self.next - 1,
            rgb: img.data,
            motion: None,
        }))
    }
}
