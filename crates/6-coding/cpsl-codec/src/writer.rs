//! Writing a package: frames pushed in and coded as they arrive, a segment per group of
//! pictures (where they start: [`crate::Segments`]), the budget shared out across segments,
//! the manifest, and the staged folder moved into place.

use crate::segment::{BudgetPlan, Carried, SegmentEncoder, SegmentReport};
use crate::{yuv, CodecError, CodingOptions, Container, RateControl, Segments};
use cpsl_core::{LayeredFrame, RefreshReason};
use cpsl_package::Segment;
use std::path::Path;

/// The bits a segment of `n` frames gets from a total budget of `bps` bits per second after
/// `done` frames that took `spent` bits: its own share, corrected by what the earlier
/// segments spent above or below theirs (a bit reservoir), by at most half the share either
/// way. A short segment cut by a refresh costs more than its share (a whole key frame); the
/// following ones pay it back, so that the package keeps to the budget. The video's `last`
/// segment may spend savings up to twice its share, since no later one can (the 720p
/// `testsrc2` clip at 3 Mbit/s ended 5.0 % under its budget with the last segment held to
/// one and a half).
pub fn segment_budget(bps: f64, fps: f64, done: u32, spent: f64, n: usize, last: bool) -> f64 {
    let share = bps * n as f64 / fps;
    let balance = bps * done as f64 / fps - spent;
    let most = if last { 2.0 } else { 1.5 };
    (share + balance).clamp(0.5 * share, most * share)
}

/// The fewest frames a segment starts with at the end of a video of known length under
/// [`Segments::Gop`]: fewer join the segment before (a group of a few frames costs nearly a
/// key frame per stream for them). The layering's shortest group at a clip's end is the same
/// (its default `min_gap`, or half the GOP).
fn tail(gop: u32) -> u32 {
    (gop / 2).clamp(1, 4)
}

/// Writes a package: segments are coded into a hidden staging folder beside the output, and
/// the finished package is moved into place by [`PackageWriter::finish`]. Dropping an
/// unfinished writer removes the staging folder, so an interrupted run never leaves a
/// half-written package; an existing package at the output is replaced only when the new
/// one is complete, and anything else there is never replaced.
pub struct PackageWriter {
    stage: cpsl_io::Staged,
    camera: cpsl_core::Camera,
    layers: u32,
    opts: CodingOptions,
    segments: Vec<Segment>,
    /// Frames of the finished segments.
    frames: u32,
    /// Bits written so far (layer and side streams).
    spent: f64,
    /// The segment being coded.
    open: Option<SegmentEncoder>,
    /// Rate-distortion models carried from the last finished segment.
    carried: Carried,
    /// Frames still to come, the next one included, when known.
    left: Option<u32>,
    /// Where the frames' depth came from (the manifest's `depth`).
    depth: Vec<cpsl_package::DepthRun>,
}

impl PackageWriter {
    /// Starts a package at `out` for frames of `camera` layered with target K `layers`.
    pub fn create(
        out: &Path,
        camera: cpsl_core::Camera,
        layers: u32,
        opts: CodingOptions,
    ) -> Result<Self, CodecError> {
        let stage = cpsl_io::Staged::folder(out, replaceable_package).map_err(|e| match e {
            cpsl_io::IoError::TargetExists { path } => CodecError::Io {
                path,
                source: std::io::Error::new(
                    std::io::ErrorKind::AlreadyExists,
                    "exists and is not a CPSL package folder; not replacing it",
                ),
            },
            e => CodecError::Write(e),
        })?;
        Ok(Self {
            stage,
            camera,
            layers,
            opts,
            segments: Vec::new(),
            frames: 0,
            spent: 0.0,
            open: None,
            carried: Carried::default(),
            left: None,
            depth: Vec::new(),
        })
    }

    /// Where the frames' depth came from, by runs of frames, for the manifest (a package of
    /// self-contained MP4 streams, an older version, carries none).
    pub fn set_depth(&mut self, runs: Vec<cpsl_package::DepthRun>) {
        self.depth = runs;
    }

    /// Tells the writer how many frames are still to come, the next one included (`None`:
    /// unknown, the default), so that under a budget the last segment is planned for the
    /// frames it will have rather than a whole group of pictures.
    pub fn set_frames_left(&mut self, left: Option<u32>) {
        self.left = left.filter(|&n| n > 0);
    }

    /// Takes the next frame and codes it (under a budget, the first frames of a segment may
    /// wait for its trial encodes). A frame that starts a segment (see [`Segments`]) closes the
    /// one before it, whose report is returned then; [`PackageWriter::flush`] or
    /// [`PackageWriter::finish`] closes the last.
    pub fn push(&mut self, frame: LayeredFrame) -> Result<Option<SegmentReport>, CodecError> {
        let expected = self.frames + self.open.as_ref().map_or(0, |o| o.frames() as u32);
        if frame.index != expected {
            return Err(CodecError::Tracks {
                frame: frame.index,
                reason: format!("frames must be pushed in order; frame {expected} expected"),
            });
        }
        let gop = self.opts.gop as usize;
        let continues = self.open.as_ref().is_some_and(|open| {
            let room = open.frames() < gop || self.left.is_some_and(|n| n < tail(self.opts.gop));
            match (self.opts.segments, frame.refresh) {
                (_, Some(RefreshReason::First)) => false,
                (Segments::Refresh, r) => r.is_none(),
                (Segments::Gop, _) => room && open.takes(&frame),
            }
        });
        match (&mut self.open, continues) {
            (Some(open), true) => {
                open.push(frame)?;
                Ok(None)
            }
            _ => {
                let report = self.close(false)?;
                // Under `Segments::Gop` a tail shorter than `tail` frames joins this segment.
                let whole = match self.opts.segments {
                    Segments::Gop => self.opts.gop + tail(self.opts.gop) - 1,
                    Segments::Refresh => self.opts.gop,
                };
                let last = self.left.is_some_and(|n| n <= whole);
                let expected = self.left.filter(|_| last);
                self.start(frame, expected, last)?;
                Ok(report)
            }
        }
    }

    /// Opens the next segment with `first`; `left`: the frames it will take, `first`
    /// included, when known (a budget plans for these, else for a GOP); `last`: they are the
    /// video's last frames.
    fn start(
        &mut self,
        first: LayeredFrame,
        left: Option<u32>,
        last: bool,
    ) -> Result<(), CodecError> {
        let budget = match self.opts.rate {
            RateControl::Budget(bps) => Some(BudgetPlan {
                bps,
                done: self.frames,
                spent: self.spent,
                expected: left.unwrap_or(self.opts.gop).max(1) as usize,
                last,
                may_be_last: last || self.left.is_none(),
            }),
            RateControl::Quality(_) => None,
        };
        let number = self.segments.len();
        let root = self.stage.path();
        self.open = Some(SegmentEncoder::start(
            root,
            number,
            first,
            self.opts,
            budget,
            &self.carried,
        )?);
        Ok(())
    }

    /// Closes the segment being coded, if any (the video's last when the frames left, as
    /// told by [`PackageWriter::set_frames_left`], say so).
    pub fn flush(&mut self) -> Result<Option<SegmentReport>, CodecError> {
        self.close(self.left.is_some_and(|n| n <= 1))
    }

    /// Closes the segment being coded, if any; `last`: no frame follows it.
    fn close(&mut self, last: bool) -> Result<Option<SegmentReport>, CodecError> {
        let Some(open) = self.open.take() else {
            return Ok(None);
        };
        let done = open.finish(last)?;
        self.frames += done.segment.frames;
        self.spent += done.report.bits;
        self.segments.push(done.segment);
        self.carried = done.carried;
        Ok(Some(done.report))
    }

    /// Codes `frames` as the next segment, whatever their refresh flags (its first frame must
    /// follow the previous segment's last).
    pub fn push_segment(&mut self, frames: &[LayeredFrame]) -> Result<SegmentReport, CodecError> {
        let (first, rest) = frames.split_first().ok_or(CodecError::Empty)?;
        self.close(false)?;
        if first.index != self.frames {
            return Err(CodecError::Tracks {
                frame: first.index,
                reason: format!(
                    "segments must be contiguous; frame {} expected",
                    self.frames
                ),
            });
        }
        // The segment's length is known: its allocation plans for it; it is the video's last
        // when the frames left, as told by [`PackageWriter::set_frames_left`], are its own.
        let last = self.left == Some(frames.len() as u32);
        self.start(first.clone(), Some(frames.len() as u32), last)?;
        let open = self.open.as_mut().expect("just started");
        for f in rest {
            if f.index != first.index + open.frames() as u32 {
                return Err(CodecError::Tracks {
                    frame: f.index,
                    reason: "a segment's frames must be contiguous".into(),
                });
            }
            open.push(f.clone())?;
        }
        Ok(self.close(last)?.expect("a segment is open"))
    }

    /// Codes the pending frames ([`PackageWriter::flush`]; their report is dropped: flush
    /// first to see it), writes the manifest and moves the package into place.
    pub fn finish(mut self) -> Result<cpsl_package::PackageManifest, CodecError> {
        self.close(true)?;
        if self.segments.is_empty() {
            return Err(CodecError::Empty);
        }
        let (cw, ch) = yuv::coded_size(self.camera.width, self.camera.height);
        let mut init_paths: Vec<&String> = self
            .segments
            .iter()
            .flat_map(|s| s.streams.iter().filter_map(|t| t.init.as_ref()))
            .collect();
        init_paths.sort();
        init_paths.dedup();
        let root = self.stage.path();
        let inits = init_paths
            .into_iter()
            .map(|p| cpsl_package::file_entry(root, p))
            .collect::<Result<Vec<_>, _>>()?;
        let m = cpsl_package::PackageManifest {
            format: cpsl_package::PACKAGE_FORMAT.into(),
            version: match self.opts.container {
                Container::Fragment => cpsl_package::SEGMENT_FRAGMENT_VERSION,
                Container::StreamFragments if !self.depth.is_empty() => cpsl_package::DEPTH_VERSION,
                Container::StreamFragments => cpsl_package::FRAGMENT_VERSION,
                Container::Mp4 => cpsl_package::version_for(
                    self.segments
                        .iter()
                        .flat_map(|s| s.streams.iter().map(|t| t.scale)),
                ),
            },
            camera: self.camera,
            frame_rate: self.opts.fps,
            frames: self.frames,
            layers: self.layers,
            codec: self.opts.codec,
            layout: cpsl_package::Layout {
                kind: "colour-over-alpha".into(),
                coded_width: cw as u32,
                coded_height: ch as u32,
                pixel_format: "yuv420p".into(),
                matrix: "bt709".into(),
                range: "limited".into(),
            },
            budget: match self.opts.rate {
                RateControl::Budget(b) => Some(b.round() as u64),
                RateControl::Quality(_) => None,
            },
            inits,
            depth: match self.opts.container {
                Container::Fragment | Container::StreamFragments => std::mem::take(&mut self.depth),
                Container::Mp4 => Vec::new(),
            },
            segments: std::mem::take(&mut self.segments),
            checksum: String::new(),
        };
        let path = self.stage.path().join(cpsl_package::MANIFEST_FILE);
        std::fs::write(&path, m.to_json()).map_err(|source| CodecError::Io { path, source })?;
        self.stage.commit(replaceable_package)?;
        Ok(m)
    }
}

/// Whether a package writer may replace what is at `out`: only a package folder.
fn replaceable_package(out: &Path) -> bool {
    out.is_dir() && cpsl_package::is_package(out)
}

#[cfg(test)]
mod tests {
    use super::segment_budget;

    #[test]
    fn the_reservoir_evens_out_segments_within_bounds() {
        // 1 Mbit/s, 30 fps, segments of 30 frames: a share of 1 Mbit.
        assert_eq!(segment_budget(1e6, 30.0, 0, 0.0, 30, false), 1e6);
        // 0.2 Mbit over after one segment: the next gets 0.8; far over: never below half.
        assert!((segment_budget(1e6, 30.0, 30, 1.2e6, 30, false) - 0.8e6).abs() < 1e-6);
        assert_eq!(segment_budget(1e6, 30.0, 30, 5e6, 30, false), 0.5e6);
        // Savings are spent, up to one and a half shares.
        assert!((segment_budget(1e6, 30.0, 60, 1.7e6, 30, false) - 1.3e6).abs() < 1e-6);
        assert_eq!(segment_budget(1e6, 30.0, 90, 0.0, 30, false), 1.5e6);
        // The last segment spends savings up to two shares, and repays as the others do.
        assert!((segment_budget(1e6, 30.0, 60, 1.3e6, 30, true) - 1.7e6).abs() < 1e-6);
        assert_eq!(segment_budget(1e6, 30.0, 90, 0.0, 30, true), 2e6);
        assert_eq!(segment_budget(1e6, 30.0, 30, 5e6, 30, true), 0.5e6);
        // A one-frame segment's share is a thirtieth.
        assert!((segment_budget(1e6, 30.0, 0, 0.0, 1, false) - 1e6 / 30.0).abs() < 1e-6);
    }
}
