//! `cpsl`: turn 2D frames into Content-Promoted Scene Layers and render them from new
//! viewpoints.

/// mimalloc keeps freed frame buffers for reuse; with the system allocator every frame's
/// multi-megabyte layers were fresh pages that the kernel had to fault in and clear.
#[global_allocator]
static ALLOCATOR: mimalloc::MiMalloc = mimalloc::MiMalloc;

mod bench;
mod demo;
mod encode;
mod eval;
mod eval_rd;
mod eval_video;
mod info;
mod layer;
mod progress;
mod render;
mod serve;
mod synth;
mod track;
mod util;
mod video;
mod view;

use clap::{Parser, Subcommand};
use std::process::ExitCode;

#[derive(Parser)]
#[command(name = "cpsl", version, about = "Content-Promoted Scene Layers: 2D video to streamable 2.5D", long_about = None)]
struct Cli {
    #[command(subcommand)]
    command: Command,
}

#[derive(Subcommand)]
enum Command {
    /// Render a layer set, a layered video or a package from a new viewpoint (--pose) or along a sweep (--sweep).
    Render(render::RenderArgs),
    /// Write a synthetic scene: input view, exact depth and ground-truth novel views.
    Synth(synth::SynthArgs),
    /// Build content-promoted layers from one image (depth, saliency, instances, energy
    /// fusion, promotion, matting, fill, edge-depth cache).
    Layer(layer::LayerArgs),
    /// Layer a video or an image sequence: groups of pictures, I-frames layered from scratch,
    /// P-frames propagated along the motion, adaptive refresh.
    LayerVideo(video::LayerVideoArgs),
    /// The whole pipeline from a video to a package: depth, layering, propagation, per-layer
    /// bitrate allocation and coding (H.264, H.265, AV1 or VP9), segmented by GOP.
    Encode(encode::EncodeArgs),
    /// Summarise a package, a layer-set folder or a layered video (each layer's surface and
    /// its bits).
    Info(info::InfoArgs),
    /// Check every checksum and reference of a package, or read every frame of a layered video
    /// or every file of a layer set as the players do.
    Verify(info::InfoArgs),
    /// Write a package folder as one archive file (an uncompressed tar that every command
    /// reads like the folder).
    Pack(encode::PackArgs),
    /// Build a layer set from an image and its depth map by depth slicing (a baseline).
    Slice(synth::SliceArgs),
    /// The main job end to end on the built-in scene: synthesise, layer, render a sweep, score.
    Demo(demo::DemoArgs),
    /// Layer real reference views, render their target views and score them (PSNR, SSIM).
    Eval(eval::EvalArgs),
    /// The temporal-stability ablation on moving clips: frame-wise layering against I/P
    /// propagation with and without refinement (boundary variance, F-SSIM, warping error,
    /// flicker, novel-view PSNR).
    EvalVideo(eval_video::EvalVideoArgs),
    /// Stereo matching on the real two-view datasets: each pair's disparity scored against
    /// ground truth (share of non-occluded pixels off by more than 1 and 2 px).
    EvalStereo(eval::EvalStereoArgs),
    /// Track the camera through a video (no poses needed): poses.json and a NeRF-style
    /// transforms.json.
    Track(track::TrackArgs),
    /// Camera tracking on the fox (its poses not read), scored against its COLMAP poses.
    EvalTrack(eval::EvalTrackArgs),
    /// Rate-distortion curves on a synthetic moving clip: CPSL packages under budgets against
    /// DIBR streaming (colour + depth) and a uniform MPI coded with the same codec.
    EvalRd(eval_rd::EvalRdArgs),
    /// Play a package or a layered video (or show a layer set) in an interactive window: drag to move the
    /// viewpoint, play/pause/seek, side-by-side stereo, on-screen frame time.
    View(view::ViewArgs),
    /// Serve packages and the browser player over HTTP (range requests, ETags, CORS).
    Serve(serve::ServeArgs),
    /// Benchmarks.
    #[command(subcommand)]
    Bench(bench::BenchCommand),
}

/// Ends the process quietly when what reads its output goes away (`cpsl info pkg | head`), as
/// command-line tools do, instead of panicking in `println!` on the broken pipe.
#[allow(unsafe_code)] // `signal` is a C function.
fn default_sigpipe() {
    #[cfg(unix)]
    // SAFETY: restoring the default disposition of SIGPIPE before any thread starts.
    unsafe {
        libc::signal(libc::SIGPIPE, libc::SIG_DFL);
    }
}

fn main() -> ExitCode {
    default_sigpipe();
    // SVT-AV1 prints its configuration unless told otherwise (1 = errors only); set before
    // any thread starts.
    if std::env::var_os("SVT_LOG").is_none() {
        std::env::set_var("SVT_LOG", "1");
    }
    tracing_subscriber::fmt()
        .with_env_filter(
            tracing_subscriber::EnvFilter::try_from_default_env()
                .unwrap_or_else(|_| tracing_subscriber::EnvFilter::new("warn")),
        )
        .with_writer(std::io::stderr)
        .init();
    match run(Cli::parse()) {
        Ok(()) => ExitCode::SUCCESS,
        Err(e) => {
            eprintln!("error: {}", report(&e));
            ExitCode::FAILURE
        }
    }
}

/// The error and its causes on one line, each cause once: library errors that name their
/// cause in their own message (`cannot read F: <io error>`) still expose it as the source.
fn report(e: &anyhow::Error) -> String {
    let mut line = String::new();
    for cause in e.chain() {
        let text = cause.to_string();
        if line.ends_with(&text) {
            continue;
        }
        if !line.is_empty() {
            line.push_str(": ");
        }
        line.push_str(&text);
    }
    line
}

fn run(cli: Cli) -> anyhow::Result<()> {
    match cli.command {
        Command::Render(a) => render::run(a),
        Command::Synth(a) => synth::run_synth(a),
        Command::Layer(a) => layer::run(a),
        Command::LayerVideo(a) => video::run(a),
        Command::Encode(a) => encode::run(a),
        Command::Info(a) => info::run(a),
        Command::Verify(a) => info::verify(a),
        Command::Pack(a) => encode::pack(a),
        Command::Slice(a) => synth::run_slice(a),
        Command::Demo(a) => demo::run(a),
        Command::Eval(a) => eval::run(a),
        Command::EvalVideo(a) => eval_video::run(a),
        Command::EvalStereo(a) => eval::run_stereo(a),
        Command::Track(a) => track::run(a),
        Command::EvalTrack(a) => eval::run_track(a),
        Command::EvalRd(a) => eval_rd::run(a),
        Command::View(a) => view::run(a),
        Command::Serve(a) => serve::run(a),
        Command::Bench(b) => bench::run(b),
    }
}
