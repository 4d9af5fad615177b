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

use cpsl_core::{Camera, LayerSet, LayeredFrame, Limits, NoProgress, RefreshReason};
use cpsl_flow::{Flow, FlowConfig, FlowMethod, Grey};
use cpsl_layering::geometry::{fit_geometry, fit_grid, LayerDepth};
use cpsl_layering::matte::edge_depth_cache_from;
use cpsl_layering::{layer_frame, GeometryMode, LayeringConfig, LayeringError};
use rayon::prelude::*;
use serde::{Deserialize, Serialize};
use std::time::Instant;
use thiserror::Error;

mod kernels;
mod motion;
mod robust;
mod warp;

use motion::{identity_map, layer_maps, mapped, shrink_flow, Depths, FrameMotion};
use warp::warp_values_pair;
pub use warp::{warp_labels, warp_values};
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
    /// The optical flow of a P-frame failed.
    #[error("motion of frame {frame}: {source}")]
    Flow {
        /// Frame index.
        frame: usize,
        /// What failed.
        source: cpsl_flow::FlowError,
    },
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
    /// The optical flow of P-frames whose motion is not given: OpenCV's DIS polished by
    /// Lucas-Kanade (the default) or the Lucas-Kanade of `cpsl-flow` alone (before 2026-11-29).
    pub flow: FlowMethod,
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
    /// Under a bit-rate budget, [`GopConfig::for_budget`] lowers `refresh_confidence` where
    /// the bits per pixel are few (off: the threshold stays, as the paper's).
    pub rate_aware_refresh: bool,
}

/// Bits per pixel below which a budget lowers the refresh threshold (1.5 Mbit/s at 1080p30,
/// 0.66 Mbit/s at 720p30); see [`GopConfig::for_budget`].
pub const REFRESH_BITS_PER_PIXEL: f64 = 0.024;

/// How much [`GopConfig::for_budget`] lowers the refresh threshold.
pub const REFRESH_DROP: f32 = 0.1;

impl Default for GopConfig {
    fn default() -> Self {
        Self {
            gop: 30,
            flow_side: 320,
            flow: FlowMethod::default(),
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
            rate_aware_refresh: true,
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

    /// The configuration for layering a video that is coded at `bits_per_pixel` (a budget in
    /// bits per second over pixels per second): with `rate_aware_refresh`, below
    /// [`REFRESH_BITS_PER_PIXEL`] the adaptive refresh's `refresh_confidence` drops by
    /// [`REFRESH_DROP`]. A refresh codes a new decomposition into every stream; where bits are
    /// that few the change costs more than the drift it removes (the 1080p synthetic clip,
    /// `cpsl eval-rd`: 0.5 Mbit/s 24.63 -> 25.35 dB, 1 Mbit/s 26.49 -> 26.81 dB). Above it the
    /// threshold stays: at 0.032 bits per pixel 0.65 gained nothing on that clip (2 Mbit/s)
    /// and 0.70 lost 1.4 dB on the fox (0.5 Mbit/s at 540x960). Without the rule, or with no
    /// positive finite rate, the configuration is unchanged.
    pub fn for_budget(self, bits_per_pixel: f64) -> Self {
        let low = bits_per_pixel > 0.0 && bits_per_pixel < REFRESH_BITS_PER_PIXEL;
        if !(self.rate_aware_refresh && low) {
            return self;
        }
        Self {
            refresh_confidence: (self.refresh_confidence - REFRESH_DROP).max(0.0),
            ..self
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
    /// The previous frame's depth, its logarithm (carried with it: the nearest-pixel warp
    /// copies values, so the carried logarithm is the logarithm of the carried depth) and
    /// owner.
    depth: Vec<f32>,
    ln_depth: Vec<f32>,
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
    /// The previous frame's layer surfaces.
    geometries: Vec<cpsl_core::Geometry>,
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

/// How far, in log depth, a mesh vertex may move between frames before its new value is
/// taken (0.5 %, five steps of the side stream's grid quantisation).
const GRID_HOLD: f32 = 0.005;

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
            flow: FlowConfig {
                method: gop.flow,
                ..FlowConfig::default()
            },
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
                .map(|s| cpsl_flow::flow(&grey, &s.grey, &self.flow))
                .transpose()
                .map_err(|source| VideoError::Flow {
                    frame: index,
                    source,
                })?,
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
        let lz = kernels::LogDepth::of(&set);
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
            .map(|(q, z)| {
                let z = z.reference();
                q.map_or((z, z), |[lo, hi]| (lo, hi))
            })
            .collect();
        timings.push(("association", ms(t)));
        let maps = vec![identity_map(w, h, grey.width, grey.height); k];
        self.state = Some(State {
            grey,
            depth: cues.depth,
            ln_depth,
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
            geometries: set.layers().iter().map(|l| l.geometry.clone()).collect(),
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
        // A model may leave pixels without depth: they keep the depth carried along. Without
        // new depth the logarithm is carried with the depth, not taken again.
        let (depth, ln_depth): (Vec<f32>, Vec<f32>) = match depth {
            Some(d) => d
                .par_iter()
                .zip(warp_values(&s.depth, &motion.at_full(w, h), w, h))
                .map(|(&z, c)| {
                    let z = if z.is_finite() && z > 0.0 { z } else { c };
                    (z, z.ln())
                })
                .unzip(),
            None => warp_values_pair(&s.depth, &s.ln_depth, &motion.at_full(w, h), w, h),
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
        // carries content the I-frame hid behind a nearer layer (extension and fill). Hidden
        // content that nothing covers any more was never seen: it is dropped so that the
        // layers behind show. Owner: the nearest layer with alpha >= 1/2. With refinement,
        // the pixels a layer shows fully opaque and unoccluded take the new frame's colour.
        // Both row by row, each row's layers settled while they are in cache.
        let t = Instant::now();
        let grid = kernels::RowGrid::new((w, h), (gw, gh));
        let (images, owner) = kernels::warp_and_settle(
            &s.key_layers,
            &maps,
            &grid,
            &s.key_owner,
            &depth,
            &depths.spans,
            rgb,
            g.refine,
        );
        let mut layers: Vec<cpsl_core::Layer> = (s.key.layers().iter().zip(images))
            .map(|(key, image)| cpsl_core::Layer {
                image,
                depth: key.depth,
                geometry: key.geometry.clone(),
                meta: key.meta.clone(),
            })
            .collect();
        timings.push(("warp and visibility", ms(t)));
        // Layer depths from the new depth: the median over each layer's pixels, smoothed
        // over time with refinement, kept in order.
        let t = Instant::now();
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
        // A slanted layer's plane and a mesh layer's grid follow the layer (a fronto-parallel
        // layer stays so, as the I-frame chose): with a new depth map, refitted over the
        // layer's pixels; with depth carried along the motion, carried along the layer's own
        // map into the I-frame, as its picture is (the carried depth map, warped frame by
        // frame with the motion of every layer, smears across layer edges). A grid vertex
        // keeps the previous frame's value unless it moved by more than `GRID_HOLD` in log
        // depth: steadier geometry, and a side stream of mostly zeros.
        let cam = *s.key.camera();
        let previous = &s.geometries;
        let key_layers = s.key.layers();
        layers
            .par_iter_mut()
            .enumerate()
            .filter(|(_, l)| !l.geometry.is_plane())
            .for_each(|(l, layer)| {
                let bytes = layer.image.as_bytes();
                let covered = |p: usize| bytes[p * 4 + 3] != 0;
                let px = LayerDepth {
                    width: w,
                    height: h,
                    depth: &depth,
                    confidence: None,
                    owner: &owner,
                    label: l as u8,
                    covered: &covered,
                    bounds: None,
                };
                let bounds = layer.extent();
                let extent = bounds.map(|e| e.map(|v| v as usize));
                // With depth carried along the motion: the I-frame's surface carried along the
                // layer's map (a plane that would not stay in front is refitted).
                let carried = depth_propagated
                    .then(|| {
                        let at = |u: f64, v: f64| mapped(&maps[l], (gw, gh), (w, h), (u, v));
                        carry_geometry(&key_layers[l], &cam, at, bounds)
                    })
                    .flatten();
                if let Some(plane @ cpsl_core::Geometry::Slanted(_)) = carried {
                    layer.geometry = plane;
                } else if let cpsl_core::Geometry::Mesh(key) = &layer.geometry {
                    let fitted = match carried {
                        Some(cpsl_core::Geometry::Mesh(g)) => {
                            Some(std::sync::Arc::unwrap_or_clone(g))
                        }
                        _ => fit_grid(&cam, &px, key.step, layer.depth),
                    };
                    let Some(mut grid) = fitted else {
                        return; // no pixel left: the grid carries over
                    };
                    if let Some(cpsl_core::Geometry::Mesh(last)) = previous.get(l) {
                        if last.inverse_depth.len() == grid.inverse_depth.len() {
                            for (v, &p) in grid.inverse_depth.iter_mut().zip(&last.inverse_depth) {
                                if (*v / p).ln().abs() <= GRID_HOLD {
                                    *v = p;
                                }
                            }
                        }
                    }
                    layer.geometry = cpsl_core::Geometry::Mesh(std::sync::Arc::new(grid));
                } else {
                    layer.geometry =
                        fit_geometry(GeometryMode::Slanted, &cam, &px, layer.depth, extent, 0, 0);
                }
            });
        // The warp blends premultiplied texels alike in every channel, and the refresh only
        // recolours opaque pixels: the layers are premultiplied by construction.
        let set = LayerSet::new_premultiplied(*s.key.camera(), layers, &Limits::default())?;
        let edc = edge_depth_cache_from(&depth, w, h, &owner, &set, &self.layering.matte);
        timings.push(("depths", ms(t)));
        // Temporal confidence and crack rate.
        let t = Instant::now();
        let lz = kernels::LogDepth::of(&set);
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
        s.ln_depth = ln_depth;
        s.owner = owner.clone();
        s.maps = maps;
        s.depths = set.layers().iter().map(|l| l.depth).collect();
        s.geometries = set.layers().iter().map(|l| l.geometry.clone()).collect();
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

/// The I-frame layer `key`'s surface carried to a P-frame whose pixel `(u, v)` shows the
/// I-frame's pixel `at(u, v)`: a grid takes, at each vertex, the I-frame surface's inverse
/// depth where the vertex's position maps to; a slanted plane is the plane through those
/// values on a lattice over the layer's `extent`. `None` where no surface results (a plane
/// that would reach behind the camera over the extent: refitted instead).
fn carry_geometry(
    key: &cpsl_core::Layer,
    cam: &Camera,
    at: impl Fn(f64, f64) -> (f64, f64),
    extent: Option<[u32; 4]>,
) -> Option<cpsl_core::Geometry> {
    use cpsl_core::Geometry;
    let inv = |u: f64, v: f64| {
        let (x, y) = at(u, v);
        key.geometry.inverse_depth_at(key.depth, cam, x, y)
    };
    match &key.geometry {
        Geometry::Plane => Some(Geometry::Plane),
        Geometry::Mesh(g) => {
            let mut grid = (**g).clone();
            for j in 0..g.rows {
                for i in 0..g.cols {
                    let (u, v) = g.vertex(i, j, cam.width, cam.height);
                    let z = inv(u, v) as f32;
                    if z.is_finite() && z > 0.0 {
                        grid.inverse_depth[(j * g.cols + i) as usize] = z;
                    }
                }
            }
            Some(Geometry::Mesh(std::sync::Arc::new(grid)))
        }
        Geometry::Slanted(_) => {
            let [x0, y0, x1, y1] = extent?.map(f64::from);
            const N: usize = 5;
            let samples: Vec<[f64; 4]> = (0..N * N)
                .map(|k| {
                    let u = x0 + (x1 - x0) * (k % N) as f64 / (N - 1) as f64;
                    let v = y0 + (y1 - y0) * (k / N) as f64 / (N - 1) as f64;
                    [(u - cam.cx) / cam.fx, (v - cam.cy) / cam.fy, inv(u, v), 1.0]
                })
                .collect();
            let plane = Geometry::Slanted(cpsl_core::fit_plane(&samples, 0)?);
            let box_ = [x0 - 1.0, y0 - 1.0, x1 + 1.0, y1 + 1.0];
            let (least, ..) = plane.least_inverse_depth(key.depth, cam, box_);
            (least.is_finite() && least > 0.0).then_some(plane)
        }
    }
}

fn ms(t: Instant) -> f64 {
    t.elapsed().as_secs_f64() * 1e3
}

fn with_tracks(set: LayerSet, tracks: &[u32]) -> Result<LayerSet, VideoError> {
    let (camera, mut layers) = set.into_parts();
    for (l, &t) in layers.iter_mut().zip(tracks) {
        l.meta.track = Some(t);
    }
    Ok(LayerSet::new(camera, layers, &Limits::default())?)
}

#[cfg(test)]
mod tests {
    use super::{carry_geometry, GopConfig};
    use cpsl_core::{Camera, DepthGrid, Geometry, Layer, PremulImage, Vec3};
    use std::sync::Arc;

    #[test]
    fn a_carried_surface_follows_the_layers_map() {
        let cam = Camera::centred(64, 48, 60.0);
        let blank = || PremulImage::new(64, 48);
        // A grid whose inverse depth rises along x, and a map that shifts by 8 px.
        let (cols, rows) = DepthGrid::dims(64, 48, 8);
        let inverse_depth = (0..rows)
            .flat_map(|_| (0..cols).map(|i| 0.5 + 0.01 * i as f32))
            .collect();
        let grid = DepthGrid {
            step: 8,
            cols,
            rows,
            inverse_depth,
        };
        let key = Layer {
            geometry: Geometry::Mesh(Arc::new(grid.clone())),
            ..Layer::new(blank(), 2.0)
        };
        let shift = |u: f64, v: f64| (u + 8.0, v);
        let Some(Geometry::Mesh(moved)) = carry_geometry(&key, &cam, shift, None) else {
            panic!("a mesh carries to a mesh");
        };
        for j in 0..rows {
            for i in 0..cols - 2 {
                let (u, v) = grid.vertex(i, j, 64, 48);
                let want = grid.inverse_depth_at(&cam, u + 8.0, v);
                assert!((moved.at(i, j) - want).abs() < 1e-6, "vertex ({i}, {j})");
                // One vertex on: the next vertex's value.
                assert!((moved.at(i, j) - grid.at(i + 1, j)).abs() < 1e-6);
            }
        }
        // The identity keeps a slanted plane; a shift moves it as the picture moves.
        let m = Vec3::new(0.1, -0.05, 0.5);
        let key = Layer {
            geometry: Geometry::Slanted(m),
            ..Layer::new(blank(), 2.0)
        };
        let extent = Some([4, 4, 59, 43]);
        let same = carry_geometry(&key, &cam, |u, v| (u, v), extent);
        let Some(Geometry::Slanted(n)) = same else {
            panic!("a plane carries to a plane");
        };
        assert!((n - m).norm() < 1e-9, "{n:?}");
        let moved = carry_geometry(&key, &cam, shift, extent).expect("in front");
        for (u, v) in [(10.0, 10.0), (40.0, 30.0)] {
            let got = moved.inverse_depth_at(2.0, &cam, u, v);
            let want = key.geometry.inverse_depth_at(2.0, &cam, u + 8.0, v);
            assert!((got - want).abs() < 1e-9);
        }
        // A plane that the shift would take behind the camera over the extent: none.
        let steep = Layer {
            geometry: Geometry::Slanted(Vec3::new(-2.0, 0.0, 0.5)),
            ..Layer::new(blank(), 2.0)
        };
        let far = |u: f64, v: f64| (u + 40.0, v);
        assert!(carry_geometry(&steep, &cam, far, extent).is_none());
        // Fronto-parallel layers stay so.
        let flat = Layer::new(blank(), 2.0);
        assert_eq!(
            carry_geometry(&flat, &cam, shift, extent),
            Some(Geometry::Plane)
        );
    }

    #[test]
    fn a_small_budget_lowers_the_refresh_threshold() {
        let g = GopConfig::default();
        let at = |bpp: f64| g.for_budget(bpp).refresh_confidence;
        let near = |a: f32, b: f32| (a - b).abs() < 1e-6;
        // Plenty of bits, or none said: unchanged.
        for bpp in [1.0, 0.064, 0.032, 0.024, 0.0, -1.0, f64::NAN] {
            assert!(near(at(bpp), 0.75), "{bpp}: {}", at(bpp));
        }
        // Few: 0.1 lower.
        assert!(near(at(0.016), 0.65));
        assert!(near(at(0.002), 0.65));
        // The 1080p synthetic clip at 30 fps: 1 Mbit/s is few, 2 Mbit/s is not.
        assert!(near(at(1e6 / (1920.0 * 1080.0 * 30.0)), 0.65));
        assert!(near(at(2e6 / (1920.0 * 1080.0 * 30.0)), 0.75));
        // The rule off: the paper's fixed threshold.
        let fixed = GopConfig {
            rate_aware_refresh: false,
            ..g
        };
        assert!(near(fixed.for_budget(0.01).refresh_confidence, 0.75));
        // Everything else stays.
        assert_eq!(
            GopConfig {
                refresh_confidence: 0.75,
                ..g.for_budget(0.01)
            },
            g
        );
    }
}
