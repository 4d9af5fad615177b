//! Content-promoted layering of one frame (paper §3.2), stage by stage:
//! cues ([`crate::cues`]) -> depth-semantic fusion ([`crate::fuse`]) -> promotion and merging
//! ([`crate::promote`]) -> matting, extension and fill ([`crate::matte`]) -> Edge-Depth Cache.

use crate::cues::{CueConfig, Cues};
use crate::error::LayeringError;
use crate::fuse::{fuse, Fusion, FusionConfig};
use crate::matte::{build_layers, edge_depth_cache, upsample_owner, MatteConfig};
use crate::promote::{promote, Plan, PromoteConfig};
use cpsl_core::{Camera, Edc, LayerSet, Progress, ProgressEvent};
use serde::{Deserialize, Serialize};
use std::time::Instant;

/// Every stage's configuration; saved with the output.
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields, default)]
pub struct LayeringConfig {
    /// Target number of layers `K` (2..=16).
    pub layers: usize,
    /// Cue extraction.
    pub cues: CueConfig,
    /// Depth-semantic fusion.
    pub fusion: FusionConfig,
    /// Promotion and merging.
    pub promote: PromoteConfig,
    /// Matting, extension and Edge-Depth Cache.
    pub matte: MatteConfig,
}

impl Default for LayeringConfig {
    fn default() -> Self {
        Self {
            layers: 6,
            cues: CueConfig::default(),
            fusion: FusionConfig::default(),
            promote: PromoteConfig::default(),
            matte: MatteConfig::default(),
        }
    }
}

impl LayeringConfig {
    /// Depth-only ablation: no saliency or instance terms and no promotion.
    pub fn depth_only(mut self) -> Self {
        self.fusion.saliency_weight = 0.0;
        self.fusion.instance_weight = 0.0;
        self.promote.max_promoted = 0;
        self
    }

    /// Checks ranges.
    pub fn validate(&self) -> Result<(), LayeringError> {
        if !(2..=16).contains(&self.layers) {
            return Err(LayeringError::Config {
                field: "layers",
                range: "2..=16",
                found: self.layers.to_string(),
            });
        }
        let f = &self.fusion;
        for (field, v) in [
            ("fusion.sigma", f.sigma),
            ("fusion.truncation", f.truncation),
        ] {
            if !(v.is_finite() && v > 0.0) {
                return Err(LayeringError::Config {
                    field,
                    range: "finite and > 0",
                    found: v.to_string(),
                });
            }
        }
        for (field, v) in [
            ("fusion.saliency_weight", f.saliency_weight),
            ("fusion.instance_weight", f.instance_weight),
            ("fusion.smoothness", f.smoothness),
            ("fusion.contrast", f.contrast),
            ("fusion.semantic", f.semantic),
            ("matte.feather_base", self.matte.feather_base),
            ("matte.feather_gradient", self.matte.feather_gradient),
            ("matte.feather_uncertainty", self.matte.feather_uncertainty),
            ("matte.max_feather", self.matte.max_feather),
            ("matte.extend", self.matte.extend),
            ("matte.colour_weight", self.matte.colour_weight),
            ("promote.cost_tolerance", self.promote.cost_tolerance),
        ] {
            if !(v.is_finite() && v >= 0.0) {
                return Err(LayeringError::Config {
                    field,
                    range: "finite and >= 0",
                    found: v.to_string(),
                });
            }
        }
        if self.matte.mesh_step > cpsl_core::DepthGrid::MAX_STEP {
            return Err(LayeringError::Config {
                field: "matte.mesh_step",
                range: "0 (automatic) or 1..=256",
                found: self.matte.mesh_step.to_string(),
            });
        }
        if !(self.matte.edc_step.is_finite() && self.matte.edc_step > 0.0) {
            return Err(LayeringError::Config {
                field: "matte.edc_step",
                range: "finite and > 0",
                found: self.matte.edc_step.to_string(),
            });
        }
        Ok(())
    }
}

/// The layered frame with its intermediate results.
#[derive(Debug, Clone)]
pub struct Layered {
    /// The layer set.
    pub set: LayerSet,
    /// The Edge-Depth Cache.
    pub edc: Edc,
    /// Final layer index per full-resolution pixel.
    pub owner: Vec<u8>,
    /// The fusion result at working resolution.
    pub fusion: Fusion,
    /// The promotion plan at working resolution.
    pub plan: Plan,
    /// Wall time of each stage in milliseconds, in order.
    pub timings: Vec<(&'static str, f64)>,
}

fn timed<T>(
    timings: &mut Vec<(&'static str, f64)>,
    progress: &dyn Progress,
    stage: &'static str,
    f: impl FnOnce() -> T,
) -> T {
    progress.event(ProgressEvent::Start { stage, total: None });
    let t = Instant::now();
    let r = f();
    timings.push((stage, t.elapsed().as_secs_f64() * 1e3));
    progress.event(ProgressEvent::Finish { stage });
    r
}

/// Layers a frame whose cues are already extracted (so that callers can replace the
/// instances, e.g. with model masks). `rgb` is the frame (3 bytes per pixel).
pub fn layer_cues(
    cues: &Cues,
    rgb: &[u8],
    camera: Camera,
    cfg: &LayeringConfig,
    progress: &dyn Progress,
) -> Result<Layered, LayeringError> {
    cfg.validate()?;
    camera.validate()?;
    if (camera.width as usize, camera.height as usize) != (cues.width, cues.height) {
        return Err(LayeringError::Size {
            what: "cues",
            found: cues.width * cues.height,
            expected: camera.width as usize * camera.height as usize,
            width: camera.width,
            height: camera.height,
        });
    }
    let mut timings = Vec::new();
    let fusion = timed(&mut timings, progress, "fusion", || {
        fuse(
            &cues.work,
            cfg.layers,
            &cfg.fusion,
            cfg.fusion.slanted_labels && cfg.matte.geometry != crate::GeometryMode::Plane,
        )
    });
    let plan = timed(&mut timings, progress, "promotion", || {
        promote(&cues.work, &fusion, cfg.layers, &cfg.promote)
    });
    let owner = timed(&mut timings, progress, "upsampling", || {
        upsample_owner(
            cues,
            rgb,
            &plan,
            cfg.fusion.sigma,
            cfg.fusion.truncation,
            &cfg.matte,
        )
    });
    let set = timed(&mut timings, progress, "matting and fill", || {
        build_layers(cues, rgb, &owner, &plan, camera, &cfg.matte)
    })?;
    let edc = timed(&mut timings, progress, "edge-depth cache", || {
        edge_depth_cache(cues, &owner, &set, &cfg.matte)
    });
    Ok(Layered {
        set,
        edc,
        owner,
        fusion,
        plan,
        timings,
    })
}

/// Layers an RGB frame with its z-depth: cues (with depth-component instances), then
/// [`layer_cues`]. The cue time is the first entry of the timings.
pub fn layer_frame(
    rgb: &[u8],
    depth: &[f32],
    camera: Camera,
    cfg: &LayeringConfig,
    progress: &dyn Progress,
) -> Result<(Cues, Layered), LayeringError> {
    cfg.validate()?;
    let t = Instant::now();
    let cues = Cues::compute(
        rgb,
        depth,
        camera.width as usize,
        camera.height as usize,
        &cfg.cues,
    )?;
    let cue_ms = t.elapsed().as_secs_f64() * 1e3;
    let mut layered = layer_cues(&cues, rgb, camera, cfg, progress)?;
    layered.timings.insert(0, ("cues", cue_ms));
    Ok((cues, layered))
}

#[cfg(test)]
mod tests {
    use super::*;
    use cpsl_core::NoProgress;

    #[test]
    fn degenerate_frames_still_give_valid_layer_sets() {
        let cfg = LayeringConfig::default();
        for (w, h) in [(1u32, 1u32), (8, 6), (3, 40)] {
            let cam = Camera::from_fov(w, h, 60.0);
            let n = (w * h) as usize;
            let rgb: Vec<u8> = (0..n * 3).map(|i| (i * 37 % 256) as u8).collect();
            // Flat depth: one layer.
            let (_, out) = layer_frame(&rgb, &vec![2.0; n], cam, &cfg, &NoProgress).unwrap();
            assert_eq!(out.set.len(), 1);
            assert_eq!(out.set.layers()[0].depth, 2.0);
            // Two depths.
            let depth: Vec<f32> = (0..n).map(|i| if i % 2 == 0 { 1.0 } else { 5.0 }).collect();
            let (_, out) = layer_frame(&rgb, &depth, cam, &cfg, &NoProgress).unwrap();
            // (a promoted region may sit on its own layer at the depth of another)
            for l in out.set.layers() {
                assert!(
                    (l.depth - 1.0).abs() < 1e-4 || (l.depth - 5.0).abs() < 1e-4,
                    "{w}x{h}: layer at {}",
                    l.depth
                );
            }
            assert_eq!(out.owner.len(), n);
        }
    }

    #[test]
    fn rejects_bad_configuration_and_input() {
        let cam = Camera::from_fov(4, 4, 60.0);
        let rgb = [0u8; 48];
        let bad_k = LayeringConfig {
            layers: 17,
            ..Default::default()
        };
        assert!(matches!(
            layer_frame(&rgb, &[1.0; 16], cam, &bad_k, &NoProgress),
            Err(LayeringError::Config {
                field: "layers",
                ..
            })
        ));
        let cfg = LayeringConfig::default();
        assert!(matches!(
            layer_frame(&rgb[..47], &[1.0; 16], cam, &cfg, &NoProgress),
            Err(LayeringError::Size { what: "colour", .. })
        ));
        let mut depth = [1.0f32; 16];
        depth[5] = -1.0;
        assert!(matches!(
            layer_frame(&rgb, &depth, cam, &cfg, &NoProgress),
            Err(LayeringError::BadDepth { x: 1, y: 1, .. })
        ));
        depth[5] = f32::NAN;
        assert!(matches!(
            layer_frame(&rgb, &depth, cam, &cfg, &NoProgress),
            Err(LayeringError::MissingDepth { count: 1, .. })
        ));
        let mut allow = cfg;
        allow.cues.allow_missing_depth = true;
        let (cues, _) = layer_frame(&rgb, &depth, cam, &allow, &NoProgress).unwrap();
        assert_eq!(cues.missing, 1);
        assert_eq!(cues.depth[5], 1.0);
        assert!(matches!(
            layer_frame(&rgb, &[f32::NAN; 16], cam, &allow, &NoProgress),
            Err(LayeringError::NoValidDepth)
        ));
    }
}
