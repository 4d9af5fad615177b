//! Display rotation: the quarter turns a stream's display matrix asks for, applied to
//! pictures and to motion fields.

use cpsl_core::Flow;

/// A motion field of a picture turned clockwise by `degrees` (a quarter turn): positions and
/// vectors turn with it.
pub fn rotate_motion(motion: Flow, degrees: u32) -> Flow {
    if degrees == 0 {
        return motion;
    }
    let mut data = rotate(motion.data, motion.width, motion.height, 2, degrees);
    for v in data.chunks_exact_mut(2) {
        let (dx, dy) = (v[0], v[1]);
        [v[0], v[1]] = match degrees {
            90 => [-dy, dx],
            180 => [-dx, -dy],
            _ => [dy, -dx],
        };
    }
    let (width, height) = if degrees == 180 {
        (motion.width, motion.height)
    } else {
        (motion.height, motion.width)
    };
    Flow {
        width,
        height,
        data,
    }
}

/// The clockwise rotation (0, 90, 180 or 270 degrees) that shows a picture upright, from a
/// display matrix (nine 32-bit integers, 16.16 fixed point), as FFmpeg's tools apply it; 0
/// for a rotation that is not a quarter turn.
pub fn rotation_of(matrix: &[u8]) -> u32 {
    if matrix.len() < 36 {
        return 0;
    }
    let m = |i: usize| {
        i32::from_ne_bytes(matrix[4 * i..4 * i + 4].try_into().expect("4 bytes")) as f64 / 65536.0
    };
    let (s0, s1) = (m(0).hypot(m(3)), m(1).hypot(m(4)));
    if s0 == 0.0 || s1 == 0.0 {
        return 0;
    }
    let deg = (m(1) / s1).atan2(m(0) / s0).to_degrees().round();
    let deg = deg.rem_euclid(360.0) as u32;
    if deg.is_multiple_of(90) {
        deg % 360
    } else {
        0
    }
}

/// A `w x h` picture of `n`-sample pixels turned clockwise by `degrees` (0, 90, 180 or 270).
pub fn rotate<T: Copy>(data: Vec<T>, w: usize, h: usize, n: usize, degrees: u32) -> Vec<T> {
    if degrees == 0 {
        return data;
    }
    let (ow, oh) = if degrees == 180 { (w, h) } else { (h, w) };
    let mut out = Vec::with_capacity(data.len());
    for y in 0..oh {
        for x in 0..ow {
            // The source pixel that lands on (x, y).
            let (sx, sy) = match degrees {
                90 => (y, h - 1 - x),
                180 => (w - 1 - x, h - 1 - y),
                _ => (w - 1 - y, x),
            };
            out.extend_from_slice(&data[(sy * w + sx) * n..][..n]);
        }
    }
    out
}
