//! H.264 motion vectors (FFmpeg's `AVMotionVector` side data) as a dense backward motion field.

use cpsl_core::Flow;

/// Size in bytes of FFmpeg's `AVMotionVector`: `int32 source; uint8 w, h; int16 src_x, src_y,
/// dst_x, dst_y; uint64 flags; int32 motion_x, motion_y; uint16 motion_scale` (dst is the block
/// centre, `src = dst + motion / motion_scale`).
const MV_SIZE: usize = 40;

/// A dense backward motion field from `AVMotionVector` records, if they cover at least half of
/// the frame with vectors into the previous frame (`source == -1`). Uncovered pixels (intra
/// blocks) get the median vector.
pub fn motion_from_vectors(raw: &[u8], w: usize, h: usize) -> Option<Flow> {
    let i16_at = |b: &[u8], o: usize| i16::from_ne_bytes([b[o], b[o + 1]]) as i32;
    let i32_at = |b: &[u8], o: usize| i32::from_ne_bytes([b[o], b[o + 1], b[o + 2], b[o + 3]]);
    let mut data = vec![0f32; w * h * 2];
    let mut covered = vec![false; w * h];
    let mut vectors = Vec::new();
    for r in raw.chunks_exact(MV_SIZE) {
        let source = i32_at(r, 0);
        let (bw, bh) = (r[4] as i32, r[5] as i32);
        let (dx, dy) = (i16_at(r, 10), i16_at(r, 12));
        let (mx, my) = (i32_at(r, 24), i32_at(r, 28));
        let scale = u16::from_ne_bytes([r[32], r[33]]).max(1) as f32;
        if source != -1 {
            continue;
        }
        let (u, v) = (mx as f32 / scale, my as f32 / scale);
        vectors.push((u, v));
        for y in (dy - bh / 2).max(0)..(dy + bh / 2).min(h as i32) {
            for x in (dx - bw / 2).max(0)..(dx + bw / 2).min(w as i32) {
                let p = y as usize * w + x as usize;
                data[p * 2] = u;
                data[p * 2 + 1] = v;
                covered[p] = true;
            }
        }
    }
    let n = covered.iter().filter(|&&c| c).count();
    if n * 2 < w * h {
        return None;
    }
    let median = |mut v: Vec<f32>| {
        let m = v.len() / 2;
        *v.select_nth_unstable_by(m, f32::total_cmp).1
    };
    let mu = median(vectors.iter().map(|v| v.0).collect());
    let mv = median(vectors.iter().map(|v| v.1).collect());
    for p in (0..w * h).filter(|&p| !covered[p]) {
        data[p * 2] = mu;
        data[p * 2 + 1] = mv;
    }
    Some(Flow {
        width: w,
        height: h,
        data,
    })
}
