//! LPIPS through ONNX Runtime against the reference value of the independent numpy
//! implementation (`scripts/lpips_reference.py`, run once on the same weights; its images and
//! value are the fixtures here). Needs the graph from `scripts/setup-models.sh`.

use cpsl_models::lpips::{default_path, Lpips};
use std::path::Path;

fn png(name: &str) -> (u32, u32, Vec<u8>) {
    let p = Path::new(env!("CARGO_MANIFEST_DIR"))
        .join("tests/fixtures")
        .join(name);
    let img = image::open(&p).unwrap().to_rgb8();
    (img.width(), img.height(), img.into_raw())
}

#[test]
fn lpips_matches_the_numpy_reference() {
    let path = default_path();
    if !path.is_file() || !cpsl_models::runtime::available() {
        assert!(
            std::env::var_os("CPSL_REQUIRE_MODELS").is_none(),
            "{} missing: run scripts/setup-models.sh",
            path.display()
        );
        eprintln!("skipped: {} missing", path.display());
        return;
    }
    let refs: serde_json::Value = serde_json::from_slice(
        &std::fs::read(
            Path::new(env!("CARGO_MANIFEST_DIR")).join("tests/fixtures/lpips_reference.json"),
        )
        .unwrap(),
    )
    .unwrap();
    let (w, h, a) = png("lpips_a.png");
    let (_, _, b) = png("lpips_b.png");
    let mut m = Lpips::open(&path).unwrap();
    let same = m.distance(&a, &a, w, h).unwrap();
    assert!(same.abs() < 1e-6, "identical images: {same}");
    let blur = m.distance(&a, &b, w, h).unwrap() as f64;
    let want = refs["lpips_blur"].as_f64().unwrap();
    assert!((blur - want).abs() < 1e-3, "LPIPS {blur}, reference {want}");
    // Symmetric, and a bad size is an error.
    let back = m.distance(&b, &a, w, h).unwrap() as f64;
    assert!((back - blur).abs() < 1e-5);
    assert!(m.distance(&a[..30], &a[..30], 10, 1).is_err());
}
