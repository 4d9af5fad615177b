//! Content-promoted layering on the synthetic scene, where the true object partition and
//! depths are known.

use cpsl_core::{LayerRole, NoProgress, Pose};
use cpsl_layering::{layer_frame, LayeringConfig};
use cpsl_render::PreparedLayers;
use cpsl_synth::Scene;

/// Objects of the default scene that stand in front of the wall and floor, with depths.
const OBJECTS: [(&str, f64); 4] = [("board", 2.5), ("pole", 3.2), ("disc", 4.0), ("panel", 6.0)];

fn psnr(a: &[u8], b: &[u8]) -> f64 {
    let mse = a
        .iter()
        .zip(b)
        .map(|(&x, &y)| (x as f64 - y as f64).powi(2))
        .sum::<f64>()
        / a.len() as f64;
    10.0 * (255.0f64 * 255.0 / mse.max(1e-12)).log10()
}

/// IoU of each foreground object with the layer that holds most of it, and that layer.
fn object_iou(scene: &Scene, object: &[u16], owner: &[u8]) -> Vec<(String, f64, usize)> {
    OBJECTS
        .iter()
        .map(|(name, _)| {
            let id = scene.objects.iter().position(|o| o.name == *name).unwrap() as u16;
            let layers = *owner.iter().max().unwrap() as usize + 1;
            let mut inter = vec![0usize; layers];
            let mut size = vec![0usize; layers];
            let mut area = 0;
            for (&o, &l) in object.iter().zip(owner) {
                size[l as usize] += 1;
                if o == id {
                    area += 1;
                    inter[l as usize] += 1;
                }
            }
            let best = (0..layers).max_by_key(|&l| inter[l]).unwrap();
            let iou = inter[best] as f64 / (area + size[best] - inter[best]) as f64;
            (name.to_string(), iou, best)
        })
        .collect()
}

#[test]
fn label_map_matches_objects_layers_are_ordered_and_identity_reproduces_input() {
    let scene = Scene::default_scene(320, 240);
    let view = scene.render(&scene.camera, &Pose::IDENTITY, 0.0, 2);
    let cfg = LayeringConfig::default();
    let (_, out) = layer_frame(&view.rgb, &view.depth, scene.camera, &cfg, &NoProgress).unwrap();
    let set = &out.set;
    assert!(set.len() <= 6 && set.len() >= 4, "{} layers", set.len());

    let ious = object_iou(&scene, &view.object, &out.owner);
    let (_, base) = layer_frame(
        &view.rgb,
        &view.depth,
        scene.camera,
        &cfg.depth_only(),
        &NoProgress,
    )
    .unwrap();
    let base_ious = object_iou(&scene, &view.object, &base.owner);
    for ((name, iou, layer), (_, b, _)) in ious.iter().zip(&base_ious) {
        eprintln!(
            "{name}: IoU {iou:.3} (depth only {b:.3}), layer {layer} at z {:.3}",
            set.layers()[*layer].depth
        );
    }
    let mean = ious.iter().map(|r| r.1).sum::<f64>() / ious.len() as f64;
    let base_mean = base_ious.iter().map(|r| r.1).sum::<f64>() / ious.len() as f64;
    eprintln!("mean IoU {mean:.3}, depth only {base_mean:.3}");
    for l in set.layers() {
        eprintln!("layer z {:.3} {:?}", l.depth, l.meta);
    }
    // The fronto-parallel objects each get a layer of their own at their true depth; the
    // slanted panel shares its layer with the floor at the same depth.
    for (name, iou, layer) in &ious[..3] {
        let z = OBJECTS.iter().find(|o| o.0 == name).unwrap().1;
        assert!(*iou > 0.95, "{name}: IoU {iou:.3}");
        assert!(
            (set.layers()[*layer].depth - z).abs() < 0.01 * z,
            "{name} layer depth"
        );
    }
    assert!(
        mean > base_mean + 0.1,
        "promotion improves the partition: {mean:.3} vs {base_mean:.3}"
    );
    // Layers are ordered like the objects they hold.
    assert!(ious[..3].windows(2).all(|w| w[0].2 < w[1].2));

    // Identity render reproduces the input.
    let img = PreparedLayers::new(set).render(&Pose::IDENTITY);
    let p = psnr(&img.over_background([0, 0, 0]), &view.rgb);
    eprintln!("identity PSNR {p:.2} dB");
    assert!(p >= 45.0, "identity PSNR {p:.2} dB");
    assert!(set.layers().windows(2).all(|w| w[0].depth < w[1].depth));
    assert_eq!(
        set.layers().last().unwrap().meta.role,
        Some(LayerRole::Background)
    );
    assert!(!out.edc.samples.is_empty());
}
