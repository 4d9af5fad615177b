//! Small helpers shared by the commands.

/// How the renderers resample layers (`--filter`). Offline renders and evaluations default
/// to `cubic`, the real-time players and the render benchmark to `bilinear`.
#[derive(Clone, Copy, Debug, clap::ValueEnum)]
pub enum FilterArg {
    /// Bilinear (2x2 taps): the players' default, the fastest.
    Bilinear,
    /// Catmull-Rom bicubic (4x4 taps): sharper at sub-pixel shifts; lower LPIPS on every
    /// scene of EVALUATION.md, PSNR within 0.1 dB; about 3x the CPU's render time.
    Cubic,
}

impl From<FilterArg> for cpsl_render::Filter {
    fn from(f: FilterArg) -> Self {
        match f {
            FilterArg::Bilinear => Self::Bilinear,
            FilterArg::Cubic => Self::Cubic,
        }
    }
}

/// The long help of `--geometry`, shared by every command that layers.
pub const GEOMETRY_HELP: &str = "Layer surfaces: `plane` (the paper's fronto-parallel planes), \
`slanted` (a plane fitted to each layer's depth where it fits clearly better; the default for \
video) or `mesh` (a depth mesh or a slanted plane where either fits clearly better; the \
default for single images). Overrides the configuration file's.";

/// Parses `R,G,B` (0-255 each).
pub fn parse_rgb(s: &str) -> Result<[u8; 3], String> {
    let v: Vec<u8> = s
        .split(',')
        .map(|p| p.trim().parse::<u8>())
        .collect::<Result<_, _>>()
        .map_err(|e| format!("colour '{s}': {e}; expected R,G,B with values 0-255"))?;
    <[u8; 3]>::try_from(v)
        .map_err(|v| format!("colour '{s}': expected 3 values, found {}", v.len()))
}

/// Where the frames' depth came from: how many frames got the depth asked for, then each run
/// of frames that fell back as a warning (at most ten; video.json has every frame's note).
pub fn print_depth_runs(runs: &[cpsl_pipeline::video::DepthRun]) {
    let Some(last) = runs.last() else { return };
    let len = |r: &cpsl_pipeline::video::DepthRun| (r.last - r.first + 1) as usize;
    let fell: Vec<_> = runs.iter().filter(|r| r.is_fallback()).collect();
    let fallen: usize = fell.iter().map(|r| len(r)).sum();
    let total = (last.last - runs[0].first + 1) as usize;
    println!(
        "depth as asked on {} of {total} frames{}",
        total - fallen,
        match fell.len() {
            0 => String::new(),
            n => format!("; {fallen} frames in {n} run(s) fell back"),
        }
    );
    for r in fell.iter().take(10) {
        let frames = match r.first == r.last {
            true => format!("frame {}", r.first),
            false => format!("frames {}-{}", r.first, r.last),
        };
        eprintln!("warning: depth of {frames}: {}", r.note);
    }
    if fell.len() > 10 {
        eprintln!(
            "warning: ... and {} more runs of fallbacks",
            fell.len() - 10
        );
    }
}

/// Says on stderr that `damaged` packets of `input` were skipped, if any.
pub fn warn_damaged(input: &std::path::Path, damaged: usize) {
    if damaged > 0 {
        eprintln!(
            "warning: {}: {damaged} damaged packet(s) skipped; their frames are missing",
            input.display()
        );
    }
}
