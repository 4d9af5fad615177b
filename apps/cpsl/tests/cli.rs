//! The `cpsl` binary end to end on a small synthetic scene, and its error handling.

mod common;

use common::{cpsl, fails, models_present, ok, s};
use std::path::Path;
use std::process::Command;

#[test]
fn synth_slice_render_pose_and_sweep() {
    let d = tempfile::tempdir().unwrap();
    let scene = d.path().join("scene");
    let layers = d.path().join("layers");
    ok(&[
        "synth",
        "-o",
        s(&scene),
        "--width",
        "96",
        "--height",
        "72",
        "--supersample",
        "1",
    ]);
    for f in [
        "input.png",
        "depth.pfm",
        "depth.png",
        "objects.png",
        "camera.json",
        "views.json",
        "views/tx+0.10.png",
    ] {
        assert!(scene.join(f).exists(), "synth wrote {f}");
    }
    let out = ok(&[
        "slice",
        s(&scene.join("input.png")),
        "--depth",
        s(&scene.join("depth.pfm")),
        "--camera",
        s(&scene.join("camera.json")),
        "-o",
        s(&layers),
        "--layers",
        "4",
    ]);
    assert!(out.contains("wrote 4 layers"), "{out}");
    assert!(layers.join("config.json").exists());

    let png = d.path().join("view.png");
    ok(&[
        "render",
        s(&layers),
        "--pose",
        "0.1,0,0,0,2,0",
        "-o",
        s(&png),
    ]);
    let sharp = cpsl_io::images::read_rgb8(&png, &Default::default()).unwrap();
    assert_eq!((sharp.width, sharp.height), (96, 72));
    // The bicubic filter (the default of offline renders) draws the same view as the
    // players' bilinear one, sharper: close to it, not equal.
    let bilinear = d.path().join("view_bilinear.png");
    ok(&[
        "render",
        s(&layers),
        "--pose",
        "0.1,0,0,0,2,0",
        "--filter",
        "bilinear",
        "-o",
        s(&bilinear),
    ]);
    let img = cpsl_io::images::read_rgb8(&bilinear, &Default::default()).unwrap();
    // A mean squared difference above 0 and below 100: finite PSNR above 28.1 dB.
    let apart = cpsl_core::image::psnr(&img.data, &sharp.data);
    assert!(
        apart.is_finite() && apart > 10.0 * (255.0f64 * 255.0 / 100.0).log10(),
        "bilinear vs cubic {apart:.2} dB"
    );
    // The view looks past the frame's edge: filled by default, the given colour with
    // --background R,G,B.
    let black = d.path().join("view_black.png");
    let pose = ["--pose", "0.3,0,0,0,0,0"];
    let filled = d.path().join("view_filled.png");
    ok(&[&["render", s(&layers), "-o", s(&filled)], &pose[..]].concat());
    let blacks = |p: &Path| {
        let i = cpsl_io::images::read_rgb8(p, &Default::default()).unwrap();
        i.data.chunks_exact(3).filter(|c| c == &[0, 0, 0]).count()
    };
    ok(&[
        &[
            "render",
            s(&layers),
            "-o",
            s(&black),
            "--background",
            "0,0,0",
        ],
        &pose[..],
    ]
    .concat());
    assert!(blacks(&black) >= 72, "a black band: {}", blacks(&black));
    assert_eq!(blacks(&filled), 0, "filled");
    fails(
        &["render", s(&layers), "-o", "x.png", "--background", "grey"],
        "`fill`",
    );

    // Identity render reproduces the input exactly.
    let id = d.path().join("id.png");
    ok(&["render", s(&layers), "--pose", "0,0,0,0,0,0", "-o", s(&id)]);
    let input = cpsl_io::images::read_rgb8(&scene.join("input.png"), &Default::default()).unwrap();
    assert_eq!(
        cpsl_io::images::read_rgb8(&id, &Default::default()).unwrap(),
        input
    );

    // --gpu renders the same view (on a GPU or lavapipe; bicubic as the CPU's default), or
    // falls back to the CPU saying so.
    let gpu_png = d.path().join("view_gpu.png");
    let o = cpsl(&[
        "render",
        s(&layers),
        "--pose",
        "0.1,0,0,0,2,0",
        "-o",
        s(&gpu_png),
        "--gpu",
    ]);
    assert!(o.status.success(), "{}", String::from_utf8_lossy(&o.stderr));
    let err = String::from_utf8_lossy(&o.stderr);
    assert!(
        err.contains("rendering on"),
        "--gpu names its adapter or the fallback: {err}"
    );
    let gpu_img = cpsl_io::images::read_rgb8(&gpu_png, &Default::default()).unwrap();
    let psnr = cpsl_eval::metrics::psnr(&gpu_img.data, &sharp.data);
    assert!(psnr >= 45.0, "GPU render {psnr:.2} dB from the CPU's");

    let sweep = d.path().join("sweep");
    ok(&[
        "render",
        s(&layers),
        "--sweep",
        "tx:-0.1:0.1:3",
        "-o",
        s(&sweep),
    ]);
    for f in ["frame_000.png", "frame_002.png", "sheet.png"] {
        assert!(sweep.join(f).exists(), "sweep wrote {f}");
    }
    let have_ffmpeg = Command::new("ffmpeg")
        .arg("-version")
        .output()
        .is_ok_and(|o| o.status.success());
    assert_eq!(
        sweep.join("sweep.mp4").exists(),
        have_ffmpeg,
        "sweep.mp4 written exactly when FFmpeg is present"
    );
}

#[test]
fn clear_errors_and_nothing_written() {
    let d = tempfile::tempdir().unwrap();
    let missing = d.path().join("nope");
    fails(
        &[
            "render",
            s(&missing),
            "--pose",
            "0,0,0,0,0,0",
            "-o",
            "x.png",
        ],
        "manifest.json",
    );
    fails(
        &["render", s(&missing), "--pose", "1,2,3", "-o", "x.png"],
        "expected 6 finite numbers",
    );
    fails(
        &["render", s(&missing), "--sweep", "qx:0:1:3", "-o", "x"],
        "axis must be",
    );
    fails(
        &["serve", s(&missing), "--addr", "127.0.0.1:0"],
        "cannot serve",
    );
    fails(&["bench", "serve", s(d.path())], "no package under");
    // A video or an image where layers are expected.
    let file = d.path().join("clip.mp4");
    std::fs::write(&file, b"not layers").unwrap();
    fails(
        &["render", s(&file), "--pose", "0,0,0,0,0,0", "-o", "x.png"],
        "is a file, not a layer-set folder or a package",
    );
    // An I/O error named in its wrapper's message is not repeated as the cause.
    fails(&["verify", s(&missing)], "(os error 2)");
    fails(
        &["eval-video", "kitti", "--true-motion"],
        "--true-motion needs the synthetic clip",
    );
    // A variant set goes into a folder of its own: anything else there is not replaced.
    let taken = d.path().join("taken");
    std::fs::create_dir(&taken).unwrap();
    fails(
        &[
            "encode",
            s(&missing),
            "-o",
            s(&taken),
            "--variants",
            "500k,1M",
        ],
        "is not a variant set",
    );
    fails(
        &[
            "encode",
            s(&missing),
            "-o",
            s(&taken),
            "--variants",
            "1M",
            "--bitrate",
            "1M",
        ],
        "cannot be used with",
    );

    // Depth of the wrong size: error naming both sizes, no layer set written.
    let scene = d.path().join("scene");
    ok(&[
        "synth",
        "-o",
        s(&scene),
        "--width",
        "32",
        "--height",
        "24",
        "--supersample",
        "1",
    ]);
    let other = d.path().join("other");
    ok(&[
        "synth",
        "-o",
        s(&other),
        "--width",
        "40",
        "--height",
        "24",
        "--supersample",
        "1",
    ]);
    let out = d.path().join("layers");
    fails(
        &[
            "slice",
            s(&scene.join("input.png")),
            "--depth",
            s(&other.join("depth.pfm")),
            "-o",
            s(&out),
        ],
        "depth is 40x24 but the image is 32x24",
    );
    assert!(!out.exists());
    fails(
        &[
            "slice",
            s(&scene.join("depth.png")),
            "--depth",
            s(&scene.join("input.png")),
            "-o",
            s(&out),
        ],
        "expected a 16-bit greyscale PNG, found Rgb8",
    );
    assert!(!out.exists());
    fails(
        &[
            "slice",
            s(&scene.join("input.png")),
            "--depth",
            s(&scene.join("camera.json")),
            "-o",
            s(&out),
        ],
        "unknown depth format '.json'",
    );
    assert!(!out.exists());
    // A uint16 .npy depth in millimetres works through --depth-scale.
    let pfm = cpsl_io::pfm::read_pfm(&scene.join("depth.pfm"), &Default::default()).unwrap();
    let mut npy = b"\x93NUMPY\x01\x00".to_vec();
    let mut header = format!(
        "{{'descr': '<u2', 'fortran_order': False, 'shape': ({}, {}), }}",
        pfm.height, pfm.width
    );
    while (10 + header.len() + 1) % 64 != 0 {
        header.push(' ');
    }
    header.push('\n');
    npy.extend_from_slice(&(header.len() as u16).to_le_bytes());
    npy.extend_from_slice(header.as_bytes());
    for z in &pfm.data {
        npy.extend_from_slice(&((z * 1000.0).round() as u16).to_le_bytes());
    }
    let npy_path = d.path().join("depth_mm.npy");
    std::fs::write(&npy_path, npy).unwrap();
    let layers = d.path().join("from_npy");
    let msg = ok(&[
        "slice",
        s(&scene.join("input.png")),
        "--depth",
        s(&npy_path),
        "-o",
        s(&layers),
        "--depth-scale",
        "0.001",
    ]);
    assert!(msg.contains("depths 2.500"), "{msg}");
    fails(
        &[
            "slice",
            s(&scene.join("input.png")),
            "--depth",
            s(&scene.join("depth.pfm")),
            "-o",
            s(&out),
            "--layers",
            "0",
        ],
        "0",
    );
}

#[test]
fn slice_with_a_depth_model() {
    if !common::fastdepth_present() {
        return;
    }
    let d = tempfile::tempdir().unwrap();
    let scene = d.path().join("scene");
    ok(&[
        "synth",
        "-o",
        s(&scene),
        "--width",
        "64",
        "--height",
        "48",
        "--supersample",
        "1",
    ]);
    let layers = d.path().join("layers");
    let out = ok(&[
        "slice",
        s(&scene.join("input.png")),
        "--depth-model",
        "fastdepth",
        "-o",
        s(&layers),
        "--layers",
        "3",
    ]);
    assert!(out.contains("wrote 3 layers"), "{out}");
    let cfg = std::fs::read_to_string(layers.join("config.json")).unwrap();
    assert!(cfg.contains("fastdepth_7.onnx"), "{cfg}");
    // A file that is not ONNX, with a valid description: clear error, nothing written.
    let bogus = d.path().join("bogus.onnx");
    std::fs::write(&bogus, b"not a model").unwrap();
    std::fs::copy(
        std::path::Path::new(env!("CARGO_MANIFEST_DIR")).join("../../models/fastdepth.json"),
        d.path().join("bogus.json"),
    )
    .unwrap();
    let none = d.path().join("none");
    fails(
        &[
            "slice",
            s(&scene.join("input.png")),
            "--depth-model",
            s(&bogus),
            "-o",
            s(&none),
        ],
        "not a usable ONNX model",
    );
    assert!(!none.exists());
}

#[test]
fn eval_on_real_data_and_its_errors() {
    let data = std::path::Path::new(env!("CARGO_MANIFEST_DIR")).join("../../../shared/data");
    let d = tempfile::tempdir().unwrap();
    fails(
        &["eval", "all", "--data", s(&d.path().join("none"))],
        "data folder not found",
    );
    if !data.is_dir() {
        eprintln!(
            "skipped the rest of eval_on_real_data_and_its_errors: {} not found",
            data.display()
        );
        return;
    }
    fails(
        &["eval", "kitti/06", "--data", s(&data)],
        "unknown dataset 'kitti/06'",
    );
    let json = d.path().join("report.json");
    let html = d.path().join("report");
    let out = ok(&[
        "eval",
        "middlebury2003/Teddy",
        "--data",
        s(&data),
        "--json",
        s(&json),
        "--html",
        s(&html),
    ]);
    assert!(
        out.contains("depth-slice") && out.contains("single-plane") && out.contains("cpsl-no-dps"),
        "{out}"
    );
    let report: serde_json::Value = serde_json::from_slice(&std::fs::read(&json).unwrap()).unwrap();
    let methods: Vec<&str> = report
        .as_array()
        .unwrap()
        .iter()
        .map(|r| r["method"].as_str().unwrap())
        .collect();
    assert_eq!(
        methods,
        [
            "cpsl",
            "cpsl-no-dps",
            "cpsl-depth-only",
            "depth-slice",
            "mpi",
            "mpi-k",
            "single-plane",
            "dibr",
            "dibr-fill"
        ]
    );
    let by = |m: &str| {
        report
            .as_array()
            .unwrap()
            .iter()
            .find(|r| r["method"] == m)
            .unwrap()
    };
    let first = by("cpsl");
    assert_eq!(first["dataset"], "middlebury2003/Teddy");
    assert!(first["mean_psnr"].as_f64().unwrap() > 15.0, "{first}");
    let view = &first["views"][0];
    for key in [
        "psnr",
        "ssim",
        "lpips",
        "crack",
        "hole",
        "covisible",
        "offset",
    ] {
        assert!(view.get(key).is_some(), "views[].{key} in {view}");
    }
    // Unfilled DIBR cracks along depth edges; CPSL does not.
    assert!(by("dibr")["mean_crack"].as_f64().unwrap() > 0.05);
    assert!(first["mean_crack"].as_f64().unwrap() <= 0.01);
    if models_present(&["lpips_alex_v0.1.onnx"]) {
        let l = first["mean_lpips"].as_f64().unwrap();
        assert!(l > 0.0 && l < 0.5, "LPIPS {l}");
    }
    let index = std::fs::read_to_string(html.join("index.html")).unwrap();
    assert!(index.contains("<svg") && index.contains("crops/middlebury2003_Teddy_cpsl.png"));
    assert!(html
        .join("crops/middlebury2003_Teddy_ground_truth.png")
        .is_file());
    // Coded: the layers go through a one-frame package and are decoded before rendering.
    fails(
        &[
            "eval",
            "middlebury2003/Teddy",
            "--data",
            s(&data),
            "--bitrate",
            "3M",
        ],
        "--codec",
    );
    let kept = d.path().join("packages");
    let coded_json = d.path().join("coded.json");
    let run = |budget: &str| {
        ok(&[
            "eval",
            "middlebury2003/Teddy",
            "--data",
            s(&data),
            "--method",
            "cpsl",
            "--no-lpips",
            "--codec",
            "h264",
            "--bitrate",
            budget,
            "--keep-packages",
            s(&kept),
            "--json",
            s(&coded_json),
        ]);
        let r: serde_json::Value =
            serde_json::from_slice(&std::fs::read(&coded_json).unwrap()).unwrap();
        (
            r[0]["mean_psnr"].as_f64().unwrap(),
            r[0]["bits"].as_f64().unwrap(),
        )
    };
    let (low_psnr, low_bits) = run("2M");
    let (high_psnr, high_bits) = run("30M");
    let pkg = kept.join("middlebury2003_Teddy_cpsl.cpsl");
    assert!(ok(&["verify", s(&pkg)]).contains("ok"));
    let uncoded = first["mean_psnr"].as_f64().unwrap();
    // The coded frame costs more bits at the higher budget and gets closer to the uncoded
    // layers; coding never adds quality. (Measured, bicubic: uncoded 29.86 dB, coded at 30
    // Mbit/s 28.81 with grids refined to 4 px where Teddy's depth bends; bilinear 29.88 and
    // 28.84, with 8-px grids 29.22 and 28.37.)
    assert!(high_bits > 2.0 * low_bits, "{low_bits} vs {high_bits}");
    assert!(
        low_psnr < high_psnr && high_psnr <= uncoded + 0.05 && high_psnr > uncoded - 1.25,
        "{low_psnr} {high_psnr} {uncoded}"
    );
}

/// The README's main job, small: a still layered and swept, then a moving clip encoded into a
/// package (exact depth per frame) and played back along a sweep.
#[test]
fn demo_end_to_end_small() {
    let d = tempfile::tempdir().unwrap();
    let out = d.path().join("demo");
    let stdout = ok(&[
        "demo",
        "-o",
        s(&out),
        "--width",
        "128",
        "--height",
        "96",
        "--clip-frames",
        "12",
    ]);
    for step in ["1/5", "2/5", "3/5", "4/5", "5/5"] {
        assert!(stdout.contains(step), "{step} missing from {stdout}");
    }
    for f in [
        "scene/input.png",
        "layers/config.json",
        "sweep/sheet.png",
        "scores.json",
        "clip/frames/frame_0011.png",
        "clip/depth/frame_0011.pfm",
        "clip_sweep/frame_011.png",
        "clip_sweep/sheet.png",
    ] {
        assert!(out.join(f).is_file(), "{f} missing");
    }
    let info = ok(&["info", s(&out.join("clip.cpsl"))]);
    assert!(
        info.contains("12 frames") && info.contains("h264"),
        "{info}"
    );
    ok(&["verify", s(&out.join("clip.cpsl"))]);
    let scores: serde_json::Value =
        serde_json::from_slice(&std::fs::read(out.join("clip_scores.json")).unwrap()).unwrap();
    let frames = scores["frames"].as_array().unwrap();
    assert_eq!(frames.len(), 2, "frames 0 and 10 scored: {scores}");
    for f in frames {
        // A novel view 0.15 units aside: the uncompressed still scores 25.5 and 23.0 dB at 0.1
        // and 0.2 units; this package scores 22.7 and 22.4 dB (16.5 dB when starved at 500k).
        let p = f["psnr_db"].as_f64().unwrap();
        assert!(p > 21.0, "novel view from the package: {p} dB");
    }
    let bits = scores["bitrate_bps"].as_f64().unwrap();
    assert!(bits <= 2e6 * 1.1, "budget kept: {bits}");
}

/// `cpsl eval-rd` on a tiny clip, without LPIPS.
const EVAL_RD_TINY: [&str; 12] = [
    "eval-rd",
    "--width",
    "96",
    "--height",
    "64",
    "--frames",
    "6",
    "--mpi-planes",
    "4",
    "--score-every",
    "3",
    "--no-lpips",
];

/// `cpsl eval-rd` on a tiny clip: four curves, coded rates that follow the settings, and its
/// errors.
#[test]
fn eval_rd_small() {
    let d = tempfile::tempdir().unwrap();
    let json = d.path().join("rd.json");
    let base = EVAL_RD_TINY;
    let mut args = base.to_vec();
    args.extend([
        "--bitrates",
        "200k,2M",
        "--qualities",
        "18,44",
        "--json",
        s(&json),
    ]);
    let out = ok(&args);
    assert!(out.contains("| cpsl | uncompressed |"), "{out}");
    let v: serde_json::Value = serde_json::from_slice(&std::fs::read(&json).unwrap()).unwrap();
    let curves = v["curves"].as_array().unwrap();
    let names: Vec<&str> = curves
        .iter()
        .map(|c| c["method"].as_str().unwrap())
        .collect();
    assert_eq!(names, ["cpsl", "dibr", "dibr-16", "mpi"]);
    for c in curves {
        let p = c["points"].as_array().unwrap();
        assert_eq!(p.len(), 2, "{c}");
        let rate = |i: usize| p[i]["bitrate"].as_f64().unwrap();
        let psnr = |i: usize| p[i]["psnr"].as_f64().unwrap();
        // The first setting is the richer one (2 Mbit/s, CRF 18) for every method.
        assert!(rate(0) < rate(1) || c["method"] != "cpsl", "{c}");
        assert!(rate(0) > rate(1) || c["method"] == "cpsl", "{c}");
        let (hi, lo) = if c["method"] == "cpsl" {
            (1, 0)
        } else {
            (0, 1)
        };
        assert!(psnr(hi) >= psnr(lo) - 0.2, "more bits, no worse: {c}");
        let un = c["uncompressed"]["psnr"].as_f64().unwrap();
        assert!(psnr(hi) <= un + 0.5, "coding adds no quality: {c}");
        assert!(un > 15.0, "{c}");
    }
    for r in ["dibr_rate_ratio", "dibr16_rate_ratio", "mpi_rate_ratio"] {
        assert_eq!(v["summary"][r].as_array().map(Vec::len), Some(2), "{r}");
    }
    let mut bad = base.to_vec();
    bad.extend(["--qualities", "99"]);
    let o = cpsl(&bad);
    assert!(!o.status.success());
    assert!(String::from_utf8_lossy(&o.stderr).contains("--qualities 99"));
}

/// `cpsl eval-rd --input h264`: CPSL layered from the clip coded as H.264 with B-frames (its
/// motion vectors used), scored as from the pictures.
#[test]
fn eval_rd_through_h264() {
    let d = tempfile::tempdir().unwrap();
    let json = d.path().join("rd.json");
    let mut args = EVAL_RD_TINY.to_vec();
    args.extend(["--bitrates", "2M", "--qualities", "30", "--input", "h264"]);
    args.extend(["--json", s(&json)]);
    ok(&args);
    let v: serde_json::Value = serde_json::from_slice(&std::fs::read(&json).unwrap()).unwrap();
    assert_eq!(v["clip"]["input"], "h264");
    let cpsl = &v["curves"][0];
    assert_eq!(cpsl["method"], "cpsl");
    assert!(
        cpsl["uncompressed"]["psnr"].as_f64().unwrap() > 15.0,
        "{cpsl}"
    );
    assert!(cpsl["points"][0]["psnr"].as_f64().unwrap() > 15.0, "{cpsl}");
}

#[test]
fn info_summarises_a_layer_set_with_its_grid_files() {
    let d = tempfile::tempdir().unwrap();
    let scene = d.path().join("scene");
    let layers = d.path().join("layers");
    ok(&["synth", "-o", s(&scene), "--width", "96", "--height", "72"]);
    ok(&[
        "layer",
        s(&scene.join("input.png")),
        "--depth",
        s(&scene.join("depth.pfm")),
        "--camera",
        s(&scene.join("camera.json")),
        "--geometry",
        "mesh",
        "--layers",
        "4",
        "-o",
        s(&layers),
    ]);
    // The scene's floor and walls bend across layers: meshes, each grid in its own file.
    let grids: Vec<_> = std::fs::read_dir(&layers)
        .unwrap()
        .filter_map(|e| e.ok())
        .filter(|e| e.path().extension().is_some_and(|x| x == "grid"))
        .collect();
    assert!(!grids.is_empty(), "no mesh layer");
    let manifest = std::fs::read_to_string(layers.join("manifest.json")).unwrap();
    assert!(manifest.contains("\"version\": 3") && !manifest.contains("inverse_depth"));
    let info = ok(&["info", s(&layers)]);
    assert!(info.contains("cpsl-layerset v3, 96x72"), "{info}");
    assert_eq!(info.matches("mesh ").count(), grids.len(), "{info}");
    assert!(info.contains("edge-depth cache"), "{info}");
    // A folder that is neither a package nor layers says what it expected.
    std::fs::write(layers.join("manifest.json"), b"{\"format\": \"other\"}").unwrap();
    fails(&["info", s(&layers)], "manifest.json");
}
