//! Monocular depth from ONNX models.
//!
//! A model is an `.onnx` file plus a description (JSON, by default `<model>.json` next to it):
//!
//! ```json
//! {
//!   "name": "Depth Anything V2 Small",
//!   "input": { "size": { "multiple_of": { "multiple": 14, "long_side": 518 } },
//!              "mean": [0.485, 0.456, 0.406], "std": [0.229, 0.224, 0.225] },
//!   "output": { "kind": "inverse_depth", "scale": 1.0, "shift": 0.0 }
//! }
//! ```
//!
//! The image is resized (bilinear) to the input size, scaled to `[0, 1]`, normalised with
//! `(v - mean) / std` per RGB channel and fed as one `1x3xHxW` float tensor. The first output
//! (`1x1xHxW`, `1xHxW` or `HxW`) is resized back to the image size and converted with
//! `v' = scale * v + shift`: depth `z = v'` for `metric_depth` and `relative_depth`, and
//! `z = 1 / v'` for `inverse_depth` (disparity). Non-positive or non-finite depths become NaN
//! (unknown).

use crate::error::ModelError;
use crate::runtime;
use cpsl_core::resample::{resize_bilinear, resize_bilinear_unit};
use ort::session::Session;
use ort::value::Tensor;
use serde::{Deserialize, Serialize};
use std::path::{Path, PathBuf};

/// How the network input is sized.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum InputSize {
    /// Always `[width, height]`.
    Fixed([u32; 2]),
    /// The long image side scaled to `long_side`, both sides rounded to a multiple of
    /// `multiple` (Depth Anything: 14 and 518).
    MultipleOf {
        /// Both sides are multiples of this.
        multiple: u32,
        /// Target length of the long side.
        long_side: u32,
    },
}

/// Input of a depth model.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct InputDesc {
    /// Sizing rule.
    pub size: InputSize,
    /// Per-channel mean (RGB, on the [0, 1] scale).
    #[serde(default)]
    pub mean: [f32; 3],
    /// Per-channel standard deviation (RGB).
    #[serde(default = "ones")]
    pub std: [f32; 3],
}

fn ones() -> [f32; 3] {
    [1.0; 3]
}

/// What the model outputs.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum OutputKind {
    /// Depth in metres (after scale and shift).
    MetricDepth,
    /// Depth up to an unknown scale.
    RelativeDepth,
    /// Inverse depth / disparity, up to scale (Depth Anything, MiDaS).
    InverseDepth,
}

/// Output of a depth model.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct OutputDesc {
    /// Kind of output.
    pub kind: OutputKind,
    /// Multiplier applied to the raw output.
    #[serde(default = "one")]
    pub scale: f32,
    /// Offset added after scaling.
    #[serde(default)]
    pub shift: f32,
}

fn one() -> f32 {
    1.0
}

/// Description of a monocular depth model.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct DepthModelDesc {
    /// Human-readable name.
    #[serde(default)]
    pub name: String,
    /// Input.
    pub input: InputDesc,
    /// Output.
    pub output: OutputDesc,
}

/// Largest accepted network input side.
const MAX_INPUT_SIDE: u32 = 4096;

impl DepthModelDesc {
    /// Parses and validates a description.
    pub fn parse(bytes: &[u8], path: &Path) -> Result<Self, ModelError> {
        let bad = |reason: String| ModelError::Description {
            path: path.into(),
            reason,
        };
        let d: Self = serde_json::from_slice(bytes).map_err(|e| bad(e.to_string()))?;
        match d.input.size {
            InputSize::Fixed([w, h]) if w == 0 || h == 0 || w > MAX_INPUT_SIDE || h > MAX_INPUT_SIDE => {
                return Err(bad(format!("input.size.fixed must be in 1..={MAX_INPUT_SIDE}, found {w}x{h}")))
            }
            InputSize::MultipleOf { multiple, long_side }
                if multiple == 0 || long_side < multiple || long_side > MAX_INPUT_SIDE =>
            {
                return Err(bad(format!(
                    "input.size.multiple_of needs 0 < multiple <= long_side <= {MAX_INPUT_SIDE}, found {multiple} and {long_side}"
                )))
            }
            _ => {}
        }
        if d.input.std.iter().any(|s| !(s.is_finite() && *s != 0.0))
            || d.input.mean.iter().any(|m| !m.is_finite())
        {
            return Err(bad(
                "input.mean must be finite and input.std finite and non-zero".into(),
            ));
        }
        if !(d.output.scale.is_finite() && d.output.scale != 0.0 && d.output.shift.is_finite()) {
            return Err(bad(
                "output.scale must be finite and non-zero, output.shift finite".into(),
            ));
        }
        Ok(d)
    }

    /// Reads a description file.
    pub fn load(path: &Path) -> Result<Self, ModelError> {
        let bytes = std::fs::read(path).map_err(|cause| ModelError::Io {
            path: path.into(),
            cause,
        })?;
        Self::parse(&bytes, path)
    }

    /// Network input size `(width, height)` for an image of `w x h`.
    pub fn input_size(&self, w: u32, h: u32) -> (u32, u32) {
        match self.input.size {
            InputSize::Fixed([iw, ih]) => (iw, ih),
            InputSize::MultipleOf {
                multiple,
                long_side,
            } => {
                let s = long_side as f64 / w.max(h).max(1) as f64;
                let r = |v: u32| {
                    let m = multiple as f64;
                    (((v as f64 * s) / m).round().max(1.0) * m) as u32
                };
                (r(w), r(h))
            }
        }
    }
}

/// A depth map estimated for an image, at the image's size.
#[derive(Debug, Clone, PartialEq)]
pub struct DepthEstimate {
    /// Width in pixels.
    pub width: u32,
    /// Height in pixels.
    pub height: u32,
    /// z-depth per pixel (model units; NaN where unknown).
    pub depth: Vec<f32>,
}

/// A monocular depth model running in ONNX Runtime.
pub struct OnnxDepth {
    session: Session,
    desc: DepthModelDesc,
    path: PathBuf,
}

impl std::fmt::Debug for OnnxDepth {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        write!(f, "OnnxDepth({})", self.path.display())
    }
}

/// The description path used when none is given: `<model>.json`.
pub fn sidecar_path(model: &Path) -> PathBuf {
    model.with_extension("json")
}

impl OnnxDepth {
    /// Loads `model` with its description (`desc`, or `<model>.json` when `None`).
    pub fn open(model: &Path, desc: Option<DepthModelDesc>) -> Result<Self, ModelError> {
        if !model.is_file() {
            return Err(ModelError::Io {
                path: model.into(),
                cause: std::io::Error::new(std::io::ErrorKind::NotFound, "model file not found"),
            });
        }
        let desc = match desc {
            Some(d) => d,
            None => DepthModelDesc::load(&sidecar_path(model))?,
        };
        let session = runtime::session(model)?;
        if session.inputs().len() != 1 || session.outputs().is_empty() {
            return Err(ModelError::Interface {
                path: model.into(),
                reason: format!(
                    "a depth model needs exactly one input and at least one output, found {} and {}",
                    session.inputs().len(),
                    session.outputs().len()
                ),
            });
        }
        Ok(Self {
            session,
            desc,
            path: model.into(),
        })
    }

    /// The model's description.
    pub fn desc(&self) -> &DepthModelDesc {
        &self.desc
    }

    /// Estimates depth for an RGB image (`rgb`: 3 bytes per pixel, row-major).
    pub fn estimate(
        &mut self,
        rgb: &[u8],
        width: u32,
        height: u32,
    ) -> Result<DepthEstimate, ModelError> {
        let n = width as usize * height as usize;
        if n == 0 || rgb.len() != n * 3 {
            return Err(ModelError::Input(format!(
                "{} bytes for a {width}x{height} RGB image ({} expected)",
                rgb.len(),
                n * 3
            )));
        }
        let (iw, ih) = self.desc.input_size(width, height);
        let resized = resize_bilinear_unit(
            rgb,
            width as usize,
            height as usize,
            3,
            iw as usize,
            ih as usize,
        );
        let plane = iw as usize * ih as usize;
        let mut nchw = vec![0f32; plane * 3];
        let (mean, std) = (self.desc.input.mean, self.desc.input.std);
        for (i, px) in resized.chunks_exact(3).enumerate() {
            for c in 0..3 {
                nchw[c * plane + i] = (px[c] - mean[c]) / std[c];
            }
        }
        let input = Tensor::from_array((
            [1usize, 3, ih as usize, iw as usize],
            nchw.into_boxed_slice(),
        ))
        .map_err(|e| ModelError::Inference(e.to_string()))?;
        let outputs = self
            .session
            .run(ort::inputs![input])
            .map_err(|e| ModelError::Inference(e.to_string()))?;
        let (shape, data) =
            outputs[0]
                .try_extract_tensor::<f32>()
                .map_err(|e| ModelError::Interface {
                    path: self.path.clone(),
                    reason: format!("output 0 is not a float tensor: {e}"),
                })?;
        let dims: Vec<i64> = shape.iter().copied().collect();
        let (oh, ow) = match dims.as_slice() {
            [.., h, w] if dims[..dims.len() - 2].iter().all(|&d| d == 1) && *h > 0 && *w > 0 => {
                (*h as usize, *w as usize)
            }
            _ => {
                return Err(ModelError::Interface {
                    path: self.path.clone(),
                    reason: format!(
                        "expected a 1x1xHxW, 1xHxW or HxW output, found shape {dims:?}"
                    ),
                })
            }
        };
        let raw = resize_bilinear(data, ow, oh, 1, width as usize, height as usize);
        let (scale, shift, kind) = (
            self.desc.output.scale,
            self.desc.output.shift,
            self.desc.output.kind,
        );
        let depth = raw
            .iter()
            .map(|&v| {
                let v = scale * v + shift;
                let z = match kind {
                    OutputKind::InverseDepth => 1.0 / v,
                    OutputKind::MetricDepth | OutputKind::RelativeDepth => v,
                };
                if z.is_finite() && z > 0.0 {
                    z
                } else {
                    f32::NAN
                }
            })
            .collect();
        Ok(DepthEstimate {
            width,
            height,
            depth,
        })
    }
}

impl cpsl_core::DepthSource for OnnxDepth {
    fn name(&self) -> String {
        format!("model {}", self.path.display())
    }

    fn depth(
        &mut self,
        rgb: &[u8],
        width: u32,
        height: u32,
    ) -> Result<Vec<f32>, cpsl_core::DepthSourceError> {
        self.estimate(rgb, width, height)
            .map(|e| e.depth)
            .map_err(|e| cpsl_core::DepthSourceError {
                source_name: self.name(),
                cause: Box::new(e),
            })
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn desc(json: &str) -> Result<DepthModelDesc, ModelError> {
        DepthModelDesc::parse(json.as_bytes(), Path::new("m.json"))
    }

    #[test]
    fn fastdepth_and_depth_anything_are_describable() {
        let fd = DepthModelDesc::load(
            &PathBuf::from(env!("CARGO_MANIFEST_DIR")).join("../../../models/fastdepth.json"),
        )
        .unwrap();
        assert_eq!(fd.input_size(640, 480), (224, 224));
        assert_eq!(fd.output.kind, OutputKind::MetricDepth);
        let da = desc(
            r#"{"name":"Depth Anything V2 Small","input":{"size":{"multiple_of":{"multiple":14,"long_side":518}},
                "mean":[0.485,0.456,0.406],"std":[0.229,0.224,0.225]},"output":{"kind":"inverse_depth"}}"#,
        )
        .unwrap();
        // 1920x1080 -> long side 518, short side 291.4 -> 294 (multiple of 14).
        assert_eq!(da.input_size(1920, 1080), (518, 294));
        assert_eq!(da.output.scale, 1.0);
    }

    #[test]
    fn rejects_bad_descriptions() {
        for (json, frag) in [
            (
                r#"{"input":{"size":{"fixed":[0,10]}},"output":{"kind":"metric_depth"}}"#,
                "fixed",
            ),
            (
                r#"{"input":{"size":{"multiple_of":{"multiple":0,"long_side":5}}},"output":{"kind":"metric_depth"}}"#,
                "multiple_of",
            ),
            (
                r#"{"input":{"size":{"fixed":[4,4]},"std":[1,0,1]},"output":{"kind":"metric_depth"}}"#,
                "std",
            ),
            (
                r#"{"input":{"size":{"fixed":[4,4]}},"output":{"kind":"metric_depth","scale":0}}"#,
                "scale",
            ),
            (
                r#"{"input":{"size":{"fixed":[4,4]}},"output":{"kind":"disparity"}}"#,
                "disparity",
            ),
            (
                r#"{"input":{"size":{"fixed":[4,4]}},"output":{"kind":"metric_depth"},"extra":1}"#,
                "extra",
            ),
        ] {
            let e = desc(json).unwrap_err().to_string();
            assert!(e.contains(frag) && e.contains("m.json"), "{e}");
        }
    }

    #[test]
    fn resize_is_identity_at_same_size_and_keeps_ramps() {
        let src: Vec<f32> = (0..12).map(|v| v as f32).collect();
        assert_eq!(resize_bilinear(&src, 4, 3, 1, 4, 3), src);
        let up = resize_bilinear(&[0.0, 1.0], 2, 1, 1, 4, 1);
        assert_eq!(up, vec![0.0, 0.25, 0.75, 1.0]);
    }
}
