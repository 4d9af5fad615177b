//! The layer-set manifest (`manifest.json`), format `cpsl-layerset` versions 1 and 2.
//!
//! ```json
//! {
//!   "format": "cpsl-layerset",
//!   "version": 1,
//!   "camera": { "width": 640, "height": 480, "fx": 554.3, "fy": 554.3, "cx": 319.5, "cy": 239.5 },
//!   "layers": [
//!     { "file": "layer_00.png", "depth": 2.0, "meta": { "role": "region" } },
//!     { "file": "layer_01.png", "depth": 8.0, "meta": { "role": "background" } }
//!   ]
//! }
//! ```
//! Version 2 adds each layer's `geometry` when it is not the fronto-parallel plane, e.g.
//! `"geometry": { "slanted": [0.0, 0.12, 0.2] }` (the plane `m` of [`crate::Geometry`]) or a
//! mesh's grid inline (`"geometry": { "mesh": { "step": 8, "cols": .., "rows": ..,
//! "inverse_depth": [..] } }`). Version 3 adds `"grid": "layer_00.grid"`: a mesh layer's grid
//! in a binary side file next to the manifest (`cpsl_io::grid`), the layer then without a
//! `geometry` field. Writers use the oldest version that holds the layers (1 when every layer
//! is fronto-parallel, 3 when a layer has a mesh), so older readers still read what they can.
//! Layers are listed nearest first; each file is an RGBA PNG (straight alpha, 8 bits) of the
//! camera's size next to the manifest. Unknown fields are rejected so that typos are caught.

use crate::camera::Camera;
use crate::geometry::Geometry;
use crate::layer::LayerMeta;
use serde::{Deserialize, Serialize};
use thiserror::Error;

/// Format name written in every manifest.
pub const FORMAT_NAME: &str = "cpsl-layerset";
/// Newest manifest version this build reads and writes.
pub const FORMAT_VERSION: u32 = 3;

/// Camera as written in a manifest (same fields as [`Camera`]).
pub type CameraSpec = Camera;

/// One layer entry of a manifest.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct LayerEntry {
    /// File name of the layer image, relative to the manifest (no directories).
    pub file: String,
    /// Reference depth `z_k`.
    pub depth: f64,
    /// The layer's surface (version 2; absent for the fronto-parallel plane).
    #[serde(default, skip_serializing_if = "Geometry::is_plane")]
    pub geometry: Geometry,
    /// The side file holding the layer's mesh grid (version 3), a plain file name next to the
    /// manifest; `geometry` is then absent.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub grid: Option<String>,
    /// Optional metadata.
    #[serde(default, skip_serializing_if = "is_default_meta")]
    pub meta: LayerMeta,
}

fn is_default_meta(m: &LayerMeta) -> bool {
    *m == LayerMeta::default()
}

/// The parsed manifest.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct Manifest {
    /// Always [`FORMAT_NAME`].
    pub format: String,
    /// Format version, at most [`FORMAT_VERSION`].
    pub version: u32,
    /// Reference camera.
    pub camera: CameraSpec,
    /// Layers, nearest first.
    pub layers: Vec<LayerEntry>,
}

/// Why the head of a versioned JSON document (its `format` and `version` fields) was rejected.
#[derive(Debug, Clone, PartialEq, Eq)]
pub enum HeadError {
    /// Not JSON, or the field is missing.
    Json(String),
    /// Another format.
    Format(String),
    /// A version this build does not read.
    Version(u32),
}

/// Checks the `format` and `version` fields of a versioned JSON document before anything else,
/// so that a file of a newer version gets a version error rather than an unknown-field error;
/// versions `1..=max_version` are read.
pub fn check_head(bytes: &[u8], format: &str, max_version: u32) -> Result<(), HeadError> {
    #[derive(Deserialize)]
    struct Head {
        format: Option<String>,
        version: Option<u32>,
    }
    let head: Head = serde_json::from_slice(bytes).map_err(|e| HeadError::Json(e.to_string()))?;
    match head.format.as_deref() {
        Some(f) if f == format => {}
        Some(other) => return Err(HeadError::Format(other.into())),
        None => return Err(HeadError::Json("missing field `format`".into())),
    }
    match head.version {
        Some(v) if (1..=max_version).contains(&v) => Ok(()),
        Some(v) => Err(HeadError::Version(v)),
        None => Err(HeadError::Json("missing field `version`".into())),
    }
}

impl From<HeadError> for ManifestError {
    fn from(e: HeadError) -> Self {
        match e {
            HeadError::Json(m) => Self::Json(m),
            HeadError::Format(f) => Self::Format(f),
            HeadError::Version(v) => Self::Version(v),
        }
    }
}

/// Why a manifest was rejected.
#[derive(Debug, Error, Clone, PartialEq)]
pub enum ManifestError {
    /// Not valid JSON or not the expected shape.
    #[error("invalid JSON: {0}")]
    Json(String),
    /// The `format` field is not `cpsl-layerset`.
    #[error("field `format`: expected \"{FORMAT_NAME}\", found \"{0}\"")]
    Format(String),
    /// The version is newer than this build understands (or zero).
    #[error("field `version`: this build reads versions 1..={FORMAT_VERSION}, found {0}")]
    Version(u32),
    /// A field that the manifest's version does not have.
    #[error(
        "field `layers[{index}].{field}` needs version {needs}, the manifest is version {version}"
    )]
    NewerField {
        /// Layer index.
        index: usize,
        /// The field.
        field: &'static str,
        /// The version that introduced it.
        needs: u32,
        /// The manifest's version.
        version: u32,
    },
    /// A layer has both a `geometry` and a `grid` file.
    #[error("field `layers[{0}].grid`: a layer with a grid file has no `geometry` field")]
    GridAndGeometry(usize),
    /// A layer file name is unsafe or duplicated.
    #[error("field `layers[{index}].file`: {reason}, found \"{file}\"")]
    FileName {
        /// Layer index.
        index: usize,
        /// The file name.
        file: Box<str>,
        /// What is wrong with it.
        reason: &'static str,
    },
    /// A grid file name is unsafe or duplicated.
    #[error("field `layers[{index}].grid`: {reason}, found \"{file}\"")]
    GridName {
        /// Layer index.
        index: usize,
        /// The file name.
        file: Box<str>,
        /// What is wrong with it.
        reason: &'static str,
    },
}

impl Manifest {
    /// Parses and checks a manifest: shape, format name, version and file names. Camera,
    /// depths and sizes are checked when the layer set is built.
    pub fn parse(bytes: &[u8]) -> Result<Self, ManifestError> {
        check_head(bytes, FORMAT_NAME, FORMAT_VERSION)?;
        let m: Manifest =
            serde_json::from_slice(bytes).map_err(|e| ManifestError::Json(e.to_string()))?;
        let mut seen = std::collections::HashSet::new();
        for (index, l) in m.layers.iter().enumerate() {
            let newer = |field, needs| ManifestError::NewerField {
                index,
                field,
                needs,
                version: m.version,
            };
            if m.version < 2 && !l.geometry.is_plane() {
                return Err(newer("geometry", 2));
            }
            if m.version < 3 && l.grid.is_some() {
                return Err(newer("grid", 3));
            }
            if l.grid.is_some() && !l.geometry.is_plane() {
                return Err(ManifestError::GridAndGeometry(index));
            }
            let grid = l.grid.iter().map(|g| (true, g));
            for (is_grid, file) in std::iter::once((false, &l.file)).chain(grid) {
                let reason = unsafe_file_name(file).or_else(|| {
                    (!seen.insert(file.as_str())).then_some("file name used twice in the manifest")
                });
                if let Some(reason) = reason {
                    let file = file.as_str().into();
                    return Err(match is_grid {
                        false => ManifestError::FileName {
                            index,
                            file,
                            reason,
                        },
                        true => ManifestError::GridName {
                            index,
                            file,
                            reason,
                        },
                    });
                }
            }
        }
        Ok(m)
    }

    /// The oldest version that holds every layer's fields.
    pub fn needed_version(layers: &[LayerEntry]) -> u32 {
        if layers.iter().any(|l| l.grid.is_some()) {
            3
        } else if layers.iter().all(|l| l.geometry.is_plane()) {
            1
        } else {
            2
        }
    }

    /// Serialises as pretty JSON.
    pub fn to_json(&self) -> String {
        serde_json::to_string_pretty(self).expect("manifest serialises")
    }
}

/// Why a file name is unsafe to join to the layer-set directory, if it is.
pub fn unsafe_file_name(name: &str) -> Option<&'static str> {
    if name.is_empty() {
        Some("must not be empty")
    } else if name.contains('/') || name.contains('\\') {
        Some("must be a plain file name without directories")
    } else if name == "." || name == ".." || name.starts_with('.') {
        Some("must not start with '.'")
    } else if name.len() > 255 || name.chars().any(|c| c.is_control()) {
        Some("must be at most 255 printable characters")
    } else {
        None
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn doc(version: u32, file: &str) -> String {
        format!(
            r#"{{"format":"cpsl-layerset","version":{version},
            "camera":{{"width":4,"height":3,"fx":2,"fy":2,"cx":1.5,"cy":1}},
            "layers":[{{"file":"{file}","depth":1.5}}]}}"#
        )
    }

    #[test]
    fn parses_and_round_trips() {
        let m = Manifest::parse(doc(1, "a.png").as_bytes()).unwrap();
        assert_eq!(Manifest::parse(m.to_json().as_bytes()).unwrap(), m);
    }

    proptest::proptest! {
        /// Arbitrary bytes and single-byte corruptions of a valid manifest never panic.
        #[test]
        fn never_panics(bytes in proptest::collection::vec(proptest::prelude::any::<u8>(), 0..512),
                        pos in 0usize..400, val in proptest::prelude::any::<u8>()) {
            let _ = Manifest::parse(&bytes);
            let mut doc = doc(1, "a.png").into_bytes();
            let i = pos % doc.len();
            doc[i] = val;
            let _ = Manifest::parse(&doc);
        }
    }

    #[test]
    fn geometry_needs_version_2() {
        let slanted = |v: u32| {
            doc(v, "a.png").replace(
                "\"depth\":1.5",
                "\"depth\":1.5,\"geometry\":{\"slanted\":[0.0,0.1,0.6]}",
            )
        };
        let m = Manifest::parse(slanted(2).as_bytes()).unwrap();
        assert_eq!(
            m.layers[0].geometry,
            Geometry::Slanted(crate::Vec3::new(0.0, 0.1, 0.6))
        );
        assert_eq!(Manifest::needed_version(&m.layers), 2);
        assert_eq!(Manifest::parse(m.to_json().as_bytes()).unwrap(), m);
        assert!(matches!(
            Manifest::parse(slanted(1).as_bytes()),
            Err(ManifestError::NewerField { index: 0, .. })
        ));
        let plane = Manifest::parse(doc(2, "a.png").as_bytes()).unwrap();
        assert_eq!(Manifest::needed_version(&plane.layers), 1);
        assert!(!plane.to_json().contains("geometry"));
    }

    #[test]
    fn grid_files_need_version_3_and_safe_names() {
        let grid = |v: u32, grid: &str| {
            doc(v, "a.png").replace(
                "\"depth\":1.5",
                &format!("\"depth\":1.5,\"grid\":\"{grid}\""),
            )
        };
        let m = Manifest::parse(grid(3, "a.grid").as_bytes()).unwrap();
        assert_eq!(m.layers[0].grid.as_deref(), Some("a.grid"));
        assert_eq!(Manifest::needed_version(&m.layers), 3);
        assert_eq!(Manifest::parse(m.to_json().as_bytes()).unwrap(), m);
        assert!(matches!(
            Manifest::parse(grid(2, "a.grid").as_bytes()),
            Err(ManifestError::NewerField {
                field: "grid",
                needs: 3,
                ..
            })
        ));
        for bad in ["../a.grid", "a.png", ".a"] {
            assert!(
                matches!(
                    Manifest::parse(grid(3, bad).as_bytes()),
                    Err(ManifestError::GridName { .. })
                ),
                "{bad}"
            );
        }
        let both = grid(3, "a.grid").replace(
            "\"depth\":1.5",
            "\"depth\":1.5,\"geometry\":{\"slanted\":[0.0,0.1,0.6]}",
        );
        let e = Manifest::parse(both.as_bytes()).unwrap_err().to_string();
        assert!(e.contains("layers[0].grid"), "{e}");
    }

    #[test]
    fn rejects_bad_headers_and_names() {
        assert_eq!(
            Manifest::parse(doc(4, "a.png").as_bytes()),
            Err(ManifestError::Version(4))
        );
        assert_eq!(
            Manifest::parse(doc(0, "a.png").as_bytes()),
            Err(ManifestError::Version(0))
        );
        assert!(matches!(
            Manifest::parse(doc(1, "../x.png").as_bytes()),
            Err(ManifestError::FileName { index: 0, .. })
        ));
        let other = doc(1, "a.png").replace("cpsl-layerset", "mpi");
        assert!(matches!(
            Manifest::parse(other.as_bytes()),
            Err(ManifestError::Format(_))
        ));
        let typo = doc(1, "a.png").replace("\"depth\"", "\"dpeth\"");
        let e = Manifest::parse(typo.as_bytes()).unwrap_err().to_string();
        assert!(e.contains("dpeth"), "{e}");
        assert!(Manifest::parse(b"{not json").is_err());
    }
}
