//! Video files through FFmpeg: any container and codec it reads, converted to RGB with the
//! matrix and range each frame declares, HDR mapped to SDR, turned upright, with H.264 motion
//! vectors.

use crate::hdr::{Signal, ToSdr, Transfer};
use crate::motion::motion_from_vectors;
use crate::orient::{rotate, rotate_motion, rotation_of};
use crate::{FrameSource, Info, InputFrame, MediaError};
use cpsl_core::ycbcr::{Matrix, ToRgb};
use ffmpeg_next as ffmpeg;
use std::path::{Path, PathBuf};

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
    /// Damaged packets skipped since the last one the decoder took.
    damaged_in_a_row: usize,
    flushed: bool,
    mvs: bool,
    /// The last frame's luma, where the decoder's motion vectors are exported.
    prev_luma: Option<Vec<u8>>,
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
    /// Opens the file and its best video stream (an H.264 stream's frames carry the decoder's
    /// motion vectors).
    pub fn open(path: &Path) -> Result<Self, MediaError> {
        Self::open_with(path, true)
    }

    /// [`VideoFile::open`], exporting the decoder's motion vectors only where `motion` asks.
    pub fn open_with(path: &Path, motion: bool) -> Result<Self, MediaError> {
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
        let mvs = motion && id == ffmpeg::codec::Id::H264;
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
                damaged: 0,
            },
            decoded: 0,
            damaged_in_a_row: 0,
            flushed: false,
            mvs,
            prev_luma: None,
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
        // The vectors' reference distances are found from this frame's and the previous
        // frame's luma (8-bit 4:2:0 only: other H.264 streams take optical flow).
        let motion = if self.mvs && self.ycc.as_ref().is_some_and(|y| y.planar420) {
            let (stride, data) = (frame.stride(0), frame.data(0));
            let mut luma = vec![0u8; w * h];
            for (y, row) in luma.chunks_exact_mut(w).enumerate() {
                row.copy_from_slice(&data[y * stride..][..w]);
            }
            let motion = self.prev_luma.as_deref().and_then(|prev| {
                let sd = frame.side_data(ffmpeg::frame::side_data::Type::MotionVectors)?;
                motion_from_vectors(sd.data(), w, h, &luma, prev)
            });
            self.prev_luma = Some(luma);
            motion
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
    let other = if y.is_multiple_of(2) {
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
                Some(packet) => match self.decoder.send_packet(&packet) {
                    Ok(()) => self.damaged_in_a_row = 0,
                    // A damaged packet is skipped (its picture is lost, and those that refer
                    // to it may show artefacts until the next key frame), unless the stream
                    // is beyond repair.
                    Err(ffmpeg::Error::InvalidData)
                        if self.damaged_in_a_row < crate::MAX_DAMAGED_IN_A_ROW =>
                    {
                        self.damaged_in_a_row += 1;
                        self.info.damaged += 1;
                    }
                    Err(e) => return Err(self.decode_error(e)),
                },
                None => {
                    self.decoder.send_eof().map_err(|e| self.decode_error(e))?;
                    self.flushed = true;
                }
            }
        }
    }
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
