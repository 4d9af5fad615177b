//! Per-pixel work of a P-frame, written for speed: row-parallel, the grid maps interpolated
//! once per row and stepped in 16.16 fixed point along each grid interval, layer samples in
//! 8-bit fixed point (as the renderer does), one fused pass for everything that looks at all
//! layers of a pixel.

use cpsl_core::{resample, PremulImage};
use rayon::prelude::*;

/// Side of the blocks in which [`Occupancy`] records content.
const BLOCK: usize = 8;

/// Where an image holds content (alpha > 0), per `BLOCK x BLOCK` block, as a summed-area
/// table so that any rectangle is answered in constant time.
struct Occupancy {
    bw: usize,
    bh: usize,
    sat: Vec<u32>,
}

impl Occupancy {
    fn new(rgba: &[u8], w: usize, h: usize) -> Self {
        let (bw, bh) = (w.div_ceil(BLOCK), h.div_ceil(BLOCK));
        let rows: Vec<Vec<bool>> = (0..bh)
            .into_par_iter()
            .map(|by| {
                let mut occ = vec![false; bw];
                for y in by * BLOCK..((by + 1) * BLOCK).min(h) {
                    let row = &rgba[y * w * 4..(y + 1) * w * 4];
                    for (bx, block) in row.chunks(BLOCK * 4).enumerate() {
                        occ[bx] |= block.iter().skip(3).step_by(4).any(|&a| a != 0);
                    }
                }
                occ
            })
            .collect();
        let mut sat = vec![0u32; (bw + 1) * (bh + 1)];
        for (by, occ) in rows.iter().enumerate() {
            let mut run = 0;
            for (bx, &o) in occ.iter().enumerate() {
                run += o as u32;
                sat[(by + 1) * (bw + 1) + bx + 1] = sat[by * (bw + 1) + bx + 1] + run;
            }
        }
        Self { bw, bh, sat }
    }

    fn is_empty(&self) -> bool {
        self.sat[self.sat.len() - 1] == 0
    }

    /// Whether any pixel in `[x0, x1] x [y0, y1]` (clamped to the image) holds content.
    fn any(&self, x0: f32, x1: f32, y0: f32, y1: f32) -> bool {
        let block = |v: f32, n: usize| ((v.max(0.0) as usize) / BLOCK).min(n - 1);
        let (bx0, bx1) = (block(x0, self.bw), block(x1, self.bw) + 1);
        let (by0, by1) = (block(y0, self.bh), block(y1, self.bh) + 1);
        let at = |x: usize, y: usize| self.sat[y * (self.bw + 1) + x];
        at(bx1, by1) + at(bx0, by0) > at(bx0, by1) + at(bx1, by0)
    }
}

/// An I-frame layer prepared once for the warps of its whole GOP: texels (RGBA8, R in the
/// low byte) with a one-pixel border that repeats the edge, so that all four taps of any
/// position within half a pixel of the image lie inside and the edge is clamped; and where
/// the layer holds content.
pub(crate) struct KeyLayer {
    texels: Vec<u32>,
    w: usize,
    h: usize,
    occupancy: Occupancy,
}

impl KeyLayer {
    pub(crate) fn new(img: &PremulImage) -> Self {
        let (w, h) = (img.width() as usize, img.height() as usize);
        let src = img.as_bytes();
        let pitch = w + 2;
        let mut texels = vec![0u32; pitch * (h + 2)];
        texels
            .par_chunks_mut(pitch)
            .enumerate()
            .for_each(|(py, row)| {
                let y = py.clamp(1, h) - 1;
                for (px, t) in row.iter_mut().enumerate() {
                    let i = (y * w + px.clamp(1, w) - 1) * 4;
                    *t = u32::from_le_bytes([src[i], src[i + 1], src[i + 2], src[i + 3]]);
                }
            });
        Self {
            texels,
            w,
            h,
            occupancy: Occupancy::new(src, w, h),
        }
    }
}

/// The bilinear blend of four RGBA pixels (top left, top right, bottom left, bottom right)
/// with 8-bit weights `ax`, `ay` ([`cpsl_core::resample::bilerp`]), packed back into RGBA8.
#[inline(always)]
fn bilinear(taps: [u32; 4], ax: u64, ay: u64) -> u32 {
    resample::pack(resample::bilerp(taps[0], taps[1], taps[2], taps[3], ax, ay))
}

/// Pixels `[x0, x1)` of a row whose grid weights are linear in x: grid nodes `c0` and `c1`,
/// the weight of `c1` at `x0` and its change per pixel (0 where the border clamps it).
struct Segment {
    x0: usize,
    x1: usize,
    c0: usize,
    c1: usize,
    f0: f32,
    df: f32,
    clamped: bool,
}

/// Segments per group of a row (see [`RowGrid`]).
const GROUP: usize = 8;

/// Up to `GROUP` consecutive segments of a row (`segs[first..first + len]`), with their
/// weights laid out for straight-line code over the group (0 past its end).
struct Group {
    first: usize,
    len: usize,
    f0: [f32; GROUP],
    df: [f32; GROUP],
}

/// The segments of a row of `n` pixels over a grid of `grid` nodes (pixel centres mapped to
/// grid coordinates, clamped to the outer nodes).
fn segments(n: usize, grid: usize) -> Vec<Segment> {
    let s = grid as f32 / n as f32;
    let last = (grid - 1) as f32;
    let mut out: Vec<Segment> = Vec::new();
    for x in 0..n {
        let g = (x as f32 + 0.5) * s - 0.5;
        let clamped = !(0.0..=last).contains(&g);
        let g = g.clamp(0.0, last);
        let c0 = (g.floor() as usize).min(grid.saturating_sub(2));
        match out.last_mut() {
            Some(seg) if seg.c0 == c0 && seg.clamped == clamped => seg.x1 = x + 1,
            _ => out.push(Segment {
                x0: x,
                x1: x + 1,
                c0,
                c1: (c0 + 1).min(grid - 1),
                f0: g - c0 as f32,
                df: if clamped { 0.0 } else { s },
                clamped,
            }),
        }
    }
    out
}

/// How a `w x h` frame's pixels interpolate a `gw x gh` grid map (bilinearly), the same for
/// every layer: the segments of a row, taken in groups, and per pixel row its two grid rows
/// and the weight of the second.
pub(crate) struct RowGrid {
    w: usize,
    h: usize,
    gw: usize,
    gh: usize,
    segs: Vec<Segment>,
    groups: Vec<Group>,
    rows: Vec<(usize, usize, f32)>,
}

impl RowGrid {
    pub(crate) fn new((w, h): (usize, usize), (gw, gh): (usize, usize)) -> Self {
        let segs = segments(w, gw);
        // Rows use the same construction along y.
        let rows = segments(h, gh)
            .iter()
            .flat_map(|s| (s.x0..s.x1).map(move |y| (s.c0, s.c1, s.f0 + s.df * (y - s.x0) as f32)))
            .collect();
        let groups = (0..segs.len())
            .step_by(GROUP)
            .map(|first| {
                let len = GROUP.min(segs.len() - first);
                let (mut f0, mut df) = ([0f32; GROUP], [0f32; GROUP]);
                for ((f, d), seg) in f0.iter_mut().zip(&mut df).zip(&segs[first..first + len]) {
                    (*f, *d) = (seg.f0, seg.df);
                }
                Group { first, len, f0, df }
            })
            .collect();
        Self {
            w,
            h,
            gw,
            gh,
            segs,
            groups,
            rows,
        }
    }
}

/// Layer `l` of the I-frame (`key`) carried along its `map` (on the [`RowGrid`]'s grid,
/// bilinearly interpolated), row by row; see [`LayerWarp::row`].
pub(crate) struct LayerWarp<'a> {
    key: &'a KeyLayer,
    map: &'a [f32],
    l: usize,
    /// Per band of pixel rows between two grid rows, per group of segments: whether the
    /// group's positions (within the hull of the grid nodes they interpolate) may reach
    /// content. `None`: the layer is empty.
    live: Option<Vec<Vec<bool>>>,
}

/// Per-task buffers of [`LayerWarp::row`].
#[derive(Default)]
pub(crate) struct RowScratch {
    lx: Vec<f32>,
    ly: Vec<f32>,
    xs: Vec<i32>,
    ys: Vec<i32>,
}

impl<'a> LayerWarp<'a> {
    pub(crate) fn new(key: &'a KeyLayer, map: &'a [f32], grid: &RowGrid, l: usize) -> Self {
        let (gw, gh) = (grid.gw, grid.gh);
        let live = (!key.occupancy.is_empty()).then(|| {
            (0..gh)
                .map(|g| {
                    let band = [g, (g + 1).min(gh - 1)];
                    grid.groups
                        .iter()
                        .map(|group| {
                            let nodes = grid.segs[group.first].c0
                                ..=grid.segs[group.first + group.len - 1].c1;
                            let hull = |c: usize| {
                                band.iter()
                                    .flat_map(|&r| {
                                        nodes.clone().map(move |n| map[(r * gw + n) * 2 + c])
                                    })
                                    .fold((f32::INFINITY, f32::NEG_INFINITY), |(lo, hi), p| {
                                        (lo.min(p), hi.max(p))
                                    })
                            };
                            let ((x0, x1), (y0, y1)) = (hull(0), hull(1));
                            key.occupancy.any(x0, x1 + 1.0, y0, y1 + 1.0)
                        })
                        .collect()
                })
                .collect()
        });
        Self { key, map, l, live }
    }

    /// Row `y` of the carried layer (bilinear, 1/256 pixel, transparent where a position lies
    /// more than half a pixel outside the image) into `row` (RGBA, zero on entry); per pixel
    /// with content, `hid` says whether that position was hidden behind a nearer layer in the
    /// I-frame (`owner < l`; false on entry). A live group's positions are all written to
    /// `scratch` before they are read (a group's segments cover its pixels without gaps).
    pub(crate) fn row(
        &self,
        grid: &RowGrid,
        y: usize,
        owner: &[u8],
        row: &mut [u8],
        hid: &mut [bool],
        scratch: &mut RowScratch,
    ) {
        let Some(live) = &self.live else {
            return;
        };
        let (g0, g1, fy) = grid.rows[y];
        let live = &live[g0];
        if !live.iter().any(|&v| v) {
            return;
        }
        let gw = grid.gw;
        let RowScratch { lx, ly, xs, ys } = scratch;
        xs.resize(grid.w, 0);
        ys.resize(grid.w, 0);
        let map = self.map;
        let (a, b) = (&map[g0 * gw * 2..][..gw * 2], &map[g1 * gw * 2..][..gw * 2]);
        lx.resize(gw, 0.0);
        ly.resize(gw, 0.0);
        let nodes = a.chunks_exact(2).zip(b.chunks_exact(2));
        for ((x, y), (a, b)) in lx.iter_mut().zip(ly.iter_mut()).zip(nodes) {
            *x = a[0] + (b[0] - a[0]) * fy;
            *y = a[1] + (b[1] - a[1]) * fy;
        }
        for (group, _) in grid.groups.iter().zip(live).filter(|(_, &v)| v) {
            // Positions (1/256 px, rounded) of the group's pixels, stepped in 16.16 fixed
            // point along each segment: first every segment's start and step (straight-line
            // code over the group, which the compiler vectorises), then its pixels.
            let segs = &grid.segs[group.first..group.first + group.len];
            let (gx0, gx1) = (segs[0].x0, segs[segs.len() - 1].x1);
            let ends = |v: &[f32]| {
                let (mut a, mut b) = ([0f32; GROUP], [0f32; GROUP]);
                for ((a, b), seg) in a.iter_mut().zip(&mut b).zip(segs) {
                    (*a, *b) = (v[seg.c0], v[seg.c1]);
                }
                (a, b)
            };
            let ((ax, bx), (ay, by)) = (ends(lx), ends(ly));
            // 16.16 fixed point (truncated: no libm call on the baseline target), clamped so
            // that no step overflows; positions clamped that far out fail the range test
            // anyway.
            let pos = |v: f32| (v * 65536.0).clamp(-(1 << 29) as f32, (1 << 29) as f32) as i32;
            let step = |v: f32| (v * 65536.0).clamp(-(1 << 24) as f32, (1 << 24) as f32) as i32;
            let (mut x0, mut y0, mut sx, mut sy) =
                ([0i32; GROUP], [0; GROUP], [0; GROUP], [0; GROUP]);
            for i in 0..GROUP {
                let (dx, dy) = (bx[i] - ax[i], by[i] - ay[i]);
                x0[i] = pos(ax[i] + dx * group.f0[i]) + 128;
                y0[i] = pos(ay[i] + dy * group.f0[i]) + 128;
                sx[i] = step(dx * group.df[i]);
                sy[i] = step(dy * group.df[i]);
            }
            for (i, seg) in segs.iter().enumerate() {
                let (mut x, mut y) = (x0[i], y0[i]);
                for (a, b) in xs[seg.x0..seg.x1].iter_mut().zip(&mut ys[seg.x0..seg.x1]) {
                    *a = x >> 8;
                    *b = y >> 8;
                    x += sx[i];
                    y += sy[i];
                }
            }
            let (xs, ys) = (&xs[gx0..gx1], &ys[gx0..gx1]);
            let (out, hid) = (&mut row[gx0 * 4..gx1 * 4], &mut hid[gx0..gx1]);
            sample_span(self.key, xs, ys, out, hid, owner, self.l);
        }
    }
}

/// The I-frame's layers (`keys`) carried along their `maps` (on `grid`'s grid) and settled
/// ([`settle_row`]) row by row, each row's layers warped and settled while they are in
/// cache. `key_owner` is the I-frame's owner, `depth` the new frame's, `spans` each layer's
/// depth bounds. Returns the carried layers and the new owner.
#[allow(clippy::too_many_arguments)]
pub(crate) fn warp_and_settle(
    keys: &[KeyLayer],
    maps: &[Vec<f32>],
    grid: &RowGrid,
    key_owner: &[u8],
    depth: &[f32],
    spans: &[(f32, f32)],
    rgb: &[u8],
    refresh: bool,
) -> (Vec<PremulImage>, Vec<u8>) {
    let (w, h, k) = (grid.w, grid.h, keys.len());
    let warps: Vec<LayerWarp> = (keys.par_iter().zip(maps).enumerate())
        .map(|(l, (key, map))| LayerWarp::new(key, map, grid, l))
        .collect();
    // Allocated on rayon's workers: allocated on the calling thread, glibc hands out fresh
    // pages whose faults cost the pass more than twice its time.
    let mut images: Vec<PremulImage> = (0..k)
        .into_par_iter()
        .map(|_| PremulImage::new(w as u32, h as u32))
        .collect();
    let mut rows: Vec<Vec<&mut [u8]>> = (0..h).map(|_| Vec::with_capacity(k)).collect();
    for img in images.iter_mut() {
        for (r, chunk) in rows.iter_mut().zip(img.as_bytes_mut().chunks_mut(w * 4)) {
            r.push(chunk);
        }
    }
    let mut owner = vec![0u8; w * h];
    rows.into_par_iter()
        .zip(owner.par_chunks_mut(w))
        .enumerate()
        .for_each_init(
            || (RowScratch::default(), vec![false; k * w], vec![0u32; w]),
            |(scratch, hidden, cover), (y, (mut layers, own))| {
                hidden.fill(false);
                for ((warp, row), hid) in warps.iter().zip(&mut layers).zip(hidden.chunks_mut(w)) {
                    warp.row(grid, y, key_owner, row, hid, scratch);
                }
                let (z, rgb) = (&depth[y * w..(y + 1) * w], &rgb[y * w * 3..(y + 1) * w * 3]);
                settle_row(&mut layers, hidden, z, spans, rgb, refresh, cover, own);
            },
        );
    (images, owner)
}

/// Samples `key` at positions `xs`, `ys` (1/256 px) into `out` (RGBA, one pixel per
/// position): transparent where a position lies more than half a pixel outside the image,
/// bilinear inside (the edge clamped). Where a sample has content, `hid` says whether the
/// I-frame showed a nearer layer than `l` there (`owner`). The AVX2 kernel computes the same
/// bits eight pixels at a time where the CPU has it.
fn sample_span(
    key: &KeyLayer,
    xs: &[i32],
    ys: &[i32],
    out: &mut [u8],
    hid: &mut [bool],
    owner: &[u8],
    l: usize,
) {
    let mut done = 0;
    #[cfg(target_arch = "x86_64")]
    if xs.len() >= 8 && crate::simd::available() {
        done = crate::simd::sample_span(&key.texels, key.w, key.h, xs, ys, out, hid, owner, l);
    }
    sample_scalar(
        key,
        &xs[done..],
        &ys[done..],
        &mut out[done * 4..],
        &mut hid[done..],
        owner,
        l,
    );
}

/// Whether the I-frame's owner at the pixel nearest `(xi, yi)` (1/256 px) is nearer than `l`.
#[inline(always)]
fn hidden_at(xi: i32, yi: i32, w: usize, h: usize, owner: &[u8], l: usize) -> bool {
    let rx = (((xi + 128) >> 8).max(0) as usize).min(w - 1);
    let ry = (((yi + 128) >> 8).max(0) as usize).min(h - 1);
    (owner[ry * w + rx] as usize) < l
}

/// The scalar kernel of [`sample_span`].
fn sample_scalar(
    key: &KeyLayer,
    xs: &[i32],
    ys: &[i32],
    out: &mut [u8],
    hid: &mut [bool],
    owner: &[u8],
    l: usize,
) {
    let (w, h) = (key.w, key.h);
    let pitch = w + 2;
    let (lim_x, lim_y) = ((w * 256) as i32 - 128, (h * 256) as i32 - 128);
    for (x, (&xi, &yi)) in xs.iter().zip(ys).enumerate() {
        if xi < -128 || yi < -128 || xi > lim_x || yi > lim_y {
            continue;
        }
        // Within half a pixel of the image: the taps lie in the padded texture.
        let (tx, ty) = ((xi >> 8) + 1, (yi >> 8) + 1);
        let i = ty as usize * pitch + tx as usize;
        let t = &key.texels[i..i + pitch + 2];
        let taps = [t[0], t[1], t[pitch], t[pitch + 1]];
        // Premultiplied: alpha 0 is an all-zero pixel.
        if taps[0] | taps[1] | taps[2] | taps[3] == 0 {
            continue;
        }
        let v = bilinear(taps, (xi & 255) as u64, (yi & 255) as u64);
        out[x * 4..x * 4 + 4].copy_from_slice(&v.to_le_bytes());
        hid[x] = hidden_at(xi, yi, w, h, owner, l);
    }
}

/// Over every pixel of a row of the carried layers (`layers`, front to back):
/// - hidden content (`hidden`, a row per layer) that nothing in front covers (cover below
///   1/2) is dropped unless the new depth (`z`) lies within the layer's span (`spans[l]`, z
///   bounds), so that the layers behind show where the guess was wrong (the back layer is
///   opaque everywhere and keeps its own);
/// - the owner (`own`) is the nearest layer with alpha >= 1/2 (the back layer where none
///   is);
/// - with `refresh`, the pixels the owner shows fully opaque take the new frame's colour
///   `rgb`.
///
/// Layer by layer along the row (each pixel still sees its layers front to back), with the
/// pixels' coverage so far in `cover`.
#[allow(clippy::too_many_arguments)]
fn settle_row(
    layers: &mut [&mut [u8]],
    hidden: &[bool],
    z: &[f32],
    spans: &[(f32, f32)],
    rgb: &[u8],
    refresh: bool,
    cover: &mut [u32],
    own: &mut [u8],
) {
    let (k, w) = (layers.len(), own.len());
    cover.fill(0); // 0..=255 * 255
    own.fill((k - 1) as u8);
    for (l, row) in layers[..k - 1].iter_mut().enumerate() {
        let hid = &hidden[l * w..(l + 1) * w];
        let (lo, hi) = spans[l];
        let pixels = row.chunks_exact_mut(4).zip(hid).zip(z);
        for (((px, &hid), &z), (c, o)) in pixels.zip(cover.iter_mut().zip(&mut *own)) {
            let a = px[3] as u32;
            if a == 0 {
                continue;
            }
            if hid && *c * 2 < 255 * 255 && !(z >= lo && z <= hi) {
                px.fill(0);
                continue;
            }
            *c += (255 * 255 - *c) * a / 255;
            if a >= 128 && *o as usize == k - 1 {
                *o = l as u8;
            }
        }
    }
    if refresh {
        for (x, (&o, c)) in own.iter().zip(rgb.chunks_exact(3)).enumerate() {
            let px = &mut layers[o as usize][x * 4..x * 4 + 4];
            if px[3] == 255 {
                px[..3].copy_from_slice(c);
            }
        }
    }
}

/// Median of each label's depths (`None` for a label without pixels), see
/// [`ln_depth_quantiles`].
pub(crate) fn median_depths(owner: &[u8], ln_depth: &[f32], k: usize) -> Vec<Option<f64>> {
    ln_depth_quantiles(owner, ln_depth, k, [0.5])
        .into_iter()
        .map(|q| q.map(|[m]| (m as f64).exp()))
        .collect()
}

/// Quantiles `qs` (increasing, below 1) of each label's `ln z` (`None` for a label without
/// pixels), from a
/// histogram of `ln_depth` (non-finite values ignored) in 4096 bins over the frame's range (to
/// 1/4096 of that range).
pub(crate) fn ln_depth_quantiles<const N: usize>(
    owner: &[u8],
    ln_depth: &[f32],
    k: usize,
    qs: [f32; N],
) -> Vec<Option<[f32; N]>> {
    const BINS: usize = 4096;
    let valid = |v: f32| v.is_finite();
    let (lo, hi) = ln_depth
        .par_iter()
        .filter(|&&v| valid(v))
        .map(|&v| (v, v))
        .reduce(
            || (f32::INFINITY, f32::NEG_INFINITY),
            |a, b| (a.0.min(b.0), a.1.max(b.1)),
        );
    if lo > hi {
        return vec![None; k];
    }
    let scale = (BINS - 1) as f32 / (hi - lo).max(1e-6);
    let counts = owner
        .par_chunks(1 << 14)
        .zip(ln_depth.par_chunks(1 << 14))
        .fold(
            || vec![0u32; k * BINS],
            |mut acc, (o, d)| {
                for (&o, &v) in o.iter().zip(d) {
                    if valid(v) {
                        acc[o as usize * BINS + ((v - lo) * scale) as i32 as usize] += 1;
                    }
                }
                acc
            },
        )
        .reduce_with(|mut a, b| {
            a.iter_mut().zip(&b).for_each(|(x, y)| *x += y);
            a
        })
        .unwrap_or_else(|| vec![0; k * BINS]);
    counts
        .chunks(BINS)
        .map(|hist| {
            let n: u32 = hist.iter().sum();
            if n == 0 {
                return None;
            }
            let mut cum = hist.iter().scan(0u32, |seen, &c| {
                *seen += c;
                Some(*seen)
            });
            let (mut bin, mut seen) = (0, 0);
            Some(qs.map(|q| {
                // Quantiles in increasing order continue the same walk.
                while seen as f32 <= q * n as f32 {
                    seen = cum.next().expect("the last bin holds all n");
                    bin += 1;
                }
                (bin as f32 - 0.5) / scale + lo
            }))
        })
        .collect()
}

/// Per layer, the mask overlap and boundary similarity of the layer's pixels (`owner`) with
/// the region whose depth fits the layer (`|ln z - lz[l](x, y)| <= tolerance`, `ln` the log depth;
/// see the crate documentation). One row-parallel pass for all layers.
pub(crate) fn agreements(
    owner: &[u8],
    ln: &[f32],
    lz: &[LogDepth],
    tolerance: f32,
    w: usize,
    h: usize,
) -> Vec<(f32, f32)> {
    let k = lz.len();
    let fits = |x: usize, y: usize, l: usize| (ln[y * w + x] - lz[l].at(x, y)).abs() <= tolerance;
    // Whether a pixel of the 3x3 block around (x, y) lies on the boundary of the region whose
    // depth fits layer l (4-neighbourhood). Each pixel's fit is found at most once: `memo`
    // holds those of the 5x5 block around (x, y) (0 not yet known, 1 no, 2 yes).
    let near_depth_edge = |l: usize, x: usize, y: usize| {
        let mut memo = [[0u8; 5]; 5];
        let mut fit = |xx: usize, yy: usize| {
            let m = &mut memo[yy + 2 - y][xx + 2 - x];
            if *m == 0 {
                *m = 1 + fits(xx, yy, l) as u8;
            }
            *m == 2
        };
        for yy in y.saturating_sub(1)..(y + 2).min(h) {
            for xx in x.saturating_sub(1)..(x + 2).min(w) {
                let me = fit(xx, yy);
                if (xx > 0 && fit(xx - 1, yy) != me)
                    || (xx + 1 < w && fit(xx + 1, yy) != me)
                    || (yy > 0 && fit(xx, yy - 1) != me)
                    || (yy + 1 < h && fit(xx, yy + 1) != me)
                {
                    return true;
                }
            }
        }
        false
    };
    // Per layer: area, depth agreement, boundary pixels, boundary pixels near a depth edge.
    let sums = (0..h)
        .into_par_iter()
        .fold(
            || vec![[0u32; 4]; k],
            |mut acc, y| {
                let row = &owner[y * w..(y + 1) * w];
                let up = if y > 0 {
                    &owner[(y - 1) * w..y * w]
                } else {
                    row
                };
                let down = if y + 1 < h {
                    &owner[(y + 1) * w..(y + 2) * w]
                } else {
                    row
                };
                // Area and depth agreement run by run of one layer along the row.
                let ln_row = &ln[y * w..(y + 1) * w];
                for (o, xs) in cpsl_layering::grid::label_runs(row) {
                    let s = &mut acc[o as usize];
                    s[0] += xs.len() as u32;
                    s[1] += lz[o as usize].fits_along(y, xs.start, &ln_row[xs], tolerance);
                }
                for (x, &o) in row.iter().enumerate() {
                    let l = o as usize;
                    let s = &mut acc[l];
                    // On the layer's boundary: a 4-neighbour (rows out of the image stand in
                    // for themselves) belongs to another layer.
                    let across = (x > 0 && row[x - 1] != o)
                        || (x + 1 < w && row[x + 1] != o)
                        || up[x] != o
                        || down[x] != o;
                    if across {
                        s[2] += 1;
                        s[3] += near_depth_edge(l, x, y) as u32;
                    }
                }
                acc
            },
        )
        .reduce(
            || vec![[0u32; 4]; k],
            |mut a, b| {
                for (x, y) in a.iter_mut().zip(&b) {
                    for i in 0..4 {
                        x[i] += y[i];
                    }
                }
                a
            },
        );
    let ratio = |a: u32, b: u32| if b > 0 { a as f32 / b as f32 } else { 1.0 };
    sums.iter()
        .map(|s| (ratio(s[1], s[0]), ratio(s[3], s[2])))
        .collect()
}

/// Share of 4-neighbour pairs across layer boundaries whose depth order contradicts the layer
/// order by more than 2 %.
pub(crate) fn crack_rate(owner: &[u8], depth: &[f32], w: usize, h: usize) -> f32 {
    let (pairs, bad) = (0..h)
        .into_par_iter()
        .map(|y| {
            let (mut pairs, mut bad) = (0u32, 0u32);
            // Each pixel's label and depth, paired with its right and its lower neighbour's.
            let mut count = |a: &[u8], za: &[f32], b: &[u8], zb: &[f32]| {
                for ((&p, &q), (&zp, &zq)) in a.iter().zip(b).zip(za.iter().zip(zb)) {
                    if p != q {
                        pairs += 1;
                        let (near, far) = if p < q { (zp, zq) } else { (zq, zp) };
                        bad += (near > far * 1.02) as u32;
                    }
                }
            };
            let (row, z) = (&owner[y * w..(y + 1) * w], &depth[y * w..(y + 1) * w]);
            count(&row[..w - 1], &z[..w - 1], &row[1..], &z[1..]);
            if y + 1 < h {
                let (below, zb) = (
                    &owner[(y + 1) * w..(y + 2) * w],
                    &depth[(y + 1) * w..(y + 2) * w],
                );
                count(row, z, below, zb);
            }
            (pairs, bad)
        })
        .reduce(|| (0, 0), |a, b| (a.0 + b.0, a.1 + b.1));
    if pairs == 0 {
        0.0
    } else {
        bad as f32 / pairs as f32
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn medians_match_sorting_within_a_bin() {
        let (w, h, k) = (97, 61, 3);
        let owner: Vec<u8> = (0..w * h).map(|p| ((p * 7) % 5 % k) as u8).collect();
        let depth: Vec<f32> = (0..w * h)
            .map(|p| 1.0 + ((p * 2654435761usize) % 1000) as f32 / 100.0)
            .collect();
        let ln: Vec<f32> = depth.iter().map(|z| z.ln()).collect();
        let got = median_depths(&owner, &ln, k);
        for (l, m) in got.iter().enumerate() {
            let mut v: Vec<f32> = (0..w * h)
                .filter(|&p| owner[p] as usize == l)
                .map(|p| depth[p])
                .collect();
            v.sort_by(f32::total_cmp);
            let want = v[v.len() / 2] as f64;
            let m = m.expect("pixels");
            // One bin of ln z over [ln 1, ln 11].
            assert!(
                (m / want).ln().abs() <= 11f64.ln() / 4095.0,
                "{m} vs {want}"
            );
        }
        assert_eq!(median_depths(&[0, 0], &[0.7, 0.7], 2)[1], None);
        // Other quantiles walk the same histogram.
        let qs = ln_depth_quantiles(&owner, &ln, k, [0.05, 0.5, 0.95]);
        for (l, q) in qs.iter().enumerate() {
            let mut v: Vec<f32> = (0..w * h)
                .filter(|&p| owner[p] as usize == l)
                .map(|p| ln[p])
                .collect();
            v.sort_by(f32::total_cmp);
            let q = q.expect("pixels");
            for (got, f) in q.iter().zip([0.05, 0.5, 0.95]) {
                let want = v[(f * v.len() as f32) as usize];
                assert!((got - want).abs() <= 11f32.ln() / 4095.0, "{got} vs {want}");
            }
        }
    }

    #[test]
    fn sampling_is_the_same_with_and_without_simd() {
        let (w, h) = (53usize, 31usize);
        let mut seed = 11u64;
        let mut next = move || {
            seed = seed
                .wrapping_mul(6364136223846793005)
                .wrapping_add(1442695040888963407);
            (seed >> 33) as u32
        };
        let mut img = PremulImage::new(w as u32, h as u32);
        for y in 0..h as u32 {
            for x in 0..w as u32 {
                // Transparent holes, partial and full alpha.
                let a = [0, 0, 255, 255, 128, 37][(next() % 6) as usize] as u32;
                let c = |v: u32| (v % (a + 1)) as u8;
                img.set_pixel(x, y, [c(next()), c(next()), c(next()), a as u8]);
            }
        }
        let key = KeyLayer::new(&img);
        let owner: Vec<u8> = (0..w * h).map(|_| (next() % 4) as u8).collect();
        let n = 4000;
        // Positions over and well beyond the image, in 1/256 px: scattered, and in runs of
        // near-unit steps (the kernel's contiguous case) that also cross the image's edges.
        let scattered: (Vec<i32>, Vec<i32>) = (0..n)
            .map(|_| {
                let x = (next() % ((w as u32 + 4) * 256)) as i32 - 512;
                (x, (next() % ((h as u32 + 4) * 256)) as i32 - 512)
            })
            .unzip();
        let mut runs = (Vec::new(), Vec::new());
        while runs.0.len() < n {
            let (mut x, mut y) = (
                (next() % ((w as u32 + 4) * 256)) as i32 - 512,
                (next() % ((h as u32 + 4) * 256)) as i32 - 512,
            );
            let (dx, dy) = (192 + (next() % 160) as i32, (next() % 9) as i32 - 4);
            for _ in 0..8 + next() % 40 {
                runs.0.push(x);
                runs.1.push(y);
                x += dx;
                y += dy;
            }
        }
        for (xs, ys) in [scattered, runs] {
            let n = xs.len();
            let (mut a, mut ha) = (vec![0u8; n * 4], vec![false; n]);
            let (mut b, mut hb) = (vec![0u8; n * 4], vec![false; n]);
            sample_scalar(&key, &xs, &ys, &mut a, &mut ha, &owner, 2);
            sample_span(&key, &xs, &ys, &mut b, &mut hb, &owner, 2);
            assert_eq!(a, b);
            assert_eq!(ha, hb);
            assert!(a.iter().any(|&v| v != 0) && a.contains(&0));
        }
        #[cfg(target_arch = "x86_64")]
        if !crate::simd::available() {
            eprintln!("no AVX2 here: only the scalar kernel was exercised");
        }
    }

    #[test]
    fn segments_reproduce_the_grid_weights() {
        for (n, grid) in [(1280, 320), (720, 180), (37, 11), (5, 2), (9, 1)] {
            let segs = segments(n, grid);
            assert_eq!(segs.first().map(|s| s.x0), Some(0));
            assert_eq!(segs.last().map(|s| s.x1), Some(n));
            let s = grid as f32 / n as f32;
            for seg in &segs {
                for x in seg.x0..seg.x1 {
                    let g = ((x as f32 + 0.5) * s - 0.5).clamp(0.0, (grid - 1) as f32);
                    let f = seg.f0 + seg.df * (x - seg.x0) as f32;
                    let got = seg.c0 as f32 + f * (seg.c1 - seg.c0) as f32;
                    assert!((got - g).abs() < 1e-3, "{n} {grid} {x}: {got} vs {g}");
                }
            }
        }
    }

    #[test]
    fn identity_warp_keeps_the_layer() {
        let (w, h, gw, gh) = (40usize, 30usize, 10usize, 8usize);
        let mut img = PremulImage::new(w as u32, h as u32);
        for y in 5..20 {
            for x in 8..30 {
                img.set_pixel(x, y, [(x * 4) as u8, (y * 5) as u8, 60, 200]);
            }
        }
        let (sx, sy) = (w as f32 / gw as f32, h as f32 / gh as f32);
        let map: Vec<f32> = (0..gw * gh)
            .flat_map(|g| {
                [
                    ((g % gw) as f32 + 0.5) * sx - 0.5,
                    ((g / gw) as f32 + 0.5) * sy - 0.5,
                ]
            })
            .collect();
        let owner = vec![1u8; w * h];
        let key = KeyLayer::new(&img);
        let grid = RowGrid::new((w, h), (gw, gh));
        let warp = |l: usize| {
            let warp = LayerWarp::new(&key, &map, &grid, l);
            let mut out = PremulImage::new(w as u32, h as u32);
            let mut hidden = vec![false; w * h];
            let mut scratch = RowScratch::default();
            let rows = out
                .as_bytes_mut()
                .chunks_mut(w * 4)
                .zip(hidden.chunks_mut(w));
            for (y, (row, hid)) in rows.enumerate() {
                warp.row(&grid, y, &owner, row, hid, &mut scratch);
            }
            (out, hidden)
        };
        let (out, hidden) = warp(1);
        // The grid's border clamps the map within half a grid cell of the edge; inside it the
        // warp is exact.
        for y in 2..h - 2 {
            for x in 3..w - 3 {
                assert_eq!(out.pixel(x as u32, y as u32), img.pixel(x as u32, y as u32));
            }
        }
        assert!(hidden.iter().all(|&h| !h));
        let (_, hidden) = warp(2);
        assert!(hidden[10 * w + 10]);
    }
}

/// A layer's log depth as the agreement test sees it: its reference depth's, its slanted
/// plane's or its mesh's at each pixel.
#[derive(Clone, Debug)]
pub(crate) struct LogDepth {
    /// `ln z_k`.
    lz: f32,
    surface: Surface,
}

/// Where a layer's log depth varies over the image.
#[derive(Clone, Debug)]
enum Surface {
    /// Fronto-parallel: `ln z_k` everywhere.
    Flat,
    /// A slanted plane's inverse depth `a x + b y + c`, its logarithm taken where asked for
    /// (the agreement test asks at a layer's own pixels and around its boundary: a full map per
    /// layer cost a P-frame more than the test itself).
    Plane([f64; 3]),
    /// A mesh's log depth, interpolated where asked for (a full map per layer cost a mesh's
    /// P-frame more than the test itself).
    Mesh(cpsl_core::geometry::GridPixels),
}

impl LogDepth {
    /// Every layer's log depth in `set`.
    pub(crate) fn of(set: &cpsl_core::LayerSet) -> Vec<Self> {
        let cam = set.camera();
        let (w, h) = (cam.width, cam.height);
        set.layers()
            .par_iter()
            .map(|l| Self {
                lz: l.depth.ln() as f32,
                surface: match &l.geometry {
                    cpsl_core::Geometry::Plane => Surface::Flat,
                    g @ cpsl_core::Geometry::Slanted(_) => {
                        Surface::Plane(g.pixel_plane(l.depth, cam).expect("a plane"))
                    }
                    cpsl_core::Geometry::Mesh(g) => {
                        // Log depth interpolated over each triangle from its vertices' (a
                        // logarithm per vertex, not per pixel; within a cell the two differ
                        // by far less than the agreement tolerance).
                        let mut log = (**g).clone();
                        log.inverse_depth
                            .iter_mut()
                            .for_each(|v| *v = -v.max(1e-12).ln());
                        Surface::Mesh(log.pixels(w, h))
                    }
                },
            })
            .collect()
    }

    /// `ln z_k` of the layer's reference depth.
    pub(crate) fn reference(&self) -> f32 {
        self.lz
    }

    /// How many of the pixels `(x0 + i, y)` have `|ln[i] - ln z| <= tolerance`, `ln z` the
    /// surface's at the pixel ([`Self::at`], one surface type per run).
    pub(crate) fn fits_along(&self, y: usize, x0: usize, ln: &[f32], tolerance: f32) -> u32 {
        fn count(ln: &[f32], x0: usize, tolerance: f32, at: impl Fn(usize) -> f32) -> u32 {
            (ln.iter().enumerate())
                .filter(|&(i, &v)| (v - at(x0 + i)).abs() <= tolerance)
                .count() as u32
        }
        match &self.surface {
            Surface::Flat => count(ln, x0, tolerance, |_| self.lz),
            Surface::Plane(_) => count(ln, x0, tolerance, |x| self.at(x, y)),
            Surface::Mesh(log) => count(ln, x0, tolerance, |x| log.at(x, y)),
        }
    }

    /// `ln z` of the layer's surface at pixel `(x, y)`.
    #[inline]
    pub(crate) fn at(&self, x: usize, y: usize) -> f32 {
        match &self.surface {
            Surface::Flat => self.lz,
            Surface::Plane([a, b, c]) => {
                -((a * x as f64 + b * y as f64 + c).max(1e-12) as f32).ln()
            }
            Surface::Mesh(log) => log.at(x, y),
        }
    }
}
