//! Coding one layer stream: a sequence of colour-over-alpha pictures written as a movie
//! fragment or an MP4 file whose first picture is a key frame, and read back.

use crate::yuv::{stack, unstack, Yuv420};
use crate::CodecError;
use cpsl_core::PremulImage;
use cpsl_package::Codec;
use ffmpeg_next as ffmpeg;
use std::marker::PhantomData;
use std::path::{Path, PathBuf};
use std::sync::Arc;

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

/// Makes every allocation of 64 KiB or more fresh memory (mapped, so zeroed) instead of
/// memory freed earlier in the process. x264 reads bytes of one of its buffers of 64 to 128
/// KiB that it never wrote (its lookahead, on small pictures: a test coding 96x64 pictures
/// four times gave two different streams; `asm=0`, `rc-lookahead=0` or `mbtree=0` hide it),
/// so what earlier encoders left there changed the coded stream: three runs of the same
/// `cpsl encode` wrote three different packages. Fresh memory makes them the same. Set by
/// the first encoder a process opens: encoding costs nothing measurable (720p `cpsl encode
/// --bitrate 3M`: 10.8 and 11.3 s with it, 10.8 and 10.7 without), but playback would lose
/// about 6 % (`cpsl bench play`, 720p: 31.5 and 32.6 frames/s against 33.5 and 35.0), so
/// decoders leave it alone. glibc only; elsewhere nothing changes.
#[allow(unsafe_code)] // `mallopt` is a C function.
fn fresh_large_allocations() {
    #[cfg(all(target_os = "linux", target_env = "gnu"))]
    // SAFETY: `mallopt` only sets glibc's allocation policy, which may change at any time.
    unsafe {
        libc::mallopt(libc::M_MMAP_THRESHOLD, 64 * 1024);
    }
}

/// x264's AVX-512 code reads bytes of its buffers that it never wrote, so on a CPU that has
/// AVX-512 whatever earlier work of the process left in that memory changed the coded stream:
/// on a Xeon with AVX-512 two packages coded from the same frames in one test process (the
/// encoders on threads whose heaps other tests had used) differed in three runs of four, with
/// or without fresh memory from 64 KiB or 16 KiB up ([`fresh_large_allocations`]); with
/// x264's AVX2 code (and its 64-byte cache-line routines) in none of eight. Filling every
/// C-heap allocation with one byte (glibc's `M_PERTURB`, tried first) also served but made
/// `cpsl encode --bitrate 3M` 15-20 % slower. Elsewhere x264 detects the CPU itself.
fn x264_asm() -> &'static str {
    #[cfg(target_arch = "x86_64")]
    if std::arch::is_x86_feature_detected!("avx512f") {
        return ":asm=AVX2,Cache64";
    }
    ""
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
                &format!("keyint={n}:min-keyint={n}:scenecut=0{}", x264_asm()),
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
    /// A fragment's in-band configuration (parameter sets, sequence header), what its init
    /// segment's configuration record is made from ([`write_init`]); empty for an MP4 file.
    pub headers: Vec<u8>,
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

/// How a layer stream is stored.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default)]
pub enum Container {
    /// Movie fragments with in-band parameter sets, read with the package's init segment for
    /// their picture size; a segment's streams are the track runs of its one fragment
    /// (package version 6).
    #[default]
    Fragment,
    /// A movie fragment per stream and segment (package versions 4 and 5, for players that
    /// read only those).
    StreamFragments,
    /// A self-contained MP4 file (package versions 1 to 3).
    Mp4,
}

impl Container {
    /// Whether streams are movie fragments (read with an init segment).
    pub fn is_fragment(self) -> bool {
        self != Container::Mp4
    }
}

/// Where an encoder's packets go.
enum Out {
    Mp4 {
        octx: ffmpeg::format::context::Output,
        ost_tb: ffmpeg::Rational,
    },
    Fragment(Vec<crate::fmp4::Coded>),
}

/// One layer stream being written picture by picture: the pictures go to the encoder as they
/// come, so that nothing waits in memory for the rest of the segment. The first picture is
/// the stream's only key frame.
pub struct StreamEncoder<T: Sample = u8> {
    path: PathBuf,
    codec: Codec,
    size: (usize, usize),
    out: Out,
    enc: ffmpeg::encoder::Video,
    frame: ffmpeg::frame::Video,
    enc_tb: ffmpeg::Rational,
    pushed: i64,
    packets: Vec<u64>,
    sample: PhantomData<T>,
}

impl<T: Sample> StreamEncoder<T> {
    /// Starts the stream file `path` (a self-contained MP4 file) for pictures of `size`
    /// (even), coded at quality `crf`, with at most `max_frames` pictures between key frames
    /// (the segment's longest).
    pub fn create(
        path: &Path,
        size: (usize, usize),
        codec: Codec,
        crf: f32,
        fps: f64,
        max_frames: usize,
    ) -> Result<Self, CodecError> {
        Self::create_as(path, Container::Mp4, size, codec, crf, fps, max_frames)
    }

    /// [`StreamEncoder::create`] in the `container`: a fragment keeps its parameter sets in
    /// band and is written when the stream finishes.
    pub fn create_as(
        path: &Path,
        container: Container,
        size: (usize, usize),
        codec: Codec,
        crf: f32,
        fps: f64,
        max_frames: usize,
    ) -> Result<Self, CodecError> {
        init()?;
        static FRESH: std::sync::Once = std::sync::Once::new();
        FRESH.call_once(fresh_large_allocations);
        let name = encoder_name(codec);
        let enc_codec =
            ffmpeg::encoder::find_by_name(name).ok_or(CodecError::MissingEncoder(name))?;
        let mut octx = match container {
            Container::Mp4 => {
                Some(ffmpeg::format::output(&path).map_err(ff("creating the output"))?)
            }
            Container::Fragment | Container::StreamFragments => None,
        };
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
        // A fragment keeps its parameter sets in band: no global header.
        if octx.as_ref().is_some_and(|o| {
            o.format()
                .flags()
                .contains(ffmpeg::format::Flags::GLOBAL_HEADER)
        }) {
            enc.set_flags(ffmpeg::codec::Flags::GLOBAL_HEADER);
        }
        let enc = enc
            .open_as_with(enc_codec, options(codec, crf, max_frames))
            .map_err(ff("opening the encoder"))?;
        let out = match octx.take() {
            Some(mut octx) => {
                let mut ost = octx.add_stream(enc_codec).map_err(ff("adding a stream"))?;
                ost.set_parameters(&enc);
                ost.set_time_base(rate.invert());
                let mut mux_opts = ffmpeg::Dictionary::new();
                mux_opts.set("movflags", "+faststart");
                // No muxer banner (the `encoder` tag naming the libavformat version): 37
                // bytes per stream and segment, and the same bytes whichever FFmpeg wrote
                // them.
                mux_opts.set("fflags", "+bitexact");
                octx.write_header_with(mux_opts)
                    .map_err(ff("writing the header"))?;
                let ost_tb = octx.stream(0).expect("stream 0").time_base();
                Out::Mp4 { octx, ost_tb }
            }
            None => Out::Fragment(Vec::new()),
        };
        let mut frame = ffmpeg::frame::Video::new(T::FORMAT, size.0 as u32, size.1 as u32);
        frame.set_color_space(ffmpeg::color::Space::BT709);
        frame.set_color_range(ffmpeg::color::Range::MPEG);
        frame.set_color_primaries(ffmpeg::color::Primaries::BT709);
        frame.set_color_transfer_characteristic(ffmpeg::color::TransferCharacteristic::BT709);
        Ok(Self {
            path: path.to_path_buf(),
            codec,
            size,
            out,
            enc,
            frame,
            enc_tb: rate.invert(),
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
            match &mut self.out {
                Out::Mp4 { octx, ost_tb } => {
                    self.packets.push(packet.size() as u64);
                    packet.set_stream(0);
                    // One frame long: without a duration the MP4 edit list cuts the last frame.
                    packet.set_duration(1);
                    packet.rescale_ts(self.enc_tb, *ost_tb);
                    packet
                        .write_interleaved(octx)
                        .map_err(ff("writing a packet"))?;
                }
                Out::Fragment(samples) => {
                    let data = crate::fmp4::to_sample(self.codec, packet.data().unwrap_or(&[]));
                    self.packets.push(data.len() as u64);
                    samples.push(crate::fmp4::Coded {
                        data,
                        pts: packet.pts().unwrap_or(samples.len() as i64),
                        key: packet.is_key(),
                    });
                }
            }
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
        let Self {
            path,
            packets,
            out,
            codec,
            ..
        } = self;
        let io = |source| CodecError::Io {
            path: path.clone(),
            source,
        };
        let headers = match out {
            Out::Mp4 { mut octx, .. } => {
                octx.write_trailer().map_err(ff("writing the trailer"))?;
                drop(octx);
                Vec::new()
            }
            Out::Fragment(samples) => {
                std::fs::write(&path, crate::fmp4::fragment(&[&samples])).map_err(io)?;
                crate::fmp4::headers(codec, &samples[0].data)
            }
        };
        let bytes = std::fs::metadata(&path).map(|m| m.len()).map_err(io)?;
        Ok(Written {
            bytes,
            packets,
            headers,
        })
    }
}

/// The MP4 sample entry of a codec whose parameter sets may be in band.
fn in_band_tag(codec: Codec) -> &'static [u8; 4] {
    match codec {
        Codec::H264 => b"avc3",
        Codec::H265 => b"hev1",
        Codec::Av1 => b"av01",
        Codec::Vp9 => b"vp09",
    }
}

/// Writes the init segment (`ftyp` + `moov`) for fragments of `codec` pictures of `size`
/// at `fps` frames per second, its configuration record made from `headers` (a fragment's
/// in-band configuration, [`Written::headers`]): FFmpeg's MP4 muxer writes it, with the
/// sample duration and flags the fragments leave out as the track's defaults.
#[allow(unsafe_code)] // FFmpeg's codec parameters have no safe setters for a tag or extradata.
pub fn write_init<T: Sample>(
    path: &Path,
    codec: Codec,
    size: (usize, usize),
    fps: f64,
    headers: &[u8],
) -> Result<u64, CodecError> {
    use ffmpeg::ffi;
    init()?;
    let name = encoder_name(codec);
    let enc_codec = ffmpeg::encoder::find_by_name(name).ok_or(CodecError::MissingEncoder(name))?;
    let rate = ffmpeg::Rational::from(fps);
    let mut octx = ffmpeg::format::output_as(&path, "mp4").map_err(ff("creating the init"))?;
    {
        let mut ost = octx.add_stream(enc_codec).map_err(ff("adding a stream"))?;
        ost.set_time_base(rate.invert());
        let tag = in_band_tag(codec);
        // SAFETY: the stream and its codec parameters belong to `octx`, alive here; the
        // extradata is allocated with FFmpeg's allocator (padded as it requires) and freed
        // with the parameters.
        unsafe {
            let par = (*ost.as_mut_ptr()).codecpar;
            (*par).codec_type = ffi::AVMediaType::AVMEDIA_TYPE_VIDEO;
            (*par).codec_id = enc_codec.id().into();
            (*par).codec_tag = u32::from_le_bytes(*tag);
            (*par).width = size.0 as i32;
            (*par).height = size.1 as i32;
            (*par).format = ffi::AVPixelFormat::from(T::FORMAT) as i32;
            (*par).color_range = ffi::AVColorRange::AVCOL_RANGE_MPEG;
            (*par).color_primaries = ffi::AVColorPrimaries::AVCOL_PRI_BT709;
            (*par).color_trc = ffi::AVColorTransferCharacteristic::AVCOL_TRC_BT709;
            (*par).color_space = ffi::AVColorSpace::AVCOL_SPC_BT709;
            if !headers.is_empty() {
                let pad = ffi::AV_INPUT_BUFFER_PADDING_SIZE as usize;
                let buf = ffi::av_mallocz(headers.len() + pad) as *mut u8;
                if buf.is_null() {
                    return Err(CodecError::Ffmpeg("out of memory".into()));
                }
                std::ptr::copy_nonoverlapping(headers.as_ptr(), buf, headers.len());
                (*par).extradata = buf;
                (*par).extradata_size = headers.len() as i32;
            }
        }
    }
    let mut opts = ffmpeg::Dictionary::new();
    opts.set("movflags", "frag_keyframe+empty_moov+default_base_moof");
    opts.set("fflags", "+bitexact");
    opts.set("video_track_timescale", &rate.numerator().to_string());
    octx.write_header_with(opts)
        .map_err(ff("writing the init"))?;
    drop(octx);
    let io = |source| CodecError::Io {
        path: path.to_path_buf(),
        source,
    };
    let written = std::fs::read(path).map_err(io)?;
    let init = crate::fmp4::finish_init(&written, rate.denominator() as u32).map_err(|reason| {
        CodecError::Stream {
            path: path.to_path_buf(),
            reason,
        }
    })?;
    std::fs::write(path, &init).map_err(io)?;
    Ok(init.len() as u64)
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

/// Moves the NAL units of `data` to keep to its front and returns their length (the whole
/// length when nothing is dropped or the data does not parse).
fn drop_user_data_nals(data: &mut [u8]) -> usize {
    let Some(units) = crate::fmp4::nal_units(data) else {
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

/// Where a reader's packets come from.
enum Source {
    /// FFmpeg's demuxer of a self-contained file.
    Demux {
        input: ffmpeg::format::context::Input,
        index: usize,
    },
    /// A movie fragment's samples, in decoding order.
    Fragment {
        data: Arc<[u8]>,
        samples: Vec<crate::fmp4::Sample>,
        codec: Codec,
        next: usize,
    },
}

/// Reads the stacked pictures of one stream one at a time, decoding only as far as the next
/// picture needs: a player holds one picture per stream, not a whole segment.
pub struct PictureReader<T: Sample = u8> {
    path: PathBuf,
    source: Source,
    dec: ffmpeg::decoder::Video,
    frame: ffmpeg::frame::Video,
    drained: bool,
    /// A picture decoded ahead (a fragment's first, to check its size on opening).
    ahead: Option<Yuv420<T>>,
    sample: PhantomData<T>,
}

fn decoder_id(codec: Codec) -> ffmpeg::codec::Id {
    match codec {
        Codec::H264 => ffmpeg::codec::Id::H264,
        Codec::H265 => ffmpeg::codec::Id::HEVC,
        Codec::Av1 => ffmpeg::codec::Id::AV1,
        Codec::Vp9 => ffmpeg::codec::Id::VP9,
    }
}

impl<T: Sample> PictureReader<T> {
    /// Opens the stream of `width x height` images at `path` (a self-contained MP4 file),
    /// checking its picture size.
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
            return Err(bad(size_reason(
                (dec.width() as usize, dec.height() as usize),
                width,
                height,
            )));
        }
        Ok(Self {
            path: path.to_path_buf(),
            source: Source::Demux { input, index },
            dec,
            frame: ffmpeg::frame::Video::empty(),
            drained: false,
            ahead: None,
            sample: PhantomData,
        })
    }

    /// Opens the stream at `path` in `container` ([`PictureReader::open`] for an MP4 file;
    /// a fragment's first run is read, as [`PictureReader::open_run`] reads it).
    pub fn open_as(
        path: &Path,
        container: Container,
        codec: Codec,
        width: u32,
        height: u32,
    ) -> Result<Self, CodecError> {
        if container == Container::Mp4 {
            return Self::open(path, width, height);
        }
        let data = std::fs::read(path).map_err(|source| CodecError::Io {
            path: path.to_path_buf(),
            source,
        })?;
        Self::open_run(path, data.into(), 0, codec, width, height)
    }

    /// Opens run `run` of the movie fragment `data` (the file at `path`, which the streams of
    /// a segment share): a stream of `codec` pictures, checked by decoding its first picture.
    pub fn open_run(
        path: &Path,
        data: Arc<[u8]>,
        run: usize,
        codec: Codec,
        width: u32,
        height: u32,
    ) -> Result<Self, CodecError> {
        init()?;
        let bad = |reason: String| CodecError::Stream {
            path: path.to_path_buf(),
            reason,
        };
        let mut runs = crate::fmp4::parse_fragment(&data).map_err(bad)?;
        if run >= runs.len() {
            return Err(bad(format!(
                "stream {run} asked for, the fragment holds {}",
                runs.len()
            )));
        }
        let samples = runs.swap_remove(run);
        if !samples[0].key {
            return Err(bad("the first picture is not a key picture".into()));
        }
        let id = decoder_id(codec);
        let found = ffmpeg::decoder::find(id).ok_or(CodecError::MissingEncoder(codec.name()))?;
        let dec = ffmpeg::codec::context::Context::new_with_codec(found)
            .decoder()
            .video()
            .map_err(|e| bad(e.to_string()))?;
        let mut reader = Self {
            path: path.to_path_buf(),
            source: Source::Fragment {
                data,
                samples,
                codec,
                next: 0,
            },
            dec,
            frame: ffmpeg::frame::Video::empty(),
            drained: false,
            ahead: None,
            sample: PhantomData,
        };
        let first = reader
            .next_picture()?
            .ok_or_else(|| bad("no pictures".into()))?;
        let (cw, ch) = crate::yuv::coded_size(width, height);
        if (first.width, first.height) != (cw, 2 * ch) {
            return Err(bad(size_reason((first.width, first.height), width, height)));
        }
        reader.ahead = Some(first);
        Ok(reader)
    }

    fn bad(&self, reason: String) -> CodecError {
        CodecError::Stream {
            path: self.path.clone(),
            reason,
        }
    }

    /// The next picture in display order, or `None` after the last.
    pub fn next_picture(&mut self) -> Result<Option<Yuv420<T>>, CodecError> {
        if let Some(p) = self.ahead.take() {
            return Ok(Some(p));
        }
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
            match self.next_packet()? {
                Some(packet) => self
                    .dec
                    .send_packet(&packet)
                    .map_err(|e| self.bad(e.to_string()))?,
                None => {
                    self.dec.send_eof().map_err(|e| self.bad(e.to_string()))?;
                    self.drained = true;
                }
            }
        }
    }

    /// The stream's next packet, `None` at its end.
    fn next_packet(&mut self) -> Result<Option<ffmpeg::Packet>, CodecError> {
        match &mut self.source {
            Source::Demux { input, index } => loop {
                let mut packet = ffmpeg::Packet::empty();
                match packet.read(input) {
                    Ok(()) if packet.stream() == *index => return Ok(Some(packet)),
                    Ok(()) => {}
                    Err(ffmpeg::Error::Eof) => return Ok(None),
                    Err(e) => return Err(self.bad(e.to_string())),
                }
            },
            Source::Fragment {
                data,
                samples,
                codec,
                next,
            } => {
                let Some(s) = samples.get(*next) else {
                    return Ok(None);
                };
                let mut packet =
                    ffmpeg::Packet::copy(&crate::fmp4::to_decoder(*codec, &data[s.range.clone()]));
                packet.set_dts(Some(*next as i64));
                packet.set_pts(Some(*next as i64 + s.offset));
                if s.key {
                    packet.set_flags(ffmpeg::packet::Flags::KEY);
                }
                *next += 1;
                Ok(Some(packet))
            }
        }
    }
}

fn size_reason(found: (usize, usize), width: u32, height: u32) -> String {
    let (cw, ch) = crate::yuv::coded_size(width, height);
    format!(
        "pictures are {}x{}, a {width}x{height} layer needs {cw}x{}",
        found.0,
        found.1,
        2 * ch
    )
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
