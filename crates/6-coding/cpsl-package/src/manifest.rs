//! The package manifest (`manifest.json`), format `cpsl-package` version 4. Older versions
//! read too: version 1 lacks the per-stream `scale` (every stream at full size), version 2
//! allows scales 1, 2 and 4, version 3 adds 8; in versions 1 to 3 every layer stream is a
//! self-contained MP4 file. Version 4 streams are movie fragments: each names the init
//! segment (`ftyp` + `moov`, one per picture size, listed in `inits`) that goes before it.
//! Version 5 adds the depth notes. From version 6 a segment's layer streams share one file,
//! the segment's `fragment`: one movie fragment with a track run per stream, in the order of
//! `streams` (one request per segment instead of one per stream, and the fragment's boxes
//! paid once); its streams name no file of their own.
//! A package of self-contained streams without an eighth-size one is still written as
//! version 2 ([`version_for`]), so players that read version 2 read it.
//!
//! The manifest names every file of the package with its size and SHA-256, so that a reader
//! (or `cpsl verify`) can check each part, and carries its own checksum: the SHA-256 of the
//! manifest's bytes with the 64 hex digits of its `checksum` field replaced by `0`s. Paths are
//! relative, made of `[A-Za-z0-9._-]` components separated by `/`, never `..`.

use cpsl_core::{Camera, HeadError};
use serde::{Deserialize, Serialize};
use sha2::{Digest, Sha256};
use thiserror::Error;

/// Format name written in every package manifest.
pub const PACKAGE_FORMAT: &str = "cpsl-package";
/// Newest package version this build reads and writes.
pub const PACKAGE_VERSION: u32 = 6;
/// The first version whose layer streams are movie fragments with init segments.
pub const FRAGMENT_VERSION: u32 = 4;
/// The first version that says where the frames' depth came from (`depth`).
pub const DEPTH_VERSION: u32 = 5;
/// The first version whose segments hold their layer streams in one fragment (`fragment`),
/// what every package of fragments is written as.
pub const SEGMENT_FRAGMENT_VERSION: u32 = 6;
/// The longest note of a [`DepthRun`], in bytes.
pub const MAX_DEPTH_NOTE: usize = 1000;

/// The downscale factors a stream may have in a package of `version`.
pub fn scales_of(version: u32) -> &'static [u32] {
    match version {
        0 | 1 => &[1],
        2 => &[1, 2, 4],
        _ => &[1, 2, 4, 8],
    }
}

/// The version a package of self-contained MP4 streams whose downscale factors are `scales`
/// is written with: the lowest that allows them, and at least 2 (what this format wrote
/// before version 3). Packages of fragments are version [`SEGMENT_FRAGMENT_VERSION`].
pub fn version_for(scales: impl IntoIterator<Item = u32>) -> u32 {
    scales.into_iter().fold(2, |v, s| {
        v.max(
            (1..FRAGMENT_VERSION)
                .find(|&v| scales_of(v).contains(&s))
                .unwrap_or(FRAGMENT_VERSION - 1),
        )
    })
}
/// File name of the manifest inside a package.
pub const MANIFEST_FILE: &str = "manifest.json";
const CHECKSUM_KEY: &str = "\"checksum\": \"";

/// The video codec of the layer streams.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "lowercase")]
pub enum Codec {
    /// H.264 / AVC (libx264).
    H264,
    /// H.265 / HEVC (libx265).
    H265,
    /// AV1 (SVT-AV1).
    Av1,
    /// VP9 (libvpx).
    Vp9,
}

impl Codec {
    /// Every codec.
    pub const ALL: [Codec; 4] = [Codec::H264, Codec::H265, Codec::Av1, Codec::Vp9];

    /// The lower-case name used in manifests and on the command line.
    pub fn name(self) -> &'static str {
        match self {
            Codec::H264 => "h264",
            Codec::H265 => "h265",
            Codec::Av1 => "av1",
            Codec::Vp9 => "vp9",
        }
    }

    /// The codec string a browser's `VideoDecoder` / `MediaSource` understands for our streams
    /// (8-bit 4:2:0).
    pub fn mime_codec(self) -> &'static str {
        match self {
            Codec::H264 => "avc1.640028",
            Codec::H265 => "hev1.1.6.L120.90",
            Codec::Av1 => "av01.0.08M.08",
            Codec::Vp9 => "vp09.00.40.08",
        }
    }
}

/// How each layer is laid out in its stream.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct Layout {
    /// Always `colour-over-alpha`: the premultiplied colour in the top half of each picture, the
    /// alpha as grey (Y only, chroma neutral) in the bottom half.
    pub kind: String,
    /// Width of the coded pictures (the frame width rounded up to even).
    pub coded_width: u32,
    /// Height of each half (the frame height rounded up to even); pictures are twice as high.
    pub coded_height: u32,
    /// Pixel format of the coded pictures (`yuv420p`).
    pub pixel_format: String,
    /// Colour matrix, also tagged in the streams (`bt709`).
    pub matrix: String,
    /// Range, also tagged in the streams (`limited`).
    pub range: String,
}

/// One file of the package.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct FileEntry {
    /// Path relative to the package root.
    pub path: String,
    /// Size in bytes.
    pub bytes: u64,
    /// SHA-256 of the content, lower-case hex.
    pub sha256: String,
}

/// One layer stream of a segment.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct StreamEntry {
    /// The coded stream: a self-contained MP4 file (versions 1 to 3) or a movie fragment
    /// (versions 4 and 5); none from version 6, where the stream is a track run of its
    /// segment's `fragment`.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub file: Option<FileEntry>,
    /// The path of the init segment that goes before the fragment (version 4; one of the
    /// manifest's `inits`).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub init: Option<String>,
    /// The track of the layer it carries.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub track: Option<u32>,
    /// Bits per second it spends.
    pub bitrate: u64,
    /// The encoder's quality setting (CRF) it was coded with.
    pub quality: f32,
    /// The downscale factor it was coded at (1, 2, 4 or 8): its pictures are the layer size
    /// divided by it, rounded up, then rounded up to even; players upsample bilinearly.
    #[serde(default = "full_size", skip_serializing_if = "is_full_size")]
    pub scale: u32,
    /// Its weight `w_k` in the bitrate allocation.
    pub weight: f32,
}

fn full_size() -> u32 {
    1
}

fn is_full_size(scale: &u32) -> bool {
    *scale == 1
}

/// One segment: a group of pictures starting with an I-frame, independently decodable.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct Segment {
    /// Index of its first frame.
    pub start: u32,
    /// Its number of frames.
    pub frames: u32,
    /// Its layer streams (the side stream says which stream holds which layer per frame).
    pub streams: Vec<StreamEntry>,
    /// The movie fragment holding its layer streams, stream `k` in track run `k` (version 6
    /// on).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub fragment: Option<FileEntry>,
    /// Its side stream.
    pub side: FileEntry,
}

impl Segment {
    /// Its files: the layer streams' (their own or the shared fragment), then the side
    /// stream.
    pub fn files(&self) -> impl Iterator<Item = &FileEntry> {
        self.streams
            .iter()
            .filter_map(|t| t.file.as_ref())
            .chain(&self.fragment)
            .chain([&self.side])
    }
}

/// The parsed package manifest.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct PackageManifest {
    /// Always [`PACKAGE_FORMAT`].
    pub format: String,
    /// Format version, at most [`PACKAGE_VERSION`].
    pub version: u32,
    /// Reference camera (also the frame size).
    pub camera: Camera,
    /// Frames per second.
    pub frame_rate: f64,
    /// Number of frames.
    pub frames: u32,
    /// Target number of layers K of the layering.
    pub layers: u32,
    /// The codec of every layer stream.
    pub codec: Codec,
    /// The layout of the layer streams.
    pub layout: Layout,
    /// The total bitrate budget in bits per second, when one was given.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub budget: Option<u64>,
    /// The init segments of the layer streams' fragments (version 4): one per picture size.
    #[serde(default, skip_serializing_if = "Vec::is_empty")]
    pub inits: Vec<FileEntry>,
    /// Where the frames' depth came from, by runs of frames (version 5), where the depth
    /// source says: stereo or the video's own views, and each fallback with its reason.
    #[serde(default, skip_serializing_if = "Vec::is_empty")]
    pub depth: Vec<DepthRun>,
    /// Segments in frame order.
    pub segments: Vec<Segment>,
    /// SHA-256 of this file with this field's digits zeroed (see the module documentation).
    pub checksum: String,
}

/// Consecutive frames whose depth came from the same place.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct DepthRun {
    /// Its first frame.
    pub first: u32,
    /// Its last frame.
    pub last: u32,
    /// Where their depth came from (e.g. `video: 81 % of pixels from 4 views, ...` or
    /// `fallback: the camera only turns; model ...`).
    pub note: String,
}

impl DepthRun {
    /// Whether the frames fell back from the depth asked for.
    pub fn is_fallback(&self) -> bool {
        self.note.starts_with("fallback")
    }
}

/// Why a manifest was rejected.
#[derive(Debug, Error, Clone, PartialEq)]
pub enum PackageManifestError {
    /// Not valid JSON, or not the expected shape.
    #[error("invalid JSON: {0}")]
    Json(String),
    /// The `format` field is not `cpsl-package`.
    #[error("field `format`: expected \"{PACKAGE_FORMAT}\", found \"{0}\"")]
    Format(String),
    /// The version is newer than this build understands (or zero).
    #[error("field `version`: this build reads versions 1..={PACKAGE_VERSION}, found {0}")]
    Version(u32),
    /// The manifest's own checksum does not match its bytes.
    #[error("manifest checksum mismatch (the manifest was modified or damaged)")]
    Checksum,
    /// A field is inconsistent.
    #[error("field `{field}`: {reason}")]
    Field {
        /// The field.
        field: String,
        /// What is wrong.
        reason: String,
    },
}

fn field(field: impl Into<String>, reason: impl Into<String>) -> PackageManifestError {
    PackageManifestError::Field {
        field: field.into(),
        reason: reason.into(),
    }
}

/// Lower-case hex SHA-256 of `bytes`.
pub fn sha256_hex(bytes: &[u8]) -> String {
    Sha256::digest(bytes)
        .iter()
        .map(|b| format!("{b:02x}"))
        .collect()
}

/// Why a package path is unsafe, if it is.
pub fn unsafe_path(path: &str) -> Option<&'static str> {
    if path.is_empty() || path.len() > 255 {
        return Some("must have 1 to 255 characters");
    }
    for c in path.split('/') {
        if c.is_empty() || c == "." || c == ".." {
            return Some("must be relative, without empty, `.` or `..` components");
        }
        if !c
            .bytes()
            .all(|b| b.is_ascii_alphanumeric() || b == b'.' || b == b'_' || b == b'-')
        {
            return Some("may only use A-Z a-z 0-9 . _ - and /");
        }
    }
    None
}

/// The manifest's bytes with the checksum's digits zeroed, and the checksum found, if the
/// `checksum` key occurs exactly once followed by 64 characters and a quote.
fn split_checksum(bytes: &[u8]) -> Option<(Vec<u8>, String)> {
    let key = CHECKSUM_KEY.as_bytes();
    let mut hits = bytes
        .windows(key.len())
        .enumerate()
        .filter(|(_, w)| *w == key);
    let (at, _) = hits.next()?;
    if hits.next().is_some() {
        return None;
    }
    let start = at + key.len();
    let digits = bytes.get(start..start + 64)?;
    if bytes.get(start + 64) != Some(&b'"') {
        return None;
    }
    let found = String::from_utf8(digits.to_vec()).ok()?;
    let mut zeroed = bytes.to_vec();
    zeroed[start..start + 64].fill(b'0');
    Some((zeroed, found))
}

/// Checks a file entry's path (safe, not the manifest's, not used before) and SHA-256;
/// `at` names where it is in the manifest.
fn check_file(
    f: &FileEntry,
    at: &str,
    seen: &mut std::collections::HashSet<String>,
) -> Result<(), PackageManifestError> {
    if let Some(reason) = unsafe_path(&f.path) {
        return Err(field(
            format!("{at}.path"),
            format!("\"{}\" {reason}", f.path),
        ));
    }
    if f.path == MANIFEST_FILE || !seen.insert(f.path.clone()) {
        return Err(field(
            format!("{at}.path"),
            format!("\"{}\" is used twice", f.path),
        ));
    }
    if f.sha256.len() != 64 || !f.sha256.bytes().all(|b| b.is_ascii_hexdigit()) {
        return Err(field(
            format!("{at}.sha256"),
            format!("\"{}\" is not a SHA-256", f.sha256),
        ));
    }
    Ok(())
}

impl PackageManifest {
    /// Parses and checks a manifest: its checksum, shape, format, version, paths and the
    /// consistency of its numbers (segments contiguous from frame 0 and adding up to `frames`,
    /// at least one stream per segment, a positive frame rate, a valid camera).
    pub fn parse(bytes: &[u8]) -> Result<Self, PackageManifestError> {
        cpsl_core::check_head(bytes, PACKAGE_FORMAT, PACKAGE_VERSION).map_err(|e| match e {
            HeadError::Json(m) => PackageManifestError::Json(m),
            HeadError::Format(f) => PackageManifestError::Format(f),
            HeadError::Version(v) => PackageManifestError::Version(v),
        })?;
        let (zeroed, found) = split_checksum(bytes)
            .ok_or_else(|| field("checksum", "missing, repeated or not 64 characters"))?;
        if sha256_hex(&zeroed) != found {
            return Err(PackageManifestError::Checksum);
        }
        let m: PackageManifest =
            serde_json::from_slice(bytes).map_err(|e| PackageManifestError::Json(e.to_string()))?;
        m.check()?;
        Ok(m)
    }

    fn check(&self) -> Result<(), PackageManifestError> {
        self.camera
            .validate()
            .map_err(|e| field("camera", e.to_string()))?;
        if !(self.frame_rate.is_finite() && self.frame_rate > 0.0 && self.frame_rate <= 1000.0) {
            return Err(field(
                "frame_rate",
                format!("{} is not in (0, 1000]", self.frame_rate),
            ));
        }
        let l = &self.layout;
        if l.kind != "colour-over-alpha" || l.pixel_format != "yuv420p" {
            return Err(field("layout", "only colour-over-alpha yuv420p is defined"));
        }
        if l.coded_width != self.camera.width.next_multiple_of(2)
            || l.coded_height != self.camera.height.next_multiple_of(2)
        {
            return Err(field(
                "layout",
                "coded size is not the frame size rounded up to even",
            ));
        }
        let mut next = 0u64;
        let mut seen = std::collections::HashSet::new();
        let fragments = self.version >= FRAGMENT_VERSION;
        if !fragments && !self.inits.is_empty() {
            return Err(field(
                "inits",
                format!("version {} packages have no init segments", self.version),
            ));
        }
        for (i, f) in self.inits.iter().enumerate() {
            check_file(f, &format!("inits[{i}]"), &mut seen)?;
        }
        for (i, s) in self.segments.iter().enumerate() {
            let at = |f: &str| format!("segments[{i}].{f}");
            if s.start as u64 != next || s.frames == 0 {
                return Err(field(
                    at("start"),
                    format!("expected {next} and at least one frame"),
                ));
            }
            next += s.frames as u64;
            if s.streams.is_empty() || s.streams.len() > crate::side::MAX_STREAMS as usize {
                return Err(field(at("streams"), "1 to 64 streams per segment"));
            }
            let allowed = scales_of(self.version);
            if let Some(t) = s.streams.iter().find(|t| !allowed.contains(&t.scale)) {
                let list: Vec<String> = allowed.iter().map(u32::to_string).collect();
                return Err(field(
                    at("scale"),
                    format!(
                        "{} is not one of {} (version {} packages)",
                        t.scale,
                        list.join(", "),
                        self.version
                    ),
                ));
            }
            for (k, t) in s.streams.iter().enumerate() {
                let listed = |p: &String| self.inits.iter().any(|f| &f.path == p);
                match (&t.init, fragments) {
                    (Some(p), true) if listed(p) => {}
                    (Some(p), true) => {
                        return Err(field(
                            at(&format!("streams[{k}].init")),
                            format!("\"{p}\" is not one of the manifest's `inits`"),
                        ))
                    }
                    (None, true) => {
                        return Err(field(
                            at(&format!("streams[{k}].init")),
                            format!("missing (version {} streams are fragments)", self.version),
                        ))
                    }
                    (Some(_), false) => {
                        return Err(field(
                            at(&format!("streams[{k}].init")),
                            format!("version {} streams have no init segment", self.version),
                        ))
                    }
                    (None, false) => {}
                }
            }
            let shared = self.version >= SEGMENT_FRAGMENT_VERSION;
            match (&s.fragment, shared) {
                (None, true) => {
                    return Err(field(
                        at("fragment"),
                        format!(
                            "missing (version {} segments hold their streams in one)",
                            self.version
                        ),
                    ))
                }
                (Some(_), false) => {
                    return Err(field(
                        at("fragment"),
                        format!("version {} segments have none", self.version),
                    ))
                }
                _ => {}
            }
            for (k, t) in s.streams.iter().enumerate() {
                if t.file.is_some() == shared {
                    let why = match shared {
                        true => "a version 6 stream is a run of its segment's `fragment`",
                        false => "missing",
                    };
                    return Err(field(at(&format!("streams[{k}].file")), why));
                }
            }
            for f in s.files() {
                check_file(f, &format!("segments[{i}]"), &mut seen)?;
            }
        }
        if self.segments.is_empty() || next != self.frames as u64 {
            return Err(field(
                "segments",
                format!("cover {next} frames, the package has {}", self.frames),
            ));
        }
        self.check_depth()
    }

    fn check_depth(&self) -> Result<(), PackageManifestError> {
        if self.depth.is_empty() {
            return Ok(());
        }
        if self.version < DEPTH_VERSION {
            return Err(field(
                "depth",
                format!("version {} packages have no depth notes", self.version),
            ));
        }
        let mut next = 0u64;
        for (i, r) in self.depth.iter().enumerate() {
            let at = |f: &str| format!("depth[{i}].{f}");
            if (r.first as u64) < next || r.last < r.first || r.last >= self.frames {
                return Err(field(
                    at("first"),
                    format!(
                        "frames {}-{}: runs are in order, apart, and within the {} frames",
                        r.first, r.last, self.frames
                    ),
                ));
            }
            if r.note.is_empty()
                || r.note.len() > MAX_DEPTH_NOTE
                || r.note.chars().any(char::is_control)
            {
                return Err(field(
                    at("note"),
                    format!("1 to {MAX_DEPTH_NOTE} bytes of printable text"),
                ));
            }
            next = r.last as u64 + 1;
        }
        Ok(())
    }

    /// Serialises as pretty JSON with a valid checksum (the `checksum` field is overwritten).
    pub fn to_json(&self) -> Vec<u8> {
        let mut m = self.clone();
        m.checksum = "0".repeat(64);
        let mut bytes = serde_json::to_vec_pretty(&m).expect("manifest serialises");
        let (zeroed, _) = split_checksum(&bytes).expect("the checksum key occurs once");
        let sum = sha256_hex(&zeroed);
        let key = CHECKSUM_KEY.as_bytes();
        let at = bytes
            .windows(key.len())
            .position(|w| w == key)
            .expect("checksum key")
            + key.len();
        bytes[at..at + 64].copy_from_slice(sum.as_bytes());
        bytes
    }

    /// Every file the manifest references, in order: the init segments, then each
    /// segment's layer streams and side stream.
    pub fn files(&self) -> impl Iterator<Item = &FileEntry> {
        self.inits
            .iter()
            .chain(self.segments.iter().flat_map(Segment::files))
    }

    /// The init segment that goes before `stream`'s fragment, if it has one.
    pub fn init_of(&self, stream: &StreamEntry) -> Option<&FileEntry> {
        let path = stream.init.as_ref()?;
        self.inits.iter().find(|f| &f.path == path)
    }

    /// Total bytes of the segments' layer streams and side streams: what the budget pays for.
    /// The init segments, fetched once per package like the manifest, are not counted.
    pub fn payload_bytes(&self) -> u64 {
        self.segments
            .iter()
            .flat_map(Segment::files)
            .map(|f| f.bytes)
            .sum()
    }

    /// Mean total bitrate in bits per second.
    pub fn bitrate(&self) -> f64 {
        self.payload_bytes() as f64 * 8.0 * self.frame_rate / self.frames.max(1) as f64
    }

    /// The segment holding frame `frame`.
    pub fn segment_of(&self, frame: u32) -> Option<usize> {
        self.segments
            .iter()
            .position(|s| (s.start..s.start + s.frames).contains(&frame))
    }
}
