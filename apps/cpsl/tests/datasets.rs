//! The real datasets load with the right geometry: layers from ground-truth depth reproduce
//! the real target views clearly better with the loader's poses and cameras than with mirrored
//! ones (a sign error in a pose, principal-point shift or depth conversion fails this), and
//! better than a single plane. Reads `../shared/data` beside the checkout; says so and
//! returns when it is absent.

use cpsl_core::{Camera, Pose, PremulImage, Vec3};
use cpsl_eval::datasets::{load, Dataset, Target, NAMES};
use cpsl_eval::metrics::psnr_masked;
use cpsl_layering::{slice_by_depth, SliceConfig};
use cpsl_render::PreparedLayers;
use std::path::PathBuf;

fn psnr(prepared: &PreparedLayers, t: &Target, pose: &Pose, cam: &Camera) -> f64 {
    let mut img = PremulImage::new(cam.width, cam.height);
    prepared.render_into(pose, cam, &mut img);
    let covered: Vec<bool> = img
        .as_bytes()
        .chunks_exact(4)
        .map(|p| p[3] == 255)
        .collect();
    assert!(
        covered.iter().filter(|&&c| c).count() as f64 > 0.85 * covered.len() as f64,
        "{}: render covers too little",
        t.name
    );
    psnr_masked(&img.over_background([0, 0, 0]), &t.rgb, &covered).unwrap()
}

fn layers(ds: &Dataset, k: usize) -> PreparedLayers {
    let config = SliceConfig {
        layers: k,
        ..SliceConfig::default()
    };
    PreparedLayers::new(&slice_by_depth(&ds.rgb, &ds.depth, ds.camera, &config).unwrap())
}

#[test]
fn loader_geometry_reproduces_the_real_views() {
    let root = PathBuf::from(env!("CARGO_MANIFEST_DIR")).join("../../../shared/data");
    if !root.is_dir() {
        eprintln!("skipped: {} not found", root.display());
        return;
    }
    for name in NAMES {
        let ds = load(&root, name).unwrap();
        let (many, one) = (layers(&ds, 16), layers(&ds, 1));
        // The view with the largest baseline (a light-field corner, or the stereo partner).
        let t = ds
            .targets
            .iter()
            .max_by(|a, b| {
                a.pose
                    .translation
                    .norm()
                    .total_cmp(&b.pose.translation.norm())
            })
            .unwrap();
        let good = psnr(&many, t, &t.pose, &t.camera);
        let tr = t.pose.translation;
        let mirrored_pose = Pose::from_translation(Vec3::new(-tr.x(), -tr.y(), -tr.z()));
        let mirrored_cam = Camera {
            cx: 2.0 * ds.camera.cx - t.camera.cx,
            cy: 2.0 * ds.camera.cy - t.camera.cy,
            ..t.camera
        };
        let mirrored = psnr(&many, t, &mirrored_pose, &mirrored_cam);
        let plane = psnr(&one, t, &t.pose, &t.camera);
        assert!(
            good > mirrored + 2.0,
            "{name}: {good:.2} dB, mirrored geometry {mirrored:.2} dB"
        );
        assert!(
            good > plane + 0.3,
            "{name}: 16 layers {good:.2} dB, single plane {plane:.2} dB"
        );
    }
}
