//! Per-pixel depth of a frame from posed neighbouring frames: dense optical flow (OpenCV's
//! DIS, [`flow`]) to each neighbour and back (against the neighbour [`warp`]ed by the plane at
//! the median depth where that plane's motion is more than a shift: a zoom walking forward, a
//! keystone orbiting, under which DIS's patches match off), pixels whose forward
//! and backward flow disagree by more than `max_fb` px dropped, each remaining pixel
//! triangulated (closest point of the two rays) and kept when in front of both cameras and
//! seen under at least `min_angle_deg`, and dropped when the flow ends farther than
//! `max_epipolar` px from the epipolar line (the pixel moved on its own). Over the neighbours
//! the inverse depths within 5 % of their median are averaged, each weighted by the square of
//! its ray angle (the inverse of its variance under a flow error of a fixed number of
//! pixels: the variance, relative to the inverse depth squared, is the flow's angular noise,
//! the median over the pixels of the agreeing samples' weighted scatter, over the summed
//! weight); the confidence is the share of the neighbours that could see the pixel (in view,
//! under enough angle) that triangulated it within 5 % of the median, and 0 unless two did,
//! and 0 within `edge_band` px of a jump in the depth (where flow smooths across an occlusion
//! boundary).
//!
//! [`fuse`] combines such depth with a monocular prior: the prior fitted to the confident
//! pixels, then the views' departure from it spread over the frame by an edge-aware filter
//! guided by the colour picture.

use crate::{Result, TrackError};
use cpsl_core::{Camera, Homography, Pose, Vec3};
use opencv::core::{Mat, Point, Scalar, Size, Vec2f, Vec3f, BORDER_CONSTANT};
use opencv::prelude::*;
use opencv::{imgproc, video, ximgproc};
use rayon::prelude::*;

/// Depth of one frame from its neighbours, at working resolution.
#[derive(Debug, Clone)]
pub struct ViewDepth {
    /// Width.
    pub width: u32,
    /// Height.
    pub height: u32,
    /// Z-depth in the trajectory's unit, NaN where no neighbour triangulated the pixel.
    pub depth: Vec<f32>,
    /// Per pixel in `[0, 1]`.
    pub confidence: Vec<f32>,
    /// Per pixel, the variance of the inverse depth relative to its square (from the
    /// neighbours' ray angles and the flow's noise, [`depth_from_flows`]); empty where not
    /// known (then [`fuse`] keeps the views' depth wherever it is confident).
    pub variance: Vec<f32>,
}

impl ViewDepth {
    /// Share of pixels with a depth.
    pub fn density(&self) -> f64 {
        self.depth.iter().filter(|z| z.is_finite()).count() as f64 / self.depth.len().max(1) as f64
    }
}

/// Settings of [`depth_from_views`].
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct MvsConfig {
    /// Least ray angle in degrees.
    pub min_angle_deg: f64,
    /// Largest forward-backward flow disagreement in working pixels.
    pub max_fb: f32,
    /// Largest distance in working pixels between the flow's end and the epipolar line
    /// (the triangulated point seen from the neighbour): beyond it the pixel moved on its own.
    pub max_epipolar: f64,
    /// Pixels within this many working pixels of a depth jump get no confidence.
    pub edge_band: u32,
    /// A jump: neighbouring inverse depths differing by more than this share.
    pub edge_jump: f32,
    /// Where the plane at the median depth moves between the frame and a neighbour by more
    /// than this many working pixels beyond a shift ([`plane_distortion`]), the flows to
    /// that neighbour are computed again against it warped by the plane ([`warp`]).
    pub warp_px: f64,
}

impl Default for MvsConfig {
    fn default() -> Self {
        // Measured on the built-in scene moving sideways (exact poses, 320x240,
        // tests/paths.rs): DIS's medium preset at half resolution with 1 degree, no band and
        // the confidence counted over every neighbour had 59 % of the pixels confident at
        // AbsRel 4.3 %; these settings and [`flow`] 70 % at 1.3 %.
        Self {
            min_angle_deg: 0.5,
            max_fb: 1.0,
            max_epipolar: 1.0,
            edge_band: 3,
            edge_jump: 0.1,
            warp_px: 2.0,
        }
    }
}

/// Dense optical flow from `a` to `b` (working grey images), two channels of `f32`: DIS's
/// fast preset down to full resolution, without its variational refinement. Measured on the
/// built-in scene moving sideways at 480x270 (exact poses, four neighbours): the medium
/// preset, which stops at half resolution, 12.8 ms a flow with 73 % of the pixels confident
/// at AbsRel 1.7 %; this 13.9 ms with 72 % at 1.0 %; the fast preset at full resolution with
/// its refinement 36 ms for 76 % at 1.0 %.
pub fn flow(a: &Mat, b: &Mat) -> Result<Mat> {
    let mut dis = video::DISOpticalFlow::create(video::DISOpticalFlow_PRESET_FAST)?;
    dis.set_finest_scale(0)?;
    dis.set_variational_refinement_iterations(0)?;
    let mut f = Mat::default();
    dis.calc(a, b, &mut f)?;
    Ok(f)
}

/// A posed neighbour with the flows from the reference frame to it and back ([`flow`]).
#[derive(Clone, Copy)]
pub struct Neighbour<'a> {
    /// Camera-to-world pose.
    pub pose: &'a Pose,
    /// Flow from the reference frame to this one.
    pub forward: &'a Mat,
    /// Flow from this frame to the reference.
    pub backward: &'a Mat,
    /// `Some(d)` when the flows were computed against this frame warped onto the reference
    /// by the plane at depth `d` fronto-parallel to the reference ([`warp`]): then they are
    /// in the warped frame's pixels.
    pub plane: Option<f64>,
}

/// The homography of the plane at depth `plane` fronto-parallel to the camera `cam` at
/// camera-to-world pose `reference`: its pixels to those of the camera at `other`
/// ([`Homography::plane_forward`], the renderer's equation 1).
fn plane_homography(cam: &Camera, reference: &Pose, other: &Pose, plane: f64) -> Homography {
    Homography::plane_forward(cam, cam, &reference.relative_to(other), plane)
}

/// `image` (a working grey image of the frame at camera-to-world pose `pose`) warped onto
/// the reference frame at `reference` by the homography of the plane at depth `plane`
/// fronto-parallel to the reference: each reference pixel takes the image where its point on
/// that plane projects (bilinear, edges replicated). Flow from the reference to the result
/// is what is left after the plane's motion: under forward motion the plane takes out the
/// zoom that a patch matcher is biased by.
pub fn warp(
    cam: &Camera,
    reference: &Pose,
    (image, pose): (&Mat, &Pose),
    plane: f64,
) -> Result<Mat> {
    let (w, h) = (cam.width as i32, cam.height as i32);
    let mut map = Mat::new_rows_cols_with_default(h, w, opencv::core::CV_32FC2, Scalar::all(-1.0))?;
    let px = map.data_typed_mut::<Vec2f>()?;
    let hom = plane_homography(cam, reference, pose, plane);
    for y in 0..h as usize {
        for x in 0..w as usize {
            if let Some((u, v)) = hom.apply(x as f64, y as f64) {
                px[y * w as usize + x] = Vec2f::from([u as f32, v as f32]);
            }
        }
    }
    let mut out = Mat::default();
    imgproc::remap(
        image,
        &mut out,
        &map,
        &opencv::core::no_array(),
        imgproc::INTER_LINEAR,
        opencv::core::BORDER_REPLICATE,
        Scalar::all(0.0),
    )?;
    Ok(out)
}

/// Largest distance in working pixels, over the frame's corners, between where the plane at
/// depth `plane` fronto-parallel to the reference moves a corner (relative to where it moves
/// the centre) and where a shift would: how far the plane's motion between the two frames is
/// from a translation (a zoom, a keystone). Infinite when the plane leaves the other view.
pub fn plane_distortion(cam: &Camera, reference: &Pose, other: &Pose, plane: f64) -> f64 {
    let (w, h) = ((cam.width - 1) as f64, (cam.height - 1) as f64);
    let hom = plane_homography(cam, reference, other, plane);
    let Some(c) = hom.apply(w / 2.0, h / 2.0) else {
        return f64::INFINITY;
    };
    [(0.0, 0.0), (w, 0.0), (0.0, h), (w, h)]
        .into_iter()
        .map(|(x, y)| match hom.apply(x, y) {
            Some((u, v)) => ((u - c.0) - (x - w / 2.0)).hypot((v - c.1) - (y - h / 2.0)),
            None => f64::INFINITY,
        })
        .fold(0.0, f64::max)
}

/// The median, over a grid of the frame's pixels, of the angle in degrees under which the
/// cameras at `reference` and `other` (camera-to-world poses) see the pixel's point at depth
/// `depth` on the reference's ray: how well the pair can triangulate a scene that far away.
/// Walking forward it is small around the focus of expansion and grows towards the edges.
pub fn ray_angle(cam: &Camera, reference: &Pose, other: &Pose, depth: f64) -> f64 {
    const STEPS: u32 = 8;
    let (c0, c1) = (reference.translation, other.translation);
    let mut angles: Vec<f64> = (0..=STEPS)
        .flat_map(|i| (0..=STEPS).map(move |k| (i, k)))
        .map(|(i, k)| {
            let x = (cam.width - 1) as f64 * i as f64 / STEPS as f64;
            let y = (cam.height - 1) as f64 * k as f64 / STEPS as f64;
            let p = c0 + reference.rotation * cam.unproject(x, y, depth);
            let cos = (p - c0).normalized().dot((p - c1).normalized());
            cos.clamp(-1.0, 1.0).acos().to_degrees()
        })
        .collect();
    let m = angles.len() / 2;
    *angles.select_nth_unstable_by(m, f64::total_cmp).1
}

/// Depth of `reference` (a working grey image and its camera-to-world pose) from
/// `neighbours`, all seen by `cam`; see the [module docs](self).
pub fn depth_from_views(
    cam: &Camera,
    reference: (&Mat, &Pose),
    neighbours: &[(&Mat, &Pose)],
    cfg: &MvsConfig,
) -> Result<ViewDepth> {
    let flows = neighbours
        .iter()
        .map(|(img, _)| Ok((flow(reference.0, img)?, flow(img, reference.0)?)))
        .collect::<Result<Vec<_>>>()?;
    let nb: Vec<(&Mat, Neighbour)> = neighbours
        .iter()
        .zip(&flows)
        .map(|((img, pose), (forward, backward))| {
            let n = Neighbour {
                pose,
                forward,
                backward,
                plane: None,
            };
            (*img, n)
        })
        .collect();
    depth_with_warps(cam, reference, &nb, cfg)
}

/// [`depth_from_flows`] from the unwarped flows of `neighbours` (with their working grey
/// images), then, where the plane at the median depth found ([`median_depth`]) moves
/// between the reference and a neighbour by more than `cfg.warp_px` beyond a shift, again
/// with the flows to that neighbour warped by the plane ([`warped_flows`]).
pub fn depth_with_warps(
    cam: &Camera,
    reference: (&Mat, &Pose),
    neighbours: &[(&Mat, Neighbour)],
    cfg: &MvsConfig,
) -> Result<ViewDepth> {
    let pose = reference.1;
    let plain: Vec<Neighbour> = neighbours
        .iter()
        .map(|(_, n)| Neighbour { plane: None, ..*n })
        .collect();
    let first = depth_from_flows(cam, pose, &plain, cfg)?;
    let Some(plane) = median_depth(&first) else {
        return Ok(first);
    };
    let warped = neighbours
        .iter()
        .map(|(img, n)| warped_flows(cam, reference, (img, n.pose), plane, cfg))
        .collect::<Result<Vec<_>>>()?;
    if warped.iter().all(Option::is_none) {
        return Ok(first);
    }
    let nb: Vec<Neighbour> = plain
        .iter()
        .zip(&warped)
        .map(|(n, w)| match w {
            Some((forward, backward)) => Neighbour {
                pose: n.pose,
                forward,
                backward,
                plane: Some(plane),
            },
            None => *n,
        })
        .collect();
    depth_from_flows(cam, pose, &nb, cfg)
}

/// The median depth of the pixels of `d` with a depth (the median of their inverse depths,
/// inverted); `None` when none has one.
pub fn median_depth(d: &ViewDepth) -> Option<f64> {
    let mut inverse: Vec<f32> = d
        .depth
        .iter()
        .filter(|z| z.is_finite() && **z > 0.0)
        .map(|z| 1.0 / z)
        .collect();
    if inverse.is_empty() {
        return None;
    }
    let m = inverse.len() / 2;
    Some(1.0 / *inverse.select_nth_unstable_by(m, f32::total_cmp).1 as f64)
}

/// The flows from `reference` to `neighbour` (working grey images with their camera-to-world
/// poses) and back, with the neighbour [`warp`]ed by the plane at depth `plane`
/// fronto-parallel to the reference, when that plane moves between the two by more than
/// `cfg.warp_px` beyond a shift ([`plane_distortion`]); `None` when it does not (the plain
/// flows serve).
pub fn warped_flows(
    cam: &Camera,
    (image, pose): (&Mat, &Pose),
    neighbour: (&Mat, &Pose),
    plane: f64,
    cfg: &MvsConfig,
) -> Result<Option<(Mat, Mat)>> {
    if plane_distortion(cam, pose, neighbour.1, plane) <= cfg.warp_px {
        return Ok(None);
    }
    let moved = warp(cam, pose, neighbour, plane)?;
    Ok(Some((flow(image, &moved)?, flow(&moved, image)?)))
}

/// [`depth_from_views`] from flows already computed: the depth of the frame at `pose`.
pub fn depth_from_flows(
    cam: &Camera,
    pose: &Pose,
    neighbours: &[Neighbour],
    cfg: &MvsConfig,
) -> Result<ViewDepth> {
    let (w, h) = (cam.width as usize, cam.height as usize);
    let (p0, c0) = (pose, pose.translation);
    let cos_min = cfg.min_angle_deg.to_radians().cos();
    // Each neighbour's flows, pose and (where its picture was warped, since its flows end in
    // the warped picture) the plane that maps them back.
    let nbs = neighbours
        .iter()
        .map(|nb| {
            for m in [nb.forward, nb.backward] {
                let size = m.size()?;
                if (size.width as usize, size.height as usize) != (w, h) || m.channels() != 2 {
                    return Err(TrackError::Input(format!(
                        "a {}x{} flow of {} channels for a {w}x{h} camera",
                        size.width,
                        size.height,
                        m.channels()
                    )));
                }
            }
            Ok((
                nb.forward.data_typed::<Vec2f>()?,
                nb.backward.data_typed::<Vec2f>()?,
                nb.pose,
                nb.plane.map(|d| plane_homography(cam, p0, nb.pose, d)),
            ))
        })
        .collect::<Result<Vec<_>>>()?;
    let inside =
        |(u, v): (f32, f32)| u >= 0.0 && v >= 0.0 && u <= (w - 1) as f32 && v <= (h - 1) as f32;
    // What neighbour `nb` says of pixel (x, y), whose ray is `d0` (world direction, camera
    // z 1): nothing when it cannot see the pixel under enough angle; else, when the pixel
    // passes the checks, its inverse depth and the square of its ray angle (the inverse of
    // its variance: a flow error of a pixel moves the depth by its share of the angle).
    let sample = |(fwd, bwd, pose, plane): &(&[Vec2f], &[Vec2f], &Pose, Option<Homography>),
                  x: usize,
                  y: usize,
                  d0: Vec3|
     -> Option<Option<(f32, f32)>> {
        let f = fwd[y * w + x];
        // Where the flow ends (in the warped neighbour's pixels when it is warped), and the
        // neighbour's pixel there.
        let end = (x as f32 + f[0], y as f32 + f[1]);
        if !inside(end) {
            return None;
        }
        let (u, v) = match plane {
            None => end,
            Some(hom) => match hom.apply(end.0 as f64, end.1 as f64) {
                Some((u, v)) if inside((u as f32, v as f32)) => (u as f32, v as f32),
                _ => return None,
            },
        };
        let c1 = pose.translation;
        let d1 = pose.rotation * cam.unproject(u as f64, v as f64, 1.0);
        let w0 = c0 - c1;
        let (a, bb, c) = (d0.dot(d0), d0.dot(d1), d1.dot(d1));
        let (d, e) = (d0.dot(w0), d1.dot(w0));
        let den = a * c - bb * bb;
        if den.abs() < 1e-12 {
            return None;
        }
        // Along d0 (whose camera z is 1, so s is the depth) and along d1.
        let s = (bb * e - c * d) / den;
        let t = (a * e - bb * d) / den;
        if s <= 0.0 || t <= 0.0 {
            return None;
        }
        let x3: Vec3 = c0 + d0 * s;
        let (r0, r1) = ((x3 - c0).normalized(), (x3 - c1).normalized());
        let cos = r0.dot(r1);
        if cos > cos_min {
            return None;
        }
        let b = bwd[(end.1.round() as usize) * w + end.0.round() as usize];
        if (f[0] + b[0]).hypot(f[1] + b[1]) > cfg.max_fb {
            return Some(None);
        }
        let Some((pu, pv)) = cam.project(pose.rotation.transpose() * (x3 - c1)) else {
            return Some(None);
        };
        if (pu - u as f64).hypot(pv - v as f64) > cfg.max_epipolar {
            return Some(None);
        }
        let angle = cos.clamp(-1.0, 1.0).acos() as f32;
        Some(Some(((1.0 / s) as f32, angle * angle)))
    };
    let (mut depth, mut confidence) = (vec![f32::NAN; w * h], vec![0.0f32; w * h]);
    // Per pixel the agreeing samples' summed weight (ray angle squared), and where two or
    // more agree, their weighted scatter: an estimate of the flow's angular noise squared.
    let mut precision = vec![0.0f32; w * h];
    // Rows in parallel; per pixel the neighbours in order.
    let noise_rows: Vec<Vec<f32>> = depth
        .par_chunks_mut(w)
        .zip(confidence.par_chunks_mut(w))
        .zip(precision.par_chunks_mut(w))
        .enumerate()
        .map(|(y, ((depth, confidence), precision))| {
            let mut noise = Vec::new();
            let mut s: Vec<(f32, f32)> = Vec::with_capacity(nbs.len());
            for x in 0..w {
                s.clear();
                // The neighbours that could see the pixel under enough angle (triangulated
                // or not).
                let mut seen = 0u8;
                let d0 = p0.rotation * cam.unproject(x as f64, y as f64, 1.0);
                for nb in &nbs {
                    if let Some(found) = sample(nb, x, y, d0) {
                        seen += 1;
                        s.extend(found);
                    }
                }
                if s.is_empty() {
                    continue;
                }
                s.sort_by(|a, b| a.0.total_cmp(&b.0));
                let m = s[s.len() / 2].0;
                // The samples that agree with the median, and their mean weighted by their
                // inverse variance.
                s.retain(|p| (p.0 - m).abs() <= 0.05 * m);
                let agree = s.len();
                let (sum, weight) = s
                    .iter()
                    .fold((0.0, 0.0), |(a, b), p| (a + p.0 * p.1, b + p.1));
                depth[x] = weight / sum;
                precision[x] = weight;
                if agree >= 2 {
                    confidence[x] = agree as f32 / f32::from(seen);
                    let mean = sum / weight;
                    let scatter: f32 = s.iter().map(|p| p.1 * ((p.0 - mean) / mean).powi(2)).sum();
                    noise.push(scatter / (agree - 1) as f32);
                }
            }
            noise
        })
        .collect();
    let mut noise: Vec<f32> = noise_rows.into_iter().flatten().collect();
    noise.sort_by(f32::total_cmp);
    let noise = noise.get(noise.len() / 2).copied().unwrap_or(f32::NAN);
    let variance = precision
        .iter()
        .map(|&p| if p > 0.0 { noise / p } else { f32::INFINITY })
        .collect();
    if cfg.edge_band > 0 {
        let band = edge_band(&depth, (w, h), cfg)?;
        for (c, b) in confidence.iter_mut().zip(band) {
            if b != 0 {
                *c = 0.0;
            }
        }
    }
    Ok(ViewDepth {
        width: cam.width,
        height: cam.height,
        depth,
        confidence,
        variance,
    })
}

/// Non-zero within `cfg.edge_band` pixels of a jump of more than `cfg.edge_jump` between
/// neighbouring inverse depths.
fn edge_band(depth: &[f32], (w, h): (usize, usize), cfg: &MvsConfig) -> Result<Vec<u8>> {
    let mut jump = vec![0u8; w * h];
    let ratio = 1.0 + cfg.edge_jump;
    for y in 0..h {
        for x in 0..w {
            let a = depth[y * w + x];
            if !a.is_finite() {
                continue;
            }
            for (xx, yy) in [(x + 1, y), (x, y + 1)] {
                if xx < w && yy < h {
                    let b = depth[yy * w + xx];
                    if b.is_finite() && a.max(b) > ratio * a.min(b) {
                        jump[y * w + x] = 1;
                        jump[yy * w + xx] = 1;
                    }
                }
            }
        }
    }
    let src = Mat::new_rows_cols_with_data(h as i32, w as i32, &jump)?;
    let side = 2 * cfg.edge_band as i32 + 1;
    let kernel = imgproc::get_structuring_element(
        imgproc::MORPH_RECT,
        Size::new(side, side),
        Point::new(-1, -1),
    )?;
    let mut out = Mat::default();
    imgproc::dilate(
        &src,
        &mut out,
        &kernel,
        Point::new(-1, -1),
        1,
        BORDER_CONSTANT,
        Scalar::all(0.0),
    )?;
    Ok(out.data_typed::<u8>()?.to_vec())
}

/// How [`fuse`] combined the two depths.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Fusion {
    /// Share of pixels whose depth came from the views.
    pub from_views: f64,
    /// `(a, b)` when the prior filled the other pixels: the affine fit `a / z + b` of its
    /// inverse depth to the views' (a curve may map it, see [`fuse`]); `None` when its depth
    /// order disagrees with the views' and they were left unknown (NaN).
    pub prior: Option<(f64, f64)>,
}

/// `depth` of the frame at `from` (working resolution, trajectory units) seen from the frame
/// at `to`: every pixel with a depth moved to where its point projects there, the nearest
/// point winning where several land on one pixel; each keeps its confidence. Pixels no point
/// reaches (disoccluded, or outside `from`'s view) are unknown.
pub fn carry(cam: &Camera, from: &Pose, depth: &ViewDepth, to: &Pose) -> Result<ViewDepth> {
    let (w, h) = (cam.width as usize, cam.height as usize);
    if (depth.width, depth.height) != (cam.width, cam.height) {
        return Err(TrackError::Input(format!(
            "carrying a {}x{} depth map with a {w}x{h} camera",
            depth.width, depth.height
        )));
    }
    let back = to.rotation.transpose();
    let (mut z, mut conf) = (vec![f32::NAN; w * h], vec![0.0f32; w * h]);
    for y in 0..h {
        for x in 0..w {
            let (d, c) = (depth.depth[y * w + x], depth.confidence[y * w + x]);
            if !(d.is_finite() && d > 0.0) {
                continue;
            }
            let world =
                from.translation + from.rotation * cam.unproject(x as f64, y as f64, d as f64);
            let p = back * (world - to.translation);
            let Some((u, v)) = cam.project(p) else {
                continue;
            };
            let (u, v) = (u.round(), v.round());
            if !(u >= 0.0 && v >= 0.0 && u < w as f64 && v < h as f64) {
                continue;
            }
            let i = v as usize * w + u as usize;
            let zt = p.z() as f32;
            if z[i].is_nan() || zt < z[i] {
                z[i] = zt;
                conf[i] = c;
            }
        }
    }
    Ok(ViewDepth {
        width: cam.width,
        height: cam.height,
        depth: z,
        confidence: conf,
        variance: Vec::new(),
    })
}

/// `z` averaged with `earlier` (another frame's depth carried to it, [`carry`]; same size)
/// in inverse depth, weighted by confidence, at the pixels where both have at least
/// `min_conf` and their inverse depths differ by at most `agree` of `z`'s; the confidence
/// stays `z`'s.
pub fn blend(z: &mut ViewDepth, earlier: &ViewDepth, min_conf: f32, agree: f32) {
    for (((a, &ca), &b), &cb) in z
        .depth
        .iter_mut()
        .zip(&z.confidence)
        .zip(&earlier.depth)
        .zip(&earlier.confidence)
    {
        if !(a.is_finite() && b.is_finite() && ca >= min_conf && cb >= min_conf) {
            continue;
        }
        let (ia, ib) = (1.0 / *a, 1.0 / b);
        if (ia - ib).abs() <= agree * ia {
            *a = (ca + cb) / (ca * ia + cb * ib);
        }
    }
}

/// `z` (z-depth, `from` = width x height, NaN where unknown) resized to `to`: its inverse
/// depth area-averaged (shrinking) or bilinearly interpolated (enlarging) over the known
/// pixels; NaN where none is near.
pub fn resize_depth(z: &[f32], from: (u32, u32), to: (u32, u32)) -> Result<Vec<f32>> {
    use opencv::core::{Size, CV_32F};
    use opencv::imgproc;
    let n = from.0 as usize * from.1 as usize;
    if z.len() != n || n == 0 || to.0 == 0 || to.1 == 0 {
        return Err(TrackError::Input(format!(
            "a {}x{} depth map has {n} values, found {}",
            from.0,
            from.1,
            z.len()
        )));
    }
    if from == to {
        return Ok(z.to_vec());
    }
    let known = |v: f32| v.is_finite() && v > 0.0;
    let inv: Vec<f32> = z
        .iter()
        .map(|&v| if known(v) { 1.0 / v } else { 0.0 })
        .collect();
    let mask: Vec<f32> = z.iter().map(|&v| f32::from(u8::from(known(v)))).collect();
    let shrink = to.0 < from.0 && to.1 < from.1;
    let resize = |v: &[f32]| -> Result<Vec<f32>> {
        let m = Mat::new_rows_cols_with_data(from.1 as i32, from.0 as i32, v)?;
        let mut out = Mat::default();
        let how = if shrink {
            imgproc::INTER_AREA
        } else {
            imgproc::INTER_LINEAR
        };
        imgproc::resize(
            &m,
            &mut out,
            Size::new(to.0 as i32, to.1 as i32),
            0.0,
            0.0,
            how,
        )?;
        debug_assert_eq!(out.typ(), CV_32F);
        Ok(out.data_typed::<f32>()?.to_vec())
    };
    let (inv, mask) = (resize(&inv)?, resize(&mask)?);
    Ok(inv
        .iter()
        .zip(&mask)
        .map(|(&i, &m)| if m > 0.5 && i > 0.0 { m / i } else { f32::NAN })
        .collect())
}

/// Fuses multi-view depth with a monocular prior of the same size (any scale), guided by
/// `guide`, the frame's picture at that size (8-bit, one or three channels):
///
/// 1. the prior's inverse depth is fitted to the views' (robust affine fit over pixels with
///    confidence of at least `min_conf`: weighted least squares re-weighted with Cauchy
///    weights; then a robust increasing piecewise-linear curve, which maps the prior instead
///    of the line where it fits the views at least [`CURVE_GAIN`] times as tightly: a
///    network's depth is bent, not only scaled and shifted);
/// 2. confident pixels keep the views' depth, unless they depart from the fitted prior by
///    more than [`OUTLIER_SCALES`] robust residual scales of the fit and by more than
///    [`OUTLIER_SHARE`] of its inverse depth: then they are the views' errors (the flow fattened
///    across an occluding edge, a repeated texture matched a period off) and count as not
///    confident;
/// 3. every other pixel takes what an edge-aware filter (OpenCV's fast global smoother,
///    confidence weighted: the filtered values over the filtered confidence) spreads from the
///    confident pixels around it, within regions of similar colour: where the fitted prior
///    explains the views well (its misfit at most 1 % of the inverse depth), the fitted
///    prior plus the views' departure from it, so the prior bends to the views and keeps its
///    own shape; where it explains them badly (5 % or more, as FastDepth on real footage),
///    the views' own inverse depth; a blend between. Far from any confident pixel the fitted
///    prior stands; where the fit turns the prior's order around, those pixels stay unknown
///    (NaN).
///
/// Where the views carry a variance ([`ViewDepth::variance`]), a confident pixel's inverse
/// depth is averaged with step 3's estimate there, each weighted by its inverse variance; the
/// estimate's variance is the robust spread of the confident views around it less the views'
/// median variance (an exact prior in other units: a few tenths of a percent; FastDepth:
/// several percent, so the views stand).
///
/// The result's confidence is the views' where they are kept, the filtered confidence where
/// their depth was spread (times `min_conf`), and 0 where the fitted prior stands alone.
/// `None` when fewer than 1 % of the pixels are confident.
pub fn fuse(
    views: &ViewDepth,
    prior: &[f32],
    guide: &Mat,
    min_conf: f32,
) -> Result<Option<(ViewDepth, Fusion)>> {
    let size = guide.size()?;
    if prior.len() != views.depth.len()
        || (size.width as u32, size.height as u32) != (views.width, views.height)
    {
        return Err(TrackError::Input(format!(
            "fusing {}x{} views with a prior of {} values and a {}x{} picture",
            views.width,
            views.height,
            prior.len(),
            size.width,
            size.height
        )));
    }
    let confident = |z: f32, c: f32| z.is_finite() && c >= min_conf;
    let samples: Vec<(f64, f64)> = views
        .depth
        .iter()
        .zip(&views.confidence)
        .zip(prior)
        .filter(|((&z, &c), p)| confident(z, c) && p.is_finite() && **p > 0.0)
        .map(|((z, _), p)| (1.0 / *p as f64, 1.0 / *z as f64))
        .collect();
    if samples.len() < prior.len() / 100 || samples.len() < 10 {
        return Ok(None);
    }
    let floor = samples.iter().map(|s| s.1).fold(f64::INFINITY, f64::min) * 0.5;
    // The fits need a few tens of thousands of pixels, not every confident one (a carried
    // depth map is confident almost everywhere): every k-th.
    let samples: Vec<(f64, f64)> = samples
        .iter()
        .step_by(samples.len().div_ceil(FIT_SAMPLES))
        .copied()
        .collect();
    let Some((a, b, affine_scale)) = fit_affine(&samples) else {
        return Ok(None);
    };
    // A monotone curve through the affine fit absorbs how a network bends depth (its inverse
    // depth to some power, compressed far away); it stands where it explains the views better.
    let curve = Curve::fit(&samples, affine_scale).filter(|(_, s)| *s < CURVE_GAIN * affine_scale);
    let spread_scale = curve.as_ref().map_or(affine_scale, |c| c.1);
    // How far the prior's shape is trusted: by how well it explains the views (the fit's
    // robust residual scale relative to the inverse depth).
    let mut ys: Vec<f64> = samples.iter().map(|s| s.1).collect();
    let misfit = affine_scale / crate::median(&mut ys);
    let own =
        ((misfit - TRUSTED_MISFIT) / (UNTRUSTED_MISFIT - TRUSTED_MISFIT)).clamp(0.0, 1.0) as f32;
    // A prior whose order the views turn around (a <= 0) has nothing to give.
    let prior_fits = a > 0.0;
    let fitted: Vec<f32> = prior
        .iter()
        .map(|&p| {
            if prior_fits && p.is_finite() && p > 0.0 {
                let x = 1.0 / p as f64;
                let y = curve.as_ref().map_or(a * x + b, |(c, _)| c.at(x));
                y.max(floor) as f32
            } else {
                f32::NAN
            }
        })
        .collect();
    let (n, floor) = (prior.len(), floor as f32);
    // A confident pixel far off the fitted prior, by the fit's own spread and by a share of
    // its inverse depth, is the views' error (flow fattened across an occluding edge, a
    // repeated texture matched a period off): dropped.
    let limit = (OUTLIER_SCALES * spread_scale) as f32;
    let confident = |z: f32, c: f32, f: f32| {
        confident(z, c) && !(f.is_finite() && (1.0 / z - f).abs() > limit.max(OUTLIER_SHARE * f))
    };
    // Over the confident pixels, weighted by confidence: the views' departure from the fitted
    // prior (0 where it has none), their inverse depth, and the weights, filtered together.
    let weighted: Vec<Vec3f> = views
        .depth
        .iter()
        .zip(&views.confidence)
        .zip(&fitted)
        .map(|((&z, &c), &f)| {
            if !confident(z, c, f) {
                return Vec3f::from([0.0, 0.0, 0.0]);
            }
            let departure = if f.is_finite() { 1.0 / z - f } else { 0.0 };
            Vec3f::from([c * departure, c / z, c])
        })
        .collect();
    let spread = edge_aware(guide, &weighted)?;
    // What the surroundings say at a pixel: the fitted prior bent by the views' departure
    // from it, or the views' own inverse depth spread, as far as the prior is trusted.
    let estimates: Vec<Option<f32>> = fitted
        .iter()
        .zip(&spread)
        .map(|(&f, s)| {
            if s[2] <= SPREAD_MIN_WEIGHT {
                return None;
            }
            let near = s[1] / s[2];
            Some(if f.is_finite() {
                own * near + (1.0 - own) * (f + s[0] / s[2])
            } else {
                near
            })
        })
        .collect();
    // The estimate's own variance (relative, squared): the robust spread of the confident
    // views around it less what the views' variance explains.
    let known = views.variance.len() == n;
    let mut residuals = Vec::new();
    let mut variances = Vec::new();
    if known {
        for i in 0..n {
            let (z, c, f) = (views.depth[i], views.confidence[i], fitted[i]);
            if let (true, Some(e)) = (confident(z, c, f), estimates[i]) {
                if views.variance[i].is_finite() {
                    residuals.push(((1.0 / z - e) / e).abs());
                    variances.push(views.variance[i]);
                }
            }
        }
    }
    let estimate_variance = if residuals.len() >= 10 {
        let mid = |v: &mut Vec<f32>| {
            let m = v.len() / 2;
            *v.select_nth_unstable_by(m, f32::total_cmp).1
        };
        let r = 1.4826 * mid(&mut residuals);
        (r * r - mid(&mut variances)).max(1e-6)
    } else {
        f32::INFINITY
    };
    let mut from_views = 0usize;
    let (mut depth, mut confidence) = (Vec::with_capacity(n), Vec::with_capacity(n));
    for (i, ((&z, &c), (&f, s))) in views
        .depth
        .iter()
        .zip(&views.confidence)
        .zip(fitted.iter().zip(&spread))
        .enumerate()
    {
        let (z, c) = if confident(z, c, f) {
            from_views += 1;
            // The views and the estimate around them, each weighted by its inverse variance.
            match estimates[i] {
                Some(e) if known && views.variance[i].is_finite() => {
                    let (pv, pe) = (1.0 / views.variance[i], 1.0 / estimate_variance);
                    let inv = (pv / z + pe * e) / (pv + pe);
                    (1.0 / inv.max(floor), c)
                }
                _ => (z, c),
            }
        } else if let Some(e) = estimates[i] {
            (1.0 / e.max(floor), s[2] * min_conf)
        } else {
            (1.0 / f, 0.0)
        };
        depth.push(if z.is_finite() && z > 0.0 {
            z
        } else {
            f32::NAN
        });
        confidence.push(c);
    }
    let fused = ViewDepth {
        width: views.width,
        height: views.height,
        depth,
        confidence,
        variance: Vec::new(),
    };
    Ok(Some((
        fused,
        Fusion {
            from_views: from_views as f64 / n as f64,
            prior: prior_fits.then_some((a, b)),
        },
    )))
}

/// How many robust residual scales of the prior's fit a confident pixel may depart from the
/// fitted prior (and [`OUTLIER_SHARE`] of its inverse depth). Measured on the built-in scene
/// (tests/paths.rs): the orbit's fused AbsRel with an exact prior 12.8 % without the check,
/// 0.67 % with it; with a network-like prior 14.2 % and 9.9 %; the fox's novel views 0.03 dB
/// lower (FastDepth's fit there spreads by 13 % of the inverse depth, so little is dropped).
pub const OUTLIER_SCALES: f64 = 6.0;

/// What a confident pixel may always depart from the fitted prior, as a share of its
/// inverse depth: the views may put an object the prior misses up to this much nearer or
/// farther (`the_views_bend_the_prior_up_to_colour_edges`: 14 to 25 %).
pub const OUTLIER_SHARE: f32 = 0.3;

/// Least filtered confidence for the views' spread depth to count.
const SPREAD_MIN_WEIGHT: f32 = 1e-4;

/// Misfit (robust residual scale over the median inverse depth) of a prior whose shape is
/// trusted: the views' departure from it is spread. Measured on the built-in scene: the exact
/// depth in other units 0.9 %, blurred and bent as a monocular network's 6 %; FastDepth on
/// the fox 2.5 % to 25 %, median 13 %.
const TRUSTED_MISFIT: f64 = 0.01;
/// Misfit of a prior whose shape is not trusted at all: the views' own inverse depth is
/// spread (between the two, a blend).
const UNTRUSTED_MISFIT: f64 = 0.05;

/// How much lower than the affine fit's the curve's robust residual scale must be for the
/// curve to stand. On the built-in scene's forward path with a network-like prior the curve
/// was 9 % tighter and worse (8.4 % AbsRel over the 90 % most confident pixels against 8.0).
pub const CURVE_GAIN: f64 = 0.9;

/// A piecewise-linear, increasing map of the prior's inverse depth to the views', knots at
/// quantiles of the prior's, extended linearly beyond the end knots.
struct Curve {
    knots: Vec<f64>,
    values: Vec<f64>,
}

impl Curve {
    /// The curve's value at `x`.
    fn at(&self, x: f64) -> f64 {
        self.on_segment(Self::segment(&self.knots, x), x)
    }

    /// The segment of `knots` (at least two) that holds `x`, or the end segment nearer it.
    fn segment(knots: &[f64], x: f64) -> usize {
        knots.partition_point(|&k| k <= x).clamp(1, knots.len() - 1) - 1
    }

    /// The line of segment `j` (knots `j` and `j + 1`) at `x`.
    fn on_segment(&self, j: usize, x: f64) -> f64 {
        let (t, v) = (&self.knots, &self.values);
        v[j] + (v[j + 1] - v[j]) * (x - t[j]) / (t[j + 1] - t[j])
    }

    /// Robust fit to `(prior, views)` inverse-depth pairs (least squares re-weighted with
    /// Cauchy weights, starting from `scale`): knots at quantiles of the prior's inverse depth,
    /// one segment per [`CURVE_SAMPLES`] samples and at most [`CURVE_SEGMENTS`], at least a
    /// `2 * CURVE_SEGMENTS`-th of the range apart; a knot where the fit turns down is dropped
    /// and the rest fitted again. `None` with too few samples or knots, or when the fit still
    /// turns down. With the robust scale.
    fn fit(samples: &[(f64, f64)], scale: f64) -> Option<(Self, f64)> {
        let segments = (samples.len() / CURVE_SAMPLES).min(CURVE_SEGMENTS);
        if segments < 2 {
            return None;
        }
        let mut xs: Vec<f64> = samples.iter().map(|s| s.0).collect();
        xs.sort_by(f64::total_cmp);
        let quantile =
            |q: f64| xs[((q * (xs.len() - 1) as f64).round() as usize).min(xs.len() - 1)];
        let (lo, hi) = (quantile(0.01), quantile(0.99));
        let gap = (hi - lo) / (2 * CURVE_SEGMENTS) as f64;
        let mut knots = vec![lo];
        for j in 1..segments {
            let t = quantile(0.01 + 0.98 * j as f64 / segments as f64);
            if t - knots[knots.len() - 1] >= gap && hi - t >= gap {
                knots.push(t);
            }
        }
        knots.push(hi);
        while knots.len() >= 3 {
            let (curve, scale) = Self::fit_knots(samples, knots.clone(), scale)?;
            match curve.values.windows(2).position(|v| v[1] <= v[0]) {
                None => return Some((curve, scale)),
                // Drop the interior knot of the segment that turns down.
                Some(j) => {
                    knots.remove(if j + 1 == knots.len() - 1 { j } else { j + 1 });
                }
            }
        }
        None
    }

    /// The robust fit with the given knots; `None` when singular.
    fn fit_knots(samples: &[(f64, f64)], knots: Vec<f64>, mut scale: f64) -> Option<(Self, f64)> {
        let m = knots.len();
        // Each sample's segment, found once: the rounds only change the values.
        let segment: Vec<usize> = samples
            .iter()
            .map(|&(x, _)| Self::segment(&knots, x))
            .collect();
        let mut curve = Self {
            knots,
            values: vec![0.0; m],
        };
        // Each sample's absolute residual from the last round's curve, and a copy to take
        // their median in.
        let mut e = vec![0.0; samples.len()];
        let mut sorted = Vec::with_capacity(samples.len());
        for round in 0..6 {
            // Normal equations of the hat-function basis (tridiagonal, row-major).
            let mut n = vec![0.0; m * m];
            let mut r = vec![0.0; m];
            let t = &curve.knots;
            for ((&(x, y), &j), &e) in samples.iter().zip(&segment).zip(&e) {
                let w = if round == 0 {
                    1.0
                } else {
                    let e = e / scale;
                    1.0 / (1.0 + e * e)
                };
                let u = (x - t[j]) / (t[j + 1] - t[j]);
                let (h0, h1) = (1.0 - u, u);
                n[j * m + j] += w * h0 * h0;
                n[j * m + j + 1] += w * h0 * h1;
                n[(j + 1) * m + j] += w * h0 * h1;
                n[(j + 1) * m + j + 1] += w * h1 * h1;
                r[j] += w * h0 * y;
                r[j + 1] += w * h1 * y;
            }
            curve.values = crate::ba::cholesky_solve(&mut n, m, r)?;
            for ((&(x, y), &j), e) in samples.iter().zip(&segment).zip(&mut e) {
                *e = (y - curve.on_segment(j, x)).abs();
            }
            sorted.clear();
            sorted.extend_from_slice(&e);
            scale = (1.4826 * crate::median(&mut sorted)).max(1e-9);
        }
        curve
            .values
            .iter()
            .all(|v| v.is_finite())
            .then_some((curve, scale))
    }
}

/// Most (prior, views) pairs the prior's fits take: beyond it, every k-th confident pixel.
/// On the fox the fused frames have 50 000 to 120 000 confident pixels at 480x270; all of
/// them took the fits 50 to 140 ms.
const FIT_SAMPLES: usize = 20_000;

/// Samples per segment of the prior's curve.
const CURVE_SAMPLES: usize = 500;
/// Most segments of the prior's curve.
const CURVE_SEGMENTS: usize = 6;

/// Robust affine fit `y = a x + b` (least squares re-weighted with Cauchy weights); `None`
/// when degenerate.
fn fit_affine(samples: &[(f64, f64)]) -> Option<(f64, f64, f64)> {
    let (mut a, mut b) = (1.0, 0.0);
    let mut scale = f64::INFINITY;
    for _ in 0..6 {
        let (mut sw, mut sx, mut sy, mut sxx, mut sxy) = (0.0, 0.0, 0.0, 0.0, 0.0);
        for &(x, y) in samples {
            let w = if scale.is_finite() {
                let r = (y - (a * x + b)) / scale;
                1.0 / (1.0 + r * r)
            } else {
                1.0
            };
            sw += w;
            sx += w * x;
            sy += w * y;
            sxx += w * x * x;
            sxy += w * x * y;
        }
        let den = sw * sxx - sx * sx;
        if den.abs() < 1e-18 {
            return None;
        }
        a = (sw * sxy - sx * sy) / den;
        b = (sy - a * sx) / sw;
        let mut r: Vec<f64> = samples
            .iter()
            .map(|&(x, y)| (y - (a * x + b)).abs())
            .collect();
        scale = (1.4826 * crate::median(&mut r)).max(1e-9);
    }
    (a.is_finite() && b.is_finite()).then_some((a, b, scale))
}

/// `values` (per pixel of `guide`) filtered by OpenCV's fast global smoother guided by
/// `guide`: smooth within regions of similar colour, not across edges. Settings measured on
/// the built-in scene (a blurred prior: 3.0 % AbsRel over every pixel with the colour
/// picture as guide, 4.6 % with grey).
fn edge_aware(guide: &Mat, values: &[Vec3f]) -> Result<Vec<Vec3f>> {
    let size = guide.size()?;
    let src = Mat::new_rows_cols_with_data(size.height, size.width, values)?;
    let mut out = Mat::default();
    ximgproc::fast_global_smoother_filter(guide, &src, &mut out, 30.0, 8.0, 0.25, 3)?;
    Ok(out.data_typed::<Vec3f>()?.to_vec())
}

#[cfg(test)]
mod tests {
    use super::{fuse, resize_depth, ViewDepth};
    use opencv::core::{Mat, Scalar, CV_8U};
    use opencv::prelude::*;

    #[test]
    fn the_plane_warp_takes_out_a_zoom_and_leaves_a_shift() {
        use cpsl_core::{Camera, Pose, Vec3};
        let cam = Camera::from_fov(64, 48, 60.0);
        let here = Pose::IDENTITY;
        // Sideways a fronto-parallel plane only shifts; walking forward it grows.
        let side = Pose::from_translation(Vec3::new(0.1, 0.0, 0.0));
        let ahead = Pose::from_translation(Vec3::new(0.0, 0.0, 0.2));
        assert!(super::plane_distortion(&cam, &here, &side, 2.0) < 1e-9);
        let zoom = super::plane_distortion(&cam, &here, &ahead, 2.0);
        // A corner 39.4 px from the centre moves by a tenth of it more than the centre.
        assert!(
            (zoom - 0.1 * 31.5f64.hypot(23.5) / 0.9).abs() < 1e-6,
            "{zoom}"
        );
        // An image seen from ahead, warped back by the plane it shows, is the image again.
        let image: Vec<u8> = (0..48 * 64)
            .map(|i| ((i % 64) * 2 + (i / 64) * 2) as u8)
            .collect();
        let near = Mat::new_rows_cols_with_data(48, 64, &image)
            .unwrap()
            .try_clone()
            .unwrap();
        let warped = super::warp(&cam, &here, (&near, &here), 2.0).unwrap();
        assert_eq!(warped.data_typed::<u8>().unwrap(), &image[..]);
        let far = super::warp(&cam, &ahead, (&near, &here), 1.8).unwrap();
        let back = super::warp(&cam, &here, (&far, &ahead), 2.0).unwrap();
        let back = back.data_typed::<u8>().unwrap();
        // Away from the border (replicated where the zoomed view lacks it), within rounding.
        for y in 8..40 {
            for x in 8..56 {
                let (a, b) = (back[y * 64 + x] as i32, image[y * 64 + x] as i32);
                assert!((a - b).abs() <= 2, "({x}, {y}): {a} against {b}");
            }
        }
    }

    #[test]
    fn the_ray_angle_grows_with_the_baseline_and_is_small_walking_forward() {
        use cpsl_core::{Camera, Pose, Vec3};
        let cam = Camera::from_fov(64, 48, 60.0);
        let here = Pose::IDENTITY;
        let angle = |x: f64, z: f64, yaw: f64| {
            let other = Pose::from_euler_deg(Vec3::new(x, 0.0, z), 0.0, yaw, 0.0);
            super::ray_angle(&cam, &here, &other, 5.0)
        };
        assert_eq!(angle(0.0, 0.0, 0.0), 0.0);
        // Sideways by 0.1 at depth 5: atan(0.1 / 5) = 1.15 degrees on the axis, a little
        // less off it, where the points are farther.
        let side = angle(0.1, 0.0, 0.0);
        assert!(
            side > 0.8 && side <= 0.1f64.atan2(5.0).to_degrees() + 1e-9,
            "{side}"
        );
        // Twice the baseline, about twice the angle; the other camera's turn changes nothing.
        assert!((angle(0.2, 0.0, 0.0) / side - 2.0).abs() < 0.02);
        assert!((angle(0.1, 0.0, 10.0) - side).abs() < 1e-9);
        // Walking forward as far, the rays part far less (nothing at the centre).
        let ahead = angle(0.0, 0.1, 0.0);
        assert!(ahead > 0.0 && ahead < side / 2.0, "{ahead} against {side}");
    }

    #[test]
    fn blending_averages_agreeing_confident_depth_only() {
        let view = |depth: Vec<f32>, confidence: Vec<f32>| ViewDepth {
            width: 5,
            height: 1,
            depth,
            confidence,
            variance: Vec::new(),
        };
        // Agreeing (1/2 and 1/2.04, equal weights), agreeing with twice the weight, too far
        // apart (a moving point), one not confident, one unknown.
        let mut z = view(
            vec![2.0, 2.0, 2.0, 2.0, f32::NAN],
            vec![0.8, 0.5, 0.8, 0.8, 0.0],
        );
        let earlier = view(
            vec![2.04, 2.04, 3.0, 2.04, 2.0],
            vec![0.8, 1.0, 0.8, 0.4, 1.0],
        );
        super::blend(&mut z, &earlier, 0.5, 0.05);
        let inv = |a: f32, wa: f32, b: f32, wb: f32| (wa + wb) / (wa / a + wb / b);
        assert!(
            (z.depth[0] - inv(2.0, 1.0, 2.04, 1.0)).abs() < 1e-5,
            "{:?}",
            z.depth
        );
        assert!(
            (z.depth[1] - inv(2.0, 1.0, 2.04, 2.0)).abs() < 1e-5,
            "{:?}",
            z.depth
        );
        assert_eq!(&z.depth[2..4], &[2.0, 2.0]);
        assert!(z.depth[4].is_nan());
        assert_eq!(z.confidence, vec![0.8, 0.5, 0.8, 0.8, 0.0]);
    }

    #[test]
    fn fusion_fits_the_prior_or_leaves_what_it_cannot_place() {
        // A ramp of inverse depth 0.2..0.5 seen by the views on the left half only.
        let (w, h) = (16u32, 4u32);
        let inv: Vec<f32> = (0..w * h).map(|i| 0.2 + 0.02 * (i % w) as f32).collect();
        let seen = |i: usize| i % w as usize >= w as usize / 2;
        let views = ViewDepth {
            width: w,
            height: h,
            depth: (0..inv.len())
                .map(|i| if seen(i) { f32::NAN } else { 1.0 / inv[i] })
                .collect(),
            confidence: (0..inv.len())
                .map(|i| if seen(i) { 0.0 } else { 1.0 })
                .collect(),
            variance: Vec::new(),
        };
        let guide =
            Mat::new_rows_cols_with_default(h as i32, w as i32, CV_8U, Scalar::all(128.0)).unwrap();
        // A prior in other units (inverse depth 3x + 0.1) fills the right half exactly.
        let prior: Vec<f32> = inv.iter().map(|v| 1.0 / (3.0 * v + 0.1)).collect();
        let (z, f) = fuse(&views, &prior, &guide, 0.5).unwrap().unwrap();
        let z = z.depth;
        let (a, b) = f.prior.unwrap();
        assert!(
            (a - 1.0 / 3.0).abs() < 1e-3 && (b + 0.1 / 3.0).abs() < 1e-3,
            "{a} {b}"
        );
        assert!((f.from_views - 0.5).abs() < 1e-9);
        assert!(z.iter().zip(&inv).all(|(z, v)| (z * v - 1.0).abs() < 1e-3));
        // A prior whose order is reversed gives nothing: the views stay, the rest is the
        // views' inverse depth spread from the seen half.
        let reversed = inv.clone();
        let (z, f) = fuse(&views, &reversed, &guide, 0.5).unwrap().unwrap();
        let z = z.depth;
        assert!(f.prior.is_none());
        for (i, v) in z.iter().enumerate() {
            if seen(i) {
                assert!((0.2..=0.36).contains(&(1.0 / v)), "pixel {i}: {v}");
            } else {
                assert!((v * inv[i] - 1.0).abs() < 1e-6, "pixel {i}");
            }
        }
        // Wrong sizes are errors.
        assert!(fuse(&views, &prior[1..], &guide, 0.5).is_err());
    }

    #[test]
    fn the_views_bend_the_prior_up_to_colour_edges() {
        // The prior's inverse depth ramps 0.2..0.35 down the rows; the views see columns 0..12
        // as the prior has it and columns 28..32 nearer (inverse depth 0.05 more); the
        // picture changes colour at column 20, where the truth steps.
        let (w, h) = (32usize, 4usize);
        let inv: Vec<f32> = (0..w * h).map(|i| 0.2 + 0.05 * (i / w) as f32).collect();
        let col = |i: usize| i % w;
        let truth = |i: usize| inv[i] + if col(i) >= 20 { 0.05 } else { 0.0 };
        let seen = |i: usize| col(i) < 12 || col(i) >= 28;
        let views = ViewDepth {
            width: w as u32,
            height: h as u32,
            depth: (0..w * h)
                .map(|i| if seen(i) { 1.0 / truth(i) } else { f32::NAN })
                .collect(),
            confidence: (0..w * h).map(|i| f32::from(u8::from(seen(i)))).collect(),
            variance: Vec::new(),
        };
        let prior: Vec<f32> = inv.iter().map(|v| 1.0 / (3.0 * v)).collect();
        let guide = Mat::from_exact_iter((0..w * h).map(|i| if col(i) < 20 { 40u8 } else { 200 }))
            .unwrap()
            .reshape(1, h as i32)
            .unwrap()
            .try_clone()
            .unwrap();
        let (z, f) = fuse(&views, &prior, &guide, 0.5).unwrap().unwrap();
        let z = z.depth;
        let (a, _) = f.prior.unwrap();
        assert!((a - 1.0 / 3.0).abs() < 0.01, "{a}");
        for (i, z) in z.iter().enumerate() {
            let r = z * truth(i);
            assert!((r - 1.0).abs() < 0.02, "pixel {i}: {r}");
        }
    }

    #[test]
    fn a_curve_maps_a_bent_prior_and_an_affine_one() {
        // The views' inverse depth is the prior's to the power 1.6 (a network compressing
        // the far range), a tenth of the samples wild.
        let bent = |x: f64| 0.1 * x.powf(1.6);
        let samples: Vec<(f64, f64)> = (0..4000)
            .map(|i| {
                let x = 1.0 + 2.0 * (i as f64 / 4000.0);
                (x, if i % 10 == 3 { 0.5 * bent(x) } else { bent(x) })
            })
            .collect();
        let (_, _, affine) = super::fit_affine(&samples).unwrap();
        let (c, scale) = super::Curve::fit(&samples, affine).unwrap();
        assert!(scale < 0.2 * affine, "{scale} against {affine}");
        for x in [1.0, 1.5, 2.2, 3.0] {
            assert!((c.at(x) / bent(x) - 1.0).abs() < 0.015, "{x}: {}", c.at(x));
        }
        // An affine map is found as it is, also beyond the samples.
        let line: Vec<(f64, f64)> = samples.iter().map(|&(x, _)| (x, 0.3 * x - 0.1)).collect();
        let (c, _) = super::Curve::fit(&line, 1.0).unwrap();
        assert!((c.at(4.0) - 1.1).abs() < 1e-9 && (c.at(0.5) - 0.05).abs() < 1e-9);
        // A map that turns down has no curve; too few samples neither.
        let hump: Vec<(f64, f64)> = samples
            .iter()
            .map(|&(x, _)| (x, -(x - 2.0).powi(2)))
            .collect();
        assert!(super::Curve::fit(&hump, 1.0).is_none());
        assert!(super::Curve::fit(&samples[..600], affine).is_none());
    }

    #[test]
    fn resizing_keeps_depth_and_unknown_pixels() {
        // 8x4 at depth 2 with the left half unknown; a plane of inverse depth ramps.
        let mut z = vec![2.0f32; 32];
        for y in 0..4 {
            z[y * 8..y * 8 + 4].fill(f32::NAN);
        }
        let small = resize_depth(&z, (8, 4), (4, 2)).unwrap();
        assert!(small[..2].iter().all(|v| v.is_nan()), "{small:?}");
        assert!(
            small[2..4].iter().all(|v| (v - 2.0).abs() < 1e-5),
            "{small:?}"
        );
        let big = resize_depth(&small, (4, 2), (8, 4)).unwrap();
        assert!(big[7].is_finite() && (big[7] - 2.0).abs() < 1e-5 && big[0].is_nan());
        let ramp: Vec<f32> = (0..16).map(|i| 1.0 / (1.0 + (i % 4) as f32)).collect();
        let r = resize_depth(&ramp, (4, 4), (2, 2)).unwrap();
        // Inverse depths 1,2 average to 1.5 (depth 2/3), 3,4 to 3.5.
        assert!(
            (r[0] - 1.0 / 1.5).abs() < 1e-5 && (r[1] - 1.0 / 3.5).abs() < 1e-5,
            "{r:?}"
        );
        assert!(resize_depth(&ramp, (4, 3), (2, 2)).is_err());
    }
}
