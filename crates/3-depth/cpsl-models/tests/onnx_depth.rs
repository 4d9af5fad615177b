//! ONNX depth models end to end: a tiny ONNX graph written by hand here (no download), the
//! model-file errors, and the real FastDepth where `scripts/setup-models.sh` fetched it.
//!
//! Without the ONNX Runtime library these tests say so and return, unless
//! `CPSL_REQUIRE_MODELS=1` (set by `.ci/run`), where that is a failure.

use cpsl_models::depth::{sidecar_path, DepthModelDesc, OnnxDepth};
use cpsl_models::{runtime, ModelError};
use std::path::{Path, PathBuf};

fn runtime_or_skip(test: &str) -> bool {
    if runtime::available() {
        return true;
    }
    let msg = format!(
        "{test}: ONNX Runtime not found at {} (run scripts/setup-models.sh)",
        runtime::library_path().display()
    );
    assert!(std::env::var_os("CPSL_REQUIRE_MODELS").is_none(), "{msg}");
    eprintln!("skipped {msg}");
    false
}

/// Minimal protobuf encoding, enough for an ONNX ModelProto.
fn varint(mut v: u64, out: &mut Vec<u8>) {
    while v >= 0x80 {
        out.push((v as u8) | 0x80);
        v >>= 7;
    }
    out.push(v as u8);
}
fn int_field(num: u64, v: u64, out: &mut Vec<u8>) {
    varint(num << 3, out);
    varint(v, out);
}
fn bytes_field(num: u64, b: &[u8], out: &mut Vec<u8>) {
    varint((num << 3) | 2, out);
    varint(b.len() as u64, out);
    out.extend_from_slice(b);
}

/// A float tensor value info `name` with a fixed shape.
fn value_info(name: &str, dims: &[u64]) -> Vec<u8> {
    let mut shape = Vec::new();
    for &d in dims {
        let mut dim = Vec::new();
        int_field(1, d, &mut dim); // dim_value
        bytes_field(1, &dim, &mut shape);
    }
    let mut tensor = Vec::new();
    int_field(1, 1, &mut tensor); // elem_type FLOAT
    bytes_field(2, &shape, &mut tensor);
    let mut ty = Vec::new();
    bytes_field(1, &tensor, &mut ty);
    let mut vi = Vec::new();
    bytes_field(1, name.as_bytes(), &mut vi);
    bytes_field(2, &ty, &mut vi);
    vi
}

/// ONNX model (opset 13): depth = ReduceMean(image, axes=[1], keepdims=1), for a
/// 1x3x`h`x`w` input: the mean of R, G and B.
fn tiny_depth_model(w: u64, h: u64) -> Vec<u8> {
    let mut attr = Vec::new();
    bytes_field(1, b"axes", &mut attr);
    int_field(8, 1, &mut attr); // ints: [1]
    int_field(20, 7, &mut attr); // type INTS
    let mut node = Vec::new();
    bytes_field(1, b"image", &mut node);
    bytes_field(2, b"depth", &mut node);
    bytes_field(3, b"mean_rgb", &mut node);
    bytes_field(4, b"ReduceMean", &mut node);
    bytes_field(5, &attr, &mut node);
    let mut graph = Vec::new();
    bytes_field(1, &node, &mut graph);
    bytes_field(2, b"tiny_depth", &mut graph);
    bytes_field(11, &value_info("image", &[1, 3, h, w]), &mut graph);
    bytes_field(12, &value_info("depth", &[1, 1, h, w]), &mut graph);
    let mut opset = Vec::new();
    bytes_field(1, b"", &mut opset);
    int_field(2, 13, &mut opset);
    let mut model = Vec::new();
    int_field(1, 7, &mut model); // ir_version
    bytes_field(2, b"cpsl-test", &mut model);
    bytes_field(7, &graph, &mut model);
    bytes_field(8, &opset, &mut model);
    model
}

fn write_model(dir: &Path, kind: &str, scale: f32, shift: f32) -> PathBuf {
    let p = dir.join(format!("tiny_{kind}.onnx"));
    std::fs::write(&p, tiny_depth_model(8, 6)).unwrap();
    let desc = format!(
        r#"{{"name":"tiny","input":{{"size":{{"fixed":[8,6]}}}},"output":{{"kind":"{kind}","scale":{scale},"shift":{shift}}}}}"#
    );
    std::fs::write(sidecar_path(&p), desc).unwrap();
    p
}

/// An RGB image whose grey level rises from left to right.
fn ramp(w: u32, h: u32) -> Vec<u8> {
    (0..h)
        .flat_map(|_| (0..w).flat_map(move |x| [(50 + 150 * x / (w - 1)) as u8; 3]))
        .collect()
}

#[test]
fn tiny_graph_metric_and_inverse_outputs() {
    if !runtime_or_skip("tiny_graph_metric_and_inverse_outputs") {
        return;
    }
    let d = tempfile::tempdir().unwrap();
    // Metric: depth = 10 * mean + 1, so a flat image of 51/255 = 0.2 gives 3.0 everywhere.
    let mut m = OnnxDepth::open(&write_model(d.path(), "metric_depth", 10.0, 1.0), None).unwrap();
    let flat = vec![51u8; 32 * 24 * 3];
    let e = m.estimate(&flat, 32, 24).unwrap();
    assert_eq!((e.width, e.height, e.depth.len()), (32, 24, 32 * 24));
    assert!(
        e.depth.iter().all(|z| (z - 3.0).abs() < 1e-4),
        "{:?}",
        &e.depth[..4]
    );
    // Inverse depth: brighter (larger output) means nearer; orientation is preserved.
    let mut inv = OnnxDepth::open(&write_model(d.path(), "inverse_depth", 1.0, 0.0), None).unwrap();
    let e = inv.estimate(&ramp(40, 10), 40, 10).unwrap();
    let (left, right) = (e.depth[5 * 40 + 1], e.depth[5 * 40 + 38]);
    assert!(left > right && right > 0.0, "left {left} right {right}");
    // A zero output is unknown depth, not infinity.
    let e = inv.estimate(&[0u8; 8 * 6 * 3], 8, 6).unwrap();
    assert!(e.depth.iter().all(|z| z.is_nan()));
    // Wrong buffer size: clear error.
    assert!(matches!(
        inv.estimate(&[0u8; 10], 8, 6),
        Err(ModelError::Input(_))
    ));
}

#[test]
fn model_file_errors() {
    if !runtime_or_skip("model_file_errors") {
        return;
    }
    let d = tempfile::tempdir().unwrap();
    let p = d.path().join("not_onnx.onnx");
    std::fs::write(&p, b"this is not an ONNX file").unwrap();
    let desc = DepthModelDesc::load(
        &PathBuf::from(env!("CARGO_MANIFEST_DIR")).join("../../../models/fastdepth.json"),
    )
    .unwrap();
    let e = OnnxDepth::open(&p, Some(desc.clone())).unwrap_err();
    assert!(matches!(e, ModelError::Model { .. }), "{e}");
    assert!(e.to_string().contains("not_onnx.onnx"));
    let e = OnnxDepth::open(&d.path().join("missing.onnx"), Some(desc)).unwrap_err();
    assert!(e.to_string().contains("missing.onnx"), "{e}");
    // No description next to the model: the error names the expected description file.
    std::fs::write(d.path().join("bare.onnx"), tiny_depth_model(8, 6)).unwrap();
    let e = OnnxDepth::open(&d.path().join("bare.onnx"), None).unwrap_err();
    assert!(e.to_string().contains("bare.json"), "{e}");
}

#[test]
fn fastdepth_from_the_cache() {
    let model = runtime::cache_dir().join("models/fastdepth_7.onnx");
    if !model.is_file() {
        assert!(
            std::env::var_os("CPSL_REQUIRE_MODELS").is_none(),
            "{} missing: run scripts/setup-models.sh",
            model.display()
        );
        eprintln!(
            "skipped fastdepth_from_the_cache: {} not fetched",
            model.display()
        );
        return;
    }
    if !runtime_or_skip("fastdepth_from_the_cache") {
        return;
    }
    let mut m = OnnxDepth::open(&model, None).unwrap();
    let (w, h) = (96, 72);
    let e = m.estimate(&ramp(w, h), w, h).unwrap();
    let valid: Vec<f32> = e.depth.iter().copied().filter(|z| z.is_finite()).collect();
    assert_eq!(
        valid.len(),
        e.depth.len(),
        "FastDepth gives metric depth everywhere"
    );
    let (lo, hi) = valid
        .iter()
        .fold((f32::MAX, 0f32), |(a, b), &z| (a.min(z), b.max(z)));
    assert!(
        lo > 0.05 && hi < 50.0 && hi > lo,
        "plausible indoor depth range, found {lo}..{hi}"
    );
}
