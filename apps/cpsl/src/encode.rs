//! `cpsl encode`, `cpsl info` and `cpsl verify`: the whole pipeline from a video to a package
//! (depth, layering, propagation, coding), and the package's summary and integrity check.

use crate::video::{layer_video, VideoLayering};
use anyhow::{bail, Context, Result};
use clap::{Args, ValueEnum};
use cpsl_codec::{CodingOptions, PackageWriter, RateControl, SegmentReport};
use cpsl_package::{Codec, Package};
use std::path::PathBuf;
use std::sync::atomic::{AtomicBool, Ordering};
use std::sync::Arc;
use std::time::Instant;

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

/// Fails clearly when this FFmpeg cannot encode `codec`.
pub fn require_encoder(codec: Codec) -> Result<()> {
    if !cpsl_codec::has_encoder(codec) {
        bail!(
            "this FFmpeg has no {} encoder (scripts/setup-system.sh installs Debian's, which has all four)",
            codec.name()
        );
    }
    Ok(())
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
    /// Input: a video file (any container and codec FFmpeg reads), an image, or a folder of
    /// PNG/JPEG frames.
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
    #[command(flatten)]
    pub layering: VideoLayering,
}

/// Warns about a segment that missed its budget.
fn warn_over_budget(r: &SegmentReport) {
    if !r.feasible {
        tracing::warn!(
            "segment at frame {}: {:.0} bits spent of a budget of {:.0} ({})",
            r.start,
            r.bits,
            r.budget_bits.unwrap_or(0.0),
            if r.at_floor {
                "the cheapest coding, lowest quality at the smallest size, needs more"
            } else {
                "the allocator's correction rounds did not reach it"
            }
        );
    }
}

/// Runs `cpsl encode`.
pub fn run(a: EncodeArgs) -> Result<()> {
    let codec = Codec::from(a.codec);
    require_encoder(codec)?;
    let (q_min, q_max, q_default) = cpsl_codec::quality_range(codec);
    let rate = match (a.bitrate, a.quality) {
        (Some(b), _) => RateControl::Budget(b),
        (None, Some(q)) if (q_min..=q_max).contains(&q) => RateControl::Quality(q),
        (None, Some(q)) => bail!("--quality {q}: {} takes {q_min} to {q_max}", codec.name()),
        (None, None) => RateControl::Quality(q_default),
    };
    // One (package, rate) per output: the package itself, or one per variant.
    // With --archive the folder is written to a hidden sibling and packed into --output.
    let unpacked = a.archive.then(|| {
        let name = a.output.file_name().unwrap_or_default().to_string_lossy();
        a.output.with_file_name(format!(".{name}.folder"))
    });
    let outputs: Vec<(PathBuf, RateControl)> = if a.variants.is_empty() {
        let replaceable = match a.archive {
            true => cpsl_package::is_archive(&a.output),
            false => cpsl_package::is_package(&a.output) && a.output.is_dir(),
        };
        if a.output.exists() && !replaceable {
            bail!(
                "{} exists and is not a CPSL package{}; not replacing it",
                a.output.display(),
                if a.archive { " archive" } else { "" }
            );
        }
        vec![(unpacked.clone().unwrap_or_else(|| a.output.clone()), rate)]
    } else {
        let set = a.output.join(cpsl_package::VARIANTS_FILE);
        if a.output.exists() && !set.is_file() {
            bail!(
                "{} exists and is not a variant set (no {}); not replacing it",
                a.output.display(),
                cpsl_package::VARIANTS_FILE
            );
        }
        let mut budgets = a.variants.clone();
        budgets.sort_by(f64::total_cmp);
        budgets.dedup();
        std::fs::create_dir_all(&a.output)
            .with_context(|| format!("creating {}", a.output.display()))?;
        budgets
            .into_iter()
            .map(|b| {
                let p = a.output.join(format!("{:.0}k.cpsl", b / 1e3));
                if p.exists() && !cpsl_package::is_package(&p) {
                    bail!("{} exists and is not a CPSL package", p.display());
                }
                Ok((p, RateControl::Budget(b)))
            })
            .collect::<Result<_>>()?
    };
    let fps = match a.fps {
        Some(f) if f.is_finite() && (0.1..=1000.0).contains(&f) => f,
        Some(f) => bail!("--fps {f}: give 0.1 to 1000 frames per second"),
        None => {
            cpsl_media::open(&a.input)
                .with_context(|| format!("opening {}", a.input.display()))?
                .info()
                .fps
        }
    };
    let (cfg, gop, mut depth) = a.layering.setup()?;
    // Ctrl-C stops after the current frame; the staging folder is removed, nothing is left
    // half-written.
    let stop = Arc::new(AtomicBool::new(false));
    {
        let stop = stop.clone();
        ctrlc::set_handler(move || stop.store(true, Ordering::SeqCst))
            .context("installing the Ctrl-C handler")?;
    }
    let mut writers: Vec<PackageWriter> = Vec::new();
    let mut coding = 0.0;
    let t = Instant::now();
    layer_video(&a.input, &a.layering, &cfg, gop, &mut depth, |r| {
        if stop.load(Ordering::SeqCst) {
            bail!("interrupted; no package written");
        }
        let f = &r.frame;
        if writers.is_empty() {
            for (path, rate) in &outputs {
                let opts = CodingOptions {
                    codec,
                    rate: *rate,
                    fps,
                };
                writers.push(PackageWriter::create(
                    path,
                    *f.set.camera(),
                    a.layering.layers,
                    opts,
                )?);
            }
        }
        let t = Instant::now();
        for writer in writers.iter_mut() {
            let report = writer
                .push(f.clone())
                .with_context(|| format!("coding the segment before frame {}", f.index))?;
            report.iter().for_each(warn_over_budget);
        }
        coding += t.elapsed().as_secs_f64();
        Ok(())
    })?;
    anyhow::ensure!(!writers.is_empty(), "no frames");
    if stop.load(Ordering::SeqCst) {
        bail!("interrupted; no package written");
    }
    let t_last = Instant::now();
    for writer in writers.iter_mut() {
        let report = writer.flush().context("coding the last segment")?;
        report.iter().for_each(warn_over_budget);
    }
    coding += t_last.elapsed().as_secs_f64();
    let secs = t.elapsed().as_secs_f64();
    for (w, (path, _)) in writers.into_iter().zip(&outputs) {
        let m = w.finish()?;
        let path = match &unpacked {
            Some(folder) => {
                let packed = cpsl_package::pack(folder, &a.output);
                std::fs::remove_dir_all(folder)
                    .with_context(|| format!("removing {}", folder.display()))?;
                packed.with_context(|| format!("packing {}", a.output.display()))?;
                &a.output
            }
            None => path,
        };
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
    if !a.variants.is_empty() {
        let names = outputs.iter().filter_map(|(p, _)| p.file_name()?.to_str());
        let set = cpsl_package::VariantSet::new(names.map(String::from).collect());
        set.write(&a.output)?;
        println!(
            "wrote {} ({} variants)",
            a.output.join(cpsl_package::VARIANTS_FILE).display(),
            set.variants.len()
        );
    }
    Ok(())
}

/// Arguments of `cpsl info` and `cpsl verify`.
#[derive(Args)]
pub struct PackageArgs {
    /// The package (a folder, or an archive from `cpsl pack` or `cpsl encode --archive`).
    pub package: PathBuf,
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

/// Runs `cpsl info`.
pub fn info(a: PackageArgs) -> Result<()> {
    let pkg = Package::open(&a.package)?;
    let m = pkg.manifest();
    let c = &m.camera;
    println!("{}: {} v{}", a.package.display(), m.format, m.version);
    println!(
        "  {}x{} at {:.3} fps, {} frames ({:.2} s), camera fx {:.1} fy {:.1} cx {:.1} cy {:.1}",
        c.width,
        c.height,
        m.frame_rate,
        m.frames,
        m.frames as f64 / m.frame_rate,
        c.fx,
        c.fy,
        c.cx,
        c.cy
    );
    println!(
        "  codec {} ({}), {} {}x{} pictures, {} {} range, target K {}",
        m.codec.name(),
        m.codec.mime_codec(),
        m.layout.kind,
        m.layout.coded_width,
        2 * m.layout.coded_height,
        m.layout.matrix,
        m.layout.range,
        m.layers
    );
    println!(
        "  {:.1} kB, {:.0} kbit/s{}",
        m.payload_bytes() as f64 / 1e3,
        m.bitrate() / 1e3,
        match m.budget {
            Some(b) => format!(" (budget {:.0} kbit/s)", b as f64 / 1e3),
            None => " (constant quality)".into(),
        }
    );
    println!("  segment  frames      streams  kbit/s  quality per stream (/2, /4, /8: coded at half, quarter, eighth size)");
    for (i, s) in m.segments.iter().enumerate() {
        let kbps: f64 = s.streams.iter().map(|t| t.bitrate as f64).sum::<f64>() / 1e3;
        let q: Vec<String> = s
            .streams
            .iter()
            .map(|t| match t.scale {
                1 => format!("{:.0}", t.quality),
                f => format!("{:.0}/{f}", t.quality),
            })
            .collect();
        println!(
            "  {i:>7}  {:>5}-{:<5}  {:>7}  {kbps:>6.0}  {}",
            s.start,
            s.start + s.frames - 1,
            s.streams.len(),
            q.join(" ")
        );
    }
    Ok(())
}

/// Runs `cpsl verify`.
pub fn verify(a: PackageArgs) -> Result<()> {
    let pkg = Package::open(&a.package)?;
    let problems = pkg.verify();
    let files = pkg.manifest().files().count() + 1;
    if problems.is_empty() {
        println!("{}: ok ({files} files checked)", a.package.display());
        Ok(())
    } else {
        for p in &problems {
            eprintln!("{p}");
        }
        bail!(
            "{}: {} of {files} files damaged or missing",
            a.package.display(),
            problems.len()
        )
    }
}
