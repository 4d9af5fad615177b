//! Baselines that do not use layers, run through the same evaluation as CPSL.

use cpsl_core::fill::push_pull;
use cpsl_core::{Camera, Pose};

/// A view synthesised by a baseline.
#[derive(Debug, Clone, PartialEq)]
pub struct Synthesised {
    /// RGB, 3 bytes per pixel (black where nothing landed, unless filled).
    pub rgb: Vec<u8>,
    /// Pixels that received content from the reference (before any hole filling).
    pub covered: Vec<bool>,
}

/// Depth-image-based rendering: every reference pixel with a valid depth is unprojected,
/// moved into the viewer's frame and splatted to the nearest target pixel, the nearest surface
/// winning (z-buffer). Without `fill`, pixels that receive nothing stay black: the cracks
/// where surfaces stretch and the holes where background is revealed. With `fill`, they are
/// push-pull filled from the covered pixels.
pub fn dibr(
    rgb: &[u8],
    depth: &[f32],
    src: &Camera,
    pose: &Pose,
    dst: &Camera,
    fill: bool,
) -> Synthesised {
    let (sw, sh) = (src.width as usize, src.height as usize);
    let (dw, dh) = (dst.width as usize, dst.height as usize);
    assert_eq!(rgb.len(), sw * sh * 3, "dibr: colour size");
    assert_eq!(depth.len(), sw * sh, "dibr: depth size");
    let mut zbuf = vec![f64::INFINITY; dw * dh];
    let mut out = vec![0u8; dw * dh * 3];
    for v in 0..sh {
        for u in 0..sw {
            let z = depth[v * sw + u];
            if !(z.is_finite() && z > 0.0) {
                continue;
            }
            let p = pose.ref_to_view(src.unproject(u as f64, v as f64, z as f64));
            let Some((x, y)) = dst.project(p) else {
                continue;
            };
            let (xi, yi) = (x.round(), y.round());
            if xi < 0.0 || yi < 0.0 || xi >= dw as f64 || yi >= dh as f64 {
                continue;
            }
            let i = yi as usize * dw + xi as usize;
            if p.z() < zbuf[i] {
                zbuf[i] = p.z();
                out[i * 3..i * 3 + 3].copy_from_slice(&rgb[(v * sw + u) * 3..(v * sw + u) * 3 + 3]);
            }
        }
    }
    let covered: Vec<bool> = zbuf.iter().map(|z| z.is_finite()).collect();
    if fill {
        let mut col: Vec<f32> = out.iter().map(|&c| c as f32).collect();
        let w: Vec<f32> = covered.iter().map(|&c| c as u8 as f32).collect();
        if push_pull(&mut col, &w, dw, dh, 3) {
            out = col
                .iter()
                .map(|v| v.round().clamp(0.0, 255.0) as u8)
                .collect();
        }
    }
    Synthesised { rgb: out, covered }
}

#[cfg(test)]
mod tests {
    use super::*;
    use cpsl_core::Vec3;

    #[test]
    fn identity_reproduces_and_translation_shifts_by_disparity() {
        let cam = Camera::from_fov(40, 20, 60.0);
        let rgb: Vec<u8> = (0..40 * 20 * 3).map(|i| (i % 251) as u8).collect();
        let depth = vec![2.0f32; 40 * 20];
        let same = dibr(&rgb, &depth, &cam, &Pose::IDENTITY, &cam, false);
        assert_eq!(same.rgb, rgb);
        assert!(same.covered.iter().all(|&c| c));
        // Moving right by t shifts content left by f t / z = 3 px.
        let t = 3.0 * 2.0 / cam.fx;
        let moved = dibr(
            &rgb,
            &depth,
            &cam,
            &Pose::from_translation(Vec3::new(t, 0.0, 0.0)),
            &cam,
            false,
        );
        assert_eq!(&moved.rgb[..3], &rgb[9..12]);
        assert!(!moved.covered[39], "the right edge is revealed");
        let filled = dibr(
            &rgb,
            &depth,
            &cam,
            &Pose::from_translation(Vec3::new(t, 0.0, 0.0)),
            &cam,
            true,
        );
        assert_ne!(&filled.rgb[39 * 3..40 * 3], &[0, 0, 0], "holes are filled");
    }

    #[test]
    fn nearer_surface_wins() {
        let cam = Camera::from_fov(8, 1, 60.0);
        let rgb: Vec<u8> = (0..8).flat_map(|i| [i as u8 * 30; 3]).collect();
        // Pixel 4 is near, everything else far: moving left makes pixel 4 land on pixel 5's
        // spot, where it must win over the far pixel that also lands there.
        let mut depth = vec![100.0f32; 8];
        depth[4] = 1.0;
        let t = -1.0 / cam.fx; // 1 px shift to the right for the near pixel
        let out = dibr(
            &rgb,
            &depth,
            &cam,
            &Pose::from_translation(Vec3::new(t, 0.0, 0.0)),
            &cam,
            false,
        );
        assert_eq!(out.rgb[5 * 3], 4 * 30);
    }
}
