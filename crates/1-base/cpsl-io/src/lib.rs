//! CPSL files on disk.
//!
//! * [`layerset`]: the layer-set folder (`manifest.json` + one RGBA PNG per layer + optional
//!   side files), read with full validation under [`cpsl_core::Limits`] and written atomically.
//! * [`grid`]: a mesh layer's depth grid as a side file of its layer set.
//! * [`images`]: PNG/JPEG reading with size limits checked before decoding, PNG writing.
//! * [`pfm`]: Portable Float Map files.
//! * [`depth`]: depth maps from PFM, 16-bit PNG or NumPy `.npy`.
//! * [`video`]: the index of a layered video folder (`video.json`), as players read it.

pub mod atomic;
pub mod depth;
pub mod error;
pub mod grid;
pub mod images;
pub mod layerset;
pub mod pfm;
pub mod video;

pub use atomic::{write_file_atomic, write_json, Staged};
pub use error::IoError;
pub use layerset::{read_edc, read_layer_set, write_layer_set, EDC_FILE, MANIFEST_FILE};
