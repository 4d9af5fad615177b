//! `cpsl demo`: the main job end to end on the built-in synthetic scene: a still layered and
//! rendered along a sweep, then a moving clip of the scene encoded into a package and played
//! back along a sweep.

use crate::encode::CodecArg;
use crate::layer::InstanceArg;
use crate::progress::Bars;
use crate::synth::{depth_list, estimate_depth};
use anyhow::{Context, Result};
use clap::Args;
use cpsl_codec::RateControl;
use cpsl_core::{FixedDepth, Pose, Progress, ProgressEvent, Vec3};
use cpsl_eval::metrics::psnr;
use cpsl_io::images::write_png;
use cpsl_io::pfm::{write_pfm, FloatImage};
use cpsl_layering::GeometryMode;
use cpsl_package::Package;
use cpsl_pipeline::encode::{encode, EncodeJob, EncodeTarget};
use cpsl_pipeline::image::{layer_image, write_image_layers};
use cpsl_pipeline::sources::{layering_config, CameraChoice, VideoDepth};
use cpsl_pipeline::synthetic::{synthesise, SynthOptions};
use cpsl_pipeline::video::{MotionSource, PFrameDepth, VideoJob};
use cpsl_player::sweep::{render_sweep, Output, Sweep};
use cpsl_player::Source;
use cpsl_render::{CpuRenderer, DpsConfig, Filter, FrameLayers, Renderer};
use cpsl_synth::Scene;
use cpsl_temporal::GopConfig;
use serde::Serialize;
use std::path::PathBuf;
use std::sync::atomic::AtomicBool;

/// The demo's renders are offline: Catmull-Rom, as `cpsl render` by default.
const OFFLINE: CpuRenderer = CpuRenderer::new(Filter::Cubic);

/// Arguments of `cpsl demo`.
#[derive(Args)]
pub struct DemoArgs {
    /// Output folder.
    #[arg(short, long, default_value = "out/demo")]
    pub output: PathBuf,
    /// Image width.
    #[arg(long, default_value_t = 640)]
    pub width: u32,
    /// Image height.
    #[arg(long, default_value_t = 480)]
    pub height: u32,
    /// Number of layers K.
    #[arg(long, default_value_t = 6, value_parser = clap::value_parser!(u32).range(2..=16))]
    pub layers: u32,
    /// Layer surfaces: `plane`, `slanted` (video's default) or `mesh` (single images').
    #[arg(long, long_help = crate::util::GEOMETRY_HELP)]
    pub geometry: Option<GeometryMode>,
    /// Layering configuration as JSON (as for `cpsl layer --config`).
    #[arg(long)]
    pub config: Option<PathBuf>,
    /// Instance masks for layering.
    #[arg(long, value_enum, default_value_t = InstanceArg::Components)]
    pub instances: InstanceArg,
    /// Layer from a monocular depth model (`fastdepth` or an .onnx path) instead of the
    /// ground-truth depth. Monocular depth has no absolute scale, so it is scaled to match
    /// the median of the ground truth before slicing.
    #[arg(long)]
    pub depth_model: Option<String>,
    /// Frames of the moving clip encoded into a package (30 per second).
    #[arg(long, default_value_t = 60, value_parser = clap::value_parser!(u32).range(1..=3000))]
    pub clip_frames: u32,
    /// Codec of the package's layer streams.
    #[arg(long, value_enum, default_value_t = CodecArg::H264)]
    pub codec: CodecArg,
    /// Total bitrate of the package.
    #[arg(long, default_value = "2M", value_parser = crate::encode::parse_bitrate)]
    pub bitrate: f64,
}

/// Frame rate of the demo clip.
const CLIP_FPS: f64 = 30.0;
/// The novel viewpoint at which the clip's package is scored.
const CLIP_NOVEL: [f64; 3] = [0.15, 0.0, 0.0];

#[derive(Serialize)]
struct Score {
    view: String,
    pose: String,
    identity: bool,
    /// PSNR against the ray-cast ground truth; `null` when the render is identical.
    psnr_db: Option<f64>,
}

/// Runs `cpsl demo`.
pub fn run(a: DemoArgs) -> Result<()> {
    let bars = Bars::default();
    let synth_dir = a.output.join("scene");
    let synth = synthesise(
        &SynthOptions {
            output: synth_dir.clone(),
            width: a.width,
            height: a.height,
            time: 0.0,
            supersample: 3,
        },
        &bars,
    )?;
    println!(
        "1/5 synthesised scene, depth and {} ground-truth views in {}",
        synth.views.len(),
        synth_dir.display()
    );

    let layer_dir = a.output.join("layers");
    let config = layering_config(a.config.as_deref(), a.layers, a.geometry)?;
    let (depth, source) = match &a.depth_model {
        None => (synth.depth.clone(), "ray-cast ground truth".to_string()),
        Some(model) => {
            let cam = synth.scene.camera;
            let (est, source) = estimate_depth(model, None, &synth.rgb, cam.width, cam.height)?;
            let (aligned, s) = cpsl_eval::datasets::align_median(&est, &synth.depth)
                .with_context(|| format!("{source}: no valid depth to align"))?;
            (
                aligned,
                format!("{source}, median-scaled by {s:.3} to the ground truth"),
            )
        }
    };
    let cam = synth.scene.camera;
    let mut fixed = FixedDepth {
        name: source.clone(),
        width: cam.width,
        height: cam.height,
        depth,
    };
    let run = layer_image(
        &synth.rgb,
        cam,
        &mut fixed,
        true,
        &config,
        a.instances.into(),
        &bars,
    )?;
    write_image_layers(&layer_dir, &run, &config, &source, true)?;
    let set = run.layered.set;
    println!(
        "2/5 layered into {} layers at depths [{}] ({} promoted) in {} (depth: {source})",
        set.len(),
        depth_list(&set),
        set.layers()
            .iter()
            .filter(|l| l.meta.role == Some(cpsl_core::LayerRole::Instance))
            .count(),
        layer_dir.display()
    );

    let mut source = Source::Still(Box::new(FrameLayers::new(
        set.clone(),
        Some(run.layered.edc.clone()),
    )));
    let sweep_dir = a.output.join("sweep");
    let sweep = Sweep::parse("tx:-0.3:0.3:61").expect("valid sweep");
    render_sweep(
        &mut source,
        &OFFLINE,
        true,
        &sweep.poses(),
        &sweep_dir,
        Output::Fill,
        30,
        &bars,
    )?;
    let video = sweep_dir.join("sweep.mp4");
    println!(
        "3/5 rendered a 61-frame sweep in {}{}",
        sweep_dir.display(),
        if video.exists() {
            " (sweep.mp4, sheet.png)"
        } else {
            " (sheet.png)"
        }
    );

    let prepared = source.at(0)?;
    let mut scores = Vec::new();
    for (entry, truth) in &synth.views {
        let mut img = cpsl_core::PremulImage::new(set.camera().width, set.camera().height);
        OFFLINE.render(
            prepared,
            &entry.pose_matrix,
            set.camera(),
            Some(&DpsConfig::DEFAULT),
            &mut img,
        )?;
        scores.push(Score {
            view: entry.name.clone(),
            pose: entry.pose.clone(),
            identity: entry.pose_matrix == cpsl_core::Pose::IDENTITY,
            psnr_db: Some(psnr(&img.over_fill(), truth)).filter(|p| p.is_finite()),
        });
    }
    // The reference view reproduces the input; average the novel views.
    let novel: Vec<f64> = scores
        .iter()
        .filter(|s| !s.identity)
        .map(|s| s.psnr_db.unwrap_or(f64::INFINITY))
        .collect();
    let mean = novel.iter().sum::<f64>() / novel.len().max(1) as f64;
    println!(
        "novel views vs ray-cast ground truth: mean PSNR {mean:.2} dB over {} novel views",
        novel.len(),
    );
    for s in &scores {
        let note = if s.identity { "  (reference view)" } else { "" };
        match s.psnr_db {
            Some(p) => println!("  {:<12} {p:>6.2} dB{note}", s.view),
            None => println!("  {:<12}  exact{note}", s.view),
        }
    }
    cpsl_io::write_json(&a.output.join("scores.json"), &scores)?;
    clip(&a, &synth.scene, &bars)
}

/// Stages 4 and 5: a moving clip of the scene (frames and exact depth, or the --depth-model)
/// through `cpsl encode` into a package, played back along a sweep and scored at a novel
/// viewpoint against the ray-cast truth.
fn clip(a: &DemoArgs, scene: &Scene, bars: &Bars) -> Result<()> {
    let dir = a.output.join("clip");
    let (frames_dir, depth_dir) = (dir.join("frames"), dir.join("depth"));
    for d in [&frames_dir, &depth_dir] {
        if d.exists() {
            std::fs::remove_dir_all(d).with_context(|| format!("clearing {}", d.display()))?;
        }
        std::fs::create_dir_all(d).with_context(|| format!("creating {}", d.display()))?;
    }
    let cam = scene.camera;
    let n = a.clip_frames as usize;
    bars.event(ProgressEvent::Start {
        stage: "ray cast clip",
        total: Some(n as u64),
    });
    let novel = Pose::from_translation(Vec3::new(CLIP_NOVEL[0], CLIP_NOVEL[1], CLIP_NOVEL[2]));
    let mut truth = Vec::new();
    for i in 0..n {
        let time = i as f64 / CLIP_FPS;
        let v = scene.render(&cam, &Pose::IDENTITY, time, 2);
        let name = format!("frame_{i:04}");
        write_png(
            &frames_dir.join(format!("{name}.png")),
            cam.width,
            cam.height,
            3,
            &v.rgb,
        )?;
        let depth = FloatImage {
            width: cam.width,
            height: cam.height,
            data: v.depth,
        };
        write_pfm(&depth_dir.join(format!("{name}.pfm")), &depth)?;
        if i % 10 == 0 {
            truth.push((i, scene.render(&cam, &novel, time, 2).rgb));
        }
        bars.event(ProgressEvent::Advance {
            stage: "ray cast clip",
            done: i as u64 + 1,
        });
    }
    bars.event(ProgressEvent::Finish {
        stage: "ray cast clip",
    });
    let camera_json = dir.join("camera.json");
    cpsl_io::write_json(&camera_json, &cam)?;

    let package = a.output.join("clip.cpsl");
    let exact = a.depth_model.is_none();
    // The defaults of `cpsl encode`: GOP 30, full temporal layering, decoder motion.
    let mut depth = match &a.depth_model {
        None => VideoDepth::frames(&depth_dir, 0.001)?,
        Some(m) => VideoDepth::model(m, None)?,
    };
    let job = EncodeJob {
        video: VideoJob {
            input: frames_dir.clone(),
            camera: CameraChoice::File(camera_json),
            layering: layering_config(
                a.config.as_deref(),
                a.layers,
                Some(a.geometry.unwrap_or(GeometryMode::VIDEO_DEFAULT)),
            )?,
            gop: GopConfig::default(),
            motion: MotionSource::Auto,
            p_depth: PFrameDepth::default(),
            max_frames: None,
            stereo: None,
        },
        codec: a.codec.into(),
        container: cpsl_codec::Container::Fragment,
        segments: cpsl_codec::Segments::default(),
        fps: Some(CLIP_FPS),
        target: EncodeTarget::Package(package.clone(), RateControl::Budget(a.bitrate)),
    };
    encode(&job, &mut depth, bars, &AtomicBool::new(false))?;
    println!(
        "4/5 encoded a moving clip of the scene ({n} frames, {}) into {}",
        if exact {
            "exact depth"
        } else {
            "depth from the model"
        },
        package.display()
    );

    let mut source = Source::open(&package)?;
    let sweep_dir = a.output.join("clip_sweep");
    let poses = Sweep::parse(&format!("tx:-0.3:0.3:{n}"))
        .expect("valid sweep")
        .poses();
    render_sweep(
        &mut source,
        &OFFLINE,
        true,
        &poses,
        &sweep_dir,
        Output::Fill,
        CLIP_FPS as u32,
        bars,
    )?;
    let mut img = cpsl_core::PremulImage::new(cam.width, cam.height);
    let mut scores = Vec::new();
    for (i, t) in &truth {
        OFFLINE.render(
            source.at(*i)?,
            &novel,
            &cam,
            Some(&DpsConfig::DEFAULT),
            &mut img,
        )?;
        scores.push(serde_json::json!({
            "frame": i,
            "psnr_db": psnr(&img.over_fill(), t),
        }));
    }
    let mean = scores
        .iter()
        .map(|s| s["psnr_db"].as_f64().unwrap_or(0.0))
        .sum::<f64>()
        / scores.len() as f64;
    let bitrate = Package::open(&package)?.manifest().bitrate();
    cpsl_io::write_json(
        &a.output.join("clip_scores.json"),
        &serde_json::json!({
            "package": package,
            "bitrate_bps": bitrate,
            "novel_pose": novel,
            "frames": scores,
        }),
    )?;
    println!(
        "5/5 played the package along a sweep in {}; novel view (tx {}) vs ray-cast truth at {:.0} kbit/s: mean PSNR {mean:.2} dB (every 10th frame, clip_scores.json)",
        sweep_dir.display(),
        CLIP_NOVEL[0],
        bitrate / 1e3,
    );
    Ok(())
}
