//! One layered frame of a video, as temporal layering produces it and the codec consumes it.

use crate::{Edc, LayerSet};
use serde::{Deserialize, Serialize};

/// Why a frame is an I-frame (layered from scratch instead of carried along the motion).
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum RefreshReason {
    /// The first frame of the video.
    First,
    /// The GOP was full.
    Gop,
    /// Mean temporal confidence stayed low.
    Confidence,
    /// The crack rate stayed high.
    Crack,
}

impl RefreshReason {
    /// A short name (`first`, `gop`, `confidence`, `crack`), as in `video.json`.
    pub fn name(self) -> &'static str {
        match self {
            Self::First => "first",
            Self::Gop => "gop",
            Self::Confidence => "confidence",
            Self::Crack => "crack",
        }
    }
}

/// One layered frame of a video.
#[derive(Debug, Clone)]
pub struct LayeredFrame {
    /// Frame index in the video.
    pub index: u32,
    /// `Some(reason)` for an I-frame, `None` for a P-frame.
    pub refresh: Option<RefreshReason>,
    /// The layers (tracks in their metadata).
    pub set: LayerSet,
    /// The Edge-Depth Cache.
    pub edc: Edc,
    /// Layer index per pixel (empty where the producer has none, e.g. a decoded frame).
    pub owner: Vec<u8>,
    /// Temporal confidence per layer (1 on I-frames).
    pub confidence: Vec<f32>,
    /// Crack rate above the last I-frame's.
    pub crack: f32,
    /// Whether the depth was carried along the motion instead of estimated.
    pub depth_propagated: bool,
    /// Wall time per stage in milliseconds.
    pub timings: Vec<(&'static str, f64)>,
}

impl LayeredFrame {
    /// A frame of `set` alone: no owner map, full confidence, no timings.
    pub fn new(index: u32, refresh: Option<RefreshReason>, set: LayerSet, edc: Edc) -> Self {
        let confidence = vec![1.0; set.len()];
        Self {
            index,
            refresh,
            set,
            edc,
            owner: Vec::new(),
            confidence,
            crack: 0.0,
            depth_propagated: false,
            timings: Vec::new(),
        }
    }
}
