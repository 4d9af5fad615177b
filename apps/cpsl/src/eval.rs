//! `cpsl eval`: layer real reference views, render their target views, score them against the
//! real images (PSNR, SSIM, LPIPS, crack and hole ratios) and report as a table, JSON and HTML.

use crate::encode::CodecArg;
use crate::layer::InstanceArg;
use crate::progress::Bars;
use crate::util::FilterArg;
use anyhow::{Context as _, Result};
use clap::{Args, ValueEnum};
use cpsl_eval::views::{evaluate_views, Method, Row, ViewsOptions};
use cpsl_layering::GeometryMode;
use std::path::PathBuf;

/// Methods `cpsl eval` compares.
#[derive(Clone, Copy, PartialEq, Eq, ValueEnum)]
pub enum MethodArg {
    /// Content-promoted scene layers (`cpsl layer`): K layers, rendered with the Dynamic Pixel
    /// Strip guided by the Edge-Depth Cache.
    Cpsl,
    /// CPSL rendered without the Dynamic Pixel Strip (ablation).
    CpslNoDps,
    /// CPSL without the saliency and instance terms and without promotion (with DPS).
    CpslDepthOnly,
    /// Depth slicing into K layers (k-means on inverse depth), hard alpha.
    DepthSlice,
    /// Uniform multiplane image: --mpi-planes planes uniform in inverse depth, hard alpha.
    Mpi,
    /// Uniform multiplane image with K planes (the same budget as CPSL).
    MpiK,
    /// One plane at the median depth: the reference image shifted as a whole (no parallax
    /// between objects), the "plain 2D" baseline.
    SinglePlane,
    /// Depth-image-based rendering: per-pixel forward warp with a z-buffer, holes left empty.
    Dibr,
    /// DIBR with push-pull hole filling.
    DibrFill,
    /// All of the above.
    All,
}

impl From<MethodArg> for Method {
    fn from(m: MethodArg) -> Self {
        match m {
            MethodArg::Cpsl => Method::Cpsl,
            MethodArg::CpslNoDps => Method::CpslNoDps,
            MethodArg::CpslDepthOnly => Method::CpslDepthOnly,
            MethodArg::DepthSlice => Method::DepthSlice,
            MethodArg::Mpi => Method::Mpi,
            MethodArg::MpiK => Method::MpiK,
            MethodArg::SinglePlane => Method::SinglePlane,
            MethodArg::Dibr => Method::Dibr,
            MethodArg::DibrFill => Method::DibrFill,
            MethodArg::All => Method::All,
        }
    }
}

/// Arguments of `cpsl eval`.
#[derive(Args)]
pub struct EvalArgs {
    /// Dataset name (hci/backgammon, middlebury2005/Art|Books|Dolls,
    /// middlebury2003/Teddy|Cones, middlebury-mview/templeSparseRing) or `all`.
    pub dataset: String,
    /// Folder holding the datasets (`../shared/data` beside the checkout).
    #[arg(long, default_value = "../shared/data")]
    pub data: PathBuf,
    /// Method.
    #[arg(long, value_enum, default_value_t = MethodArg::All)]
    pub method: MethodArg,
    /// Number of layers K for CPSL, depth slicing and `mpi-k`.
    #[arg(long, default_value_t = 6, value_parser = clap::value_parser!(u32).range(2..=16))]
    pub layers: u32,
    /// Layer surfaces: `plane`, `slanted` (video's default) or `mesh` (single images').
    #[arg(long, long_help = crate::util::GEOMETRY_HELP)]
    pub geometry: Option<GeometryMode>,
    /// Number of planes of the `mpi` baseline.
    #[arg(long, default_value_t = 32, value_parser = clap::value_parser!(u32).range(1..=64))]
    pub mpi_planes: u32,
    /// Layering configuration for CPSL as JSON (as for `cpsl layer --config`).
    #[arg(long)]
    pub config: Option<PathBuf>,
    /// Instance masks for CPSL.
    #[arg(long, value_enum, default_value_t = InstanceArg::Components)]
    pub instances: InstanceArg,
    /// Depth: `gt` (the dataset's ground truth), `stereo` (matched from the dataset's own
    /// stereo pair: the reference and the view to its right; HCI and Middlebury) or a model, `model:<name>` (`model:fastdepth`,
    /// `model:path.onnx`; `fastdepth` alone also works), median-scaled to the ground truth (or,
    /// for the temple ring, which has none, to the depth of the scene centre given by the
    /// poses).
    #[arg(long, default_value = "gt")]
    pub depth: String,
    /// Skip LPIPS (it needs the graph from scripts/setup-models.sh).
    #[arg(long)]
    pub no_lpips: bool,
    /// Write the full report (per view) as JSON; the schema is in EVALUATION.md.
    #[arg(long)]
    pub json: Option<PathBuf>,
    /// Write an HTML report (tables, per-view plots, image crops) into this folder.
    #[arg(long)]
    pub html: Option<PathBuf>,
    /// Code the layers of every layered method (the CPSL ones, depth slicing, the MPIs, the
    /// single plane) as a one-frame package with this codec and decode the package before
    /// rendering, so that the scores include the coding loss (DIBR stays uncoded).
    #[arg(long, value_enum)]
    pub codec: Option<CodecArg>,
    /// Budget for --codec in bits per second of a 30 frames/s stream (the frame gets a
    /// thirtieth of it), e.g. `3M`; without it every stream is coded at the codec's default
    /// quality.
    #[arg(long, value_parser = crate::encode::parse_bitrate, requires = "codec")]
    pub bitrate: Option<f64>,
    /// Keep the packages of --codec in this folder (`<dataset>_<method>.cpsl`; by default they
    /// go to a temporary folder).
    #[arg(long, requires = "codec")]
    pub keep_packages: Option<PathBuf>,
    /// How the CPU renderer resamples the layered methods' layers: `cubic` (Catmull-Rom,
    /// sharper; as `cpsl render` and the players with `filter=cubic` / key C) or `bilinear`
    /// (the players' real-time default; EVALUATION.md compares them).
    #[arg(long, value_enum, default_value_t = FilterArg::Cubic)]
    pub filter: FilterArg,
}

/// Runs `cpsl eval`.
pub fn run(a: EvalArgs) -> Result<()> {
    let opts = ViewsOptions {
        dataset: a.dataset,
        data: a.data,
        method: a.method.into(),
        layers: a.layers,
        geometry: a.geometry,
        mpi_planes: a.mpi_planes,
        config: a.config,
        instances: a.instances.into(),
        depth: a.depth,
        lpips: !a.no_lpips,
        html: a.html.clone(),
        codec: a.codec.map(Into::into),
        bitrate: a.bitrate,
        keep_packages: a.keep_packages,
        filter: a.filter.into(),
    };
    println!(
        "{:<22} {:<16} {:>3} {:>8} {:>7} {:>7} {:>7} {:>7} {:>5}{}",
        "dataset",
        "method",
        "K",
        "PSNR dB",
        "SSIM",
        "LPIPS",
        "crack",
        "hole",
        "views",
        if opts.codec.is_some() {
            "  kbit/frame"
        } else {
            ""
        }
    );
    let reports = evaluate_views(&opts, &Bars::default(), |row| match row {
        Row::Skipped(name, why) => println!("{name:<22} skipped: {why}"),
        Row::Scored(r) => println!(
            "{:<22} {:<16} {:>3} {:>8.2} {:>7.4} {:>7} {:>7.4} {:>7.4} {:>5}{}",
            r.dataset,
            r.method,
            r.layers,
            r.mean_psnr,
            r.mean_ssim,
            r.mean_lpips.map_or("-".to_string(), |l| format!("{l:.4}")),
            r.mean_crack,
            r.mean_hole,
            r.views.len(),
            r.bits
                .map_or(String::new(), |b| format!(" {:>12.1}", b / 1e3))
        ),
    })?;
    if let Some(path) = &a.json {
        cpsl_io::write_json(path, &reports)?;
        println!("wrote {}", path.display());
    }
    if let Some(dir) = &a.html {
        println!("wrote {}", dir.join("index.html").display());
    }
    Ok(())
}

/// Arguments of `cpsl eval-stereo`.
#[derive(Args)]
pub struct EvalStereoArgs {
    /// Dataset with a stereo pair (middlebury2005/Art|Books|Dolls, middlebury2003/Teddy|Cones,
    /// hci/backgammon) or `all`.
    #[arg(default_value = "all")]
    pub dataset: String,
    /// Folder holding the datasets (`../shared/data` beside the checkout).
    #[arg(long, default_value = "../shared/data")]
    pub data: PathBuf,
    /// Matching block side in pixels (odd).
    #[arg(long, default_value_t = cpsl_stereo::StereoConfig::default().block)]
    pub block: u32,
    /// Write the scores as JSON.
    #[arg(long)]
    pub json: Option<PathBuf>,
}

/// Runs `cpsl eval-stereo`: matches each pair and scores the disparity against ground truth.
pub fn run_stereo(a: EvalStereoArgs) -> Result<()> {
    let names = if a.dataset == "all" {
        cpsl_eval::stereo::stereo_names()
    } else {
        vec![a.dataset.as_str()]
    };
    let cfg = cpsl_stereo::StereoConfig {
        block: a.block,
        ..Default::default()
    };
    println!(
        "{:<22} {:>9} {:>11} {:>8} {:>8} {:>7} {:>7} {:>8} {:>8}",
        "dataset", "size", "range px", "dy px", "matched", "bad>1", "bad>2", "mean px", "ms"
    );
    let mut scores = Vec::new();
    for name in names {
        let s = cpsl_eval::stereo::score(&a.data, name, &cfg)?;
        println!(
            "{:<22} {:>9} {:>11} {:>8} {:>7.1}% {:>6.1}% {:>6.1}% {:>8.2} {:>8.0}",
            s.dataset,
            format!("{}x{}", s.size.0, s.size.1),
            format!("{}..{}", s.range.0, s.range.0 + s.range.1 as i32),
            s.vertical_offset
                .map_or("-".to_string(), |d| format!("{d:.2}")),
            100.0 * s.density,
            100.0 * s.bad1,
            100.0 * s.bad2,
            s.mean_abs,
            s.ms
        );
        scores.push(s);
    }
    if let Some(path) = &a.json {
        cpsl_io::write_json(path, &scores)?;
        println!("wrote {}", path.display());
    }
    Ok(())
}

/// Arguments of `cpsl eval-track`.
#[derive(Args)]
pub struct EvalTrackArgs {
    /// Folder holding the datasets (`../shared/data` beside the checkout).
    #[arg(long, default_value = "../shared/data")]
    pub data: PathBuf,
    /// Write the score as JSON.
    #[arg(long)]
    pub json: Option<PathBuf>,
    /// Also score the fox's depth (FastDepth alone, and from the video) at the 3-D points of
    /// an independent reconstruction of its frames, as `scripts/fox_sfm_points.py` writes
    /// them (pycolmap); when the file has that reconstruction's camera path, score it against
    /// the fox's poses too (how far two reconstructions disagree).
    #[arg(long, value_name = "POINTS_JSON")]
    pub depth_points: Option<PathBuf>,
    /// Also write the solved camera path as `poses.json` (as `cpsl track` writes it).
    #[arg(long)]
    pub poses: Option<PathBuf>,
}

/// Runs `cpsl eval-track`: tracks the fox without its poses and scores the result.
pub fn run_track(a: EvalTrackArgs) -> Result<()> {
    // Read first: a bad file fails before the tracking's seconds are spent.
    let reconstruction = a
        .depth_points
        .as_deref()
        .map(cpsl_eval::tracking::read_reconstruction)
        .transpose()?;
    let (s, path, names) = cpsl_eval::tracking::fox(
        &a.data,
        reconstruction
            .as_ref()
            .map(|r| &r.poses)
            .filter(|p| !p.is_empty()),
    )?;
    if let Some(out) = &a.poses {
        let (poses, _) = cpsl_pipeline::track::pose_files(&path, path.camera, &names, None);
        cpsl_io::write_json(out, &poses)?;
    }
    println!(
        "{}: {} of {} frames placed in {} segment(s) and {} world(s), motion {}, {} points, reprojection {:.2} px, rotation error {:.3} deg ({:.3} deg aligned), translation direction {:.2} deg, {:.0} ms/frame",
        s.clip, s.placed, s.frames, s.segments, s.worlds, s.motion, s.points, s.reprojection_px, s.rotation_deg, s.rotation_aligned_deg, s.translation_dir_deg, s.ms_per_frame
    );
    if let Some(r) = &s.reference {
        println!(
            "the reconstruction's own path ({} frames placed) against the fox's poses: rotation error {:.3} deg ({:.3} deg aligned), translation direction {:.2} deg",
            r.placed, r.rotation_deg, r.rotation_aligned_deg, r.translation_dir_deg
        );
    }
    let mut depth = Vec::new();
    if let Some(points) = reconstruction.as_ref().map(|r| &r.points) {
        let fox = cpsl_eval::video::load_fox(&a.data, 4, false)?;
        let v = cpsl_eval::tracking::video_depth(&fox.frames, fox.camera, &fox.depth)?;
        let (video, how) = (v.depth, v.how);
        for (name, z) in [
            (fox.depth_name.as_str(), &fox.depth),
            (how.as_str(), &video),
        ] {
            let d =
                cpsl_eval::tracking::depth_at_points(name, z, fox.camera, &fox.video.files, points)
                    .with_context(|| {
                        format!("no point of the reconstruction lands on the depth of {name}")
                    })?;
            println!(
                "depth at the reconstruction's points ({} points in {} frames): AbsRel {:.4} with one scale for the clip (median {:.4}), {:.4} with a scale per frame; {}",
                d.points, d.frames, d.abs_rel, d.median_rel, d.abs_rel_per_frame, d.depth
            );
            depth.push(d);
        }
    }
    if let Some(path) = &a.json {
        #[derive(serde::Serialize)]
        struct Report<'a> {
            #[serde(flatten)]
            tracking: &'a cpsl_eval::tracking::TrackScore,
            #[serde(skip_serializing_if = "Vec::is_empty")]
            depth_at_points: Vec<cpsl_eval::tracking::PointDepthScore>,
        }
        cpsl_io::write_json(
            path,
            &Report {
                tracking: &s,
                depth_at_points: depth,
            },
        )?;
        println!("wrote {}", path.display());
    }
    Ok(())
}
