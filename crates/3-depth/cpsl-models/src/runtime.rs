//! Locating and loading ONNX Runtime.

use crate::error::ModelError;
use ort::session::Session;
use std::path::{Path, PathBuf};
use std::sync::OnceLock;

/// File name of the runtime library that `scripts/setup-models.sh` installs.
pub const ORT_LIBRARY: &str = "libonnxruntime.so.1.31.1";

/// The model cache: `$CPSL_CACHE`, else `$HOME/.cache/cpsl`.
pub fn cache_dir() -> PathBuf {
    match std::env::var_os("CPSL_CACHE") {
        Some(p) => PathBuf::from(p),
        None => std::env::var_os("HOME")
            .map(PathBuf::from)
            .unwrap_or_else(|| PathBuf::from("."))
            .join(".cache/cpsl"),
    }
}

/// Where the runtime library is looked for: `ORT_DYLIB_PATH`, else the cache.
pub fn library_path() -> PathBuf {
    std::env::var_os("ORT_DYLIB_PATH")
        .map(PathBuf::from)
        .unwrap_or_else(|| cache_dir().join("onnxruntime").join(ORT_LIBRARY))
}

static ENV: OnceLock<Result<ort::environment::Environment, String>> = OnceLock::new();

/// The process-wide ONNX Runtime environment, loading the library on first use.
pub fn environment() -> Result<&'static ort::environment::Environment, ModelError> {
    ENV.get_or_init(|| {
        let path = library_path();
        if !path.is_file() {
            return Err(format!("{} does not exist", path.display()));
        }
        ort::init_from(&path)
            .map_err(|e| format!("{}: {e}", path.display()))?
            .with_name("cpsl")
            .build()
            .map_err(|e| format!("{}: {e}", path.display()))
    })
    .as_ref()
    .map_err(|e| ModelError::Runtime(e.clone()))
}

/// A session loaded from `path` in the process-wide environment. Its threads block as soon as
/// a run ends instead of spinning for more work: the layering's own threads need the cores
/// between two runs (`cpsl layer-video` on the fox: 10 % less CPU time, 3-7 % less wall time).
pub(crate) fn session(path: &Path) -> Result<Session, ModelError> {
    let env = environment()?;
    Session::builder(env)
        .and_then(|b| Ok(b.with_intra_op_spinning(false)?))
        .and_then(|mut b| b.commit_from_file(path))
        .map_err(|e| ModelError::Model {
            path: path.into(),
            reason: e.to_string(),
        })
}

/// True when the runtime library can be loaded (used by tests to report what they skip).
pub fn available() -> bool {
    environment().is_ok()
}
