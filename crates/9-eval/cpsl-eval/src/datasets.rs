//! The real multi-view datasets in `../shared/data`, each loaded as a reference view with
//! ground-truth z-depth and target views with their poses and cameras, in the conventions of
//! `cpsl-core` (`X_ref = R X_view + t`, integer pixel centres). Geometry follows the data's
//! README (checked there by warping one view onto another):
//!
//! * **HCI 4D light field** (`hci/backgammon`): 9x9 parallel cameras 512x512,
//!   `f = focal_mm / sensor_mm * 512`, baseline `b`, focus distance `F`; view (row, col) is
//!   translated by `((col-4) b, (row-4) b, 0)` with its principal point shifted by
//!   `f b (col-4) / F` (and rows likewise), so the focus plane has zero disparity; depth
//!   `Z = 1 / (d / (f b) + 1 / F)` from the centre view's disparity `d`. Targets: the 80
//!   non-centre views.
//! * **Middlebury 2005** (`middlebury2005/{Art,Books,Dolls}`, third size): view5 is 160 mm to
//!   the right of view1, `f = 3740 / 3` px, depth `Z = 3740 * 0.16 / (value + dmin)` m from
//!   `disp1.png` (0 = unknown); the observed shift is `value / 3` px, so view5's principal
//!   point sits `dmin / 3` px to the right.
//! * **Middlebury 2003** (`middlebury2003/{Teddy,Cones}`, quarter size): im6 is to the right
//!   of im2, disparity `value / 4` px, no calibration: a camera with `f = 450` px and a
//!   0.1-unit baseline reproduces the disparities (`Z = 450 * 0.1 * 4 / value`).

use cpsl_core::{Camera, Limits, Mat3, Pose, Vec3};
use cpsl_io::IoError;
use std::path::{Path, PathBuf};
use thiserror::Error;

/// Why a dataset could not be loaded.
#[derive(Debug, Error)]
pub enum DatasetError {
    /// A file could not be read or decoded.
    #[error(transparent)]
    Io(#[from] IoError),
    /// A file has unexpected content.
    #[error("{path}: {reason}")]
    Format {
        /// File.
        path: PathBuf,
        /// What is wrong.
        reason: String,
    },
    /// The name is not a known dataset.
    #[error("unknown dataset '{0}': expected one of {names}", names = NAMES.join(", "))]
    Unknown(String),
}

/// Names of the datasets this module loads.
pub const NAMES: [&str; 7] = [
    "hci/backgammon",
    "middlebury2005/Art",
    "middlebury2005/Books",
    "middlebury2005/Dolls",
    "middlebury2003/Teddy",
    "middlebury2003/Cones",
    "middlebury-mview/templeSparseRing",
];

/// A real view to reproduce.
#[derive(Debug, Clone)]
pub struct Target {
    /// View name (file stem).
    pub name: String,
    /// Viewer pose relative to the reference camera.
    pub pose: Pose,
    /// The target view's camera (may differ from the reference in its principal point).
    pub camera: Camera,
    /// Ground-truth RGB.
    pub rgb: Vec<u8>,
}

/// A reference view with ground-truth depth and target views.
#[derive(Debug, Clone)]
pub struct Dataset {
    /// Dataset name (one of [`NAMES`]).
    pub name: String,
    /// Reference camera.
    pub camera: Camera,
    /// Reference RGB.
    pub rgb: Vec<u8>,
    /// Ground-truth z-depth of the reference view (NaN where unknown; all NaN when the
    /// dataset has none).
    pub depth: Vec<f32>,
    /// Depth of the scene's centre in the reference camera when the poses determine it but
    /// no depth map exists (the temple ring: where the cameras' optical axes meet). Used to
    /// give scale-free depth estimates a metric scale.
    pub centre_depth: Option<f32>,
    /// Views to reproduce.
    pub targets: Vec<Target>,
}

fn rgb(path: &Path) -> Result<(u32, u32, Vec<u8>), DatasetError> {
    let img = cpsl_io::images::read_rgb8(path, &Limits::default())?;
    Ok((img.width, img.height, img.data))
}

/// 8-bit greyscale values of a disparity PNG.
fn grey(path: &Path) -> Result<(u32, u32, Vec<u8>), DatasetError> {
    let (w, h, data) = rgb(path)?;
    Ok((w, h, data.chunks_exact(3).map(|p| p[0]).collect()))
}

fn format(path: &Path, reason: impl Into<String>) -> DatasetError {
    DatasetError::Format {
        path: path.into(),
        reason: reason.into(),
    }
}

/// Loads dataset `name` from the data root (the folder holding the datasets' folders).
pub fn load(root: &Path, name: &str) -> Result<Dataset, DatasetError> {
    match name.split_once('/') {
        Some(("hci", scene)) if name == "hci/backgammon" => hci(root, scene, name),
        Some(("middlebury2005", scene)) if NAMES.contains(&name) => {
            middlebury2005(root, scene, name)
        }
        Some(("middlebury2003", scene)) if NAMES.contains(&name) => {
            middlebury2003(root, scene, name)
        }
        Some(("middlebury-mview", scene)) if NAMES.contains(&name) => temple(root, scene, name),
        _ => Err(DatasetError::Unknown(name.into())),
    }
}

fn hci(root: &Path, scene: &str, name: &str) -> Result<Dataset, DatasetError> {
    let dir = root.join("hci_lightfield_4d").join(scene);
    let cfg_path = dir.join("parameters.cfg");
    let cfg = std::fs::read_to_string(&cfg_path).map_err(|e| IoError::io(&cfg_path, e))?;
    let get = |key: &str| -> Result<f64, DatasetError> {
        cfg.lines()
            .filter_map(|l| l.split_once('='))
            .find(|(k, _)| k.trim() == key)
            .and_then(|(_, v)| v.trim().parse::<f64>().ok())
            .ok_or_else(|| format(&cfg_path, format!("missing or bad '{key}'")))
    };
    let (w, h, rgb_ref) = rgb(&dir.join("input_Cam040.png"))?;
    let f = get("focal_length_mm")? / get("sensor_size_mm")? * w as f64;
    let b = get("baseline_mm")? / 1000.0;
    let focus = get("focus_distance_m")?;
    let disp_path = dir.join("gt_disp_lowres.pfm");
    let disp = cpsl_io::pfm::read_pfm(&disp_path, &Limits::default())?;
    if (disp.width, disp.height) != (w, h) {
        return Err(format(
            &disp_path,
            format!("{}x{}, the views are {w}x{h}", disp.width, disp.height),
        ));
    }
    let depth = disp
        .data
        .iter()
        .map(|&d| {
            let z = 1.0 / (d as f64 / (f * b) + 1.0 / focus);
            if z.is_finite() && z > 0.0 {
                z as f32
            } else {
                f32::NAN
            }
        })
        .collect();
    let camera = Camera::centred(w, h, f);
    let mut targets = Vec::new();
    for row in 0..9i32 {
        for col in 0..9i32 {
            if (row, col) == (4, 4) {
                continue;
            }
            let file = format!("input_Cam{:03}.png", 9 * row + col);
            let (tw, th, data) = rgb(&dir.join(&file))?;
            if (tw, th) != (w, h) {
                return Err(format(
                    &dir.join(&file),
                    format!("{tw}x{th}, the centre view is {w}x{h}"),
                ));
            }
            let (dc, dr) = ((col - 4) as f64, (row - 4) as f64);
            targets.push(Target {
                name: file.trim_end_matches(".png").into(),
                pose: Pose::from_translation(Vec3::new(dc * b, dr * b, 0.0)),
                camera: Camera {
                    cx: camera.cx + f * b * dc / focus,
                    cy: camera.cy + f * b * dr / focus,
                    ..camera
                },
                rgb: data,
            });
        }
    }
    Ok(Dataset {
        name: name.into(),
        camera,
        rgb: rgb_ref,
        depth,
        centre_depth: None,
        targets,
    })
}

/// A rectified pair: reference and target to its right, disparity `value / scale` px.
#[allow(clippy::too_many_arguments)]
fn stereo_pair(
    name: &str,
    reference: &Path,
    target: &Path,
    disparity: &Path,
    f: f64,
    baseline: f64,
    disparity_scale: f64,
    offset: f64,
) -> Result<Dataset, DatasetError> {
    let (w, h, rgb_ref) = rgb(reference)?;
    let (tw, th, rgb_t) = rgb(target)?;
    let (dw, dh, disp) = grey(disparity)?;
    if (tw, th) != (w, h) || (dw, dh) != (w, h) {
        return Err(format(
            target,
            format!("views and disparity differ in size ({w}x{h}, {tw}x{th}, {dw}x{dh})"),
        ));
    }
    // Depth from the full disparity (value + offset) / scale px; the images are shifted by
    // offset / scale px, which the target's principal point carries.
    let depth = disp
        .iter()
        .map(|&v| {
            if v == 0 {
                f32::NAN
            } else {
                (f * baseline * disparity_scale / (v as f64 + offset)) as f32
            }
        })
        .collect();
    let camera = Camera::centred(w, h, f);
    let tname = target
        .file_stem()
        .unwrap_or_default()
        .to_string_lossy()
        .into_owned();
    Ok(Dataset {
        name: name.into(),
        camera,
        rgb: rgb_ref,
        depth,
        centre_depth: None,
        targets: vec![Target {
            name: tname,
            pose: Pose::from_translation(Vec3::new(baseline, 0.0, 0.0)),
            camera: Camera {
                cx: camera.cx + offset / disparity_scale,
                ..camera
            },
            rgb: rgb_t,
        }],
    })
}

fn middlebury2005(root: &Path, scene: &str, name: &str) -> Result<Dataset, DatasetError> {
    let dir = root
        .join("middlebury_2005_2003_stereo/2005_ThirdSize")
        .join(scene);
    let dmin_path = dir.join("dmin.txt");
    let dmin: f64 = std::fs::read_to_string(&dmin_path)
        .map_err(|e| IoError::io(&dmin_path, e))?
        .trim()
        .parse()
        .map_err(|e| format(&dmin_path, format!("not a number: {e}")))?;
    stereo_pair(
        name,
        &dir.join("view1.png"),
        &dir.join("view5.png"),
        &dir.join("disp1.png"),
        3740.0 / 3.0,
        0.16,
        3.0,
        dmin,
    )
}

fn middlebury2003(root: &Path, scene: &str, name: &str) -> Result<Dataset, DatasetError> {
    let dir = root
        .join("middlebury_2005_2003_stereo/2003_QuarterSize")
        .join(scene);
    stereo_pair(
        name,
        &dir.join("im2.png"),
        &dir.join("im6.png"),
        &dir.join("disp2.png"),
        450.0,
        0.1,
        4.0,
        0.0,
    )
}

/// Scales `estimate` so that its median matches the median of `truth` (monocular depth has no
/// absolute scale). Returns the scaled depth and the factor, or `None` when either has no
/// valid value.
pub fn align_median(estimate: &[f32], truth: &[f32]) -> Option<(Vec<f32>, f32)> {
    let s = median(truth)? / median(estimate)?;
    (s.is_finite() && s > 0.0).then(|| (estimate.iter().map(|z| z * s).collect(), s))
}

/// Median of the finite positive values.
pub use cpsl_core::median_depth as median;

/// A real handheld video with a camera pose per frame and no depth.
#[derive(Debug, Clone)]
pub struct PosedVideo {
    /// Frame files in time order.
    pub files: Vec<PathBuf>,
    /// The camera at full resolution, a pinhole once the frames are undistorted with
    /// [`PosedVideo::lens`].
    pub camera: Camera,
    /// The lens distortion of the frames as filmed.
    pub lens: Distortion,
    /// Per frame: the camera in world coordinates (`X_world = R X_camera + t`, x right, y down,
    /// z forward), in the poses' arbitrary unit.
    pub poses: Vec<Pose>,
    /// Per frame: z-depth of the point nearest to every optical axis (the filmed object, for a
    /// video that circles it), in the poses' unit. Gives scale-free depth a scale.
    pub centre_depth: Vec<f32>,
}

impl PosedVideo {
    /// Frame `to`'s camera relative to frame `from`'s: the pose at which `from`'s layers
    /// reproduce frame `to`.
    pub fn relative(&self, from: usize, to: usize) -> Pose {
        self.poses[from].relative_to(&self.poses[to])
    }
}

/// Lens distortion in the OpenCV / COLMAP `OPENCV` model: normalised image coordinates
/// `(x, y)` are filmed at `x (1 + k1 r^2 + k2 r^4) + 2 p1 x y + p2 (r^2 + 2 x^2)` and
/// `y (1 + k1 r^2 + k2 r^4) + p1 (r^2 + 2 y^2) + 2 p2 x y`, `r^2 = x^2 + y^2`.
#[derive(Debug, Clone, Copy, Default, PartialEq)]
pub struct Distortion {
    /// Radial coefficients.
    pub k1: f64,
    /// Radial coefficient of `r^4`.
    pub k2: f64,
    /// Tangential coefficients.
    pub p1: f64,
    /// Second tangential coefficient.
    pub p2: f64,
}

impl Distortion {
    /// Where the undistorted normalised point `(x, y)` was filmed.
    pub fn distort(&self, x: f64, y: f64) -> (f64, f64) {
        let r2 = x * x + y * y;
        let radial = 1.0 + self.k1 * r2 + self.k2 * r2 * r2;
        (
            x * radial + 2.0 * self.p1 * x * y + self.p2 * (r2 + 2.0 * x * x),
            y * radial + self.p1 * (r2 + 2.0 * y * y) + 2.0 * self.p2 * x * y,
        )
    }

    /// An RGB image (3 bytes per pixel) filmed through this lens by `camera` (at any
    /// resolution: the model works on normalised coordinates), resampled bilinearly to what
    /// the pinhole `camera` sees; pixels whose source lies outside take the nearest edge.
    ///
    /// # Panics
    /// If `rgb` does not hold `camera`'s pixels.
    pub fn undistort_rgb(&self, rgb: &[u8], camera: &Camera) -> Vec<u8> {
        let (w, h) = (camera.width as usize, camera.height as usize);
        assert_eq!(rgb.len(), w * h * 3, "undistort_rgb: image size");
        let mut out = vec![0u8; w * h * 3];
        for (p, px) in out.chunks_exact_mut(3).enumerate() {
            let x = ((p % w) as f64 - camera.cx) / camera.fx;
            let y = ((p / w) as f64 - camera.cy) / camera.fy;
            let (dx, dy) = self.distort(x, y);
            let sx = (dx * camera.fx + camera.cx).clamp(0.0, (w - 1) as f64);
            let sy = (dy * camera.fy + camera.cy).clamp(0.0, (h - 1) as f64);
            let (x0, y0) = (sx.floor() as usize, sy.floor() as usize);
            let (x1, y1) = ((x0 + 1).min(w - 1), (y0 + 1).min(h - 1));
            let (fx, fy) = (sx - x0 as f64, sy - y0 as f64);
            for (c, v) in px.iter_mut().enumerate() {
                let at = |x: usize, y: usize| rgb[(y * w + x) * 3 + c] as f64;
                let top = at(x0, y0) * (1.0 - fx) + at(x1, y0) * fx;
                let bottom = at(x0, y1) * (1.0 - fx) + at(x1, y1) * fx;
                *v = (top * (1.0 - fy) + bottom * fy).round() as u8;
            }
        }
        out
    }
}

/// The instant-ngp fox: 50 frames of a phone video circling a figurine, 1080x1920, with COLMAP
/// poses (`transforms_present_frames_DERIVED.json`, camera-to-world in the OpenGL convention,
/// converted here by flipping the camera's y and z axes).
pub fn fox(root: &Path) -> Result<PosedVideo, DatasetError> {
    let dir = root.join("instant_ngp_fox_video_frames");
    let path = dir.join("transforms_present_frames_DERIVED.json");
    let text = std::fs::read_to_string(&path).map_err(|e| IoError::io(&path, e))?;
    let json: serde_json::Value =
        serde_json::from_str(&text).map_err(|e| format(&path, e.to_string()))?;
    let num = |key: &str| {
        json[key]
            .as_f64()
            .ok_or_else(|| format(&path, format!("missing or bad '{key}'")))
    };
    let camera = Camera {
        width: num("w")? as u32,
        height: num("h")? as u32,
        fx: num("fl_x")?,
        fy: num("fl_y")?,
        cx: num("cx")?,
        cy: num("cy")?,
    };
    // Distortion terms left out are zero.
    let coef = |key: &str| match &json[key] {
        serde_json::Value::Null => Ok(0.0),
        v => v
            .as_f64()
            .filter(|v| v.is_finite())
            .ok_or_else(|| format(&path, format!("bad '{key}'"))),
    };
    let lens = Distortion {
        k1: coef("k1")?,
        k2: coef("k2")?,
        p1: coef("p1")?,
        p2: coef("p2")?,
    };
    let frames = json["frames"]
        .as_array()
        .filter(|f| !f.is_empty())
        .ok_or_else(|| format(&path, "no frames"))?;
    let (mut files, mut poses) = (Vec::new(), Vec::new());
    for (i, f) in frames.iter().enumerate() {
        let bad = || {
            format(
                &path,
                format!("frame {i}: bad file_path or transform_matrix"),
            )
        };
        let file = f["file_path"].as_str().ok_or_else(bad)?;
        let m: Vec<Vec<f64>> = f["transform_matrix"]
            .as_array()
            .ok_or_else(bad)?
            .iter()
            .map(|row| {
                row.as_array()
                    .map(|r| r.iter().filter_map(|v| v.as_f64()).collect::<Vec<f64>>())
                    .filter(|r| r.len() == 4)
                    .ok_or_else(bad)
            })
            .collect::<Result<_, _>>()?;
        if m.len() < 3 {
            return Err(bad());
        }
        // OpenGL camera axes (y up, looking down -z) to OpenCV's: negate columns 1 and 2.
        let rotation = Mat3([
            [m[0][0], -m[0][1], -m[0][2]],
            [m[1][0], -m[1][1], -m[1][2]],
            [m[2][0], -m[2][1], -m[2][2]],
        ]);
        let pose = Pose {
            rotation,
            translation: Vec3::new(m[0][3], m[1][3], m[2][3]),
        };
        if !pose.is_finite() {
            return Err(bad());
        }
        files.push(dir.join(file));
        poses.push(pose);
    }
    let centre = axes_meeting_point(
        poses
            .iter()
            .map(|p| (p.translation, p.rotation * Vec3::new(0.0, 0.0, 1.0))),
    )
    .ok_or_else(|| format(&path, "optical axes are parallel: no scene centre"))?;
    let centre_depth = poses
        .iter()
        .map(|p| p.ref_to_view(centre).z() as f32)
        .collect();
    Ok(PosedVideo {
        files,
        camera,
        lens,
        poses,
        centre_depth,
    })
}

/// The point nearest to every optical axis, given as (camera centre, viewing direction)
/// pairs in world coordinates: the solution of `sum (I - a a^T) X = sum (I - a a^T) C`.
/// `None` when the axes are parallel.
fn axes_meeting_point(axes: impl Iterator<Item = (Vec3, Vec3)>) -> Option<Vec3> {
    let mut m = Mat3([[0.0; 3]; 3]);
    let mut b = Vec3::ZERO;
    for (c, a) in axes {
        let a = a.normalized();
        let p = Mat3::IDENTITY.add(&Mat3::outer(a, a).scale(-1.0));
        m = m.add(&p);
        b = b + p * c;
    }
    m.inverse().map(|mi| mi * b)
}

/// The temple ring: reference `templeSR0001`, targets its ring neighbours `templeSR0002` and
/// `templeSR0010` (22.7 degrees either side). No depth; the optical axes' meeting point gives
/// the scene centre's depth.
fn temple(root: &Path, scene: &str, name: &str) -> Result<Dataset, DatasetError> {
    let dir = root.join("middlebury_mview_sparse_ring").join(scene);
    let par = dir.join("templeSR_par.txt");
    let text = std::fs::read_to_string(&par).map_err(|e| IoError::io(&par, e))?;
    // name -> (K, R, t), world to camera.
    let mut views = Vec::new();
    for line in text.lines().skip(1) {
        let f: Vec<&str> = line.split_whitespace().collect();
        if f.len() != 22 {
            return Err(format(&par, format!("line '{line}': 22 fields expected")));
        }
        let v: Vec<f64> = f[1..]
            .iter()
            .map(|x| x.parse::<f64>())
            .collect::<Result<_, _>>()
            .map_err(|e| format(&par, format!("line '{line}': {e}")))?;
        let k = (v[0], v[4], v[2], v[5]);
        let r = Mat3([
            [v[9], v[10], v[11]],
            [v[12], v[13], v[14]],
            [v[15], v[16], v[17]],
        ]);
        let t = Vec3::new(v[18], v[19], v[20]);
        views.push((f[0].trim_end_matches(".png").to_string(), k, r, t));
    }
    let find = |n: &str| {
        views
            .iter()
            .find(|v| v.0 == n)
            .ok_or_else(|| format(&par, format!("no view {n}")))
    };
    let centre = axes_meeting_point(views.iter().map(|(_, _, r, t)| {
        (
            -(r.transpose() * *t),
            r.transpose() * Vec3::new(0.0, 0.0, 1.0),
        )
    }))
    .ok_or_else(|| format(&par, "optical axes are parallel: no scene centre"))?;
    let camera_of = |k: (f64, f64, f64, f64), w: u32, h: u32| Camera {
        width: w,
        height: h,
        fx: k.0,
        fy: k.1,
        cx: k.2,
        cy: k.3,
    };
    let (_, k0, r0, t0) = find("templeSR0001")?;
    let (w, h, rgb_ref) = rgb(&dir.join("templeSR0001.png"))?;
    let mut targets = Vec::new();
    for n in ["templeSR0002", "templeSR0010"] {
        let (_, k, r, t) = find(n)?;
        let (tw, th, data) = rgb(&dir.join(format!("{n}.png")))?;
        // X_ref = R0 R^T X_view + (t0 - R0 R^T t).
        let rot = *r0 * r.transpose();
        targets.push(Target {
            name: n.into(),
            pose: Pose {
                rotation: rot,
                translation: *t0 - rot * *t,
            },
            camera: camera_of(*k, tw, th),
            rgb: data,
        });
    }
    Ok(Dataset {
        name: name.into(),
        camera: camera_of(*k0, w, h),
        rgb: rgb_ref,
        depth: vec![f32::NAN; (w * h) as usize],
        centre_depth: Some((*r0 * centre + *t0).z() as f32),
        targets,
    })
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn undistortion_reads_where_the_lens_put_each_point() {
        let camera = Camera {
            width: 64,
            height: 48,
            fx: 50.0,
            fy: 50.0,
            cx: 31.5,
            cy: 23.5,
        };
        // A ramp along x: the value at pixel x is 3 x, so a pixel's output tells where it read.
        let rgb: Vec<u8> = (0..64 * 48).flat_map(|p| [(p % 64 * 3) as u8; 3]).collect();
        assert_eq!(Distortion::default().undistort_rgb(&rgb, &camera), rgb);
        let lens = Distortion {
            k1: 0.1,
            k2: -0.05,
            ..Distortion::default()
        };
        let out = lens.undistort_rgb(&rgb, &camera);
        let row = 23 * 64;
        for x in [5usize, 20, 31, 45, 60] {
            let n = (x as f64 - camera.cx) / camera.fx;
            let (dx, _) = lens.distort(n, (23.0 - camera.cy) / camera.fy);
            let read = (dx * camera.fx + camera.cx).clamp(0.0, 63.0);
            let got = out[(row + x) * 3] as f64 / 3.0;
            assert!(
                (got - read).abs() < 0.2,
                "x {x}: read {got}, lens says {read}"
            );
        }
        // k1 > 0 dominates: the sides read from further out.
        assert!(out[(row + 5) * 3] < rgb[(row + 5) * 3]);
        assert!(out[(row + 60) * 3] > rgb[(row + 60) * 3]);
    }
}
