//! `cpsl view`: the desktop viewer (`cpsl-viewer`, whose documentation lists the controls) on
//! a package, a layered video or a layer set.

use crate::util::FilterArg;
use anyhow::Result;
use clap::Args;
use cpsl_core::Pose;
use cpsl_viewer::{ViewOptions, ViewerEvent};
use std::path::PathBuf;

/// Arguments of `cpsl view`.
#[derive(Args)]
pub struct ViewArgs {
    /// A package (from `cpsl encode`), a layered video (from `cpsl layer-video`) or a layer-set
    /// folder (from `cpsl layer`).
    pub source: PathBuf,
    /// Frame to start at.
    #[arg(long, default_value_t = 0)]
    pub frame: u32,
    /// Starting viewer pose `tx,ty,tz,rx,ry,rz` (as `cpsl render --pose`); dragging moves
    /// away from it, R returns to the reference view.
    #[arg(long, allow_hyphen_values = true, value_parser = Pose::parse)]
    pub pose: Option<Pose>,
    /// Start paused.
    #[arg(long)]
    pub paused: bool,
    /// Side-by-side stereo (left eye on the left), for headsets and 3D displays.
    #[arg(long)]
    pub stereo: bool,
    /// Distance between the eyes in scene units.
    #[arg(long, default_value_t = 0.06)]
    pub eye_separation: f64,
    /// Without the Dynamic Pixel Strip.
    #[arg(long)]
    pub no_dps: bool,
    /// Without the on-screen readout.
    #[arg(long)]
    pub no_hud: bool,
    /// How the layers are resampled at start: `bilinear` or `cubic` (Catmull-Rom: sharper,
    /// 16 texel reads a layer and pixel instead of 4); key C toggles.
    #[arg(long, value_enum, default_value_t = FilterArg::Bilinear)]
    pub filter: FilterArg,
    /// Close after this many seconds (for demos and tests).
    #[arg(long)]
    pub exit_after: Option<f64>,
}

/// Runs `cpsl view`.
pub fn run(a: ViewArgs) -> Result<()> {
    let events = |e: ViewerEvent| match e {
        ViewerEvent::Opened { adapter, format } => eprintln!("cpsl view: {adapter} ({format})"),
        // Tests wait for this line before taking a screenshot.
        ViewerEvent::Shown { adapter } => println!("shown on {adapter}"),
    };
    Ok(cpsl_viewer::run(
        ViewOptions {
            source: a.source,
            frame: a.frame,
            pose: a.pose,
            paused: a.paused,
            stereo: a.stereo,
            eye_separation: a.eye_separation,
            dps: !a.no_dps,
            hud: !a.no_hud,
            filter: a.filter.into(),
            exit_after: a.exit_after,
        },
        events,
    )?)
}
