//! Coding one segment as its frames arrive: layers mapped to streams by track, the bit
//! allocation under the segment's budget, the layer streams, and the side stream.
//!
//! At constant quality the encoders open with the segment's first frame and take each
//! picture as it comes, so no frame waits (unless the encoders would not fit in memory
//! together: see [`concurrent_encoders`]). Under a budget each stream needs a rate-distortion
//! model: one carried from the previous segment (by track, re-anchored on what the stream
//! cost there; after a refresh for changed content and in a segment that may be the last,
//! also on one trial encode of the new content), or, for a new stream or one whose cost drifted from its model, trial encodes of
//! every other one of the segment's first frames (up to 10, as memory allows; at least
//! [`TRIAL_FRAMES`]), the only frames held in memory. The allocation is made for the
//! segment's expected length and the pictures go into the encoders as they arrive; what a
//! segment misses is repaid by the next ones (see [`crate::segment_budget`]), and the last,
//! whose pictures are also kept in raw files, is corrected from its files.

use crate::alloc::{self, RdModel, Trial};
use crate::stream::{quality_range, write_init, Container, PictureReader, StreamEncoder, Written};
use crate::{scale, yuv, CodecError, CodingOptions, RateControl};
use cpsl_core::{Geometry, LayeredFrame, PremulImage, RefreshReason};
use cpsl_package::{
    file_entry, segment_dir, Codec, FileEntry, Segment, SideFrame, SideLayer, SideStream,
    StreamEntry,
};
use rayon::prelude::*;
use std::collections::HashMap;
use std::path::{Path, PathBuf};

/// Fewest frames a segment holds for its trial encodes (its first ones).
pub const TRIAL_FRAMES: usize = 4;

/// Most frames a segment holds for its trial encodes, which code every other one: trials on
/// the first 4 frames underestimated what the later pictures of the fox's segments cost
/// (their layers drift from the key frame) by 1.6 to 2 times, and every segment overspent
/// its plan by 40 to 60 %.
const HELD_FRAMES: usize = 10;

/// Memory the held frames may take (at 4K, 5 frames of 6 layers).
const HELD_MEMORY: u64 = 1_000_000_000;

/// How many more retries the last segment's correction may make when one lands beyond the
/// budget's 5 % on the other side (see `SegmentEncoder::correct`).
const RETRIES: usize = 2;

/// How far (as a ratio either way) a stream's cost may stray from its model before the model
/// is fitted again.
const DRIFT: f64 = 2.0;

/// What coding one segment did.
#[derive(Debug, Clone, PartialEq)]
pub struct SegmentReport {
    /// The index of the segment's first frame.
    pub start: u32,
    /// The segment's frames.
    pub frames: u32,
    /// The budget of the segment in bits (`None` at constant quality).
    pub budget_bits: Option<f64>,
    /// Bits written (layer streams and side stream).
    pub bits: f64,
    /// Quality chosen per stream.
    pub quality: Vec<f32>,
    /// Downscale factor chosen per stream (see [`scale`]).
    pub scale: Vec<u32>,
    /// Whether the budget was met (within 10 %): the allocation found it within reach of its
    /// models and the streams kept to them.
    pub feasible: bool,
    /// Whether every stream is at the cheapest coding: the worst quality at the smallest
    /// size of the ladder (an unmet budget is then below what any coding needs).
    pub at_floor: bool,
    /// Encodes run (trials and final), over all streams.
    pub encodes: usize,
    /// Streams whose model was fitted by trial encodes in this segment (the others' came from
    /// the segment before).
    pub fitted: usize,
}

/// A key under which a stream's models are carried to the next segment: its layers' track
/// (`true`), and its index (`false`), which a stream of the next segment falls back on when
/// its track is new (a layer at the same place in the depth order tends to hold like
/// content; the drift check catches it when not).
pub(crate) type StreamKey = (bool, u32);

/// Whether a correction's retry that brings a segment of budget `bits` from `total` bits to
/// `tried` is kept: over the budget (by more than 5 %), if it spends less; otherwise, if it
/// spends more and stays within 5 % over.
fn retry_kept(bits: f64, total: f64, tried: f64) -> bool {
    match total > 1.05 * bits {
        true => tried < total,
        false => tried > total && tried <= 1.05 * bits,
    }
}

/// Qualities between the coding `now` and an `other` one measured (each with its streams'
/// bits), when their totals lie beyond a budget of `bits` by more than 5 % on either side:
/// each stream moved the same share of the way from its quality towards the other's
/// (rounded), its rate interpolated log-linearly between the two measurements, at the share
/// (in steps of 5 %) whose total comes closest to `bits` without exceeding it; `None` when
/// they do not straddle the budget or no share changes a quality.
fn between(bits: f64, now: (&[f32], &[f64]), other: (&[f32], &[f64])) -> Option<Vec<f32>> {
    let (a, b): (f64, f64) = (now.1.iter().sum(), other.1.iter().sum());
    let beyond = |x: f64, y: f64| x > 1.05 * bits && y < 0.95 * bits;
    if !(beyond(a, b) || beyond(b, a)) {
        return None;
    }
    let at = |t: f64| -> (Vec<f32>, f64) {
        let mut total = 0.0;
        let q = (0..now.0.len())
            .map(|k| {
                let (q0, q1, r0, r1) = (now.0[k], other.0[k], now.1[k], other.1[k]);
                let q = (q0 + t as f32 * (q1 - q0)).round();
                total += match q1 != q0 && r0 > 0.0 && r1 > 0.0 {
                    true => r0 * (r1 / r0).powf(f64::from((q - q0) / (q1 - q0))),
                    false => r0,
                };
                q
            })
            .collect();
        (q, total)
    };
    (1..20)
        .map(|i| at(i as f64 / 20.0))
        .filter(|(q, total)| q.as_slice() != now.0 && *total <= bits)
        .max_by(|x, y| x.1.total_cmp(&y.1))
        .map(|(q, _)| q)
}

/// What a segment hands the next under a budget.
#[derive(Debug, Clone)]
pub(crate) struct Carried {
    /// Models per stream key, one per rung of the ladder from full size down (a prefix).
    models: HashMap<StreamKey, Vec<RdModel>>,
    /// What the other pictures of whole segments cost against their trials' estimate: the
    /// first pictures after a key frame differ little from it, so trials on them misjudge the
    /// rest (0.85 of it on `testsrc2`, where the pictures stay alike; 1.8 times on the fox,
    /// whose layers drift from their key frame). Trials' other-picture bits are scaled by it;
    /// 1 until a segment measures it.
    inter_scale: f64,
}

impl Default for Carried {
    fn default() -> Self {
        Self {
            models: HashMap::new(),
            inter_scale: 1.0,
        }
    }
}

/// The stream of each layer of `f`, given the tracks of the segment's streams (from its first
/// frame): layers follow their track, or their index where layers have no tracks.
fn map_frame(tracks: &[Option<u32>], f: &LayeredFrame) -> Result<Vec<u8>, CodecError> {
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
}

/// One frame's side information: the layer-to-stream map, depths, surfaces, confidence,
/// refresh flag and the Edge-Depth Cache summary; `first` for the segment's first frame.
fn side_frame(f: &LayeredFrame, map: &[u8], first: bool) -> SideFrame {
    SideFrame {
        index: f.index,
        intra: first,
        refresh: first.then(|| f.refresh.unwrap_or(RefreshReason::Gop)),
        layers: f
            .set
            .layers()
            .iter()
            .zip(map)
            .enumerate()
            .map(|(k, (l, &s))| SideLayer {
                stream: s,
                depth: l.depth as f32,
                geometry: l.geometry.clone(),
                confidence: f.confidence.get(k).copied().unwrap_or(1.0).clamp(0.0, 1.0),
                track: l.meta.track,
            })
            .collect(),
        edc: cpsl_package::summarise_edc(&f.edc),
    }
}

/// Stream weights from the I-frame: its layers' saliency and share of depth-edge samples.
fn stream_weights(first: &LayeredFrame) -> Vec<f32> {
    let mut edges = vec![0usize; first.set.len()];
    for s in &first.edc.samples {
        for k in [s.front, s.back] {
            if let Some(e) = edges.get_mut(k as usize) {
                *e += 1;
            }
        }
    }
    let max_edges = edges.iter().copied().max().unwrap_or(0);
    first
        .set
        .layers()
        .iter()
        .zip(&edges)
        .map(|(l, &e)| alloc::weight(l.meta.saliency.unwrap_or(0.0), e, max_edges))
        .collect()
}

/// Under a budget, the share of a segment's bits its side stream may take before mesh layers
/// give up their grids.
const GEOMETRY_SHARE: f64 = 0.2;

/// Encodes `side`, first making mesh layers' geometry cheaper while the stream is above
/// `max_bits`: the stream whose grids cost the most steps down its ladder (`ladders`, per frame
/// and layer: [`cpsl_core::Layer::geometry_ladder`], coarser grids and then a plane), one rung
/// at a time. Geometry competes with colour for the budget; a grid that would starve the
/// layers' pictures gets coarser, and goes when even the coarsest would.
fn geometry_within(
    side: &mut SideStream,
    ladders: &[Vec<Vec<Geometry>>],
    max_bits: f64,
) -> Vec<u8> {
    let mut bytes = side.encode();
    let mut rung = std::collections::BTreeMap::<u8, usize>::new();
    while bytes.len() as f64 * 8.0 > max_bits {
        let mut cost = std::collections::BTreeMap::<u8, usize>::new();
        for l in side.frames.iter().flat_map(|f| &f.layers) {
            if matches!(l.geometry, Geometry::Mesh(_)) {
                *cost.entry(l.stream).or_default() += cpsl_package::geometry_bytes(&l.geometry);
            }
        }
        let Some((&worst, _)) = cost.iter().max_by_key(|(_, &c)| c) else {
            break;
        };
        let r = rung.entry(worst).or_default();
        for (sf, f) in side.frames.iter_mut().zip(ladders) {
            for (l, ladder) in sf.layers.iter_mut().zip(f) {
                if l.stream == worst && !ladder.is_empty() {
                    l.geometry = ladder[(*r).min(ladder.len() - 1)].clone();
                }
            }
        }
        *r += 1;
        bytes = side.encode();
    }
    bytes
}

/// The qualities of the trial encodes of rung `rung`: a quarter and three fifths of the
/// quality range, and for the smaller rungs also the range's end. The smaller rungs are tried
/// only when full size would need a quality beyond its upper trial's (see
/// `SegmentEncoder::choose`), so that is where they are used: measured there, they are
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

/// The stacked picture of `img` at rung factor `factor` (1: full size).
fn picture(img: &PremulImage, factor: u32) -> yuv::Yuv420 {
    if factor == 1 {
        yuv::stack(img)
    } else {
        yuv::stack(&scale::downscale(img, factor))
    }
}

/// Bytes an encoder holds per pixel of its pictures: x264 at the `veryfast` preset, one
/// thread, 3840x4320 pictures, holds 1.13 GB (its lookahead, B-frames and reference planes
/// with their half-pixel interpolations).
const ENCODER_BYTES_PER_PIXEL: u64 = 70;

/// Memory the encoders of a segment may take together.
const ENCODER_MEMORY: u64 = 2_000_000_000;

/// How many full-size layer-stream encoders may run at once for `width x height` frames
/// within [`ENCODER_MEMORY`] (at least one).
fn concurrent_encoders(width: u32, height: u32) -> usize {
    let (cw, ch) = yuv::coded_size(width, height);
    let per = (cw * 2 * ch) as u64 * ENCODER_BYTES_PER_PIXEL;
    (ENCODER_MEMORY / per).max(1) as usize
}

/// A thread pool of at most `n` threads (and no more than the global pool's), for work whose
/// memory grows with the number of jobs running at once.
fn pool(n: usize) -> Result<rayon::ThreadPool, CodecError> {
    rayon::ThreadPoolBuilder::new()
        .num_threads(n.clamp(1, rayon::current_num_threads()))
        .build()
        .map_err(|e| CodecError::Ffmpeg(format!("starting encoder threads: {e}")))
}

/// Where a stream's pictures go: straight into its encoder, or into a raw file beside the
/// stream: when the segment's encoders would not fit in memory together (large frames), that
/// file is coded when the segment ends, a few streams at a time; when the segment may be a
/// budget's last (whose correction codes streams again), the encoder takes the pictures as
/// they come too (`encoder`), and the file only serves a correction.
enum Sink {
    Encoder(StreamEncoder),
    Spill {
        /// The stream's encoder when it codes the pictures as they come.
        encoder: Option<StreamEncoder>,
        file: std::io::BufWriter<std::fs::File>,
        /// The raw file, and the stream it becomes.
        raw: PathBuf,
        out: PathBuf,
        size: (usize, usize),
        quality: f32,
        pictures: usize,
    },
}

impl Sink {
    /// A spill file for the stream at `out` of pictures of `size` at `quality`, beside the
    /// stream's `encoder` when it codes them as they come.
    fn spill(
        out: &Path,
        size: (usize, usize),
        quality: f32,
        encoder: Option<StreamEncoder>,
    ) -> Result<Self, CodecError> {
        let raw = out.with_extension("yuv.part");
        let file = std::fs::File::create(&raw).map_err(|source| CodecError::Io {
            path: raw.clone(),
            source,
        })?;
        Ok(Self::Spill {
            encoder,
            file: std::io::BufWriter::new(file),
            raw,
            out: out.to_path_buf(),
            size,
            quality,
            pictures: 0,
        })
    }

    fn push(&mut self, p: &yuv::Yuv420) -> Result<(), CodecError> {
        match self {
            Self::Encoder(e) => e.push(p),
            Self::Spill {
                encoder,
                file,
                raw,
                pictures,
                ..
            } => {
                use std::io::Write;
                if let Some(e) = encoder {
                    e.push(p)?;
                }
                let io = |source| CodecError::Io {
                    path: raw.clone(),
                    source,
                };
                for plane in [&p.y, &p.u, &p.v] {
                    file.write_all(plane).map_err(io)?;
                }
                *pictures += 1;
                Ok(())
            }
        }
    }

    /// Closes the stream, coding a spilled one from its file, which is returned to code
    /// again (the caller removes it).
    fn finish(
        self,
        container: Container,
        codec: Codec,
        fps: f64,
        gop: usize,
    ) -> Result<(Written, Option<Raw>), CodecError> {
        match self {
            Self::Encoder(e) => Ok((e.finish()?, None)),
            Self::Spill {
                encoder,
                file,
                raw,
                out,
                size,
                quality,
                pictures,
            } => {
                let flushed = file.into_inner().map_err(|e| CodecError::Io {
                    path: raw.clone(),
                    source: e.into_error(),
                });
                drop(flushed?);
                let raw = Raw {
                    raw,
                    out,
                    size,
                    pictures,
                };
                let written = match encoder {
                    Some(e) => e.finish()?,
                    None => raw.encode_to(&raw.out, container, codec, quality, fps, gop)?,
                };
                Ok((written, Some(raw)))
            }
        }
    }
}

/// A stream's pictures in a raw file, and the stream file they are coded into.
struct Raw {
    raw: PathBuf,
    out: PathBuf,
    size: (usize, usize),
    pictures: usize,
}

impl Raw {
    /// Codes the pictures into the stream file `to` at `quality`.
    fn encode_to(
        &self,
        to: &Path,
        container: Container,
        codec: Codec,
        quality: f32,
        fps: f64,
        gop: usize,
    ) -> Result<Written, CodecError> {
        use std::io::Read;
        let io = |source| CodecError::Io {
            path: self.raw.clone(),
            source,
        };
        let (w, h) = self.size;
        let mut e = StreamEncoder::create_as(to, container, (w, h), codec, quality, fps, gop)?;
        let mut input = std::io::BufReader::new(std::fs::File::open(&self.raw).map_err(io)?);
        for _ in 0..self.pictures {
            let mut plane = |n: usize| -> Result<Vec<u8>, CodecError> {
                let mut v = vec![0; n];
                input.read_exact(&mut v).map_err(io)?;
                Ok(v)
            };
            let (y, u, v) = (plane(w * h)?, plane(w * h / 4)?, plane(w * h / 4)?);
            e.push(&yuv::Yuv420 {
                width: w,
                height: h,
                y,
                u,
                v,
            })?;
        }
        e.finish()
    }
}

/// A segment's share of a budget, from the writer: see [`crate::segment_budget`].
#[derive(Debug, Clone, Copy)]
pub(crate) struct BudgetPlan {
    /// Bits per second of the package.
    pub bps: f64,
    /// Frames coded before the segment.
    pub done: u32,
    /// Bits they took.
    pub spent: f64,
    /// The segment's expected length in frames (the GOP).
    pub expected: usize,
    /// Whether the expected frames are all the video has left.
    pub last: bool,
    /// Whether the segment may be the video's last (it is, or the frames left are unknown):
    /// only the last segment may be coded again (see `SegmentEncoder::correct`).
    pub may_be_last: bool,
}

impl BudgetPlan {
    /// The segment's bits if it has `frames` frames (the video's last segment when they are
    /// the expected ones and those are the last).
    fn bits(&self, fps: f64, frames: usize) -> f64 {
        let last = self.last && frames >= self.expected;
        crate::segment_budget(self.bps, fps, self.done, self.spent, frames, last)
    }
}

/// Trial encodes of one stream: its index, the rung, the qualities.
type Job = (usize, usize, Vec<f32>);

/// The rung and quality chosen per stream.
struct Coding {
    rung: Vec<usize>,
    quality: Vec<f32>,
    feasible: bool,
}

/// A finished segment: its manifest entry, its report, and the models to carry on.
pub(crate) struct Finished {
    pub segment: Segment,
    pub report: SegmentReport,
    pub carried: Carried,
}

/// A segment being coded: started at a frame the writer chose (see [`crate::Segments`]), fed
/// frame by frame, finished where the next starts or at the end of the video.
pub(crate) struct SegmentEncoder {
    root: PathBuf,
    dir_name: String,
    number: usize,
    opts: CodingOptions,
    size: (u32, u32),
    start: u32,
    /// Each stream's track (from the first frame).
    tracks: Vec<Option<u32>>,
    weights: Vec<f32>,
    /// The ladder's downscale factors (only `[1]` at constant quality).
    rungs: Vec<u32>,
    budget: Option<BudgetPlan>,
    /// Per stream, models for the first rungs of the ladder (none until fitted or carried).
    models: Vec<Vec<RdModel>>,
    /// Per stream, the models of the segment before when a refresh for changed content keeps
    /// them from carrying over: their other-picture rates, measured over a whole segment,
    /// replace the trials'.
    history: Vec<Vec<RdModel>>,
    /// Per stream, whether its other-picture rates come from this segment's trials.
    fresh: Vec<bool>,
    /// Per stream, whether its models came over a refresh for changed content (or into a
    /// segment that may be the budget's last) and wait to be moved onto the new content by one
    /// trial encode (see [`SegmentEncoder::reanchor`]).
    stale: Vec<bool>,
    /// See [`Carried::inter_scale`].
    inter_scale: f64,
    /// Streams fitted by trial encodes here.
    fitted: usize,
    /// Frames waiting for the coding to be chosen, with their layer-to-stream maps.
    pending: Vec<(LayeredFrame, Vec<u8>)>,
    /// Frames to hold for trial encodes ([`TRIAL_FRAMES`] to [`HELD_FRAMES`], as memory
    /// allows).
    hold: usize,
    coding: Option<Coding>,
    /// Where each stream's pictures go once the coding is chosen.
    sinks: Vec<Sink>,
    /// How many encoders may run at once (see [`concurrent_encoders`]).
    parallel: usize,
    /// The threads trial and spilled encodes run on: at most `parallel`.
    pool: rayon::ThreadPool,
    side: Vec<SideFrame>,
    /// Per frame and layer, under a budget: the cheaper surfaces of a mesh layer.
    ladders: Vec<Vec<Vec<Geometry>>>,
    frames: usize,
    encodes: usize,
    blank: PremulImage,
}

impl SegmentEncoder {
    /// Starts segment `number` in `root` with its first frame; under a budget, the streams
    /// whose track had a model in the segment before (`carried`) start from it.
    pub fn start(
        root: &Path,
        number: usize,
        first: LayeredFrame,
        opts: CodingOptions,
        budget: Option<BudgetPlan>,
        carried: &Carried,
    ) -> Result<Self, CodecError> {
        let cam = *first.set.camera();
        let dir_name = segment_dir(number);
        let dir = root.join(&dir_name);
        std::fs::create_dir_all(&dir).map_err(|source| CodecError::Io { path: dir, source })?;
        let tracks: Vec<Option<u32>> = first.set.layers().iter().map(|l| l.meta.track).collect();
        // A refresh for lost confidence or cracks says the content changed: models carry over
        // it only once one trial encode has moved them onto the new content (`stale`), and
        // where that trial finds them too far off, their other pictures' rates still serve
        // the models fitted again (see `history`). So do they into a segment that may be the
        // budget's last, whose miss no later segment repays: there a correction codes the
        // streams again (720p testsrc2 at 3 Mbit/s: the last segment, a quarter cheaper than
        // the first at equal quality, landed 24 % under its budget and took two retries of
        // every stream, 3.4-4.3 s; with the trial it landed 3 % under and took none; with the
        // segment before's other-picture rates kept for a stream fitted again, as after a
        // refresh, one retry).
        let carries = matches!(first.refresh, None | Some(RefreshReason::Gop));
        let probe = !carries || budget.is_some_and(|p| p.may_be_last);
        let found: Vec<Vec<RdModel>> = tracks
            .iter()
            .enumerate()
            .map(|(k, t)| {
                let by_track = t.and_then(|t| carried.models.get(&(true, t)));
                let found = by_track.or_else(|| carried.models.get(&(false, k as u32)));
                found
                    .filter(|_| budget.is_some())
                    .cloned()
                    .unwrap_or_default()
            })
            .collect();
        let stale = found.iter().map(|m| probe && !m.is_empty()).collect();
        let history = match carries {
            true => vec![Vec::new(); tracks.len()],
            false => found.clone(),
        };
        let models = found;
        let fresh = (0..tracks.len())
            .map(|k| models[k].is_empty() && history[k].is_empty())
            .collect();
        let rungs = match budget {
            Some(_) => scale::rungs(cam.width, cam.height),
            None => vec![1],
        };
        let parallel = concurrent_encoders(cam.width, cam.height);
        let mut s = Self {
            root: root.to_path_buf(),
            dir_name,
            number,
            opts,
            size: (cam.width, cam.height),
            start: first.index,
            weights: stream_weights(&first),
            tracks,
            rungs,
            budget,
            models,
            history,
            fresh,
            stale,
            inter_scale: carried.inter_scale,
            fitted: 0,
            pending: Vec::new(),
            hold: {
                let bytes = (first.set.layers().len().max(1) as u64)
                    * u64::from(cam.width)
                    * u64::from(cam.height)
                    * 4;
                ((HELD_MEMORY / bytes) as usize).clamp(TRIAL_FRAMES, HELD_FRAMES)
            },
            coding: None,
            sinks: Vec::new(),
            parallel,
            pool: pool(parallel)?,
            side: Vec::new(),
            ladders: Vec::new(),
            frames: 0,
            encodes: 0,
            blank: PremulImage::new(cam.width, cam.height),
        };
        s.push(first)?;
        Ok(s)
    }

    /// The frames taken so far.
    pub fn frames(&self) -> usize {
        self.frames
    }

    /// Whether [`SegmentEncoder::push`] takes `frame`: each of its layers has a stream (its
    /// track's, or its index's where layers have no tracks). A refreshed frame whose layers
    /// all kept their tracks (the layering found each in the frame before) continues the
    /// streams, which code the new decomposition as the rest of their group.
    pub fn takes(&self, frame: &LayeredFrame) -> bool {
        map_frame(&self.tracks, frame).is_ok()
    }

    /// Takes the segment's next frame (see [`SegmentEncoder::takes`]): coded at once, or held
    /// until the coding is chosen.
    pub fn push(&mut self, frame: LayeredFrame) -> Result<(), CodecError> {
        let map = map_frame(&self.tracks, &frame)?;
        self.side.push(side_frame(&frame, &map, self.frames == 0));
        if self.budget.is_some() {
            let cam = frame.set.camera();
            let ladders = frame.set.layers().iter().map(|l| l.geometry_ladder(cam));
            self.ladders.push(ladders.collect());
        }
        self.frames += 1;
        if self.coding.is_some() {
            return self.feed(&frame, &map);
        }
        self.pending.push((frame, map));
        self.choose(false).map(|_| ())
    }

    /// Sends one frame's pictures to the streams' sinks, in parallel.
    fn feed(&mut self, frame: &LayeredFrame, map: &[u8]) -> Result<(), CodecError> {
        let coding = self.coding.as_ref().expect("the coding is chosen");
        let layers = frame.set.layers();
        let (blank, rungs) = (&self.blank, &self.rungs);
        self.sinks
            .par_iter_mut()
            .enumerate()
            .try_for_each(|(k, s)| {
                let img = map
                    .iter()
                    .position(|&s| s as usize == k)
                    .map_or(blank, |li| &layers[li].image);
                s.push(&picture(img, rungs[coding.rung[k]]))
            })
    }

    /// The segment's side stream with `frames`.
    fn side_stream(&self, frames: Vec<SideFrame>) -> SideStream {
        SideStream {
            segment: self.number as u32,
            start: self.start,
            streams: self.tracks.len() as u16,
            width: self.size.0,
            height: self.size.1,
            frames,
        }
    }

    /// The bits of the plan for a segment of `frames` frames left to the layer streams: the
    /// side stream's bits are estimated from the frames so far, and mesh grids give way to
    /// planes beyond their share (see `geometry_within`).
    fn layer_bits(&self, plan: &BudgetPlan, frames: usize) -> f64 {
        let bits = plan.bits(self.opts.fps, frames);
        let side = self.side_stream(self.side.clone()).encode().len() as f64 * 8.0;
        let side = side * frames as f64 / self.side.len().max(1) as f64;
        bits - side.min(GEOMETRY_SHARE * bits)
    }

    /// Chooses every stream's rung and quality and opens the encoders, unless trial encodes
    /// are needed and fewer frames than it holds for them are here (`finishing`: no more will
    /// come). Returns whether the coding is chosen.
    fn choose(&mut self, finishing: bool) -> Result<bool, CodecError> {
        let n_streams = self.tracks.len();
        let codec = self.opts.codec;
        let (q_min, q_max, _) = quality_range(codec);
        let coding = match (self.opts.rate, self.budget) {
            (RateControl::Budget(_), Some(plan)) => {
                let can_trial = finishing || self.pending.len() >= self.hold;
                let frames = match finishing {
                    true => self.frames,
                    false => plan.expected.max(self.frames),
                };
                let bits = self.layer_bits(&plan, frames);
                let lacking = |models: &[Vec<RdModel>], rungs: usize| -> Vec<Job> {
                    (0..n_streams)
                        .flat_map(|k| {
                            (models[k].len()..rungs).map(move |r| (k, r, trial_qualities(codec, r)))
                        })
                        .collect()
                };
                let sized = |models: &[Vec<RdModel>]| -> Vec<Vec<RdModel>> {
                    models
                        .iter()
                        .map(|m| m.iter().map(|r| r.clone().for_frames(frames)).collect())
                        .collect()
                };
                let jobs = lacking(&self.models, 1);
                if !jobs.is_empty() {
                    if !can_trial {
                        return Ok(false);
                    }
                    self.fit(&jobs)?;
                }
                if self.stale.contains(&true) {
                    if !can_trial {
                        return Ok(false);
                    }
                    let a =
                        alloc::allocate(&sized(&self.models), &self.weights, bits, q_min, q_max);
                    self.reanchor(&a, frames)?;
                    // Streams whose trial found their models too far off.
                    let jobs = lacking(&self.models, 1);
                    if !jobs.is_empty() {
                        self.fit(&jobs)?;
                    }
                }
                // Down the ladder one rung at a time, for the streams that would take their
                // smallest fitted rung at a quality worse than its upper trial's (all of them
                // while the budget is out of reach); full size is then also tried at the worst
                // quality, and a stream that would take the best quality its model is trusted
                // at also at the range's best, so that rates there are interpolated, not
                // extrapolated.
                let upper = |r: usize| trial_qualities(codec, r)[1];
                let a = loop {
                    let a =
                        alloc::allocate(&sized(&self.models), &self.weights, bits, q_min, q_max);
                    let mut jobs: Vec<Job> = Vec::new();
                    for k in 0..n_streams {
                        let (r, q) = (a.rung[k], a.quality[k]);
                        let smallest = self.models[k].len() - 1;
                        if smallest + 1 < self.rungs.len()
                            && (!a.feasible || (r == smallest && q > upper(r)))
                        {
                            jobs.push((k, smallest + 1, trial_qualities(codec, smallest + 1)));
                        }
                        if r == 0 && q > upper(0) && self.models[k][0].max_q() < q_max {
                            jobs.push((k, 0, vec![q_max]));
                        }
                        // A generous budget: the best quality the model is trusted at is
                        // taken, so the range's best end is tried too.
                        let m = &self.models[k][r];
                        if q <= m.best_q() && m.min_q() > q_min {
                            jobs.push((k, r, vec![q_min]));
                        }
                    }
                    if jobs.is_empty() {
                        break a;
                    }
                    if !can_trial {
                        return Ok(false);
                    }
                    self.fit(&jobs)?;
                };
                Coding {
                    rung: a.rung,
                    quality: a.quality,
                    feasible: a.feasible,
                }
            }
            _ => {
                let q = match self.opts.rate {
                    RateControl::Quality(q) => q.clamp(q_min, q_max),
                    RateControl::Budget(_) => unreachable!("a budget has a plan"),
                };
                Coding {
                    rung: vec![0; n_streams],
                    quality: vec![q; n_streams],
                    feasible: true,
                }
            }
        };
        let (w, h) = self.size;
        // The streams are coded as the frames arrive, as at constant quality, unless the
        // encoders would not fit in memory together: the pictures then wait on disk. Under a
        // budget where the segment may be the last, they are also kept (on disk) for its
        // correction round (coding them only there made `--bitrate 3M` of the 720p testsrc2
        // wait 1.9 s for the last segment's streams, against 0.3 s).
        let spill = self.parallel < n_streams;
        let keep = self.budget.is_some_and(|p| p.may_be_last);
        self.sinks = (0..n_streams)
            .map(|k| {
                let (sw, sh) = scale::scaled_size(w, h, self.rungs[coding.rung[k]]);
                let (cw, ch) = yuv::coded_size(sw, sh);
                let path = self.root.join(self.stream_rel(k));
                let q = coding.quality[k];
                let encoder = || {
                    let (fps, gop) = (self.opts.fps, self.gop());
                    let container = self.opts.container;
                    StreamEncoder::create_as(&path, container, (cw, 2 * ch), codec, q, fps, gop)
                };
                match (spill, keep) {
                    (true, _) => Sink::spill(&path, (cw, 2 * ch), q, None),
                    (false, true) => Sink::spill(&path, (cw, 2 * ch), q, Some(encoder()?)),
                    (false, false) => encoder().map(Sink::Encoder),
                }
            })
            .collect::<Result<_, _>>()?;
        self.encodes += n_streams;
        self.coding = Some(coding);
        for (f, map) in std::mem::take(&mut self.pending) {
            self.feed(&f, &map)?;
        }
        Ok(true)
    }

    fn gop(&self) -> usize {
        (self.opts.gop as usize).max(self.frames).max(1)
    }

    /// The package path of the init segment for the fragments of streams at downscale
    /// `scale`, written from `written`'s configuration if the package has none yet.
    fn init_for(&self, scale: u32, written: &Written) -> Result<String, CodecError> {
        let (sw, sh) = scale::scaled_size(self.size.0, self.size.1, scale);
        let (cw, ch) = yuv::coded_size(sw, sh);
        let rel = format!("init_{cw}x{}.mp4", 2 * ch);
        let path = self.root.join(&rel);
        if !path.exists() {
            let (codec, fps) = (self.opts.codec, self.opts.fps);
            write_init::<u8>(&path, codec, (cw, 2 * ch), fps, &written.headers)?;
        }
        Ok(rel)
    }

    /// Joins the segment's `n` stream fragments into its one fragment (stream `k` in run
    /// `k`), removing theirs.
    fn join_streams(&self, n: usize) -> Result<FileEntry, CodecError> {
        let paths: Vec<PathBuf> = (0..n).map(|k| self.root.join(self.stream_rel(k))).collect();
        let parts = paths
            .iter()
            .map(|p| {
                std::fs::read(p).map_err(|source| CodecError::Io {
                    path: p.clone(),
                    source,
                })
            })
            .collect::<Result<Vec<_>, _>>()?;
        let joined = crate::fmp4::join(&parts).map_err(|reason| CodecError::Stream {
            path: paths[0].clone(),
            reason,
        })?;
        let rel = format!("{}/layers.m4s", self.dir_name);
        let path = self.root.join(&rel);
        std::fs::write(&path, joined).map_err(|source| CodecError::Io { path, source })?;
        for p in &paths {
            let _ = std::fs::remove_file(p);
        }
        Ok(file_entry(&self.root, &rel)?)
    }

    fn stream_rel(&self, k: usize) -> String {
        let ext = match self.opts.container {
            Container::Fragment | Container::StreamFragments => "m4s",
            Container::Mp4 => "mp4",
        };
        format!("{}/layer_{k:02}.{ext}", self.dir_name)
    }

    /// Trial encodes of the held frames, per job: stream, rung, qualities. Each is decoded,
    /// brought back to the frame size and scored with the proxy distortion. A job for a rung
    /// the stream has a model of adds its trials to it; the others (each stream's rungs in
    /// increasing order, following those it has) add models.
    fn fit(&mut self, jobs: &[Job]) -> Result<(), CodecError> {
        let (fitted, m) = self.trials(jobs)?;
        let mut streams: Vec<usize> = jobs.iter().map(|j| j.0).collect();
        streams.dedup();
        self.fitted += streams
            .iter()
            .filter(|&&k| self.models[k].is_empty())
            .count();
        for ((k, r, _), trials) in jobs.iter().zip(fitted) {
            self.encodes += trials.len();
            match self.models[*k].get_mut(*r) {
                Some(model) => trials.iter().for_each(|t| model.add(t)),
                None => {
                    let model = RdModel::fit(&trials, m);
                    let model = match self.history[*k].get(*r) {
                        Some(h) => model.with_inter_of(h),
                        None => model,
                    };
                    self.models[*k].push(model);
                }
            }
        }
        Ok(())
    }

    /// Moves the models that came over a refresh for changed content (or into a segment that
    /// may be the budget's last) onto the new content:
    /// one trial encode per stream at the rung and quality `a` (allocated from those models
    /// for segments of `frames` frames) gives it, and every rung's key-frame bits and
    /// distortion are scaled by what that trial measured against the model (as a segment's
    /// cost re-anchors the rates at its end). The other pictures' bits stay those measured
    /// over whole segments (a trial's, on every other frame, are biased; fitting again kept
    /// them too, see `history`). A stream whose trial lands more than [`DRIFT`] from its
    /// model is fitted again. Before, every stream was fitted again after such a refresh: on
    /// the fox, whose refreshes come every 4 to 10 frames, 42 to 63 encodes a segment.
    fn reanchor(&mut self, a: &alloc::Allocation, frames: usize) -> Result<(), CodecError> {
        let jobs: Vec<Job> = (0..self.tracks.len())
            .filter(|&k| self.stale[k])
            .map(|k| (k, a.rung[k], vec![a.quality[k]]))
            .collect();
        let (trials, _) = self.trials(&jobs)?;
        self.encodes += jobs.len();
        for ((k, r, _), t) in jobs.iter().zip(trials) {
            let (k, t) = (*k, &t[0]);
            self.stale[k] = false;
            let model = &self.models[k][*r];
            let (pi, pp) = model.intra_inter(t.q);
            let pd = model.distortion(t.q);
            let ri = t.intra / pi.max(1.0);
            let rd = t.distortion.max(1e-12) / pd.max(1e-12);
            let bits = |i: f64, p: f64| i + (frames.max(1) - 1) as f64 * p;
            let now = bits(t.intra, t.inter.unwrap_or(pp));
            if (now / bits(pi, pp).max(1.0)).ln().abs() > DRIFT.ln() {
                self.models[k].clear();
                continue;
            }
            for m in self.models[k].iter_mut() {
                let mi = m.intra_inter(t.q).0;
                let md = m.distortion(t.q);
                m.anchor(t.q, mi * ri, None);
                m.anchor_distortion(t.q, md * rd);
            }
        }
        Ok(())
    }

    /// Runs the trial encodes of `jobs` on the held frames (every other one where that still
    /// makes [`TRIAL_FRAMES`]); returns each job's trials and the frames they coded.
    fn trials(&self, jobs: &[Job]) -> Result<(Vec<Vec<Trial>>, usize), CodecError> {
        let (w, h) = self.size;
        // Every other held frame when that still makes the fewest: the trials span the frames
        // held at the cost of fewer.
        let step = if self.pending.len() >= 2 * TRIAL_FRAMES {
            2
        } else {
            1
        };
        let pending: Vec<&(LayeredFrame, Vec<u8>)> = self.pending.iter().step_by(step).collect();
        let m = pending.len();
        let (codec, fps, gop) = (self.opts.codec, self.opts.fps, self.gop());
        let container = self.opts.container;
        let dir = self.root.join(&self.dir_name);
        let (blank, rungs) = (&self.blank, &self.rungs);
        let pending = &pending;
        let (inter_scale, parallel) = (self.inter_scale, self.parallel);
        let fitted: Vec<Vec<Trial>> = self.pool.install(|| {
            jobs.par_iter()
                .map(|(k, r, qualities)| {
                    let (k, r) = (*k, *r);
                    let factor = rungs[r];
                    let (sw, sh) = scale::scaled_size(w, h, factor);
                    // The stream's layer in each held frame.
                    let srcs: Vec<&PremulImage> = pending
                        .iter()
                        .map(|(f, map)| {
                            let at = map.iter().position(|&s| s as usize == k);
                            at.map_or(blank, |li| &f.set.layers()[li].image)
                        })
                        .collect();
                    // How much of it shows there.
                    let vis = |(f, map): &(LayeredFrame, Vec<u8>)| -> Vec<u8> {
                        match map.iter().position(|&s| s as usize == k) {
                            Some(li) => {
                                let front: Vec<&PremulImage> =
                                    f.set.layers()[..li].iter().map(|l| &l.image).collect();
                                alloc::visibility(&front, w, h)
                            }
                            None => vec![0; (w * h) as usize],
                        }
                    };
                    // Held for the job's qualities, unless the encoders run one at a time
                    // (large frames): each trial then makes them as it goes (at 4K, five held
                    // frames' pictures are 124 MB and their visibilities 41 MB).
                    let lean = parallel == 1;
                    let held_vis: Option<Vec<Vec<u8>>> =
                        (!lean).then(|| pending.iter().map(|p| vis(p)).collect());
                    let held_pics: Option<Vec<yuv::Yuv420>> =
                        (!lean).then(|| srcs.iter().map(|i| picture(i, factor)).collect());
                    let (cw, ch) = yuv::coded_size(sw, sh);
                    let size = (cw, 2 * ch);
                    // A job's qualities are coded in parallel too, so that a round of
                    // fewer jobs than threads (one stream's new content, say) keeps them
                    // all busy.
                    qualities
                        .par_iter()
                        .enumerate()
                        .map(|(t, &q)| {
                            let path = dir.join(format!("layer_{k:02}.trial{r}{t}.mp4"));
                            let run = || -> Result<(Written, f64), CodecError> {
                                let mut e = StreamEncoder::create_as(
                                    &path, container, size, codec, q, fps, gop,
                                )?;
                                for (i, src) in srcs.iter().enumerate() {
                                    match &held_pics {
                                        Some(pics) => e.push(&pics[i])?,
                                        None => e.push(&picture(src, factor))?,
                                    }
                                }
                                let written = e.finish()?;
                                let mut reader =
                                    PictureReader::<u8>::open_as(&path, container, codec, sw, sh)?;
                                let mut err = 0.0;
                                for (i, src) in srcs.iter().enumerate() {
                                    let p = reader.next_picture()?.ok_or_else(|| {
                                        CodecError::Stream {
                                            path: path.clone(),
                                            reason: format!("fewer pictures than the {m} coded"),
                                        }
                                    })?;
                                    let dec =
                                        scale::upscale(yuv::unstack(&p, sw, sh), w, h, factor);
                                    err += match &held_vis {
                                        Some(v) => alloc::distortion(src, &dec, &v[i]),
                                        None => alloc::distortion(src, &dec, &vis(pending[i])),
                                    };
                                }
                                Ok((written, err))
                            };
                            let result = run();
                            let _ = std::fs::remove_file(&path);
                            let (written, err) = result?;
                            let (intra, inter) = written.intra_inter_bits();
                            Ok(Trial {
                                q,
                                intra,
                                inter: (m > 1).then_some(inter_scale * inter),
                                // Summed over the picture, not averaged per stream: a layer's
                                // share of the frame's error.
                                distortion: err / (4.0 * (w * h) as f64 * m as f64),
                            })
                        })
                        .collect::<Result<Vec<Trial>, CodecError>>()
                })
                .collect::<Result<_, CodecError>>()
        })?;
        Ok((fitted, m))
    }

    /// Under a budget, when the `last` segment's coded streams (with the side stream,
    /// estimated) miss its budget by more than 5 % either way: a correction. Every stream's
    /// model is anchored on what it cost, the qualities are allocated again on the same rungs
    /// (over the budget, no stream may cost more than it did), and the streams whose quality
    /// changed are coded again from their kept pictures (`raws`); a retry that lands beyond
    /// the budget's 5 % on the other side is followed by up to [`RETRIES`] more, between the
    /// codings on either side (see `between`).
    fn correct(
        &mut self,
        last: bool,
        coding: &mut Coding,
        written: &mut [Written],
        raws: &[Option<Raw>],
    ) -> Result<(), CodecError> {
        let (Some(plan), RateControl::Budget(_)) = (self.budget, self.opts.rate) else {
            return Ok(());
        };
        let (fps, frames, codec) = (self.opts.fps, self.frames, self.opts.codec);
        let bits = self.layer_bits(&plan, frames);
        let spent: Vec<f64> = written.iter().map(|w| w.bytes as f64 * 8.0).collect();
        let total: f64 = spent.iter().sum();
        // Only the last segment corrects: the bit reservoir evens out the others, and a
        // correction keeps each stream's rung, so that over the budget it can only coarsen
        // the streams (measured on the fox: 0.1 to 0.45 dB lower at equal rate when every
        // segment corrected). Over the budget, no stream may then cost more than it did.
        let under = total < 0.95 * bits;
        if !last || (total <= 1.05 * bits && !under) {
            return Ok(());
        }
        let mut models = Vec::with_capacity(written.len());
        for (k, wr) in written.iter().enumerate() {
            let Some(m) = self.models[k].get(coding.rung[k]) else {
                return Ok(());
            };
            let mut m = m.clone().for_frames(frames);
            let (intra, inter) = wr.intra_inter_bits();
            m.anchor(coding.quality[k], intra, (frames > 1).then_some(inter));
            models.push(vec![m]);
        }
        let (q_min, q_max, _) = quality_range(codec);
        let a = match under {
            true => alloc::allocate(&models, &self.weights, bits, q_min, q_max),
            false => alloc::allocate_capped(&models, &self.weights, bits, (q_min, q_max), &spent),
        };
        let (gop, container) = (self.gop(), self.opts.container);
        let retry = |raw: &Raw| raw.out.with_extension("retry.mp4");
        let mut target = a.quality;
        // A retry that lands beyond the budget's 5 % on the other side is followed by one
        // between the two codings measured, each stream's rate interpolated between them (the
        // anchored models extrapolate: 1080p testsrc2 at 6 Mbit/s, the last segment's retry
        // cost 1.5 times their estimate and was dropped, leaving the package 20 % under).
        for _ in 0..=RETRIES {
            let jobs: Vec<(usize, f32, &Raw)> = (0..written.len())
                .filter(|&k| target[k] != coding.quality[k])
                .filter_map(|k| Some((k, target[k], raws[k].as_ref()?)))
                .collect();
            if jobs.is_empty() {
                break;
            }
            let again: Vec<Written> = self.pool.install(|| {
                jobs.par_iter()
                    .map(|&(_, q, raw)| raw.encode_to(&retry(raw), container, codec, q, fps, gop))
                    .collect::<Result<_, _>>()
            })?;
            self.encodes += jobs.len();
            let now: Vec<f64> = written.iter().map(|w| w.bytes as f64 * 8.0).collect();
            let mut tried = now.clone();
            for (j, w) in jobs.iter().zip(&again) {
                tried[j.0] = w.bytes as f64 * 8.0;
            }
            let keep = retry_kept(bits, now.iter().sum(), tried.iter().sum());
            let (mut other, mut other_bits) = (coding.quality.clone(), now);
            for (&(k, q, raw), wr) in jobs.iter().zip(again) {
                let io = |source| CodecError::Io {
                    path: raw.out.clone(),
                    source,
                };
                if keep {
                    std::fs::rename(retry(raw), &raw.out).map_err(io)?;
                    coding.quality[k] = q;
                    written[k] = wr;
                } else {
                    std::fs::remove_file(retry(raw)).map_err(io)?;
                    (other[k], other_bits[k]) = (q, tried[k]);
                }
            }
            let now: Vec<f64> = written.iter().map(|w| w.bytes as f64 * 8.0).collect();
            match between(bits, (&coding.quality, &now), (&other, &other_bits)) {
                Some(q) => target = q,
                None => break,
            }
        }
        Ok(())
    }

    /// Codes what is held, closes the streams, writes the side stream and returns the
    /// segment's manifest entry, its report and, under a budget, the models for the next
    /// segment: each stream's model anchored on what the stream cost, unless the cost strayed
    /// from the model by more than [`DRIFT`] (the stream is then fitted again).
    pub fn finish(mut self, last: bool) -> Result<Finished, CodecError> {
        if self.coding.is_none() {
            self.choose(true)?;
        }
        let mut coding = self.coding.take().expect("chosen when finishing");
        let (codec, fps, gop) = (self.opts.codec, self.opts.fps, self.gop());
        let container = self.opts.container;
        let sinks = std::mem::take(&mut self.sinks);
        let (mut written, raws): (Vec<Written>, Vec<Option<Raw>>) = self
            .pool
            .install(|| {
                sinks
                    .into_par_iter()
                    .map(|s| s.finish(container, codec, fps, gop))
                    .collect::<Result<Vec<_>, _>>()
            })?
            .into_iter()
            .unzip();
        let frames = self.frames;
        // What the other pictures cost against the trials' estimate, bits-weighted in logs.
        let (mut log_ratio, mut weight) = (0.0, 0.0);
        for (k, wr) in written.iter().enumerate() {
            let (inter, model) = (wr.intra_inter_bits().1, self.models[k].get(coding.rung[k]));
            let Some(trial) = model.map(|m| m.intra_inter(coding.quality[k]).1) else {
                continue;
            };
            if self.fresh[k] && frames > 1 && inter > 0.0 && trial > 0.0 {
                let w = inter * (frames - 1) as f64;
                log_ratio += w * (inter / trial).ln();
                weight += w;
            }
        }
        let corrected = self.correct(last, &mut coding, &mut written, &raws);
        for r in raws.iter().flatten() {
            let _ = std::fs::remove_file(&r.raw);
        }
        corrected?;
        let side_frames = std::mem::take(&mut self.side);
        let mut side = self.side_stream(side_frames);
        let budget_bits = self.budget.map(|p| p.bits(fps, frames));
        let side_bytes = match budget_bits {
            Some(bits) => geometry_within(&mut side, &self.ladders, GEOMETRY_SHARE * bits),
            None => side.encode(),
        };
        let side_rel = format!("{}/side.bin", self.dir_name);
        let side_path = self.root.join(&side_rel);
        std::fs::write(&side_path, &side_bytes).map_err(|source| CodecError::Io {
            path: side_path,
            source,
        })?;
        let seconds = frames as f64 / fps;
        let root = &self.root;
        // A lone fragment's boxes, paid once in the segment's fragment.
        let shared = crate::fmp4::FRAGMENT_BYTES as u64;
        let n = written.len() as u64;
        let streams = written
            .iter()
            .enumerate()
            .map(|(k, wr)| {
                let scale = self.rungs[coding.rung[k]];
                let init = match container.is_fragment() {
                    true => Some(self.init_for(scale, wr)?),
                    false => None,
                };
                let (file, bytes) = match container {
                    Container::Fragment => (None, wr.bytes - shared + shared / n),
                    _ => (Some(file_entry(root, &self.stream_rel(k))?), wr.bytes),
                };
                Ok(StreamEntry {
                    file,
                    init,
                    track: self.tracks[k],
                    bitrate: (bytes as f64 * 8.0 / seconds).round() as u64,
                    quality: coding.quality[k],
                    scale,
                    weight: self.weights[k],
                })
            })
            .collect::<Result<Vec<_>, CodecError>>()?;
        let fragment = match container {
            Container::Fragment => Some(self.join_streams(written.len())?),
            Container::StreamFragments | Container::Mp4 => None,
        };
        let stream_bytes = match &fragment {
            Some(f) => f.bytes,
            None => written.iter().map(|wr| wr.bytes).sum(),
        };
        let bits = (stream_bytes + side_bytes.len() as u64) as f64 * 8.0;
        let mut carried = Carried {
            models: HashMap::new(),
            inter_scale: self.inter_scale,
        };
        for (k, wr) in written.iter().enumerate() {
            let (r, q) = (coding.rung[k], coding.quality[k]);
            let Some(model) = self.models[k].get_mut(r) else {
                continue;
            };
            let predicted = model.clone().for_frames(frames).rate(q);
            let cost = wr.bytes as f64 * 8.0;
            let (intra, inter) = wr.intra_inter_bits();
            if (cost / predicted).ln().abs() > DRIFT.ln() {
                continue;
            }
            let (pi, pp) = model.intra_inter(q);
            model.anchor(q, intra, (frames > 1).then_some(inter));
            // The stream's other rungs are off by what this one was: without that, rungs
            // known only from trials that overestimated (or underestimated) kept a stream on
            // its rung whatever its budget (720p testsrc2: half-size streams at the best
            // quality and 35 % of the budget unspent).
            let (ri, rp) = (intra / pi.max(1.0), inter / pp.max(1.0));
            for (o, m) in self.models[k].iter_mut().enumerate() {
                if o != r {
                    let (mi, mp) = m.intra_inter(q);
                    m.anchor(q, mi * ri, (frames > 1).then_some(mp * rp));
                }
            }
            if self.models[k].iter().all(RdModel::carries) {
                if let Some(t) = self.tracks[k] {
                    carried.models.insert((true, t), self.models[k].clone());
                }
                let models = std::mem::take(&mut self.models[k]);
                carried.models.insert((false, k as u32), models);
            }
        }
        if weight > 0.0 {
            carried.inter_scale = (self.inter_scale * (log_ratio / weight).exp()).clamp(0.25, 4.0);
        }
        let q_max = quality_range(self.opts.codec).1;
        let cheapest = self.rungs.len() - 1;
        let at_floor =
            (0..written.len()).all(|k| coding.quality[k] >= q_max && coding.rung[k] == cheapest);
        Ok(Finished {
            segment: Segment {
                start: self.start,
                frames: frames as u32,
                streams,
                fragment,
                side: file_entry(root, &side_rel)?,
            },
            report: SegmentReport {
                start: self.start,
                frames: frames as u32,
                budget_bits,
                bits,
                quality: coding.quality,
                scale: coding.rung.iter().map(|&r| self.rungs[r]).collect(),
                feasible: coding.feasible && budget_bits.is_none_or(|b| bits <= 1.1 * b),
                at_floor,
                encodes: self.encodes,
                fitted: self.fitted,
            },
            carried,
        })
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn over_its_share_a_grid_gets_coarser_before_it_goes() {
        use cpsl_core::{Camera, DepthGrid, Edc, Layer, PremulImage};
        use cpsl_package::{SideFrame, SideLayer};
        // One 64x48 mesh layer, fully covered, with a bumpy surface (costly to code).
        let cam = Camera::from_fov(64, 48, 60.0);
        let (cols, rows) = DepthGrid::dims(64, 48, 4);
        let grid = DepthGrid {
            step: 4,
            cols,
            rows,
            inverse_depth: (0..cols * rows)
                .map(|k| 0.5 + 0.01 * ((k * 7919) % 31) as f32)
                .collect(),
        };
        let mut image = PremulImage::new(64, 48);
        image.as_bytes_mut().fill(255);
        let mut layer = Layer::new(image, 2.0);
        layer.geometry = Geometry::Mesh(std::sync::Arc::new(grid));
        let ladder = layer.geometry_ladder(&cam);
        let steps: Vec<Option<u32>> = ladder
            .iter()
            .map(|g| match g {
                Geometry::Mesh(g) => Some(g.step),
                _ => None,
            })
            .collect();
        assert_eq!(
            steps,
            [Some(8), Some(16), None],
            "coarser grids, then a plane"
        );
        let side = |g: &Geometry| SideStream {
            segment: 0,
            start: 0,
            streams: 1,
            width: 64,
            height: 48,
            frames: vec![SideFrame {
                index: 0,
                intra: true,
                refresh: None,
                layers: vec![SideLayer {
                    stream: 0,
                    depth: 2.0,
                    geometry: g.clone(),
                    confidence: 1.0,
                    track: None,
                }],
                edc: Edc::empty(64, 48, 1, 1.0),
            }],
        };
        let ladders = vec![vec![ladder.clone()]];
        let bytes = |g: &Geometry| side(g).encode().len() as f64 * 8.0;
        // Room for the twice-coarser grid: that is what it keeps.
        let mut s = side(&layer.geometry);
        geometry_within(&mut s, &ladders, bytes(&ladder[0]) + 1.0);
        assert_eq!(s.frames[0].layers[0].geometry, ladder[0]);
        // No room for any grid: the plane.
        let mut s = side(&layer.geometry);
        geometry_within(&mut s, &ladders, bytes(&ladder[2]) + 1.0);
        assert_eq!(s.frames[0].layers[0].geometry, ladder[2]);
        // Room for all: unchanged.
        let mut s = side(&layer.geometry);
        geometry_within(&mut s, &ladders, f64::MAX);
        assert_eq!(s.frames[0].layers[0].geometry, layer.geometry);
    }

    #[test]
    fn a_correction_keeps_retries_towards_the_budget_and_interpolates_past_it() {
        // Short of 100 bits: more is taken up to 105, not beyond.
        assert!(super::retry_kept(100.0, 80.0, 104.0));
        assert!(!super::retry_kept(100.0, 80.0, 120.0));
        assert!(!super::retry_kept(100.0, 80.0, 70.0));
        // Over: anything cheaper is taken, even if still over.
        assert!(super::retry_kept(100.0, 130.0, 110.0));
        assert!(super::retry_kept(100.0, 130.0, 60.0));
        assert!(!super::retry_kept(100.0, 130.0, 140.0));
        // Beyond on both sides: in between, each stream's rate interpolated. Two streams at
        // 26 and 30 cost 40 + 40; at 16 and 20, 80 + 80: halving the way (21, 25) predicts
        // 2 x 40 sqrt(2) = 113, over 100; a third of the way (23, 27: 0.3) predicts 98.5.
        let (now, other) = ([26.0, 30.0], [16.0, 20.0]);
        let (rn, ro) = ([40.0, 40.0], [80.0, 80.0]);
        let q = super::between(100.0, (&now, &rn), (&other, &ro));
        assert_eq!(q, Some(vec![23.0, 27.0]));
        // Either way round; a stream alike on both sides stays.
        let q = super::between(100.0, (&other, &ro), (&now, &rn));
        assert_eq!(q, Some(vec![23.0, 27.0]));
        let q = super::between(100.0, (&[26.0, 33.0], &rn), (&[16.0, 33.0], &[120.0, 40.0]));
        assert_eq!(q.as_ref().map(|q| q[1]), Some(33.0), "{q:?}");
        // Within 5 % on one side, or both on one side: done.
        assert_eq!(
            super::between(100.0, (&now, &[48.0, 48.0]), (&other, &ro)),
            None
        );
        assert_eq!(
            super::between(100.0, (&now, &rn), (&other, &[45.0, 45.0])),
            None
        );
    }

    #[test]
    fn a_spilled_stream_codes_to_the_same_bytes() {
        let dir = tempfile::tempdir().unwrap();
        let pictures: Vec<yuv::Yuv420> = (0..5u32)
            .map(|t| {
                let rgb: Vec<u8> = (0..64 * 48)
                    .flat_map(|i| [(i % 64 * 4 + t) as u8, (i / 64 * 5) as u8, 90])
                    .collect();
                yuv::stack(&PremulImage::from_rgb(64, 48, &rgb).unwrap())
            })
            .collect();
        let size = (pictures[0].width, pictures[0].height);
        let mut written = Vec::new();
        for (name, spill) in [("direct.mp4", false), ("spilled.mp4", true)] {
            let out = dir.path().join(name);
            let mut sink = match spill {
                true => Sink::spill(&out, size, 30.0, None).unwrap(),
                false => Sink::Encoder(
                    StreamEncoder::create(&out, size, Codec::H264, 30.0, 30.0, 8).unwrap(),
                ),
            };
            for p in &pictures {
                sink.push(p).unwrap();
            }
            let (w, raw) = sink.finish(Container::Mp4, Codec::H264, 30.0, 8).unwrap();
            assert_eq!(raw.is_some(), spill);
            if let Some(raw) = raw {
                // Coded again from the kept pictures: the same stream.
                assert_eq!(
                    raw.encode_to(&raw.out, Container::Mp4, Codec::H264, 30.0, 30.0, 8)
                        .unwrap(),
                    w
                );
                std::fs::remove_file(&raw.raw).unwrap();
            }
            written.push(w);
            // Only the stream is left.
            let left: Vec<_> = std::fs::read_dir(dir.path()).unwrap().collect();
            assert_eq!(left.len(), written.len(), "{left:?}");
        }
        assert_eq!(written[0], written[1]);
        assert_eq!(written[0].packets.len(), 5);
        let bytes = |n: &str| std::fs::read(dir.path().join(n)).unwrap();
        assert_eq!(bytes("direct.mp4"), bytes("spilled.mp4"));
        // Far more encoders fit at 720p than at 4K, and at least one always does.
        assert!(concurrent_encoders(1280, 720) >= 6);
        assert_eq!(concurrent_encoders(3840, 2160), 1);
        assert_eq!(concurrent_encoders(16384, 16384), 1);
    }
}
