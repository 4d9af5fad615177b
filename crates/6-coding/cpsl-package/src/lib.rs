//! The CPSL package (`.cpsl`): a directory that any HTTP server or CDN can serve as static
//! files.
//!
//! ```text
//! clip.cpsl/
//!   manifest.json                 format, version, camera, frame rate, codec, layout, budget,
//!                                 per segment: streams (path, bytes, SHA-256, bitrate, track)
//!   seg_000000/layer_00.mp4       one MP4 per layer stream and segment (colour over alpha)
//!   seg_000000/layer_01.mp4 ...
//!   seg_000000/side.bin           side stream: EDC, layer depths, confidence, refresh flags
//!   seg_000001/...
//! ```
//!
//! The same package can also travel as one file, an uncompressed tar of that directory
//! ([`pack`]); [`Package::open`] reads either form.
//!
//! A segment is one group of pictures: it starts with an I-frame and decodes without any other
//! segment, so a player can start or seek at any segment and a cache can keep segments as
//! immutable objects. This crate reads and checks packages and writes manifests and side
//! streams; the layer streams themselves are coded by `cpsl-codec`.

mod archive;
mod manifest;
mod side;
mod variants;

pub use archive::{is_archive, pack, unpack};
pub use manifest::{
    scales_of, sha256_hex, unsafe_path, version_for, Codec, DepthRun, FileEntry, Layout,
    PackageManifest, PackageManifestError, Segment, StreamEntry, DEPTH_VERSION, FRAGMENT_VERSION,
    MANIFEST_FILE, MAX_DEPTH_NOTE, PACKAGE_FORMAT, PACKAGE_VERSION, SEGMENT_FRAGMENT_VERSION,
};
pub use side::{
    geometry_bytes, summarise_edc, SideError, SideFrame, SideLayer, SideStream, GRID_STEP,
    MAX_SEGMENT_FRAMES, MAX_STREAMS, SIDE_MAGIC, SIDE_VERSION,
};
pub use variants::{VariantSet, VARIANTS_FILE, VARIANTS_FORMAT};

use std::path::{Path, PathBuf};
use std::sync::Arc;
use thiserror::Error;

/// Errors of reading a package.
#[derive(Debug, Error)]
pub enum PackageError {
    /// A file could not be read.
    #[error("cannot read {path}: {source}")]
    Io {
        /// The file.
        path: PathBuf,
        /// The cause.
        source: std::io::Error,
    },
    /// The manifest is invalid.
    #[error("{path}: {source}")]
    Manifest {
        /// The manifest file.
        path: PathBuf,
        /// What is wrong.
        source: PackageManifestError,
    },
    /// A file does not match its manifest entry.
    #[error("{path}: {reason}")]
    Mismatch {
        /// The file.
        path: PathBuf,
        /// What differs.
        reason: String,
    },
    /// A side stream is invalid or does not fit its segment.
    #[error("{path}: {reason}")]
    Side {
        /// The side-stream file.
        path: PathBuf,
        /// What is wrong.
        reason: String,
    },
    /// Writing an output failed.
    #[error(transparent)]
    Write(#[from] cpsl_io::IoError),
}

/// An opened package: its root and checked manifest.
#[derive(Debug, Clone)]
pub struct Package {
    root: PathBuf,
    /// What was opened (the folder, or the archive file): how files are named in messages.
    opened: PathBuf,
    manifest: PackageManifest,
    /// Where an archive was unpacked (removed when the last clone is dropped).
    _unpacked: Option<Arc<tempfile::TempDir>>,
}

/// Whether `path` looks like a package: a directory with a package manifest, or a package
/// archive ([`pack`]).
pub fn is_package(path: &Path) -> bool {
    if is_archive(path) {
        return true;
    }
    std::fs::read(path.join(MANIFEST_FILE))
        .map(|b| {
            serde_json::from_slice::<serde_json::Value>(&b)
                .is_ok_and(|v| v["format"] == PACKAGE_FORMAT)
        })
        .unwrap_or(false)
}

impl Package {
    /// Opens a package directory, or a package archive (unpacked into a private temporary
    /// folder), and checks its manifest (files are checked when read).
    pub fn open(root: &Path) -> Result<Self, PackageError> {
        if root.is_file() {
            if !is_archive(root) {
                return Err(PackageError::Mismatch {
                    path: root.to_path_buf(),
                    reason: "a file that is not a package archive".into(),
                });
            }
            let dir = tempfile::Builder::new()
                .prefix("cpsl-package-")
                .tempdir()
                .map_err(|source| PackageError::Io {
                    path: std::env::temp_dir(),
                    source,
                })?;
            unpack(root, dir.path())?;
            let mut pkg = Self::open_folder(dir.path(), root)?;
            pkg._unpacked = Some(Arc::new(dir));
            return Ok(pkg);
        }
        Self::open_folder(root, root)
    }

    /// Opens the package folder `root`, naming its files under `opened` in messages.
    fn open_folder(root: &Path, opened: &Path) -> Result<Self, PackageError> {
        let bytes = std::fs::read(root.join(MANIFEST_FILE)).map_err(|source| PackageError::Io {
            path: opened.join(MANIFEST_FILE),
            source,
        })?;
        let manifest = PackageManifest::parse(&bytes).map_err(|source| PackageError::Manifest {
            path: opened.join(MANIFEST_FILE),
            source,
        })?;
        Ok(Self {
            root: root.to_path_buf(),
            opened: opened.to_path_buf(),
            manifest,
            _unpacked: None,
        })
    }

    /// The manifest.
    pub fn manifest(&self) -> &PackageManifest {
        &self.manifest
    }

    /// The package root (for an archive, the private folder it was unpacked into).
    pub fn root(&self) -> &Path {
        &self.root
    }

    /// What was opened: the package folder or the archive file.
    pub fn opened(&self) -> &Path {
        &self.opened
    }

    /// Where a file of the package lies.
    pub fn path_of(&self, f: &FileEntry) -> PathBuf {
        self.root.join(&f.path)
    }

    /// How a file of the package is named in messages: its path in the folder, or for an
    /// archive `ARCHIVE/member` (never the private folder it was unpacked into).
    pub fn display_path(&self, f: &FileEntry) -> PathBuf {
        self.opened.join(&f.path)
    }

    /// Reads one file and checks its size and SHA-256 against the manifest. Symbolic links
    /// are refused so that a package cannot point outside itself.
    pub fn read(&self, f: &FileEntry) -> Result<Vec<u8>, PackageError> {
        let path = self.path_of(f);
        let io = |source| PackageError::Io {
            path: self.display_path(f),
            source,
        };
        let meta = std::fs::symlink_metadata(&path).map_err(io)?;
        let mismatch = |reason: String| PackageError::Mismatch {
            path: self.display_path(f),
            reason,
        };
        if !meta.is_file() {
            return Err(mismatch("not a regular file".into()));
        }
        if meta.len() != f.bytes {
            return Err(mismatch(format!(
                "{} bytes, the manifest says {}",
                meta.len(),
                f.bytes
            )));
        }
        let bytes = std::fs::read(&path).map_err(io)?;
        if sha256_hex(&bytes) != f.sha256 {
            return Err(mismatch("SHA-256 differs from the manifest".into()));
        }
        Ok(bytes)
    }

    /// Reads and checks segment `i`'s side stream against its segment: number, first frame,
    /// frame count, stream count and frame size.
    pub fn side_stream(&self, i: usize) -> Result<SideStream, PackageError> {
        let seg = &self.manifest.segments[i];
        let bytes = self.read(&seg.side)?;
        let path = self.display_path(&seg.side);
        let side = SideStream::decode(&bytes).map_err(|e| PackageError::Side {
            path: path.clone(),
            reason: e.to_string(),
        })?;
        let cam = &self.manifest.camera;
        let expected = (
            i as u32,
            seg.start,
            seg.frames as usize,
            seg.streams.len(),
            cam.width,
            cam.height,
        );
        let found = (
            side.segment,
            side.start,
            side.frames.len(),
            side.streams as usize,
            side.width,
            side.height,
        );
        if expected != found {
            return Err(PackageError::Side {
                path,
                reason: format!(
                    "(segment, start, frames, streams, width, height) = {found:?}, the manifest says {expected:?}"
                ),
            });
        }
        Ok(side)
    }

    /// Checks every part of the package: the manifest (its checksum and consistency), every
    /// file's presence, size and SHA-256, and every side stream. Returns every problem found
    /// (empty when the package is intact).
    pub fn verify(&self) -> Vec<PackageError> {
        let mut problems = Vec::new();
        for f in &self.manifest.inits {
            if let Err(e) = self.read(f) {
                problems.push(e);
            }
        }
        for (i, seg) in self.manifest.segments.iter().enumerate() {
            for f in seg
                .streams
                .iter()
                .filter_map(|t| t.file.as_ref())
                .chain(&seg.fragment)
            {
                if let Err(e) = self.read(f) {
                    problems.push(e);
                }
            }
            if let Err(e) = self.side_stream(i) {
                problems.push(e);
            }
        }
        problems
    }
}

/// A file entry for `rel` under `root`, with its size and SHA-256.
pub fn file_entry(root: &Path, rel: &str) -> Result<FileEntry, PackageError> {
    let path = root.join(rel);
    let bytes = std::fs::read(&path).map_err(|source| PackageError::Io { path, source })?;
    Ok(FileEntry {
        path: rel.to_string(),
        bytes: bytes.len() as u64,
        sha256: sha256_hex(&bytes),
    })
}

/// The folder of segment `i` inside a package.
pub fn segment_dir(i: usize) -> String {
    format!("seg_{i:06}")
}
