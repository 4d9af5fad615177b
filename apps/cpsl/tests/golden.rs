//! Golden images: small renders committed under `tests/golden/`. Regenerate them with
//! `CPSL_UPDATE_GOLDEN=1 cargo test -p cpsl --test golden`; on a mismatch the actual image and
//! an amplified difference image are written to `target/tmp/golden-failures/`.

use cpsl_core::{LayerSet, Pose, PremulImage, Vec3};
use cpsl_layering::{slice_by_depth, SliceConfig};
use cpsl_render::PreparedLayers;
use cpsl_synth::layers::{synthetic_layer_set, Coverage};
use cpsl_synth::Scene;
use std::path::PathBuf;

/// Largest per-channel difference accepted, in premultiplied 8-bit values (the renderer is
/// deterministic; one step covers rounding differences between platforms' float libraries in
/// the ray caster). Files are straight-alpha PNGs, but the comparison is made premultiplied:
/// un-premultiplying would amplify one-step differences of semi-transparent pixels.
const TOLERANCE: u8 = 1;

fn check(name: &str, set: &LayerSet, pose: &Pose) {
    let img = PreparedLayers::new(set).render(pose);
    let (w, h) = (img.width(), img.height());
    let rgba = img.to_straight();
    let path = PathBuf::from(env!("CARGO_MANIFEST_DIR"))
        .join("tests/golden")
        .join(format!("{name}.png"));
    if std::env::var_os("CPSL_UPDATE_GOLDEN").is_some() {
        cpsl_io::images::write_png(&path, w, h, 4, &rgba).unwrap();
        return;
    }
    let golden = cpsl_io::images::read_rgba8(&path, &Default::default())
        .unwrap_or_else(|e| panic!("{e}: run with CPSL_UPDATE_GOLDEN=1 to create it"));
    assert_eq!(
        (golden.width, golden.height),
        (w, h),
        "{name}: size changed"
    );
    let golden = PremulImage::from_straight(w, h, &golden.data).unwrap();
    let mut worst = 0u8;
    let diff: Vec<u8> = img
        .as_bytes()
        .iter()
        .zip(golden.as_bytes())
        .enumerate()
        .map(|(i, (a, b))| {
            let d = a.abs_diff(*b);
            worst = worst.max(d);
            if i % 4 == 3 {
                255
            } else {
                d.saturating_mul(32)
            }
        })
        .collect();
    if worst > TOLERANCE {
        let dir = PathBuf::from(env!("CARGO_TARGET_TMPDIR")).join("golden-failures");
        cpsl_io::images::write_png(&dir.join(format!("{name}.actual.png")), w, h, 4, &rgba)
            .unwrap();
        cpsl_io::images::write_png(&dir.join(format!("{name}.diff.png")), w, h, 4, &diff).unwrap();
        panic!(
            "{name}: differs from the golden image by up to {worst} (tolerance {TOLERANCE}); actual and diff written to {}",
            dir.display()
        );
    }
}

#[test]
fn synthetic_layers_at_three_poses() {
    let set = synthetic_layer_set(96, 64, 4, Coverage::Typical, 11);
    check("layers_identity", &set, &Pose::IDENTITY);
    check(
        "layers_translate",
        &set,
        &Pose::from_translation(Vec3::new(0.15, -0.05, 0.2)),
    );
    check(
        "layers_rotate",
        &set,
        &Pose::from_euler_deg(Vec3::new(-0.05, 0.0, 0.0), 2.0, 4.0, -3.0),
    );
}

#[test]
fn depth_sliced_scene_novel_views() {
    let scene = Scene::default_scene(128, 96);
    let view = scene.render(&scene.camera, &Pose::IDENTITY, 0.0, 2);
    let set = slice_by_depth(
        &view.rgb,
        &view.depth,
        scene.camera,
        &SliceConfig::default(),
    )
    .unwrap();
    check(
        "scene_right",
        &set,
        &Pose::from_translation(Vec3::new(0.25, 0.0, 0.0)),
    );
    check(
        "scene_orbit",
        &set,
        &Pose::from_euler_deg(Vec3::new(-0.2, -0.1, 0.1), 0.0, 3.0, 0.0),
    );
}
