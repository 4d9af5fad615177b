//! Helpers shared by the CLI test binaries.
#![allow(dead_code)] // each test binary uses its own subset

use std::path::{Path, PathBuf};
use std::process::{Command, Output};

/// Runs the `cpsl` binary.
pub fn cpsl(args: &[&str]) -> Output {
    Command::new(env!("CARGO_BIN_EXE_cpsl"))
        .args(args)
        .output()
        .expect("cpsl runs")
}

/// Runs `cpsl`, asserts success and returns its stdout.
pub fn ok(args: &[&str]) -> String {
    let o = cpsl(args);
    assert!(
        o.status.success(),
        "cpsl {args:?} failed: {}",
        String::from_utf8_lossy(&o.stderr)
    );
    String::from_utf8_lossy(&o.stdout).into_owned()
}

/// Runs `cpsl`, asserts failure with `fragment` in its error, each cause said once (no run
/// of `": "`-separated parts repeats right after itself).
pub fn fails(args: &[&str], fragment: &str) {
    let o = cpsl(args);
    let err = String::from_utf8_lossy(&o.stderr);
    assert!(!o.status.success(), "cpsl {args:?} should fail");
    assert!(
        err.contains(fragment),
        "cpsl {args:?}: {err:?} lacks {fragment:?}"
    );
    // Each cause once: no run of ": "-separated parts repeats right after itself.
    let line = err.lines().find(|l| l.starts_with("error: ")).unwrap();
    let parts: Vec<&str> = line.split(": ").collect();
    for len in 1..=parts.len() / 2 {
        for i in 0..=parts.len() - 2 * len {
            assert!(
                parts[i..i + len] != parts[i + len..i + 2 * len],
                "cpsl {args:?}: {line:?} repeats {:?}",
                parts[i..i + len].join(": ")
            );
        }
    }
}

/// A path as `&str`.
pub fn s(p: &Path) -> &str {
    p.to_str().unwrap()
}

/// Whether the model cache holds ONNX Runtime and every file in `models` (relative to
/// `$CPSL_CACHE/models`); fails instead when `CPSL_REQUIRE_MODELS` is set.
pub fn models_present(models: &[&str]) -> bool {
    let cache = std::env::var_os("CPSL_CACHE")
        .map(PathBuf::from)
        .unwrap_or_else(|| PathBuf::from(std::env::var_os("HOME").unwrap()).join(".cache/cpsl"));
    let present = cache.join("onnxruntime/libonnxruntime.so.1.31.1").is_file()
        && models
            .iter()
            .all(|m| cache.join("models").join(m).is_file());
    assert!(
        present || std::env::var_os("CPSL_REQUIRE_MODELS").is_none(),
        "models missing in {}: run scripts/setup-models.sh",
        cache.display()
    );
    present
}

/// Whether FastDepth is in the model cache ([`models_present`]); says the test is skipped
/// where it is not.
pub fn fastdepth_present() -> bool {
    let present = models_present(&["fastdepth_7.onnx"]);
    if !present {
        eprintln!("skipped: FastDepth not in the model cache (scripts/setup-models.sh)");
    }
    present
}

/// Writes a 7-frame 192x128 H.264 clip of FFmpeg's `testsrc2` at 10 fps to `path`, with
/// `extra` encoder arguments.
pub fn test_clip(path: &Path, extra: &[&str]) {
    let status = Command::new("ffmpeg")
        .args(["-v", "error", "-y", "-f", "lavfi", "-i"])
        .arg("testsrc2=size=192x128:rate=10")
        .args(["-frames:v", "7", "-c:v", "libx264", "-pix_fmt", "yuv420p"])
        .args(extra)
        .arg(path)
        .status()
        .expect("the ffmpeg tool (scripts/setup-system.sh)");
    assert!(status.success());
}
