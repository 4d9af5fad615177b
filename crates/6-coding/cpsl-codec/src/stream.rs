//! Coding one layer stream: a sequence of colour-over-alpha pictures written as an MP4 file
//! whose first picture is a key frame, and read back.

use crate::yuv::{stack, unstack, Yuv420};
use crate::CodecError;
use cpsl_core::PremulImage;
use cpsl_package::Codec;
use ffmpeg_next as ffmpeg;
use std::marker::PhantomData;
use std::path::{Path, PathBuf};

/// The encoder's quality scale (CRF) for a codec: (lowest, highest, default). Lower is better.
pub fn quality_range(codec: Codec) -> (f32, f32, f32) {
    match codec {
        Codec::H264 => (10.0, 51.0, 23.0),
        Codec::H265 => (10.0, 51.0, 28.0),
        Codec::Av1 => (10.0, 63.0, 35.0),
        Codec::Vp9 => (10.0, 63.0, 32.0),
    }
}

fn encoder_name(codec: Codec) -> &'static str {
    match codec {
        Codec::H264 => "libx264",
        Codec::H265 => "libx265",
        Codec::Av1 => "libsvtav1",
        Codec::Vp9 => "libvpx-vp9",
    }
}

/// Whether this FFmpeg build has the encoder of `codec`.
pub fn has_encoder(codec: Codec) -> bool {
    init().is_ok() && ffmpeg::encoder::find_by_name(encoder_name(codec)).is_some()
}

pub(crate) fn init() -> Result<(), CodecError> {
    ffmpeg::init().map_err(|e| CodecError::Ffmpeg(e.to_string()))?;
    ffmpeg::util::log::set_level(ffmpeg::util::log::Level::Fatal);
    Ok(())
}

/// Encoder options: one key frame at the start, no scene-cut key frames, a speed preset fit for
/// 2 cores, constant quality `crf`; x265 writes no informational SEI (its version and options,
/// about 2.3 kB in every stream's header).
fn options(codec: Codec, crf: f32, frames: usize) -> ffmpeg::Dictionary<'static> {
    let mut o = ffmpeg::Dictionary::new();
    let n = frames.max(1);
    match codec {
        Codec::H264 => {
            o.set("preset", "veryfast");
            o.set("crf", &format!("{crf:.1}"));
            o.set(
                "x264-params",
                &format!("keyint={n}:min-keyint={n}:scenecut=0"),
            );
        }
        Codec::H265 => {
            o.set("preset", "ultrafast");
            o.set("crf", &format!("{crf:.1}"));
            o.set(
                "x265-params",
                &format!("log-level=error:keyint={n}:min-keyint={n}:scenecut=0:info=0"),
            );
        }
        Codec::Av1 => {
            o.set("preset", "10");
            o.set("crf", &format!("{}", crf.round() as i32));
        }
        Codec::Vp9 => {
            o.set("deadline", "realtime");
            o.set("cpu-used", "8");
            o.set("crf", &format!("{}", crf.round() as i32));
            o.set("b", "0");
            o.set("row-mt", "1");
        }
    }
    o.set("threads", "1");
    o
}

/// A picture sample type and the pixel format that carries it: `u8` is 8-bit 4:2:0 (`yuv420p`),
/// `u16` 10-bit 4:2:0 (`yuv420p10le`, values up to 1023).
pub trait Sample: Copy + sealed::Sealed {
    /// The FFmpeg pixel format.
    #[doc(hidden)]
    const FORMAT: ffmpeg::format::Pixel;
    /// Writes `src` as the bytes of one row of that format.
    #[doc(hidden)]
    fn put(dst: &mut [u8], src: &[Self]);
    /// Reads `n` samples of one row of that format.
    #[doc(hidden)]
    fn get(src: &[u8], n: usize) -> Vec<Self>;
}

mod sealed {
    pub trait Sealed {}
    impl Sealed for u8 {}
    impl Sealed for u16 {}
}

impl Sample for u8 {
    const FORMAT: ffmpeg::format::Pixel = ffmpeg::format::Pixel::YUV420P;
    fn put(dst: &mut [u8], src: &[u8]) {
        dst[..src.len()].copy_from_slice(src);
    }
    fn get(src: &[u8], n: usize) -> Vec<u8> {
        src[..n].to_vec()
    }
}

impl Sample for u16 {
    const FORMAT: ffmpeg::format::Pixel = ffmpeg::format::Pixel::YUV420P10LE;
    fn put(dst: &mut [u8], src: &[u16]) {
        for (d, s) in dst.chunks_exact_mut(2).zip(src) {
            d.copy_from_slice(&s.to_le_bytes());
        }
    }
    fn get(src: &[u8], n: usize) -> Vec<u16> {
        src[..2 * n]
            .chunks_exact(2)
            .map(|b| u16::from_le_bytes([b[0], b[1]]))
            .collect()
    }
}

fn ff(what: &'static str) -> impl Fn(ffmpeg::Error) -> CodecError {
    move |e| CodecError::Ffmpeg(format!("{what}: {e}"))
}

/// Encodes `layers` (one stream's pictures, all the same size) at quality `crf` into the MP4
/// file `path`, tagged BT.709 limited range. Returns the file size in bytes.
pub fn encode_stream(
    path: &Path,
    layers: &[&PremulImage],
    codec: Codec,
    crf: f32,
    fps: f64,
) -> Result<u64, CodecError> {
    let first = layers.first().ok_or(CodecError::Empty)?;
    let (w, h) = (first.width(), first.height());
    if let Some(l) = layers.iter().find(|l| (l.width(), l.height()) != (w, h)) {
        return Err(CodecError::Size {
            expected: (w, h),
            found: (l.width(), l.height()),
        });
    }
    encode_pictures(path, layers.len(), &|i| stack(layers[i]), codec, crf, fps)
}

/// Encodes `count` pictures of the same even size, picture `i` made by `picture(i)`, at quality
/// `crf` into the MP4 file `path`, tagged BT.709 limited range, at the samples' bit depth.
/// Returns the file size in bytes.
pub fn encode_pictures<T: Sample>(
    path: &Path,
    count: usize,
    picture: &dyn Fn(usize) -> Yuv420<T>,
    codec: Codec,
    crf: f32,
    fps: f64,
) -> Result<u64, CodecError> {
    if count == 0 {
        return Err(CodecError::Empty);
    }
    let first = picture(0);
    let mut enc = StreamEncoder::create(path, (first.width, first.height), codec, crf, fps, count)?;
    enc.push(&first)?;
    for i in 1..count {
        enc.push(&picture(i))?;
    }
    Ok(enc.finish()?.bytes)
}

/// What [`StreamEncoder::finish`] wrote.
#[derive(Debug, Clone, PartialEq)]
pub struct Written {
    /// The file's size in bytes.
    pub bytes: u64,
    /// Each coded picture's size in bytes, in decoding order (the key frame first).
    pub packets: Vec<u64>,
}

impl Written {
    /// Bits of the key frame with the container's (everything but the other pictures), and
    /// the mean bits of the other pictures (0 when there are none).
    pub fn intra_inter_bits(&self) -> (f64, f64) {
        let rest = &self.packets[self.packets.len().min(1)..];
        let rest_bytes: u64 = rest.iter().sum();
        let intra = self.bytes.saturating_sub(rest_bytes) as f64 * 8.0;
        (intra, rest_bytes as f64 * 8.0 / rest.len().max(1) as f64)
    }
}

/// One layer stream being written picture by picture: the pictures go to the encoder as they
/// come, so that nothing waits in memory for the rest of the segment. The first picture is
/// the stream's only key frame.
pub struct StreamEncoder<T: Sample = u8> {
    path: PathBuf,
    codec: Codec,
    size: (usize, usize),
    octx: ffmpeg::format::context::Output,
    enc: ffmpeg::encoder::Video,
    frame: ffmpeg::frame::Video,
    enc_tb: ffmpeg::Rational,
    ost_tb: ffmpeg::Rational,
    pushed: i64,
    packets: Vec<u64>,
    sample: PhantomData<T>,
}

impl<T: Sample> StreamEncoder<T> {
    /// Starts the MP4 file `path` for pictures of `size` (even), coded at quality `crf`, with
    /// at most `max_frames` pictures between key frames (the segment's longest).
    pub fn create(
        path: &Path,
        size: (usize, usize),
        codec: Codec,
        crf: f32,
        fps: f64,
        max_frames: usize,
    ) -> Result<Self, CodecError> {
        init()?;
        let name = encoder_name(codec);
        let enc_codec =
            ffmpeg::encoder::find_by_name(name).ok_or(CodecError::MissingEncoder(name))?;
        let mut octx = ffmpeg::format::output(&path).map_err(ff("creating the output"))?;
        let global = octx
            .format()
            .flags()
            .contains(ffmpeg::format::Flags::GLOBAL_HEADER);
        let mut ost = octx.add_stream(enc_codec).map_err(ff("adding a stream"))?;
        let mut enc = ffmpeg::codec::context::Context::new_with_codec(enc_codec)
            .encoder()
            .video()
            .map_err(ff("creating the encoder"))?;
        let rate = ffmpeg::Rational::from(fps);
        enc.set_width(size.0 as u32);
        enc.set_height(size.1 as u32);
        enc.set_format(T::FORMAT);
        enc.set_time_base(rate.invert());
        enc.set_frame_rate(Some(rate));
        enc.set_gop(max_frames.max(1) as u32);
        enc.set_colorspace(ffmpeg::color::Space::BT709);
        enc.set_color_range(ffmpeg::color::Range::MPEG);
        enc.set_color_primaries(ffmpeg::color::Primaries::BT709);
        enc.set_color_transfer_characteristic(ffmpeg::color::TransferCharacteristic::BT709);
        if global {
            enc.set_flags(ffmpeg::codec::Flags::GLOBAL_HEADER);
        }
        let enc = enc
            .open_as_with(enc_codec, options(codec, crf, max_frames))
            .map_err(ff("opening the encoder"))?;
        ost.set_parameters(&enc);
        ost.set_time_base(rate.invert());
        let mut mux_opts = ffmpeg::Dictionary::new();
        mux_opts.set("movflags", "+faststart");
        // No muxer banner (the `encoder` tag naming the libavformat version): 37 bytes per
        // stream and segment, and the same bytes whichever FFmpeg wrote them.
        mux_opts.set("fflags", "+bitexact");
        octx.write_header_with(mux_opts)
            .map_err(ff("writing the header"))?;
        let ost_tb = octx.stream(0).expect("stream 0").time_base();
        let mut frame = ffmpeg::frame::Video::new(T::FORMAT, size.0 as u32, size.1 as u32);
        frame.set_color_space(ffmpeg::color::Space::BT709);
        frame.set_color_range(ffmpeg::color::Range::MPEG);
        frame.set_color_primaries(ffmpeg::color::Primaries::BT709);
        frame.set_color_transfer_characteristic(ffmpeg::color::TransferCharacteristic::BT709);
        Ok(Self {
            path: path.to_path_buf(),
            codec,
            size,
            octx,
            enc,
            frame,
            enc_tb: rate.invert(),
            ost_tb,
            pushed: 0,
            packets: Vec::new(),
            sample: PhantomData,
        })
    }

    /// Codes the next picture.
    pub fn push(&mut self, p: &Yuv420<T>) -> Result<(), CodecError> {
        if (p.width, p.height) != self.size {
            return Err(CodecError::Size {
                expected: (self.size.0 as u32, self.size.1 as u32),
                found: (p.width as u32, p.height as u32),
            });
        }
        fill_frame(&mut self.frame, p);
        self.frame.set_pts(Some(self.pushed));
        self.frame.set_kind(if self.pushed == 0 {
            ffmpeg::picture::Type::I
        } else {
            ffmpeg::picture::Type::None
        });
        self.enc.send_frame(&self.frame).map_err(ff("encoding"))?;
        self.pushed += 1;
        self.drain()
    }

    fn drain(&mut self) -> Result<(), CodecError> {
        let mut packet = ffmpeg::Packet::empty();
        while self.enc.receive_packet(&mut packet).is_ok() {
            if self.codec == Codec::H264 {
                drop_user_data_sei(&mut packet);
            }
            self.packets.push(packet.size() as u64);
            packet.set_stream(0);
            // One frame long: without a duration the MP4 edit list cuts the last frame.
            packet.set_duration(1);
            packet.rescale_ts(self.enc_tb, self.ost_tb);
            packet
                .write_interleaved(&mut self.octx)
                .map_err(ff("writing a packet"))?;
        }
        Ok(())
    }

    /// Flushes the encoder and closes the file.
    pub fn finish(mut self) -> Result<Written, CodecError> {
        if self.pushed == 0 {
            return Err(CodecError::Empty);
        }
        self.enc.send_eof().map_err(ff("flushing the encoder"))?;
        self.drain()?;
        self.octx
            .write_trailer()
            .map_err(ff("writing the trailer"))?;
        let Self {
            path,
            packets,
            octx,
            ..
        } = self;
        drop(octx);
        let bytes = std::fs::metadata(&path)
            .map(|m| m.len())
            .map_err(|source| CodecError::Io {
                path: path.clone(),
                source,
            })?;
        Ok(Written { bytes, packets })
    }
}

/// Removes from an H.264 packet every SEI NAL unit that opens with a user-data-unregistered
/// message: x264's version and options string, about 660 bytes in each stream's first picture
/// that decoders ignore. A packet that parses neither as Annex B nor as length-prefixed NAL
/// units is left as it is.
fn drop_user_data_sei(packet: &mut ffmpeg::Packet) {
    let Some(data) = packet.data_mut() else {
        return;
    };
    let kept = drop_user_data_nals(data);
    if kept < data.len() {
        packet.shrink(kept);
    }
}

/// The NAL units of an H.264 access unit: (start, payload start, end) of each, the start
/// including its start code or length prefix. `None` if `data` is neither Annex B (start
/// codes) nor tiled by 4-byte length prefixes.
fn nal_units(data: &[u8]) -> Option<Vec<(usize, usize, usize)>> {
    let mut units = Vec::new();
    if data.starts_with(&[0, 0, 1]) || data.starts_with(&[0, 0, 0, 1]) {
        // Annex B: emulation prevention keeps 00 00 01 out of the payloads.
        let codes: Vec<usize> = (0..data.len().saturating_sub(2))
            .filter(|&i| data[i..i + 3] == [0, 0, 1])
            .collect();
        for (k, &c) in codes.iter().enumerate() {
            let start = if c > 0 && data[c - 1] == 0 { c - 1 } else { c };
            let end = codes
                .get(k + 1)
                .map_or(data.len(), |&n| if data[n - 1] == 0 { n - 1 } else { n });
            units.push((start, c + 3, end));
        }
        return Some(units);
    }
    let mut at = 0;
    while at < data.len() {
        let b = data.get(at..at + 4)?;
        let len = u32::from_be_bytes([b[0], b[1], b[2], b[3]]) as usize;
        let end = at + 4 + len;
        if len == 0 || end > data.len() {
            return None;
        }
        units.push((at, at + 4, end));
        at = end;
    }
    Some(units)
}

/// Moves the NAL units of `data` to keep to its front and returns their length (the whole
/// length when nothing is dropped or the data does not parse).
fn drop_user_data_nals(data: &mut [u8]) -> usize {
    let Some(units) = nal_units(data) else {
        return data.len();
    };
    let mut out = 0;
    for (start, payload, end) in units {
        // NAL type 6 (SEI) whose first message has payload type 5 (user data unregistered).
        let user_sei =
            payload < end && data[payload] & 0x1f == 6 && data.get(payload + 1) == Some(&5);
        if !user_sei {
            data.copy_within(start..end, out);
            out += end - start;
        }
    }
    out
}

fn fill_frame<T: Sample>(frame: &mut ffmpeg::frame::Video, pic: &Yuv420<T>) {
    let planes = [
        (&pic.y, pic.width, pic.height),
        (&pic.u, pic.width / 2, pic.height / 2),
        (&pic.v, pic.width / 2, pic.height / 2),
    ];
    for (i, (src, w, h)) in planes.into_iter().enumerate() {
        let stride = frame.stride(i);
        let dst = frame.data_mut(i);
        for y in 0..h {
            T::put(&mut dst[y * stride..], &src[y * w..(y + 1) * w]);
        }
    }
}

fn read_frame<T: Sample>(frame: &ffmpeg::frame::Video) -> Yuv420<T> {
    let (w, h) = (frame.width() as usize, frame.height() as usize);
    let plane = |i: usize, pw: usize, ph: usize| {
        let stride = frame.stride(i);
        let d = frame.data(i);
        let mut out = Vec::with_capacity(pw * ph);
        for y in 0..ph {
            out.extend(T::get(&d[y * stride..], pw));
        }
        out
    };
    Yuv420 {
        width: w,
        height: h,
        y: plane(0, w, h),
        u: plane(1, w / 2, h / 2),
        v: plane(2, w / 2, h / 2),
    }
}

/// Decodes a layer stream written by [`encode_stream`] (or any 8-bit 4:2:0 stream of the same
/// layout) into `width x height` layers, one per picture.
pub fn decode_stream(path: &Path, width: u32, height: u32) -> Result<Vec<PremulImage>, CodecError> {
    Ok(decode_pictures(path, width, height)?
        .iter()
        .map(|p| unstack(p, width, height))
        .collect())
}

/// Decodes a stream of stacked pictures for `width x height` images (as written by
/// [`encode_pictures`]), checking their size and bit depth.
pub fn decode_pictures<T: Sample>(
    path: &Path,
    width: u32,
    height: u32,
) -> Result<Vec<Yuv420<T>>, CodecError> {
    let mut reader = PictureReader::open(path, width, height)?;
    let mut out = Vec::new();
    while let Some(p) = reader.next_picture()? {
        out.push(p);
    }
    if out.is_empty() {
        return Err(reader.bad("no pictures".into()));
    }
    Ok(out)
}

/// Reads the stacked pictures of one stream one at a time, decoding only as far as the next
/// picture needs: a player holds one picture per stream, not a whole segment.
pub struct PictureReader<T: Sample = u8> {
    path: PathBuf,
    input: ffmpeg::format::context::Input,
    index: usize,
    dec: ffmpeg::decoder::Video,
    frame: ffmpeg::frame::Video,
    drained: bool,
    sample: PhantomData<T>,
}

impl<T: Sample> PictureReader<T> {
    /// Opens the stream of `width x height` images at `path`, checking its picture size.
    pub fn open(path: &Path, width: u32, height: u32) -> Result<Self, CodecError> {
        init()?;
        let bad = |reason: String| CodecError::Stream {
            path: path.to_path_buf(),
            reason,
        };
        let input = ffmpeg::format::input(&path).map_err(|e| bad(e.to_string()))?;
        let st = input
            .streams()
            .best(ffmpeg::media::Type::Video)
            .ok_or_else(|| bad("no video stream".into()))?;
        let index = st.index();
        let ctx = ffmpeg::codec::context::Context::from_parameters(st.parameters())
            .map_err(|e| bad(e.to_string()))?;
        let dec = ctx.decoder().video().map_err(|e| bad(e.to_string()))?;
        let (cw, ch) = crate::yuv::coded_size(width, height);
        if (dec.width() as usize, dec.height() as usize) != (cw, 2 * ch) {
            return Err(bad(format!(
                "pictures are {}x{}, a {width}x{height} layer needs {cw}x{}",
                dec.width(),
                dec.height(),
                2 * ch
            )));
        }
        Ok(Self {
            path: path.to_path_buf(),
            input,
            index,
            dec,
            frame: ffmpeg::frame::Video::empty(),
            drained: false,
            sample: PhantomData,
        })
    }

    fn bad(&self, reason: String) -> CodecError {
        CodecError::Stream {
            path: self.path.clone(),
            reason,
        }
    }

    /// The next picture in display order, or `None` after the last.
    pub fn next_picture(&mut self) -> Result<Option<Yuv420<T>>, CodecError> {
        loop {
            match self.dec.receive_frame(&mut self.frame) {
                Ok(()) => {
                    if self.frame.format() != T::FORMAT {
                        return Err(self.bad(format!(
                            "pixel format {:?}, {:?} expected",
                            self.frame.format(),
                            T::FORMAT
                        )));
                    }
                    return Ok(Some(read_frame(&self.frame)));
                }
                Err(ffmpeg::Error::Eof) => return Ok(None),
                Err(ffmpeg::Error::Other { errno }) if errno == ffmpeg::error::EAGAIN => {}
                Err(e) => return Err(self.bad(e.to_string())),
            }
            if self.drained {
                return Ok(None);
            }
            // The decoder wants input: the next packet of the stream, or the end.
            let mut packet = ffmpeg::Packet::empty();
            match packet.read(&mut self.input) {
                Ok(()) if packet.stream() == self.index => self
                    .dec
                    .send_packet(&packet)
                    .map_err(|e| self.bad(e.to_string()))?,
                Ok(()) => {}
                Err(ffmpeg::Error::Eof) => {
                    self.dec.send_eof().map_err(|e| self.bad(e.to_string()))?;
                    self.drained = true;
                }
                Err(e) => return Err(self.bad(e.to_string())),
            }
        }
    }
}

#[cfg(test)]
mod tests {
    use super::drop_user_data_nals;

    fn unit(bytes: &[u8]) -> Vec<u8> {
        let mut v = (bytes.len() as u32).to_be_bytes().to_vec();
        v.extend_from_slice(bytes);
        v
    }

    #[test]
    fn only_user_data_sei_is_dropped() {
        let slice = unit(&[0x65, 1, 2, 3]);
        let user = unit(&[0x06, 5, 9, b'x', b'2', b'6', b'4', 0x80]);
        let timing = unit(&[0x06, 1, 1, 0, 0x80]);
        let mut data = [
            unit(&[0x67, 7, 7]),
            user.clone(),
            timing.clone(),
            slice.clone(),
        ]
        .concat();
        let n = drop_user_data_nals(&mut data);
        let want = [unit(&[0x67, 7, 7]), timing, slice].concat();
        assert_eq!(&data[..n], &want[..]);
        // Nothing to drop, or data that is not length-prefixed: untouched.
        let mut plain = want.clone();
        assert_eq!(drop_user_data_nals(&mut plain), want.len());
        let mut cut = user[..5].to_vec();
        assert_eq!(drop_user_data_nals(&mut cut), 5);
        // Annex B, with 3- and 4-byte start codes, as libx264 hands its packets over.
        let mut annex_b = [
            &[0u8, 0, 1, 0x06, 5, 2, 0xaa, 0x80][..],
            &[0, 0, 0, 1, 0x06, 1, 1, 0, 0x80],
            &[0, 0, 0, 1, 0x65, 0, 0, 3, 1, 4],
        ]
        .concat();
        let n = drop_user_data_nals(&mut annex_b);
        assert_eq!(
            &annex_b[..n],
            &[0, 0, 0, 1, 0x06, 1, 1, 0, 0x80, 0, 0, 0, 1, 0x65, 0, 0, 3, 1, 4][..]
        );
    }
}
