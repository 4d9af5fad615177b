//! Property tests of the CPU reference renderer against closed forms and a naive renderer.

use cpsl_core::{Camera, DepthGrid, Geometry, Layer, LayerSet, Limits, Pose, PremulImage, Vec3};
use cpsl_render::{Filter, PreparedLayers};
use cpsl_synth::layers::{meshed, slanted, synthetic_layer_set, Coverage};
use proptest::prelude::*;

/// Random premultiplied layers with random alpha (including 0 and 255 runs).
fn random_set(w: u32, h: u32, k: usize, seed: u64) -> LayerSet {
    let mut s = seed
        .wrapping_mul(6364136223846793005)
        .wrapping_add(1442695040888963407);
    let mut next = move || {
        s ^= s << 13;
        s ^= s >> 7;
        s ^= s << 17;
        s
    };
    let layers = (0..k)
        .map(|i| {
            let mut data = Vec::with_capacity((w * h * 4) as usize);
            for _ in 0..w * h {
                let r = next();
                let a = match r % 4 {
                    0 => 0u8,
                    1 => 255,
                    _ => (r >> 8) as u8,
                };
                for c in 0..3 {
                    let v = (r >> (16 + 8 * c)) as u8;
                    data.push(cpsl_core::image::premultiply(v, a));
                }
                data.push(a);
            }
            Layer::new(
                PremulImage::from_premul(w, h, data).unwrap(),
                1.0 + i as f64,
            )
        })
        .collect();
    LayerSet::new(Camera::from_fov(w, h, 60.0), layers, &Limits::default()).unwrap()
}

/// Straightforward renderer, independent of the homography code: each viewer ray meets each
/// layer's plane (`m . X = 1` in the reference frame, fronto-parallel or slanted), the point
/// projects into the reference camera, exact f64 bilinear filtering, equation 2 in f64.
fn naive_render(set: &LayerSet, pose: &Pose) -> Vec<[f64; 4]> {
    naive_render_with(set, pose, Filter::Bilinear)
}

/// Catmull-Rom weight of a tap at distance `d` px.
fn catmull_rom(d: f64) -> f64 {
    let d = d.abs();
    if d < 1.0 {
        1.5 * d * d * d - 2.5 * d * d + 1.0
    } else if d < 2.0 {
        -0.5 * d * d * d + 2.5 * d * d - 4.0 * d + 2.0
    } else {
        0.0
    }
}

/// [`naive_render`] with either filter. The cubic one reads 4x4 texels where one of the
/// central 2x2 is covered, and clamps alpha to [0, 1] and colour to [0, alpha].
fn naive_render_with(set: &LayerSet, pose: &Pose, filter: Filter) -> Vec<[f64; 4]> {
    let cam = set.camera();
    let (w, h) = (cam.width as i64, cam.height as i64);
    let texel = |l: &Layer, x: i64, y: i64| -> [f64; 4] {
        if x < 0 || y < 0 || x >= w || y >= h {
            [0.0; 4]
        } else {
            l.image.pixel(x as u32, y as u32).map(|v| v as f64 / 255.0)
        }
    };
    let t = pose.translation;
    // The reference position where the viewer ray through (x, y) meets the plane m . X = 1,
    // if it does in front of the viewer and the viewer is on the reference camera's side.
    let meet = |m: Vec3, x: f64, y: f64| -> Option<(f64, (f64, f64))> {
        let gap = 1.0 - m.dot(t);
        let r = pose.rotation * Vec3::new((x - cam.cx) / cam.fx, (y - cam.cy) / cam.fy, 1.0);
        if gap <= 1e-9 || m.dot(r) <= 0.0 {
            return None;
        }
        let along = gap / m.dot(r);
        Some((along, cam.project(r * along + t)?))
    };
    let hit = |l: &Layer, x: f64, y: f64| -> Option<(f64, f64)> {
        let Geometry::Mesh(g) = &l.geometry else {
            return meet(l.geometry.plane(l.depth), x, y).map(|h| h.1);
        };
        // A mesh: the nearest triangle whose plane the ray meets inside the triangle (as
        // seen in the reference image).
        let mut best: Option<(f64, (f64, f64))> = None;
        for cj in 0..g.rows - 1 {
            for ci in 0..g.cols - 1 {
                for tri in 0..2 {
                    let Some(m) = g.triangle_plane(cam, ci, cj, tri) else {
                        continue;
                    };
                    let Some((along, (u, v))) = meet(m, x, y) else {
                        continue;
                    };
                    let p = DepthGrid::triangle(ci, cj, tri)
                        .map(|(i, j)| g.vertex(i, j, cam.width, cam.height));
                    let side = |a: (f64, f64), b: (f64, f64)| {
                        (b.0 - a.0) * (v - a.1) - (b.1 - a.1) * (u - a.0) >= -1e-9
                    };
                    let inside = side(p[0], p[1]) && side(p[1], p[2]) && side(p[2], p[0]);
                    if inside && best.is_none_or(|b| along < b.0) {
                        best = Some((along, (u, v)));
                    }
                }
            }
        }
        best.map(|b| b.1)
    };
    let mut out = vec![[0.0; 4]; (w * h) as usize];
    for y in 0..h {
        for x in 0..w {
            let mut t = 1.0;
            let o = &mut out[(y * w + x) as usize];
            for l in set.layers() {
                let Some((sx, sy)) = hit(l, x as f64, y as f64) else {
                    continue;
                };
                let (x0, y0) = (sx.floor(), sy.floor());
                let (fx, fy) = (sx - x0, sy - y0);
                let (x0, y0) = (x0 as i64, y0 as i64);
                let mut p = [0.0; 4];
                let taps: Vec<(i64, i64, f64)> = match filter {
                    Filter::Bilinear => vec![
                        (0, 0, (1.0 - fx) * (1.0 - fy)),
                        (1, 0, fx * (1.0 - fy)),
                        (0, 1, (1.0 - fx) * fy),
                        (1, 1, fx * fy),
                    ],
                    Filter::Cubic => {
                        let centre = [(0, 0), (1, 0), (0, 1), (1, 1)];
                        if centre
                            .iter()
                            .all(|&(dx, dy)| texel(l, x0 + dx, y0 + dy) == [0.0; 4])
                        {
                            continue;
                        }
                        (-1..3)
                            .flat_map(|dy| (-1..3).map(move |dx| (dx, dy)))
                            .map(|(dx, dy)| {
                                let wgt = catmull_rom(fx - dx as f64) * catmull_rom(fy - dy as f64);
                                (dx, dy, wgt)
                            })
                            .collect()
                    }
                };
                for (dx, dy, wgt) in taps {
                    let s = texel(l, x0 + dx, y0 + dy);
                    for c in 0..4 {
                        p[c] += wgt * s[c];
                    }
                }
                if filter == Filter::Cubic {
                    p[3] = p[3].clamp(0.0, 1.0);
                    for c in 0..3 {
                        p[c] = p[c].clamp(0.0, p[3]);
                    }
                }
                for c in 0..4 {
                    o[c] += t * p[c];
                }
                t *= 1.0 - p[3];
            }
        }
    }
    out
}

/// Largest and mean absolute difference over all channels.
fn abs_diff(a: &[[f32; 4]], b: &[[f64; 4]]) -> (f64, f64) {
    let diffs = a
        .iter()
        .zip(b)
        .flat_map(|(p, q)| (0..4).map(move |c| (p[c] as f64 - q[c]).abs()));
    let (max, sum) = diffs.fold((0.0, 0.0), |(m, s), d| (f64::max(m, d), s + d));
    (max, sum / (4 * a.len().max(1)) as f64)
}

proptest! {
    #![proptest_config(ProptestConfig::with_cases(24))]

    /// Identity pose reproduces the closed-form composite of equation 2 within 1e-6, for
    /// fronto-parallel, slanted and mesh layers.
    #[test]
    fn identity_pose_reproduces_composite(w in 1u32..90, h in 1u32..70, k in 1usize..6, seed in any::<u64>()) {
        let set = random_set(w, h, k, seed);
        let expect = set.composite_reference();
        // Every geometry: the identity pose samples every texel exactly.
        for set in [set.clone(), slanted(set.clone()), meshed(set, 7)] {
            for filter in [Filter::Bilinear, Filter::Cubic] {
                let got = PreparedLayers::new(&set)
                    .with_filter(filter)
                    .render_f32(&Pose::IDENTITY, set.camera());
                for (g, e) in got.iter().zip(&expect) {
                    for c in 0..4 {
                        prop_assert!((g[c] - e[c]).abs() <= 1e-6, "{filter:?}: {g:?} vs {e:?}");
                    }
                }
            }
        }
    }

    /// Any pose (rotation, translation including towards the planes): the tiled, skipping
    /// renderer agrees with the naive f64 renderer within its documented sampling error.
    ///
    /// A sample is within 3 LSB of exact (1 LSB of 8-bit filtering, and positions within
    /// 1/256 px on each axis of a texture whose slope is at most 255 per pixel). Compositing
    /// `I = P_1 + (1 - a_1) I_rest` adds at most the errors of `P_1` and `a_1` per layer, so
    /// the composite is within `(2k - 1) * 3` LSB. The mean error catches anything systematic:
    /// over 500 random cases it stays below 0.36 LSB, and the largest single error seen is 3.05.
    #[test]
    fn matches_naive_renderer(
        seed in any::<u64>(), k in 1usize..5,
        tx in -0.3f64..0.3, ty in -0.3f64..0.3, tz in -0.5f64..0.9,
        rx in -8.0f64..8.0, ry in -8.0f64..8.0, rz in -8.0f64..8.0,
    ) {
        let set = random_set(83, 61, k, seed);
        let pose = Pose::from_euler_deg(Vec3::new(tx, ty, tz), rx, ry, rz);
        let got = PreparedLayers::new(&set).render_f32(&pose, set.camera());
        let (max, mean) = abs_diff(&got, &naive_render(&set, &pose));
        prop_assert!(max <= (2 * k - 1) as f64 * 3.0 / 255.0, "max error {max}");
        prop_assert!(mean <= 0.5 / 255.0, "mean error {mean}");
    }

    /// The same with the Catmull-Rom filter, on planes and meshes (the same bounds: a cubic
    /// sample's slope can exceed 255 per pixel only by its overshoot).
    #[test]
    fn cubic_filter_matches_naive_renderer(
        seed in any::<u64>(), k in 1usize..4, mesh in any::<bool>(),
        tx in -0.2f64..0.2, ty in -0.2f64..0.2, tz in -0.3f64..0.5,
        rx in -5.0f64..5.0, ry in -5.0f64..5.0, rz in -5.0f64..5.0,
    ) {
        let set = random_set(83, 61, k, seed);
        let set = if mesh { meshed(set, 9) } else { set };
        let pose = Pose::from_euler_deg(Vec3::new(tx, ty, tz), rx, ry, rz);
        let got = PreparedLayers::new(&set)
            .with_filter(Filter::Cubic)
            .render_f32(&pose, set.camera());
        let (max, mean) = abs_diff(&got, &naive_render_with(&set, &pose, Filter::Cubic));
        prop_assert!(max <= (2 * k - 1) as f64 * 3.0 / 255.0, "max error {max}");
        prop_assert!(mean <= 0.5 / 255.0, "mean error {mean}");
    }

    /// The same on depth meshes: each triangle's homography is the ray-triangle intersection,
    /// and the triangles of a grid leave no crack.
    #[test]
    fn meshes_match_naive_renderer(
        seed in any::<u64>(), k in 1usize..4, step in 6u32..24,
        tx in -0.2f64..0.2, ty in -0.2f64..0.2, tz in -0.3f64..0.5,
        rx in -5.0f64..5.0, ry in -5.0f64..5.0, rz in -5.0f64..5.0,
    ) {
        let set = meshed(random_set(83, 61, k, seed), step);
        let pose = Pose::from_euler_deg(Vec3::new(tx, ty, tz), rx, ry, rz);
        let got = PreparedLayers::new(&set).render_f32(&pose, set.camera());
        let (max, mean) = abs_diff(&got, &naive_render(&set, &pose));
        prop_assert!(max <= (2 * k - 1) as f64 * 3.0 / 255.0, "max error {max}");
        prop_assert!(mean <= 0.5 / 255.0, "mean error {mean}");
    }

    /// The same on slanted planes: each layer's homography is the ray-plane intersection.
    #[test]
    fn slanted_planes_match_naive_renderer(
        seed in any::<u64>(), k in 1usize..5,
        tx in -0.3f64..0.3, ty in -0.3f64..0.3, tz in -0.5f64..0.9,
        rx in -8.0f64..8.0, ry in -8.0f64..8.0, rz in -8.0f64..8.0,
    ) {
        let set = slanted(random_set(83, 61, k, seed));
        let pose = Pose::from_euler_deg(Vec3::new(tx, ty, tz), rx, ry, rz);
        let got = PreparedLayers::new(&set).render_f32(&pose, set.camera());
        let (max, mean) = abs_diff(&got, &naive_render(&set, &pose));
        prop_assert!(max <= (2 * k - 1) as f64 * 3.0 / 255.0, "max error {max}");
        prop_assert!(mean <= 0.5 / 255.0, "mean error {mean}");
    }
}

proptest! {
    #![proptest_config(ProptestConfig::with_cases(24))]

    /// The SIMD kernel (where the CPU has one) and the scalar kernel produce identical bits,
    /// on planes and on meshes (whose triangles' short spans end in a masked group), in
    /// `f32` and in 8-bit output.
    #[test]
    fn simd_and_scalar_kernels_agree_exactly(
        seed in any::<u64>(), k in 1usize..5, w in 1u32..150, h in 1u32..40,
        tx in -0.3f64..0.3, ty in -0.3f64..0.3, tz in -0.5f64..0.9,
        rx in -8.0f64..8.0, ry in -8.0f64..8.0, rz in -8.0f64..8.0,
        mesh in proptest::option::of(3u32..12),
    ) {
        let set = random_set(w, h, k, seed);
        let set = match mesh {
            Some(step) => meshed(set, step),
            None => set,
        };
        let pose = Pose::from_euler_deg(Vec3::new(tx, ty, tz), rx, ry, rz);
        let cam = *set.camera();
        let (simd, scalar) = (
            PreparedLayers::new(&set).with_simd(true),
            PreparedLayers::new(&set).with_simd(false),
        );
        for (a, b) in simd.render_f32(&pose, &cam).iter().zip(&scalar.render_f32(&pose, &cam)) {
            prop_assert_eq!(a.map(f32::to_bits), b.map(f32::to_bits));
        }
        // And the 8-bit output stage (its own AVX2 packing).
        let (a, b) = (simd.render(&pose), scalar.render(&pose));
        prop_assert_eq!(a.as_bytes(), b.as_bytes());
    }
}

#[test]
fn simd_kernel_is_used_where_available() {
    let set = random_set(16, 8, 1, 1);
    let p = PreparedLayers::new(&set);
    #[cfg(target_arch = "x86_64")]
    assert_eq!(p.simd(), std::arch::is_x86_feature_detected!("avx2"));
    assert!(!p.with_simd(false).simd());
}

#[test]
fn typical_content_matches_naive_and_skips_work() {
    let set = synthetic_layer_set(320, 200, 6, Coverage::Typical, 3);
    let pose = Pose::from_euler_deg(Vec3::new(0.1, -0.05, 0.2), 1.0, -2.0, 0.5);
    let prepared = PreparedLayers::new(&set);
    let (err, _) = abs_diff(
        &prepared.render_f32(&pose, set.camera()),
        &naive_render(&set, &pose),
    );
    assert!(err <= 3.0 / 255.0, "max error {err}");
    let mut out = PremulImage::new(320, 200);
    let stats = prepared.render_into(&pose, set.camera(), &mut out);
    assert!(
        stats.skipped > 0,
        "empty footprints must be skipped: {stats:?}"
    );
    assert!(
        stats.opaque_stops > 0,
        "opaque footprints must stop the layer loop: {stats:?}"
    );
}

#[test]
fn pure_translation_shifts_a_plane_by_f_t_over_z() {
    let set = synthetic_layer_set(200, 120, 1, Coverage::Typical, 9);
    let cam = *set.camera();
    let z = set.layers()[0].depth;
    // Choose t so that the shift f t / z is exactly 7 px.
    let t = 7.0 * z / cam.fx;
    let out = PreparedLayers::new(&set).render(&Pose::from_translation(Vec3::new(t, 0.0, 0.0)));
    let src = &set.layers()[0].image;
    for y in 0..cam.height {
        for x in 0..cam.width - 7 {
            assert_eq!(out.pixel(x, y), src.pixel(x + 7, y), "at ({x}, {y})");
        }
        // Content that came from outside the layer is transparent.
        assert_eq!(out.pixel(cam.width - 1, y)[3], 0);
    }
    // Half-pixel shift: each output is the rounded mean of two neighbours (within 1 LSB).
    let t = 0.5 * z / cam.fx;
    let out = PreparedLayers::new(&set).render(&Pose::from_translation(Vec3::new(0.0, t, 0.0)));
    for y in 0..cam.height - 1 {
        for x in 0..cam.width {
            let (a, b, o) = (src.pixel(x, y), src.pixel(x, y + 1), out.pixel(x, y));
            for c in 0..4 {
                let mean = (a[c] as f64 + b[c] as f64) / 2.0;
                assert!(
                    (o[c] as f64 - mean).abs() <= 1.0,
                    "({x},{y}) c{c}: {o:?} {a:?} {b:?}"
                );
            }
        }
    }
}

#[test]
fn plane_behind_viewer_is_not_drawn() {
    let set = synthetic_layer_set(64, 48, 2, Coverage::Dense, 1);
    let front = set.layers()[0].depth;
    let pose = Pose::from_translation(Vec3::new(0.0, 0.0, front + 0.1));
    let out = PreparedLayers::new(&set).render_f32(&pose, set.camera());
    // Only the back layer remains; it is opaque and seen from close up, so it fills the view.
    assert!(out.iter().all(|p| (p[3] - 1.0).abs() < 1e-6));
}

#[test]
fn renders_to_a_different_target_camera() {
    let set = synthetic_layer_set(160, 100, 3, Coverage::Typical, 5);
    let half = set.camera().scaled(0.5);
    let prepared = PreparedLayers::new(&set);
    let mut out = PremulImage::new(half.width, half.height);
    prepared.render_into(&Pose::IDENTITY, &half, &mut out);
    // The back layer is opaque, so the half-size view is fully covered.
    assert!(out.as_bytes().chunks_exact(4).all(|p| p[3] == 255));
}

#[test]
fn opaque_layer_moved_off_frame_edge_reveals_the_layer_behind() {
    // Two fully opaque layers: a near one that parallax slides off the frame edge and a far
    // one that must show through where the near one no longer covers.
    let (w, h) = (130u32, 70u32);
    let cam = Camera::from_fov(w, h, 60.0);
    let near = PremulImage::from_rgb(w, h, &vec![200u8; (w * h * 3) as usize]).unwrap();
    let far = PremulImage::from_rgb(w, h, &vec![50u8; (w * h * 3) as usize]).unwrap();
    let set = LayerSet::new(
        cam,
        vec![Layer::new(near, 1.0), Layer::new(far, 10.0)],
        &Limits::default(),
    )
    .unwrap();
    let pose = Pose::from_translation(Vec3::new(0.05, 0.03, 0.0));
    let got = PreparedLayers::new(&set).render_f32(&pose, &cam);
    let (err, _) = abs_diff(&got, &naive_render(&set, &pose));
    assert!(err <= 3.0 / 255.0, "max error {err}");
    let p = got[((h - 3) * w + w - 3) as usize];
    assert!(
        (p[0] - 50.0 / 255.0).abs() < 1e-3 && (p[3] - 1.0).abs() < 1e-6,
        "far layer visible near the corner: {p:?}"
    );
}

#[test]
fn cubic_filter_keeps_detail_that_bilinear_blurs() {
    // A stripe pattern of period 6 px shifted by half a pixel: bilinear attenuates it by
    // cos(pi / 6) (13 % of the amplitude lost), Catmull-Rom by less than a quarter of that.
    let (w, h) = (96u32, 8u32);
    let cam = Camera::from_fov(w, h, 60.0);
    let wave = |x: f64| 128.0 + 100.0 * (2.0 * std::f64::consts::PI * x / 6.0).sin();
    let rgb: Vec<u8> = (0..w * h)
        .flat_map(|i| [wave((i % w) as f64).round() as u8; 3])
        .collect();
    let set = LayerSet::new(
        cam,
        vec![Layer::new(PremulImage::from_rgb(w, h, &rgb).unwrap(), 2.0)],
        &Limits::default(),
    )
    .unwrap();
    let pose = Pose::from_translation(Vec3::new(0.5 * 2.0 / cam.fx, 0.0, 0.0));
    let rms = |filter: Filter| {
        let out = PreparedLayers::new(&set).with_filter(filter).render(&pose);
        let err: Vec<f64> = (4..w - 4)
            .map(|x| out.pixel(x, 4)[0] as f64 - wave(x as f64 + 0.5))
            .collect();
        (err.iter().map(|e| e * e).sum::<f64>() / err.len() as f64).sqrt()
    };
    let (bilinear, cubic) = (rms(Filter::Bilinear), rms(Filter::Cubic));
    assert!(bilinear > 8.0, "bilinear rms {bilinear}");
    assert!(
        cubic < 0.25 * bilinear,
        "cubic rms {cubic} vs bilinear {bilinear}"
    );
}
