//! Playback of what cpsl makes: a seekable [`Player`] for packages (every layer stream of a
//! segment decoded in lock step, one picture at a time, so a player holds one frame), a
//! [`LayeredVideo`] for the folders of `cpsl layer-video` (each frame's layer set read when
//! asked for), a [`Source`] that is a package, a layered video or a layer-set folder, the
//! [`Frames`] both sequences share, and the choice of renderer
//! ([`choose_renderer`]: the GPU where asked for and present, else the CPU reference), and
//! rendering along a sweep of poses into frames, a contact sheet and an MP4 ([`sweep`]), and
//! timed playback ([`mod@bench`]).

pub mod bench;
pub mod sweep;

use cpsl_codec::{CodecError, SegmentReader};
use cpsl_core::{Camera, Limits, Progress, ProgressEvent};
use cpsl_package::{Package, PackageError};
use cpsl_render::{CpuRenderer, Filter, FrameLayers, Renderer};
use std::path::{Path, PathBuf};
use thiserror::Error;

/// Why playback failed.
#[derive(Debug, Error)]
pub enum PlayerError {
    /// The package cannot be opened.
    #[error("opening the package {path}: {source}")]
    Open {
        /// What was opened.
        path: PathBuf,
        /// Why it failed.
        source: PackageError,
    },
    /// A frame past the end.
    #[error("frame {frame}: the input has {frames} frames")]
    NoFrame {
        /// The frame asked for.
        frame: u32,
        /// How many there are.
        frames: u32,
    },
    /// A segment cannot be decoded.
    #[error("decoding segment {segment} of {package}: {source}")]
    Decode {
        /// The segment.
        segment: usize,
        /// The package.
        package: PathBuf,
        /// Why.
        source: CodecError,
    },
    /// A segment's streams ended before the frame asked for.
    #[error("decoding segment {segment} of {package}: it ended before frame {frame}")]
    Ended {
        /// The segment.
        segment: usize,
        /// The package.
        package: PathBuf,
        /// The frame asked for.
        frame: u32,
    },
    /// A frame of a layered video has another camera than its first frame.
    #[error("{path}: camera {found:?} differs from the first frame's {first:?}")]
    Camera {
        /// The frame's layer-set folder.
        path: PathBuf,
        /// Its camera.
        found: Box<Camera>,
        /// The first frame's.
        first: Box<Camera>,
    },
    /// A layer-set folder cannot be read.
    #[error("reading layer set {path}: {source}")]
    LayerSet {
        /// The folder.
        path: PathBuf,
        /// Why.
        source: cpsl_io::IoError,
    },
    /// Writing an image failed.
    #[error(transparent)]
    Write(#[from] cpsl_io::IoError),
    /// A folder cannot be made.
    #[error("{path}: {source}")]
    File {
        /// The folder.
        path: PathBuf,
        /// Why.
        source: std::io::Error,
    },
    /// A renderer failed.
    #[error(transparent)]
    Render(#[from] cpsl_render::RenderError),
    /// The GPU renderer failed.
    #[error(transparent)]
    Gpu(#[from] cpsl_render_gpu::GpuError),
    /// The `ffmpeg` tool failed.
    #[error("{0}")]
    Ffmpeg(String),
    /// A file is neither a package archive nor a folder.
    #[error(
        "{0} is a file, not a layer-set folder or a package (`cpsl layer` makes layers from an \
         image, `cpsl encode` a package from a video)"
    )]
    NotLayers(PathBuf),
}

/// Plays a package: decodes frame after frame of the segment holding the requested one. A
/// request ahead in the open segment decodes on; one behind it or in another segment reopens
/// that segment at its key frame.
pub struct Player {
    pkg: Package,
    /// The open segment and its reader.
    reader: Option<(usize, SegmentReader)>,
    /// The last frame handed out by [`Player::frame`].
    current: Option<(u32, FrameLayers)>,
}

impl Player {
    /// Opens a package folder or archive (its manifest checked; files are checked as they are
    /// decoded).
    pub fn open(path: &Path) -> Result<Self, PlayerError> {
        let pkg = Package::open(path).map_err(|source| PlayerError::Open {
            path: path.to_path_buf(),
            source,
        })?;
        Ok(Self::new(pkg))
    }

    /// Plays an opened package.
    pub fn new(pkg: Package) -> Self {
        Self {
            pkg,
            reader: None,
            current: None,
        }
    }

    /// The package.
    pub fn package(&self) -> &Package {
        &self.pkg
    }

    /// Number of frames.
    pub fn frames(&self) -> u32 {
        self.pkg.manifest().frames
    }

    /// Decodes frame `f` with its Edge-Depth Cache.
    pub fn decode(&mut self, f: u32) -> Result<FrameLayers, PlayerError> {
        let m = self.pkg.manifest();
        let seg = m.segment_of(f).ok_or(PlayerError::NoFrame {
            frame: f,
            frames: m.frames,
        })?;
        let start = m.segments[seg].start;
        let ahead = |(s, r): &(usize, SegmentReader)| *s == seg && start + r.given() <= f;
        if !self.reader.as_ref().is_some_and(ahead) {
            let reader = SegmentReader::open(&self.pkg, seg).map_err(|source| {
                self.reader = None;
                PlayerError::Decode {
                    segment: seg,
                    package: self.pkg.opened().to_path_buf(),
                    source,
                }
            })?;
            self.reader = Some((seg, reader));
        }
        let (_, reader) = self.reader.as_mut().expect("opened above");
        loop {
            match reader.next() {
                Some(Ok(d)) if d.side.index == f => {
                    return Ok(FrameLayers::new(d.set, Some(d.side.edc)));
                }
                Some(Ok(_)) => {}
                failed => {
                    // A failed reader is not reused: the next request reopens the segment.
                    self.reader = None;
                    let package = self.pkg.opened().to_path_buf();
                    return Err(match failed {
                        Some(Err(source)) => PlayerError::Decode {
                            segment: seg,
                            package,
                            source,
                        },
                        _ => PlayerError::Ended {
                            segment: seg,
                            package,
                            frame: f,
                        },
                    });
                }
            }
        }
    }

    /// Frame `f`, decoded once and kept until another frame is asked for.
    pub fn frame(&mut self, f: u32) -> Result<&FrameLayers, PlayerError> {
        if self.current.as_ref().is_none_or(|c| c.0 != f) {
            let frame = self.decode(f)?;
            self.current = Some((f, frame));
        }
        Ok(&self.current.as_ref().expect("decoded above").1)
    }
}

/// A sequence of frames decoded one at a time, from any thread: a package ([`Player`]) or a
/// layered video ([`LayeredVideo`]).
pub trait Frames: Send {
    /// Number of frames.
    fn frames(&self) -> u32;
    /// Decodes frame `f` with its Edge-Depth Cache.
    fn decode(&mut self, f: u32) -> Result<FrameLayers, PlayerError>;
}

impl Frames for Player {
    fn frames(&self) -> u32 {
        Player::frames(self)
    }
    fn decode(&mut self, f: u32) -> Result<FrameLayers, PlayerError> {
        Player::decode(self, f)
    }
}

/// Reads a layer-set folder with its Edge-Depth Cache, when it has one.
fn read_layers(path: &Path) -> Result<FrameLayers, PlayerError> {
    let limits = Limits::default();
    let layer_set = |source| PlayerError::LayerSet {
        path: path.to_path_buf(),
        source,
    };
    let set = cpsl_io::read_layer_set(path, &limits).map_err(layer_set)?;
    let edc = cpsl_io::read_edc(path, &set, &limits).map_err(layer_set)?;
    Ok(FrameLayers::new(set, edc))
}

/// Plays the folder of `cpsl layer-video` (`video.json` and a layer set per frame): each
/// frame's layer set is read when asked for; every frame must have the first one's camera.
pub struct LayeredVideo {
    dir: PathBuf,
    index: cpsl_io::video::VideoIndex,
    camera: Camera,
    /// The last frame handed out by [`LayeredVideo::frame`].
    current: Option<(u32, FrameLayers)>,
}

impl LayeredVideo {
    /// Opens a layered video folder: its index checked and its first frame read.
    pub fn open(dir: &Path) -> Result<Self, PlayerError> {
        let index =
            cpsl_io::video::read_video_index(dir).map_err(|source| PlayerError::LayerSet {
                path: dir.to_path_buf(),
                source,
            })?;
        let first = read_layers(&dir.join(&index.frames[0]))?;
        Ok(Self {
            dir: dir.to_path_buf(),
            camera: *first.set.camera(),
            index,
            current: Some((0, first)),
        })
    }

    /// The camera of every frame.
    pub fn camera(&self) -> &Camera {
        &self.camera
    }

    /// Frames per second.
    pub fn fps(&self) -> f64 {
        self.index.fps
    }

    /// Frame `f`, read once and kept until another frame is asked for.
    pub fn frame(&mut self, f: u32) -> Result<&FrameLayers, PlayerError> {
        if self.current.as_ref().is_none_or(|c| c.0 != f) {
            let frame = Frames::decode(self, f)?;
            self.current = Some((f, frame));
        }
        Ok(&self.current.as_ref().expect("read above").1)
    }
}

impl Frames for LayeredVideo {
    fn frames(&self) -> u32 {
        self.index.frames.len() as u32
    }

    fn decode(&mut self, f: u32) -> Result<FrameLayers, PlayerError> {
        let frames = self.frames();
        let name = self
            .index
            .frames
            .get(f as usize)
            .ok_or(PlayerError::NoFrame { frame: f, frames })?;
        let path = self.dir.join(name);
        let layers = read_layers(&path)?;
        if *layers.set.camera() != self.camera {
            return Err(PlayerError::Camera {
                path,
                found: Box::new(*layers.set.camera()),
                first: Box::new(self.camera),
            });
        }
        Ok(layers)
    }
}

/// What is played: one layer set, the frames of a layered video, or those of a package.
pub enum Source {
    /// A layer set (with its cache, when its folder has one).
    Still(Box<FrameLayers>),
    /// A layered video folder.
    Video(Box<LayeredVideo>),
    /// A package.
    Package(Box<Player>),
}

impl Source {
    /// Opens a package (folder or archive), a layered video folder or a layer-set folder.
    pub fn open(path: &Path) -> Result<Self, PlayerError> {
        if cpsl_package::is_package(path) {
            return Ok(Source::Package(Box::new(Player::open(path)?)));
        }
        if path.is_file() {
            return Err(PlayerError::NotLayers(path.to_path_buf()));
        }
        if path.join(cpsl_io::video::VIDEO_FILE).is_file() {
            return Ok(Source::Video(Box::new(LayeredVideo::open(path)?)));
        }
        Ok(Source::Still(Box::new(read_layers(path)?)))
    }

    /// Number of frames (1 for a layer set).
    pub fn frames(&self) -> u32 {
        match self {
            Source::Still(_) => 1,
            Source::Video(v) => v.frames(),
            Source::Package(p) => p.frames(),
        }
    }

    /// Frame `f` (a layer set is every frame).
    pub fn frame(&mut self, f: u32) -> Result<&FrameLayers, PlayerError> {
        match self {
            Source::Still(s) => Ok(s),
            Source::Video(v) => v.frame(f),
            Source::Package(p) => p.frame(f),
        }
    }

    /// The layers at step `i` of a loop: frame `i` modulo the number of frames.
    pub fn at(&mut self, i: usize) -> Result<&FrameLayers, PlayerError> {
        let n = self.frames() as usize;
        self.frame((i % n) as u32)
    }
}

/// The renderer to draw with, resampling with `filter`: the GPU (wgpu) when `gpu` asks for it
/// and an adapter exists, else the CPU reference, with a warning saying why when the GPU was
/// asked for.
pub fn choose_renderer(gpu: bool, filter: Filter, progress: &dyn Progress) -> Box<dyn Renderer> {
    if gpu {
        match cpsl_render_gpu::GpuRenderer::new() {
            Ok(mut g) => {
                g.set_filter(filter);
                return Box::new(g);
            }
            Err(e) => progress.event(ProgressEvent::Warning {
                message: format!("--gpu: {e}; rendering on the CPU instead"),
            }),
        }
    }
    Box::new(CpuRenderer::new(filter))
}
