//! The single-file form of a package: an uncompressed POSIX tar of the package directory,
//! the manifest first, then every file the manifest lists in segment order. The layer streams
//! are already compressed, so the archive stores them as they are; deterministic headers
//! (mode 0644, time 0, no owner) make the same package give the same archive bytes.
//!
//! Reading extracts the archive into a private temporary folder that lives as long as the
//! opened [`crate::Package`]: only regular files with plain relative names (no `..`, no
//! absolute paths, no links, nothing twice) come out, and the manifest's checksums are then
//! checked as for a directory.

use crate::{Package, PackageError, MANIFEST_FILE};
use std::io::{Read, Write};
use std::path::{Component, Path, PathBuf};

/// Most bytes an archive may unpack to (1 TiB); each entry is also bounded by the archive's
/// own size.
const MAX_UNPACKED: u64 = 1 << 40;

fn io(path: &Path) -> impl FnOnce(std::io::Error) -> PackageError + '_ {
    move |source| PackageError::Io {
        path: path.to_path_buf(),
        source,
    }
}

fn bad(path: &Path, reason: impl Into<String>) -> PackageError {
    PackageError::Mismatch {
        path: path.to_path_buf(),
        reason: reason.into(),
    }
}

/// Whether `path` is a package archive: a file whose first tar entry is the package manifest.
pub fn is_archive(path: &Path) -> bool {
    let mut head = [0u8; 512];
    let Ok(mut f) = std::fs::File::open(path) else {
        return false;
    };
    if !path.is_file() || f.read_exact(&mut head).is_err() {
        return false;
    }
    let name = &head[..100];
    let name = &name[..name.iter().position(|&b| b == 0).unwrap_or(100)];
    name == MANIFEST_FILE.as_bytes() && &head[257..262] == b"ustar"
}

/// Writes the package at `root` (checked completely first: manifest, every file, every side
/// stream) as one archive at `out`, through a temporary sibling renamed into place. An
/// existing archive at `out` is replaced; anything else there is left alone. Returns the
/// archive's size in bytes.
pub fn pack(root: &Path, out: &Path) -> Result<u64, PackageError> {
    let pkg = Package::open(root)?;
    if let Some(first) = pkg.verify().into_iter().next() {
        return Err(first);
    }
    if out.exists() && !is_archive(out) {
        return Err(bad(
            out,
            "exists and is not a package archive; not replacing it",
        ));
    }
    let stage = cpsl_io::Staged::file(out, is_archive)?;
    let tmp = stage.path();
    let file = std::fs::File::create(tmp).map_err(io(tmp))?;
    let mut tar = tar::Builder::new(std::io::BufWriter::new(file));
    tar.mode(tar::HeaderMode::Deterministic);
    let files = pkg.manifest().files().map(|f| f.path.as_str());
    for rel in std::iter::once(MANIFEST_FILE).chain(files) {
        let path = root.join(rel);
        let bytes = std::fs::read(&path).map_err(io(&path))?;
        let mut header = tar::Header::new_ustar();
        header.set_size(bytes.len() as u64);
        header.set_mode(0o644);
        header.set_mtime(0);
        header.set_entry_type(tar::EntryType::Regular);
        tar.append_data(&mut header, rel, bytes.as_slice())
            .map_err(io(&path))?;
    }
    let mut w = tar.into_inner().map_err(io(tmp))?;
    w.flush().map_err(io(tmp))?;
    w.into_inner()
        .map_err(|e| PackageError::Io {
            path: tmp.to_path_buf(),
            source: e.into_error(),
        })?
        .sync_all()
        .map_err(io(tmp))?;
    stage.commit(is_archive)?;
    std::fs::metadata(out).map(|m| m.len()).map_err(io(out))
}

/// Extracts the archive at `archive` into the empty folder `dest` (see the module
/// documentation for what is refused).
pub fn unpack(archive: &Path, dest: &Path) -> Result<(), PackageError> {
    let file = std::fs::File::open(archive).map_err(io(archive))?;
    let size = file.metadata().map_err(io(archive))?.len();
    let mut tar = tar::Archive::new(std::io::BufReader::new(file));
    let mut seen = std::collections::HashSet::new();
    let mut total = 0u64;
    for entry in tar.entries().map_err(io(archive))? {
        let mut entry = entry.map_err(io(archive))?;
        let rel: PathBuf = entry.path().map_err(io(archive))?.into_owned();
        let shown = archive.join(&rel);
        if entry.header().entry_type() != tar::EntryType::Regular {
            return Err(bad(&shown, "archive entry is not a regular file"));
        }
        // The manifest's own rule for file paths, and no hidden names.
        let plain = rel.components().all(|c| matches!(c, Component::Normal(_)))
            && rel.to_str().is_some_and(|s| {
                crate::unsafe_path(s).is_none() && !s.split('/').any(|c| c.starts_with('.'))
            });
        if !plain {
            return Err(bad(
                &shown,
                "archive entry name is not a plain relative path",
            ));
        }
        if !seen.insert(rel.clone()) {
            return Err(bad(&shown, "archive entry appears twice"));
        }
        let len = entry.header().size().map_err(io(archive))?;
        total = total.saturating_add(len);
        if len > size || total > MAX_UNPACKED {
            return Err(bad(
                &shown,
                "archive entry is larger than the archive allows",
            ));
        }
        let path = dest.join(&rel);
        if let Some(parent) = path.parent() {
            std::fs::create_dir_all(parent).map_err(io(parent))?;
        }
        let mut out = std::fs::File::create_new(&path).map_err(io(&path))?;
        let copied = std::io::copy(&mut (&mut entry).take(len), &mut out).map_err(io(&path))?;
        if copied != len {
            return Err(bad(&shown, "archive entry is truncated"));
        }
    }
    if !seen.contains(Path::new(MANIFEST_FILE)) {
        return Err(bad(archive, "the archive has no manifest.json"));
    }
    Ok(())
}

#[cfg(test)]
mod tests {
    use super::*;

    /// An archive entry: name, kind, contents.
    type Entry<'a> = (&'a str, tar::EntryType, &'a [u8]);

    /// A tar with raw entry names (the builder itself refuses hostile ones).
    fn raw_tar(entries: &[Entry<'_>]) -> Vec<u8> {
        let mut out = Vec::new();
        for (name, kind, data) in entries {
            let mut h = tar::Header::new_ustar();
            h.as_mut_bytes()[..name.len()].copy_from_slice(name.as_bytes());
            h.set_size(data.len() as u64);
            h.set_mode(0o644);
            h.set_entry_type(*kind);
            if *kind == tar::EntryType::Symlink {
                h.set_link_name("/etc/passwd").unwrap();
            }
            h.set_cksum();
            out.extend_from_slice(h.as_bytes());
            out.extend_from_slice(data);
            out.resize(out.len().div_ceil(512) * 512, 0);
        }
        out.resize(out.len() + 1024, 0);
        out
    }

    #[test]
    fn hostile_archives_are_refused_and_write_nothing_outside() {
        let d = tempfile::tempdir().unwrap();
        let manifest = (MANIFEST_FILE, tar::EntryType::Regular, &b"{}"[..]);
        let cases: Vec<(Vec<Entry<'_>>, &str)> = vec![
            (
                vec![manifest, ("../evil", tar::EntryType::Regular, b"x")],
                "plain",
            ),
            (
                vec![manifest, ("/tmp/evil", tar::EntryType::Regular, b"x")],
                "plain",
            ),
            (
                vec![manifest, ("seg/../../evil", tar::EntryType::Regular, b"x")],
                "plain",
            ),
            (
                vec![manifest, (".hidden", tar::EntryType::Regular, b"x")],
                "plain",
            ),
            (
                vec![manifest, ("link", tar::EntryType::Symlink, b"")],
                "regular",
            ),
            (
                vec![manifest, ("dir", tar::EntryType::Directory, b"")],
                "regular",
            ),
            (vec![manifest, manifest], "twice"),
            (
                vec![("seg/a.mp4", tar::EntryType::Regular, b"x")],
                "no manifest",
            ),
        ];
        for (i, (entries, want)) in cases.iter().enumerate() {
            let archive = d.path().join(format!("a{i}.cpsl"));
            std::fs::write(&archive, raw_tar(entries)).unwrap();
            let dest = d.path().join(format!("out{i}"));
            std::fs::create_dir(&dest).unwrap();
            let e = unpack(&archive, &dest).unwrap_err().to_string();
            assert!(e.contains(want), "case {i}: {e}");
        }
        assert!(!d.path().join("evil").exists());
        assert!(!Path::new("/tmp/evil").exists());
        // A truncated archive is an error, not a panic.
        let mut bytes = raw_tar(&[(MANIFEST_FILE, tar::EntryType::Regular, &[b'{'; 3000])]);
        bytes.truncate(1200);
        let archive = d.path().join("cut.cpsl");
        std::fs::write(&archive, bytes).unwrap();
        let dest = d.path().join("cut");
        std::fs::create_dir(&dest).unwrap();
        assert!(unpack(&archive, &dest).is_err());
        // Not an archive at all.
        let plain = d.path().join("plain.cpsl");
        std::fs::write(&plain, b"hello").unwrap();
        assert!(!is_archive(&plain));
        assert!(Package::open(&plain).is_err());
    }
}
