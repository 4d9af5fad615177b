//! `cpsl eval-video`: the temporal-stability ablation (paper Table 2) on moving clips:
//! frame-wise depth slicing (the normalising baseline), frame-wise CPSL, I/P propagation,
//! and I/P with refinement and adaptive refresh with hysteresis.

use crate::util::FilterArg;
use anyhow::Result;
use clap::{Args, ValueEnum};
use cpsl_eval::video::{evaluate_video, Clip, VideoOptions, VideoRow};
use cpsl_layering::GeometryMode;
use std::path::PathBuf;

/// The clips.
#[derive(ValueEnum, Clone, Copy, Debug, PartialEq, Eq)]
pub enum ClipArg {
    /// The built-in scene with its moving board, pole and disc (exact depth, true motion and
    /// ray-cast novel views).
    Synthetic,
    /// HCI backgammon, the centre row of the 9x9 grid as a camera sweep (ground-truth depth
    /// warped to each view; the row above as novel views).
    HciRow,
    /// The fox handheld phone video (50 frames, a quarter of full size, FastDepth scaled by the
    /// poses; each frame rendered at the next frame's camera and scored against it).
    Fox,
    /// KITTI odometry 06 colour frames 12, 13, 14, 17 (FastDepth).
    Kitti,
    /// All of the above.
    All,
}

impl From<ClipArg> for Clip {
    fn from(c: ClipArg) -> Self {
        match c {
            ClipArg::Synthetic => Clip::Synthetic,
            ClipArg::HciRow => Clip::HciRow,
            ClipArg::Fox => Clip::Fox,
            ClipArg::Kitti => Clip::Kitti,
            ClipArg::All => Clip::All,
        }
    }
}

/// Arguments of `cpsl eval-video`.
#[derive(Args)]
pub struct EvalVideoArgs {
    /// Clip.
    #[arg(value_enum, default_value_t = ClipArg::All)]
    pub clip: ClipArg,
    /// Folder holding the datasets.
    #[arg(long, default_value = "../shared/data")]
    pub data: PathBuf,
    /// Frames per group of pictures for the I/P methods.
    #[arg(long, default_value_t = 30)]
    pub gop: usize,
    /// Number of layers K.
    #[arg(long, default_value_t = 6)]
    pub layers: usize,
    /// Layer surfaces: `plane`, `slanted` (video's default) or `mesh` (single images').
    #[arg(long, long_help = crate::util::GEOMETRY_HELP)]
    pub geometry: Option<GeometryMode>,
    /// How the CPU renderer resamples the layers for the novel views: `cubic` (Catmull-Rom,
    /// sharper, as `cpsl render`) or `bilinear` (the players' real-time default).
    #[arg(long, value_enum, default_value_t = FilterArg::Cubic)]
    pub filter: FilterArg,
    /// Skip the flicker score (it needs the LPIPS model of scripts/setup-models.sh).
    #[arg(long)]
    pub no_lpips: bool,
    /// Give the I/P methods the clip's true motion instead of estimating it (only the
    /// synthetic clip has one): what propagation scores with perfect motion.
    #[arg(long)]
    pub true_motion: bool,
    /// Depth of the fox: `video` (the default: from the video itself, camera tracking and
    /// multi-view depth fused with FastDepth) or `fastdepth` (per frame, one scale for the clip).
    #[arg(long, default_value = "video", value_parser = ["fastdepth", "video"])]
    pub depth: String,
    /// Write the results as JSON.
    #[arg(long)]
    pub json: Option<PathBuf>,
}

/// Runs `cpsl eval-video`.
pub fn run(a: EvalVideoArgs) -> Result<()> {
    let opts = VideoOptions {
        clip: a.clip.into(),
        data: a.data,
        gop: a.gop,
        layers: a.layers,
        geometry: a.geometry,
        lpips: !a.no_lpips,
        true_motion: a.true_motion,
        video_depth: a.depth == "video",
        filter: a.filter.into(),
    };
    println!(
        "{:<10} {:<36} {:>6} {:>9} {:>9} {:>8} {:>8} {:>8} {:>8} {:>8}",
        "clip",
        "method",
        "I/all",
        "bnd px^2",
        "vs fw",
        "F-SSIM",
        "warp",
        "flicker",
        "PSNR",
        "LPIPS"
    );
    let opt = |v: Option<f64>, p: usize| v.map_or("-".to_string(), |x| format!("{x:.p$}"));
    let rows = evaluate_video(&opts, |row| match row {
        VideoRow::Scored(row) => println!(
            "{:<10} {:<36} {:>6} {:>9.3} {:>9.3} {:>8.4} {:>8.4} {:>8} {:>8} {:>8}",
            row.clip,
            row.method,
            format!("{}/{}", row.i_frames, row.frames),
            row.boundary_variance_px2,
            row.boundary_variance_vs_frame_wise,
            row.f_ssim,
            row.warping_error,
            opt(row.flicker, 4),
            opt(row.psnr, 2),
            opt(row.lpips, 3),
        ),
        VideoRow::ObjectPartition {
            clip,
            boundary_variance_px2,
        } => println!(
            "{:<10} {:<36} {:>6} {:>9.3}   (exact object contours moving with the true motion)",
            clip, "true object partition", "-", boundary_variance_px2
        ),
    })?;
    if let Some(p) = &a.json {
        cpsl_io::write_json(p, &rows)?;
        println!("wrote {}", p.display());
    }
    Ok(())
}
