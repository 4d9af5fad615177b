//! Tiled warp-and-composite kernel.

use crate::mesh::MeshWarp;
use crate::prepared::{Filter, PreparedLayer, PreparedLayers};
use cpsl_core::resample::bilerp;
use cpsl_core::{Camera, Geometry, Pose, PremulImage};
use rayon::prelude::*;

/// Output tile width in pixels.
pub const TILE_W: usize = 64;
/// Output tile height in pixels (rows rendered by one parallel task).
pub const TILE_H: usize = 16;
const TILE: usize = TILE_W * TILE_H;

/// `1 - a / 255` for every 8-bit alpha, computed exactly as the closed form does.
const ONE_MINUS: [f32; 256] = {
    let mut t = [0.0f32; 256];
    let mut i = 0;
    while i < 256 {
        t[i] = 1.0 - i as f32 / 255.0;
        i += 1;
    }
    t
};

/// Catmull-Rom weights of the four taps at `x0 - 1 ..= x0 + 2` for each fraction `f / 256`
/// of a pixel past `x0` (they sum to 1; at `f = 0` they are `[0, 1, 0, 0]`, so an identity
/// warp stays exact).
const CUBIC: [[f32; 4]; 256] = {
    let mut t = [[0.0f32; 4]; 256];
    let mut i = 0;
    while i < 256 {
        let f = i as f32 / 256.0;
        let (f2, f3) = (f * f, f * f * f);
        t[i] = [
            0.5 * (-f3 + 2.0 * f2 - f),
            0.5 * (3.0 * f3 - 5.0 * f2 + 2.0),
            0.5 * (-3.0 * f3 + 4.0 * f2 + f),
            0.5 * (f3 - f2),
        ];
        i += 1;
    }
    t
};

/// Shortest span the AVX2 kernel takes (its last group of eight is masked to the pixels
/// left); shorter ones are sampled one by one.
#[cfg(target_arch = "x86_64")]
const SIMD_SPAN: usize = 4;

/// Fixed-point offset that keeps positions >= -2 px positive before truncation.
const OFFSET: i32 = 512;

/// Counters describing how much work a render did (for tests and profiling).
#[derive(Debug, Default, Clone, Copy, PartialEq, Eq)]
pub struct RenderStats {
    /// (tile, layer) pairs that were rasterised.
    pub drawn: u64,
    /// (tile, layer) pairs skipped because the footprint was empty or outside the layer.
    pub skipped: u64,
    /// Tiles whose layer loop ended early behind a fully opaque footprint.
    pub opaque_stops: u64,
}

impl std::ops::Add for RenderStats {
    type Output = Self;
    fn add(self, o: Self) -> Self {
        Self {
            drawn: self.drawn + o.drawn,
            skipped: self.skipped + o.skipped,
            opaque_stops: self.opaque_stops + o.opaque_stops,
        }
    }
}

/// How one layer maps target pixels to source pixels for a pose.
pub(crate) enum Warp {
    /// One inverse homography for the whole layer (fronto-parallel or slanted plane).
    Plane([[f64; 3]; 3]),
    /// One per triangle of a mesh.
    Mesh(MeshWarp),
}

impl Warp {
    /// Source position of target pixel `(x, y)`, if the layer's surface is there.
    pub(crate) fn source(&self, x: usize, y: usize) -> Option<(f64, f64)> {
        match self {
            Self::Plane(h) => {
                let (u, v) = (x as f64, y as f64);
                let d = h[2][0] * u + h[2][1] * v + h[2][2];
                (d > 0.0).then(|| {
                    (
                        (h[0][0] * u + h[0][1] * v + h[0][2]) / d,
                        (h[1][0] * u + h[1][1] * v + h[1][2]) / d,
                    )
                })
            }
            Self::Mesh(m) => m.source(x, y),
        }
    }
}

enum Class {
    Skip,
    Draw { check_w: bool, opaque: bool },
}

/// Decides how the output tile `[x0, x0 + tw) x [y0, y0 + th)` meets `layer` (of size
/// `sw x sh`) warped by the inverse homography `h`.
fn classify(
    h: &[[f64; 3]; 3],
    layer: &PreparedLayer,
    tile: [usize; 4],
    sw: usize,
    sh: usize,
) -> Class {
    let [x0, y0, tw, th] = tile;
    let (xa, xb, ya, yb) = (
        x0 as f64,
        (x0 + tw - 1) as f64,
        y0 as f64,
        (y0 + th - 1) as f64,
    );
    let mut bad = 0;
    let (mut minx, mut maxx, mut miny, mut maxy) = (f64::MAX, f64::MIN, f64::MAX, f64::MIN);
    for (x, y) in [(xa, ya), (xb, ya), (xa, yb), (xb, yb)] {
        let w = h[2][0] * x + h[2][1] * y + h[2][2];
        if w <= 0.0 {
            bad += 1;
            continue;
        }
        let sx = (h[0][0] * x + h[0][1] * y + h[0][2]) / w;
        let sy = (h[1][0] * x + h[1][1] * y + h[1][2]) / w;
        minx = minx.min(sx);
        maxx = maxx.max(sx);
        miny = miny.min(sy);
        maxy = maxy.max(sy);
    }
    match bad {
        4 => return Class::Skip,
        1..=3 => {
            return Class::Draw {
                check_w: true,
                opaque: false,
            }
        }
        _ => {}
    }
    // Bilinear taps of the footprint, with a margin for rounding to 1/256 px.
    const M: f64 = 0.01;
    if !(minx.is_finite() && maxx.is_finite() && miny.is_finite() && maxy.is_finite()) {
        return Class::Draw {
            check_w: true,
            opaque: false,
        };
    }
    // Far-off footprints (beyond 2^40 px) are clamped before the integer floor.
    const FAR: f64 = (1u64 << 40) as f64;
    let fl = |v: f64| floor(v.clamp(-FAR, FAR));
    let ix0 = fl(minx - M);
    let ix1 = fl(maxx + M) + 1.0;
    let iy0 = fl(miny - M);
    let iy1 = fl(maxy + M) + 1.0;
    let (swf, shf) = (sw as f64, sh as f64);
    if ix1 < 0.0 || iy1 < 0.0 || ix0 > swf - 1.0 || iy0 > shf - 1.0 {
        return Class::Skip;
    }
    let cx0 = ix0.max(0.0) as usize;
    let cy0 = iy0.max(0.0) as usize;
    let cx1 = ix1.min(swf - 1.0) as usize;
    let cy1 = iy1.min(shf - 1.0) as usize;
    let (nonempty, translucent) = layer.counts(cx0, cy0, cx1, cy1);
    if nonempty == 0 {
        return Class::Skip;
    }
    let inside = ix0 >= 0.0 && iy0 >= 0.0 && ix1 <= swf - 1.0 && iy1 <= shf - 1.0;
    Class::Draw {
        check_w: false,
        opaque: inside && translucent == 0,
    }
}

/// Adds texel `p` weighted by `w` to a cubic row sum (lanes R, B, G, A as `bilerp` gives them).
#[inline(always)]
fn add_tap(row: &mut [f32; 4], p: u32, w: f32) {
    if p != 0 {
        let c = [p & 255, (p >> 16) & 255, (p >> 8) & 255, p >> 24];
        for (r, c) in row.iter_mut().zip(c) {
            *r += w * c as f32;
        }
    }
}

/// Adds a cubic row sum weighted by `w` to the sample.
#[inline(always)]
fn add_row(acc: &mut [f32; 4], row: [f32; 4], w: f32) {
    for (a, r) in acc.iter_mut().zip(row) {
        *a += w * r;
    }
}

/// A cubic sample's lanes (R, B, G, A) rounded to 0..255, colour at most alpha.
#[inline(always)]
fn pack_cubic(acc: [f32; 4]) -> u64 {
    let al = (acc[3] + 0.5).clamp(0.0, 255.0) as u64;
    let lane = |v: f32| ((v + 0.5).max(0.0) as u64).min(al);
    lane(acc[0]) | lane(acc[1]) << 16 | lane(acc[2]) << 32 | al << 48
}

/// Adds a filtered sample `v` (lanes R, B, G, A) under transmittance `tv`. Accumulators
/// keep the same lane order; the output stage reorders to RGBA.
#[inline(always)]
fn composite(o: &mut [f32; 4], t: &mut f32, tv: f32, v: u64, opaqued: &mut u32) {
    let al = (v >> 48) as usize;
    if al != 0 {
        // Transmittance reaches exactly zero behind a fully opaque sample.
        *opaqued += (al == 255) as u32;
        let f = [
            v as u16 as f32,
            (v >> 16) as u16 as f32,
            (v >> 32) as u16 as f32,
            al as u16 as f32,
        ];
        for c in 0..4 {
            o[c] += tv * f[c];
        }
        *t = tv * ONE_MINUS[al];
    }
}

/// A layer texture as the kernels see it.
#[derive(Clone, Copy)]
struct Tex<'a> {
    /// Padded texels, row pitch `pitch` = width + 2 (see [`PreparedLayer`]).
    texels: &'a [u32],
    pitch: usize,
    /// Unpadded width and height.
    sw: u64,
    sh: u64,
    /// Use the AVX2 kernel for linear spans (bilinear only).
    simd: bool,
    /// Sample with the Catmull-Rom kernel instead of the bilinear one.
    cubic: bool,
}

/// One output row segment being composited: accumulators, transmittances and the count of
/// pixels that became opaque.
struct Span<'a> {
    acc: &'a mut [[f32; 4]],
    trans: &'a mut [f32],
    opaqued: u32,
}

impl Tex<'_> {
    /// Samples and composites the texture at `(xi, yi)`, in 1/256 px fixed point.
    #[inline(always)]
    fn sample(&self, xi: i64, yi: i64, o: &mut [f32; 4], t: &mut f32, opaqued: &mut u32) {
        let (x0, y0) = (xi >> 8, yi >> 8);
        // x0 in [-1, w-1] and y0 in [-1, h-1]: all four taps inside the padded texture.
        // Values below -1 wrap to huge unsigned numbers and fail too.
        if ((x0 + 1) as u64) <= self.sw && ((y0 + 1) as u64) <= self.sh {
            let pitch = self.pitch;
            let i = (y0 + 1) as usize * pitch + (x0 + 1) as usize;
            if let Some(q) = self.texels.get(i..i + pitch + 2) {
                let (p00, p01, p10, p11) = (q[0], q[1], q[pitch], q[pitch + 1]);
                // The cubic kernel reads 4x4 texels, but only where one of the central
                // four (the bilinear taps) is covered: the layer's extent and every skip
                // test stay the bilinear ones.
                if (p00 | p01 | p10 | p11) != 0 {
                    let (fx, fy) = ((xi & 255) as u64, (yi & 255) as u64);
                    let v = if self.cubic {
                        self.cubic(i, fx as usize, fy as usize)
                    } else {
                        bilerp(p00, p01, p10, p11, fx, fy)
                    };
                    let tv = *t;
                    composite(o, t, tv, v, opaqued);
                }
            }
        }
    }

    /// Catmull-Rom sample around padded texel `i` (the first bilinear tap) at fraction
    /// `(fx, fy)` / 256, as lanes R, B, G, A rounded to 0..255, colour at most alpha. Taps
    /// beyond the padded texture read as transparent, as the padding does.
    #[inline(always)]
    fn cubic(&self, i: usize, fx: usize, fy: usize) -> u64 {
        let pitch = self.pitch;
        let (wx, wy) = (&CUBIC[fx], &CUBIC[fy]);
        let mut acc = [0f32; 4];
        // Rows -1..=2 inside the padded texture: read them as they lie. A tap one column left
        // of column 0 lands on the row above's right padding and one right of the right
        // padding on the row below's left padding, both transparent as they should be.
        let first = i.wrapping_sub(pitch + 1);
        if let Some(taps) = self.texels.get(first..first.wrapping_add(3 * pitch + 4)) {
            for (j, &wyj) in wy.iter().enumerate() {
                let mut row = [0f32; 4];
                for (&p, &wxk) in taps[j * pitch..j * pitch + 4].iter().zip(wx) {
                    add_tap(&mut row, p, wxk);
                }
                add_row(&mut acc, row, wyj);
            }
            return pack_cubic(acc);
        }
        let (cx, cy) = (i % pitch, i / pitch);
        let rows = self.texels.len() / pitch;
        for (j, &wyj) in wy.iter().enumerate() {
            let Some(y) = (cy + j).checked_sub(1).filter(|&y| y < rows) else {
                continue;
            };
            let mut row = [0f32; 4];
            for (k, &wxk) in wx.iter().enumerate() {
                let Some(x) = (cx + k).checked_sub(1).filter(|&x| x < pitch) else {
                    continue;
                };
                add_tap(&mut row, self.texels[y * pitch + x], wxk);
            }
            add_row(&mut acc, row, wyj);
        }
        pack_cubic(acc)
    }

    /// Linear stepping: positions in 16.16 fixed point from `start` by `step` per pixel.
    #[inline(always)]
    fn draw_linear(&self, start: [i64; 2], step: [i64; 2], span: &mut Span<'_>) {
        // Pre-add half a 1/256 step so that a shift rounds to nearest.
        let (mut x, mut y) = (start[0] + 128, start[1] + 128);
        #[cfg(target_arch = "x86_64")]
        if self.simd && !self.cubic && span.trans.len() >= SIMD_SPAN {
            let last = span.trans.len() as i64 - 1;
            let fits = |v: i64| v.abs() < (1 << 30);
            let ends = [x, y, x + step[0] * last, y + step[1] * last];
            if ends.iter().all(|&v| fits(v)) && fits(step[0] * 8) && fits(step[1] * 8) {
                crate::simd::draw_linear(
                    self.texels,
                    self.pitch,
                    self.sw as u32,
                    self.sh as u32,
                    [x as i32, y as i32],
                    [step[0] as i32, step[1] as i32],
                    span.acc,
                    span.trans,
                    &mut span.opaqued,
                );
                return;
            }
        }
        for (o, t) in span.acc.iter_mut().zip(span.trans.iter_mut()) {
            if *t > 0.0 {
                self.sample(x >> 8, y >> 8, o, t, &mut span.opaqued);
            }
            x += step[0];
            y += step[1];
        }
    }

    /// Projective stepping with a division per pixel (strong perspective, or a plane that
    /// crosses the viewer's horizon when `CHECK_W`).
    #[inline(always)]
    fn draw_projective<const CHECK_W: bool>(
        &self,
        start: [f32; 3],
        inc: [f32; 3],
        span: &mut Span<'_>,
    ) {
        let [mut a, mut b, mut w] = start;
        for (o, t) in span.acc.iter_mut().zip(span.trans.iter_mut()) {
            if *t > 0.0 && (!CHECK_W || w > 0.0) {
                let inv = 1.0 / w;
                let xi = (a * inv * 256.0 + (OFFSET as f32 + 0.5)) as i64 - OFFSET as i64;
                let yi = (b * inv * 256.0 + (OFFSET as f32 + 0.5)) as i64 - OFFSET as i64;
                self.sample(xi, yi, o, t, &mut span.opaqued);
            }
            a += inc[0];
            b += inc[1];
            w += inc[2];
        }
    }
}

/// Largest deviation, in px, tolerated between the exact projective mapping and its linear
/// interpolation along a row.
const MAX_LINEAR_ERROR: f64 = 1.0 / 512.0;

/// Source position `(sx, sy)` and `w` of output pixel `(x, y)`.
#[inline(always)]
fn map(h: &[[f64; 3]; 3], x: f64, y: f64) -> (f64, f64, f64) {
    let w = h[2][0] * x + h[2][1] * y + h[2][2];
    let inv = 1.0 / w;
    (
        (h[0][0] * x + h[0][1] * y + h[0][2]) * inv,
        (h[1][0] * x + h[1][1] * y + h[1][2]) * inv,
        w,
    )
}

/// Deviation, in px, between the projective mapping and its chord at the middle of the row
/// interval `[x, x + n]`, with the source positions of its ends; `None` when the plane is not
/// in front of the viewer at both ends. For a 1-D projective map this deviation peaks near
/// the middle and scales with the square of the interval length.
#[inline]
#[allow(clippy::type_complexity)]
fn chord_error(
    h: &[[f64; 3]; 3],
    x: f64,
    y: f64,
    n: usize,
) -> Option<(((f64, f64), (f64, f64)), f64)> {
    let xe = x + n as f64;
    let ((sx0, sy0, w0), (sx1, sy1, w1)) = (map(h, x, y), map(h, xe, y));
    if !(w0 > 0.0 && w1 > 0.0) {
        return None;
    }
    let ends = ((sx0, sy0), (sx1, sy1));
    if h[2][0] == 0.0 {
        return Some((ends, 0.0));
    }
    let (sxm, sym, _) = map(h, (x + xe) * 0.5, y);
    let err = (sxm - (sx0 + sx1) * 0.5)
        .abs()
        .max((sym - (sy0 + sy1) * 0.5).abs());
    err.is_finite().then_some((ends, err))
}

/// Start and step, in 16.16 fixed point, of `m` pixels from source position `a` towards `b`
/// (the exact positions of the span's first pixel and of the pixel just after it).
#[inline]
fn linear_span(a: (f64, f64), b: (f64, f64), m: usize) -> Option<([i64; 2], [i64; 2])> {
    let fx = |v: f64| v * 65536.0;
    let (x, y) = (fx(a.0), fx(a.1));
    let (dx, dy) = (fx((b.0 - a.0) / m as f64), fx((b.1 - a.1) / m as f64));
    let lim = (1u64 << 40) as f64;
    [x, y, dx, dy]
        .iter()
        .all(|v| v.abs() < lim)
        .then(|| ([round(x), round(y)], [round(dx), round(dy)]))
}

/// Rounds to the nearest integer (ties away from zero) with a truncating conversion: `f64::round`
/// is a library call without SSE4.1.
#[inline(always)]
fn round(v: f64) -> i64 {
    (v + 0.5f64.copysign(v)) as i64
}

/// Largest integer not above `v`, for `|v| < 2^62`.
#[inline(always)]
fn floor(v: f64) -> f64 {
    let t = v as i64 as f64;
    if t > v {
        t - 1.0
    } else {
        t
    }
}

/// Length of the sub-spans into which a row segment of `n` pixels with chord error `err` is
/// cut so that linear interpolation stays within [`MAX_LINEAR_ERROR`]; `None` when even
/// 4-pixel sub-spans would be too coarse.
#[inline]
fn sub_span_len(err: f64, n: usize) -> Option<usize> {
    let mut len = n;
    loop {
        let scaled = err * (len as f64 / n as f64).powi(2);
        if scaled < MAX_LINEAR_ERROR {
            return Some(len.max(1));
        }
        if len <= 4 {
            return None;
        }
        len = len.div_ceil(2);
    }
}

/// Warps row `y` of the output tile starting at column `x0` (the span's width) from one layer
/// and composites it under what is already there.
fn draw_layer_row(
    tex: &Tex<'_>,
    layer: &PreparedLayer,
    h: &[[f64; 3]; 3],
    x0: usize,
    y: usize,
    check_w: bool,
    span: &mut Span<'_>,
) {
    let n = span.acc.len();
    let (x, yf) = (x0 as f64, y as f64);
    let mut s0 = 0;
    if !check_w {
        if let Some(((first, last), len)) =
            chord_error(h, x, yf, n).and_then(|(ends, e)| Some((ends, sub_span_len(e, n)?)))
        {
            // Exact positions at sub-span boundaries, each computed once (the row's ends by
            // the chord test).
            let at = |i: usize| match i {
                0 => first,
                i if i == n => last,
                i => {
                    let (sx, sy, _) = map(h, x + i as f64, yf);
                    (sx, sy)
                }
            };
            let mut from = first;
            while s0 < n {
                let m = len.min(n - s0);
                let to = at(s0 + m);
                let Some((p, d)) = linear_span(from, to, m) else {
                    break; // far-off coordinates: the projective path draws the rest
                };
                let mut sub = Span {
                    acc: &mut span.acc[s0..s0 + m],
                    trans: &mut span.trans[s0..s0 + m],
                    opaqued: 0,
                };
                if !span_misses_layer(layer, tex, p, d, m) {
                    tex.draw_linear(p, d, &mut sub);
                }
                span.opaqued += sub.opaqued;
                s0 += m;
                from = to;
            }
            if s0 == n {
                return;
            }
        }
    }
    let xs = x + s0 as f64;
    let start = [
        (h[0][0] * xs + h[0][1] * yf + h[0][2]) as f32,
        (h[1][0] * xs + h[1][1] * yf + h[1][2]) as f32,
        (h[2][0] * xs + h[2][1] * yf + h[2][2]) as f32,
    ];
    let inc = [h[0][0] as f32, h[1][0] as f32, h[2][0] as f32];
    let mut rest = Span {
        acc: &mut span.acc[s0..],
        trans: &mut span.trans[s0..],
        opaqued: 0,
    };
    if check_w {
        tex.draw_projective::<true>(start, inc, &mut rest);
    } else {
        tex.draw_projective::<false>(start, inc, &mut rest);
    }
    span.opaqued += rest.opaqued;
}

/// True when the bilinear taps of a linear span (16.16 start `p`, step `d`, `m` pixels) meet
/// only empty source rows, so the span can be skipped without reading texels.
#[inline]
fn span_misses_layer(
    layer: &PreparedLayer,
    tex: &Tex<'_>,
    p: [i64; 2],
    d: [i64; 2],
    m: usize,
) -> bool {
    let end = [p[0] + d[0] * (m as i64 - 1), p[1] + d[1] * (m as i64 - 1)];
    // Whole pixels, widened by one for rounding and one for the second bilinear tap.
    let lo = |a: i64, b: i64| (a.min(b) >> 16) - 1;
    let hi = |a: i64, b: i64| (a.max(b) >> 16) + 2;
    let (x0, x1) = (lo(p[0], end[0]), hi(p[0], end[0]));
    let (y0, y1) = (lo(p[1], end[1]), hi(p[1], end[1]));
    let (sw, sh) = (tex.sw as i64, tex.sh as i64);
    if x1 < 0 || y1 < 0 || x0 >= sw || y0 >= sh {
        return true;
    }
    // Steep spans cross many rows: not worth checking.
    if y1 - y0 > 8 {
        return false;
    }
    layer.rows_empty(
        x0.max(0) as u32,
        x1.min(sw - 1) as u32,
        y0.max(0) as usize,
        y1.min(sh - 1) as usize,
    )
}

/// One output pixel from its accumulator (lanes R, B, G, A on a 0..255 scale): 8-bit RGBA,
/// rounded half up and saturating, colour at most alpha.
#[inline(always)]
pub(crate) fn pack_pixel(s: &[f32; 4]) -> [u8; 4] {
    let a = (s[3] + 0.5) as u8;
    [
        ((s[0] + 0.5) as u8).min(a),
        ((s[2] + 0.5) as u8).min(a),
        ((s[1] + 0.5) as u8).min(a),
        a,
    ]
}

/// Packs a row of accumulators into `dst` (four bytes each), with the AVX2 kernel when `simd`.
fn pack_row(acc: &[[f32; 4]], dst: &mut [u8], simd: bool) {
    #[cfg(target_arch = "x86_64")]
    if simd {
        return crate::simd::pack_rgba8(acc, dst);
    }
    let _ = simd;
    for (d, s) in dst.chunks_exact_mut(4).zip(acc) {
        d.copy_from_slice(&pack_pixel(s));
    }
}

impl PreparedLayers {
    pub(crate) fn warps(&self, pose: &Pose, target: &Camera) -> Vec<Option<Warp>> {
        self.layers
            .par_iter()
            .map(|l| match &l.geometry {
                Geometry::Mesh(grid) => Some(Warp::Mesh(MeshWarp::new(
                    grid,
                    &l.cells,
                    &self.camera,
                    target,
                    pose,
                ))),
                g => g
                    .inverse_homography(l.depth, &self.camera, target, pose)
                    .filter(|h| h.0.is_finite())
                    .map(|h| Warp::Plane(h.0 .0)),
            })
            .collect()
    }

    /// Renders the band of rows `[y0, y0 + th)` tile by tile; `emit` receives each finished
    /// tile's accumulators (premultiplied RGBA on a 0..255 scale, row pitch [`TILE_W`]).
    fn render_band(
        &self,
        warps: &[Option<Warp>],
        width: usize,
        y0: usize,
        th: usize,
        filter: Filter,
        mut emit: impl FnMut(usize, usize, &[[f32; 4]]),
    ) -> RenderStats {
        let (sw, sh) = (self.camera.width as usize, self.camera.height as usize);
        let mut stats = RenderStats::default();
        let mut acc = vec![[0f32; 4]; TILE];
        let mut trans = vec![1f32; TILE];
        for x0 in (0..width).step_by(TILE_W) {
            let tw = TILE_W.min(width - x0);
            acc.fill([0.0; 4]);
            trans.fill(1.0);
            // Pixels per tile row whose transmittance is still above zero.
            let mut alive = [tw as u32; TILE_H];
            for (layer, warp) in self.layers.iter().zip(warps) {
                let Some(warp) = warp else { continue };
                let tex = Tex {
                    texels: &layer.texels,
                    pitch: layer.pitch,
                    sw: sw as u64,
                    sh: sh as u64,
                    simd: self.simd,
                    cubic: filter == Filter::Cubic,
                };
                let opaque = match warp {
                    Warp::Plane(h) => {
                        let (check_w, opaque) = match classify(h, layer, [x0, y0, tw, th], sw, sh) {
                            Class::Skip => {
                                stats.skipped += 1;
                                continue;
                            }
                            // A cubic sample next to a translucent texel may dip below
                            // opaque: only the bilinear kernel may stop the tile early.
                            Class::Draw { check_w, opaque } => (check_w, opaque && !tex.cubic),
                        };
                        for (r, alive_r) in alive[..th].iter_mut().enumerate() {
                            if *alive_r == 0 {
                                continue;
                            }
                            let row = r * TILE_W..r * TILE_W + tw;
                            let mut span = Span {
                                acc: &mut acc[row.clone()],
                                trans: &mut trans[row],
                                opaqued: 0,
                            };
                            draw_layer_row(&tex, layer, h, x0, y0 + r, check_w, &mut span);
                            *alive_r -= span.opaqued;
                        }
                        opaque
                    }
                    Warp::Mesh(mesh) => {
                        let bin = mesh.bin(x0, y0);
                        if bin.is_empty() {
                            stats.skipped += 1;
                            continue;
                        }
                        for &i in bin {
                            let tri = &mesh.tris[i as usize];
                            let (r0, r1) = tri.rows();
                            for (r, alive_r) in alive[..th].iter_mut().enumerate() {
                                let y = (y0 + r) as i64;
                                if *alive_r == 0 || y < r0 || y >= r1 {
                                    continue;
                                }
                                let (a, b) = tri.span(y);
                                let (a, b) = (a.max(x0 as i64), b.min((x0 + tw) as i64));
                                if a >= b {
                                    continue;
                                }
                                let (a, b) = (a as usize - x0, b as usize - x0);
                                let row = r * TILE_W + a..r * TILE_W + b;
                                let mut span = Span {
                                    acc: &mut acc[row.clone()],
                                    trans: &mut trans[row],
                                    opaqued: 0,
                                };
                                draw_layer_row(
                                    &tex,
                                    layer,
                                    &tri.h,
                                    x0 + a,
                                    y as usize,
                                    false,
                                    &mut span,
                                );
                                *alive_r -= span.opaqued;
                            }
                        }
                        false
                    }
                };
                stats.drawn += 1;
                if opaque || alive[..th].iter().all(|&n| n == 0) {
                    stats.opaque_stops += 1;
                    break;
                }
            }
            emit(x0, tw, &acc);
        }
        stats
    }

    /// Renders the view seen by a camera `target` at `pose` into `out` (premultiplied RGBA;
    /// uncovered pixels are transparent). `out` must have the target camera's size.
    pub fn render_into(&self, pose: &Pose, target: &Camera, out: &mut PremulImage) -> RenderStats {
        self.render_into_with(pose, target, out, self.filter)
    }

    /// [`PreparedLayers::render_into`] with `filter` instead of the prepared layers' own.
    pub fn render_into_with(
        &self,
        pose: &Pose,
        target: &Camera,
        out: &mut PremulImage,
        filter: Filter,
    ) -> RenderStats {
        assert_eq!(
            (out.width(), out.height()),
            (target.width, target.height),
            "output image must match the target camera"
        );
        let warps = self.warps(pose, target);
        let width = target.width as usize;
        out.as_bytes_mut()
            .par_chunks_mut(width * 4 * TILE_H)
            .enumerate()
            .map(|(band, bytes)| {
                let th = bytes.len() / (width * 4);
                self.render_band(&warps, width, band * TILE_H, th, filter, |x0, tw, acc| {
                    for r in 0..th {
                        let dst = &mut bytes[(r * width + x0) * 4..(r * width + x0 + tw) * 4];
                        pack_row(&acc[r * TILE_W..r * TILE_W + tw], dst, self.simd);
                    }
                })
            })
            .reduce(RenderStats::default, |a, b| a + b)
    }

    /// Renders the view at `pose` with the reference camera into a new image.
    pub fn render(&self, pose: &Pose) -> PremulImage {
        let cam = self.camera;
        let mut out = PremulImage::new(cam.width, cam.height);
        self.render_into(pose, &cam, &mut out);
        out
    }

    /// Renders into `f32` premultiplied RGBA in `[0, 1]` without 8-bit output rounding (for
    /// tests and metrics).
    pub fn render_f32(&self, pose: &Pose, target: &Camera) -> Vec<[f32; 4]> {
        let warps = self.warps(pose, target);
        let width = target.width as usize;
        let mut out = vec![[0f32; 4]; width * target.height as usize];
        out.par_chunks_mut(width * TILE_H)
            .enumerate()
            .for_each(|(band, px)| {
                let th = px.len() / width;
                self.render_band(
                    &warps,
                    width,
                    band * TILE_H,
                    th,
                    self.filter,
                    |x0, tw, acc| {
                        for r in 0..th {
                            for (d, s) in px[r * width + x0..r * width + x0 + tw]
                                .iter_mut()
                                .zip(&acc[r * TILE_W..r * TILE_W + tw])
                            {
                                // Accumulator lanes are R, B, G, A.
                                *d = [s[0], s[2], s[1], s[3]].map(|v| v / 255.0);
                            }
                        }
                    },
                );
            });
        out
    }
}
