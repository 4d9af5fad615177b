//! Coverage metrics of a synthesised view (defined in EVALUATION.md). `V` is the set of pixels
//! the method covered (accumulated alpha at least 1/2, or a splat landed) before any hole
//! filling.
//!
//! * hole ratio = `|not V| / |image|`;
//! * crack ratio = `|close3x3(V) \ V| / |band|` counted inside `band`, the pixels within `r`
//!   of depth edges of the target view: one-pixel gaps along silhouettes.

use cpsl_core::{Camera, Pose};

/// `|not V| / |image|`.
pub fn hole_ratio(covered: &[bool]) -> f64 {
    covered.iter().filter(|&&c| !c).count() as f64 / covered.len().max(1) as f64
}

/// 3x3 closing: dilation then erosion with a 3x3 square, the outside of the image counting
/// as uncovered (and `V` kept). Uncovered pixels on the image border therefore never close: a
/// strip revealed along the frame edge is not a crack.
pub fn close3x3(v: &[bool], w: usize, h: usize) -> Vec<bool> {
    let dilated: Vec<bool> = (0..w * h)
        .map(|p| {
            let (x, y) = (p % w, p / w);
            (y.saturating_sub(1)..(y + 2).min(h))
                .any(|yy| (x.saturating_sub(1)..(x + 2).min(w)).any(|xx| v[yy * w + xx]))
        })
        .collect();
    (0..w * h)
        .map(|p| {
            let (x, y) = (p % w, p / w);
            v[p] || (x > 0
                && y > 0
                && x + 1 < w
                && y + 1 < h
                && (y - 1..y + 2).all(|yy| (x - 1..x + 2).all(|xx| dilated[yy * w + xx])))
        })
        .collect()
}

/// `|close3x3(V) \ V ∩ band| / |band|`; 0 when the band is empty.
pub fn crack_ratio(covered: &[bool], band: &[bool], w: usize, h: usize) -> f64 {
    let n = band.iter().filter(|&&b| b).count();
    if n == 0 {
        return 0.0;
    }
    let closed = close3x3(covered, w, h);
    let cracks = (0..w * h)
        .filter(|&p| band[p] && closed[p] && !covered[p])
        .count();
    cracks as f64 / n as f64
}

/// The co-visibility mask of a target view: pixels that see surfaces the reference saw, i.e.
/// where a per-pixel forward warp of the reference with `depth` lands, with its one- and
/// two-pixel cracks closed (two 3x3 closings). Disocclusions and content outside the
/// reference frame are excluded. The same mask scores every method of a comparison.
pub fn covisible(depth: &[f32], src: &Camera, pose: &Pose, dst: &Camera) -> Vec<bool> {
    let black = vec![0u8; depth.len() * 3];
    let warped = crate::baselines::dibr(&black, depth, src, pose, dst, false);
    let (w, h) = (dst.width as usize, dst.height as usize);
    close3x3(&close3x3(&warped.covered, w, h), w, h)
}

/// The band of a target view: pixels within `r` (Chebyshev distance) of a depth edge, found by
/// forward-projecting the reference's depth edges (4-neighbours whose depths differ by more
/// than `ratio`, the nearer pixel of the pair) into the target with the reference depth.
pub fn edge_band(
    depth: &[f32],
    src: &Camera,
    pose: &Pose,
    dst: &Camera,
    ratio: f32,
    r: usize,
) -> Vec<bool> {
    let (sw, sh) = (src.width as usize, src.height as usize);
    let (dw, dh) = (dst.width as usize, dst.height as usize);
    let valid = |z: f32| z.is_finite() && z > 0.0;
    let mut edge = vec![false; dw * dh];
    for v in 0..sh {
        for u in 0..sw {
            let z = depth[v * sw + u];
            if !valid(z) {
                continue;
            }
            let is_edge = [
                (u + 1, v),
                (u, v + 1),
                (u.wrapping_sub(1), v),
                (u, v.wrapping_sub(1)),
            ]
            .iter()
            .any(|&(x, y)| {
                x < sw && y < sh && {
                    let o = depth[y * sw + x];
                    valid(o) && o > z * (1.0 + ratio)
                }
            });
            if !is_edge {
                continue;
            }
            let p = pose.ref_to_view(src.unproject(u as f64, v as f64, z as f64));
            if let Some((x, y)) = dst.project(p) {
                let (x, y) = (x.round(), y.round());
                if x >= 0.0 && y >= 0.0 && x < dw as f64 && y < dh as f64 {
                    edge[y as usize * dw + x as usize] = true;
                }
            }
        }
    }
    // Dilate by r.
    let mut row = vec![false; dw * dh];
    for y in 0..dh {
        for x in 0..dw {
            row[y * dw + x] = edge[y * dw + x.saturating_sub(r)..y * dw + (x + r + 1).min(dw)]
                .iter()
                .any(|&b| b);
        }
    }
    (0..dw * dh)
        .map(|p| {
            let (x, y) = (p % dw, p / dw);
            (y.saturating_sub(r)..(y + r + 1).min(dh)).any(|yy| row[yy * dw + x])
        })
        .collect()
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn hole_and_crack_ratios_on_known_masks() {
        let (w, h) = (10, 6);
        let mut v = vec![true; w * h];
        // A one-pixel vertical crack at x = 4 and a 3-pixel-wide hole at x = 7..=9 on row 0.
        for y in 0..h {
            v[y * w + 4] = false;
        }
        v[7..10].fill(false);
        assert!((hole_ratio(&v) - 9.0 / 60.0).abs() < 1e-12);
        let band = vec![true; w * h];
        // The closing fills the crack column away from the image border; the hole on the
        // border row is not a crack.
        let closed = close3x3(&v, w, h);
        assert!((1..h - 1).all(|y| closed[y * w + 4]));
        assert!(!closed[4] && !closed[(h - 1) * w + 4] && !closed[8]);
        let c = crack_ratio(&v, &band, w, h);
        assert!((c - 4.0 / 60.0).abs() < 1e-12, "{c}");
        // Outside the band nothing counts.
        let none = vec![false; w * h];
        assert_eq!(crack_ratio(&v, &none, w, h), 0.0);
        let mut left = vec![false; w * h];
        (0..h).for_each(|y| left[y * w + 4] = true);
        assert!((crack_ratio(&v, &left, w, h) - 4.0 / 6.0).abs() < 1e-12);
        // Full coverage: no cracks.
        assert_eq!(crack_ratio(&vec![true; w * h], &band, w, h), 0.0);
    }

    #[test]
    fn covisibility_excludes_disocclusions_and_the_revealed_border() {
        let cam = Camera::from_fov(40, 10, 60.0);
        // Near plane on the left half, far on the right; the viewer moves right, so the near
        // half shifts left more: a disocclusion opens at the edge and the right border is
        // revealed.
        let depth: Vec<f32> = (0..400)
            .map(|i| if i % 40 < 20 { 1.0 } else { 4.0 })
            .collect();
        let shift = 8.0; // pixels of the near plane (the far one moves 2)
        let pose = Pose::from_translation(cpsl_core::Vec3::new(shift / cam.fx, 0.0, 0.0));
        let m = covisible(&depth, &cam, &pose, &cam);
        for y in 0..10 {
            let row: Vec<bool> = (0..40).map(|x| m[y * 40 + x]).collect();
            // The near plane now covers x = 0..=11, the far plane x = 18..=37.
            assert!(row[..12].iter().all(|&b| b), "{row:?}");
            assert!(
                row[13..17].iter().all(|&b| !b),
                "disocclusion excluded: {row:?}"
            );
            assert!(row[18..38].iter().all(|&b| b), "{row:?}");
            assert!(!row[38] && !row[39], "revealed border excluded: {row:?}");
        }
        assert!(covisible(&depth, &cam, &Pose::IDENTITY, &cam)
            .iter()
            .all(|&b| b));
    }

    #[test]
    fn band_follows_the_projected_edge() {
        let cam = Camera::from_fov(20, 10, 60.0);
        // Near plane on the left half, far on the right: edge at x = 9 (the nearer side).
        let depth: Vec<f32> = (0..200)
            .map(|i| if i % 20 < 10 { 1.0 } else { 4.0 })
            .collect();
        let band = edge_band(&depth, &cam, &Pose::IDENTITY, &cam, 0.1, 1);
        for y in 0..10 {
            for x in 0..20 {
                assert_eq!(band[y * 20 + x], (8..=10).contains(&x), "({x}, {y})");
            }
        }
    }
}
