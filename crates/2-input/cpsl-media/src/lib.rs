//! Media input: RGB frames from a video file (through FFmpeg: any container and codec it
//! reads) or from a folder of images (an image sequence, in file-name order).
//!
//! Y'CbCr video is converted to RGB with the matrix and range the stream declares (BT.709,
//! BT.601, BT.2020, SMPTE 240M; limited or full range). Where it declares no matrix, BT.601
//! is used, as FFmpeg's own scaler does (and as the `ffmpeg` tool encodes untagged video).
//! HDR video (PQ or HLG with BT.2020 primaries, as phones record it) is mapped to SDR BT.709.
//! Pictures are turned upright by the stream's display matrix (quarter turns), as players
//! show them.
//!
//! H.264 streams are decoded with `flags2=+export_mvs`, and each frame carries the decoder's
//! motion vectors as a dense backward motion field ([`InputFrame::motion`]) when they describe it
//! (P-frames predicted from the previous frame only); callers fall back to optical flow
//! otherwise.

use cpsl_core::ycbcr::{Matrix, ToRgb};
use cpsl_core::Flow;
use ffmpeg_next as ffmpeg;
use rayon::prelude::*;
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

/// A motion field of a picture turned clockwise by `degrees` (a quarter turn): positions and
/// vectors turn with it.
pub fn rotate_motion(motion: Flow, degrees: u32) -> Flow {
    if degrees == 0 {
        return motion;
    }
    let mut data = rotate(motion.data, motion.width, motion.height, 2, degrees);
    for v in data.chunks_exact_mut(2) {
        let (dx, dy) = (v[0], v[1]);
        [v[0], v[1]] = match degrees {
            90 => [-dy, dx],
            180 => [-dx, -dy],
            _ => [dy, -dx],
        };
    }
    let (width, height) = if degrees == 180 {
        (motion.width, motion.height)
    } else {
        (motion.height, motion.width)
    };
    Flow {
        width,
        height,
        data,
    }
}

/// One decoded frame.
#[derive(Debug, Clone)]
pub struct InputFrame {
    /// Index in the input.
    pub index: usize,
    /// RGB, 3 bytes per pixel, row major.
    pub rgb: Vec<u8>,
    /// Backward motion from the decoder's motion vectors, where the stream has them.
    pub motion: Option<Flow>,
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
    /// Clockwise rotation applied to every decoded picture, in degrees (0, 90, 180 or 270):
    /// the stream's display matrix, as players show it (phone videos filmed upright). The
    /// width and height above are after it.
    pub rotation: u32,
    /// The transfer function of an HDR video (`PQ` or `HLG`, BT.2020 primaries), whose
    /// pictures are mapped to SDR BT.709: reference white (203 cd/m2) to white, highlights
    /// rolled off. `None` for SDR video and images.
    pub hdr: Option<&'static str>,
}

/// A source of frames.
pub trait FrameSource {
    /// What the input is.
    fn info(&self) -> &Info;
    /// The next frame, `Ok(None)` at the end.
    fn next_frame(&mut self) -> Result<Option<InputFrame>, MediaError>;
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
                rotation: 0,
                hdr: None,
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

/// A video file decoded by FFmpeg.
pub struct VideoFile {
    path: PathBuf,
    input: ffmpeg::format::context::Input,
    stream: usize,
    decoder: ffmpeg::decoder::Video,
    /// To 8-bit RGB (RGB and grey sources) or to 8-bit 4:4:4 Y'CbCr in the source's range,
    /// converted to RGB here with the frame's matrix; to 16 bits (RGB or 4:4:4 Y'CbCr) for
    /// HDR sources; none for 8-bit 4:2:0 SDR sources, whose chroma is upsampled here.
    scaler: Option<ffmpeg::software::scaling::Context>,
    ycc: Option<YccSource>,
    /// HDR video: the mapping of its BT.2020 R'G'B' to SDR BT.709.
    to_sdr: Option<ToSdr>,
    /// Decoded (coded) picture size, before the rotation, and format: every frame must keep
    /// them.
    coded: (usize, usize),
    format: ffmpeg::format::Pixel,
    info: Info,
    decoded: usize,
    flushed: bool,
    mvs: bool,
}

/// How a Y'CbCr source's samples are read.
struct YccSource {
    /// The pixel format says full range (`yuvj*`).
    full: bool,
    /// 8-bit planar 4:2:0 (`yuv420p`, `yuvj420p`): converted without the scaler.
    planar420: bool,
    /// Tables of the last (matrix, range).
    tables: Option<(Matrix, bool, ToRgb)>,
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
        let rotation = st
            .side_data()
            .find(|d| d.kind() == ffmpeg::codec::packet::side_data::Type::DisplayMatrix)
            .map_or(0, |d| rotation_of(d.data()));
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
        let format = decoder.format();
        let name = format.descriptor().map_or("", |d| d.name());
        let ycc = (!is_rgb_format(name)).then(|| YccSource {
            full: name.starts_with("yuvj"),
            planar420: name == "yuv420p" || name == "yuvj420p",
            tables: None,
        });
        let (hdr, to_sdr) = match decoder.color_transfer_characteristic() {
            ffmpeg::color::TransferCharacteristic::SMPTE2084 => {
                (Some("PQ"), Some(ToSdr::new(Transfer::Pq)))
            }
            ffmpeg::color::TransferCharacteristic::ARIB_STD_B67 => {
                (Some("HLG"), Some(ToSdr::new(Transfer::Hlg)))
            }
            _ => (None, None),
        };
        use ffmpeg::format::Pixel;
        let target = match (&ycc, to_sdr.is_some()) {
            // HDR keeps 16 bits to the mapping: a PQ step of 8 bits is about three SDR steps.
            (None, true) => Some(Pixel::RGB48LE),
            (Some(_), true) => Some(Pixel::YUV444P16LE),
            (None, false) => Some(Pixel::RGB24),
            (Some(y), false) if y.planar420 => None,
            (Some(y), false) if y.full => Some(Pixel::YUVJ444P),
            (Some(_), false) => Some(Pixel::YUV444P),
        };
        let scaler = target
            .map(|t| {
                ffmpeg::software::scaling::Context::get(
                    format,
                    w,
                    h,
                    t,
                    w,
                    h,
                    ffmpeg::software::scaling::Flags::BILINEAR,
                )
            })
            .transpose()
            .map_err(|e| fail(e.to_string()))?;
        let (width, height) = if rotation % 180 == 90 { (h, w) } else { (w, h) };
        Ok(Self {
            path: path.to_path_buf(),
            input,
            stream,
            decoder,
            scaler,
            ycc,
            to_sdr,
            coded: (w as usize, h as usize),
            format,
            info: Info {
                width,
                height,
                fps,
                frames,
                codec: codec.name().to_string(),
                rotation,
                hdr,
            },
            decoded: 0,
            flushed: false,
            mvs,
        })
    }

    fn convert(&mut self, frame: &ffmpeg::frame::Video) -> Result<InputFrame, MediaError> {
        let (w, h) = self.coded;
        let size = (frame.width() as usize, frame.height() as usize);
        if size != (w, h) || frame.format() != self.format {
            return Err(MediaError::Decode {
                path: self.path.clone(),
                frames: self.decoded,
                reason: format!(
                    "the pictures change from {w}x{h} {:?} to {}x{} {:?} mid-stream",
                    self.format,
                    size.0,
                    size.1,
                    frame.format()
                ),
            });
        }
        let mut scaled = ffmpeg::frame::Video::empty();
        let pic = match &mut self.scaler {
            Some(scaler) => {
                let run = scaler.run(frame, &mut scaled);
                run.map_err(|e| self.decode_error(e))?;
                &scaled
            }
            None => frame,
        };
        let mut rgb = vec![0u8; w * h * 3];
        let plane = |i: usize| (pic.stride(i), pic.data(i));
        match (&mut self.ycc, &self.to_sdr) {
            (None, None) => {
                let (stride, data) = plane(0);
                for (y, out) in rgb.chunks_exact_mut(w * 3).enumerate() {
                    out.copy_from_slice(&data[y * stride..][..w * 3]);
                }
            }
            (None, Some(map)) => {
                let (stride, data) = plane(0);
                map.apply(&mut rgb, w, |y, [r, g, b]| {
                    for (x, px) in data[y * stride..][..6 * w].chunks_exact(6).enumerate() {
                        let v = |c: usize| f32::from(u16::from_le_bytes([px[c], px[c + 1]]));
                        [r[x], g[x], b[x]] = [v(0), v(2), v(4)].map(|v| v / 65535.0);
                    }
                });
            }
            (Some(src), Some(map)) => {
                // The scaler gives yuvj (8-bit full range) sources limited range.
                let full = !src.full && frame.color_range() == ffmpeg::color::Range::JPEG;
                let signal = Signal::new(matrix_of(frame.color_space()), full);
                let ((sy, py), (su, pu), (sv, pv)) = (plane(0), plane(1), plane(2));
                map.apply(&mut rgb, w, |y, [r, g, b]| {
                    let l = samples16(&py[y * sy..][..2 * w]);
                    let cb = samples16(&pu[y * su..][..2 * w]);
                    let cr = samples16(&pv[y * sv..][..2 * w]);
                    let samples = l.zip(cb).zip(cr);
                    for (x, ((l, cb), cr)) in samples.enumerate() {
                        [r[x], g[x], b[x]] = signal.rgb(l, cb, cr);
                    }
                });
            }
            (Some(src), None) => {
                let matrix = matrix_of(frame.color_space());
                let full = src.full || frame.color_range() == ffmpeg::color::Range::JPEG;
                if src
                    .tables
                    .as_ref()
                    .is_none_or(|t| (t.0, t.1) != (matrix, full))
                {
                    src.tables = Some((matrix, full, ToRgb::new(matrix, full)));
                }
                let t = &src.tables.as_ref().expect("set above").2;
                let ((sy, py), (su, pu), (sv, pv)) = (plane(0), plane(1), plane(2));
                if src.planar420 {
                    let (cw, ch) = (w.div_ceil(2), h.div_ceil(2));
                    let (mut cb, mut cr) = (vec![0u8; w], vec![0u8; w]);
                    let mut rows = Vec::with_capacity(cw + 1);
                    for (y, out) in rgb.chunks_exact_mut(w * 3).enumerate() {
                        upsample_chroma(pu, (su, cw, ch), y, &mut rows, &mut cb);
                        upsample_chroma(pv, (sv, cw, ch), y, &mut rows, &mut cr);
                        let luma = &py[y * sy..][..w];
                        for (x, px) in out.chunks_exact_mut(3).enumerate() {
                            px.copy_from_slice(&t.rgb(luma[x], cb[x], cr[x]));
                        }
                    }
                } else {
                    for (y, out) in rgb.chunks_exact_mut(w * 3).enumerate() {
                        let (ly, lu, lv) = (&py[y * sy..], &pu[y * su..], &pv[y * sv..]);
                        for (x, px) in out.chunks_exact_mut(3).enumerate() {
                            px.copy_from_slice(&t.rgb(ly[x], lu[x], lv[x]));
                        }
                    }
                }
            }
        }
        let motion = if self.mvs {
            frame
                .side_data(ffmpeg::frame::side_data::Type::MotionVectors)
                .and_then(|sd| motion_from_vectors(sd.data(), w, h))
        } else {
            None
        };
        self.decoded += 1;
        Ok(InputFrame {
            index: self.decoded - 1,
            rgb: rotate(rgb, w, h, 3, self.info.rotation),
            motion: motion.map(|m| rotate_motion(m, self.info.rotation)),
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

/// Row `y` of a 4:2:0 chroma plane (`cw x ch` samples, `stride` apart) upsampled to the luma
/// width (`out.len()`), bilinearly, with the chroma siting of H.264, H.265 and MPEG-2 (left):
/// a sample sits on the even luma columns and halfway between two luma rows. `rows` is
/// scratch space.
fn upsample_chroma(
    plane: &[u8],
    (stride, cw, ch): (usize, usize, usize),
    y: usize,
    rows: &mut Vec<u16>,
    out: &mut [u8],
) {
    let c = y / 2;
    // The nearer chroma row weighs 3/4, the other (above for even rows) 1/4.
    let other = if y % 2 == 0 {
        c.saturating_sub(1)
    } else {
        (c + 1).min(ch - 1)
    };
    let (near, far) = (&plane[c * stride..][..cw], &plane[other * stride..][..cw]);
    rows.clear();
    rows.extend(
        near.iter()
            .zip(far)
            .map(|(&n, &f)| 3 * u16::from(n) + u16::from(f)),
    );
    rows.push(rows[cw - 1]);
    // In eighths: even columns on a sample, odd ones halfway to the next.
    for (i, o) in out.chunks_mut(2).enumerate() {
        let (a, b) = (rows[i], rows[i + 1]);
        o[0] = ((2 * a + 4) >> 3) as u8;
        if let Some(odd) = o.get_mut(1) {
            *odd = ((a + b + 4) >> 3) as u8;
        }
    }
}

/// 16-bit little-endian samples.
fn samples16(bytes: &[u8]) -> impl Iterator<Item = f32> + '_ {
    bytes
        .chunks_exact(2)
        .map(|v| f32::from(u16::from_le_bytes([v[0], v[1]])))
}

/// Whether an FFmpeg pixel format holds RGB or grey samples (converted to RGB by FFmpeg's
/// scaler) rather than Y'CbCr.
fn is_rgb_format(name: &str) -> bool {
    ["rgb", "bgr", "gbr", "gray", "ya8", "ya16", "pal8", "mono"]
        .iter()
        .any(|k| name.contains(k))
}

/// The transfer function of an HDR video.
#[derive(Debug, Clone, Copy, PartialEq)]
enum Transfer {
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
struct Signal {
    y0: f32,
    /// Reciprocals of the luma and chroma scales.
    ys: f32,
    cs: f32,
    /// The matrix's [`Matrix::chroma_weights`].
    weights: [f32; 4],
}

impl Signal {
    fn new(matrix: Matrix, full: bool) -> Self {
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
    fn rgb(&self, y: f32, cb: f32, cr: f32) -> [f32; 3] {
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
struct ToSdr {
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
    fn new(transfer: Transfer) -> Self {
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
    fn apply(&self, rgb: &mut [u8], w: usize, signal: impl Fn(usize, &mut [Vec<f32>; 3]) + Sync) {
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
    fn map_row(&self, planes: &mut [Vec<f32>; 3], out: &mut [u8]) {
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

/// The matrix a stream declares; BT.601 where it declares none (FFmpeg's default).
fn matrix_of(space: ffmpeg::color::Space) -> Matrix {
    use ffmpeg::color::Space;
    match space {
        Space::BT709 => Matrix::BT709,
        Space::BT2020NCL | Space::BT2020CL => Matrix::BT2020,
        Space::SMPTE240M => Matrix::SMPTE240M,
        Space::FCC => Matrix::FCC,
        _ => Matrix::BT601,
    }
}

/// The clockwise rotation (0, 90, 180 or 270 degrees) that shows a picture upright, from a
/// display matrix (nine 32-bit integers, 16.16 fixed point), as FFmpeg's tools apply it; 0
/// for a rotation that is not a quarter turn.
pub fn rotation_of(matrix: &[u8]) -> u32 {
    if matrix.len() < 36 {
        return 0;
    }
    let m = |i: usize| {
        i32::from_ne_bytes(matrix[4 * i..4 * i + 4].try_into().expect("4 bytes")) as f64 / 65536.0
    };
    let (s0, s1) = (m(0).hypot(m(3)), m(1).hypot(m(4)));
    if s0 == 0.0 || s1 == 0.0 {
        return 0;
    }
    let deg = (m(1) / s1).atan2(m(0) / s0).to_degrees().round();
    let deg = deg.rem_euclid(360.0) as u32;
    if deg % 90 == 0 {
        deg % 360
    } else {
        0
    }
}

/// A `w x h` picture of `n`-sample pixels turned clockwise by `degrees` (0, 90, 180 or 270).
pub fn rotate<T: Copy>(data: Vec<T>, w: usize, h: usize, n: usize, degrees: u32) -> Vec<T> {
    if degrees == 0 {
        return data;
    }
    let (ow, oh) = if degrees == 180 { (w, h) } else { (h, w) };
    let mut out = Vec::with_capacity(data.len());
    for y in 0..oh {
        for x in 0..ow {
            // The source pixel that lands on (x, y).
            let (sx, sy) = match degrees {
                90 => (y, h - 1 - x),
                180 => (w - 1 - x, h - 1 - y),
                _ => (w - 1 - y, x),
            };
            out.extend_from_slice(&data[(sy * w + sx) * n..][..n]);
        }
    }
    out
}

impl FrameSource for VideoFile {
    fn info(&self) -> &Info {
        &self.info
    }

    fn next_frame(&mut self) -> Result<Option<InputFrame>, MediaError> {
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
pub fn motion_from_vectors(raw: &[u8], w: usize, h: usize) -> Option<Flow> {
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
    Some(Flow {
        width: w,
        height: h,
        data,
    })
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn chroma_is_upsampled_with_left_siting() {
        // 2x2 chroma samples for a 3x4 picture (odd width), stride 5.
        let plane = [0u8, 80, 9, 9, 9, 160, 240, 9, 9, 9];
        let mut rows = Vec::new();
        let mut out = [0u8; 3];
        let mut row = |y| {
            upsample_chroma(&plane, (5, 2, 2), y, &mut rows, &mut out);
            out
        };
        // Even columns sit on a sample, odd ones halfway; rows are 3:1 blends of the nearer
        // and the other chroma row (clamped at the edges).
        assert_eq!(row(0), [0, 40, 80]);
        assert_eq!(row(1), [40, 80, 120]);
        assert_eq!(row(2), [120, 160, 200]);
        assert_eq!(row(3), [160, 200, 240]);
    }
}
