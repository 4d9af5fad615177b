//! Synthetic ground truth on disk: the built-in ray-cast scene's input view, exact depth,
//! object ids and ground-truth novel views, as files that every command reads.

use crate::error::PipelineError;
use cpsl_core::{Camera, Pose, Progress, ProgressEvent};
use cpsl_io::images::write_png;
use cpsl_io::pfm::{write_pfm, FloatImage};
use cpsl_synth::Scene;
use serde::Serialize;
use std::path::PathBuf;

type Result<T> = std::result::Result<T, PipelineError>;

/// What `synthesise` writes.
#[derive(Debug, Clone)]
pub struct SynthOptions {
    /// Output folder.
    pub output: PathBuf,
    /// Image width.
    pub width: u32,
    /// Image height.
    pub height: u32,
    /// Scene time in seconds (objects move with their velocities).
    pub time: f64,
    /// Supersamples per pixel side for colour (anti-aliasing).
    pub supersample: u32,
}

/// One ground-truth view in `views.json`.
#[derive(Clone, Serialize)]
pub struct ViewEntry {
    /// View name.
    pub name: String,
    /// Image file, relative to the synth folder.
    pub file: String,
    /// Pose as accepted by `cpsl render --pose`.
    pub pose: String,
    /// The full pose.
    pub pose_matrix: Pose,
}

/// `views.json`.
#[derive(Serialize)]
struct ViewsFile<'a> {
    camera: &'a Camera,
    time: f64,
    views: Vec<ViewEntry>,
}

/// A synthetic scene written to disk.
pub struct SynthOutput {
    /// The scene.
    pub scene: Scene,
    /// Input view RGB.
    pub rgb: Vec<u8>,
    /// Input z-depth.
    pub depth: Vec<f32>,
    /// Ground-truth views: entry and RGB.
    pub views: Vec<(ViewEntry, Vec<u8>)>,
}

fn pose_string(p: &Pose) -> String {
    let (rx, ry, rz) = p.euler_deg();
    let t = p.translation;
    // Adding 0.0 turns -0.0 into 0.0; values are rounded to 1e-9 to drop float noise.
    let v = [t.x(), t.y(), t.z(), rx, ry, rz].map(|v| ((v * 1e9).round() / 1e9) + 0.0);
    format!("{},{},{},{},{},{}", v[0], v[1], v[2], v[3], v[4], v[5])
}

/// Renders the default scene and its ground-truth views and writes them to `a.output`:
/// `input.png`, `depth.pfm` (+ `depth.png` preview), `objects.png`, `camera.json`,
/// `scene.json`, `views/*.png` and `views.json`.
pub fn synthesise(a: &SynthOptions, progress: &dyn Progress) -> Result<SynthOutput> {
    if !((16..=8192).contains(&a.width) && (16..=8192).contains(&a.height)) {
        return Err(PipelineError::Invalid(format!(
            "--width and --height must be in 16..=8192, found {}x{}",
            a.width, a.height
        )));
    }
    let dir = &a.output;
    let views_dir = dir.join("views");
    std::fs::create_dir_all(&views_dir).map_err(|source| PipelineError::File {
        path: views_dir,
        source,
    })?;
    let scene = Scene::default_scene(a.width, a.height);
    let cam = scene.camera;
    let views = Scene::default_views();
    progress.event(ProgressEvent::Start {
        stage: "ray cast views",
        total: Some(views.len() as u64 + 1),
    });
    let input = scene.render(&cam, &Pose::IDENTITY, a.time, a.supersample);
    progress.event(ProgressEvent::Advance {
        stage: "ray cast views",
        done: 1,
    });
    write_png(&dir.join("input.png"), cam.width, cam.height, 3, &input.rgb)?;
    let depth = FloatImage {
        width: cam.width,
        height: cam.height,
        data: input.depth.clone(),
    };
    write_pfm(&dir.join("depth.pfm"), &depth)?;
    write_png(
        &dir.join("depth.png"),
        cam.width,
        cam.height,
        1,
        &depth_preview(&input.depth),
    )?;
    let ids: Vec<u8> = input.object.iter().map(|&o| o.min(255) as u8).collect();
    write_png(&dir.join("objects.png"), cam.width, cam.height, 1, &ids)?;
    cpsl_io::write_json(&dir.join("camera.json"), &cam)?;
    cpsl_io::write_json(&dir.join("scene.json"), &scene)?;
    let mut out_views = Vec::new();
    for (i, (name, pose)) in views.iter().enumerate() {
        let v = scene.render(&cam, pose, a.time, a.supersample);
        let file = format!("views/{name}.png");
        write_png(&dir.join(&file), cam.width, cam.height, 3, &v.rgb)?;
        out_views.push((
            ViewEntry {
                name: name.clone(),
                file,
                pose: pose_string(pose),
                pose_matrix: *pose,
            },
            v.rgb,
        ));
        progress.event(ProgressEvent::Advance {
            stage: "ray cast views",
            done: i as u64 + 2,
        });
    }
    progress.event(ProgressEvent::Finish {
        stage: "ray cast views",
    });
    let file = ViewsFile {
        camera: &cam,
        time: a.time,
        views: out_views.iter().map(|(e, _)| e.clone()).collect(),
    };
    cpsl_io::write_json(&dir.join("views.json"), &file)?;
    Ok(SynthOutput {
        scene,
        rgb: input.rgb,
        depth: input.depth,
        views: out_views,
    })
}

/// 8-bit preview of a depth map: inverse depth normalised to [0, 255] (near is bright).
fn depth_preview(depth: &[f32]) -> Vec<u8> {
    let inv: Vec<f32> = depth
        .iter()
        .map(|&z| {
            if z.is_finite() && z > 0.0 {
                1.0 / z
            } else {
                0.0
            }
        })
        .collect();
    let (lo, hi) = inv
        .iter()
        .fold((f32::MAX, 0f32), |(a, b), &v| (a.min(v), b.max(v)));
    let span = (hi - lo).max(1e-12);
    inv.iter()
        .map(|&v| ((v - lo) / span * 255.0).round() as u8)
        .collect()
}
