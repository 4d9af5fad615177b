//! Depth from two rectified views (stereo video, stereo photographs, two-camera rigs).
//!
//! [`match_pair`] runs OpenCV's semi-global matcher (`StereoSGBM`) on a left/right pair of
//! the same size:
//!
//! 1. **Rectification check.** ORB features are matched across the views (cross-checked
//!    Hamming matches); the median vertical offset of the matches is the pair's vertical
//!    misalignment. Beyond a quarter pixel the right view is shifted back by it before
//!    matching. The horizontal offsets of the same matches give the disparity search range
//!    (so converged pairs with negative disparities, like 3-D films, are matched too).
//! 2. **Matching.** SGBM in its three-way mode on colour, 3x3 blocks, the standard penalties
//!    (`P1 = 8 c b^2`, `P2 = 32 c b^2`), pre-filter cap 15, a uniqueness margin of 5 %, a
//!    left-right consistency check (at most 1 px) and speckle filtering; disparities come in
//!    sixteenths of a pixel (sub-pixel parabola fit). Both views are padded sideways by the
//!    search range first, so that the left columns are searched over the whole range too.
//!    These settings were chosen on the Middlebury pairs (`cpsl eval-stereo`; the full
//!    eight-path mode, larger blocks and OpenCV's WLS disparity filter all scored worse).
//! 3. **Occlusion fill.** Pixels that fail the checks (occlusions next to foreground edges,
//!    textureless areas) take the smaller of the nearest valid disparities to their left and
//!    right on the same row (the background side, where occlusions lie), then a 3x3 median
//!    removes single-pixel outliers; [`Disparity::valid`] keeps which pixels were matched.
//!
//! [`Disparity::depth`] turns disparity into z-depth, `Z = f b / (d + offset)`, where `offset`
//! is the right principal point minus the left one (zero for a parallel rig).
//!
//! [`split`] cuts a side-by-side or top-bottom frame into its two views.

use opencv::core::{self, Mat, Scalar, Vector};
use opencv::prelude::*;
use opencv::{calib3d, features2d, imgproc};
use thiserror::Error;

/// Why a pair could not be matched.
#[derive(Debug, Error)]
pub enum StereoError {
    /// The views' sizes or byte counts do not fit together.
    #[error("{0}")]
    Input(String),
    /// OpenCV failed.
    #[error("OpenCV: {0}")]
    OpenCv(#[from] opencv::Error),
}

type Result<T> = std::result::Result<T, StereoError>;

/// How the two views share a frame.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum StereoLayout {
    /// Left view in the left half, right view in the right half.
    SideBySide,
    /// Left view in the top half, right view in the bottom half.
    TopBottom,
}

impl std::str::FromStr for StereoLayout {
    type Err = String;
    fn from_str(s: &str) -> std::result::Result<Self, String> {
        match s {
            "sbs" => Ok(Self::SideBySide),
            "tab" => Ok(Self::TopBottom),
            other => Err(format!(
                "unknown stereo layout {other:?} (sbs: side by side, tab: top and bottom)"
            )),
        }
    }
}

impl StereoLayout {
    /// The name the command line uses.
    pub fn name(self) -> &'static str {
        match self {
            Self::SideBySide => "sbs",
            Self::TopBottom => "tab",
        }
    }

    /// The size of one view of a `width x height` frame; an error when the split dimension
    /// is odd.
    pub fn view_size(self, width: u32, height: u32) -> Result<(u32, u32)> {
        match self {
            Self::SideBySide if width >= 2 && width.is_multiple_of(2) => Ok((width / 2, height)),
            Self::TopBottom if height >= 2 && height.is_multiple_of(2) => Ok((width, height / 2)),
            Self::SideBySide => Err(StereoError::Input(format!(
                "a side-by-side frame needs an even width, found {width}"
            ))),
            Self::TopBottom => Err(StereoError::Input(format!(
                "a top-bottom frame needs an even height, found {height}"
            ))),
        }
    }
}

/// Splits an RGB frame (3 bytes per pixel) into its left and right views and their size.
pub fn split(
    rgb: &[u8],
    width: u32,
    height: u32,
    layout: StereoLayout,
) -> Result<(Vec<u8>, Vec<u8>, u32, u32)> {
    check_rgb(rgb, width, height)?;
    let (vw, vh) = layout.view_size(width, height)?;
    let (w, h) = (width as usize, height as usize);
    match layout {
        StereoLayout::SideBySide => {
            let half = vw as usize;
            let (mut l, mut r) = (Vec::with_capacity(half * h * 3), Vec::new());
            r.reserve(half * h * 3);
            for row in rgb.chunks_exact(w * 3) {
                l.extend_from_slice(&row[..half * 3]);
                r.extend_from_slice(&row[half * 3..]);
            }
            Ok((l, r, vw, vh))
        }
        StereoLayout::TopBottom => {
            let n = w * vh as usize * 3;
            Ok((rgb[..n].to_vec(), rgb[n..].to_vec(), vw, vh))
        }
    }
}

fn check_rgb(rgb: &[u8], width: u32, height: u32) -> Result<()> {
    let n = width as usize * height as usize * 3;
    if width == 0 || height == 0 || rgb.len() != n {
        return Err(StereoError::Input(format!(
            "a {width}x{height} RGB image has {n} bytes, found {}",
            rgb.len()
        )));
    }
    Ok(())
}

/// Matching settings; [`StereoConfig::default`] is what the pipelines use.
#[derive(Debug, Clone, PartialEq)]
pub struct StereoConfig {
    /// Matching block side in pixels (odd).
    pub block: u32,
    /// Disparity search range `(least, count)` in pixels (count a multiple of 16); `None`
    /// sets it from the feature matches (or `0..width/4` when too few match).
    pub range: Option<(i32, u32)>,
    /// SGBM uniqueness margin in percent.
    pub uniqueness: u32,
    /// Largest left-right disagreement in pixels (negative: no check).
    pub lr_max_diff: i32,
    /// Speckle filter: largest blob (pixels) removed as noise, 0 for none.
    pub speckle_window: u32,
    /// Least local texture (mean absolute horizontal grey gradient over 5x5 pixels, in grey
    /// levels) where a match counts; flatter pixels are left unmatched.
    pub min_texture: f32,
    /// Correct a vertical misalignment found by the rectification check.
    pub correct_vertical: bool,
    /// Fill unmatched pixels from the background side of their row, then take a 3x3 median
    /// (removes single-pixel outliers); without it unmatched pixels stay NaN.
    pub fill: bool,
}

impl Default for StereoConfig {
    fn default() -> Self {
        Self {
            block: 3,
            range: None,
            uniqueness: 5,
            lr_max_diff: 1,
            speckle_window: 100,
            min_texture: 0.3,
            correct_vertical: true,
            fill: true,
        }
    }
}

/// A disparity map of the left view: a left pixel `(x, y)` shows the point seen at
/// `(x - d, y)` in the right view.
#[derive(Debug, Clone)]
pub struct Disparity {
    /// Width.
    pub width: u32,
    /// Height.
    pub height: u32,
    /// Disparity in pixels per left pixel, row by row; NaN where unknown (only when not
    /// filled).
    pub values: Vec<f32>,
    /// Per pixel, whether matching (with its checks) found it, rather than the fill.
    pub valid: Vec<bool>,
    /// Vertical offset of the right view in pixels found by the rectification check (it was
    /// removed before matching when the configuration says so); `None` when too few features
    /// matched to tell.
    pub vertical_offset: Option<f32>,
    /// The disparity range searched, `(least, count)`.
    pub range: (i32, u32),
}

impl Disparity {
    /// Share of pixels that matching found.
    pub fn density(&self) -> f64 {
        self.valid.iter().filter(|&&v| v).count() as f64 / self.valid.len().max(1) as f64
    }

    /// Z-depth per pixel, `focal * baseline / (d + offset)`, NaN where the disparity is
    /// unknown or puts the point at or behind infinity.
    pub fn depth(&self, focal: f64, baseline: f64, offset: f64) -> Vec<f32> {
        self.values
            .iter()
            .map(|&d| {
                let s = d as f64 + offset;
                if d.is_finite() && s > 1e-3 {
                    (focal * baseline / s) as f32
                } else {
                    f32::NAN
                }
            })
            .collect()
    }
}

/// Matches a rectified pair (RGB, 3 bytes per pixel, both `width x height`); see the
/// [crate docs](crate).
pub fn match_pair(
    left: &[u8],
    right: &[u8],
    width: u32,
    height: u32,
    cfg: &StereoConfig,
) -> Result<Disparity> {
    check_rgb(left, width, height)?;
    check_rgb(right, width, height)?;
    if cfg.block.is_multiple_of(2) || !(1..=31).contains(&cfg.block) {
        return Err(StereoError::Input(format!(
            "the matching block must be odd and 1..=31, found {}",
            cfg.block
        )));
    }
    let (w, h) = (width as i32, height as i32);
    // Owned copies: OpenCV's borrowed views do not pass as plain matrices.
    let l = Mat::new_rows_cols_with_bytes::<core::Vec3b>(h, w, left)?.try_clone()?;
    let r = Mat::new_rows_cols_with_bytes::<core::Vec3b>(h, w, right)?.try_clone()?;
    let l_grey = grey(&l)?;
    let offsets = feature_offsets(&l_grey, &grey(&r)?)?;
    let vertical_offset = (offsets.len() >= MIN_MATCHES)
        .then(|| median(&mut offsets.iter().map(|o| o.1).collect::<Vec<_>>()));
    let mut shifted = Mat::default();
    let r = match vertical_offset {
        Some(dy) if cfg.correct_vertical && dy.abs() > 0.25 => {
            // Move the right view up by dy: x' = x, y' = y - dy.
            let m = Mat::from_slice_2d(&[[1.0f64, 0.0, 0.0], [0.0, 1.0, -dy as f64]])?;
            imgproc::warp_affine(
                &r,
                &mut shifted,
                &m,
                r.size()?,
                imgproc::INTER_LINEAR,
                core::BORDER_REPLICATE,
                Scalar::default(),
            )?;
            &shifted
        }
        _ => &r,
    };
    let range = match cfg.range {
        Some((lo, n)) => (lo, n.div_ceil(16).max(1) * 16),
        None => search_range(&offsets, width),
    };
    let c = 3i32;
    let b = cfg.block as i32;
    let mut sgbm = calib3d::StereoSGBM::create(
        range.0,
        range.1 as i32,
        b,
        8 * c * b * b,
        32 * c * b * b,
        cfg.lr_max_diff,
        15,
        cfg.uniqueness as i32,
        cfg.speckle_window as i32,
        2,
        calib3d::StereoSGBM_MODE_SGBM_3WAY,
    )?;
    // Pad the views sideways by the search range, so that the left columns (whose partners
    // lie left of the right view's edge for large disparities) are matched over the whole
    // range like the others; the results are cropped back.
    let (pad_left, pad_right) = ((range.0 + range.1 as i32).max(0), (-range.0).max(0));
    let pad = |m: &Mat| -> Result<Mat> {
        let mut out = Mat::default();
        core::copy_make_border(
            m,
            &mut out,
            0,
            0,
            pad_left,
            pad_right,
            core::BORDER_REPLICATE,
            Scalar::default(),
        )?;
        Ok(out)
    };
    let (l, r) = (pad(&l)?, pad(r)?);
    let mut raw = Mat::default();
    sgbm.compute(&l, &r, &mut raw)?;
    // OpenCV marks failures with (least disparity - 1) * 16.
    let invalid = ((range.0 - 1) * 16) as i16;
    let fixed = raw.data_typed::<i16>()?;
    let pw = (w + pad_left + pad_right) as usize;
    let mut values: Vec<f32> = fixed
        .chunks_exact(pw)
        .flat_map(|row| &row[pad_left as usize..pad_left as usize + width as usize])
        .map(|&v| {
            if v == invalid {
                f32::NAN
            } else {
                v as f32 / 16.0
            }
        })
        .collect();
    // Flat areas (a black frame, a blank wall) match anywhere equally well: unmatched.
    if cfg.min_texture > 0.0 {
        for (v, t) in values.iter_mut().zip(texture(&l_grey)?) {
            if t < cfg.min_texture {
                *v = f32::NAN;
            }
        }
    }
    let valid: Vec<bool> = values.iter().map(|v| v.is_finite()).collect();
    if cfg.fill {
        fill_rows(&mut values, width as usize);
        let m = Mat::new_rows_cols_with_data(h, w, &values)?.try_clone()?;
        let mut out = Mat::default();
        imgproc::median_blur(&m, &mut out, 3)?;
        values = out.data_typed::<f32>()?.to_vec();
    }
    Ok(Disparity {
        width,
        height,
        values,
        valid,
        vertical_offset,
        range,
    })
}

fn grey(m: &Mat) -> Result<Mat> {
    let mut g = Mat::default();
    imgproc::cvt_color(m, &mut g, imgproc::COLOR_RGB2GRAY, 0)?;
    Ok(g)
}

/// Per pixel of a grey image, the mean absolute horizontal gradient over 5x5 pixels (grey
/// levels per pixel).
fn texture(grey: &Mat) -> Result<Vec<f32>> {
    let mut dx = Mat::default();
    imgproc::sobel(
        grey,
        &mut dx,
        core::CV_32F,
        1,
        0,
        1,
        1.0,
        0.0,
        core::BORDER_REPLICATE,
    )?;
    let mut abs = Mat::default();
    core::absdiff(&dx, &Scalar::all(0.0), &mut abs)?;
    let mut mean = Mat::default();
    imgproc::blur(
        &abs,
        &mut mean,
        core::Size::new(5, 5),
        core::Point::new(-1, -1),
        core::BORDER_REPLICATE,
    )?;
    // The 1-wide Sobel is a central difference: half of it is the gradient per pixel.
    Ok(mean.data_typed::<f32>()?.iter().map(|v| v * 0.5).collect())
}

/// Fewest feature matches that decide the vertical offset and the search range.
const MIN_MATCHES: usize = 20;

/// `(x_left - x_right, y_right - y_left)` of cross-checked ORB matches between the views
/// (grey).
fn feature_offsets(l: &Mat, r: &Mat) -> Result<Vec<(f32, f32)>> {
    let mut orb = features2d::ORB::create(
        2000,
        1.2,
        8,
        31,
        0,
        2,
        features2d::ORB_ScoreType::HARRIS_SCORE,
        31,
        20,
    )?;
    let mut detect = |m: &Mat| -> Result<(Vector<core::KeyPoint>, Mat)> {
        let mut kp = Vector::new();
        let mut desc = Mat::default();
        orb.detect_and_compute(m, &core::no_array(), &mut kp, &mut desc, false)?;
        Ok((kp, desc))
    };
    let (kl, dl) = detect(l)?;
    let (kr, dr) = detect(r)?;
    if kl.is_empty() || kr.is_empty() {
        return Ok(Vec::new());
    }
    let matcher = features2d::BFMatcher::create(core::NORM_HAMMING, true)?;
    let mut matches = Vector::new();
    matcher.train_match(&dl, &dr, &mut matches, &core::no_array())?;
    let mut out = Vec::new();
    for m in matches.iter() {
        if m.distance > 48.0 {
            continue;
        }
        let (a, b) = (kl.get(m.query_idx as usize)?, kr.get(m.train_idx as usize)?);
        let (pa, pb) = (a.pt(), b.pt());
        // Rectified views: far from the same row is a wrong match, not an offset.
        let dy = pb.y - pa.y;
        if dy.abs() <= 8.0 {
            out.push((pa.x - pb.x, dy));
        }
    }
    Ok(out)
}

/// Disparity search range from feature offsets: their 1st to 99th percentile with a margin,
/// or `0..width/4` (at least 16) with too few matches.
fn search_range(offsets: &[(f32, f32)], width: u32) -> (i32, u32) {
    let fallback = (0, (width / 4).div_ceil(16).max(1) * 16);
    if offsets.len() < MIN_MATCHES {
        return fallback;
    }
    let mut dx: Vec<f32> = offsets.iter().map(|o| o.0).collect();
    dx.sort_by(f32::total_cmp);
    let at = |q: f64| dx[((dx.len() - 1) as f64 * q).round() as usize];
    let (lo, hi) = (at(0.01), at(0.99));
    let margin = ((hi - lo) * 0.15).max(8.0);
    let least = ((lo - margin).floor() as i32).min(0);
    let most = (hi + margin).ceil() as i32;
    let count = ((most - least).max(16) as u32).div_ceil(16) * 16;
    (least, count.min(width.div_ceil(16) * 16).max(16))
}

fn median(v: &mut [f32]) -> f32 {
    v.sort_by(f32::total_cmp);
    let n = v.len();
    if n % 2 == 1 {
        v[n / 2]
    } else {
        0.5 * (v[n / 2 - 1] + v[n / 2])
    }
}

/// Fills NaNs along each row with the smaller of the nearest finite values to the left and
/// right (the background side); rows without a value stay NaN.
fn fill_rows(values: &mut [f32], width: usize) {
    for row in values.chunks_exact_mut(width) {
        let mut left = vec![f32::NAN; width];
        let mut last = f32::NAN;
        for (x, v) in row.iter().enumerate() {
            if v.is_finite() {
                last = *v;
            }
            left[x] = last;
        }
        let mut next = f32::NAN;
        for x in (0..width).rev() {
            if row[x].is_finite() {
                next = row[x];
                continue;
            }
            row[x] = match (left[x].is_finite(), next.is_finite()) {
                (true, true) => left[x].min(next),
                (true, false) => left[x],
                (false, true) => next,
                (false, false) => f32::NAN,
            };
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn fill_takes_the_background_side() {
        let mut v = vec![5.0, f32::NAN, f32::NAN, 2.0, f32::NAN];
        fill_rows(&mut v, 5);
        assert_eq!(v, vec![5.0, 2.0, 2.0, 2.0, 2.0]);
    }

    #[test]
    fn split_layouts() {
        // 4x2 frame, pixel value = x + 10 y.
        let rgb: Vec<u8> = (0..2)
            .flat_map(|y| (0..4).flat_map(move |x| [x + 10 * y; 3]))
            .collect();
        let (l, r, w, h) = split(&rgb, 4, 2, StereoLayout::SideBySide).unwrap();
        assert_eq!((w, h), (2, 2));
        assert_eq!(
            l.iter().step_by(3).copied().collect::<Vec<_>>(),
            [0, 1, 10, 11]
        );
        assert_eq!(
            r.iter().step_by(3).copied().collect::<Vec<_>>(),
            [2, 3, 12, 13]
        );
        let (l, r, w, h) = split(&rgb, 4, 2, StereoLayout::TopBottom).unwrap();
        assert_eq!((w, h), (4, 1));
        assert_eq!(
            l.iter().step_by(3).copied().collect::<Vec<_>>(),
            [0, 1, 2, 3]
        );
        assert_eq!(
            r.iter().step_by(3).copied().collect::<Vec<_>>(),
            [10, 11, 12, 13]
        );
        assert!(split(&rgb, 3, 2, StereoLayout::SideBySide).is_err());
        assert!(split(&rgb[1..], 4, 2, StereoLayout::SideBySide).is_err());
    }

    #[test]
    fn depth_from_disparity() {
        let d = Disparity {
            width: 3,
            height: 1,
            values: vec![10.0, f32::NAN, -2.0],
            valid: vec![true, false, true],
            vertical_offset: None,
            range: (0, 16),
        };
        let z = d.depth(100.0, 0.1, 0.0);
        assert_eq!(z[0], 1.0);
        assert!(z[1].is_nan() && z[2].is_nan());
        assert_eq!(d.depth(100.0, 0.1, 3.0)[2], 10.0);
    }
}
