//! One interface over every renderer: a frame's layers ([`FrameLayers`]) drawn at a pose by a
//! [`Renderer`], the CPU reference ([`CpuRenderer`]) or another one tested against it.

use crate::{DpsConfig, Filter, PreparedLayers};
use cpsl_core::{Camera, Edc, LayerSet, Pose, PremulImage};
use std::sync::OnceLock;
use thiserror::Error;

/// One frame's layers: the layer set, its Edge-Depth Cache when there is one, and their
/// preparation for the CPU renderer, made on first use (other renderers upload the layers
/// themselves).
pub struct FrameLayers {
    /// The layers.
    pub set: LayerSet,
    /// Their Edge-Depth Cache.
    pub edc: Option<Edc>,
    prepared: OnceLock<PreparedLayers>,
}

impl FrameLayers {
    /// A frame of `set` (with `edc`) to render.
    pub fn new(set: LayerSet, edc: Option<Edc>) -> Self {
        Self {
            set,
            edc,
            prepared: OnceLock::new(),
        }
    }

    /// The layers prepared for the CPU renderer.
    pub fn prepared(&self) -> &PreparedLayers {
        self.prepared.get_or_init(|| {
            let prepared = PreparedLayers::new(&self.set);
            match &self.edc {
                Some(e) => prepared.with_edc(e),
                None => prepared,
            }
        })
    }
}

/// Why a renderer could not draw a view.
#[derive(Debug, Error)]
#[error("{renderer}: {source}")]
pub struct RenderError {
    /// The renderer's name.
    pub renderer: String,
    /// What went wrong.
    pub source: Box<dyn std::error::Error + Send + Sync>,
}

/// Draws a frame's layers from a new viewpoint.
pub trait Renderer {
    /// A short description (for the GPU renderer, its adapter).
    fn name(&self) -> String;

    /// Renders `frame` at `pose` for camera `target` into `out` (resized to the target), with
    /// the Dynamic Pixel Strip when `dps` is given. The alpha of `out` is the view's coverage
    /// ([`PremulImage::covered`]).
    fn render(
        &self,
        frame: &FrameLayers,
        pose: &Pose,
        target: &Camera,
        dps: Option<&DpsConfig>,
        out: &mut PremulImage,
    ) -> Result<(), RenderError>;
}

/// The CPU reference renderer behind the [`Renderer`] interface.
#[derive(Debug, Clone, Copy, Default)]
pub struct CpuRenderer {
    /// How layers are resampled: bilinear by default, as the real-time players draw;
    /// [`Filter::Cubic`] for sharper offline renders (the `cpsl` CLI's default for renders
    /// and evaluations).
    pub filter: Filter,
}

impl CpuRenderer {
    /// The CPU renderer with `filter`.
    pub const fn new(filter: Filter) -> Self {
        Self { filter }
    }
}

impl CpuRenderer {
    /// Renders `frame` at `pose` for camera `target`, with the Dynamic Pixel Strip when `dps`
    /// is given (on the CPU this cannot fail).
    pub fn view(
        &self,
        frame: &FrameLayers,
        pose: &Pose,
        target: &Camera,
        dps: Option<&DpsConfig>,
    ) -> PremulImage {
        let mut out = PremulImage::new(target.width, target.height);
        self.draw(frame, pose, target, dps, &mut out);
        out
    }

    fn draw(
        &self,
        frame: &FrameLayers,
        pose: &Pose,
        target: &Camera,
        dps: Option<&DpsConfig>,
        out: &mut PremulImage,
    ) {
        if (out.width(), out.height()) != (target.width, target.height) {
            *out = PremulImage::new(target.width, target.height);
        }
        let prepared = frame.prepared();
        match dps {
            Some(cfg) => {
                prepared.render_dps_into_with(pose, target, out, cfg, self.filter);
            }
            None => {
                prepared.render_into_with(pose, target, out, self.filter);
            }
        }
    }
}

impl Renderer for CpuRenderer {
    fn name(&self) -> String {
        match self.filter {
            Filter::Bilinear => "CPU reference renderer".into(),
            Filter::Cubic => "CPU reference renderer (bicubic)".into(),
        }
    }

    fn render(
        &self,
        frame: &FrameLayers,
        pose: &Pose,
        target: &Camera,
        dps: Option<&DpsConfig>,
        out: &mut PremulImage,
    ) -> Result<(), RenderError> {
        self.draw(frame, pose, target, dps, out);
        Ok(())
    }
}
