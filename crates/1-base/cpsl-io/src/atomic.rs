//! Atomic writes of files and folders: everything is built under a hidden sibling name
//! (`.NAME.<pid>-<nanos>.partial`) and renamed into place when complete, so a reader never sees
//! half an output and an interrupted or failed write leaves nothing behind.

use crate::error::IoError;
use std::fs;
use std::path::{Path, PathBuf};

/// A file or folder being written next to its final location. Dropping it without
/// [`Staged::commit`] removes everything written so far.
#[derive(Debug)]
pub struct Staged {
    tmp: PathBuf,
    target: PathBuf,
    folder: bool,
    committed: bool,
}

fn unique_suffix() -> String {
    let nanos = std::time::SystemTime::now()
        .duration_since(std::time::UNIX_EPOCH)
        .map(|d| d.subsec_nanos())
        .unwrap_or(0);
    format!("{}-{nanos}", std::process::id())
}

/// `.NAME.<pid>-<nanos>.<what>` beside `target`.
fn sibling(target: &Path, what: &str) -> PathBuf {
    let name = target
        .file_name()
        .map(|n| n.to_string_lossy().into_owned())
        .unwrap_or_else(|| "out".into());
    target.with_file_name(format!(".{name}.{}.{what}", unique_suffix()))
}

impl Staged {
    /// Starts staging the folder `target` (an empty folder is created to write into).
    /// `replaceable` decides whether an existing `target` may be replaced on commit; it is
    /// checked now, before any work, and again at commit.
    pub fn folder(target: &Path, replaceable: impl Fn(&Path) -> bool) -> Result<Self, IoError> {
        let stage = Self::start(target, true, replaceable)?;
        fs::create_dir(&stage.tmp).map_err(|e| IoError::io(&stage.tmp, e))?;
        Ok(stage)
    }

    /// Starts staging the file `target`: write it at [`Staged::path`].
    pub fn file(target: &Path, replaceable: impl Fn(&Path) -> bool) -> Result<Self, IoError> {
        Self::start(target, false, replaceable)
    }

    fn start(
        target: &Path,
        folder: bool,
        replaceable: impl Fn(&Path) -> bool,
    ) -> Result<Self, IoError> {
        if target.exists() && !replaceable(target) {
            return Err(IoError::TargetExists {
                path: target.to_path_buf(),
            });
        }
        let target = match target.parent() {
            Some(p) if !p.as_os_str().is_empty() => target.to_path_buf(),
            _ => Path::new(".").join(target),
        };
        let parent = target.parent().expect("joined to a folder");
        fs::create_dir_all(parent).map_err(|e| IoError::io(parent, e))?;
        Ok(Self {
            tmp: sibling(&target, "partial"),
            target,
            folder,
            committed: false,
        })
    }

    /// Where to write: the temporary folder or file.
    pub fn path(&self) -> &Path {
        &self.tmp
    }

    /// Writes one file into the staged folder and flushes it to disk.
    pub fn write_file(&self, name: &str, bytes: &[u8]) -> Result<(), IoError> {
        use std::io::Write;
        let p = self.tmp.join(name);
        let mut f = fs::File::create(&p).map_err(|e| IoError::io(&p, e))?;
        f.write_all(bytes).map_err(|e| IoError::io(&p, e))?;
        f.sync_all().map_err(|e| IoError::io(&p, e))
    }

    /// Moves the staged output into place, replacing an existing target if `replaceable`
    /// allows it.
    pub fn commit(mut self, replaceable: impl Fn(&Path) -> bool) -> Result<(), IoError> {
        let target = self.target.clone();
        if target.exists() && !replaceable(&target) {
            return Err(IoError::TargetExists { path: target });
        }
        // A file is replaced by the rename itself; a folder is first moved aside.
        let old = if self.folder && target.exists() {
            let old = sibling(&target, "old");
            fs::rename(&target, &old).map_err(|e| IoError::io(&target, e))?;
            Some(old)
        } else {
            None
        };
        if let Err(e) = fs::rename(&self.tmp, &target) {
            if let Some(old) = &old {
                let _ = fs::rename(old, &target);
            }
            return Err(IoError::io(&target, e));
        }
        self.committed = true;
        if let Some(old) = old {
            let _ = fs::remove_dir_all(old);
        }
        if let Ok(d) = fs::File::open(target.parent().expect("joined to a folder")) {
            let _ = d.sync_all();
        }
        Ok(())
    }
}

impl Drop for Staged {
    fn drop(&mut self) {
        if !self.committed {
            let _ = match self.folder {
                true => fs::remove_dir_all(&self.tmp),
                false => fs::remove_file(&self.tmp),
            };
        }
    }
}

/// Writes a file via a staged sibling and a rename, so readers never see a partial file.
pub fn write_file_atomic(path: &Path, bytes: &[u8]) -> Result<(), IoError> {
    let stage = Staged::file(path, |_| true)?;
    fs::write(stage.path(), bytes).map_err(|e| IoError::io(stage.path(), e))?;
    stage.commit(|_| true)
}

/// Writes `value` as pretty JSON, atomically ([`write_file_atomic`]).
pub fn write_json(path: &Path, value: &impl serde::Serialize) -> Result<(), IoError> {
    let json = serde_json::to_string_pretty(value)
        .map_err(|e| IoError::io(path, std::io::Error::other(e)))?;
    write_file_atomic(path, json.as_bytes())
}

#[cfg(test)]
mod tests {
    use super::*;

    fn entries(dir: &Path) -> Vec<String> {
        let mut v: Vec<String> = fs::read_dir(dir)
            .unwrap()
            .map(|e| e.unwrap().file_name().to_string_lossy().into_owned())
            .collect();
        v.sort();
        v
    }

    #[test]
    fn folders_and_files_appear_whole_or_not_at_all() {
        let dir = tempfile::tempdir().unwrap();
        let out = dir.path().join("out");
        // Dropped before commit: nothing is left.
        let stage = Staged::folder(&out, |_| true).unwrap();
        stage.write_file("a", b"1").unwrap();
        assert!(!out.exists());
        drop(stage);
        assert!(entries(dir.path()).is_empty());
        // Committed: in place, replacing the previous folder.
        for content in [b"1", b"2"] {
            let stage = Staged::folder(&out, |_| true).unwrap();
            stage.write_file("a", content).unwrap();
            stage.commit(|_| true).unwrap();
        }
        assert_eq!(fs::read(out.join("a")).unwrap(), b"2");
        assert_eq!(entries(dir.path()), ["out"]);
        // Not replaceable: refused up front, and at commit if it appeared meanwhile.
        assert!(matches!(
            Staged::folder(&out, |_| false),
            Err(IoError::TargetExists { .. })
        ));
        let late = dir.path().join("late");
        let stage = Staged::file(&late, |p| !p.exists()).unwrap();
        fs::write(stage.path(), b"new").unwrap();
        fs::write(&late, b"theirs").unwrap();
        assert!(stage.commit(|p| !p.exists()).is_err());
        assert_eq!(fs::read(&late).unwrap(), b"theirs");
        write_file_atomic(&late, b"mine").unwrap();
        assert_eq!(fs::read(&late).unwrap(), b"mine");
        write_json(&late, &[1, 2]).unwrap();
        assert_eq!(fs::read_to_string(&late).unwrap(), "[\n  1,\n  2\n]");
        assert_eq!(entries(dir.path()), ["late", "out"]);
    }
}
