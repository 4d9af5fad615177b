//! Media input: RGB frames from a video file (through FFmpeg: any container and codec it
//! reads) or from a folder of images (an image sequence, in file-name order).
//!
//! H.264 streams are decoded with `flags2=+export_mvs`, and each frame carries the decoder's
//! motion vectors as a dense backward motion field ([`Frame::motion`]) when they describe it
//! (P-frames predicted from the previous frame only); callers fall back to optical flow
//! otherwise.

use ffmpeg_next as ffmpeg;
use std::path::{Path, PathBuf};
use thiserror::Error;

/// Errors of media input.
#[derive(Debug, Error)]
pub enum MediaError {
    /// The path does not exist or cannot be read.
    #[error("cannot read {path}: {reason}")]
    Unreadable {
        /// The path.
        path: PathBuf,
        /// Why.
        reason: String,
    },
    /// The file has no video stream.
    #[error("{0} has no video stream")]
    NoVideo(PathBuf),
    /// The input holds no frame.
    #[error("{0} holds no frames")]
    Empty(PathBuf),
    /// Decoding failed part-way (truncated or corrupt input).
    #[error("{path}: decoding failed after {frames} frames: {reason}")]
    Decode {
        /// The path.
        path: PathBuf,
        /// Frames decoded before the failure.
        frames: usize,
        /// Why.
        reason: String,
    },
    /// A frame of an image sequence differs in size from the first.
    #[error("{path} is {found:?} pixels, the sequence is {expected:?}")]
    FrameSize {
        /// The file.
        path: PathBuf,
        /// Its size.
        found: (u32, u32),
        /// The first frame's.
        expected: (u32, u32),
    },
    /// Reading an image failed.
    #[error(transparent)]
    Image(#[from] cpsl_io::IoError),
}

/// A dense motion field: per pixel `(dx, dy)` to the pixel of the previous frame it shows.
#[derive(Debug, Clone, PartialEq)]
pub struct Motion {
    /// Width.
    pub width: usize,
    /// Height.
    pub height: usize,
    /// `[dx0, dy0, dx1, dy1, ...]`.
    pub data: Vec<f32>,
}

/// One decoded frame.
#[derive(Debug, Clone)]
pub struct Frame {
    /// Index in the input.
    pub index: usize,
    /// RGB, 3 bytes per pixel, row major.
    pub rgb: Vec<u8>,
    /// Backward motion from the decoder's motion vectors, where the stream has them.
    pub motion: Option<Motion>,
}

/// What the input is.
#[derive(Debug, Clone, PartialEq)]
pub struct Info {
    /// Width.
    pub width: u32,
    /// Height.
    pub height: u32,
    /// Frames per second (image sequences: 30).
    pub fps: f64,
    /// Frame count if known in advance.
    pub frames: Option<usize>,
    /// Codec name (`image` for image sequences).
    pub codec: String,
}

/// A source of frames.
pub trait FrameSource {
    /// What the input is.
    fn info(&self) -> &Info;
    /// The next frame, `Ok(None)` at the end.
    fn next_frame(&mut self) -> Result<Option<Frame>, MediaError>;
}

/// Opens a video file or an image folder.
pub fn open(path: &Path) -> Result<Box<dyn FrameSource>, MediaError> {
    if path.is_dir() {
        Ok(Box::new(ImageSequence::open(path)?))
    } else {
        Ok(Box::new(VideoFile::open(path)?))
    }
}

/// A folder of PNG or JPEG images, in file-name order.
pub struct ImageSequence {
    files: Vec<PathBuf>,
    next: usize,
    info: Info,
}

impl ImageSequence {
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

    fn next_frame(&mut self) -> Result<Option<Frame>, MediaError> {
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
        Ok(Some(Frame {
            index: self.next - 1,
            rgb: img.data,
            motion: None,
        }))
    }
}

/// A video file decoded by FFmpeg.
pub struct VideoFile {
    path: PathBuf,
    input: ffmpeg::format::context::Input,
    stream: usize,
    decoder: ffmpeg::decoder::Video,
    scaler: ffmpeg::software::scaling::Context,
    info: Info,
    decoded: usize,
    flushed: bool,
    mvs: bool,
}

impl VideoFile {
    /// Opens the file and its best video stream.
    pub fn open(path: &Path) -> Result<Self, MediaError> {
        let fail = |reason: String| MediaError::Unreadable {
            path: path.to_path_buf(),
            reason,
        };
        ffmpeg::init().map_err(|e| fail(e.to_string()))?;
        // Errors come back as values; FFmpeg's own log stays quiet.
        ffmpeg::util::log::set_level(ffmpeg::util::log::Level::Fatal);
        if !path.exists() {
            return Err(fail("no such file".into()));
        }
        let input = ffmpeg::format::input(&path).map_err(|e| fail(e.to_string()))?;
        let st = input
            .streams()
            .best(ffmpeg::media::Type::Video)
            .ok_or_else(|| MediaError::NoVideo(path.to_path_buf()))?;
        let stream = st.index();
        let rate = st.avg_frame_rate();
        let fps = if rate.denominator() != 0 && rate.numerator() > 0 {
            rate.numerator() as f64 / rate.denominator() as f64
        } else {
            30.0
        };
        let frames = (st.frames() > 0).then_some(st.frames() as usize);
        let ctx = ffmpeg::codec::context::Context::from_parameters(st.parameters())
            .map_err(|e| fail(e.to_string()))?;
        let id = ctx.id();
        let mvs = id == ffmpeg::codec::Id::H264;
        let codec =
            ffmpeg::decoder::find(id).ok_or_else(|| fail(format!("no decoder for {id:?}")))?;
        let mut opts = ffmpeg::Dictionary::new();
        if mvs {
            opts.set("flags2", "+export_mvs");
        }
        let decoder = ctx
            .decoder()
            .open_as_with(codec, opts)
            .and_then(|o| o.video())
            .map_err(|e| fail(e.to_string()))?;
        let (w, h) = (decoder.width(), decoder.height());
        if w == 0 || h == 0 {
            return Err(fail("the video stream has no size".into()));
        }
        let scaler = ffmpeg::software::scaling::Context::get(
            decoder.format(),
            w,
            h,
            ffmpeg::format::Pixel::RGB24,
            w,
            h,
            ffmpeg::software::scaling::Flags::BILINEAR,
        )
        .map_err(|e| fail(e.to_string()))?;
        Ok(Self {
            path: path.to_path_buf(),
            input,
            stream,
            decoder,
            scaler,
            info: Info {
                width: w,
                height: h,
                fps,
                frames,
                codec: codec.name().to_string(),
            },
            decoded: 0,
            flushed: false,
            mvs,
        })
    }

    fn convert(&mut self, frame: &ffmpeg::frame::Video) -> Result<Frame, MediaError> {
        let mut rgb = ffmpeg::frame::Video::empty();
        self.scaler
            .run(frame, &mut rgb)
            .map_err(|e| self.decode_error(e))?;
        let (w, h) = (self.info.width as usize, self.info.height as usize);
        let stride = rgb.stride(0);
        let data = rgb.data(0);
        let mut out = Vec::with_capacity(w * h * 3);
        for y in 0..h {
            out.extend_from_slice(&data[y * stride..y * stride + w * 3]);
        }
        let motion = if self.mvs {
            frame
                .side_data(ffmpeg::frame::side_data::Type::MotionVectors)
                .and_then(|sd| motion_from_vectors(sd.data(), w, h))
        } else {
            None
        };
        self.decoded += 1;
        Ok(Frame {
            index: self.decoded - 1,
            rgb: out,
            motion,
        })
    }

    fn decode_error(&self, e: ffmpeg::Error) -> MediaError {
        MediaError::Decode {
            path: self.path.clone(),
            frames: self.decoded,
            reason: e.to_string(),
        }
    }
}

impl FrameSource for VideoFile {
    fn info(&self) -> &Info {
        &self.info
    }

    fn next_frame(&mut self) -> Result<Option<Frame>, MediaError> {
        let mut frame = ffmpeg::frame::Video::empty();
        loop {
            match self.decoder.receive_frame(&mut frame) {
                Ok(()) => return self.convert(&frame).map(Some),
                Err(ffmpeg::Error::Eof) => {
                    return if self.decoded == 0 {
                        Err(MediaError::Empty(self.path.clone()))
                    } else {
                        Ok(None)
                    };
                }
                Err(ffmpeg::Error::Other { errno }) if errno == ffmpeg::util::error::EAGAIN => {}
                Err(e) => return Err(self.decode_error(e)),
            }
            if self.flushed {
                return if self.decoded == 0 {
                    Err(MediaError::Empty(self.path.clone()))
                } else {
                    Ok(None)
                };
            }
            // Feed the next packet of our stream, or flush at the end.
            let next = self
                .input
                .packets()
                .find(|(s, _)| s.index() == self.stream)
                .map(|(_, p)| p);
            match next {
                Some(packet) => {
                    self.decoder
                        .send_packet(&packet)
                        .map_err(|e| self.decode_error(e))?;
                }
                None => {
                    self.decoder.send_eof().map_err(|e| self.decode_error(e))?;
                    self.flushed = true;
                }
            }
        }
    }
}

/// Size in bytes of FFmpeg's `AVMotionVector`: `int32 source; uint8 w, h; int16 src_x, src_y,
/// dst_x, dst_y; uint64 flags; int32 motion_x, motion_y; uint16 motion_scale` (dst is the block
/// centre, `src = dst + motion / motion_scale`).
const MV_SIZE: usize = 40;

/// A dense backward motion field from `AVMotionVector` records, if they cover at least half of
/// the frame with vectors into the previous frame (`source == -1`). Uncovered pixels (intra
/// blocks) get the median vector.
pub fn motion_from_vectors(raw: &[u8], w: usize, h: usize) -> Option<Motion> {
    let i16_at = |b: &[u8], o: usize| i16::from_ne_bytes([b[o], b[o + 1]]) as i32;
    let i32_at = |b: &[u8], o: usize| i32::from_ne_bytes([b[o], b[o + 1], b[o + 2], b[o + 3]]);
    let mut data = vec![0f32; w * h * 2];
    let mut covered = vec![false; w * h];
    let mut vectors = Vec::new();
    for r in raw.chunks_exact(MV_SIZE) {
        let source = i32_at(r, 0);
        let (bw, bh) = (r[4] as i32, r[5] as i32);
        let (dx, dy) = (i16_at(r, 10), i16_at(r, 12));
        let (mx, my) = (i32_at(r, 24), i32_at(r, 28));
        let scale = u16::from_ne_bytes([r[32], r[33]]).max(1) as f32;
        if source != -1 {
            continue;
        }
        let (u, v) = (mx as f32 / scale, my as f32 / scale);
        vectors.push((u, v));
        for y in (dy - bh / 2).max(0)..(dy + bh / 2).min(h as i32) {
            for x in (dx - bw / 2).max(0)..(dx + bw / 2).min(w as i32) {
                let p = y as usize * w + x as usize;
                data[p * 2] = u;
                data[p * 2 + 1] = v;
                covered[p] = true;
            }
        }
    }
    let n = covered.iter().filter(|&&c| c).count();
    if n * 2 < w * h {
        return None;
    }
    let median = |mut v: Vec<f32>| {
        let m = v.len() / 2;
        *v.select_nth_unstable_by(m, f32::total_cmp).1
    };
    let mu = median(vectors.iter().map(|v| v.0).collect());
    let mv = median(vectors.iter().map(|v| v.1).collect());
    for p in (0..w * h).filter(|&p| !covered[p]) {
        data[p * 2] = mu;
        data[p * 2 + 1] = mv;
    }
    Some(Motion {
        width: w,
        height: h,
        data,
    })
}
