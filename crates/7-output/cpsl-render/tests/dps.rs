//! The Dynamic Pixel Strip bridges a deliberate one-pixel gap between two layers (crack ratio
//! from > 0 to 0), leaves covered pixels untouched and does not invent content in wide holes.

use cpsl_core::{Camera, Layer, LayerSet, Limits, Pose, PremulImage, Vec3};
use cpsl_eval::coverage::crack_ratio;
use cpsl_render::{DpsConfig, PreparedLayers};

const W: u32 = 48;
const H: u32 = 24;

/// Front layer (red, depth 2) on columns `< 20`, back layer (blue, depth 6) on columns
/// `>= 20 + gap`; nothing behind the gap.
fn gapped(gap: u32) -> LayerSet {
    let mut front = PremulImage::new(W, H);
    let mut back = PremulImage::new(W, H);
    for y in 0..H {
        for x in 0..W {
            if x < 20 {
                front.set_pixel(x, y, [200, 30, 30, 255]);
            } else if x >= 20 + gap {
                back.set_pixel(x, y, [30, 40, 220, 255]);
            }
        }
    }
    LayerSet::new(
        Camera::from_fov(W, H, 60.0),
        vec![Layer::new(front, 2.0), Layer::new(back, 6.0)],
        &Limits::default(),
    )
    .unwrap()
}

fn covered(img: &PremulImage) -> Vec<bool> {
    img.as_bytes()
        .chunks_exact(4)
        .map(|p| p[3] >= 128)
        .collect()
}

#[test]
fn strip_closes_a_one_pixel_crack_without_touching_covered_pixels() {
    let set = gapped(1);
    let prepared = PreparedLayers::new(&set);
    let cam = *set.camera();
    let band = vec![true; (W * H) as usize];
    for pose in [
        Pose::IDENTITY,
        Pose::from_translation(Vec3::new(0.0, 0.02, 0.0)),
    ] {
        let plain = prepared.render(&pose);
        let before = crack_ratio(&covered(&plain), &band, W as usize, H as usize);
        assert!(before > 0.0, "the gap is a crack");
        let mut out = PremulImage::new(W, H);
        let stats = prepared.render_dps_into(&pose, &cam, &mut out, &DpsConfig::default());
        let after = crack_ratio(&covered(&out), &band, W as usize, H as usize);
        assert_eq!(after, 0.0, "DPS closes the crack ({} pixels)", stats.pixels);
        assert!(stats.pixels >= H as usize);
        for (p, (a, b)) in plain
            .as_bytes()
            .chunks_exact(4)
            .zip(out.as_bytes().chunks_exact(4))
            .enumerate()
        {
            if a[3] >= 128 {
                assert_eq!(a, b, "covered pixel {p} changed");
            } else {
                // The strip blends the two sides: red and blue, no other hue.
                assert_eq!(b[3], 255);
                assert!(b[1] <= 40 && b[0] >= 30 && b[2] >= 30, "strip colour {b:?}");
            }
        }
    }
}

#[test]
fn strip_leaves_wide_holes_and_single_sided_borders_alone() {
    // A 20-pixel gap is a disocclusion, not a crack.
    let set = gapped(20);
    let prepared = PreparedLayers::new(&set);
    let mut out = PremulImage::new(W, H);
    let stats = prepared.render_dps_into(
        &Pose::IDENTITY,
        set.camera(),
        &mut out,
        &DpsConfig::default(),
    );
    assert_eq!(stats.pixels, 0);
    assert_eq!(out, prepared.render(&Pose::IDENTITY));
    // Moving the viewer reveals a strip outside the reference frame at the border: one-sided,
    // left as it is.
    let set = gapped(0);
    let prepared = PreparedLayers::new(&set);
    let pose = Pose::from_translation(Vec3::new(-0.05, 0.0, 0.0));
    let plain = prepared.render(&pose);
    prepared.render_dps_into(&pose, set.camera(), &mut out, &DpsConfig::default());
    let border_uncovered = |img: &PremulImage| (0..H).filter(|&y| img.pixel(0, y)[3] < 128).count();
    assert!(border_uncovered(&plain) > 0);
    assert_eq!(border_uncovered(&out), border_uncovered(&plain));
}
