//! Coding one segment: streams mapped to tracks, pictures, the bit allocation under the
//! segment's budget, the layer streams and the side stream.

use crate::stream::{decode_pictures, encode_stream, quality_range};
use crate::{alloc, scale, yuv, CodecError, CodingOptions, RateControl};
use cpsl_core::{LayeredFrame, PremulImage, RefreshReason};
use cpsl_package::{
    file_entry, segment_dir, Codec, Segment, SideFrame, SideLayer, SideStream, StreamEntry,
};
use rayon::prelude::*;
use std::path::Path;
use std::sync::OnceLock;

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

/// Per stream, per frame: the layer's picture (`blank` where the frame lacks it).
fn stream_pictures<'a>(
    frames: &'a [LayeredFrame],
    map: &[Vec<u8>],
    n_streams: usize,
    blank: &'a PremulImage,
) -> Vec<Vec<&'a PremulImage>> {
    let mut pictures: Vec<Vec<&PremulImage>> = vec![vec![blank; frames.len()]; n_streams];
    for (fi, (f, m)) in frames.iter().zip(map).enumerate() {
        for (l, &s) in f.set.layers().iter().zip(m) {
            pictures[s as usize][fi] = &l.image;
        }
    }
    pictures
}

/// The segment's side stream: per frame the layer-to-stream map, depths, confidence, refresh
/// flags and the Edge-Depth Cache summary.
fn side_stream(
    number: usize,
    frames: &[LayeredFrame],
    map: &[Vec<u8>],
    (w, h): (u32, u32),
) -> SideStream {
    let first = &frames[0];
    SideStream {
        segment: number as u32,
        start: first.index,
        streams: first.set.len() as u16,
        width: w,
        height: h,
        frames: frames
            .iter()
            .zip(map)
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
                        geometry: l.geometry.clone(),
                        confidence: f.confidence.get(k).copied().unwrap_or(1.0).clamp(0.0, 1.0),
                        track: l.meta.track,
                    })
                    .collect(),
                edc: cpsl_package::summarise_edc(&f.edc),
            })
            .collect(),
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

/// The first choice of rung and quality per stream: the given quality, or under a budget
/// the allocation over rate-distortion models fitted from trial encodes (`fit`), first at
/// full size and, only where full size would need a quality worse than the upper trial's, on
/// the smaller rungs too (`prepare_smaller` makes their pictures first).
fn choose_coding(
    opts: &CodingOptions,
    seconds: f64,
    side_bits: f64,
    weights: &[f32],
    rungs: usize,
    fit: impl Fn(&[usize]) -> Result<Vec<Vec<alloc::RdModel>>, CodecError>,
    prepare_smaller: impl Fn(),
) -> Result<Choice, CodecError> {
    let n_streams = weights.len();
    let (q_min, q_max, _) = quality_range(opts.codec);
    Ok(match opts.rate {
        RateControl::Quality(q) => Choice {
            rung: vec![0; n_streams],
            quality: vec![q.clamp(q_min, q_max); n_streams],
            feasible: true,
            budget: None,
            encodes: 0,
        },
        RateControl::Budget(bps) => {
            let budget = bps * seconds - side_bits;
            let mut models = fit(&[0])?;
            let mut encodes = 2 * n_streams;
            let mut a = alloc::allocate(&models, weights, budget, q_min, q_max);
            let upper = trial_qualities(opts.codec, 0)[1];
            if rungs > 1 && !(a.feasible && a.quality.iter().all(|&q| q <= upper)) {
                let lower: Vec<usize> = (1..rungs).collect();
                prepare_smaller();
                for (m, l) in models.iter_mut().zip(fit(&lower)?) {
                    m.extend(l);
                }
                encodes += 3 * n_streams * lower.len();
                a = alloc::allocate(&models, weights, budget, q_min, q_max);
            }
            Choice {
                rung: a.rung,
                quality: a.quality,
                feasible: a.feasible,
                budget: Some((bps * seconds, models)),
                encodes,
            }
        }
    })
}

/// What [`choose_coding`] chose.
struct Choice {
    rung: Vec<usize>,
    quality: Vec<f32>,
    feasible: bool,
    /// The segment's total bits and the models, under a budget.
    budget: Option<(f64, Vec<Vec<alloc::RdModel>>)>,
    /// Trial encodes run.
    encodes: usize,
}

/// Under a budget, the share of a segment's bits its side stream may take before mesh layers
/// give up their grids.
const GEOMETRY_SHARE: f64 = 0.1;

/// Encodes `side`, first replacing mesh layers' grids by planes ([`cpsl_core::Layer::flattened`])
/// while the stream is above `max_bits`: the stream whose grids cost the most first. Geometry
/// competes with colour for the budget; a grid that would starve the layers' pictures goes.
fn geometry_within(side: &mut SideStream, frames: &[LayeredFrame], max_bits: f64) -> Vec<u8> {
    let mut bytes = side.encode();
    while bytes.len() as f64 * 8.0 > max_bits {
        let mut cost = std::collections::BTreeMap::<u8, usize>::new();
        for l in side.frames.iter().flat_map(|f| &f.layers) {
            if matches!(l.geometry, cpsl_core::Geometry::Mesh(_)) {
                *cost.entry(l.stream).or_default() += cpsl_package::geometry_bytes(&l.geometry);
            }
        }
        let Some((&worst, _)) = cost.iter().max_by_key(|(_, &c)| c) else {
            break;
        };
        for (sf, f) in side.frames.iter_mut().zip(frames) {
            for (l, layer) in sf.layers.iter_mut().zip(f.set.layers()) {
                if l.stream == worst {
                    l.geometry = layer.flattened(f.set.camera());
                }
            }
        }
        bytes = side.encode();
    }
    bytes
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
    let blank = PremulImage::new(w, h);
    let pictures = stream_pictures(frames, &map, n_streams, &blank);
    let dir_name = segment_dir(number);
    let dir = root.join(&dir_name);
    std::fs::create_dir_all(&dir).map_err(|source| CodecError::Io {
        path: dir.clone(),
        source,
    })?;
    let seconds = frames.len() as f64 / opts.fps;
    let mut side = side_stream(number, frames, &map, (w, h));
    let side_bytes = match opts.rate {
        RateControl::Budget(bps) => {
            geometry_within(&mut side, frames, GEOMETRY_SHARE * bps * seconds)
        }
        RateControl::Quality(_) => side.encode(),
    };
    let side_rel = format!("{dir_name}/side.bin");
    let side_path = root.join(&side_rel);
    std::fs::write(&side_path, &side_bytes).map_err(|source| CodecError::Io {
        path: side_path,
        source,
    })?;
    let weights = stream_weights(first);
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
    let (q_min, q_max, _) = quality_range(opts.codec);
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
    let side_bits = side_bytes.len() as f64 * 8.0;
    // The smaller pictures are made before the smaller rungs are fitted in parallel.
    let choice = choose_coding(opts, seconds, side_bits, &weights, rungs.len(), fit, || {
        pics(0, 1);
    })?;
    let (rung, quality, feasible, budget) =
        (choice.rung, choice.quality, choice.feasible, choice.budget);
    let mut encodes = choice.encodes;
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
