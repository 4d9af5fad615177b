//! Layer streams of a CPSL package: coding a segment (a group of pictures of layer sets) into
//! one standard video stream per layer plus a side stream, with the per-layer bitrate
//! allocation, and decoding a segment back into layer sets.
//!
//! **Layout.** Each layer of a segment is one MP4 file of 8-bit 4:2:0 pictures twice the frame
//! height: premultiplied colour on top, alpha as grey below ([`yuv`]), tagged BT.709 limited
//! range; under a tight budget a stream may be coded at a half, a quarter or an eighth of the
//! frame size ([`scale`]). Per-layer streams keep per-layer rate control exact; a segment's streams hold the
//! same frames and start with a key frame, so a player decodes them in lock-step (the browser
//! player with WebCodecs). The side stream (`side.bin`, see `cpsl-package`) maps each frame's
//! layers to streams and carries depths, confidence, refresh flags and the Edge-Depth Cache.

pub mod alloc;
pub mod scale;
mod stream;
pub mod yuv;

pub use stream::{
    decode_pictures, decode_stream, encode_pictures, encode_stream, has_encoder, quality_range,
    PictureReader, Sample,
};

use cpsl_core::{Camera, Layer, LayerSet, LayeredFrame, Limits, PremulImage, RefreshReason};
use cpsl_package::{
    file_entry, segment_dir, Codec, Package, PackageError, Segment, SideFrame, SideLayer,
    SideStream, StreamEntry,
};
use rayon::prelude::*;
use std::path::{Path, PathBuf};
use std::sync::OnceLock;
use thiserror::Error;

/// Errors of coding layer streams.
#[derive(Debug, Error)]
pub enum CodecError {
    /// FFmpeg failed.
    #[error("FFmpeg: {0}")]
    Ffmpeg(String),
    /// The FFmpeg build lacks an encoder.
    #[error("this FFmpeg has no {0} encoder")]
    MissingEncoder(&'static str),
    /// Nothing to code.
    #[error("no pictures to code")]
    Empty,
    /// Pictures of different sizes.
    #[error("picture of {found:?} pixels in a stream of {expected:?}")]
    Size {
        /// The stream's size.
        expected: (u32, u32),
        /// The odd picture's.
        found: (u32, u32),
    },
    /// The layers of a frame do not map onto the segment's streams.
    #[error("frame {frame}: {reason}")]
    Tracks {
        /// Frame index.
        frame: u32,
        /// What is wrong.
        reason: String,
    },
    /// A layer stream cannot be decoded or does not fit its segment.
    #[error("{path}: {reason}")]
    Stream {
        /// The stream file.
        path: PathBuf,
        /// What is wrong.
        reason: String,
    },
    /// A file operation failed.
    #[error("{path}: {source}")]
    Io {
        /// The file.
        path: PathBuf,
        /// The cause.
        source: std::io::Error,
    },
    /// The package is damaged.
    #[error(transparent)]
    Package(#[from] PackageError),
    /// Writing the package failed.
    #[error(transparent)]
    Write(#[from] cpsl_io::IoError),
    /// A segment index past the package's segments.
    #[error("no segment {index}: the package has {count}")]
    NoSegment {
        /// The index asked for.
        index: usize,
        /// How many segments there are.
        count: usize,
    },
    /// A decoded layer set is invalid.
    #[error("decoded frame {frame}: {reason}")]
    Layers {
        /// Frame index.
        frame: u32,
        /// What is wrong.
        reason: String,
    },
}

/// How a segment's bits are spent.
#[derive(Debug, Clone, Copy, PartialEq)]
pub enum RateControl {
    /// Every stream at this quality (CRF).
    Quality(f32),
    /// A total budget in bits per second for layer and side streams, allocated per layer.
    Budget(f64),
}

/// Coding options.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct CodingOptions {
    /// The codec of the layer streams.
    pub codec: Codec,
    /// Rate control.
    pub rate: RateControl,
    /// Frames per second.
    pub fps: f64,
}

/// What coding one segment did.
#[derive(Debug, Clone, PartialEq)]
pub struct SegmentReport {
    /// The index of the segment's first frame.
    pub start: u32,
    /// The budget of the segment in bits (`None` at constant quality).
    pub budget_bits: Option<f64>,
    /// Bits written (layer streams and side stream).
    pub bits: f64,
    /// Quality chosen per stream.
    pub quality: Vec<f32>,
    /// Downscale factor chosen per stream (see [`scale`]).
    pub scale: Vec<u32>,
    /// Whether the budget could be met.
    pub feasible: bool,
    /// Whether every stream is at the cheapest coding: the worst quality at the smallest
    /// size of the ladder (an unmet budget is then below what any coding needs).
    pub at_floor: bool,
    /// Encodes run (trials, final and corrections), over all streams.
    pub encodes: usize,
}

/// Assigns every layer of every frame to a stream: stream `k` carries the track of the first
/// frame's layer `k`; later frames' layers follow their track (or their index where layers
/// have no tracks).
fn stream_map(frames: &[LayeredFrame]) -> Result<Vec<Vec<u8>>, CodecError> {
    let first = &frames[0].set;
    let tracks: Vec<Option<u32>> = first.layers().iter().map(|l| l.meta.track).collect();
    frames
        .iter()
        .map(|f| {
            let bad = |reason: String| CodecError::Tracks {
                frame: f.index,
                reason,
            };
            let mut used = vec![false; tracks.len()];
            f.set
                .layers()
                .iter()
                .enumerate()
                .map(|(i, l)| {
                    let s = match l.meta.track {
                        Some(t) => tracks.iter().position(|&u| u == Some(t)),
                        None => (i < tracks.len() && tracks[i].is_none()).then_some(i),
                    }
                    .ok_or_else(|| {
                        bad(format!(
                            "layer {i} (track {:?}) is not in the segment's first frame",
                            l.meta.track
                        ))
                    })?;
                    if std::mem::replace(&mut used[s], true) {
                        return Err(bad(format!("two layers map to stream {s}")));
                    }
                    Ok(s as u8)
                })
                .collect()
        })
        .collect()
}

/// Codes one segment into `root/seg_NNNNNN/` (layer streams and side stream) and returns its
/// manifest entry. The first frame must be an I-frame, the others P-frames of the same layers.
pub fn encode_segment(
    root: &Path,
    number: usize,
    frames: &[LayeredFrame],
    opts: &CodingOptions,
) -> Result<(Segment, SegmentReport), CodecError> {
    let first = frames.first().ok_or(CodecError::Empty)?;
    let (w, h) = (first.set.camera().width, first.set.camera().height);
    let map = stream_map(frames)?;
    let n_streams = first.set.len();
    // Per stream, per frame: the layer's picture (transparent where the frame lacks it).
    let blank = PremulImage::new(w, h);
    let mut pictures: Vec<Vec<&PremulImage>> = vec![vec![&blank; frames.len()]; n_streams];
    for (fi, (f, m)) in frames.iter().zip(&map).enumerate() {
        for (l, &s) in f.set.layers().iter().zip(m) {
            pictures[s as usize][fi] = &l.image;
        }
    }
    let dir_name = segment_dir(number);
    let dir = root.join(&dir_name);
    std::fs::create_dir_all(&dir).map_err(|source| CodecError::Io {
        path: dir.clone(),
        source,
    })?;
    // The side stream.
    let side = SideStream {
        segment: number as u32,
        start: first.index,
        streams: n_streams as u16,
        width: w,
        height: h,
        frames: frames
            .iter()
            .zip(&map)
            .enumerate()
            .map(|(i, (f, m))| SideFrame {
                index: f.index,
                intra: i == 0,
                refresh: if i == 0 {
                    Some(f.refresh.unwrap_or(RefreshReason::Gop))
                } else {
                    None
                },
                layers: f
                    .set
                    .layers()
                    .iter()
                    .zip(m)
                    .enumerate()
                    .map(|(k, (l, &s))| SideLayer {
                        stream: s,
                        depth: l.depth as f32,
                        confidence: f.confidence.get(k).copied().unwrap_or(1.0).clamp(0.0, 1.0),
                        track: l.meta.track,
                    })
                    .collect(),
                edc: cpsl_package::summarise_edc(&f.edc),
            })
            .collect(),
    };
    let side_rel = format!("{dir_name}/side.bin");
    let side_bytes = side.encode();
    let side_path = root.join(&side_rel);
    std::fs::write(&side_path, &side_bytes).map_err(|source| CodecError::Io {
        path: side_path,
        source,
    })?;
    // Weights from the I-frame: saliency and share of depth-edge samples.
    let mut edges = vec![0usize; n_streams];
    for s in &first.edc.samples {
        for k in [s.front, s.back] {
            if let Some(e) = edges.get_mut(k as usize) {
                *e += 1;
            }
        }
    }
    let max_edges = edges.iter().copied().max().unwrap_or(0);
    let weights: Vec<f32> = first
        .set
        .layers()
        .iter()
        .zip(&edges)
        .map(|(l, &e)| alloc::weight(l.meta.saliency.unwrap_or(0.0), e, max_edges))
        .collect();
    let stream_rel = |k: usize| format!("{dir_name}/layer_{k:02}.mp4");
    // The resolution ladder: only a budget may send a stream below full size.
    let rungs = match opts.rate {
        RateControl::Budget(_) => scale::rungs(w, h),
        RateControl::Quality(_) => vec![1],
    };
    // The smaller pictures, made when the smaller rungs are first fitted (see below: before
    // any parallel job can ask for them, so that no job waits on its own initialisation).
    let scaled: OnceLock<Vec<Vec<Vec<PremulImage>>>> = OnceLock::new();
    let pics = |k: usize, r: usize| -> Vec<&PremulImage> {
        if r == 0 {
            return pictures[k].clone();
        }
        let scaled = scaled.get_or_init(|| {
            rungs[1..]
                .iter()
                .map(|&f| {
                    pictures
                        .iter()
                        .map(|p| p.par_iter().map(|i| scale::downscale(i, f)).collect())
                        .collect()
                })
                .collect()
        });
        scaled[r - 1][k].iter().collect()
    };
    let encode_one = |k: usize, r: usize, q: f32, path: &Path| {
        encode_stream(path, &pics(k, r), opts.codec, q, opts.fps)
    };
    let seconds = frames.len() as f64 / opts.fps;
    let (q_min, q_max, _) = quality_range(opts.codec);
    let mut encodes = 0;
    let (rung, quality, feasible, budget) = match opts.rate {
        RateControl::Quality(q) => (
            vec![0; n_streams],
            vec![q.clamp(q_min, q_max); n_streams],
            true,
            None,
        ),
        RateControl::Budget(bps) => {
            let budget = bps * seconds - side_bytes.len() as f64 * 8.0;
            let fit = |which: &[usize]| {
                trial_models(
                    root,
                    &stream_rel,
                    &pictures,
                    &pics,
                    &rungs,
                    which,
                    frames,
                    &map,
                    opts,
                )
            };
            let mut models = fit(&[0])?;
            encodes += 2 * n_streams;
            let mut a = alloc::allocate(&models, &weights, budget, q_min, q_max);
            // The smaller rungs are fitted only when full size would need a quality worse
            // than the upper trial's: within the trials' range full size wins anyway.
            let upper = trial_qualities(opts.codec, 0)[1];
            if rungs.len() > 1 && !(a.feasible && a.quality.iter().all(|&q| q <= upper)) {
                let lower: Vec<usize> = (1..rungs.len()).collect();
                pics(0, 1);
                for (m, l) in models.iter_mut().zip(fit(&lower)?) {
                    m.extend(l);
                }
                encodes += 3 * n_streams * lower.len();
                a = alloc::allocate(&models, &weights, budget, q_min, q_max);
            }
            (a.rung, a.quality, a.feasible, Some((bps * seconds, models)))
        }
    };
    let budget_bits = budget.as_ref().map(|b| b.0);
    let encode_jobs = |jobs: &[(usize, usize, f32)]| -> Result<Vec<f64>, CodecError> {
        jobs.par_iter()
            .map(|&(k, r, q)| {
                encode_one(k, r, q, &root.join(stream_rel(k))).map(|bytes| bytes as f64 * 8.0)
            })
            .collect()
    };
    let jobs: Vec<(usize, usize, f32)> = (0..n_streams).map(|k| (k, rung[k], quality[k])).collect();
    let mut coding = alloc::Coding {
        bits: encode_jobs(&jobs)?,
        rung,
        quality,
    };
    encodes += n_streams;
    let side_bits = side_bytes.len() as f64 * 8.0;
    let mut feasible = feasible;
    // Rates extrapolated beyond the trial qualities may miss, and a correction may move a
    // stream to a rung whose model is not yet anchored: up to four correction rounds.
    if let Some((total, mut models)) = budget {
        let (n, ok) = alloc::correct(
            &mut models,
            &weights,
            total - side_bits,
            (q_min, q_max),
            &mut coding,
            4,
            encode_jobs,
        )?;
        encodes += n;
        feasible &= ok && coding.bits.iter().sum::<f64>() + side_bits <= total * 1.1;
    }
    let at_floor = coding.at_floor(q_max, |_| rungs.len() - 1);
    let alloc::Coding {
        rung,
        quality,
        bits: sizes,
    } = coding;
    let scale: Vec<u32> = rung.iter().map(|&r| rungs[r]).collect();
    let mut streams = Vec::with_capacity(n_streams);
    for k in 0..n_streams {
        streams.push(StreamEntry {
            file: file_entry(root, &stream_rel(k))?,
            track: first.set.layers()[k].meta.track,
            bitrate: (sizes[k] / seconds).round() as u64,
            quality: quality[k],
            scale: scale[k],
            weight: weights[k],
        });
    }
    let bits = sizes.iter().sum::<f64>() + side_bits;
    Ok((
        Segment {
            start: first.index,
            frames: frames.len() as u32,
            streams,
            side: file_entry(root, &side_rel)?,
        },
        SegmentReport {
            start: first.index,
            budget_bits,
            bits,
            quality,
            scale,
            feasible,
            at_floor,
            encodes,
        },
    ))
}

/// The qualities of the trial encodes of rung `rung`: a quarter and three fifths of the
/// quality range, and for the smaller rungs also the range's end. The smaller rungs are tried
/// only when full size would need a quality beyond its upper trial's (see
/// [`encode_segment`]), so that is where they are used: measured there, they are
/// interpolated, not extrapolated (rates flatten at the worst qualities).
fn trial_qualities(codec: Codec, rung: usize) -> Vec<f32> {
    let (q_min, q_max, _) = quality_range(codec);
    let mut q = vec![
        (q_min + 0.25 * (q_max - q_min)).round(),
        (q_min + 0.6 * (q_max - q_min)).round(),
    ];
    if rung > 0 {
        q.push(q_max);
    }
    q
}

/// Trial encodes per stream and rung `which` of the ladder `rungs` (at the
/// [`trial_qualities`]), each decoded, brought back to the frame size and scored with the
/// proxy distortion on up to 8 evenly spaced frames. Returns the models per stream, then per
/// rung of `which`.
#[allow(clippy::too_many_arguments)]
fn trial_models<'a>(
    root: &Path,
    stream_rel: &(dyn Fn(usize) -> String + Sync),
    pictures: &[Vec<&'a PremulImage>],
    pics: &(dyn Fn(usize, usize) -> Vec<&'a PremulImage> + Sync),
    rungs: &[u32],
    which: &[usize],
    frames: &[LayeredFrame],
    map: &[Vec<u8>],
    opts: &CodingOptions,
) -> Result<Vec<Vec<alloc::RdModel>>, CodecError> {
    let step = frames.len().div_ceil(8).max(1);
    let sampled: Vec<usize> = (0..frames.len()).step_by(step).collect();
    let (w, h) = (frames[0].set.camera().width, frames[0].set.camera().height);
    // Visibility of each stream's layer in the sampled frames.
    let n_streams = pictures.len();
    let mut vis: Vec<Vec<Vec<u8>>> = vec![Vec::new(); n_streams];
    for &fi in &sampled {
        let layers = frames[fi].set.layers();
        let mut seen = vec![false; n_streams];
        for (k, &s) in map[fi].iter().enumerate() {
            let front: Vec<&PremulImage> = layers[..k].iter().map(|l| &l.image).collect();
            vis[s as usize].push(alloc::visibility(&front, w, h));
            seen[s as usize] = true;
        }
        for (s, v) in vis.iter_mut().enumerate() {
            if !seen[s] {
                v.push(vec![0; (w * h) as usize]);
            }
        }
    }
    let jobs: Vec<(usize, usize)> = (0..n_streams)
        .flat_map(|k| which.iter().map(move |&r| (k, r)))
        .collect();
    let fitted: Vec<alloc::RdModel> = jobs
        .into_par_iter()
        .map(|(k, r)| {
            let (sw, sh) = scale::scaled_size(w, h, rungs[r]);
            let mut points = Vec::new();
            for (t, q) in trial_qualities(opts.codec, r).into_iter().enumerate() {
                let path = root.join(stream_rel(k).replace(".mp4", &format!(".trial{r}{t}.mp4")));
                let bytes = encode_stream(&path, &pics(k, r), opts.codec, q, opts.fps);
                let decoded = bytes.and_then(|b| decode_pictures(&path, sw, sh).map(|d| (b, d)));
                let _ = std::fs::remove_file(&path);
                let (bytes, decoded) = decoded?;
                // Summed, not averaged per stream: a layer's share of the picture's error.
                // Only the sampled pictures are converted back.
                let mut e = 0.0;
                for (j, &fi) in sampled.iter().enumerate() {
                    let p = decoded.get(fi).ok_or_else(|| CodecError::Stream {
                        path: path.clone(),
                        reason: format!("{} pictures, {} expected", decoded.len(), frames.len()),
                    })?;
                    let dec = scale::upscale(yuv::unstack(p, sw, sh), w, h, rungs[r]);
                    e += alloc::distortion(pictures[k][fi], &dec, &vis[k][j]);
                }
                let norm = 4.0 * (w * h) as f64 * sampled.len() as f64;
                points.push((q, bytes as f64 * 8.0, e / norm));
            }
            Ok(alloc::RdModel::fit(&points))
        })
        .collect::<Result<_, CodecError>>()?;
    Ok(fitted.chunks(which.len()).map(<[_]>::to_vec).collect())
}

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
        let streams = seg
            .streams
            .par_iter()
            .map(|s| {
                pkg.read(&s.file)?;
                let size = scale::scaled_size(camera.width, camera.height, s.scale);
                let shown = pkg.display_path(&s.file);
                let reader = PictureReader::open(&pkg.path_of(&s.file), size.0, size.1)
                    .map_err(|e| shown_as(e, &shown))?;
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

/// The bits a segment of `n` frames gets from a total budget of `bps` bits per second after
/// `done` frames that took `spent` bits: its own share, corrected by what the earlier
/// segments spent above or below theirs (a bit reservoir), by at most half the share either
/// way. A short segment cut by a refresh costs more than its share (a whole key frame); the
/// following ones pay it back, so that the package keeps to the budget.
pub fn segment_budget(bps: f64, fps: f64, done: u32, spent: f64, n: usize) -> f64 {
    let share = bps * n as f64 / fps;
    let balance = bps * done as f64 / fps - spent;
    (share + balance).clamp(0.5 * share, 1.5 * share)
}

/// Writes a package: segments are coded into a hidden staging folder beside the output, and
/// the finished package is moved into place by [`PackageWriter::finish`]. Dropping an
/// unfinished writer removes the staging folder, so an interrupted run never leaves a
/// half-written package; an existing package at the output is replaced only when the new
/// one is complete, and anything else there is never replaced.
pub struct PackageWriter {
    stage: cpsl_io::Staged,
    camera: cpsl_core::Camera,
    layers: u32,
    opts: CodingOptions,
    segments: Vec<Segment>,
    frames: u32,
    /// Bits written so far (layer and side streams).
    spent: f64,
    /// Frames of the segment being gathered by [`PackageWriter::push`].
    pending: Vec<LayeredFrame>,
}

impl PackageWriter {
    /// Starts a package at `out` for frames of `camera` layered with target K `layers`.
    pub fn create(
        out: &Path,
        camera: cpsl_core::Camera,
        layers: u32,
        opts: CodingOptions,
    ) -> Result<Self, CodecError> {
        let stage = cpsl_io::Staged::folder(out, replaceable_package).map_err(|e| match e {
            cpsl_io::IoError::TargetExists { path } => CodecError::Io {
                path,
                source: std::io::Error::new(
                    std::io::ErrorKind::AlreadyExists,
                    "exists and is not a CPSL package folder; not replacing it",
                ),
            },
            e => CodecError::Write(e),
        })?;
        Ok(Self {
            stage,
            camera,
            layers,
            opts,
            segments: Vec::new(),
            frames: 0,
            spent: 0.0,
            pending: Vec::new(),
        })
    }

    /// Takes the next frame. An I-frame closes the segment gathered so far, which is coded
    /// then and its report returned; [`PackageWriter::flush`] or [`PackageWriter::finish`]
    /// codes the last one.
    pub fn push(&mut self, frame: LayeredFrame) -> Result<Option<SegmentReport>, CodecError> {
        let report = match frame.refresh {
            Some(_) => self.flush()?,
            None => None,
        };
        self.pending.push(frame);
        Ok(report)
    }

    /// Codes the frames pushed since the last segment, if any, as a segment.
    pub fn flush(&mut self) -> Result<Option<SegmentReport>, CodecError> {
        if self.pending.is_empty() {
            return Ok(None);
        }
        let frames = std::mem::take(&mut self.pending);
        self.push_segment(&frames).map(Some)
    }

    /// Codes the next segment (its first frame must follow the previous segment's last).
    pub fn push_segment(&mut self, frames: &[LayeredFrame]) -> Result<SegmentReport, CodecError> {
        if frames.first().map(|f| f.index) != Some(self.frames) {
            return Err(CodecError::Tracks {
                frame: frames.first().map_or(0, |f| f.index),
                reason: format!(
                    "segments must be contiguous; frame {} expected",
                    self.frames
                ),
            });
        }
        let opts = match self.opts.rate {
            RateControl::Budget(bps) => {
                let fps = self.opts.fps;
                let bits = segment_budget(bps, fps, self.frames, self.spent, frames.len());
                CodingOptions {
                    rate: RateControl::Budget(bits * fps / frames.len() as f64),
                    ..self.opts
                }
            }
            RateControl::Quality(_) => self.opts,
        };
        let (seg, report) = encode_segment(self.stage.path(), self.segments.len(), frames, &opts)?;
        self.frames += seg.frames;
        self.spent += report.bits;
        self.segments.push(seg);
        Ok(report)
    }

    /// Codes the pending frames ([`PackageWriter::flush`]; their report is dropped: flush
    /// first to see it), writes the manifest and moves the package into place.
    pub fn finish(mut self) -> Result<cpsl_package::PackageManifest, CodecError> {
        self.flush()?;
        if self.segments.is_empty() {
            return Err(CodecError::Empty);
        }
        let (cw, ch) = yuv::coded_size(self.camera.width, self.camera.height);
        let m = cpsl_package::PackageManifest {
            format: cpsl_package::PACKAGE_FORMAT.into(),
            version: cpsl_package::version_for(
                self.segments
                    .iter()
                    .flat_map(|s| s.streams.iter().map(|t| t.scale)),
            ),
            camera: self.camera,
            frame_rate: self.opts.fps,
            frames: self.frames,
            layers: self.layers,
            codec: self.opts.codec,
            layout: cpsl_package::Layout {
                kind: "colour-over-alpha".into(),
                coded_width: cw as u32,
                coded_height: ch as u32,
                pixel_format: "yuv420p".into(),
                matrix: "bt709".into(),
                range: "limited".into(),
            },
            budget: match self.opts.rate {
                RateControl::Budget(b) => Some(b.round() as u64),
                RateControl::Quality(_) => None,
            },
            segments: std::mem::take(&mut self.segments),
            checksum: String::new(),
        };
        let path = self.stage.path().join(cpsl_package::MANIFEST_FILE);
        std::fs::write(&path, m.to_json()).map_err(|source| CodecError::Io { path, source })?;
        self.stage.commit(replaceable_package)?;
        Ok(m)
    }
}

/// Whether a package writer may replace what is at `out`: only a package folder.
fn replaceable_package(out: &Path) -> bool {
    out.is_dir() && cpsl_package::is_package(out)
}

#[cfg(test)]
mod tests {
    use super::segment_budget;

    #[test]
    fn the_reservoir_repays_overspending_and_spends_savings_within_half_a_share() {
        // 1 Mbit/s, 30 fps, segments of 30 frames: a share of 1 Mbit.
        assert_eq!(segment_budget(1e6, 30.0, 0, 0.0, 30), 1e6);
        // 0.2 Mbit over after one segment: the next gets 0.8; far over: never below half.
        assert!((segment_budget(1e6, 30.0, 30, 1.2e6, 30) - 0.8e6).abs() < 1e-6);
        assert_eq!(segment_budget(1e6, 30.0, 30, 5e6, 30), 0.5e6);
        // Savings are spent, up to one and a half shares.
        assert!((segment_budget(1e6, 30.0, 60, 1.7e6, 30) - 1.3e6).abs() < 1e-6);
        assert_eq!(segment_budget(1e6, 30.0, 90, 0.0, 30), 1.5e6);
        // A one-frame segment's share is a thirtieth.
        assert!((segment_budget(1e6, 30.0, 0, 0.0, 1) - 1e6 / 30.0).abs() < 1e-6);
    }
}
