//! Fragmented MP4 layer streams. A segment's layer streams are one movie fragment
//! (`moof` + `mdat`, ISO/IEC 14496-12) of one track, one track run per stream, the streams
//! one after the other (package version 6; versions 4 and 5 wrote one fragment of one run per
//! stream, which read the same way). Each run's key picture carries its parameter sets in
//! band (sample entries `avc3`, `hev1`, `av01`, `vp09`), so a run decodes on its own; a
//! package holds one initialisation segment (`ftyp` + `moov`) per picture size. An init
//! segment followed by a segment's fragment is an ordinary fragmented MP4 file that FFmpeg's
//! demuxer reads (tested): the layers play one after the other. It is not a CMAF segment:
//! CMAF asks for a `tfdt`, which a fragment decoded on its own does not need (below).
//!
//! The fragment is as small as the standard allows: `moof` with `mfhd`, a `traf` of `tfhd`
//! (track 1, data offsets from the `moof`) and per stream one `trun` with its data offset,
//! each sample's size, the first sample's flags (a sync sample) and, when the stream reorders
//! pictures (B-frames), each sample's composition offset (signed, version 1, so that
//! decoding times are the picture indices and presentation starts at 0 without an edit
//! list); sample durations and the other samples' flags (non-sync) are the defaults of the
//! init segment's `trex`. That is 56 bytes per segment plus, per stream, 24 and 4 per
//! picture, 8 with reordering ([`overhead`]), against about 1,100 bytes of `ftyp` + `moov`
//! in every stream of every segment in a self-contained MP4. There is no `tfdt`: a fragment
//! is decoded on its own (from time 0), never appended to another.

use cpsl_package::Codec;

/// One coded picture in MP4 sample form (NAL units with 4-byte length prefixes for H.264 and
/// H.265; AV1 without temporal delimiters), in decoding order.
#[derive(Debug, Clone)]
pub(crate) struct Coded {
    /// The sample.
    pub data: Vec<u8>,
    /// Its presentation index (the picture's place in display order).
    pub pts: i64,
    /// A key (sync) picture.
    pub key: bool,
}

/// Sample flags: depends on others, not a sync sample.
const NON_SYNC: u32 = 0x0101_0000;
/// Sample flags: depends on no other picture (a sync sample).
const SYNC: u32 = 0x0200_0000;
/// `tfhd` flag: data offsets count from the `moof`.
const BASE_IS_MOOF: u32 = 0x02_0000;
/// `trun` flags.
const DATA_OFFSET: u32 = 0x1;
const FIRST_FLAGS: u32 = 0x4;
const SIZES: u32 = 0x200;
const OFFSETS: u32 = 0x800;

/// Bytes of a fragment's own boxes, whatever its runs: `moof` and `mfhd`, `traf` and `tfhd`,
/// and the `mdat` header.
pub(crate) const FRAGMENT_BYTES: usize = 56;

/// Bytes a fragment spends beyond its samples: [`FRAGMENT_BYTES`] for the fragment (`moof` with `mfhd`,
/// `traf` with `tfhd`, and the `mdat` header) and for each run of `n` pictures 24 plus 4 per
/// picture, 8 with reordering.
pub(crate) fn overhead(runs: &[(usize, bool)]) -> usize {
    FRAGMENT_BYTES
        + runs
            .iter()
            .map(|&(n, reordered)| 24 + n * if reordered { 8 } else { 4 })
            .sum::<usize>()
}

fn put_box(out: &mut Vec<u8>, kind: &[u8; 4], body: impl FnOnce(&mut Vec<u8>)) {
    let at = out.len();
    out.extend_from_slice(&[0, 0, 0, 0]);
    out.extend_from_slice(kind);
    body(out);
    let size = (out.len() - at) as u32;
    out[at..at + 4].copy_from_slice(&size.to_be_bytes());
}

fn u32s(out: &mut Vec<u8>, values: &[u32]) {
    for v in values {
        out.extend_from_slice(&v.to_be_bytes());
    }
}

/// Each sample's composition offset (presentation index minus decoding index) in a run.
fn composition_offsets(samples: &[Coded]) -> Vec<i64> {
    samples
        .iter()
        .enumerate()
        .map(|(i, s)| s.pts - i as i64)
        .collect()
}

/// The fragment (`moof` + `mdat`) of one track holding `runs` one after the other, each a
/// stream whose first sample is a key picture: one track run per stream, its samples
/// together in the `mdat`. Composition offsets count within each run, so a run decodes on
/// its own, and as the track it is part of (decoding times continuing from run to run).
pub(crate) fn fragment(runs: &[&[Coded]]) -> Vec<u8> {
    let offsets: Vec<Vec<i64>> = runs.iter().map(|r| composition_offsets(r)).collect();
    let shape: Vec<(usize, bool)> = runs
        .iter()
        .zip(&offsets)
        .map(|(r, o)| (r.len(), o.iter().any(|&o| o != 0)))
        .collect();
    let payload: usize = runs
        .iter()
        .flat_map(|r| r.iter())
        .map(|s| s.data.len())
        .sum();
    let moof_size = overhead(&shape) - 8;
    let mut out = Vec::with_capacity(moof_size + 8 + payload);
    put_box(&mut out, b"moof", |o| {
        put_box(o, b"mfhd", |o| u32s(o, &[0, 1]));
        put_box(o, b"traf", |o| {
            put_box(o, b"tfhd", |o| u32s(o, &[BASE_IS_MOOF, 1]));
            let mut data_at = moof_size + 8;
            for ((samples, offsets), &(_, reordered)) in runs.iter().zip(&offsets).zip(&shape) {
                put_box(o, b"trun", |o| {
                    let version: u32 = if offsets.iter().any(|&o| o < 0) { 1 } else { 0 };
                    let flags =
                        DATA_OFFSET | FIRST_FLAGS | SIZES | if reordered { OFFSETS } else { 0 };
                    let first = if samples.first().is_some_and(|s| s.key) {
                        SYNC
                    } else {
                        NON_SYNC
                    };
                    u32s(
                        o,
                        &[
                            version << 24 | flags,
                            samples.len() as u32,
                            data_at as u32,
                            first,
                        ],
                    );
                    for (s, &off) in samples.iter().zip(offsets) {
                        u32s(o, &[s.data.len() as u32]);
                        if reordered {
                            u32s(o, &[off as i32 as u32]);
                        }
                    }
                });
                data_at += samples.iter().map(|s| s.data.len()).sum::<usize>();
            }
        });
    });
    debug_assert_eq!(out.len(), moof_size);
    out.extend_from_slice(&((payload + 8) as u32).to_be_bytes());
    out.extend_from_slice(b"mdat");
    for s in runs.iter().flat_map(|r| r.iter()) {
        out.extend_from_slice(&s.data);
    }
    out
}

/// The runs of the fragments `parts` (each a file [`fragment`] wrote) as one fragment, in
/// order: how a segment's layer streams, coded one file each, become its one file.
pub(crate) fn join(parts: &[Vec<u8>]) -> Result<Vec<u8>, String> {
    let mut runs = Vec::new();
    for part in parts {
        for run in parse_fragment(part)? {
            runs.push(
                run.iter()
                    .enumerate()
                    .map(|(i, s)| Coded {
                        data: part[s.range.clone()].to_vec(),
                        pts: i as i64 + s.offset,
                        key: s.key,
                    })
                    .collect::<Vec<_>>(),
            );
        }
    }
    let views: Vec<&[Coded]> = runs.iter().map(Vec::as_slice).collect();
    Ok(fragment(&views))
}

/// One sample of a parsed fragment.
#[derive(Debug, Clone, PartialEq)]
pub(crate) struct Sample {
    /// Its bytes in the file.
    pub range: std::ops::Range<usize>,
    /// A sync sample.
    pub key: bool,
    /// Its presentation time minus its decoding index, in samples.
    pub offset: i64,
}

/// A box: type, body range, end.
fn boxes(data: &[u8], start: usize, end: usize) -> Result<Vec<([u8; 4], usize, usize)>, String> {
    let mut out = Vec::new();
    let mut at = start;
    while at < end {
        let head = data
            .get(at..at + 8)
            .filter(|_| at + 8 <= end)
            .ok_or("a box header runs past its parent")?;
        let size = u32::from_be_bytes([head[0], head[1], head[2], head[3]]) as usize;
        let kind = [head[4], head[5], head[6], head[7]];
        let (body, size) = match size {
            0 => (at + 8, end - at),
            1 => {
                let s = data.get(at + 8..at + 16).ok_or("a box header is cut")?;
                (
                    at + 16,
                    u64::from_be_bytes(s.try_into().expect("8 bytes")) as usize,
                )
            }
            s => (at + 8, s),
        };
        let box_end = at.checked_add(size).filter(|&e| e <= end && e >= body);
        let box_end = box_end.ok_or_else(|| {
            format!(
                "box '{}' overruns its parent",
                String::from_utf8_lossy(&kind)
            )
        })?;
        out.push((kind, body, box_end));
        at = box_end;
    }
    Ok(out)
}

fn be32(data: &[u8], at: usize, end: usize) -> Result<u32, String> {
    (at + 4 <= end)
        .then(|| u32::from_be_bytes(data[at..at + 4].try_into().expect("4 bytes")))
        .ok_or_else(|| "a box is too short for its fields".to_string())
}

/// The samples of a file holding one movie fragment of one track (an init segment before it
/// is skipped), run by run, each in decoding order, checked to lie inside the file.
pub(crate) fn parse_fragment(data: &[u8]) -> Result<Vec<Vec<Sample>>, String> {
    let top = boxes(data, 0, data.len())?;
    let (_, moof, moof_end) = *top
        .iter()
        .find(|b| &b.0 == b"moof")
        .ok_or("no movie fragment ('moof')")?;
    if top.iter().filter(|b| &b.0 == b"moof").count() != 1 {
        return Err("more than one movie fragment".into());
    }
    let moof_start = moof - 8;
    let trafs: Vec<_> = boxes(data, moof, moof_end)?
        .into_iter()
        .filter(|b| &b.0 == b"traf")
        .collect();
    let [(_, traf, traf_end)] = trafs[..] else {
        return Err(format!("{} track fragments, one expected", trafs.len()));
    };
    let inner = boxes(data, traf, traf_end)?;
    let (_, tfhd, tfhd_end) = *inner
        .iter()
        .find(|b| &b.0 == b"tfhd")
        .ok_or("no track fragment header ('tfhd')")?;
    let tf_flags = be32(data, tfhd, tfhd_end)? & 0xff_ffff;
    let mut at = tfhd + 8;
    let mut base = moof_start;
    if tf_flags & 0x1 != 0 {
        let hi = be32(data, at, tfhd_end)? as u64;
        let lo = be32(data, at + 4, tfhd_end)? as u64;
        base = (hi << 32 | lo) as usize;
        at += 8;
    }
    for bit in [0x2, 0x8, 0x10] {
        if tf_flags & bit != 0 {
            at += 4;
        }
    }
    let default_flags = match tf_flags & 0x20 {
        0 => NON_SYNC,
        _ => be32(data, at, tfhd_end)?,
    };
    let mut runs = Vec::new();
    let mut next = base;
    for &(_, trun, trun_end) in inner.iter().filter(|b| &b.0 == b"trun") {
        let mut samples = Vec::new();
        let head = be32(data, trun, trun_end)?;
        let (version, flags) = (head >> 24, head & 0xff_ffff);
        let count = be32(data, trun + 4, trun_end)? as usize;
        let mut at = trun + 8;
        if flags & DATA_OFFSET != 0 {
            next = (base as i64 + be32(data, at, trun_end)? as i32 as i64).max(0) as usize;
            at += 4;
        }
        let mut first = None;
        if flags & FIRST_FLAGS != 0 {
            first = Some(be32(data, at, trun_end)?);
            at += 4;
        }
        let fields = [0x100, 0x200, 0x400, 0x800]
            .iter()
            .filter(|&&f| flags & f != 0)
            .count();
        if flags & SIZES == 0 {
            return Err("a track run without sample sizes".into());
        }
        if count.saturating_mul(4 * fields) > trun_end.saturating_sub(at) {
            return Err(format!("a track run of {count} samples is cut"));
        }
        for i in 0..count {
            let mut field = |f: u32| -> Option<u32> {
                (flags & f != 0).then(|| {
                    let v = u32::from_be_bytes(data[at..at + 4].try_into().expect("4 bytes"));
                    at += 4;
                    v
                })
            };
            field(0x100);
            let size = field(0x200).expect("sizes are present") as usize;
            let sample_flags = field(0x400)
                .or(if i == 0 { first } else { None })
                .unwrap_or(default_flags);
            let offset = field(0x800).map_or(0, |v| match version {
                0 => v as i64,
                _ => v as i32 as i64,
            });
            let end = next
                .checked_add(size)
                .filter(|&e| e <= data.len())
                .ok_or_else(|| {
                    format!(
                        "sample {} of run {} lies past the end of the file",
                        samples.len(),
                        runs.len()
                    )
                })?;
            samples.push(Sample {
                range: next..end,
                key: sample_flags & 0x1_0000 == 0,
                offset,
            });
            next = end;
        }
        if samples.is_empty() {
            return Err(format!("run {} has no samples", runs.len()));
        }
        runs.push(samples);
    }
    if runs.is_empty() {
        return Err("no samples".into());
    }
    Ok(runs)
}

/// Patches the `trex` of an init segment so that fragments inherit a sample duration of
/// `duration` and non-sync flags; returns the init segment (`ftyp` + `moov`) alone.
pub(crate) fn finish_init(data: &[u8], duration: u32) -> Result<Vec<u8>, String> {
    let top = boxes(data, 0, data.len())?;
    let mut out = Vec::new();
    for &(kind, body, end) in &top {
        if &kind == b"ftyp" || &kind == b"moov" {
            out.extend_from_slice(&data[body - 8..end]);
        }
    }
    let moov = boxes(&out, 0, out.len())?
        .into_iter()
        .find(|b| &b.0 == b"moov")
        .ok_or("the muxer wrote no 'moov'")?;
    let mvex = boxes(&out, moov.1, moov.2)?
        .into_iter()
        .find(|b| &b.0 == b"mvex")
        .ok_or("the muxer wrote no 'mvex'")?;
    let (_, trex, trex_end) = boxes(&out, mvex.1, mvex.2)?
        .into_iter()
        .find(|b| &b.0 == b"trex")
        .ok_or("the muxer wrote no 'trex'")?;
    if trex_end - trex != 24 {
        return Err("an unexpected 'trex'".into());
    }
    // version/flags, track, description index, duration, size, flags.
    out[trex + 12..trex + 16].copy_from_slice(&duration.to_be_bytes());
    out[trex + 20..trex + 24].copy_from_slice(&NON_SYNC.to_be_bytes());
    Ok(out)
}

/// The NAL units of an H.264 or H.265 access unit: (start, payload start, end) of each, the
/// start including its start code or length prefix. `None` if `data` is neither Annex B
/// (start codes) nor tiled by 4-byte length prefixes. Encoders hand Annex B over, so data
/// opening with a start code is read as such (a length-prefixed sample whose first unit is
/// 256 to 511 bytes long opens with the same bytes: use [`length_prefixed`] for samples).
pub(crate) fn nal_units(data: &[u8]) -> Option<Vec<(usize, usize, usize)>> {
    if !(data.starts_with(&[0, 0, 1]) || data.starts_with(&[0, 0, 0, 1])) {
        return length_prefixed(data);
    }
    // Annex B: emulation prevention keeps 00 00 01 out of the payloads.
    let codes: Vec<usize> = (0..data.len().saturating_sub(2))
        .filter(|&i| data[i..i + 3] == [0, 0, 1])
        .collect();
    let mut units = Vec::new();
    for (k, &c) in codes.iter().enumerate() {
        let start = if c > 0 && data[c - 1] == 0 { c - 1 } else { c };
        let end = codes
            .get(k + 1)
            .map_or(data.len(), |&n| if data[n - 1] == 0 { n - 1 } else { n });
        units.push((start, c + 3, end));
    }
    Some(units)
}

/// The NAL units of an MP4 sample (4-byte length prefixes), as [`nal_units`] gives them;
/// `None` if the prefixes do not tile `data`.
pub(crate) fn length_prefixed(data: &[u8]) -> Option<Vec<(usize, usize, usize)>> {
    let mut units = Vec::new();
    let mut at = 0;
    while at < data.len() {
        let b = data.get(at..at + 4)?;
        let len = u32::from_be_bytes([b[0], b[1], b[2], b[3]]) as usize;
        let end = at + 4 + len;
        if len == 0 || end > data.len() {
            return None;
        }
        units.push((at, at + 4, end));
        at = end;
    }
    Some(units)
}

/// The OBUs of an AV1 temporal unit: (start, type, end) of each. `None` if an OBU has no
/// size field or overruns the data.
fn obus(data: &[u8]) -> Option<Vec<(usize, u8, usize)>> {
    let mut out = Vec::new();
    let mut at = 0;
    while at < data.len() {
        let header = data[at];
        let kind = (header >> 3) & 0xf;
        if header & 0x2 == 0 {
            return None;
        }
        let mut p = at + 1 + usize::from(header & 0x4 != 0);
        let mut size = 0usize;
        for i in 0..8 {
            let b = *data.get(p)?;
            p += 1;
            size |= ((b & 0x7f) as usize) << (7 * i);
            if b & 0x80 == 0 {
                break;
            }
        }
        let end = p.checked_add(size).filter(|&e| e <= data.len())?;
        out.push((at, kind, end));
        at = end;
    }
    Some(out)
}

/// An encoder's packet in MP4 sample form: H.264 and H.265 NAL units with 4-byte length
/// prefixes, AV1 without temporal delimiters; VP9 as it is.
pub(crate) fn to_sample(codec: Codec, packet: &[u8]) -> Vec<u8> {
    match codec {
        Codec::H264 | Codec::H265 => match nal_units(packet) {
            Some(units) if packet.starts_with(&[0, 0, 1]) || packet.starts_with(&[0, 0, 0, 1]) => {
                let mut out = Vec::with_capacity(packet.len() + units.len());
                for (_, payload, end) in units {
                    out.extend_from_slice(&((end - payload) as u32).to_be_bytes());
                    out.extend_from_slice(&packet[payload..end]);
                }
                out
            }
            _ => packet.to_vec(),
        },
        Codec::Av1 => match obus(packet) {
            Some(units) => units
                .iter()
                .filter(|u| u.1 != 2)
                .flat_map(|&(s, _, e)| &packet[s..e])
                .copied()
                .collect(),
            None => packet.to_vec(),
        },
        Codec::Vp9 => packet.to_vec(),
    }
}

/// A sample back in the form a decoder without a configuration record reads: H.264 and
/// H.265 with start codes (the parameter sets are in band); others as they are.
pub(crate) fn to_decoder(codec: Codec, sample: &[u8]) -> Vec<u8> {
    match codec {
        Codec::H264 | Codec::H265 => match length_prefixed(sample) {
            Some(units) => {
                let mut out = sample.to_vec();
                for (start, _, _) in units {
                    out[start..start + 4].copy_from_slice(&[0, 0, 0, 1]);
                }
                out
            }
            _ => sample.to_vec(),
        },
        _ => sample.to_vec(),
    }
}

/// The configuration a key sample carries in band, as a muxer's extradata: H.264 SPS and
/// PPS, H.265 VPS, SPS and PPS (with start codes), the AV1 sequence header OBU; nothing for
/// VP9.
pub(crate) fn headers(codec: Codec, sample: &[u8]) -> Vec<u8> {
    let mut out = Vec::new();
    match codec {
        Codec::H264 | Codec::H265 => {
            for (_, payload, end) in length_prefixed(sample).unwrap_or_default() {
                let Some(&b) = sample.get(payload) else {
                    continue;
                };
                let is_set = match codec {
                    Codec::H264 => matches!(b & 0x1f, 7 | 8),
                    _ => matches!((b >> 1) & 0x3f, 32..=34),
                };
                if is_set {
                    out.extend_from_slice(&[0, 0, 0, 1]);
                    out.extend_from_slice(&sample[payload..end]);
                }
            }
        }
        Codec::Av1 => {
            for (s, kind, e) in obus(sample).unwrap_or_default() {
                if kind == 1 {
                    out.extend_from_slice(&sample[s..e]);
                }
            }
        }
        Codec::Vp9 => {}
    }
    out
}

#[cfg(test)]
mod tests {
    use super::*;

    fn coded(data: &[u8], pts: i64, key: bool) -> Coded {
        Coded {
            data: data.to_vec(),
            pts,
            key,
        }
    }

    #[test]
    fn a_fragment_parses_back_with_its_overhead() {
        // Decoding order I0 P3 B1 B2 (display 0 1 2 3): offsets 0, +2, -1, -1.
        let s = [
            coded(&[1; 10], 0, true),
            coded(&[2; 5], 3, false),
            coded(&[3; 7], 1, false),
            coded(&[4; 1], 2, false),
        ];
        let f = fragment(&[&s]);
        assert_eq!(f.len(), overhead(&[(4, true)]) + 23);
        assert_eq!(overhead(&[(4, true)]), 80 + 4 * 8);
        let back = parse_fragment(&f).unwrap();
        assert_eq!(back.len(), 1);
        let offsets: Vec<i64> = back[0].iter().map(|b| b.offset).collect();
        assert_eq!(offsets, [0, 2, -1, -1]);
        assert_eq!(
            back[0].iter().map(|b| b.key).collect::<Vec<_>>(),
            [true, false, false, false]
        );
        for (b, c) in back[0].iter().zip(&s) {
            assert_eq!(&f[b.range.clone()], &c.data[..]);
        }
        // Without reordering: sizes only.
        let plain = [coded(&[1; 3], 0, true), coded(&[2; 4], 1, false)];
        let f = fragment(&[&plain]);
        assert_eq!(f.len(), overhead(&[(2, false)]) + 7);
        let back = parse_fragment(&f).unwrap();
        assert_eq!(back[0][1].range, f.len() - 4..f.len());
        assert_eq!(back[0][1].offset, 0);
        // Cut or damaged: errors, never panics.
        for n in [0, 8, 40, f.len() - 1] {
            assert!(parse_fragment(&f[..n]).is_err(), "cut at {n}");
        }
        let mut big = f.clone();
        let count_at = 8 + 16 + 8 + 16 + 12;
        big[count_at..count_at + 4].copy_from_slice(&1000u32.to_be_bytes());
        assert!(parse_fragment(&big).is_err());
    }

    #[test]
    fn streams_joined_into_one_fragment_come_back_run_by_run() {
        let a = [
            coded(&[1; 10], 0, true),
            coded(&[2; 5], 2, false),
            coded(&[3; 7], 1, false),
        ];
        let b = [coded(&[4; 3], 0, true), coded(&[5; 4], 1, false)];
        let c = [coded(&[6; 9], 0, true)];
        let parts = [fragment(&[&a]), fragment(&[&b]), fragment(&[&c])];
        let joined = join(&parts).unwrap();
        // The fragment's 56 bytes are paid once, not three times.
        let shape = [(3, true), (2, false), (1, false)];
        assert_eq!(joined.len(), overhead(&shape) + 38);
        assert_eq!(
            parts.iter().map(Vec::len).sum::<usize>() - joined.len(),
            2 * 56
        );
        let runs = parse_fragment(&joined).unwrap();
        assert_eq!(runs.len(), 3);
        for (run, src) in runs.iter().zip([&a[..], &b, &c]) {
            assert_eq!(run.len(), src.len());
            for (i, (s, c)) in run.iter().zip(src).enumerate() {
                assert_eq!(&joined[s.range.clone()], &c.data[..]);
                assert_eq!((s.key, i as i64 + s.offset), (c.key, c.pts));
            }
        }
        // Joining what is joined changes nothing; a damaged part is an error.
        assert_eq!(join(std::slice::from_ref(&joined)).unwrap(), joined);
        assert!(join(&[parts[0].clone(), parts[1][..20].to_vec()]).is_err());
    }

    #[test]
    fn nal_units_change_framing_both_ways() {
        let annex_b = [
            &[0u8, 0, 0, 1, 0x67, 1, 2][..],
            &[0, 0, 1, 0x68, 3],
            &[0, 0, 0, 1, 0x65, 0, 0, 3, 1],
        ]
        .concat();
        let sample = to_sample(Codec::H264, &annex_b);
        assert_eq!(
            sample,
            [
                &[0u8, 0, 0, 3, 0x67, 1, 2][..],
                &[0, 0, 0, 2, 0x68, 3],
                &[0, 0, 0, 5, 0x65, 0, 0, 3, 1]
            ]
            .concat()
        );
        assert_eq!(
            to_decoder(Codec::H264, &sample),
            [
                &[0u8, 0, 0, 1, 0x67, 1, 2][..],
                &[0, 0, 0, 1, 0x68, 3],
                &[0, 0, 0, 1, 0x65, 0, 0, 3, 1]
            ]
            .concat()
        );
        assert_eq!(
            headers(Codec::H264, &sample),
            [&[0u8, 0, 0, 1, 0x67, 1, 2][..], &[0, 0, 0, 1, 0x68, 3]].concat()
        );
        // A sample whose first unit is 256 to 511 bytes long opens like a start code.
        let long = [&[0u8, 0, 1, 0][..], &[0x65; 256]].concat();
        assert_eq!(to_decoder(Codec::H264, &long)[..5], [0, 0, 0, 1, 0x65]);
    }

    #[test]
    fn av1_samples_lose_their_temporal_delimiters() {
        // Temporal delimiter, sequence header (3 bytes), frame (2 bytes).
        let tu = [0x12, 0, 0x0a, 3, 7, 7, 7, 0x32, 2, 9, 9];
        assert_eq!(to_sample(Codec::Av1, &tu), tu[2..].to_vec());
        assert_eq!(headers(Codec::Av1, &tu), tu[2..7].to_vec());
        // Without size fields: left alone.
        assert_eq!(to_sample(Codec::Av1, &[0x10, 1]), vec![0x10, 1]);
    }
}
