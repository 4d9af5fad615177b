//! `cpsl eval-rd`: rate-distortion curves of coded CPSL against DIBR streaming and a uniform
//! MPI coded with the same codec, on a synthetic moving clip or the fox video
//! (`cpsl_eval::rd`).

use crate::encode::{parse_bitrate, CodecArg, ContainerArg, SegmentAtArg};
use crate::progress::Bars;
use crate::util::FilterArg;
use crate::video::PDepthArg;
use anyhow::Result;
use clap::{Args, ValueEnum};
use cpsl_eval::rd::{evaluate_rd, Curve, Ratio, RdClip, RdInput, RdOptions, Summary};
use cpsl_layering::GeometryMode;
use cpsl_package::Codec;
use std::path::PathBuf;

/// The clips.
#[derive(ValueEnum, Clone, Copy, Debug, PartialEq, Eq)]
pub enum RdClipArg {
    /// The built-in scene moving, ray cast with exact depth; novel views at tx = +-0.12.
    Synthetic,
    /// The fox phone video at half size (540x960, up to 50 frames), FastDepth scaled by the
    /// poses; a scored frame is rendered at each neighbouring frame's camera that is 2 to 30
    /// degrees away and scored against that frame.
    Fox,
}

impl From<RdClipArg> for RdClip {
    fn from(c: RdClipArg) -> Self {
        match c {
            RdClipArg::Synthetic => RdClip::Synthetic,
            RdClipArg::Fox => RdClip::Fox,
        }
    }
}

/// Arguments of `cpsl eval-rd`.
#[derive(Args)]
pub struct EvalRdArgs {
    /// Clip.
    #[arg(long, value_enum, default_value_t = RdClipArg::Synthetic)]
    pub clip: RdClipArg,
    /// Folder holding the datasets (for the fox).
    #[arg(long, default_value = "../shared/data")]
    pub data: PathBuf,
    /// Width of the synthetic clip.
    #[arg(long, default_value_t = 1920)]
    pub width: u32,
    /// Height of the synthetic clip.
    #[arg(long, default_value_t = 1080)]
    pub height: u32,
    /// Frames of the clip (30 per second; one GOP of 30 frames by default; the fox has 50).
    #[arg(long, default_value_t = 30, value_parser = clap::value_parser!(u32).range(2..=300))]
    pub frames: u32,
    /// Number of CPSL layers K.
    #[arg(long, default_value_t = 6, value_parser = clap::value_parser!(u32).range(2..=16))]
    pub layers: u32,
    /// Layer surfaces: `plane`, `slanted` (video's default) or `mesh` (single images').
    #[arg(long, long_help = crate::util::GEOMETRY_HELP)]
    pub geometry: Option<GeometryMode>,
    /// Planes of the MPI baseline.
    #[arg(long, default_value_t = 32, value_parser = clap::value_parser!(u32).range(2..=64))]
    pub mpi_planes: u32,
    /// Codec of every method's streams.
    #[arg(long, value_enum, default_value_t = CodecArg::H264)]
    pub codec: CodecArg,
    /// How the layer streams are stored (CPSL and the MPI baseline).
    #[arg(long, value_enum, default_value_t = ContainerArg::Fragment)]
    pub container: ContainerArg,
    /// Where CPSL's segments start (as `cpsl encode --segment-at`).
    #[arg(long, value_enum, default_value_t = SegmentAtArg::Gop)]
    pub segment_at: SegmentAtArg,
    /// Layer CPSL once for every budget with the paper's fixed refresh threshold, instead of
    /// for each budget with the threshold it sets (as `cpsl encode --bitrate` does).
    #[arg(long)]
    pub fixed_refresh: bool,
    /// CPSL budgets (total bits per second).
    #[arg(long, value_delimiter = ',', default_value = "0.5M,1M,2M,3M,6M", value_parser = parse_bitrate)]
    pub bitrates: Vec<f64>,
    /// Qualities (CRF) of the baselines; by default five points spread over the codec's range.
    #[arg(long, value_delimiter = ',')]
    pub qualities: Option<Vec<f32>>,
    /// Score every N-th frame (at two novel viewpoints each).
    #[arg(long, default_value_t = 15, value_parser = clap::value_parser!(u32).range(1..))]
    pub score_every: u32,
    /// Skip LPIPS.
    #[arg(long)]
    pub no_lpips: bool,
    /// How the CPU renderer resamples CPSL's and the MPI's layers: `cubic` (Catmull-Rom, as
    /// `cpsl render`) or `bilinear` (the players' real-time default).
    #[arg(long, value_enum, default_value_t = FilterArg::Cubic)]
    pub filter: FilterArg,
    /// Depth of the fox: `video` (the default: from the video itself, camera tracking and
    /// multi-view depth fused with FastDepth) or `fastdepth` (per frame, one scale for the clip).
    #[arg(long, default_value = "video", value_parser = ["fastdepth", "video"])]
    pub depth: String,
    /// Where CPSL's P-frames take their depth, as `cpsl layer-video --p-depth`: `poses` (the
    /// I-frame's depth carried by the tracked camera's poses, on the fox with depth from the
    /// video; along the motion otherwise), `motion` (along the motion: the paper's) or
    /// `estimated` (the clip's own depth of every frame).
    #[arg(long, value_enum, default_value_t = PDepthArg::Poses)]
    pub p_depth: PDepthArg,
    /// What CPSL's layering is given of the clip: `pictures` (the default), `h264` (the
    /// pictures coded as H.264 by the ffmpeg tool at libx264's defaults, three B-frames, CRF
    /// 12, and decoded, P-frames' motion from its motion vectors, as `cpsl layer-video` of such
    /// a file) or `h264-flow` (the same pictures, motion from optical flow)
    #[arg(long, value_enum, default_value_t = InputArg::Pictures)]
    pub input: InputArg,
    /// Write the curves and summary as JSON.
    #[arg(long)]
    pub json: Option<PathBuf>,
}

/// `--input`.
#[derive(ValueEnum, Clone, Copy, Debug)]
pub enum InputArg {
    /// The pictures themselves.
    Pictures,
    /// Through H.264, motion from its vectors.
    H264,
    /// Through H.264, motion from optical flow.
    H264Flow,
}

/// Runs `cpsl eval-rd`.
pub fn run(a: EvalRdArgs) -> Result<()> {
    let codec = Codec::from(a.codec);
    let opts = RdOptions {
        clip: a.clip.into(),
        data: a.data,
        width: a.width,
        height: a.height,
        frames: a.frames,
        layers: a.layers,
        geometry: a.geometry,
        mpi_planes: a.mpi_planes,
        codec,
        container: a.container.into(),
        segments: a.segment_at.into(),
        rate_aware_refresh: !a.fixed_refresh,
        bitrates: a.bitrates,
        qualities: a.qualities,
        score_every: a.score_every,
        lpips: !a.no_lpips,
        filter: a.filter.into(),
        video_depth: a.depth == "video",
        p_depth: a.p_depth.into(),
        input: match a.input {
            InputArg::Pictures => RdInput::Pictures,
            InputArg::H264 => RdInput::H264Vectors,
            InputArg::H264Flow => RdInput::H264Flow,
        },
    };
    let report = evaluate_rd(&opts, &Bars::default(), |method, p| {
        let spend: Vec<String> = p
            .segments
            .iter()
            .map(|s| {
                format!(
                    "{} frames {:.0}/{:.0}",
                    s.frames, s.spent_kbit, s.budget_kbit
                )
            })
            .collect();
        eprintln!(
            "{method} {}: {:.0} kbit/s, {:.2} dB{}",
            p.setting,
            p.bitrate.unwrap_or(0.0) / 1e3,
            p.psnr,
            match spend.is_empty() {
                true => String::new(),
                false => format!(" (segments, kbit spent/budget: {})", spend.join(", ")),
            }
        )
    })?;
    let description = report.clip["description"].as_str().unwrap_or_default();
    print_tables(description, codec, &report.curves, &report.summary);
    if let Some(path) = &a.json {
        cpsl_io::write_json(path, &report)?;
        println!("wrote {}", path.display());
    }
    Ok(())
}

fn print_tables(clip: &str, codec: Codec, curves: &[Curve], s: &Summary) {
    println!("rate-distortion, {}, {clip}", codec.name());
    println!("| method | setting | kbit/s | PSNR (dB) | LPIPS | proxy |");
    println!("|---|---|---|---|---|---|");
    let opt = |v: Option<f64>, d: usize| v.map_or("-".into(), |v| format!("{v:.d$}"));
    for c in curves {
        for p in std::iter::once(&c.uncompressed).chain(&c.points) {
            println!(
                "| {} | {} | {} | {:.2} | {} | {} |",
                c.method,
                p.setting,
                opt(p.bitrate.map(|b| b / 1e3), 0),
                p.psnr,
                opt(p.lpips, 3),
                p.proxy.map_or("-".into(), |v| format!("{v:.2e}")),
            );
        }
    }
    let ratios = |r: &[Ratio]| {
        r.iter()
            .map(Ratio::to_string)
            .collect::<Vec<_>>()
            .join(", ")
    };
    println!(
        "bitrate of DIBR / CPSL at equal PSNR, per CPSL point: {}",
        ratios(&s.dibr_rate_ratio)
    );
    println!(
        "bitrate of DIBR with 16-bit depth / CPSL at equal PSNR, per CPSL point: {}",
        ratios(&s.dibr16_rate_ratio)
    );
    println!(
        "bitrate of MPI / CPSL at equal PSNR, per CPSL point: {}",
        ratios(&s.mpi_rate_ratio)
    );
    println!(
        "CPSL at <= 3 Mbit/s: {} dB below its uncompressed layers",
        opt(s.cpsl_gap_at_3m_db, 2)
    );
    println!(
        "proxy distortion vs LPIPS, Spearman over coded layered points: {}",
        opt(s.proxy_lpips_spearman, 3)
    );
}
