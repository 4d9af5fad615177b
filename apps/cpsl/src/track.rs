//! `cpsl track`: a video's camera path from the video itself, written as `poses.json` and a
//! NeRF-style `transforms.json`.

use crate::layer::CameraArgs;
use crate::progress::Bars;
use anyhow::Result;
use clap::Args;
use cpsl_pipeline::track::{pose_files, track_video};
use std::path::PathBuf;

/// Arguments of `cpsl track`.
#[derive(Args)]
pub struct TrackArgs {
    /// A video file or a folder of PNG/JPEG frames.
    pub input: PathBuf,
    /// Output `poses.json`: per frame the camera-to-world pose (OpenCV axes, the first
    /// frame's camera as the world, the first baseline as the unit), PnP inliers, whether it
    /// was placed and its segment (where tracking broke off, at a jump or a cut, the frames
    /// after it are solved again as a new segment with its own world and unit); the camera
    /// motion found (translating, rotating, static, untracked).
    #[arg(short, long)]
    pub output: PathBuf,
    /// Also write the placed frames as a NeRF-style `transforms.json` (OpenGL axes; readable
    /// by instant-ngp, nerfstudio and Gaussian-splatting tools); of several segments, the one
    /// with the most placed frames.
    #[arg(long)]
    pub transforms: Option<PathBuf>,
    #[command(flatten)]
    pub camera: CameraArgs,
    #[command(flatten)]
    pub tracking: crate::layer::TrackingArgs,
    /// Stop after this many frames.
    #[arg(long)]
    pub max_frames: Option<usize>,
}

/// Runs `cpsl track`.
pub fn run(a: TrackArgs) -> Result<()> {
    let (t, camera, names) = track_video(
        &a.input,
        &a.camera.choice(),
        a.tracking.config(),
        a.max_frames,
        &Bars::default(),
    )?;
    let dir = a.input.is_dir().then_some(a.input.as_path());
    let (poses, nerf) = pose_files(&t, camera, &names, dir);
    cpsl_io::write_json(&a.output, &poses)?;
    if let Some(path) = &a.transforms {
        cpsl_io::write_json(path, &nerf)?;
    }
    let placed = t.poses.iter().filter(|p| p.is_some()).count();
    let (segments, worlds) = (t.segments(), t.worlds());
    println!(
        "{}: camera {}, {placed} of {} frames placed{}, {} points, reprojection {}; wrote {}{}",
        a.input.display(),
        t.motion.name(),
        names.len(),
        match (segments, worlds) {
            (1, _) => String::new(),
            (s, 1) => format!(
                " in {s} segments (tracking broke off between them; relocalisation tied them \
                 into one world)"
            ),
            (s, w) => format!(
                " in {s} segments (tracking broke off between them) and {w} worlds (segments \
                 relocalisation could not tie have their own origin and scale)"
            ),
        },
        t.points,
        if t.reprojection_px.is_finite() {
            format!("{:.2} px", t.reprojection_px)
        } else {
            "-".into()
        },
        a.output.display(),
        a.transforms
            .as_ref()
            .map_or(String::new(), |p| format!(" and {}", p.display()))
    );
    if let Some(path) = a.transforms.as_ref().filter(|_| worlds > 1) {
        eprintln!(
            "note: {} holds world {} only (the one with the most placed frames)",
            path.display(),
            t.largest_world()
        );
    }
    if placed == 0 {
        eprintln!(
            "note: no pose without a baseline (the camera {}); depth must come from a model",
            match t.motion.name() {
                "static" => "barely moves",
                "rotating" => "only turns, or the scene is one plane",
                _ => "could not be tracked: too little texture or too few frames",
            }
        );
    }
    Ok(())
}
