//! Decoding a segment frame by frame: every layer stream advanced one picture at a time, in
//! lock step, back to layer sets with their Edge-Depth Cache summary.

use crate::stream::PictureReader;
use crate::{scale, yuv, CodecError};
use cpsl_core::{Camera, Layer, LayerSet, Limits, PremulImage};
use cpsl_package::{Package, SideFrame};
use rayon::prelude::*;
use std::path::{Path, PathBuf};
use std::sync::Arc;

/// One decoded frame of a package.
#[derive(Debug, Clone)]
pub struct DecodedFrame {
    /// Its side information.
    pub side: SideFrame,
    /// Its layers.
    pub set: LayerSet,
}

/// Decodes segment `i` of a package: every layer stream (checked against the manifest) and
/// the side stream, into one layer set per frame. A player keeps memory bounded with
/// [`SegmentReader`] instead, which this collects.
pub fn decode_segment(pkg: &Package, i: usize) -> Result<Vec<DecodedFrame>, CodecError> {
    SegmentReader::open(pkg, i)?.collect()
}

/// One layer stream of a segment being read.
struct StreamCursor {
    reader: PictureReader,
    /// Its pictures' size before upscaling, and the factor.
    size: (u32, u32),
    scale: u32,
    /// The file as the user knows it (inside an archive, not its private copy).
    shown: PathBuf,
}

/// Decodes a segment frame by frame: every layer stream in lock step (in parallel, one
/// picture each), with the side stream, so that only the current frame's pictures are held.
/// Each file is checked against the manifest when the reader opens; a stream with fewer or
/// more pictures than the segment's frames is an error when it shows.
pub struct SegmentReader {
    camera: Camera,
    streams: Vec<StreamCursor>,
    side: std::vec::IntoIter<SideFrame>,
    frames: u32,
    done: u32,
    /// No more items: the end was reached (and checked) or an error returned.
    ended: bool,
}

impl SegmentReader {
    /// Opens segment `i` of a package.
    pub fn open(pkg: &Package, i: usize) -> Result<Self, CodecError> {
        let m = pkg.manifest();
        let seg = m.segments.get(i).ok_or(CodecError::NoSegment {
            index: i,
            count: m.segments.len(),
        })?;
        let side = pkg.side_stream(i)?;
        let camera = m.camera;
        // The segment's one fragment (version 6), read and checked once for all its streams.
        let shared = match &seg.fragment {
            Some(f) => Some((Arc::<[u8]>::from(pkg.read(f)?), pkg.display_path(f))),
            None => None,
        };
        let streams = seg
            .streams
            .par_iter()
            .enumerate()
            .map(|(k, s)| {
                let size = scale::scaled_size(camera.width, camera.height, s.scale);
                let (w, h) = size;
                let reader = match (&shared, &s.file) {
                    (Some((data, shown)), _) => {
                        let shown = PathBuf::from(format!("{} (stream {k})", shown.display()));
                        PictureReader::open_run(&shown, data.clone(), k, m.codec, w, h)
                            .map(|r| (r, shown))
                    }
                    (None, Some(file)) => {
                        let data = pkg.read(file)?;
                        let shown = pkg.display_path(file);
                        // A fragment decodes on its own (its parameter sets are in band);
                        // its init segment is for standard MP4 readers.
                        match s.init {
                            Some(_) => {
                                PictureReader::open_run(&shown, data.into(), 0, m.codec, w, h)
                            }
                            None => PictureReader::open(&pkg.path_of(file), w, h)
                                .map_err(|e| shown_as(e, &shown)),
                        }
                        .map(|r| (r, shown))
                    }
                    (None, None) => Err(CodecError::Stream {
                        path: pkg.display_path(&seg.side),
                        reason: format!("stream {k} has no file"),
                    }),
                };
                let (reader, shown) = reader?;
                Ok(StreamCursor {
                    reader,
                    size,
                    scale: s.scale,
                    shown,
                })
            })
            .collect::<Result<_, CodecError>>()?;
        Ok(Self {
            camera,
            streams,
            side: side.frames.into_iter(),
            frames: seg.frames,
            done: 0,
            ended: false,
        })
    }

    /// The segment's number of frames.
    pub fn frames(&self) -> u32 {
        self.frames
    }

    /// How many frames the reader has given so far.
    pub fn given(&self) -> u32 {
        self.done
    }

    fn next_frame(&mut self, f: SideFrame) -> Result<DecodedFrame, CodecError> {
        let (cam, done, frames) = (self.camera, self.done, self.frames);
        let mut pictures: Vec<Option<PremulImage>> = self
            .streams
            .par_iter_mut()
            .map(|s| {
                let p = s
                    .reader
                    .next_picture()
                    .map_err(|e| shown_as(e, &s.shown))?
                    .ok_or_else(|| CodecError::Stream {
                        path: s.shown.clone(),
                        reason: format!("{done} pictures, the segment has {frames} frames"),
                    })?;
                let img = yuv::unstack(&p, s.size.0, s.size.1);
                Ok(Some(scale::upscale(img, cam.width, cam.height, s.scale)))
            })
            .collect::<Result<_, CodecError>>()?;
        // Each picture moves into the one layer that uses it (the side stream maps layers to
        // streams one to one, which `SideStream::decode` checks).
        let layers = f
            .layers
            .iter()
            .map(|l| {
                let image = pictures
                    .get_mut(l.stream as usize)
                    .and_then(Option::take)
                    .ok_or_else(|| CodecError::Layers {
                        frame: f.index,
                        reason: format!("stream {} missing or used twice", l.stream),
                    })?;
                let mut layer = Layer::new(image, l.depth as f64);
                layer.geometry = l.geometry.clone();
                layer.clip_to_geometry(&self.camera);
                layer.meta.track = l.track;
                Ok(layer)
            })
            .collect::<Result<_, CodecError>>()?;
        // The pictures are premultiplied by construction (`yuv::unstack` clamps colour to
        // alpha): no second scan of every pixel.
        let set = LayerSet::new_premultiplied(cam, layers, &Limits::default()).map_err(|e| {
            CodecError::Layers {
                frame: f.index,
                reason: e.to_string(),
            }
        })?;
        Ok(DecodedFrame { side: f, set })
    }

    /// After the last frame: no stream may hold another picture.
    fn check_end(&mut self) -> Result<(), CodecError> {
        let frames = self.frames;
        self.streams.par_iter_mut().try_for_each(|s| {
            match s.reader.next_picture().map_err(|e| shown_as(e, &s.shown))? {
                None => Ok(()),
                Some(_) => Err(CodecError::Stream {
                    path: s.shown.clone(),
                    reason: format!("more pictures than the segment's {frames} frames"),
                }),
            }
        })
    }
}

impl Iterator for SegmentReader {
    type Item = Result<DecodedFrame, CodecError>;

    fn next(&mut self) -> Option<Self::Item> {
        if self.ended {
            return None;
        }
        let result = match self.side.next() {
            Some(f) => self.next_frame(f),
            None => {
                self.ended = true;
                return self.check_end().err().map(Err);
            }
        };
        self.done += 1;
        self.ended = result.is_err();
        Some(result)
    }
}

/// A stream error naming the file as the user knows it.
fn shown_as(e: CodecError, shown: &Path) -> CodecError {
    match e {
        CodecError::Stream { reason, .. } => CodecError::Stream {
            path: shown.to_path_buf(),
            reason,
        },
        e => e,
    }
}
