//! Every rejection of the layer-set reader, with the file and field named in the message.

use cpsl_core::{Camera, Layer, LayerSet, Limits, PremulImage};
use cpsl_io::{read_layer_set, write_layer_set, IoError};
use serde_json::Value;
use std::path::{Path, PathBuf};

fn valid(dir: &Path) -> PathBuf {
    let cam = Camera::from_fov(8, 6, 60.0);
    let layers = (0..3)
        .map(|i| {
            let img = PremulImage::from_rgb(8, 6, &[40 * i as u8; 8 * 6 * 3]).unwrap();
            Layer::new(img, 1.0 + i as f64)
        })
        .collect();
    let set = LayerSet::new(cam, layers, &Limits::default()).unwrap();
    let p = dir.join("ls");
    write_layer_set(&p, &set, &[]).unwrap();
    p
}

fn edit_manifest(p: &Path, f: impl FnOnce(&mut Value)) {
    let m = p.join("manifest.json");
    let mut v: Value = serde_json::from_slice(&std::fs::read(&m).unwrap()).unwrap();
    f(&mut v);
    std::fs::write(&m, serde_json::to_vec(&v).unwrap()).unwrap();
}

/// Reads, expects an error, and checks that its message contains every fragment.
fn rejects(p: &Path, fragments: &[&str]) -> IoError {
    let e = read_layer_set(p, &Limits::default()).expect_err("must be rejected");
    let msg = e.to_string();
    for f in fragments {
        assert!(msg.contains(f), "message {msg:?} lacks {f:?}");
    }
    e
}

#[test]
fn accepts_the_valid_set() {
    let d = tempfile::tempdir().unwrap();
    assert_eq!(
        read_layer_set(&valid(d.path()), &Limits::default())
            .unwrap()
            .len(),
        3
    );
}

#[test]
fn missing_manifest() {
    let d = tempfile::tempdir().unwrap();
    let p = valid(d.path());
    std::fs::remove_file(p.join("manifest.json")).unwrap();
    assert!(matches!(
        rejects(&p, &["manifest.json"]),
        IoError::Io { .. }
    ));
}

#[test]
fn missing_layer_file() {
    let d = tempfile::tempdir().unwrap();
    let p = valid(d.path());
    std::fs::remove_file(p.join("layer_01.png")).unwrap();
    assert!(matches!(rejects(&p, &["layer_01.png"]), IoError::Io { .. }));
}

#[test]
fn mismatched_layer_size() {
    let d = tempfile::tempdir().unwrap();
    let p = valid(d.path());
    cpsl_io::images::write_png(&p.join("layer_02.png"), 9, 6, 4, &[0; 9 * 6 * 4]).unwrap();
    let e = rejects(&p, &["layer_02.png", "9x6", "8x6"]);
    assert!(matches!(e, IoError::ImageSize { .. }));
}

#[test]
fn corrupt_layer_png() {
    let d = tempfile::tempdir().unwrap();
    let p = valid(d.path());
    let f = p.join("layer_00.png");
    let bytes = std::fs::read(&f).unwrap();
    std::fs::write(&f, &bytes[..bytes.len() / 2]).unwrap();
    rejects(&p, &["layer_00.png"]);
    std::fs::write(&f, b"not a png at all").unwrap();
    rejects(&p, &["layer_00.png"]);
}

#[test]
fn nan_depth() {
    let d = tempfile::tempdir().unwrap();
    let p = valid(d.path());
    // JSON has no NaN literal: a NaN written by a careless tool is a JSON error.
    let m = p.join("manifest.json");
    let s = std::fs::read_to_string(&m)
        .unwrap()
        .replacen("\"depth\": 2.0", "\"depth\": NaN", 1);
    std::fs::write(&m, s).unwrap();
    rejects(&p, &["manifest.json", "invalid JSON"]);
    // Out-of-range numbers are rejected the same way.
    let s = std::fs::read_to_string(&m)
        .unwrap()
        .replacen("NaN", "1e999", 1);
    std::fs::write(&m, s).unwrap();
    rejects(&p, &["manifest.json", "invalid JSON"]);
}

#[test]
fn non_positive_depth() {
    let d = tempfile::tempdir().unwrap();
    let p = valid(d.path());
    edit_manifest(&p, |v| v["layers"][0]["depth"] = (-1.0).into());
    let e = rejects(&p, &["manifest.json", "layer 0", "depth", "-1"]);
    assert!(matches!(e, IoError::Invalid { .. }));
    edit_manifest(&p, |v| v["layers"][0]["depth"] = 0.0.into());
    rejects(&p, &["layer 0", "depth"]);
}

#[test]
fn non_increasing_depths() {
    let d = tempfile::tempdir().unwrap();
    let p = valid(d.path());
    edit_manifest(&p, |v| v["layers"][2]["depth"] = 2.0.into());
    rejects(&p, &["manifest.json", "layer 2", "increase strictly"]);
    edit_manifest(&p, |v| v["layers"][2]["depth"] = 1.5.into());
    rejects(&p, &["layer 2", "1.5 after 2"]);
}

#[test]
fn unknown_version_and_format() {
    let d = tempfile::tempdir().unwrap();
    let p = valid(d.path());
    edit_manifest(&p, |v| v["version"] = 7.into());
    rejects(&p, &["manifest.json", "version", "found 7"]);
    edit_manifest(&p, |v| {
        v["version"] = 1.into();
        v["format"] = "something-else".into();
    });
    rejects(&p, &["manifest.json", "format", "something-else"]);
}

#[test]
fn unknown_or_misspelt_field() {
    let d = tempfile::tempdir().unwrap();
    let p = valid(d.path());
    edit_manifest(&p, |v| v["layers"][1]["dpeth"] = 3.0.into());
    rejects(&p, &["manifest.json", "dpeth"]);
}

#[test]
fn absurd_sizes() {
    let d = tempfile::tempdir().unwrap();
    let p = valid(d.path());
    edit_manifest(&p, |v| v["camera"]["width"] = 1_000_000.into());
    rejects(&p, &["manifest.json", "1000000x6", "limit"]);
    edit_manifest(&p, |v| {
        v["camera"]["width"] = 16_000.into();
        v["camera"]["height"] = 16_000.into();
    });
    rejects(&p, &["manifest.json", "16000x16000", "limit"]);
    edit_manifest(&p, |v| v["camera"]["width"] = 0.into());
    rejects(&p, &["manifest.json", "camera"]);
}

#[test]
fn too_many_layers() {
    let d = tempfile::tempdir().unwrap();
    let p = valid(d.path());
    let limits = Limits {
        max_layers: 2,
        ..Limits::default()
    };
    let e = read_layer_set(&p, &limits).unwrap_err().to_string();
    assert!(e.contains("3 layers") && e.contains("limit of 2"), "{e}");
}

#[test]
fn oversized_manifest() {
    let d = tempfile::tempdir().unwrap();
    let p = valid(d.path());
    let m = p.join("manifest.json");
    let mut s = std::fs::read_to_string(&m).unwrap();
    s.push_str(&" ".repeat(17 << 20));
    std::fs::write(&m, s).unwrap();
    assert!(matches!(
        rejects(&p, &["manifest.json", "limit"]),
        IoError::FileTooLarge { .. }
    ));
}

#[test]
fn unsafe_file_names() {
    let d = tempfile::tempdir().unwrap();
    let p = valid(d.path());
    edit_manifest(&p, |v| v["layers"][0]["file"] = "../../etc/passwd".into());
    rejects(&p, &["manifest.json", "layers[0].file", "../../etc/passwd"]);
    edit_manifest(&p, |v| {
        v["layers"][0]["file"] = "layer_01.png".into();
    });
    rejects(&p, &["layers[1].file", "used twice"]);
}

#[test]
fn bad_camera_intrinsics() {
    let d = tempfile::tempdir().unwrap();
    let p = valid(d.path());
    edit_manifest(&p, |v| v["camera"]["fx"] = (-3.0).into());
    rejects(&p, &["manifest.json", "fx", "-3"]);
}

#[test]
fn slanted_layers_round_trip_and_bad_planes_are_rejected() {
    let d = tempfile::tempdir().unwrap();
    let p = valid(d.path());
    // A gentle slant: read back as written, in a version 2 manifest.
    edit_manifest(&p, |v| {
        v["version"] = 2.into();
        v["layers"][1]["geometry"] = serde_json::json!({ "slanted": [0.0, 0.1, 0.5] });
    });
    let set = read_layer_set(&p, &Limits::default()).unwrap();
    assert_eq!(
        set.layers()[1].geometry,
        cpsl_core::Geometry::Slanted(cpsl_core::Vec3::new(0.0, 0.1, 0.5))
    );
    let again = d.path().join("again");
    write_layer_set(&again, &set, &[]).unwrap();
    assert_eq!(read_layer_set(&again, &Limits::default()).unwrap(), set);
    // A plane whose horizon crosses the layer: depth <= 0 over part of its extent.
    edit_manifest(&p, |v| {
        v["layers"][1]["geometry"] = serde_json::json!({ "slanted": [0.0, 4.0, 0.5] })
    });
    rejects(&p, &["manifest.json", "layer 1", "geometry", "depth"]);
    // Geometry in a version 1 manifest.
    edit_manifest(&p, |v| v["version"] = 1.into());
    rejects(&p, &["manifest.json", "layers[1].geometry", "version 2"]);
    // Wrong shape.
    edit_manifest(&p, |v| {
        v["version"] = 2.into();
        v["layers"][1]["geometry"] = serde_json::json!({ "slanted": [0.0, 0.1] })
    });
    rejects(&p, &["manifest.json", "invalid JSON"]);
}

#[test]
fn mesh_grids_go_to_side_files_and_bad_ones_are_rejected() {
    let d = tempfile::tempdir().unwrap();
    let p = valid(d.path());
    let (cols, rows) = cpsl_core::DepthGrid::dims(8, 6, 4);
    let grid = |inverse_depth: Vec<f32>| serde_json::json!({ "mesh": { "step": 4, "cols": cols, "rows": rows, "inverse_depth": inverse_depth } });
    // A version 2 manifest with the grid inline is still read...
    let values: Vec<f32> = (0..cols * rows).map(|i| 0.5 - 0.01 * i as f32).collect();
    edit_manifest(&p, |v| {
        v["version"] = 2.into();
        v["layers"][1]["geometry"] = grid(values.clone());
    });
    let set = read_layer_set(&p, &Limits::default()).unwrap();
    let cpsl_core::Geometry::Mesh(g) = &set.layers()[1].geometry else {
        panic!("not a mesh: {:?}", set.layers()[1].geometry)
    };
    assert_eq!(g.inverse_depth, values);
    // ...and written as version 3 with the grid in a side file, read back exactly.
    let again = d.path().join("again");
    write_layer_set(&again, &set, &[]).unwrap();
    let manifest = std::fs::read_to_string(again.join("manifest.json")).unwrap();
    assert!(manifest.contains("\"version\": 3"), "{manifest}");
    assert!(
        manifest.contains("\"grid\": \"layer_01.grid\""),
        "{manifest}"
    );
    assert!(!manifest.contains("inverse_depth"), "{manifest}");
    assert_eq!(read_layer_set(&again, &Limits::default()).unwrap(), set);
    // A grid file missing, for another camera, cut short, or with a value that is no depth.
    let file = again.join("layer_01.grid");
    let bytes = std::fs::read(&file).unwrap();
    std::fs::remove_file(&file).unwrap();
    rejects(&again, &["layer_01.grid"]);
    let mut other = bytes.clone();
    other[16..20].copy_from_slice(&(cols + 1).to_le_bytes());
    std::fs::write(&file, &other).unwrap();
    rejects(&again, &["layer_01.grid", "8x6 layer at step 4 needs"]);
    std::fs::write(&file, &bytes[..bytes.len() - 2]).unwrap();
    rejects(&again, &["layer_01.grid", "values"]);
    let mut bad = g.as_ref().clone();
    bad.inverse_depth[3] = -1.0;
    std::fs::write(&file, cpsl_io::grid::encode_grid(&bad)).unwrap();
    rejects(&again, &["layer_01.grid", "vertex (0, 1)", "-1"]);
    // The grid field in a version 2 manifest.
    std::fs::write(&file, &bytes).unwrap();
    edit_manifest(&again, |v| v["version"] = 2.into());
    rejects(&again, &["manifest.json", "layers[1].grid", "version 3"]);
}
