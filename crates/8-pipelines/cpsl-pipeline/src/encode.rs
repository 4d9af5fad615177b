//! A video to a package: frames decoded, layered and pushed into the package writers as they
//! arrive (each writer codes a segment when its group of pictures closes), written as a
//! package folder, a single archive file, or one package per budget with a `variants.json`;
//! or the frames of a layered video folder, coded as they were layered ([`encode_layered`]).

use crate::error::{Context, PipelineError};
use crate::sources::VideoDepth;
use crate::video::{layer_video, VideoJob};
use cpsl_codec::{CodingOptions, Container, PackageWriter, RateControl, SegmentReport};
use cpsl_core::{LayeredFrame, Progress, ProgressEvent};
use cpsl_package::{Codec, PackageManifest, VariantSet, VARIANTS_FILE};
use std::path::{Path, PathBuf};
use std::sync::atomic::{AtomicBool, Ordering};
use std::time::Instant;

/// What an encode writes.
#[derive(Debug, Clone, PartialEq)]
pub enum EncodeTarget {
    /// One package folder at this rate.
    Package(PathBuf, RateControl),
    /// One package as a single archive file at this rate.
    Archive(PathBuf, RateControl),
    /// One package per budget (bits per second) in this folder, with `variants.json`.
    Variants(PathBuf, Vec<f64>),
}

/// How a video is encoded.
#[derive(Debug, Clone)]
pub struct EncodeJob {
    /// How the frames are layered (its `layering.layers` is the package's K).
    pub video: VideoJob,
    /// Codec of the layer streams.
    pub codec: Codec,
    /// How the layer streams are stored.
    pub container: Container,
    /// Where segments start.
    pub segments: cpsl_codec::Segments,
    /// Frames per second of the package; the input's when `None`.
    pub fps: Option<f64>,
    /// What to write.
    pub target: EncodeTarget,
}

/// What an encode wrote.
#[derive(Debug, Clone)]
pub struct Encoded {
    /// Each package written (for variants, cheapest first) and its manifest.
    pub packages: Vec<(PathBuf, PackageManifest)>,
    /// Each package's segment reports, in segment order.
    pub reports: Vec<Vec<SegmentReport>>,
    /// The variant set, if one was written.
    pub variant_set: Option<PathBuf>,
    /// Seconds end to end.
    pub seconds: f64,
    /// Seconds spent coding.
    pub coding_seconds: f64,
    /// Damaged packets of the input that were skipped (their frames are missing).
    pub damaged_packets: usize,
    /// Where the frames' depth came from, where the source says (`depth_runs`).
    pub depth: Vec<crate::video::DepthRun>,
}

/// Fails clearly when this FFmpeg cannot encode `codec`.
pub fn require_encoder(codec: Codec) -> Result<(), PipelineError> {
    if cpsl_codec::has_encoder(codec) {
        Ok(())
    } else {
        Err(PipelineError::Invalid(format!(
            "this FFmpeg has no {} encoder (scripts/setup-system.sh installs Debian's, which has all four)",
            codec.name()
        )))
    }
}

/// The packages to write, each with its rate: one, or one per budget.
fn plan(target: &EncodeTarget) -> Result<Vec<(PathBuf, RateControl)>, PipelineError> {
    let refuse = |what: String| Err(PipelineError::Invalid(what));
    match target {
        EncodeTarget::Package(out, rate) => {
            if out.exists() && !(out.is_dir() && cpsl_package::is_package(out)) {
                return refuse(format!(
                    "{} exists and is not a CPSL package; not replacing it",
                    out.display()
                ));
            }
            Ok(vec![(out.clone(), *rate)])
        }
        EncodeTarget::Archive(out, rate) => {
            if out.exists() && !cpsl_package::is_archive(out) {
                return refuse(format!(
                    "{} exists and is not a CPSL package archive; not replacing it",
                    out.display()
                ));
            }
            Ok(vec![(archive_folder(out), *rate)])
        }
        EncodeTarget::Variants(dir, budgets) => {
            if dir.exists() && !dir.join(VARIANTS_FILE).is_file() {
                return refuse(format!(
                    "{} exists and is not a variant set (no {VARIANTS_FILE}); not replacing it",
                    dir.display()
                ));
            }
            let mut budgets = budgets.clone();
            budgets.sort_by(f64::total_cmp);
            budgets.dedup();
            std::fs::create_dir_all(dir).map_err(|source| PipelineError::File {
                path: dir.clone(),
                source,
            })?;
            budgets
                .into_iter()
                .map(|b| {
                    let p = dir.join(format!("{:.0}k.cpsl", b / 1e3));
                    if p.exists() && !cpsl_package::is_package(&p) {
                        return Err(PipelineError::Invalid(format!(
                            "{} exists and is not a CPSL package",
                            p.display()
                        )));
                    }
                    Ok((p, RateControl::Budget(b)))
                })
                .collect()
        }
    }
}

/// The budget the layering is made for: the package's, or the variants' median (the lower of
/// the middle two); `None` at constant quality.
fn layering_budget(outputs: &[(PathBuf, RateControl)]) -> Option<f64> {
    let budgets: Vec<f64> = outputs
        .iter()
        .filter_map(|(_, r)| match r {
            RateControl::Budget(b) => Some(*b),
            RateControl::Quality(_) => None,
        })
        .collect();
    budgets.get(budgets.len().saturating_sub(1) / 2).copied()
}

/// Says when a segment missed its budget.
fn warn_over_budget(r: &SegmentReport, progress: &dyn Progress) {
    if !r.feasible {
        progress.event(ProgressEvent::Warning {
            message: format!(
                "segment at frame {}: {:.0} bits spent of a budget of {:.0} ({})",
                r.start,
                r.bits,
                r.budget_bits.unwrap_or(0.0),
                if r.at_floor {
                    "the cheapest coding, lowest quality at the smallest size, needs more"
                } else {
                    "the streams cost more than their models said; the next segments make up for it"
                }
            ),
        });
    }
}

/// The package's frame rate: `given` (checked) or the input's.
fn frame_rate(given: Option<f64>, input: f64) -> Result<f64, PipelineError> {
    match given {
        Some(f) if f.is_finite() && (0.1..=1000.0).contains(&f) => Ok(f),
        Some(f) => Err(PipelineError::Invalid(format!(
            "--fps {f}: give 0.1 to 1000 frames per second"
        ))),
        None => Ok(input),
    }
}

/// The packages of one encode, fed layered frames one at a time (every writer codes a segment
/// when its group of pictures closes).
struct Packages<'a> {
    job: &'a EncodeJob,
    outputs: Vec<(PathBuf, RateControl)>,
    fps: f64,
    /// Frames per group of pictures, and layers per frame (K).
    gop: u32,
    layers: u32,
    writers: Vec<PackageWriter>,
    reports: Vec<Vec<SegmentReport>>,
    /// Seconds spent coding.
    coding: f64,
    /// Each frame's depth note.
    notes: Vec<(u32, Option<String>)>,
    progress: &'a dyn Progress,
    stop: &'a AtomicBool,
}

impl<'a> Packages<'a> {
    /// Packages for `outputs` at `fps`, `gop` frames per group and `layers` per frame, none
    /// created before the first frame.
    fn new(
        job: &'a EncodeJob,
        outputs: Vec<(PathBuf, RateControl)>,
        (fps, gop, layers): (f64, u32, u32),
        progress: &'a dyn Progress,
        stop: &'a AtomicBool,
    ) -> Self {
        Self {
            job,
            reports: vec![Vec::new(); outputs.len()],
            outputs,
            fps,
            gop,
            layers,
            writers: Vec::new(),
            coding: 0.0,
            notes: Vec::new(),
            progress,
            stop,
        }
    }

    /// Codes `f` into every package (where a segment closes), `frames_left` counting it.
    fn push(
        &mut self,
        f: LayeredFrame,
        depth_note: Option<String>,
        frames_left: Option<usize>,
    ) -> Result<(), PipelineError> {
        self.notes.push((f.index, depth_note));
        if self.stop.load(Ordering::SeqCst) {
            return Err(PipelineError::Interrupted("package"));
        }
        if self.writers.is_empty() {
            for (path, rate) in &self.outputs {
                let opts = CodingOptions {
                    codec: self.job.codec,
                    rate: *rate,
                    fps: self.fps,
                    gop: self.gop,
                    container: self.job.container,
                    segments: self.job.segments,
                };
                let camera = *f.set.camera();
                self.writers
                    .push(PackageWriter::create(path, camera, self.layers, opts)?);
            }
        }
        let t = Instant::now();
        let index = f.index;
        let left = frames_left.map(|n| n as u32);
        // Every writer but the last gets a copy; the last takes the frame.
        let n = self.writers.len();
        let mut frame = Some(f);
        for (i, writer) in self.writers.iter_mut().enumerate() {
            let f = match i + 1 == n {
                true => frame.take().expect("the last writer takes the frame"),
                false => frame.clone().expect("kept for the last writer"),
            };
            writer.set_frames_left(left);
            let report = writer
                .push(f)
                .context_with(|| format!("coding the segment before frame {index}"))?;
            report
                .iter()
                .for_each(|r| warn_over_budget(r, self.progress));
            self.reports[i].extend(report);
        }
        self.coding += t.elapsed().as_secs_f64();
        Ok(())
    }

    /// Codes the last segments and writes the target (the run started at `started`).
    fn finish(mut self, started: Instant, damaged: usize) -> Result<Encoded, PipelineError> {
        if self.stop.load(Ordering::SeqCst) {
            return Err(PipelineError::Interrupted("package"));
        }
        let depth_runs =
            crate::video::depth_runs(self.notes.iter().map(|(i, n)| (*i, n.as_deref())));
        let mut packages = Vec::new();
        let outputs = std::mem::take(&mut self.outputs);
        for ((writer, (path, _)), reports) in self
            .writers
            .into_iter()
            .zip(&outputs)
            .zip(&mut self.reports)
        {
            let t = Instant::now();
            let mut writer = writer;
            writer.set_depth(depth_runs.clone());
            let report = writer
                .flush()
                .context_with(|| "coding the last segment".into())?;
            report
                .iter()
                .for_each(|r| warn_over_budget(r, self.progress));
            reports.extend(report);
            let manifest = writer.finish()?;
            self.coding += t.elapsed().as_secs_f64();
            packages.push((path.clone(), manifest));
        }
        let mut variant_set = None;
        match &self.job.target {
            EncodeTarget::Archive(out, _) => {
                let folder = &packages[0].0;
                let packed = cpsl_package::pack(folder, out);
                std::fs::remove_dir_all(folder).map_err(|source| PipelineError::File {
                    path: folder.clone(),
                    source,
                })?;
                packed.context_with(|| format!("packing {}", out.display()))?;
                packages[0].0 = out.clone();
            }
            EncodeTarget::Variants(dir, _) => {
                let names = packages.iter().filter_map(|(p, _)| p.file_name()?.to_str());
                VariantSet::new(names.map(String::from).collect()).write(dir)?;
                variant_set = Some(dir.join(VARIANTS_FILE));
            }
            EncodeTarget::Package(..) => {}
        }
        Ok(Encoded {
            packages,
            reports: self.reports,
            variant_set,
            seconds: started.elapsed().as_secs_f64(),
            coding_seconds: self.coding,
            damaged_packets: damaged,
            depth: depth_runs,
        })
    }
}

/// Encodes the job's video: one layering pass feeds every package of the target. `stop`,
/// when set (e.g. by Ctrl-C), ends the run after the current frame with nothing written.
pub fn encode(
    job: &EncodeJob,
    depth: &mut VideoDepth,
    progress: &dyn Progress,
    stop: &AtomicBool,
) -> Result<Encoded, PipelineError> {
    require_encoder(job.codec)?;
    let input = &job.video.input;
    crate::video::refuse_layers(input)?;
    let outputs = plan(&job.target)?;
    let media = cpsl_media::open(input)
        .context_with(|| format!("opening {}", input.display()))?
        .info()
        .clone();
    let fps = frame_rate(job.fps, media.fps)?;
    // Under a budget the layering's refresh weighs what it costs (`GopConfig::for_budget`);
    // variants share one layering, made for their median budget.
    let mut video = job.video.clone();
    if let Some(bps) = layering_budget(&outputs) {
        let (w, h) = match job.video.stereo {
            Some(layout) => layout
                .view_size(media.width, media.height)
                .unwrap_or((0, 0)),
            None => (media.width, media.height),
        };
        video.gop = video
            .gop
            .for_budget(bps / (f64::from(w) * f64::from(h) * fps));
    }
    let shape = (
        fps,
        job.video.gop.gop as u32,
        job.video.layering.layers as u32,
    );
    let mut packages = Packages::new(job, outputs, shape, progress, stop);
    let t = Instant::now();
    let info = layer_video(&video, depth, progress, |r| {
        packages.push(r.frame, r.depth_note, r.frames_left)
    })?;
    packages.finish(t, info.damaged)
}

/// The progress stage of reading a layered video's frames.
pub const READING: &str = "reading layers";

/// Encodes the layered video folder `job.video.input` (the output of `cpsl layer-video`) as
/// it was layered: its layer sets, refreshes, tracks, temporal confidence and depth notes,
/// its K and group length (`job.video`'s layering and GOP are not used, and a budget does not
/// change refreshes made already). `stop` as for [`encode`].
pub fn encode_layered(
    job: &EncodeJob,
    progress: &dyn Progress,
    stop: &AtomicBool,
) -> Result<Encoded, PipelineError> {
    require_encoder(job.codec)?;
    let dir = &job.video.input;
    // At least one frame (checked by the reader), so `finish` has a package to write.
    let video = crate::video::read_manifest(dir)?;
    let fps = frame_rate(job.fps, video.fps)?;
    let outputs = plan(&job.target)?;
    let shape = (fps, video.gop.gop as u32, video.layering.layers as u32);
    let mut packages = Packages::new(job, outputs, shape, progress, stop);
    let t = Instant::now();
    let n = video.frames.len();
    progress.event(ProgressEvent::Start {
        stage: READING,
        total: Some(n as u64),
    });
    let limits = cpsl_core::Limits::default();
    for (i, e) in video.frames.iter().enumerate() {
        let path = dir.join(&e.dir);
        let set = cpsl_io::read_layer_set(&path, &limits)?;
        let edc = cpsl_io::read_edc(&path, &set, &limits)?.ok_or_else(|| {
            PipelineError::Invalid(format!(
                "{}: no {} (cpsl layer-video writes one per frame)",
                path.display(),
                cpsl_io::EDC_FILE
            ))
        })?;
        let frame = LayeredFrame {
            confidence: e.confidence.clone(),
            crack: e.crack,
            depth_propagated: e.depth == "propagated",
            ..LayeredFrame::new(e.index, e.refresh, set, edc)
        };
        packages.push(frame, e.depth_note.clone(), Some(n - i))?;
        progress.event(ProgressEvent::Advance {
            stage: READING,
            done: i as u64 + 1,
        });
    }
    progress.event(ProgressEvent::Finish { stage: READING });
    packages.finish(t, video.damaged_packets)
}

/// The hidden sibling folder that an archive is written to and packed from.
fn archive_folder(out: &Path) -> PathBuf {
    let name = out.file_name().unwrap_or_default().to_string_lossy();
    out.with_file_name(format!(".{name}.folder"))
}
