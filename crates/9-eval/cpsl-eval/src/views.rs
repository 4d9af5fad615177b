//! Novel views of real scenes (`cpsl eval`): layer each dataset's reference view, render its
//! target views, score them against the real images (PSNR, SSIM, LPIPS, crack and hole
//! ratios) for CPSL and the baselines, and report as rows, JSON and HTML.

use crate::baselines::dibr;
use crate::coverage::{covisible, crack_ratio, edge_band, hole_ratio};
use crate::datasets::{self, align_median, Dataset, Target};
use crate::error::{Context, EvalError};
use crate::metrics::{psnr_masked, ssim};
use crate::report::today;
use cpsl_codec::{CodingOptions, PackageWriter, RateControl};
use cpsl_core::{
    Edc, FixedDepth, LayerSet, LayeredFrame, NoProgress, Progress, ProgressEvent, RefreshReason,
};
use cpsl_layering::GeometryMode;
use cpsl_layering::{slice_by_depth, Bins, LayeringConfig, SliceConfig};
use cpsl_package::Codec;
use cpsl_pipeline::image::{layer_image, InstanceMode};
use cpsl_render::{CpuRenderer, DpsConfig, Filter, FrameLayers};
use serde::Serialize;
use std::path::{Path, PathBuf};

type Result<T> = std::result::Result<T, EvalError>;

/// Methods compared.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize)]
#[serde(rename_all = "kebab-case")]
pub enum Method {
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

impl Method {
    /// The method's name in reports.
    pub fn name(self) -> &'static str {
        match self {
            Method::Cpsl => "cpsl",
            Method::CpslNoDps => "cpsl-no-dps",
            Method::CpslDepthOnly => "cpsl-depth-only",
            Method::DepthSlice => "depth-slice",
            Method::Mpi => "mpi",
            Method::MpiK => "mpi-k",
            Method::SinglePlane => "single-plane",
            Method::Dibr => "dibr",
            Method::DibrFill => "dibr-fill",
            Method::All => "all",
        }
    }

    /// Every method but `All`.
    pub const EVERY: [Method; 9] = [
        Method::Cpsl,
        Method::CpslNoDps,
        Method::CpslDepthOnly,
        Method::DepthSlice,
        Method::Mpi,
        Method::MpiK,
        Method::SinglePlane,
        Method::Dibr,
        Method::DibrFill,
    ];
}

/// What to evaluate, and how.
#[derive(Debug, Clone)]
pub struct ViewsOptions {
    /// Dataset name (see [`datasets::NAMES`]) or `all`.
    pub dataset: String,
    /// Folder holding the datasets.
    pub data: PathBuf,
    /// Method (`All` for every one).
    pub method: Method,
    /// Number of layers K for CPSL, depth slicing and `mpi-k`.
    pub layers: u32,
    /// Layer surfaces for CPSL (`None`: the configuration's, by default the best).
    pub geometry: Option<GeometryMode>,
    /// Number of planes of the `mpi` baseline.
    pub mpi_planes: u32,
    /// Layering configuration for CPSL (a file as for `cpsl layer --config`).
    pub config: Option<PathBuf>,
    /// Instance masks for CPSL.
    pub instances: InstanceMode,
    /// Depth: `gt` or a model, `model:<name>` (or the name alone), median-scaled to the
    /// ground truth (for the temple ring, to the depth of the scene centre).
    pub depth: String,
    /// Score LPIPS (a warning and no LPIPS where its graph is missing).
    pub lpips: bool,
    /// Write an HTML report (tables, per-view plots, image crops) into this folder.
    pub html: Option<PathBuf>,
    /// Code the layers of every layered method as a one-frame package with this codec and
    /// decode it before rendering (DIBR stays uncoded).
    pub codec: Option<Codec>,
    /// Budget for `codec` in bits per second of a 30 frames/s stream.
    pub bitrate: Option<f64>,
    /// Keep the packages of `codec` in this folder (by default a temporary one).
    pub keep_packages: Option<PathBuf>,
    /// How the layered methods' layers are resampled.
    pub filter: Filter,
}

/// What a run reports as it goes.
pub enum Row<'a> {
    /// A method scored on a dataset.
    Scored(&'a MethodReport),
    /// A dataset skipped, and why.
    Skipped(&'a str, &'static str),
}

/// Frame rate the budget of `cpsl eval --bitrate` refers to.
const CODED_FPS: f64 = 30.0;

/// Where `cpsl eval --codec` writes its packages, and how it codes them.
struct RoundTrip {
    opts: CodingOptions,
    dir: PathBuf,
    _temp: Option<tempfile::TempDir>,
}

impl RoundTrip {
    fn new(a: &ViewsOptions) -> Result<Option<Self>> {
        let Some(codec) = a.codec else {
            return Ok(None);
        };
        cpsl_pipeline::encode::require_encoder(codec)?;
        let rate = match a.bitrate {
            Some(b) => RateControl::Budget(b),
            None => RateControl::Quality(cpsl_codec::quality_range(codec).2),
        };
        let (dir, temp) = match &a.keep_packages {
            Some(d) => {
                std::fs::create_dir_all(d).map_err(|e| EvalError::file(d, e))?;
                (d.clone(), None)
            }
            None => {
                let t = tempfile::tempdir()
                    .map_err(|e| EvalError::file(std::env::temp_dir(), e))
                    .context_with(|| "creating a temporary folder".into())?;
                (t.path().to_path_buf(), Some(t))
            }
        };
        Ok(Some(Self {
            opts: CodingOptions {
                codec,
                rate,
                fps: CODED_FPS,
                gop: 1,
                container: cpsl_codec::Container::Fragment,
                segments: cpsl_codec::Segments::default(),
            },
            dir,
            _temp: temp,
        }))
    }

    /// Codes `set` (with its Edge-Depth Cache, if any) as the one frame of a package named
    /// after `dataset` and `method`, decodes it and returns the decoded layers, their cache
    /// and the bits the frame took.
    fn round_trip(
        &self,
        dataset: &str,
        method: &str,
        set: LayerSet,
        edc: Option<Edc>,
    ) -> Result<(LayerSet, Edc, f64)> {
        let path = self.dir.join(format!("{}_{method}.cpsl", slug(dataset)));
        let edc = edc.unwrap_or_else(|| {
            let step = cpsl_layering::matte::MatteConfig::default().edc_step;
            Edc::empty(
                set.camera().width,
                set.camera().height,
                set.len() as u16,
                step,
            )
        });
        let mut writer = PackageWriter::create(&path, *set.camera(), set.len() as u32, self.opts)?;
        let frame = LayeredFrame::new(0, Some(RefreshReason::First), set, edc);
        writer.push_segment(&[frame])?;
        let manifest = writer.finish()?;
        let pkg = cpsl_package::Package::open(&path)
            .context_with(|| format!("opening {}", path.display()))?;
        let frame = cpsl_codec::decode_segment(&pkg, 0)
            .context_with(|| format!("decoding {}", path.display()))?
            .into_iter()
            .next()
            .ok_or_else(|| EvalError::Invalid(format!("{}: no frame", path.display())))?;
        Ok((frame.set, frame.side.edc, manifest.bitrate() / CODED_FPS))
    }
}

/// Scores of one rendered view.
#[derive(Debug, Clone, Serialize)]
pub struct ViewScore {
    /// The target view's name.
    pub view: String,
    /// Distance of the target camera from the reference camera (scene units).
    pub offset: f64,
    /// Fraction of the view in the co-visibility mask (the pixels every metric scores).
    pub covisible: f64,
    /// PSNR (dB) over the co-visibility mask; null if it is empty.
    pub psnr: Option<f64>,
    /// SSIM over the co-visibility mask.
    pub ssim: f64,
    /// LPIPS (AlexNet, v0.1) with pixels outside the mask taken from the target; null when
    /// skipped.
    pub lpips: Option<f64>,
    /// Crack ratio in the depth-edge band (see EVALUATION.md).
    pub crack: f64,
    /// Hole ratio: fraction of pixels not covered before any filling.
    pub hole: f64,
}

/// One method's scores on one dataset (the JSON schema is in EVALUATION.md).
#[derive(Debug, Clone, Serialize)]
pub struct MethodReport {
    /// The dataset.
    pub dataset: String,
    /// The method's name.
    pub method: String,
    /// Layers (0 for DIBR).
    pub layers: usize,
    /// The depth used.
    pub depth: String,
    /// Bits the coded frame took (`--codec`), null when uncoded.
    pub bits: Option<f64>,
    /// Mean PSNR (dB) over the views with scored pixels.
    pub mean_psnr: f64,
    /// Mean SSIM.
    pub mean_ssim: f64,
    /// Mean LPIPS, when scored.
    pub mean_lpips: Option<f64>,
    /// Mean crack ratio.
    pub mean_crack: f64,
    /// Mean hole ratio.
    pub mean_hole: f64,
    /// Every view.
    pub views: Vec<ViewScore>,
}

impl MethodReport {
    /// The report of `method` on `dataset` from its views' scores (LPIPS averaged where the
    /// views have it).
    fn new(
        dataset: &str,
        method: Method,
        layers: usize,
        depth: &str,
        bits: Option<f64>,
        views: Vec<ViewScore>,
    ) -> Self {
        let scored = views.iter().any(|v| v.lpips.is_some());
        Self {
            dataset: dataset.into(),
            method: method.name().into(),
            layers,
            depth: depth.into(),
            bits,
            mean_psnr: mean(
                views
                    .iter()
                    .filter_map(|v| v.psnr)
                    .filter(|p| p.is_finite()),
            ),
            mean_ssim: mean(views.iter().map(|v| v.ssim)),
            mean_lpips: scored.then(|| mean(views.iter().filter_map(|v| v.lpips))),
            mean_crack: mean(views.iter().map(|v| v.crack)),
            mean_hole: mean(views.iter().map(|v| v.hole)),
            views,
        }
    }
}

/// LPIPS, or a warning and `None` where its graph cannot be loaded.
fn open_lpips(progress: &dyn Progress) -> Option<std::cell::RefCell<cpsl_models::Lpips>> {
    match cpsl_models::Lpips::open(&cpsl_models::lpips::default_path()) {
        Ok(m) => Some(std::cell::RefCell::new(m)),
        Err(e) => {
            progress.event(ProgressEvent::Warning {
                message: format!("LPIPS skipped: {e}"),
            });
            None
        }
    }
}

/// A synthesised target view.
struct Synth {
    /// RGB over black.
    rgb: Vec<u8>,
    /// `V`: covered before any filling.
    covered: Vec<bool>,
}

/// Everything one dataset's scoring needs besides the method: per target view the depth-edge
/// band and the co-visibility mask, and LPIPS.
struct Scorer<'a> {
    ds: &'a Dataset,
    bands: Vec<Vec<bool>>,
    masks: Vec<Vec<bool>>,
    lpips: Option<&'a std::cell::RefCell<cpsl_models::Lpips>>,
}

impl<'a> Scorer<'a> {
    /// The scorer of `ds`'s target views: their depth-edge bands and co-visibility masks
    /// from `depth`, and LPIPS when given.
    fn new(
        ds: &'a Dataset,
        depth: &[f32],
        lpips: Option<&'a std::cell::RefCell<cpsl_models::Lpips>>,
    ) -> Self {
        let per_target = |f: &dyn Fn(&Target) -> Vec<bool>| ds.targets.iter().map(f).collect();
        Self {
            ds,
            bands: per_target(&|t| edge_band(depth, &ds.camera, &t.pose, &t.camera, 0.05, 2)),
            masks: per_target(&|t| covisible(depth, &ds.camera, &t.pose, &t.camera)),
            lpips,
        }
    }

    /// Scores every target view synthesised by `synth`; returns the scores and the view
    /// with the largest offset (for the report's crops).
    fn score(
        &self,
        synth: impl Fn(&Target) -> Synth,
        progress: &dyn Progress,
    ) -> Result<(Vec<ViewScore>, Vec<u8>)> {
        let stage = "render views";
        progress.event(ProgressEvent::Start {
            stage,
            total: Some(self.ds.targets.len() as u64),
        });
        let far = farthest(self.ds);
        let mut kept = Vec::new();
        let mut out = Vec::new();
        for (i, t) in self.ds.targets.iter().enumerate() {
            let s = synth(t);
            let (w, h) = (t.camera.width as usize, t.camera.height as usize);
            let mask = &self.masks[i];
            let lpips = match self.lpips {
                Some(m) => {
                    // Pixels outside the mask count as perfect, as for PSNR and SSIM.
                    let mut img = s.rgb.clone();
                    for (p, &sc) in mask.iter().enumerate() {
                        if !sc {
                            img[p * 3..p * 3 + 3].copy_from_slice(&t.rgb[p * 3..p * 3 + 3]);
                        }
                    }
                    Some(
                        m.borrow_mut()
                            .distance(&img, &t.rgb, t.camera.width, t.camera.height)?
                            as f64,
                    )
                }
                None => None,
            };
            out.push(ViewScore {
                view: t.name.clone(),
                offset: t.pose.translation.norm(),
                covisible: mask.iter().filter(|&&m| m).count() as f64 / mask.len() as f64,
                psnr: psnr_masked(&s.rgb, &t.rgb, mask),
                ssim: ssim(&s.rgb, &t.rgb, w, h, Some(mask)),
                lpips,
                crack: crack_ratio(&s.covered, &self.bands[i], w, h),
                hole: hole_ratio(&s.covered),
            });
            if i == far {
                kept = s.rgb;
            }
            progress.event(ProgressEvent::Advance {
                stage,
                done: i as u64 + 1,
            });
        }
        progress.event(ProgressEvent::Finish { stage });
        Ok((out, kept))
    }
}

/// Index of the target farthest from the reference.
fn farthest(ds: &Dataset) -> usize {
    (0..ds.targets.len())
        .max_by(|&a, &b| {
            let n = |i: usize| ds.targets[i].pose.translation.norm();
            n(a).total_cmp(&n(b))
        })
        .unwrap_or(0)
}

/// Renders a target view of a frame's layers, with or without the Dynamic Pixel Strip.
fn render_layers(frame: &FrameLayers, t: &Target, dps: bool, filter: Filter) -> Synth {
    let img = CpuRenderer::new(filter).view(
        frame,
        &t.pose,
        &t.camera,
        dps.then_some(&DpsConfig::DEFAULT),
    );
    Synth {
        rgb: img.over_fill(),
        covered: img.covered(128),
    }
}

fn mean(v: impl Iterator<Item = f64>) -> f64 {
    let (s, n) = v.fold((0.0, 0usize), |(s, n), x| (s + x, n + 1));
    s / n.max(1) as f64
}

/// The depth to layer `ds` with and its description, or why the dataset is skipped (no
/// ground truth for `gt`, no stereo pair for `stereo`).
fn dataset_depth(
    ds: &Dataset,
    depth: &str,
) -> Result<std::result::Result<(Vec<f32>, String), &'static str>> {
    if depth == "gt" {
        if ds.centre_depth.is_some() {
            return Ok(Err("no ground-truth depth (use --depth model:fastdepth)"));
        }
        return Ok(Ok((ds.depth.clone(), "ground truth".to_string())));
    }
    if depth == "stereo" {
        if crate::stereo::pair(ds).is_none() {
            return Ok(Err("no stereo pair (no view beside the reference)"));
        }
        let (z, _, desc) = crate::stereo::stereo_depth(ds, &cpsl_stereo::StereoConfig::default())?;
        return Ok(Ok((z, desc)));
    }
    let model = depth.strip_prefix("model:").unwrap_or(depth);
    let mut m: Box<dyn cpsl_core::DepthSource> =
        Box::new(cpsl_pipeline::sources::open_depth_model(model, None)?);
    let (est, source) = (
        m.depth(&ds.rgb, ds.camera.width, ds.camera.height)?,
        m.name(),
    );
    let truth = match ds.centre_depth {
        Some(z) => vec![z; est.len()],
        None => ds.depth.clone(),
    };
    let (aligned, s) = align_median(&est, &truth)
        .ok_or_else(|| EvalError::Invalid(format!("{source}: no valid depth to align")))?;
    Ok(Ok((aligned, format!("{source}, median-scaled x{s:.3}"))))
}

/// Evaluates the methods on the datasets `a` names, handing each row to `rows` as it is
/// scored; returns every method's report (and writes the HTML report when asked).
pub fn evaluate_views(
    a: &ViewsOptions,
    progress: &dyn Progress,
    mut rows: impl FnMut(Row<'_>),
) -> Result<Vec<MethodReport>> {
    if !a.data.is_dir() {
        return Err(EvalError::Invalid(format!(
            "{}: data folder not found (pass --data with the folder that holds hci_lightfield_4d/ and middlebury_2005_2003_stereo/)",
            a.data.display()
        )));
    }
    let names: Vec<&str> = if a.dataset == "all" {
        datasets::NAMES.to_vec()
    } else {
        vec![a.dataset.as_str()]
    };
    let methods: Vec<Method> = match a.method {
        Method::All => Method::EVERY.to_vec(),
        m => vec![m],
    };
    let coding = RoundTrip::new(a)?;
    let lpips = if a.lpips { open_lpips(progress) } else { None };
    let mut reports = Vec::new();
    let mut crops = Vec::new();
    for name in names {
        let ds = datasets::load(&a.data, name).context_with(|| format!("loading {name}"))?;
        let (depth, depth_name) = match dataset_depth(&ds, &a.depth)? {
            Ok(d) => d,
            Err(why) => {
                rows(Row::Skipped(name, why));
                continue;
            }
        };
        // Score the same pixels whatever the depth: co-visibility and depth-edge bands come
        // from the ground truth where the dataset has it.
        let truth = if ds.depth.iter().any(|z| z.is_finite()) {
            &ds.depth
        } else {
            &depth
        };
        let scorer = Scorer::new(&ds, truth, lpips.as_ref());
        for &method in &methods {
            // The layers as rendered: the set itself, or the set coded and decoded again.
            let prepare = |set: LayerSet, edc: Option<Edc>| -> Result<(FrameLayers, Option<f64>)> {
                Ok(match &coding {
                    None => (FrameLayers::new(set, edc), None),
                    Some(c) => {
                        let (set, edc, bits) = c.round_trip(name, method.name(), set, edc)?;
                        (FrameLayers::new(set, Some(edc)), Some(bits))
                    }
                })
            };
            let sliced = |k: usize, bins: Bins| -> Result<(FrameLayers, usize, Option<f64>)> {
                let config = SliceConfig {
                    layers: k,
                    bins,
                    ..SliceConfig::default()
                };
                let set = slice_by_depth(&ds.rgb, &depth, ds.camera, &config)
                    .context_with(|| format!("layering {name}"))?;
                let layers = set.len();
                let (prepared, bits) = prepare(set, None)?;
                Ok((prepared, layers, bits))
            };
            let ((views, crop), layers, bits) = match method {
                Method::Cpsl | Method::CpslNoDps | Method::CpslDepthOnly => {
                    let mut cfg = LayeringConfig {
                        layers: a.layers as usize,
                        ..match &a.config {
                            Some(p) => cpsl_pipeline::sources::read_config(p)?,
                            None => LayeringConfig::default(),
                        }
                    };
                    if method == Method::CpslDepthOnly {
                        cfg = cfg.depth_only();
                    }
                    if let Some(g) = a.geometry {
                        cfg.matte.geometry = g;
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
                        &NoProgress,
                    )
                    .context_with(|| format!("layering {name}"))?;
                    let layers = run.layered.set.len();
                    let (prepared, bits) = prepare(run.layered.set, Some(run.layered.edc))?;
                    let dps = method != Method::CpslNoDps;
                    (
                        scorer.score(|t| render_layers(&prepared, t, dps, a.filter), progress)?,
                        layers,
                        bits,
                    )
                }
                Method::DepthSlice | Method::Mpi | Method::MpiK | Method::SinglePlane => {
                    let (k, bins) = match method {
                        Method::DepthSlice => (a.layers as usize, Bins::KMeans),
                        Method::Mpi => (a.mpi_planes as usize, Bins::UniformInverse),
                        Method::MpiK => (a.layers as usize, Bins::UniformInverse),
                        _ => (1, Bins::KMeans),
                    };
                    let (prepared, n, bits) = sliced(k, bins)?;
                    (
                        scorer.score(|t| render_layers(&prepared, t, false, a.filter), progress)?,
                        n,
                        bits,
                    )
                }
                Method::Dibr | Method::DibrFill => {
                    let fill = method == Method::DibrFill;
                    let scored = scorer.score(
                        |t| {
                            let s = dibr(&ds.rgb, &depth, &ds.camera, &t.pose, &t.camera, fill);
                            Synth {
                                rgb: s.rgb,
                                covered: s.covered,
                            }
                        },
                        progress,
                    )?;
                    (scored, 0, None)
                }
                Method::All => unreachable!("expanded above"),
            };
            let r = MethodReport::new(name, method, layers, &depth_name, bits, views);
            rows(Row::Scored(&r));
            if a.html.is_some() {
                let t = &ds.targets[farthest(&ds)];
                crops.push(Crop {
                    dataset: name.into(),
                    method: method.name().into(),
                    width: t.camera.width as usize,
                    height: t.camera.height as usize,
                    rgb: crop,
                    truth: t.rgb.clone(),
                    view: t.name.clone(),
                });
            }
            reports.push(r);
        }
    }
    if let Some(dir) = &a.html {
        write_html(dir, &reports, &crops, a)?;
    }
    Ok(reports)
}

/// The synthesised view kept for a report crop.
struct Crop {
    dataset: String,
    method: String,
    view: String,
    width: usize,
    height: usize,
    rgb: Vec<u8>,
    truth: Vec<u8>,
}

fn slug(s: &str) -> String {
    s.chars()
        .map(|c| if c.is_ascii_alphanumeric() { c } else { '_' })
        .collect()
}

fn esc(s: &str) -> String {
    s.replace('&', "&amp;")
        .replace('<', "&lt;")
        .replace('>', "&gt;")
}

/// The centre `cw x ch` region of an RGB image.
fn centre_crop(rgb: &[u8], w: usize, h: usize, cw: usize, ch: usize) -> Vec<u8> {
    let (x0, y0) = ((w - cw) / 2, (h - ch) / 2);
    (y0..y0 + ch)
        .flat_map(|y| rgb[(y * w + x0) * 3..(y * w + x0 + cw) * 3].iter().copied())
        .collect()
}

/// An SVG line plot of `value` against each view's offset, one line per method.
fn svg_plot(
    reports: &[&MethodReport],
    title: &str,
    value: impl Fn(&ViewScore) -> Option<f64>,
) -> String {
    let (w, h, m) = (420.0, 240.0, 40.0);
    let pts: Vec<(f64, f64)> = reports
        .iter()
        .flat_map(|r| {
            r.views
                .iter()
                .filter_map(|v| value(v).map(|y| (v.offset, y)))
        })
        .filter(|p| p.1.is_finite())
        .collect();
    if pts.is_empty() {
        return String::new();
    }
    let (x0, x1) = pts
        .iter()
        .fold((f64::MAX, f64::MIN), |a, p| (a.0.min(p.0), a.1.max(p.0)));
    let (y0, y1) = pts
        .iter()
        .fold((f64::MAX, f64::MIN), |a, p| (a.0.min(p.1), a.1.max(p.1)));
    let sx = |x: f64| m + (x - x0) / (x1 - x0).max(1e-12) * (w - 2.0 * m);
    let sy = |y: f64| h - m - (y - y0) / (y1 - y0).max(1e-12) * (h - 2.0 * m);
    let colours = [
        "#d62728", "#ff7f0e", "#8c564b", "#2ca02c", "#1f77b4", "#17becf", "#7f7f7f", "#9467bd",
        "#e377c2",
    ];
    let mut svg = format!(
        "<svg xmlns='http://www.w3.org/2000/svg' width='{w}' height='{h}' font-size='10'>\
         <text x='{m}' y='14'>{} (x: viewpoint offset {x0:.3}..{x1:.3}; y: {y0:.3}..{y1:.3})</text>\
         <rect x='{m}' y='{m}' width='{}' height='{}' fill='none' stroke='#999'/>",
        esc(title),
        w - 2.0 * m,
        h - 2.0 * m
    );
    for (i, r) in reports.iter().enumerate() {
        let mut v: Vec<(f64, f64)> = r
            .views
            .iter()
            .filter_map(|v| value(v).map(|y| (v.offset, y)))
            .filter(|p| p.1.is_finite())
            .collect();
        v.sort_by(|a, b| a.0.total_cmp(&b.0));
        let c = colours[i % colours.len()];
        for p in &v {
            svg += &format!(
                "<circle cx='{:.1}' cy='{:.1}' r='2' fill='{c}'/>",
                sx(p.0),
                sy(p.1)
            );
        }
        svg += &format!(
            "<text x='{}' y='{}' fill='{c}'>{}</text>",
            w - m + 2.0 - 40.0,
            m + 12.0 * (i as f64 + 1.0),
            esc(&r.method)
        );
    }
    svg + "</svg>"
}

/// Writes `index.html` with per-dataset tables, plots of PSNR and crack ratio against the
/// viewpoint offset, and centre crops of the farthest target for every method.
fn write_html(
    dir: &Path,
    reports: &[MethodReport],
    crops: &[Crop],
    a: &ViewsOptions,
) -> Result<()> {
    std::fs::create_dir_all(dir.join("crops")).map_err(|e| EvalError::file(dir, e))?;
    let mut html = format!(
        "<!doctype html><meta charset='utf-8'><title>cpsl eval</title>\
         <style>body{{font-family:sans-serif;margin:2em}}table{{border-collapse:collapse}}\
         td,th{{border:1px solid #ccc;padding:2px 8px;text-align:right}}img{{image-rendering:pixelated;margin:2px}}\
         figure{{display:inline-block;margin:4px;text-align:center;font-size:11px}}</style>\
         <h1>cpsl eval</h1><p>{} &middot; depth: {} &middot; K = {} &middot; metrics over scored pixels; \
         crack and hole ratios as defined in EVALUATION.md</p>",
        today(),
        esc(&a.depth),
        a.layers
    );
    let mut names: Vec<&str> = reports.iter().map(|r| r.dataset.as_str()).collect();
    names.dedup();
    for name in names {
        let rs: Vec<&MethodReport> = reports.iter().filter(|r| r.dataset == name).collect();
        html += &format!(
            "<h2>{}</h2><p>depth: {}</p><table><tr><th>method</th><th>K</th><th>PSNR dB</th><th>SSIM</th><th>LPIPS</th><th>crack</th><th>hole</th><th>views</th><th>kbit/frame</th></tr>",
            esc(name),
            esc(&rs[0].depth)
        );
        for r in &rs {
            html += &format!(
                "<tr><th>{}</th><td>{}</td><td>{:.2}</td><td>{:.4}</td><td>{}</td><td>{:.4}</td><td>{:.4}</td><td>{}</td><td>{}</td></tr>",
                esc(&r.method),
                r.layers,
                r.mean_psnr,
                r.mean_ssim,
                r.mean_lpips.map_or("-".into(), |l| format!("{l:.4}")),
                r.mean_crack,
                r.mean_hole,
                r.views.len(),
                r.bits.map_or("-".into(), |b| format!("{:.1}", b / 1e3))
            );
        }
        html += "</table>";
        html += &svg_plot(&rs, "PSNR (dB) per view", |v| v.psnr);
        html += &svg_plot(&rs, "crack ratio per view", |v| Some(v.crack));
        let cs: Vec<&Crop> = crops.iter().filter(|c| c.dataset == name).collect();
        if let Some(first) = cs.first() {
            let (cw, ch) = (first.width.min(192), first.height.min(144));
            html += &format!(
                "<p>centre crops of {}, the target farthest from the reference:</p>",
                esc(&first.view)
            );
            let save = |label: &str, rgb: &[u8]| -> Result<String> {
                let file = format!("crops/{}_{}.png", slug(name), slug(label));
                let png = cpsl_io::images::encode_png(
                    cw as u32,
                    ch as u32,
                    3,
                    &centre_crop(rgb, first.width, first.height, cw, ch),
                )
                .map_err(|m| EvalError::Invalid(format!("{file}: {m}")))?;
                cpsl_io::write_file_atomic(&dir.join(&file), &png)?;
                Ok(format!(
                    "<figure><img src='{file}' width='{}'><figcaption>{}</figcaption></figure>",
                    cw * 2,
                    esc(label)
                ))
            };
            html += &save("ground truth", &first.truth)?;
            for c in &cs {
                html += &save(&c.method, &c.rgb)?;
            }
        }
    }
    cpsl_io::write_file_atomic(&dir.join("index.html"), html.as_bytes())
        .context_with(|| format!("writing {}", dir.join("index.html").display()))
}
