//! Media input: RGB frames from a video file (through FFmpeg: any container and codec it
//! reads) or from a folder of images (an image sequence, in file-name order).
//!
//! Y'CbCr video is converted to RGB with the matrix and range the stream declares (BT.709,
//! BT.601, BT.2020, SMPTE 240M; limited or full range). Where it declares no matrix, BT.601
//! is used, as FFmpeg's own scaler does (and as the `ffmpeg` tool encodes untagged video).
//! HDR video (PQ or HLG with BT.2020 primaries, as phones record it) is mapped to SDR BT.709.
//! Pictures are turned upright by the stream's display matrix (quarter turns), as players
//! show them.
//!
//! H.264 streams are decoded with `flags2=+export_mvs`, and each frame carries the decoder's
//! motion vectors as a dense backward motion field ([`InputFrame::motion`]) when they describe it
//! (P-frames predicted from the previous frame only); callers fall back to optical flow
//! otherwise.
//!
//! Modules: `ahead` (decoding on a thread of its own), `sequence` (image folders), `video`
//! (FFmpeg decoding and colour conversion), `hdr` (PQ/HLG to SDR), `orient` (display
//! rotation), `motion` (decoder motion vectors).

mod ahead;
mod hdr;
mod motion;
mod orient;
mod sequence;
mod video;

pub use ahead::{open_ahead, ReadAhead};
pub use motion::motion_from_vectors;
pub use orient::{rotate, rotate_motion, rotation_of};
pub use sequence::ImageSequence;
pub use video::VideoFile;

use cpsl_core::Flow;
use std::path::{Path, PathBuf};
use thiserror::Error;

/// Errors of media input.
#[derive(Debug, Error)]
pub enum MediaError {
    /// The path does not exist or cannot be read.
    #[error("cannot read {path}: {reason}")]
    Unreadable {
        /// The path.
        path: PathBuf,
        /// Why.
        reason: String,
    },
    /// The file has no video stream.
    #[error("{0} has no video stream")]
    NoVideo(PathBuf),
    /// The input holds no frame.
    #[error("{0} holds no frames")]
    Empty(PathBuf),
    /// Decoding failed part-way (truncated or corrupt input).
    #[error("{path}: decoding failed after {frames} frames: {reason}")]
    Decode {
        /// The path.
        path: PathBuf,
        /// Frames decoded before the failure.
        frames: usize,
        /// Why.
        reason: String,
    },
    /// A frame of an image sequence differs in size from the first.
    #[error("{path} is {found:?} pixels, the sequence is {expected:?}")]
    FrameSize {
        /// The file.
        path: PathBuf,
        /// Its size.
        found: (u32, u32),
        /// The first frame's.
        expected: (u32, u32),
    },
    /// Reading an image failed.
    #[error(transparent)]
    Image(#[from] cpsl_io::IoError),
}

/// One decoded frame.
#[derive(Debug, Clone)]
pub struct InputFrame {
    /// Index in the input.
    pub index: usize,
    /// RGB, 3 bytes per pixel, row major.
    pub rgb: Vec<u8>,
    /// Backward motion from the decoder's motion vectors, where the stream has them.
    pub motion: Option<Flow>,
}

/// What the input is.
#[derive(Debug, Clone, PartialEq)]
pub struct Info {
    /// Width.
    pub width: u32,
    /// Height.
    pub height: u32,
    /// Frames per second (image sequences: 30).
    pub fps: f64,
    /// Frame count if known in advance.
    pub frames: Option<usize>,
    /// Codec name (`image` for image sequences).
    pub codec: String,
    /// Clockwise rotation applied to every decoded picture, in degrees (0, 90, 180 or 270):
    /// the stream's display matrix, as players show it (phone videos filmed upright). The
    /// width and height above are after it.
    pub rotation: u32,
    /// The transfer function of an HDR video (`PQ` or `HLG`, BT.2020 primaries), whose
    /// pictures are mapped to SDR BT.709: reference white (203 cd/m2) to white, highlights
    /// rolled off. `None` for SDR video and images.
    pub hdr: Option<&'static str>,
    /// Damaged packets the decoder refused and that were skipped so far (their pictures are
    /// missing from the frames; see [`MAX_DAMAGED_IN_A_ROW`]).
    pub damaged: usize,
}

/// Most damaged packets in a row a video may have before decoding gives up with an error
/// (fewer are skipped, each costing its picture).
pub const MAX_DAMAGED_IN_A_ROW: usize = 25;

/// A source of frames.
pub trait FrameSource {
    /// What the input is.
    fn info(&self) -> &Info;
    /// The next frame, `Ok(None)` at the end.
    fn next_frame(&mut self) -> Result<Option<InputFrame>, MediaError>;
}

/// Opens a video file or an image folder; an H.264 file's frames carry the decoder's motion
/// vectors.
pub fn open(path: &Path) -> Result<Box<dyn FrameSource>, MediaError> {
    open_with(path, true)
}

/// [`open`], with the decoder's motion vectors only where `motion` asks for them (a reader
/// that needs the pictures alone saves their export and conversion).
pub fn open_with(path: &Path, motion: bool) -> Result<Box<dyn FrameSource>, MediaError> {
    if path.is_dir() {
        Ok(Box::new(ImageSequence::open(path)?))
    } else {
        Ok(Box::new(VideoFile::open_with(path, motion)?))
    }
}
