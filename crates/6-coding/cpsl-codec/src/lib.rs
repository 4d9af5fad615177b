//! Layer streams of a CPSL package: coding a segment (a group of pictures of layer sets) into
//! one standard video stream per layer plus a side stream, with the per-layer bitrate
//! allocation, and decoding a segment back into layer sets.
//!
//! **Layout.** Each layer of a segment is one stream of 8-bit 4:2:0 pictures twice the frame
//! height, a movie fragment with an init segment per picture size (package version 4) or a
//! self-contained MP4 file (versions 1 to 3; see [`Container`]): premultiplied colour on top,
//! alpha as grey below ([`yuv`]), tagged BT.709 limited range; under a tight budget a stream
//! may be coded at a half, a quarter or an eighth of the frame size ([`scale`]). Per-layer
//! streams keep per-layer rate control exact; a segment's streams hold the same frames and
//! start with a key frame, so a player decodes them in lock-step (the browser player with
//! WebCodecs). The side stream (`side.bin`, see `cpsl-package`) maps each frame's
//! layers to streams and carries depths, confidence, refresh flags and the Edge-Depth Cache.

pub mod alloc;
mod fmp4;
mod reader;
pub mod scale;
mod segment;
mod stream;
mod writer;
pub mod yuv;

pub use reader::{decode_segment, DecodedFrame, SegmentReader};
pub use segment::{SegmentReport, TRIAL_FRAMES};
pub use writer::{segment_budget, PackageWriter};

pub use stream::{
    decode_pictures, decode_stream, encode_pictures, encode_stream, has_encoder, quality_range,
    write_init, Container, PictureReader, Sample, StreamEncoder, Written,
};

use cpsl_package::{Codec, PackageError};
use std::path::PathBuf;
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
    /// Most frames per segment (the GOP): the encoders' key-frame interval and, under a
    /// budget, the length a segment's allocation plans for.
    pub gop: u32,
    /// How the layer streams are stored: movie fragments with init segments (package
    /// version 4, the default) or self-contained MP4 files (versions 2 and 3).
    pub container: Container,
    /// Where segments start.
    pub segments: Segments,
}

/// Where a package's segments, and with them the layer streams' key frames, start.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default)]
pub enum Segments {
    /// Every `gop` frames (the default), and at a refresh of the layering that brings a new
    /// layer. A refresh whose layers all kept their tracks (the layering's association found
    /// each in the frame before: the content continues) does not cut the segment: its
    /// streams code the new decomposition as the rest of their group instead of starting
    /// again with a key frame each. The video's last segment takes up to a few frames more
    /// rather than leave a short one.
    #[default]
    Gop,
    /// At every I-frame of the layering, as the paper's groups of pictures: every refresh
    /// starts each stream again with a key frame.
    Refresh,
}
