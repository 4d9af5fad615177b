//! The package listing: every package under the root (a few folders deep, symbolic links
//! not followed) and every variant set.

use cpsl_package::{is_package, Package, VARIANTS_FILE};
use serde::{Deserialize, Serialize};
use std::path::Path;

/// Folders searched below the root.
const DEPTH: usize = 3;

/// One package as the listing shows it.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct PackageSummary {
    /// Path under the root, `/`-separated.
    pub path: String,
    /// URL of the package folder on this server.
    pub url: String,
    /// Frame size.
    pub width: u32,
    /// Frame size.
    pub height: u32,
    /// Frames.
    pub frames: u32,
    /// Frames per second.
    pub frame_rate: f64,
    /// Codec name.
    pub codec: String,
    /// Segments.
    pub segments: usize,
    /// Mean bits per second of all its files.
    pub bitrate: u64,
}

/// The listing answered by `/api/packages`.
#[derive(Debug, Clone, Default, PartialEq, Serialize, Deserialize)]
pub struct Listing {
    /// Packages, by path.
    pub packages: Vec<PackageSummary>,
    /// URLs of variant sets.
    pub variant_sets: Vec<String>,
}

fn summarise(root: &Path, dir: &Path) -> Option<PackageSummary> {
    let rel = dir.strip_prefix(root).ok()?.to_str()?.replace('\\', "/");
    let pkg = Package::open(dir).ok()?;
    let m = pkg.manifest();
    let bytes = m.payload_bytes();
    let seconds = m.frames as f64 / m.frame_rate;
    Some(PackageSummary {
        url: format!("/files/{rel}/"),
        path: rel,
        width: m.camera.width,
        height: m.camera.height,
        frames: m.frames,
        frame_rate: m.frame_rate,
        codec: m.codec.name().to_string(),
        segments: m.segments.len(),
        bitrate: (bytes as f64 * 8.0 / seconds.max(1e-9)).round() as u64,
    })
}

/// Lists the packages and variant sets under `root` (canonical), sorted by path.
pub fn list_packages(root: &Path) -> Listing {
    let mut out = Listing::default();
    let mut stack = vec![(root.to_path_buf(), 0usize)];
    while let Some((dir, depth)) = stack.pop() {
        if dir != root && is_package(&dir) {
            out.packages.extend(summarise(root, &dir));
            continue;
        }
        let Ok(entries) = std::fs::read_dir(&dir) else {
            continue;
        };
        for e in entries.flatten() {
            let name = e.file_name();
            let Some(name) = name.to_str() else { continue };
            if name.starts_with('.') {
                continue;
            }
            // `file_type` does not follow symbolic links: links are never listed.
            let Ok(t) = e.file_type() else { continue };
            if t.is_dir() && depth < DEPTH {
                stack.push((e.path(), depth + 1));
            } else if t.is_file() && name == VARIANTS_FILE {
                if let Some(rel) = e.path().strip_prefix(root).ok().and_then(|p| p.to_str()) {
                    out.variant_sets
                        .push(format!("/files/{}", rel.replace('\\', "/")));
                }
            }
        }
    }
    out.packages.sort_by(|a, b| a.path.cmp(&b.path));
    out.variant_sets.sort();
    out
}

/// URLs of every file of a listed package: its manifest, its init segments, then each
/// segment's streams and side stream.
pub fn package_urls(root: &Path, p: &PackageSummary) -> Vec<String> {
    let Ok(pkg) = Package::open(&root.join(&p.path)) else {
        return Vec::new();
    };
    let mut out = vec![format!("{}manifest.json", p.url)];
    out.extend(
        pkg.manifest()
            .inits
            .iter()
            .map(|f| format!("{}{}", p.url, f.path)),
    );
    for s in &pkg.manifest().segments {
        out.extend(s.files().map(|f| format!("{}{}", p.url, f.path)));
    }
    out
}
