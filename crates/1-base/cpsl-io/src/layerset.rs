//! The layer-set folder: `manifest.json` plus one straight-alpha RGBA PNG per layer
//! (see [`cpsl_core::manifest`] for the schema) and one grid file per mesh layer
//! ([`crate::grid`]), plus optional side files written by later stages (configs, edge-depth
//! caches).
//!
//! Reading validates everything before returning and names the file and field of the first
//! problem. Writing is atomic: files go to a temporary sibling directory that is renamed into
//! place, so an interrupted write never leaves a half-written layer set.

use crate::atomic::Staged;
use crate::error::IoError;
use crate::{grid, images};
use cpsl_core::{
    Edc, Geometry, Layer, LayerEntry, LayerSet, Limits, Manifest, PremulImage, FORMAT_NAME,
};
use rayon::prelude::*;
use std::path::Path;

/// Name of the manifest inside a layer-set folder.
pub const MANIFEST_FILE: &str = "manifest.json";

/// Name of the Edge-Depth Cache side file inside a layer-set folder.
pub const EDC_FILE: &str = "edc.bin";

/// Reads the Edge-Depth Cache of a layer set, if the folder has one, and checks that it fits
/// `set` (same size and layer count).
pub fn read_edc(dir: &Path, set: &LayerSet, limits: &Limits) -> Result<Option<Edc>, IoError> {
    let path = dir.join(EDC_FILE);
    if !path.exists() {
        return Ok(None);
    }
    let bytes = read_limited(&path, limits)?;
    let edc = Edc::decode(&bytes).map_err(|e| IoError::Edc {
        path: path.clone(),
        cause: e.to_string(),
    })?;
    let cam = set.camera();
    if (edc.width, edc.height, edc.layers as usize) != (cam.width, cam.height, set.len()) {
        return Err(IoError::Edc {
            path,
            cause: format!(
                "cache is for {}x{} with {} layers, the layer set is {}x{} with {}",
                edc.width,
                edc.height,
                edc.layers,
                cam.width,
                cam.height,
                set.len()
            ),
        });
    }
    Ok(Some(edc))
}

/// Reads a file of at most `limits.max_file_bytes`.
pub(crate) fn read_limited(path: &Path, limits: &Limits) -> Result<Vec<u8>, IoError> {
    let meta = std::fs::metadata(path).map_err(|e| IoError::io(path, e))?;
    if meta.len() > limits.max_file_bytes {
        return Err(IoError::FileTooLarge {
            path: path.to_path_buf(),
            size: meta.len(),
            max: limits.max_file_bytes,
        });
    }
    std::fs::read(path).map_err(|e| IoError::io(path, e))
}

/// Reads and validates a layer-set folder.
pub fn read_layer_set(dir: &Path, limits: &Limits) -> Result<LayerSet, IoError> {
    let mpath = dir.join(MANIFEST_FILE);
    let meta = std::fs::metadata(&mpath).map_err(|e| IoError::io(&mpath, e))?;
    if meta.len() > limits.max_manifest_bytes {
        return Err(IoError::FileTooLarge {
            path: mpath,
            size: meta.len(),
            max: limits.max_manifest_bytes,
        });
    }
    let bytes = std::fs::read(&mpath).map_err(|e| IoError::io(&mpath, e))?;
    let manifest = Manifest::parse(&bytes).map_err(|cause| IoError::Manifest {
        path: mpath.clone(),
        cause,
    })?;
    let cam = manifest.camera;
    let invalid = |cause| IoError::Invalid {
        path: mpath.clone(),
        cause,
    };
    // Camera, limits, layer count and depths are checked before any image is decoded.
    cam.validate().map_err(invalid)?;
    limits
        .check_size("camera", cam.width, cam.height)
        .map_err(invalid)?;
    let placeholder: Vec<Layer> = manifest
        .layers
        .iter()
        .map(|e| Layer {
            image: PremulImage::new(1, 1),
            depth: e.depth,
            // A mesh is checked against the real camera below.
            geometry: match &e.geometry {
                Geometry::Mesh(_) => Geometry::Plane,
                g => g.clone(),
            },
            meta: e.meta.clone(),
        })
        .collect();
    let tiny = cpsl_core::Camera {
        width: 1,
        height: 1,
        ..cam
    };
    LayerSet::new(tiny, placeholder, limits).map_err(invalid)?;

    // The layers are decoded in parallel (most of the time a layer set takes to read); the
    // first failing layer in manifest order is reported.
    let read = |entry: &LayerEntry| -> Result<Layer, IoError> {
        let geometry = match &entry.grid {
            None => entry.geometry.clone(),
            Some(file) => {
                let path = dir.join(file);
                let bytes = read_limited(&path, limits)?;
                let grid = grid::decode_grid(&bytes, cam.width, cam.height)
                    .map_err(|cause| IoError::Grid { path, cause })?;
                Geometry::Mesh(std::sync::Arc::new(grid))
            }
        };
        let path = dir.join(&entry.file);
        let (w, h) = images::dimensions(&path, limits)?;
        if (w, h) != (cam.width, cam.height) {
            return Err(IoError::ImageSize {
                path,
                width: w,
                height: h,
                expected_width: cam.width,
                expected_height: cam.height,
            });
        }
        let rgba = images::read_rgba8(&path, limits)?;
        let image =
            PremulImage::from_straight(rgba.width, rgba.height, &rgba.data).map_err(|cause| {
                IoError::Invalid {
                    path: path.clone(),
                    cause,
                }
            })?;
        Ok(Layer {
            image,
            depth: entry.depth,
            geometry,
            meta: entry.meta.clone(),
        })
    };
    let read: Vec<Result<Layer, IoError>> = manifest.layers.par_iter().map(read).collect();
    let layers = read.into_iter().collect::<Result<Vec<_>, _>>()?;
    LayerSet::new(cam, layers, limits).map_err(invalid)
}

/// The manifest describing `set` with the standard file names `layer_NN.png`.
pub fn manifest_for(set: &LayerSet) -> Manifest {
    let layers: Vec<LayerEntry> = set
        .layers()
        .iter()
        .enumerate()
        .map(|(i, l)| {
            // A mesh's grid goes to a side file.
            let mesh = matches!(l.geometry, Geometry::Mesh(_));
            LayerEntry {
                file: format!("layer_{i:02}.png"),
                depth: l.depth,
                geometry: if mesh {
                    Geometry::Plane
                } else {
                    l.geometry.clone()
                },
                grid: mesh.then(|| format!("layer_{i:02}.grid")),
                meta: l.meta.clone(),
            }
        })
        .collect();
    Manifest {
        format: FORMAT_NAME.into(),
        version: Manifest::needed_version(&layers),
        camera: *set.camera(),
        layers,
    }
}

fn is_layer_set_dir(p: &Path) -> bool {
    p.is_dir()
        && (p.join(MANIFEST_FILE).is_file()
            || std::fs::read_dir(p)
                .map(|mut d| d.next().is_none())
                .unwrap_or(false))
}

/// Writes `set` (and `extras`, side files given as name and bytes) to the folder `dir`,
/// atomically. An existing layer set (or empty folder) at `dir` is replaced; anything else
/// there is left alone and reported as [`IoError::TargetExists`].
pub fn write_layer_set(
    dir: &Path,
    set: &LayerSet,
    extras: &[(&str, &[u8])],
) -> Result<(), IoError> {
    write_inner(dir, set, extras, None)
}

fn write_inner(
    dir: &Path,
    set: &LayerSet,
    extras: &[(&str, &[u8])],
    fail_after: Option<usize>,
) -> Result<(), IoError> {
    for (name, _) in extras {
        if let Some(reason) = cpsl_core::manifest::unsafe_file_name(name) {
            return Err(IoError::Image {
                path: dir.join(name),
                message: format!("side file name {reason}"),
            });
        }
    }
    let stage = Staged::folder(dir, is_layer_set_dir)?;
    let manifest = manifest_for(set);
    let (w, h) = (set.camera().width, set.camera().height);
    // The layers are compressed in parallel (most of the time a layer set takes to write),
    // then written in order.
    let pngs = manifest
        .layers
        .par_iter()
        .zip(set.layers().par_iter())
        .map(|(entry, layer)| {
            images::encode_png(w, h, 4, &layer.image.to_straight()).map_err(|message| {
                IoError::Image {
                    path: dir.join(&entry.file),
                    message,
                }
            })
        })
        .collect::<Result<Vec<_>, _>>()?;
    for (written, ((entry, png), layer)) in manifest
        .layers
        .iter()
        .zip(&pngs)
        .zip(set.layers())
        .enumerate()
    {
        if fail_after == Some(written) {
            return Err(IoError::io(
                stage.path(),
                std::io::Error::other("injected failure"),
            ));
        }
        stage.write_file(&entry.file, png)?;
        if let (Some(file), Geometry::Mesh(g)) = (&entry.grid, &layer.geometry) {
            stage.write_file(file, &grid::encode_grid(g))?;
        }
    }
    for (name, bytes) in extras {
        stage.write_file(name, bytes)?;
    }
    // The manifest goes last: a folder with a manifest is complete.
    stage.write_file(MANIFEST_FILE, manifest.to_json().as_bytes())?;
    stage.commit(is_layer_set_dir)
}

#[cfg(test)]
mod tests {
    use super::*;
    use cpsl_core::Camera;

    fn set() -> LayerSet {
        let cam = Camera::from_fov(5, 4, 60.0);
        let mut a = PremulImage::new(5, 4);
        a.set_pixel(1, 1, [100, 50, 25, 128]);
        let b = PremulImage::from_rgb(5, 4, &[7u8; 60]).unwrap();
        LayerSet::new(
            cam,
            vec![Layer::new(a, 1.0), Layer::new(b, 3.0)],
            &Limits::default(),
        )
        .unwrap()
    }

    #[test]
    fn roundtrip_is_exact() {
        let d = tempfile::tempdir().unwrap();
        let p = d.path().join("ls");
        write_layer_set(&p, &set(), &[("extra.bin", b"xyz")]).unwrap();
        assert_eq!(read_layer_set(&p, &Limits::default()).unwrap(), set());
        assert_eq!(std::fs::read(p.join("extra.bin")).unwrap(), b"xyz");
        // Rewriting over an existing layer set replaces it.
        write_layer_set(&p, &set(), &[]).unwrap();
        assert!(!p.join("extra.bin").exists());
    }

    #[test]
    fn edge_depth_cache_roundtrips_and_must_fit() {
        let d = tempfile::tempdir().unwrap();
        let p = d.path().join("ls");
        let edc = Edc {
            width: 5,
            height: 4,
            layers: 2,
            step: 0.01,
            samples: vec![cpsl_core::EdcSample {
                x: 1,
                y: 1,
                front: 0,
                back: 1,
                front_offset: 3,
                back_offset: -4,
            }],
        };
        write_layer_set(&p, &set(), &[]).unwrap();
        assert_eq!(read_edc(&p, &set(), &Limits::default()).unwrap(), None);
        write_layer_set(&p, &set(), &[(EDC_FILE, &edc.encode())]).unwrap();
        assert_eq!(
            read_edc(&p, &set(), &Limits::default()).unwrap(),
            Some(edc.clone())
        );
        let other = Edc { layers: 3, ..edc };
        write_layer_set(&p, &set(), &[(EDC_FILE, &other.encode())]).unwrap();
        let e = read_edc(&p, &set(), &Limits::default())
            .unwrap_err()
            .to_string();
        assert!(e.contains("3 layers") && e.contains("edc.bin"), "{e}");
    }

    #[test]
    fn interrupted_write_leaves_nothing() {
        let d = tempfile::tempdir().unwrap();
        let p = d.path().join("ls");
        assert!(write_inner(&p, &set(), &[], Some(1)).is_err());
        assert!(!p.exists());
        assert_eq!(
            std::fs::read_dir(d.path()).unwrap().count(),
            0,
            "temporary files left"
        );
        // An interrupted rewrite keeps the previous complete layer set.
        write_layer_set(&p, &set(), &[]).unwrap();
        assert!(write_inner(&p, &set(), &[], Some(1)).is_err());
        assert_eq!(read_layer_set(&p, &Limits::default()).unwrap(), set());
        assert_eq!(std::fs::read_dir(d.path()).unwrap().count(), 1);
    }

    #[test]
    fn refuses_to_replace_other_folders() {
        let d = tempfile::tempdir().unwrap();
        std::fs::write(d.path().join("precious.txt"), "x").unwrap();
        let e = write_layer_set(d.path(), &set(), &[]).unwrap_err();
        assert!(matches!(e, IoError::TargetExists { .. }));
        assert!(d.path().join("precious.txt").exists());
    }
}
