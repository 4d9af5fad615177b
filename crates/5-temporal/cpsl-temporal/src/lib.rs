//! Layering a video (paper §4.1 and the temporal parts of §3.2).
//!
//! Frames are organised in groups of pictures. An **I-frame** is layered from scratch
//! ([`cpsl_layering::layer_frame`]). A **P-frame** carries the I-frame's layers along the
//! motion: dense optical flow from the new frame to the previous one ([`cpsl_flow`], on a
//! `flow_side` grid; or the decoder's motion vectors) is split per layer, each layer keeping the
//! flow of its own interior (grid cells whose match lies inside the layer and whose depth
//! agrees with the match's and with the layer's; vectors count less near the boundary and not
//! at all where they disagree with their neighbourhood's median) and extending it elsewhere by
//! an affine model plus the push-pull filled residual, so motion never bleeds across a layer
//! boundary; each layer's map into the
//! I-frame is composed with its flow, and the layer's premultiplied colour and alpha are
//! sampled from the I-frame through that map (one resampling per frame, no accumulated blur).
//! Content the I-frame hid behind a nearer layer (extension and fill) that nothing covers any
//! more is dropped unless the new depth fits its layer, so the layers behind show. Layer depths follow the new depth map (the
//! median over each layer's pixels), or the previous depth carried along the motion when depth
//! estimation is skipped on P-frames.
//!
//! With **refinement** on, the pixels a layer shows fully opaque and unoccluded take the new
//! frame's colour (so that lighting and texture stay current), layer depths are an exponential
//! moving average (`depth_ema`), and I-frame refresh is adaptive with hysteresis (below).
//!
//! **Temporal confidence** `c_k` of layer `k` is an exponential moving average of the mean of
//! two agreements between the propagated mask and the new depth, each relative to its value at
//! the last I-frame: *mask overlap* (the share of the mask whose depth lies within `depth_tolerance`
//! of the layer's, in `ln z`) and *boundary similarity* (the share of the mask's boundary
//! pixels within one pixel of a boundary of that depth-consistent region). The **crack rate** is
//! the share of 4-neighbour pairs across layer boundaries whose depth order contradicts the
//! layer order by more than 2 % (the nearer layer's pixel lies behind the farther one's: such a
//! boundary opens a crack or an overlap when the viewer moves), above its I-frame value.
//! A refresh (new I-frame) happens when the GOP is full, or, with adaptive refresh, when the
//! mean confidence falls below `refresh_confidence` or the crack rate rises above
//! `refresh_crack` on `hysteresis` consecutive frames and at least `min_gap` frames after the
//! last I-frame. When the caller says how many frames are left
//! ([`VideoLayerer::set_frames_left`]), no refresh starts a group shorter than `min_gap` (or
//! half of `gop`, if smaller) at the end of the clip: those last frames stay in the running
//! group, which may then exceed `gop` by that much less one (a one-frame group costs nearly a
//! whole I-frame's bits for one frame's worth of video).
//!
//! **Association**: at a refresh the new layers inherit the track ids of the propagated
//! layers they overlap most (IoU at least `min_iou`), so a layer's identity
//! ([`cpsl_core::LayerMeta::track`]) survives refreshes even when depth order changes its index.

use cpsl_core::{Camera, LayerSet, LayeredFrame, Limits, NoProgress, PremulImage, RefreshReason};
use cpsl_flow::{Flow, FlowConfig, Grey};
use cpsl_layering::matte::edge_depth_cache_from;
use cpsl_layering::{layer_frame, LayeringConfig, LayeringError};
use rayon::prelude::*;
use serde::{Deserialize, Serialize};
use std::borrow::Cow;
use std::time::Instant;
use thiserror::Error;

mod kernels;
mod robust;
#[cfg(target_arch = "x86_64")]
mod simd;

/// Errors of video layering.
#[derive(Debug, Error)]
pub enum VideoError {
    /// Layering failed.
    #[error(transparent)]
    Layering(#[from] LayeringError),
    /// A frame's size differs from the first frame's.
    #[error("frame {frame} is {found:?} pixels, the video is {expected:?}")]
    FrameSize {
        /// Frame index.
        frame: usize,
        /// Its size.
        found: (u32, u32),
        /// The video's.
        expected: (u32, u32),
    },
    /// An I-frame needs depth.
    #[error("frame {frame} is an I-frame and needs a depth map")]
    NeedDepth {
        /// Frame index.
        frame: usize,
    },
    /// Bad configuration.
    #[error("GOP configuration: {0}")]
    Config(String),
    /// Rebuilding a layer set failed.
    #[error(transparent)]
    Core(#[from] cpsl_core::CoreError),
}

/// Temporal organisation. The defaults are the full pipeline; [`GopConfig::frame_wise`] and
/// [`GopConfig::propagation_only`] are the ablations.
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields, default)]
pub struct GopConfig {
    /// Most frames in a group of pictures (1: every frame is an I-frame).
    pub gop: usize,
    /// Long side of the grid the flow runs on.
    pub flow_side: usize,
    /// Refinement: colour refresh of unoccluded opaque pixels, moving average of layer depths.
    pub refine: bool,
    /// Adaptive I-frame refresh from temporal confidence and crack rate.
    pub adaptive_refresh: bool,
    /// Weight of the previous frame in the moving average of layer depths.
    pub depth_ema: f32,
    /// `|ln z - ln z_k|` within which a pixel agrees with layer `k`.
    pub depth_tolerance: f32,
    /// Tolerance in `ln z` of the occlusion tests: a pixel whose depth differs from its
    /// match's in the previous frame by more, or lies further outside the layer's I-frame
    /// depth span, no longer shows that layer's surface (a moving occluder uncovered it) and
    /// does not move the layer; uncovered hidden content stays only within its layer's span
    /// so widened.
    pub occlusion_tolerance: f32,
    /// Weight of the past in the temporal confidence.
    pub confidence_ema: f32,
    /// Refresh when the mean temporal confidence falls below this.
    pub refresh_confidence: f32,
    /// Refresh when the crack rate rises above this.
    pub refresh_crack: f32,
    /// Consecutive frames a refresh condition must hold.
    pub hysteresis: usize,
    /// Fewest frames between an I-frame and an adaptive refresh, and the shortest group a
    /// refresh may start at the end of a clip of known length (half of `gop` if that is less).
    pub min_gap: usize,
    /// Least IoU for a new layer to inherit a track.
    pub min_iou: f32,
}

impl Default for GopConfig {
    fn default() -> Self {
        Self {
            gop: 30,
            flow_side: 320,
            refine: true,
            adaptive_refresh: true,
            depth_ema: 0.7,
            depth_tolerance: 0.05,
            occlusion_tolerance: 0.5,
            confidence_ema: 0.7,
            refresh_confidence: 0.75,
            refresh_crack: 0.05,
            hysteresis: 2,
            min_gap: 4,
            min_iou: 0.3,
        }
    }
}

impl GopConfig {
    /// Ablation: every frame layered on its own.
    pub fn frame_wise() -> Self {
        Self {
            gop: 1,
            refine: false,
            adaptive_refresh: false,
            ..Self::default()
        }
    }

    /// Ablation: I/P propagation with a fixed GOP, no refinement, no adaptive refresh.
    pub fn propagation_only() -> Self {
        Self {
            refine: false,
            adaptive_refresh: false,
            ..Self::default()
        }
    }

    /// Checks ranges.
    pub fn validate(&self) -> Result<(), VideoError> {
        let bad = |what: &str| Err(VideoError::Config(what.to_string()));
        if self.gop == 0 {
            return bad("gop must be at least 1");
        }
        if !(16..=4096).contains(&self.flow_side) {
            return bad("flow_side must be in 16..=4096");
        }
        for (name, v) in [
            ("depth_ema", self.depth_ema),
            ("confidence_ema", self.confidence_ema),
            ("refresh_confidence", self.refresh_confidence),
            ("refresh_crack", self.refresh_crack),
            ("min_iou", self.min_iou),
        ] {
            if !(0.0..=1.0).contains(&v) {
                return bad(&format!("{name} must be in [0, 1], not {v}"));
            }
        }
        for (name, v) in [
            ("depth_tolerance", self.depth_tolerance),
            ("occlusion_tolerance", self.occlusion_tolerance),
        ] {
            if !(v.is_finite() && v >= 0.0) {
                return bad(&format!("{name} must be finite and >= 0, not {v}"));
            }
        }
        Ok(())
    }
}

/// What the next frame needs from the previous ones.
struct State {
    grey: Grey,
    /// The previous frame's depth and owner.
    depth: Vec<f32>,
    owner: Vec<u8>,
    /// The last I-frame's layers and owner.
    key: LayerSet,
    key_owner: Vec<u8>,
    /// The last I-frame's layers prepared for warping.
    key_layers: Vec<kernels::KeyLayer>,
    /// Per layer, on the flow grid: where each grid pixel's point of the previous frame lies
    /// in the I-frame (full-resolution pixels, x and y interleaved).
    maps: Vec<Vec<f32>>,
    /// The previous frame's layer depths.
    depths: Vec<f64>,
    /// Per layer, the 5 % and 95 % quantiles of `ln z` over its pixels at the I-frame.
    spans: Vec<(f32, f32)>,
    tracks: Vec<u32>,
    /// Per layer: (overlap, boundary similarity) at the last I-frame.
    base: Vec<(f32, f32)>,
    base_crack: f32,
    confidence: Vec<f32>,
    since_i: usize,
    run: usize,
    pending: Option<RefreshReason>,
}

/// Layers a video frame by frame (see the crate documentation).
pub struct VideoLayerer {
    camera: Camera,
    layering: LayeringConfig,
    gop: GopConfig,
    flow: FlowConfig,
    state: Option<State>,
    next_track: u32,
    frames: usize,
    /// Frames still to come, the next one included, when the caller knows.
    left: Option<usize>,
}

impl VideoLayerer {
    /// A layerer for frames seen by `camera`.
    pub fn new(
        camera: Camera,
        layering: LayeringConfig,
        gop: GopConfig,
    ) -> Result<Self, VideoError> {
        layering.validate()?;
        gop.validate()?;
        camera.validate().map_err(LayeringError::from)?;
        Ok(Self {
            camera,
            layering,
            gop,
            flow: FlowConfig::default(),
            state: None,
            next_track: 0,
            frames: 0,
            left: None,
        })
    }

    /// Tells the layerer how many frames are still to come, the next one included (`None`:
    /// unknown, the default). With it, a refresh that would start a short group at the end of
    /// the clip is not made (see the crate documentation). A wrong count only moves refreshes:
    /// `Some(0)` counts as unknown, so frames beyond the count go on as usual.
    pub fn set_frames_left(&mut self, left: Option<usize>) {
        self.left = left;
    }

    /// Why the next frame is an I-frame, or `None` for a P-frame.
    fn refresh_due(&self) -> Option<RefreshReason> {
        let Some(s) = &self.state else {
            return Some(RefreshReason::First);
        };
        let due = if s.since_i + 1 >= self.gop.gop {
            Some(RefreshReason::Gop)
        } else {
            s.pending
        };
        let shortest = self.gop.min_gap.min(self.gop.gop / 2);
        due.filter(|_| self.left.is_none_or(|n| n == 0 || n >= shortest))
    }

    /// Whether the next frame will be an I-frame (callers may skip depth estimation when it
    /// is not).
    pub fn next_is_intra(&self) -> bool {
        self.refresh_due().is_some()
    }

    /// Layers the next frame: `rgb` 3 bytes per pixel, `depth` its z-depth (required on
    /// I-frames, see [`VideoLayerer::next_is_intra`]; on P-frames `None` carries the previous
    /// depth along the flow).
    pub fn push(&mut self, rgb: &[u8], depth: Option<&[f32]>) -> Result<LayeredFrame, VideoError> {
        self.push_with_motion(rgb, depth, None)
    }

    /// [`VideoLayerer::push`] with the motion from this frame to the previous one already
    /// known (for example from the decoder's motion vectors; full resolution, the
    /// [`cpsl_flow`] convention); `None` estimates it with optical flow.
    pub fn push_with_motion(
        &mut self,
        rgb: &[u8],
        depth: Option<&[f32]>,
        motion: Option<Flow>,
    ) -> Result<LayeredFrame, VideoError> {
        let (w, h) = (self.camera.width as usize, self.camera.height as usize);
        let index = self.frames;
        if rgb.len() != w * h * 3 || depth.is_some_and(|d| d.len() != w * h) {
            return Err(VideoError::FrameSize {
                frame: index,
                found: ((rgb.len() / 3 / h.max(1)) as u32, h as u32),
                expected: (w as u32, h as u32),
            });
        }
        let mut timings = Vec::new();
        let t = Instant::now();
        let grey = Grey::from_rgb8_scaled(rgb, w, h, self.gop.flow_side);
        // Motion from this frame to the previous one, on the grid (and at full resolution when
        // the decoder gave it).
        let given = motion.filter(|m| (m.width, m.height) == (w, h) && self.state.is_some());
        let grid = match &given {
            Some(m) => self
                .state
                .as_ref()
                .map(|_| shrink_flow(m, grey.width, grey.height)),
            None => self
                .state
                .as_ref()
                .map(|s| cpsl_flow::flow(&grey, &s.grey, &self.flow).expect("same-size grids")),
        };
        let motion = grid.map(|grid| FrameMotion { grid, full: given });
        if motion.is_some() {
            timings.push(("motion", ms(t)));
        }
        let refresh = self.refresh_due();
        let frame = match refresh {
            Some(reason) => {
                let depth = depth.ok_or(VideoError::NeedDepth { frame: index })?;
                self.intra(rgb, depth, grey, motion, reason, timings)?
            }
            None => self.predicted(rgb, depth, grey, motion.expect("P-frame"), timings)?,
        };
        self.frames += 1;
        self.left = self.left.map(|n| n.saturating_sub(1));
        Ok(frame)
    }

    fn intra(
        &mut self,
        rgb: &[u8],
        depth: &[f32],
        grey: Grey,
        motion: Option<FrameMotion>,
        reason: RefreshReason,
        mut timings: Vec<(&'static str, f64)>,
    ) -> Result<LayeredFrame, VideoError> {
        let (w, h) = (self.camera.width as usize, self.camera.height as usize);
        let (cues, layered) = layer_frame(rgb, depth, self.camera, &self.layering, &NoProgress)?;
        timings.extend(layered.timings.iter().copied());
        let k = layered.set.len();
        // Association: inherit the tracks of the propagated previous layers.
        let t = Instant::now();
        let mut tracks = vec![u32::MAX; k];
        if let (Some(s), Some(m)) = (&self.state, motion) {
            let predicted = warp_labels(&s.owner, &m.at_full(w, h), w, h);
            let kp = s.tracks.len();
            let mut inter = vec![0u32; k * kp];
            let (mut area_new, mut area_old) = (vec![0u32; k], vec![0u32; kp]);
            for (&a, &b) in layered.owner.iter().zip(&predicted) {
                inter[a as usize * kp + b as usize] += 1;
                area_new[a as usize] += 1;
                area_old[b as usize] += 1;
            }
            let mut pairs: Vec<(f32, usize, usize)> = (0..k)
                .flat_map(|a| (0..kp).map(move |b| (a, b)))
                .filter_map(|(a, b)| {
                    let i = inter[a * kp + b] as f32;
                    let u = (area_new[a] + area_old[b]) as f32 - i;
                    (u > 0.0 && i / u >= self.gop.min_iou).then_some((i / u, a, b))
                })
                .collect();
            pairs.sort_by(|x, y| y.0.total_cmp(&x.0));
            let mut used = vec![false; kp];
            for (_, a, b) in pairs {
                if tracks[a] == u32::MAX && !used[b] {
                    tracks[a] = s.tracks[b];
                    used[b] = true;
                }
            }
        }
        for t in tracks.iter_mut().filter(|t| **t == u32::MAX) {
            *t = self.next_track;
            self.next_track += 1;
        }
        let set = with_tracks(layered.set, &tracks)?;
        let lz = layer_log_depths(&set);
        let ln_depth: Vec<f32> = cues.depth.par_iter().map(|z| z.ln()).collect();
        let base = kernels::agreements(
            &layered.owner,
            &ln_depth,
            &lz,
            self.gop.depth_tolerance,
            w,
            h,
        );
        let base_crack = kernels::crack_rate(&layered.owner, &cues.depth, w, h);
        let spans = kernels::ln_depth_quantiles(&layered.owner, &ln_depth, k, [0.05, 0.95])
            .into_iter()
            .zip(&lz)
            .map(|(q, &z)| q.map_or((z, z), |[lo, hi]| (lo, hi)))
            .collect();
        timings.push(("association", ms(t)));
        let maps = vec![identity_map(w, h, grey.width, grey.height); k];
        self.state = Some(State {
            grey,
            depth: cues.depth,
            owner: layered.owner.clone(),
            key: set.clone(),
            key_owner: layered.owner.clone(),
            key_layers: set
                .layers()
                .par_iter()
                .map(|l| kernels::KeyLayer::new(&l.image))
                .collect(),
            maps,
            depths: set.layers().iter().map(|l| l.depth).collect(),
            spans,
            tracks,
            base,
            base_crack,
            confidence: vec![1.0; k],
            since_i: 0,
            run: 0,
            pending: None,
        });
        Ok(LayeredFrame {
            index: self.frames as u32,
            refresh: Some(reason),
            set,
            edc: layered.edc,
            owner: layered.owner,
            confidence: vec![1.0; k],
            crack: 0.0,
            depth_propagated: false,
            timings,
        })
    }

    fn predicted(
        &mut self,
        rgb: &[u8],
        depth: Option<&[f32]>,
        grey: Grey,
        motion: FrameMotion,
        mut timings: Vec<(&'static str, f64)>,
    ) -> Result<LayeredFrame, VideoError> {
        let (w, h) = (self.camera.width as usize, self.camera.height as usize);
        let (gw, gh) = (grey.width, grey.height);
        let g = self.gop;
        let s = self.state.as_mut().expect("P-frames follow a frame");
        let t = Instant::now();
        let k = s.key.len();
        // Each layer moves with the flow of its own interior, filled in elsewhere, so that
        // motion never bleeds across a layer boundary; its map into the I-frame follows.
        let depth_propagated = depth.is_none();
        let carried = warp_values(&s.depth, &motion.at_full(w, h), w, h);
        // A model may leave pixels without depth: they keep the depth carried along.
        let depth: Vec<f32> = match depth {
            Some(d) => d
                .par_iter()
                .zip(&carried)
                .map(|(&z, &c)| if z.is_finite() && z > 0.0 { z } else { c })
                .collect(),
            None => carried,
        };
        // Each layer's I-frame depth span, moved with the layer's depth since.
        let spans =
            s.spans
                .iter()
                .zip(&s.depths)
                .zip(s.key.layers())
                .map(|((&(lo, hi), &z), key)| {
                    let shift = (z / key.depth).ln() as f32;
                    (lo + shift, hi + shift)
                });
        let depths = Depths::new(&depth, &s.depth, (w, h), spans, g.occlusion_tolerance);
        let maps = layer_maps(&s.owner, &motion.grid, &s.maps, &depths);
        timings.push(("propagation", ms(t)));
        // The I-frame's layers carried along their motions, each pixel marked where it
        // carries content the I-frame hid behind a nearer layer (extension and fill).
        let t = Instant::now();
        let (mut layers, hidden): (Vec<cpsl_core::Layer>, Vec<Vec<bool>>) = s
            .key
            .layers()
            .par_iter()
            .zip(&maps)
            .enumerate()
            .map(|(l, (key, m))| {
                let (image, hidden) =
                    kernels::warp_layer(&s.key_layers[l], m, gw, gh, &s.key_owner, l);
                let layer = cpsl_core::Layer {
                    image,
                    depth: key.depth,
                    meta: key.meta.clone(),
                };
                (layer, hidden)
            })
            .unzip();
        timings.push(("warp", ms(t)));
        // Hidden content that nothing covers any more was never seen: it is dropped so that
        // the layers behind show. Owner: the nearest layer with alpha >= 1/2. With
        // refinement, the pixels a layer shows fully opaque and unoccluded take the new
        // frame's colour.
        let t = Instant::now();
        let owner = {
            let mut images: Vec<&mut PremulImage> =
                layers.iter_mut().map(|l| &mut l.image).collect();
            kernels::settle(&mut images, &hidden, &depth, &depths.spans, rgb, g.refine)
        };
        drop(hidden);
        timings.push(("visibility", ms(t)));
        // Layer depths from the new depth: the median over each layer's pixels, smoothed
        // over time with refinement, kept in order.
        let t = Instant::now();
        let ln_depth: Vec<f32> = depth.par_iter().map(|z| z.ln()).collect();
        let medians = kernels::median_depths(&owner, &ln_depth, k);
        let mut prev = 0.0f64;
        for (l, layer) in layers.iter_mut().enumerate() {
            let fresh = medians[l].unwrap_or(s.depths[l]);
            let z = if g.refine {
                g.depth_ema as f64 * s.depths[l] + (1.0 - g.depth_ema as f64) * fresh
            } else {
                fresh
            };
            layer.depth = z.max(prev * (1.0 + 1e-6));
            prev = layer.depth;
        }
        // The warp blends premultiplied texels alike in every channel, and the refresh only
        // recolours opaque pixels: the layers are premultiplied by construction.
        let set = LayerSet::new_premultiplied(*s.key.camera(), layers, &Limits::default())?;
        let edc = edge_depth_cache_from(&depth, w, h, &owner, &set, &self.layering.matte);
        timings.push(("depths", ms(t)));
        // Temporal confidence and crack rate.
        let t = Instant::now();
        let lz = layer_log_depths(&set);
        let now = kernels::agreements(&owner, &ln_depth, &lz, g.depth_tolerance, w, h);
        for (l, &(o, b)) in now.iter().enumerate() {
            let (o0, b0) = s.base[l];
            let rel = |v: f32, v0: f32| if v0 > 0.0 { (v / v0).min(1.0) } else { 1.0 };
            let now = 0.5 * (rel(o, o0) + rel(b, b0));
            s.confidence[l] = g.confidence_ema * s.confidence[l] + (1.0 - g.confidence_ema) * now;
        }
        let present: Vec<f32> = (0..k)
            .filter(|&l| medians[l].is_some())
            .map(|l| s.confidence[l])
            .collect();
        let mean_conf = present.iter().sum::<f32>() / present.len().max(1) as f32;
        let crack = (kernels::crack_rate(&owner, &depth, w, h) - s.base_crack).max(0.0);
        timings.push(("confidence", ms(t)));
        // Hysteresis: a condition must hold on `hysteresis` consecutive frames.
        s.since_i += 1;
        let cause = if mean_conf < g.refresh_confidence {
            Some(RefreshReason::Confidence)
        } else if crack > g.refresh_crack {
            Some(RefreshReason::Crack)
        } else {
            None
        };
        s.run = if cause.is_some() { s.run + 1 } else { 0 };
        s.pending = cause.filter(|_| {
            g.adaptive_refresh && s.run >= g.hysteresis.max(1) && s.since_i + 1 >= g.min_gap
        });
        let confidence = s.confidence.clone();
        s.grey = grey;
        s.depth = depth;
        s.owner = owner.clone();
        s.maps = maps;
        s.depths = set.layers().iter().map(|l| l.depth).collect();
        Ok(LayeredFrame {
            index: self.frames as u32,
            refresh: None,
            set,
            edc,
            owner,
            confidence,
            crack,
            depth_propagated,
            timings,
        })
    }
}

fn ms(t: Instant) -> f64 {
    t.elapsed().as_secs_f64() * 1e3
}

/// Carries labels of the previous frame to this one (nearest). Panics unless `prev` and
/// `flow` are `w x h`.
pub fn warp_labels(prev: &[u8], flow: &Flow, w: usize, h: usize) -> Vec<u8> {
    warp_nearest(prev, flow, w, h)
}

/// Carries per-pixel values of the previous frame to this one (nearest, so depth is never
/// mixed across an edge). Panics unless `prev` and `flow` are `w x h`.
pub fn warp_values(prev: &[f32], flow: &Flow, w: usize, h: usize) -> Vec<f32> {
    warp_nearest(prev, flow, w, h)
}

/// Every pixel of this frame takes the value of the previous frame's pixel nearest to where
/// the flow says it was (clamped to the image).
fn warp_nearest<T: Copy + Default + Send + Sync>(
    prev: &[T],
    flow: &Flow,
    w: usize,
    h: usize,
) -> Vec<T> {
    assert_eq!(prev.len(), w * h, "values for every pixel");
    assert_eq!(
        (flow.width, flow.height, flow.data.len()),
        (w, h, w * h * 2),
        "a flow of the frame's size"
    );
    let mut out = vec![T::default(); w * h];
    let (xmax, ymax) = ((w - 1) as f32, (h - 1) as f32);
    out.par_chunks_mut(w)
        .zip(flow.data.par_chunks(w * 2))
        .enumerate()
        .for_each(|(y, (row, f))| {
            for (x, (o, uv)) in row.iter_mut().zip(f.chunks_exact(2)).enumerate() {
                // Rounded to nearest by truncating after the clamp (no libm call on the
                // baseline target).
                let sx = (x as f32 + uv[0] + 0.5).clamp(0.0, xmax) as i32 as usize;
                let sy = (y as f32 + uv[1] + 0.5).clamp(0.0, ymax) as i32 as usize;
                *o = prev[sy * w + sx];
            }
        });
    out
}

fn with_tracks(set: LayerSet, tracks: &[u32]) -> Result<LayerSet, VideoError> {
    let (camera, mut layers) = set.into_parts();
    for (l, &t) in layers.iter_mut().zip(tracks) {
        l.meta.track = Some(t);
    }
    Ok(LayerSet::new(camera, layers, &Limits::default())?)
}

fn layer_log_depths(set: &LayerSet) -> Vec<f32> {
    set.layers().iter().map(|l| l.depth.ln() as f32).collect()
}

/// Motion from a frame to the previous one: on the flow grid, and at full resolution when
/// given.
struct FrameMotion {
    grid: Flow,
    full: Option<Flow>,
}

impl FrameMotion {
    fn at_full(&self, w: usize, h: usize) -> Cow<'_, Flow> {
        match &self.full {
            Some(f) => Cow::Borrowed(f),
            None => Cow::Owned(self.grid.resize(w, h)),
        }
    }
}

/// A full-resolution flow on a `gw x gh` grid (nearest sample at each grid pixel's centre,
/// vectors in grid pixels).
fn shrink_flow(f: &Flow, gw: usize, gh: usize) -> Flow {
    let (sx, sy) = (f.width as f32 / gw as f32, f.height as f32 / gh as f32);
    let mut data = vec![0f32; gw * gh * 2];
    for gy in 0..gh {
        for gx in 0..gw {
            let x = (((gx as f32 + 0.5) * sx) as usize).min(f.width - 1);
            let y = (((gy as f32 + 0.5) * sy) as usize).min(f.height - 1);
            let (u, v) = f.at(x, y);
            data[(gy * gw + gx) * 2] = u / sx;
            data[(gy * gw + gx) * 2 + 1] = v / sy;
        }
    }
    Flow {
        width: gw,
        height: gh,
        data,
    }
}

/// Full-resolution position of the centre of grid pixel `(gx, gy)`.
#[inline]
fn grid_to_full(g: f32, scale: f32) -> f32 {
    (g + 0.5) * scale - 0.5
}

/// Index of the full-resolution pixel nearest to grid position `(gx, gy)` (clamped to the
/// image; the saturating cast takes negatives to 0).
#[inline]
fn nearest_pixel(gx: f32, gy: f32, (sx, sy): (f32, f32), (w, h): (usize, usize)) -> usize {
    let x = ((grid_to_full(gx, sx) + 0.5) as usize).min(w - 1);
    let y = ((grid_to_full(gy, sy) + 0.5) as usize).min(h - 1);
    y * w + x
}

/// The map of a frame onto itself, on the grid.
fn identity_map(w: usize, h: usize, gw: usize, gh: usize) -> Vec<f32> {
    let (sx, sy) = (w as f32 / gw as f32, h as f32 / gh as f32);
    (0..gw * gh)
        .flat_map(|g| {
            [
                grid_to_full((g % gw) as f32, sx),
                grid_to_full((g / gw) as f32, sy),
            ]
        })
        .collect()
}

/// Bilinear sample of both channels of a 2-channel grid at `(x, y)` (clamped).
#[inline(always)]
fn sample2(d: &[f32], gw: usize, gh: usize, x: f32, y: f32) -> [f32; 2] {
    let x = x.clamp(0.0, (gw - 1) as f32);
    let y = y.clamp(0.0, (gh - 1) as f32);
    // Non-negative after the clamp: truncation is the floor.
    let (x0, y0) = (x as i32 as usize, y as i32 as usize);
    let (fx, fy) = (x - x0 as f32, y - y0 as f32);
    // Offsets of the right and lower taps (the same tap at the last column or row).
    let dx = if x0 + 1 < gw { 2 } else { 0 };
    let dy = if y0 + 1 < gh { gw * 2 } else { 0 };
    let i = (y0 * gw + x0) * 2;
    let t = &d[i..i + dy + dx + 2];
    let (a, b) = (&t[..2], &t[dx..dx + 2]);
    let (c, e) = (&t[dy..dy + 2], &t[dy + dx..dy + dx + 2]);
    [0, 1].map(|k| {
        (a[k] * (1.0 - fx) + b[k] * fx) * (1.0 - fy) + (c[k] * (1.0 - fx) + e[k] * fx) * fy
    })
}

/// Per layer, the grid flow of its own interior: grid pixels whose match in the previous
/// frame lies inside the layer (one grid pixel from any other layer) keep their flow, and
/// push-pull fills the rest, so each layer moves with its own content; a layer without such
/// pixels stays where it is. Returns each layer's new map into the I-frame: its previous
/// map (`maps`) composed with that flow.
fn layer_maps(
    prev_owner: &[u8],
    flow: &Flow,
    maps: &[Vec<f32>],
    depths: &Depths<'_>,
) -> Vec<Vec<f32>> {
    let (w, h) = (depths.w, depths.h);
    let (gw, gh) = (flow.width, flow.height);
    let (sx, sy) = (w as f32 / gw as f32, h as f32 / gh as f32);
    // The previous owner on the grid (nearest pixel).
    let cell: Vec<u8> = (0..gw * gh)
        .map(|g| prev_owner[nearest_pixel((g % gw) as f32, (g / gw) as f32, (sx, sy), (w, h))])
        .collect();
    let reach = distance_inside(&cell, gw, gh, INTERIOR_RAMP + 1);
    let block = ((gw.max(gh) as f32 * MOTION_BLOCK).round() as usize).max(1);
    // The layer whose interior each grid pixel's match lies in (255: none), and how much its
    // vector counts: vectors measured near a layer boundary mix the motions of both sides, so
    // they count less the nearer their match lies to the boundary.
    let mut inside = vec![(u8::MAX, 0f32); gw * gh];
    inside
        .par_chunks_mut(gw)
        .zip(flow.data.par_chunks(gw * 2))
        .enumerate()
        .for_each(|(gy, (row, f))| {
            for (gx, (o, uv)) in row.iter_mut().zip(f.chunks_exact(2)).enumerate() {
                // Nearest grid pixel (floor of +1/2; negatives fail the test first).
                let qx = gx as f32 + uv[0] + 0.5;
                let qy = gy as f32 + uv[1] + 0.5;
                if qx < 0.0 || qy < 0.0 || qx >= gw as f32 || qy >= gh as f32 {
                    continue;
                }
                let q = qy as usize * gw + qx as usize;
                if reach[q] >= 2
                    && depths.same_surface(cell[q], (gx, gy), (qx - 0.5, qy - 0.5), (sx, sy))
                {
                    let ramp = (reach[q] - 1) as f32 / INTERIOR_RAMP as f32;
                    *o = (cell[q], ramp.min(1.0));
                }
            }
        });
    maps.par_iter()
        .enumerate()
        .map(|(l, map)| {
            let weight: Vec<f32> = inside
                .iter()
                .map(|&(i, c)| if i as usize == l { c } else { 0.0 })
                .collect();
            // Vectors that disagree with their neighbourhood lose their weight.
            let weight = robust::local_inliers(&flow.data, &weight, gw, gh, block);
            let Some(model) = robust::Affine::fit(&flow.data, &weight, gw, gh) else {
                return compose(map, &vec![0.0; gw * gh * 2], gw, gh);
            };
            // The model plus the residual of the vectors it keeps, filled in elsewhere.
            let mut data = flow.data.clone();
            model.add_to(&mut data, gw, -1.0);
            if !cpsl_layering::fill::push_pull(&mut data, &weight, gw, gh, 2) {
                data.fill(0.0);
            }
            model.add_to(&mut data, gw, 1.0);
            compose(map, &data, gw, gh)
        })
        .collect()
}

/// What tells a pixel that still shows the surface its motion points to from one that a
/// moving occluder has just uncovered (or one a layer holds by mistake): this frame's depth
/// against the previous frame's at the match, and against the depths the layer spanned at
/// the I-frame.
struct Depths<'a> {
    now: &'a [f32],
    prev: &'a [f32],
    w: usize,
    h: usize,
    /// Bounds of `z_now / z_prev` on one surface.
    ratio: (f32, f32),
    /// Per layer, the bounds of its depth (widened by the tolerance).
    spans: Vec<(f32, f32)>,
}

impl<'a> Depths<'a> {
    /// `spans`: per layer, the 5 % and 95 % quantiles of `ln z` over its pixels;
    /// `tolerance` widens every bound in `ln z`.
    fn new(
        now: &'a [f32],
        prev: &'a [f32],
        (w, h): (usize, usize),
        spans: impl Iterator<Item = (f32, f32)>,
        tolerance: f32,
    ) -> Self {
        Self {
            now,
            prev,
            w,
            h,
            ratio: ((-tolerance).exp(), tolerance.exp()),
            spans: spans
                .map(|(lo, hi)| ((lo - tolerance).exp(), (hi + tolerance).exp()))
                .collect(),
        }
    }

    /// Whether grid pixel `(gx, gy)` shows the surface of layer `l` that its match
    /// `(mx, my)` (grid coordinates) showed in the previous frame: its depth agrees with the
    /// match's and lies within the layer's span. Pixels without a valid depth pass.
    #[inline]
    fn same_surface(
        &self,
        l: u8,
        (gx, gy): (usize, usize),
        (mx, my): (f32, f32),
        (sx, sy): (f32, f32),
    ) -> bool {
        let at = |gx: f32, gy: f32| nearest_pixel(gx, gy, (sx, sy), (self.w, self.h));
        let z = self.now[at(gx as f32, gy as f32)];
        let r = z / self.prev[at(mx, my)];
        let (lo, hi) = self.spans[l as usize];
        // Comparisons with NaN are false: a missing depth fails neither test.
        !(r < self.ratio.0 || r > self.ratio.1 || z < lo || z > hi)
    }
}

/// A layer's new map: the previous map sampled at each grid pixel's match (`flow`, on the
/// same grid).
fn compose(map: &[f32], flow: &[f32], gw: usize, gh: usize) -> Vec<f32> {
    let mut out = vec![0f32; gw * gh * 2];
    for (y, (row, f)) in out.chunks_mut(gw * 2).zip(flow.chunks(gw * 2)).enumerate() {
        for (x, (o, uv)) in row.chunks_exact_mut(2).zip(f.chunks_exact(2)).enumerate() {
            o.copy_from_slice(&sample2(map, gw, gh, x as f32 + uv[0], y as f32 + uv[1]));
        }
    }
    out
}

/// Grid pixels from a layer boundary within which interior vectors count less.
const INTERIOR_RAMP: u8 = 4;

/// Side of the blocks within which a layer's vectors are compared with their median, as a
/// share of the grid's long side.
const MOTION_BLOCK: f32 = 0.15;

/// Per pixel of a label map, its chessboard distance to the nearest pixel of another label
/// (1: a neighbour differs), at most `cap`: one plus the number of 3x3 erosions the set of
/// pixels without a differing neighbour survives.
fn distance_inside(label: &[u8], w: usize, h: usize, cap: u8) -> Vec<u8> {
    let lo = min3x3(label, w, h);
    let inv: Vec<u8> = label.iter().map(|&v| 255 - v).collect();
    let hi = min3x3(&inv, w, h);
    let mut inside: Vec<u8> = lo
        .iter()
        .zip(&hi)
        .map(|(&a, &b)| (a == 255 - b) as u8)
        .collect();
    let mut d: Vec<u8> = inside.iter().map(|&m| 1 + m).collect();
    for _ in 2..cap {
        inside = min3x3(&inside, w, h);
        d.iter_mut().zip(&inside).for_each(|(d, &m)| *d += m);
    }
    d
}

/// Minimum over the 3x3 window around every pixel (clamped at the edges), separably.
fn min3x3(v: &[u8], w: usize, h: usize) -> Vec<u8> {
    let row_min = |src: &[u8], out: &mut [u8]| {
        for (o, t) in out[1..].iter_mut().zip(src.windows(3)) {
            *o = t[0].min(t[1]).min(t[2]);
        }
        out[0] = src[0].min(src[w.min(2) - 1]);
        out[w - 1] = src[w - 1].min(src[w.saturating_sub(2)]);
    };
    let mut tmp = vec![0u8; w * h];
    tmp.chunks_mut(w)
        .zip(v.chunks(w))
        .for_each(|(o, src)| row_min(src, o));
    let mut out = vec![0u8; w * h];
    out.chunks_mut(w).enumerate().for_each(|(y, o)| {
        let (a, b, c) = (y.saturating_sub(1), y, (y + 1).min(h - 1));
        let (ra, rb, rc) = (
            &tmp[a * w..a * w + w],
            &tmp[b * w..b * w + w],
            &tmp[c * w..c * w + w],
        );
        for (((o, &x), &y), &z) in o.iter_mut().zip(ra).zip(rb).zip(rc) {
            *o = x.min(y).min(z);
        }
    });
    out
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn distance_inside_matches_brute_force() {
        let (w, h) = (37, 23);
        let label: Vec<u8> = (0..w * h)
            .map(|p| {
                let (x, y) = ((p % w) as i32, (p / w) as i32);
                ((x - 15).pow(2) + (y - 11).pow(2) < 64) as u8 + (x > 30 && y < 5) as u8 * 2
            })
            .collect();
        let got = distance_inside(&label, w, h, 6);
        for p in 0..w * h {
            let (x, y) = ((p % w) as i32, (p / w) as i32);
            let mut want = 6u8;
            for q in 0..w * h {
                let (qx, qy) = ((q % w) as i32, (q / w) as i32);
                if label[q] != label[p] {
                    want = want.min((qx - x).abs().max((qy - y).abs()) as u8);
                }
            }
            assert_eq!(got[p], want, "{x} {y}");
        }
    }
}
