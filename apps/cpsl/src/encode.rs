//! `cpsl encode` and `cpsl pack`: the whole pipeline from a video to a package (depth,
//! layering, propagation, coding), and a package folder as one archive file.

use crate::progress::Bars;
use crate::video::VideoLayeringArgs;
use anyhow::{bail, Context, Result};
use clap::{Args, ValueEnum};
use cpsl_codec::{Container, RateControl, SegmentReport};
use cpsl_package::Codec;
use cpsl_pipeline::encode::{encode, encode_layered, EncodeJob, EncodeTarget};
use std::path::{Path, PathBuf};
use std::sync::atomic::{AtomicBool, Ordering};
use std::sync::Arc;

/// Codec of the layer streams.
#[derive(ValueEnum, Clone, Copy, Debug, PartialEq, Eq)]
pub enum CodecArg {
    /// H.264 (libx264).
    H264,
    /// H.265 (libx265).
    H265,
    /// AV1 (SVT-AV1).
    Av1,
    /// VP9 (libvpx).
    Vp9,
}

impl From<CodecArg> for Codec {
    fn from(c: CodecArg) -> Self {
        match c {
            CodecArg::H264 => Codec::H264,
            CodecArg::H265 => Codec::H265,
            CodecArg::Av1 => Codec::Av1,
            CodecArg::Vp9 => Codec::Vp9,
        }
    }
}

/// How the layer streams are stored.
#[derive(ValueEnum, Clone, Copy, Debug, PartialEq, Eq)]
pub enum ContainerArg {
    /// Movie fragments with in-band parameter sets and one init segment per picture size, a
    /// segment's layer streams in one file, one track run each (package version 6): 56 bytes
    /// per segment plus, per stream, 24 and 4 or 8 per picture.
    Fragment,
    /// A movie fragment per layer stream and segment (package versions 4 and 5, for players
    /// that read only those): 80 bytes per stream and segment plus 4 or 8 per picture.
    StreamFragments,
    /// Self-contained MP4 files (package versions 2 and 3, for players that read only those):
    /// about 1.1 kB per stream and segment.
    Mp4,
}

impl From<ContainerArg> for Container {
    fn from(c: ContainerArg) -> Self {
        match c {
            ContainerArg::Fragment => Container::Fragment,
            ContainerArg::StreamFragments => Container::StreamFragments,
            ContainerArg::Mp4 => Container::Mp4,
        }
    }
}

/// Where a package's segments start.
#[derive(ValueEnum, Clone, Copy, Debug, PartialEq, Eq)]
pub enum SegmentAtArg {
    /// Every GOP, and at a refresh of the layering that brings a new layer: a refresh whose
    /// layers all kept their tracks continues the layer streams instead of starting each
    /// again with a key frame.
    Gop,
    /// At every I-frame of the layering (the paper's groups of pictures).
    Refresh,
}

impl From<SegmentAtArg> for cpsl_codec::Segments {
    fn from(c: SegmentAtArg) -> Self {
        match c {
            SegmentAtArg::Gop => Self::Gop,
            SegmentAtArg::Refresh => Self::Refresh,
        }
    }
}

/// Parses a bitrate: `3M`, `800k`, `2.5M`, `1500000` (bits per second).
pub fn parse_bitrate(s: &str) -> Result<f64, String> {
    let t = s.trim();
    let (num, mult) = match t.char_indices().last() {
        Some((i, 'k' | 'K')) => (&t[..i], 1e3),
        Some((i, 'm' | 'M')) => (&t[..i], 1e6),
        Some((i, 'g' | 'G')) => (&t[..i], 1e9),
        _ => (t, 1.0),
    };
    let v: f64 = num
        .parse()
        .map_err(|_| format!("\"{s}\" is not a bitrate such as 3M, 800k or 1500000"))?;
    let bps = v * mult;
    if bps.is_finite() && (1e3..=1e10).contains(&bps) {
        Ok(bps)
    } else {
        Err(format!("{s}: give 1k to 10G bits per second"))
    }
}

/// Arguments of `cpsl encode`.
#[derive(Args)]
pub struct EncodeArgs {
    /// Input: a video file (any container and codec FFmpeg reads), an image, a folder of
    /// PNG/JPEG frames, or a layered video (the output of `cpsl layer-video`, coded as it was
    /// layered: its K, GOP and refreshes; the layering options are not used).
    pub input: PathBuf,
    /// Output package (a folder, by convention `NAME.cpsl`; one file with --archive). Written
    /// beside it first and moved into place when complete; an existing package is replaced,
    /// anything else is refused.
    #[arg(short, long)]
    pub output: PathBuf,
    /// Write the package as one archive file (an uncompressed tar of the folder, which every
    /// command reads like the folder) instead of a folder.
    #[arg(long, conflicts_with = "variants")]
    pub archive: bool,
    /// Codec of the layer streams.
    #[arg(long, value_enum, default_value_t = CodecArg::H264)]
    pub codec: CodecArg,
    /// How the layer streams are stored.
    #[arg(long, value_enum, default_value_t = ContainerArg::Fragment)]
    pub container: ContainerArg,
    /// Where segments (and the layer streams' key frames) start: `gop`, every --gop frames
    /// and at a refresh of the layering that brings a new layer (one whose layers all kept
    /// their tracks continues the streams); or `refresh`, at every I-frame of the layering
    /// (the paper's groups of pictures).
    #[arg(long, value_enum, default_value_t = SegmentAtArg::Gop)]
    pub segment_at: SegmentAtArg,
    /// Keep the paper's fixed refresh threshold under a budget. By default a budget below
    /// 0.024 bits per pixel (1.5 Mbit/s at 1080p30, 0.66 Mbit/s at 720p30) lowers the adaptive
    /// refresh's confidence threshold by 0.1, so that the layering refreshes less where a
    /// refresh costs the streams more than the drift it removes (variants: for their median
    /// budget).
    #[arg(long)]
    pub fixed_refresh: bool,
    /// Total bitrate budget (`3M`, `800k`), allocated per layer by saliency and edges; without
    /// it every layer is coded at --quality.
    #[arg(long, value_parser = parse_bitrate)]
    pub bitrate: Option<f64>,
    /// Constant quality (the codec's CRF) when no --bitrate is given; the codec's default when
    /// omitted (h264 23, h265 28, av1 35, vp9 32).
    #[arg(long, conflicts_with = "bitrate")]
    pub quality: Option<f32>,
    /// Several budgets (`500k,1M,3M`): one package per budget from a single layering pass,
    /// written into the --output folder with a `variants.json` that the browser player
    /// (`cpsl serve`) adapts between at segment boundaries.
    #[arg(long, value_delimiter = ',', value_parser = parse_bitrate, conflicts_with_all = ["bitrate", "quality"])]
    pub variants: Vec<f64>,
    /// Frame rate of the package; the input's by default (30 for image folders).
    #[arg(long)]
    pub fps: Option<f64>,
    /// Print how each segment was coded: its budget and what it spent, the encodes run, the
    /// streams fitted by trial encodes, and each stream's quality and size.
    #[arg(long)]
    pub segments: bool,
    #[command(flatten)]
    pub layering: VideoLayeringArgs,
}

/// Runs `cpsl encode`.
pub fn run(a: EncodeArgs) -> Result<()> {
    let codec = Codec::from(a.codec);
    cpsl_pipeline::encode::require_encoder(codec)?;
    let (q_min, q_max, q_default) = cpsl_codec::quality_range(codec);
    let rate = match (a.bitrate, a.quality) {
        (Some(b), _) => RateControl::Budget(b),
        (None, Some(q)) if (q_min..=q_max).contains(&q) => RateControl::Quality(q),
        (None, Some(q)) => bail!("--quality {q}: {} takes {q_min} to {q_max}", codec.name()),
        (None, None) => RateControl::Quality(q_default),
    };
    let target = match (a.archive, a.variants.is_empty()) {
        (_, false) => EncodeTarget::Variants(a.output.clone(), a.variants.clone()),
        (true, true) => EncodeTarget::Archive(a.output.clone(), rate),
        (false, true) => EncodeTarget::Package(a.output.clone(), rate),
    };
    // A layered video folder is coded as it was layered; anything else is layered first.
    let layered = cpsl_pipeline::video::is_layered_video(&a.input);
    let (mut video, mut depth) = match layered {
        true => (a.layering.video_job(&a.input)?, None),
        false => {
            let (video, depth) = a.layering.job(&a.input)?;
            (video, Some(depth))
        }
    };
    video.gop.rate_aware_refresh = !a.fixed_refresh;
    let job = EncodeJob {
        video,
        codec,
        container: a.container.into(),
        segments: a.segment_at.into(),
        fps: a.fps,
        target,
    };
    // Ctrl-C stops after the current frame; the staging folders are removed, nothing is left
    // half-written.
    let stop = Arc::new(AtomicBool::new(false));
    {
        let stop = stop.clone();
        ctrlc::set_handler(move || stop.store(true, Ordering::SeqCst))
            .context("installing the Ctrl-C handler")?;
    }
    let done = match depth.as_mut() {
        Some(depth) => encode(&job, depth, &Bars::default(), &stop)?,
        None => encode_layered(&job, &Bars::default(), &stop)?,
    };
    let (secs, coding) = (done.seconds, done.coding_seconds);
    for (path, m) in &done.packages {
        println!(
            "wrote {} ({} frames, {} segment{}, {} at {:.0} kbit/s{}) in {secs:.1} s ({:.1} frames/s; coding {coding:.1} s, {:.1} frames/s)",
            path.display(),
            m.frames,
            m.segments.len(),
            if m.segments.len() == 1 { "" } else { "s" },
            codec.name(),
            m.bitrate() / 1e3,
            match m.budget {
                Some(b) => format!(" for a budget of {:.0} kbit/s", b as f64 / 1e3),
                None => String::new(),
            },
            m.frames as f64 / secs,
            m.frames as f64 / coding.max(1e-9)
        );
    }
    if a.segments {
        for ((path, _), reports) in done.packages.iter().zip(&done.reports) {
            print_segments(path, reports);
        }
    }
    if let Some(set) = &done.variant_set {
        println!("wrote {} ({} variants)", set.display(), done.packages.len());
    }
    crate::util::print_depth_runs(&done.depth);
    crate::util::warn_damaged(&job.video.input, done.damaged_packets);
    Ok(())
}

/// One line per segment of `reports`: frames, budget and spending, encodes, fitted streams,
/// quality per stream (`/2`, `/4`, `/8`: coded at that fraction of the size).
fn print_segments(path: &Path, reports: &[SegmentReport]) {
    println!("{}: segments", path.display());
    println!("  frames       budget kbit  spent kbit  encodes  fitted  quality per stream");
    for r in reports {
        let spent = r.bits / 1e3;
        let budget = match r.budget_bits {
            Some(b) => format!(
                "{:>11.1}  {spent:>10.1} ({:+.0} %)",
                b / 1e3,
                100.0 * (r.bits / b - 1.0)
            ),
            None => format!("{:>11}  {spent:>10.1}", "-"),
        };
        let q: Vec<String> = r
            .quality
            .iter()
            .zip(&r.scale)
            .map(|(q, s)| match s {
                1 => format!("{q:.0}"),
                s => format!("{q:.0}/{s}"),
            })
            .collect();
        println!(
            "  {:>5}-{:<5}  {budget}  {:>7}  {:>6}  {}",
            r.start,
            r.start + r.frames - 1,
            r.encodes,
            r.fitted,
            q.join(" ")
        );
    }
}

/// Arguments of `cpsl pack`.
#[derive(Args)]
pub struct PackArgs {
    /// The package folder.
    pub package: PathBuf,
    /// The archive to write (replaced if it is one; anything else is refused).
    #[arg(short, long)]
    pub output: PathBuf,
}

/// Runs `cpsl pack`.
pub fn pack(a: PackArgs) -> Result<()> {
    anyhow::ensure!(
        a.package.is_dir(),
        "{}: not a package folder",
        a.package.display()
    );
    let bytes = cpsl_package::pack(&a.package, &a.output)?;
    println!(
        "wrote {} ({:.1} kB)",
        a.output.display(),
        bytes as f64 / 1e3
    );
    Ok(())
}
