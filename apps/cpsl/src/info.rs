//! `cpsl info` and `cpsl verify`: the summary and the integrity check of a package, a layer-set
//! folder or a layered video.

use anyhow::{bail, Context, Result};
use clap::Args;
use cpsl_core::{Geometry, Limits};
use cpsl_package::Package;
use cpsl_pipeline::video::{depth_runs, read_manifest, VIDEO_FILE};
use cpsl_player::Frames;
use std::path::{Path, PathBuf};

/// Arguments of `cpsl info` and `cpsl verify`.
#[derive(Args)]
pub struct InfoArgs {
    /// A package (a folder or an archive), a layer-set folder (from `cpsl layer`) or a layered
    /// video (from `cpsl layer-video`).
    pub path: PathBuf,
}

/// Runs `cpsl info`.
pub fn run(a: InfoArgs) -> Result<()> {
    let p = &a.path;
    if p.join(VIDEO_FILE).is_file() {
        video(p)
    } else if is_layer_set(p) {
        layer_set(p, "")
    } else {
        package(p)
    }
}

/// Runs `cpsl verify`: every file of a package checked against its checksum, or every frame
/// of a layered video and every file of a layer set read and checked as the players read
/// them.
pub fn verify(a: InfoArgs) -> Result<()> {
    let p = &a.path;
    let (problems, checked) = if p.join(VIDEO_FILE).is_file() {
        let mut video = cpsl_player::LayeredVideo::open(p)?;
        let n = Frames::frames(&video);
        let problems: Vec<String> = (0..n)
            .filter_map(|f| Frames::decode(&mut video, f).err())
            .map(|e| e.to_string())
            .collect();
        (problems, format!("{n} frames"))
    } else if is_layer_set(p) {
        let limits = Limits::default();
        let set = cpsl_io::read_layer_set(p, &limits)?;
        cpsl_io::read_edc(p, &set, &limits)?;
        (Vec::new(), format!("{} layers", set.len()))
    } else {
        let pkg = Package::open(p)?;
        let problems: Vec<String> = pkg.verify().iter().map(|e| e.to_string()).collect();
        (
            problems,
            format!("{} files", pkg.manifest().files().count() + 1),
        )
    };
    if problems.is_empty() {
        println!("{}: ok ({checked} checked)", p.display());
        return Ok(());
    }
    for e in &problems {
        eprintln!("{e}");
    }
    bail!(
        "{}: {} of {checked} damaged or missing",
        p.display(),
        problems.len()
    )
}

/// Whether `dir` holds a layer-set manifest (of any version, so that a newer one gets the
/// reader's version error rather than a package error).
fn is_layer_set(dir: &Path) -> bool {
    std::fs::read(dir.join(cpsl_io::MANIFEST_FILE)).is_ok_and(|b| {
        !matches!(
            cpsl_core::check_head(&b, cpsl_core::FORMAT_NAME, u32::MAX),
            Err(cpsl_core::HeadError::Format(_) | cpsl_core::HeadError::Json(_))
        )
    })
}

/// A layer's surface in a few words.
fn surface(g: &Geometry) -> String {
    match g {
        Geometry::Plane => "plane".to_string(),
        Geometry::Slanted(m) => {
            // The plane's tilt from fronto-parallel.
            let tilt = (m.x().hypot(m.y()) / m.z().abs()).atan().to_degrees();
            format!("slanted {tilt:.0}deg")
        }
        Geometry::Mesh(g) => format!("mesh {}px", g.step),
    }
}

fn kb(path: &Path) -> f64 {
    std::fs::metadata(path).map_or(0.0, |m| m.len() as f64 / 1e3)
}

/// The summary of a layer-set folder, each line after the first indented by `indent`.
fn layer_set(dir: &Path, indent: &str) -> Result<()> {
    let limits = Limits::default();
    let set = cpsl_io::read_layer_set(dir, &limits)
        .with_context(|| format!("reading layer set {}", dir.display()))?;
    // The manifest as written (the reader has checked it).
    let manifest = cpsl_core::Manifest::parse(&std::fs::read(dir.join(cpsl_io::MANIFEST_FILE))?)?;
    let c = set.camera();
    println!(
        "{}: {} v{}, {}x{}, camera fx {:.1} fy {:.1} cx {:.1} cy {:.1}, {} layers (nearest first)",
        dir.display(),
        manifest.format,
        manifest.version,
        c.width,
        c.height,
        c.fx,
        c.fy,
        c.cx,
        c.cy,
        set.len()
    );
    println!("{indent}  layer  depth      surface          cover  image kB  grid kB  role");
    for (i, (l, e)) in set.layers().iter().zip(&manifest.layers).enumerate() {
        let covered = l
            .image
            .as_bytes()
            .chunks_exact(4)
            .filter(|p| p[3] > 0)
            .count();
        let cover = 100.0 * covered as f64 / (c.width as f64 * c.height as f64);
        let grid = e
            .grid
            .as_ref()
            .map_or("-".into(), |g| format!("{:.1}", kb(&dir.join(g))));
        println!(
            "{indent}  {i:>5}  {:<9.4}  {:<15}  {cover:>5.1}%  {:>8.1}  {grid:>7}  {}",
            l.depth,
            surface(&l.geometry),
            kb(&dir.join(&e.file)),
            l.meta
                .role
                .map_or("-".into(), |r| format!("{r:?}").to_lowercase()),
        );
    }
    match cpsl_io::read_edc(dir, &set, &limits)? {
        Some(edc) => println!(
            "{indent}  edge-depth cache: {} samples ({:.1} kB)",
            edc.samples.len(),
            kb(&dir.join(cpsl_io::EDC_FILE))
        ),
        None => println!("{indent}  no edge-depth cache"),
    }
    Ok(())
}

/// The summary of a layered video: its frames, where their depth came from, and its first
/// frame's layer set.
fn video(dir: &Path) -> Result<()> {
    let v = read_manifest(dir)?;
    let intra: Vec<_> = v.frames.iter().filter(|f| f.kind == "I").collect();
    println!(
        "{}: {} v{} from {} ({}), {}x{} at {:.3} fps, {} frames ({} I, {} P), GOP {}",
        dir.display(),
        v.format,
        v.version,
        v.input,
        v.codec,
        v.width,
        v.height,
        v.fps,
        v.frames.len(),
        intra.len(),
        v.frames.len() - intra.len(),
        v.gop.gop
    );
    println!("  depth: {}", v.depth);
    let runs = depth_runs(v.frames.iter().map(|f| (f.index, f.depth_note.as_deref())));
    for r in &runs {
        println!("    frames {:>5}-{:<5} {}", r.first, r.last, r.note);
    }
    let reasons: Vec<String> = intra
        .iter()
        .map(|f| match f.refresh {
            Some(r) => format!("{} ({})", f.index, r.name()),
            None => f.index.to_string(),
        })
        .collect();
    println!("  I-frames: {}", reasons.join(", "));
    let median = |kind: &str| {
        let mut ms: Vec<f64> = v
            .frames
            .iter()
            .filter(|f| f.kind == kind)
            .map(|f| f.ms)
            .collect();
        ms.sort_by(f64::total_cmp);
        ms.get(ms.len() / 2).copied()
    };
    if let (Some(i), p) = (median("I"), median("P")) {
        println!(
            "  layering time (median): I-frame {i:.0} ms{}",
            p.map_or(String::new(), |p| format!(", P-frame {p:.0} ms"))
        );
    }
    let bytes: u64 = v
        .frames
        .iter()
        .flat_map(|f| std::fs::read_dir(dir.join(&f.dir)).into_iter().flatten())
        .filter_map(|e| e.ok()?.metadata().ok())
        .map(|m| m.len())
        .sum();
    println!("  {:.1} MB of layer sets on disk", bytes as f64 / 1e6);
    if let Some(first) = v.frames.first() {
        print!("  first frame, ");
        layer_set(&dir.join(&first.dir), "  ")?;
    }
    Ok(())
}

/// The summary of a package.
fn package(path: &Path) -> Result<()> {
    let pkg = Package::open(path)?;
    let m = pkg.manifest();
    let c = &m.camera;
    println!("{}: {} v{}", path.display(), m.format, m.version);
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
    if !m.depth.is_empty() {
        println!("  depth (where the frames' depth came from):");
        for r in &m.depth {
            println!("    frames {:>5}-{:<5} {}", r.first, r.last, r.note);
        }
    }
    let shared = m.segments.iter().any(|s| s.fragment.is_some());
    match m.inits.len() {
        0 => println!("  streams: self-contained MP4 files"),
        n => println!(
            "  streams: {}; {n} init segments ({:.1} kB, fetched once)",
            match shared {
                true => "one movie fragment per segment, a track run per stream",
                false => "a movie fragment per stream and segment",
            },
            m.inits.iter().map(|f| f.bytes).sum::<u64>() as f64 / 1e3
        ),
    }
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
    // Each layer's surface in every segment's first frame, and what the side stream spends
    // on the segment's geometry.
    println!(
        "  segment  layers of its first frame (geometry, depth, stream kbit/s); geometry kbit/s"
    );
    for (i, s) in m.segments.iter().enumerate() {
        let side = pkg.side_stream(i)?;
        let layers: Vec<String> = side.frames[0]
            .layers
            .iter()
            .map(|l| {
                let kbps = s.streams.get(l.stream as usize).map_or(0, |t| t.bitrate) as f64 / 1e3;
                format!("{} z {:.2} {kbps:.0}", surface(&l.geometry), l.depth)
            })
            .collect();
        // The side stream's size against the same stream with every layer fronto-parallel.
        let mut flat = side.clone();
        for l in flat.frames.iter_mut().flat_map(|f| &mut f.layers) {
            l.geometry = Geometry::Plane;
        }
        let bytes = side.encode().len().saturating_sub(flat.encode().len());
        let kbps = bytes as f64 * 8.0 * m.frame_rate / s.frames as f64 / 1e3;
        println!("  {i:>7}  {} ; {kbps:.1}", layers.join(" | "));
    }
    Ok(())
}
