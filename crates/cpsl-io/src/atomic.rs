//! Atomic directory writes: build in a sibling temporary directory, then rename into place.

use crate::error::IoError;
use std::fs;
use std::path::{Path, PathBuf};

/// A directory being written next to its final location. Dropping it without
/// [`StagedDir::commit`] removes everything written so far.
#[derive(Debug)]
pub struct StagedDir {
    tmp: PathBuf,
    target: PathBuf,
    committed: bool,
}

fn unique_suffix() -> String {
    let nanos = std::time::SystemTime::now()
        .duration_since(std::time::UNIX_EPOCH)
        .map(|d| d.subsec_nanos())
        .unwrap_or(0);
    format!("{}-{nanos}", std::process::id())
}

impl StagedDir {
    /// Starts staging `target`. `replaceable` decides whether an existing `target` may be
    /// replaced on commit; it is checked now, before any work, and again at commit.
    pub fn new(target: &Path, replaceable: impl Fn(&Path) -> bool) -> Result<Self, IoError> {
        if target.exists() && !replaceable(target) {
            return Err(IoError::TargetExists {
                path: target.to_path_buf(),
            });
        }
        let parent = match target.parent() {
            Some(p) if !p.as_os_str().is_empty() => p.to_path_buf(),
            _ => PathBuf::from("."),
        };
        fs::create_dir_all(&parent).map_err(|e| IoError::io(&parent, e))?;
        let name = target
            .file_name()
            .map(|n| n.to_string_lossy().into_owned())
            .unwrap_or_else(|| "out".into());
        let tmp = parent.join(format!(".{name}.tmp-{}", unique_suffix()));
        fs::create_dir(&tmp).map_err(|e| IoError::io(&tmp, e))?;
        Ok(Self {
            tmp,
            target: target.to_path_buf(),
            committed: false,
        })
    }

    /// The temporary directory to write into.
    pub fn path(&self) -> &Path {
        &self.tmp
    }

    /// Writes one file into the staged directory and flushes it to disk.
    pub fn write_file(&self, name: &str, bytes: &[u8]) -> Result<(), IoError> {
        use std::io::Write;
        let p = self.tmp.join(name);
        let mut f = fs::File::create(&p).map_err(|e| IoError::io(&p, e))?;
        f.write_all(bytes).map_err(|e| IoError::io(&p, e))?;
        f.sync_all().map_err(|e| IoError::io(&p, e))
    }

    /// Moves the staged directory into place, replacing an existing target.
    pub fn commit(mut self) -> Result<(), IoError> {
        let target = self.target.clone();
        let old = if target.exists() {
            let name = target.file_name().unwrap_or_default().to_string_lossy();
            let old = target.with_file_name(format!(".{name}.old-{}", unique_suffix()));
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
        if let Some(parent) = target.parent() {
            if let Ok(d) = fs::File::open(if parent.as_os_str().is_empty() {
                Path::new(".")
            } else {
                parent
            }) {
                let _ = d.sync_all();
            }
        }
        Ok(())
    }
}

impl Drop for StagedDir {
    fn drop(&mut self) {
        if !self.committed {
            let _ = fs::remove_dir_all(&self.tmp);
        }
    }
}
