//! The side stream of one segment (`side.bin`): per frame, which layer stream holds each layer,
//! the layer depths, the temporal confidence, the GOP/refresh flags and the Edge-Depth Cache.
//!
//! Layout (little endian), versions 1 and 2:
//!
//! ```text
//! header   magic "CPSLSIDE" | version u16 | reserved u16 | segment u32 | start u32
//!          | frames u32 | streams u16 | reserved u16 | width u32 | height u32 | crc32 u32
//! frame    payload_len u32 | payload | crc32(payload) u32          (repeated `frames` times)
//! payload  index u32 | flags u8 | refresh u8 | layers u8 | reserved u8
//!          | layers x (stream u8 | geometry u8 | reserved 2 | depth f32 | confidence f32
//!                       | track u32 | version 2: plane 3 x f32)
//!          | version 2: per mesh layer, in layer order, a grid
//!          | edc_len u32 | compact EDC
//! grid     step u16 | cols u16 | rows u16 | reference u16 | len u32 | deflate(planes)
//! planes   per vertex (row by row) q - prediction as i16, low bytes then high bytes; q is
//!          round(ln(inverse depth) / GRID_STEP); with reference 0 the prediction is the
//!          vertex to the left (the one above for the first column, 0 for the first vertex),
//!          with reference j + 1 the same vertex of layer j's grid in the previous record
//!          (a mesh of the same size; writers pick the layer with the same track)
//! compact EDC  layers u16 | step f32 | samples u32 | deflate(planes)
//! planes   per sample, field by field: y - previous y (u16, wrapping), x - previous x (u16,
//!          wrapping), front u8, back u8, front offset i8, back offset i8
//! ```
//!
//! Samples come in scan order, so the position deltas are small and the planes deflate well
//! (the raw `edc.bin` layout costs 8 bytes per sample).
//!
//! `geometry` is 0 for the fronto-parallel plane at `depth` (plane all zero), 1 for the
//! slanted plane `m` and 2 for a mesh (plane all zero, its grid after the layer table)
//! ([`cpsl_core::Geometry`]); grids are quantised to [`GRID_STEP`] in log inverse depth
//! (0.1 % of depth). Version 1 has neither (every layer
//! fronto-parallel, `geometry` reserved as 0). Writers use version 1 when every layer of the
//! segment is fronto-parallel, so older players still read such segments.
//!
//! `flags` bit 0 marks an I-frame. `refresh` says why a frame is an I-frame (0 none, 1 first
//! frame, 2 full GOP, 3 low temporal confidence, 4 crack rate). Layers are listed nearest first;
//! `track` is `u32::MAX` where the layer has none. Every field is validated on reading, so a
//! corrupt or truncated stream is an error, never a panic.

use cpsl_core::{DepthGrid, Edc, EdcError, Geometry, RefreshReason, Vec3};
use thiserror::Error;

/// Magic bytes at the start of a side stream.
pub const SIDE_MAGIC: &[u8; 8] = b"CPSLSIDE";
/// Newest side-stream version this build reads and writes.
pub const SIDE_VERSION: u16 = 2;
/// Quantisation step of a mesh grid's log inverse depth.
pub const GRID_STEP: f64 = 1.0 / 1024.0;
/// Most frames one segment may hold.
pub const MAX_SEGMENT_FRAMES: u32 = 100_000;
/// Most layer streams one segment may hold.
pub const MAX_STREAMS: u16 = 64;
const HEADER: usize = 40;
/// Bytes of a layer record per version.
const fn layer_bytes(version: u16) -> usize {
    if version >= 2 {
        28
    } else {
        16
    }
}
const NO_TRACK: u32 = u32::MAX;

/// Why a side stream was rejected.
#[derive(Debug, Error, Clone, PartialEq)]
pub enum SideError {
    /// The header is malformed.
    #[error("side stream header: {0}")]
    Header(String),
    /// A frame record is malformed.
    #[error("side stream frame record {record}: {reason}")]
    Frame {
        /// Record number within the segment.
        record: usize,
        /// What is wrong.
        reason: String,
    },
    /// A frame's Edge-Depth Cache is malformed.
    #[error("side stream frame record {record}: edge-depth cache: {source}")]
    Edc {
        /// Record number within the segment.
        record: usize,
        /// The cache's error.
        source: EdcError,
    },
}

/// The side stream's code of a frame's refresh flag.
fn refresh_code(reason: Option<RefreshReason>) -> u8 {
    match reason {
        None => 0,
        Some(RefreshReason::First) => 1,
        Some(RefreshReason::Gop) => 2,
        Some(RefreshReason::Confidence) => 3,
        Some(RefreshReason::Crack) => 4,
    }
}

/// The refresh flag a side-stream code stands for (`None` for an unknown code).
fn refresh_from_code(c: u8) -> Option<Option<RefreshReason>> {
    Some(match c {
        0 => None,
        1 => Some(RefreshReason::First),
        2 => Some(RefreshReason::Gop),
        3 => Some(RefreshReason::Confidence),
        4 => Some(RefreshReason::Crack),
        _ => return None,
    })
}

/// One layer of one frame.
#[derive(Debug, Clone, PartialEq)]
pub struct SideLayer {
    /// The layer stream (index into the segment's streams) holding its colour and alpha.
    pub stream: u8,
    /// Reference depth in this frame (the plane's for a fronto-parallel layer).
    pub depth: f32,
    /// Its surface (the plane stored as `f32`).
    pub geometry: Geometry,
    /// Temporal confidence in [0, 1].
    pub confidence: f32,
    /// Track identity across frames.
    pub track: Option<u32>,
}

/// One frame's side information.
#[derive(Debug, Clone, PartialEq)]
pub struct SideFrame {
    /// Frame index in the video.
    pub index: u32,
    /// Whether the frame is an I-frame.
    pub intra: bool,
    /// Why it is an I-frame.
    pub refresh: Option<RefreshReason>,
    /// Its layers, nearest first.
    pub layers: Vec<SideLayer>,
    /// Its Edge-Depth Cache (layer indices refer to `layers`).
    pub edc: Edc,
}

/// The side stream of one segment.
#[derive(Debug, Clone, PartialEq)]
pub struct SideStream {
    /// Segment number.
    pub segment: u32,
    /// Index of the segment's first frame.
    pub start: u32,
    /// Number of layer streams of the segment.
    pub streams: u16,
    /// Frame width.
    pub width: u32,
    /// Frame height.
    pub height: u32,
    /// The frames, in order.
    pub frames: Vec<SideFrame>,
}

fn crc(bytes: &[u8]) -> u32 {
    crc32fast::hash(bytes)
}

impl SideStream {
    /// Serialises to the layout above.
    pub fn encode(&self) -> Vec<u8> {
        let slanted = self
            .frames
            .iter()
            .any(|f| f.layers.iter().any(|l| !l.geometry.is_plane()));
        let version: u16 = if slanted { 2 } else { 1 };
        let mut out = Vec::new();
        out.extend_from_slice(SIDE_MAGIC);
        out.extend_from_slice(&version.to_le_bytes());
        out.extend_from_slice(&0u16.to_le_bytes());
        out.extend_from_slice(&self.segment.to_le_bytes());
        out.extend_from_slice(&self.start.to_le_bytes());
        out.extend_from_slice(&(self.frames.len() as u32).to_le_bytes());
        out.extend_from_slice(&self.streams.to_le_bytes());
        out.extend_from_slice(&0u16.to_le_bytes());
        out.extend_from_slice(&self.width.to_le_bytes());
        out.extend_from_slice(&self.height.to_le_bytes());
        let c = crc(&out);
        out.extend_from_slice(&c.to_le_bytes());
        let mut previous: Option<&SideFrame> = None;
        for f in &self.frames {
            let mut p = Vec::new();
            p.extend_from_slice(&f.index.to_le_bytes());
            p.extend_from_slice(&[
                f.intra as u8,
                refresh_code(f.refresh),
                f.layers.len() as u8,
                0,
            ]);
            for l in &f.layers {
                let (tag, plane) = match &l.geometry {
                    Geometry::Plane => (0, [0.0; 3]),
                    Geometry::Slanted(m) => (1, m.0),
                    Geometry::Mesh(_) => (2, [0.0; 3]),
                };
                p.extend_from_slice(&[l.stream, tag, 0, 0]);
                p.extend_from_slice(&l.depth.to_le_bytes());
                p.extend_from_slice(&l.confidence.to_le_bytes());
                p.extend_from_slice(&l.track.unwrap_or(NO_TRACK).to_le_bytes());
                if version >= 2 {
                    for v in plane {
                        p.extend_from_slice(&(v as f32).to_le_bytes());
                    }
                }
            }
            for l in &f.layers {
                if let Geometry::Mesh(g) = &l.geometry {
                    compact_grid(g, reference(l, previous), &mut p);
                }
            }
            previous = Some(f);
            let edc = compact_edc(&f.edc);
            p.extend_from_slice(&(edc.len() as u32).to_le_bytes());
            p.extend_from_slice(&edc);
            out.extend_from_slice(&(p.len() as u32).to_le_bytes());
            out.extend_from_slice(&p);
            out.extend_from_slice(&crc(&p).to_le_bytes());
        }
        out
    }

    /// Parses and validates a side stream: checksums, counts, flags, depths (finite, positive,
    /// strictly increasing), confidences in [0, 1], stream indices, frame indices consecutive
    /// from `start`, and each frame's Edge-Depth Cache against the frame size and layer count.
    pub fn decode(bytes: &[u8]) -> Result<Self, SideError> {
        let head = |s: String| SideError::Header(s);
        if bytes.len() < HEADER {
            return Err(head(format!(
                "{} bytes, at least {HEADER} expected",
                bytes.len()
            )));
        }
        if &bytes[..8] != SIDE_MAGIC {
            return Err(head("not a CPSL side stream (bad magic)".into()));
        }
        let u16_at = |o: usize| u16::from_le_bytes([bytes[o], bytes[o + 1]]);
        let u32_at =
            |o: usize| u32::from_le_bytes([bytes[o], bytes[o + 1], bytes[o + 2], bytes[o + 3]]);
        let version = u16_at(8);
        if version == 0 || version > SIDE_VERSION {
            return Err(head(format!(
                "version {version}, this build reads 1..={SIDE_VERSION}"
            )));
        }
        if u32_at(HEADER - 4) != crc(&bytes[..HEADER - 4]) {
            return Err(head("checksum mismatch".into()));
        }
        let (segment, start, frames) = (u32_at(12), u32_at(16), u32_at(20));
        let streams = u16_at(24);
        let (width, height) = (u32_at(28), u32_at(32));
        if frames == 0 || frames > MAX_SEGMENT_FRAMES {
            return Err(head(format!(
                "{frames} frames, 1..={MAX_SEGMENT_FRAMES} allowed"
            )));
        }
        if streams == 0 || streams > MAX_STREAMS {
            return Err(head(format!(
                "{streams} streams, 1..={MAX_STREAMS} allowed"
            )));
        }
        if width == 0 || height == 0 || width > u16::MAX as u32 || height > u16::MAX as u32 {
            return Err(head(format!("frame size {width}x{height}")));
        }
        let mut pos = HEADER;
        let mut out = Vec::new();
        for record in 0..frames as usize {
            let bad = |reason: String| SideError::Frame { record, reason };
            if bytes.len() < pos + 4 {
                return Err(bad("truncated before its length".into()));
            }
            let len = u32_at(pos) as usize;
            pos += 4;
            if len < 12 || bytes.len() - pos < len + 4 {
                return Err(bad(format!(
                    "length {len} does not fit the {} bytes left",
                    bytes.len() - pos
                )));
            }
            let p = &bytes[pos..pos + len];
            if u32_at(pos + len) != crc(p) {
                return Err(bad("checksum mismatch".into()));
            }
            let frame =
                Self::decode_frame(p, version, streams, (width, height), record, out.last())?;
            let expected = start as u64 + record as u64;
            if frame.index as u64 != expected {
                return Err(bad(format!(
                    "frame index {}, expected {expected}",
                    frame.index
                )));
            }
            if (record == 0) != frame.intra {
                return Err(bad(if record == 0 {
                    "a segment must start with an I-frame".into()
                } else {
                    "an I-frame inside a segment".into()
                }));
            }
            out.push(frame);
            pos += len + 4;
        }
        if pos != bytes.len() {
            return Err(head(format!(
                "{} bytes after the last frame record",
                bytes.len() - pos
            )));
        }
        Ok(Self {
            segment,
            start,
            streams,
            width,
            height,
            frames: out,
        })
    }

    fn decode_frame(
        p: &[u8],
        version: u16,
        streams: u16,
        (width, height): (u32, u32),
        record: usize,
        previous: Option<&SideFrame>,
    ) -> Result<SideFrame, SideError> {
        let bad = |reason: String| SideError::Frame { record, reason };
        let u32_at = |o: usize| u32::from_le_bytes([p[o], p[o + 1], p[o + 2], p[o + 3]]);
        let f32_at = |o: usize| f32::from_le_bytes([p[o], p[o + 1], p[o + 2], p[o + 3]]);
        let index = u32_at(0);
        let intra = match p[4] {
            0 => false,
            1 => true,
            f => return Err(bad(format!("unknown flags {f:#04x}"))),
        };
        let refresh = refresh_from_code(p[5])
            .ok_or_else(|| bad(format!("unknown refresh reason {}", p[5])))?;
        if refresh.is_some() != intra {
            return Err(bad("refresh reason and I-frame flag disagree".into()));
        }
        let n = p[6] as usize;
        if n == 0 || n > streams as usize {
            return Err(bad(format!(
                "{n} layers, the segment has {streams} streams"
            )));
        }
        let edc_at = 8 + n * layer_bytes(version);
        if p.len() < edc_at + 4 {
            return Err(bad("truncated layer table".into()));
        }
        let mut layers = Vec::with_capacity(n);
        let mut used = vec![false; streams as usize];
        let mut meshes = Vec::new();
        for i in 0..n {
            let o = 8 + i * layer_bytes(version);
            let stream = p[o];
            if stream as usize >= streams as usize || used[stream as usize] {
                return Err(bad(format!(
                    "layer {i}: stream {stream} invalid or repeated"
                )));
            }
            used[stream as usize] = true;
            let depth = f32_at(o + 4);
            let confidence = f32_at(o + 8);
            let track = u32_at(o + 12);
            if !(depth.is_finite() && depth > 0.0) {
                return Err(bad(format!("layer {i}: depth {depth}")));
            }
            if let Some(prev) = layers.last().map(|l: &SideLayer| l.depth) {
                if depth <= prev {
                    return Err(bad(format!(
                        "layer {i}: depth {depth} not behind the previous layer's {prev}"
                    )));
                }
            }
            if !(0.0..=1.0).contains(&confidence) {
                return Err(bad(format!("layer {i}: confidence {confidence}")));
            }
            let plane = if version >= 2 {
                Vec3::new(
                    f32_at(o + 16) as f64,
                    f32_at(o + 20) as f64,
                    f32_at(o + 24) as f64,
                )
            } else {
                Vec3::ZERO
            };
            let geometry = match p[o + 1] {
                0 if plane == Vec3::ZERO => Geometry::Plane,
                1 if version >= 2 && plane.is_finite() && plane != Vec3::ZERO => {
                    Geometry::Slanted(plane)
                }
                // Its grid follows the layer table.
                2 if version >= 2 && plane == Vec3::ZERO => {
                    meshes.push(i);
                    Geometry::Plane
                }
                tag => {
                    return Err(bad(format!(
                        "layer {i}: geometry {tag} with plane {:?}",
                        plane.0
                    )))
                }
            };
            layers.push(SideLayer {
                stream,
                depth,
                geometry,
                confidence,
                track: (track != NO_TRACK).then_some(track),
            });
        }
        let mut edc_at = edc_at;
        for i in meshes {
            let (grid, used) = expand_grid(&p[edc_at..], (width, height), previous)
                .map_err(|e| bad(format!("layer {i}: mesh grid: {e}")))?;
            layers[i].geometry = Geometry::Mesh(std::sync::Arc::new(grid));
            edc_at += used;
        }
        if p.len() < edc_at + 4 {
            return Err(bad("truncated before the edge-depth cache".into()));
        }
        let edc_len = u32_at(edc_at) as usize;
        if p.len() != edc_at + 4 + edc_len {
            return Err(bad(format!(
                "edge-depth cache of {edc_len} bytes does not fill the record"
            )));
        }
        let edc = expand_edc(&p[edc_at + 4..], width, height)
            .map_err(|source| SideError::Edc { record, source })?;
        if edc.width != width || edc.height != height || edc.layers as usize != n {
            return Err(bad(format!(
                "edge-depth cache is {}x{} with {} layers, the frame {width}x{height} with {n}",
                edc.width, edc.height, edc.layers
            )));
        }
        Ok(SideFrame {
            index,
            intra,
            refresh,
            layers,
            edc,
        })
    }
}

/// Quantised log inverse depths of a grid.
fn quantise(g: &DepthGrid) -> Vec<i16> {
    g.inverse_depth
        .iter()
        .map(|&v| {
            ((v as f64).ln() / GRID_STEP)
                .round()
                .clamp(-32768.0, 32767.0) as i16
        })
        .collect()
}

/// The layer of `previous` whose grid predicts `layer`'s: a mesh with the same track and grid
/// size, as `(index, grid)`.
fn reference<'a>(
    layer: &SideLayer,
    previous: Option<&'a SideFrame>,
) -> Option<(usize, &'a DepthGrid)> {
    let (Geometry::Mesh(g), Some(track)) = (&layer.geometry, layer.track) else {
        return None;
    };
    previous?
        .layers
        .iter()
        .enumerate()
        .find_map(|(j, l)| match &l.geometry {
            Geometry::Mesh(r)
                if l.track == Some(track)
                    && (r.step, r.cols, r.rows) == (g.step, g.cols, g.rows) =>
            {
                Some((j, &**r))
            }
            _ => None,
        })
}

/// The prediction of vertex `k` (of a grid `cols` wide): from the reference grid's `k`th value
/// or, without one, from the vertex to the left (above for the first column).
#[inline]
fn predict(q: &[i16], reference: Option<&[i16]>, k: usize, cols: usize) -> i16 {
    match (reference, k % cols, k / cols) {
        (Some(r), _, _) => r[k],
        (None, 0, 0) => 0,
        (None, 0, _) => q[k - cols],
        (None, _, _) => q[k - 1],
    }
}

/// Appends the compact grid of a mesh layer, predicted from `reference` where given (see the
/// module documentation).
fn compact_grid(g: &DepthGrid, reference: Option<(usize, &DepthGrid)>, out: &mut Vec<u8>) {
    let q = quantise(g);
    let r = reference.map(|(_, r)| quantise(r));
    let n = q.len();
    let cols = g.cols as usize;
    let mut planes = vec![0u8; 2 * n];
    for (k, &v) in q.iter().enumerate() {
        let [lo, hi] = v
            .wrapping_sub(predict(&q, r.as_deref(), k, cols))
            .to_le_bytes();
        planes[k] = lo;
        planes[n + k] = hi;
    }
    let packed = miniz_oxide::deflate::compress_to_vec(&planes, 6);
    let index = reference.map_or(0, |(j, _)| j as u16 + 1);
    for v in [g.step as u16, g.cols as u16, g.rows as u16, index] {
        out.extend_from_slice(&v.to_le_bytes());
    }
    out.extend_from_slice(&(packed.len() as u32).to_le_bytes());
    out.extend_from_slice(&packed);
}

/// Bytes a layer's geometry takes in a version 2 side stream beyond the fronto-parallel
/// plane's record, coded alone: 12 for a slanted plane's coefficients, the compact grid of a
/// mesh without prediction from a previous record (an upper bound for a P-frame's).
pub fn geometry_bytes(g: &Geometry) -> usize {
    match g {
        Geometry::Plane => 0,
        Geometry::Slanted(_) => 12,
        Geometry::Mesh(grid) => {
            let mut out = Vec::new();
            compact_grid(grid, None, &mut out);
            out.len()
        }
    }
}

/// Reads a compact grid for a `width x height` frame whose previous record is `previous`;
/// returns it and the bytes it took.
fn expand_grid(
    b: &[u8],
    (width, height): (u32, u32),
    previous: Option<&SideFrame>,
) -> Result<(DepthGrid, usize), String> {
    if b.len() < 12 {
        return Err("truncated header".into());
    }
    let u16_at = |o: usize| u16::from_le_bytes([b[o], b[o + 1]]) as u32;
    let (step, cols, rows, index) = (u16_at(0), u16_at(2), u16_at(4), u16_at(6));
    let len = u32::from_le_bytes([b[8], b[9], b[10], b[11]]) as usize;
    if step == 0 || step > DepthGrid::MAX_STEP {
        return Err(format!("step {step}"));
    }
    if (cols, rows) != DepthGrid::dims(width, height, step) {
        return Err(format!(
            "{cols}x{rows} vertices, a {width}x{height} frame at step {step} has {:?}",
            DepthGrid::dims(width, height, step)
        ));
    }
    let reference = match index {
        0 => None,
        j => match previous
            .and_then(|f| f.layers.get(j as usize - 1))
            .map(|l| &l.geometry)
        {
            Some(Geometry::Mesh(r)) if (r.cols, r.rows) == (cols, rows) => Some(quantise(r)),
            _ => {
                return Err(format!(
                "predicted from layer {} of the previous record, which has no grid of this size",
                j - 1
            ))
            }
        },
    };
    if b.len() - 12 < len {
        return Err(format!("{len} bytes of values, {} left", b.len() - 12));
    }
    let n = (cols * rows) as usize;
    let planes = miniz_oxide::inflate::decompress_to_vec_with_limit(&b[12..12 + len], 2 * n)
        .map_err(|_| "values do not inflate".to_string())?;
    if planes.len() != 2 * n {
        return Err("inflated values have the wrong length".into());
    }
    let c = cols as usize;
    let mut q = vec![0i16; n];
    for k in 0..n {
        q[k] = predict(&q, reference.as_deref(), k, c)
            .wrapping_add(i16::from_le_bytes([planes[k], planes[n + k]]));
    }
    let grid = DepthGrid {
        step,
        cols,
        rows,
        inverse_depth: q
            .iter()
            .map(|&v| (v as f64 * GRID_STEP).exp() as f32)
            .collect(),
    };
    grid.check(width, height).map_err(|e| e.to_string())?;
    Ok((grid, 12 + len))
}

/// The compact EDC of a side-stream record (see the module documentation).
fn compact_edc(edc: &Edc) -> Vec<u8> {
    let n = edc.samples.len();
    let mut planes = vec![0u8; n * 8];
    let (mut px, mut py) = (0u16, 0u16);
    for (i, s) in edc.samples.iter().enumerate() {
        let dy = s.y.wrapping_sub(py).to_le_bytes();
        let dx = s.x.wrapping_sub(px).to_le_bytes();
        (px, py) = (s.x, s.y);
        planes[2 * i..2 * i + 2].copy_from_slice(&dy);
        planes[2 * n + 2 * i..2 * n + 2 * i + 2].copy_from_slice(&dx);
        planes[4 * n + i] = s.front;
        planes[5 * n + i] = s.back;
        planes[6 * n + i] = s.front_offset as u8;
        planes[7 * n + i] = s.back_offset as u8;
    }
    let mut out = Vec::new();
    out.extend_from_slice(&edc.layers.to_le_bytes());
    out.extend_from_slice(&edc.step.to_le_bytes());
    out.extend_from_slice(&(n as u32).to_le_bytes());
    out.extend_from_slice(&miniz_oxide::deflate::compress_to_vec(&planes, 6));
    out
}

/// Reads a compact EDC back and validates it (through the `edc.bin` decoder).
fn expand_edc(b: &[u8], width: u32, height: u32) -> Result<Edc, EdcError> {
    let bad = |m: &str| EdcError::Header(m.to_string());
    if b.len() < 10 {
        return Err(bad("compact cache shorter than its header"));
    }
    let layers = u16::from_le_bytes([b[0], b[1]]);
    let step = f32::from_le_bytes([b[2], b[3], b[4], b[5]]);
    let n = u32::from_le_bytes([b[6], b[7], b[8], b[9]]) as usize;
    // At most one sample per pixel: bounds the inflated size.
    if n > width as usize * height as usize {
        return Err(bad("more samples than pixels"));
    }
    let planes = miniz_oxide::inflate::decompress_to_vec_with_limit(&b[10..], n * 8)
        .map_err(|_| bad("compressed samples do not inflate"))?;
    if planes.len() != n * 8 {
        return Err(bad("inflated samples have the wrong length"));
    }
    let raw = Edc::empty(width, height, layers, step).encode();
    let mut bytes = raw[..raw.len() - 4].to_vec();
    bytes.extend_from_slice(&(n as u32).to_le_bytes());
    let (mut x, mut y) = (0u16, 0u16);
    for i in 0..n {
        y = y.wrapping_add(u16::from_le_bytes([planes[2 * i], planes[2 * i + 1]]));
        x = x.wrapping_add(u16::from_le_bytes([
            planes[2 * n + 2 * i],
            planes[2 * n + 2 * i + 1],
        ]));
        bytes.extend_from_slice(&x.to_le_bytes());
        bytes.extend_from_slice(&y.to_le_bytes());
        bytes.extend_from_slice(&[
            planes[4 * n + i],
            planes[5 * n + i],
            planes[6 * n + i],
            planes[7 * n + i],
        ]);
    }
    Edc::decode(&bytes)
}

/// The Edge-Depth Cache a side stream carries: one sample per (front, back) layer pair, at
/// the pair's first boundary sample, holding the pair's mean offsets on both sides (rounded to
/// the cache's step). The renderer reads the cache per layer pair (mean offsets on both
/// sides, `cpsl_render`'s Dynamic Pixel Strip), so the summary renders as the full cache does
/// up to half a quantisation step of `ln z`, for a few bytes per pair where the full cache
/// costs kilobytes per frame.
pub fn summarise_edc(edc: &Edc) -> Edc {
    // Per pair: first sample and the sums of both offsets.
    let mut pairs: Vec<(cpsl_core::EdcSample, i64, i64, i64)> = Vec::new();
    for s in &edc.samples {
        match pairs
            .iter_mut()
            .find(|p| (p.0.front, p.0.back) == (s.front, s.back))
        {
            Some(p) => {
                p.1 += s.front_offset as i64;
                p.2 += s.back_offset as i64;
                p.3 += 1;
            }
            None => pairs.push((*s, s.front_offset as i64, s.back_offset as i64, 1)),
        }
    }
    let mean = |sum: i64, n: i64| (sum as f64 / n as f64).round().clamp(-128.0, 127.0) as i8;
    let mut samples: Vec<cpsl_core::EdcSample> = pairs
        .into_iter()
        .map(|(first, f, b, n)| cpsl_core::EdcSample {
            front_offset: mean(f, n),
            back_offset: mean(b, n),
            ..first
        })
        .collect();
    // Scan order, as every cache keeps its samples.
    samples.sort_by_key(|s| (s.y, s.x));
    Edc {
        samples,
        ..edc.clone()
    }
}
