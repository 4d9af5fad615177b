//! `cpsl eval`: layer real reference views, render their target views, score against the real
//! images.

use crate::layer::{layer_image, InstanceMode};
use crate::progress::Bars;
use crate::synth::estimate_depth;
use anyhow::{Context, Result};
use clap::{Args, ValueEnum};
use cpsl_core::{FixedDepth, PremulImage, Progress, ProgressEvent};
use cpsl_eval::baselines::dibr;
use cpsl_eval::datasets::{self, align_median, Dataset, Target};
use cpsl_eval::metrics::{psnr_masked, ssim};
use cpsl_layering::{slice_by_depth, Bins, LayeringConfig, SliceConfig};
use cpsl_render::PreparedLayers;
use serde::Serialize;
use std::path::PathBuf;

/// Methods `cpsl eval` compares.
#[derive(Clone, Copy, PartialEq, Eq, ValueEnum, Serialize)]
#[serde(rename_all = "kebab-case")]
pub enum Method {
    /// Content-promoted scene layers (`cpsl layer`): K layers.
    Cpsl,
    /// CPSL without the saliency and instance terms and without promotion.
    CpslDepthOnly,
    /// Depth slicing into K layers (k-means on inverse depth).
    DepthSlice,
    /// Uniform multiplane image: --mpi-planes planes uniform in inverse depth, hard alpha.
    Mpi,
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

impl Method {
    fn name(self) -> &'static str {
        match self {
            Method::Cpsl => "cpsl",
            Method::CpslDepthOnly => "cpsl-depth-only",
            Method::DepthSlice => "depth-slice",
            Method::Mpi => "mpi",
            Method::SinglePlane => "single-plane",
            Method::Dibr => "dibr",
            Method::DibrFill => "dibr-fill",
            Method::All => "all",
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
    /// Layering method.
    #[arg(long, value_enum, default_value_t = Method::All)]
    pub method: Method,
    /// Number of layers K for CPSL and depth slicing.
    #[arg(long, default_value_t = 6, value_parser = clap::value_parser!(u32).range(2..=16))]
    pub layers: u32,
    /// Layering configuration for CPSL as JSON (as for `cpsl layer --config`).
    #[arg(long)]
    pub config: Option<PathBuf>,
    /// Instance masks for CPSL.
    #[arg(long, value_enum, default_value_t = InstanceMode::Components)]
    pub instances: InstanceMode,
    /// Number of planes of the uniform MPI baseline.
    #[arg(long, default_value_t = 32, value_parser = clap::value_parser!(u32).range(1..=64))]
    pub mpi_planes: u32,
    /// Depth source: `gt` (the dataset's ground truth) or a model (`fastdepth` or an .onnx
    /// path), median-scaled to the ground truth (or, for the temple ring, which has none, to
    /// the depth of the scene centre given by the poses).
    #[arg(long, default_value = "gt")]
    pub depth: String,
    /// Write the full report (per view) as JSON.
    #[arg(long)]
    pub json: Option<PathBuf>,
}

/// Scores of one rendered view.
#[derive(Serialize)]
struct ViewScore {
    view: String,
    /// PSNR over the pixels the render covers (dB).
    psnr: Option<f64>,
    /// SSIM over the covered pixels.
    ssim: f64,
    /// Fraction of pixels the render covers.
    coverage: f64,
}

#[derive(Serialize)]
struct MethodReport {
    dataset: String,
    method: String,
    layers: usize,
    depth: String,
    mean_psnr: f64,
    mean_ssim: f64,
    mean_coverage: f64,
    views: Vec<ViewScore>,
}

/// Scores every target view of `ds` synthesised by `synth` (RGB and covered pixels).
fn score(
    ds: &Dataset,
    synth: impl Fn(&Target) -> (Vec<u8>, Vec<bool>),
    progress: &dyn Progress,
) -> Vec<ViewScore> {
    let stage = "render views";
    progress.event(ProgressEvent::Start {
        stage,
        total: Some(ds.targets.len() as u64),
    });
    let out = ds
        .targets
        .iter()
        .enumerate()
        .map(|(i, t)| {
            let (rgb, covered) = synth(t);
            progress.event(ProgressEvent::Advance {
                stage,
                done: i as u64 + 1,
            });
            let (w, h) = (t.camera.width as usize, t.camera.height as usize);
            ViewScore {
                view: t.name.clone(),
                psnr: psnr_masked(&rgb, &t.rgb, &covered),
                ssim: ssim(&rgb, &t.rgb, w, h, Some(&covered)),
                coverage: covered.iter().filter(|&&c| c).count() as f64 / covered.len() as f64,
            }
        })
        .collect();
    progress.event(ProgressEvent::Finish { stage });
    out
}

/// Renders a target view from prepared layers: RGB over black and the fully covered pixels.
fn render_layers(prepared: &PreparedLayers, t: &Target) -> (Vec<u8>, Vec<bool>) {
    let mut img = PremulImage::new(t.camera.width, t.camera.height);
    prepared.render_into(&t.pose, &t.camera, &mut img);
    let covered = img
        .as_bytes()
        .chunks_exact(4)
        .map(|p| p[3] == 255)
        .collect();
    (img.over_background([0, 0, 0]), covered)
}

/// Progress sink that drops the expected warning about unknown ground-truth depth.
struct NoWarnings;

impl Progress for NoWarnings {
    fn event(&self, _event: ProgressEvent<'_>) {}
}

fn mean(v: impl Iterator<Item = f64>) -> f64 {
    let (s, n) = v.fold((0.0, 0usize), |(s, n), x| (s + x, n + 1));
    s / n.max(1) as f64
}

/// Runs `cpsl eval`.
pub fn run(a: EvalArgs) -> Result<()> {
    anyhow::ensure!(
        a.data.is_dir(),
        "{}: data folder not found (pass --data with the folder that holds hci_lightfield_4d/ and middlebury_2005_2003_stereo/)",
        a.data.display()
    );
    let names: Vec<&str> = if a.dataset == "all" {
        datasets::NAMES.to_vec()
    } else {
        vec![a.dataset.as_str()]
    };
    let bars = Bars::default();
    let mut reports = Vec::new();
    println!(
        "{:<22} {:<16} {:>3} {:>9} {:>7} {:>9} {:>6}",
        "dataset", "method", "K", "PSNR dB", "SSIM", "coverage", "views"
    );
    for name in names {
        let ds = datasets::load(&a.data, name).with_context(|| format!("loading {name}"))?;
        let (depth, depth_name) = if a.depth == "gt" {
            if ds.centre_depth.is_some() {
                println!("{name:<22} skipped: no ground-truth depth (use --depth fastdepth)");
                continue;
            }
            (ds.depth.clone(), "ground truth".to_string())
        } else {
            let (est, source) =
                estimate_depth(&a.depth, None, &ds.rgb, ds.camera.width, ds.camera.height)?;
            let truth = match ds.centre_depth {
                Some(z) => vec![z; est.len()],
                None => ds.depth.clone(),
            };
            let (aligned, s) = align_median(&est, &truth)
                .with_context(|| format!("{source}: no valid depth to align"))?;
            (aligned, format!("{source}, median-scaled x{s:.3}"))
        };
        let methods: Vec<Method> = match a.method {
            Method::All => vec![
                Method::Cpsl,
                Method::CpslDepthOnly,
                Method::DepthSlice,
                Method::Mpi,
                Method::SinglePlane,
                Method::Dibr,
                Method::DibrFill,
            ],
            m => vec![m],
        };
        for method in methods {
            let layered = |k: usize, bins: Bins| -> Result<(PreparedLayers, usize)> {
                let config = SliceConfig {
                    layers: k,
                    bins,
                    ..SliceConfig::default()
                };
                let set = slice_by_depth(&ds.rgb, &depth, ds.camera, &config)
                    .with_context(|| format!("layering {name}"))?;
                let n = set.len();
                Ok((PreparedLayers::new(&set), n))
            };
            let (views, layers) = match method {
                Method::Cpsl | Method::CpslDepthOnly => {
                    let mut cfg = LayeringConfig {
                        layers: a.layers as usize,
                        ..match &a.config {
                            Some(p) => crate::layer::read_config(p)?,
                            None => LayeringConfig::default(),
                        }
                    };
                    if method == Method::CpslDepthOnly {
                        cfg = cfg.depth_only();
                    }
                    let mut source = FixedDepth {
                        name: depth_name.clone(),
                        width: ds.camera.width,
                        height: ds.camera.height,
                        depth: depth.clone(),
                    };
                    let run = layer_image(
                        &ds.rgb,
                        ds.camera,
                        &mut source,
                        true,
                        &cfg,
                        a.instances,
                        &NoWarnings,
                    )
                    .with_context(|| format!("layering {name}"))?;
                    let prepared = PreparedLayers::new(&run.layered.set);
                    (
                        score(&ds, |t| render_layers(&prepared, t), &bars),
                        run.layered.set.len(),
                    )
                }
                Method::DepthSlice | Method::Mpi | Method::SinglePlane => {
                    let (k, bins) = match method {
                        Method::DepthSlice => (a.layers as usize, Bins::KMeans),
                        Method::Mpi => (a.mpi_planes as usize, Bins::UniformInverse),
                        _ => (1, Bins::KMeans),
                    };
                    let (prepared, n) = layered(k, bins)?;
                    (score(&ds, |t| render_layers(&prepared, t), &bars), n)
                }
                Method::Dibr | Method::DibrFill => {
                    let fill = method == Method::DibrFill;
                    let views = score(
                        &ds,
                        |t| {
                            let s = dibr(&ds.rgb, &depth, &ds.camera, &t.pose, &t.camera, fill);
                            // Filled DIBR covers every pixel it filled, i.e. all of them.
                            let covered = if fill {
                                vec![true; s.covered.len()]
                            } else {
                                s.covered
                            };
                            (s.rgb, covered)
                        },
                        &bars,
                    );
                    (views, 0)
                }
                Method::All => unreachable!("expanded above"),
            };
            let r = MethodReport {
                dataset: name.into(),
                method: method.name().into(),
                layers,
                depth: depth_name.clone(),
                mean_psnr: mean(
                    views
                        .iter()
                        .filter_map(|v| v.psnr)
                        .filter(|p| p.is_finite()),
                ),
                mean_ssim: mean(views.iter().map(|v| v.ssim)),
                mean_coverage: mean(views.iter().map(|v| v.coverage)),
                views,
            };
            println!(
                "{:<22} {:<16} {:>3} {:>9.2} {:>7.4} {:>8.1}% {:>6}",
                r.dataset,
                r.method,
                r.layers,
                r.mean_psnr,
                r.mean_ssim,
                r.mean_coverage * 100.0,
                r.views.len()
            );
            reports.push(r);
        }
    }
    if let Some(path) = &a.json {
        crate::util::write_json(path, &reports)?;
        println!("wrote {}", path.display());
    }
    Ok(())
}
