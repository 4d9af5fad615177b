// A small MP4 demuxer for the layer streams cpsl writes (one video track; a progressive MP4
// file, or a run of a movie fragment after its init segment): the decoder configuration and
// every sample's place, size, key flag and timestamps.

export interface Sample {
  offset: number;
  size: number;
  key: boolean;
  /** Presentation time in track timescale units. */
  cts: number;
  /** Decoding time in track timescale units. */
  dts: number;
}

export interface Track {
  codec: string;
  description?: Uint8Array;
  width: number;
  height: number;
  timescale: number;
  samples: Sample[];
  /** Samples are length-prefixed NAL units to be decoded as Annex B (parameter sets in band). */
  annexB?: boolean;
}

interface Box {
  type: string;
  start: number;
  end: number;
  body: number;
}

function* boxes(v: DataView, start: number, end: number): Generator<Box> {
  let p = start;
  while (p + 8 <= end) {
    let size = v.getUint32(p);
    const type = String.fromCharCode(v.getUint8(p + 4), v.getUint8(p + 5), v.getUint8(p + 6), v.getUint8(p + 7));
    let body = p + 8;
    if (size === 1) {
      size = Number(v.getBigUint64(p + 8));
      body += 8;
    } else if (size === 0) size = end - p;
    if (size < body - p || p + size > end) throw new Error(`mp4: box '${type}' overruns its parent`);
    yield { type, start: p, end: p + size, body };
    p += size;
  }
}

function child(v: DataView, parent: Box, path: string[]): Box {
  let b = parent;
  for (const t of path) {
    const next = [...boxes(v, b.body, b.end)].find((x) => x.type === t);
    if (!next) throw new Error(`mp4: no '${t}' box`);
    b = next;
  }
  return b;
}

const hex2 = (n: number) => n.toString(16).padStart(2, "0");

/** The video track of a `moov`: its sample table box, timescale and sample description. */
function videoTrack(v: DataView, buf: ArrayBuffer) {
  const top = { type: "", start: 0, end: buf.byteLength, body: 0 };
  const moov = child(v, top, ["moov"]);
  const trak = [...boxes(v, moov.body, moov.end)].find((b) => {
    if (b.type !== "trak") return false;
    const hdlr = child(v, b, ["mdia", "hdlr"]);
    return String.fromCharCode(...new Uint8Array(buf, hdlr.body + 8, 4)) === "vide";
  });
  if (!trak) throw new Error("mp4: no video track");
  const mdhd = child(v, trak, ["mdia", "mdhd"]);
  const timescale = v.getUint8(mdhd.body) === 1 ? v.getUint32(mdhd.body + 20) : v.getUint32(mdhd.body + 12);
  const stbl = child(v, trak, ["mdia", "minf", "stbl"]);

  // Sample description: the codec and its configuration record.
  const stsd = [...boxes(v, stbl.body, stbl.end)].find((b) => b.type === "stsd");
  if (!stsd) throw new Error("mp4: no stsd");
  const entry = boxes(v, stsd.body + 8, stsd.end).next().value as Box;
  const width = v.getUint16(entry.body + 24);
  const height = v.getUint16(entry.body + 26);
  let codec = "";
  let description: Uint8Array | undefined;
  for (const b of boxes(v, entry.body + 78, entry.end)) {
    const payload = new Uint8Array(buf, b.body, b.end - b.body);
    if (b.type === "avcC") {
      codec = `${entry.type}.${hex2(payload[1])}${hex2(payload[2])}${hex2(payload[3])}`;
      description = payload.slice();
    } else if (b.type === "hvcC") {
      codec = `${entry.type}.${payload[1] & 0x1f}.6.L${payload[12]}.B0`;
      description = payload.slice();
    } else if (b.type === "av1C") {
      const level = payload[1] & 0x1f;
      const tier = payload[2] >> 7 ? "H" : "M";
      codec = `av01.${payload[1] >> 5}.${String(level).padStart(2, "0")}${tier}.08`;
      description = payload.slice();
    } else if (b.type === "vpcC") {
      codec = `vp09.${String(payload[4]).padStart(2, "0")}.${String(payload[5]).padStart(2, "0")}.${String(payload[6] >> 4).padStart(2, "0")}`;
    }
  }
  if (!codec) throw new Error(`mp4: unsupported sample entry '${entry.type}'`);
  return { stbl, timescale, codec, description, width, height };
}

/** Parses a progressive MP4 with one video track. */
export function demux(buf: ArrayBuffer): Track {
  const v = new DataView(buf);
  const { stbl, timescale, codec, description, width, height } = videoTrack(v, buf);
  const get = (t: string) => [...boxes(v, stbl.body, stbl.end)].find((b) => b.type === t);

  // Sizes.
  const stsz = get("stsz");
  if (!stsz) throw new Error("mp4: no stsz");
  const fixed = v.getUint32(stsz.body + 4);
  const count = v.getUint32(stsz.body + 8);
  const sizes = Array.from({ length: count }, (_, i) => (fixed ? fixed : v.getUint32(stsz.body + 12 + 4 * i)));

  // Chunk offsets and samples per chunk.
  const stco = get("stco") ?? get("co64");
  const stsc = get("stsc");
  if (!stco || !stsc) throw new Error("mp4: no chunk tables");
  const chunks = v.getUint32(stco.body + 4);
  const chunkOffset = (i: number) =>
    stco.type === "co64" ? Number(v.getBigUint64(stco.body + 8 + 8 * i)) : v.getUint32(stco.body + 8 + 4 * i);
  const runs = v.getUint32(stsc.body + 4);
  const offsets: number[] = [];
  for (let r = 0; r < runs; r++) {
    const first = v.getUint32(stsc.body + 8 + 12 * r) - 1;
    const per = v.getUint32(stsc.body + 12 + 12 * r);
    const last = r + 1 < runs ? v.getUint32(stsc.body + 8 + 12 * (r + 1)) - 1 : chunks;
    for (let c = first; c < last; c++) {
      let o = chunkOffset(c);
      for (let s = 0; s < per && offsets.length < count; s++) {
        offsets.push(o);
        o += sizes[offsets.length - 1];
      }
    }
  }
  if (offsets.length !== count) throw new Error("mp4: chunk tables do not cover every sample");

  // Timing.
  const stts = get("stts");
  if (!stts) throw new Error("mp4: no stts");
  const dts: number[] = [];
  let t = 0;
  for (let e = 0, n = v.getUint32(stts.body + 4); e < n; e++) {
    const c = v.getUint32(stts.body + 8 + 8 * e);
    const d = v.getUint32(stts.body + 12 + 8 * e);
    for (let i = 0; i < c; i++, t += d) dts.push(t);
  }
  const cts = dts.slice();
  const ctts = get("ctts");
  if (ctts) {
    const signed = v.getUint8(ctts.body) === 1;
    let i = 0;
    for (let e = 0, n = v.getUint32(ctts.body + 4); e < n; e++) {
      const c = v.getUint32(ctts.body + 8 + 8 * e);
      const off = signed ? v.getInt32(ctts.body + 12 + 8 * e) : v.getUint32(ctts.body + 12 + 8 * e);
      for (let k = 0; k < c && i < count; k++, i++) cts[i] += off;
    }
  }
  const stss = get("stss");
  const keys = new Set<number>();
  if (stss) for (let e = 0, n = v.getUint32(stss.body + 4); e < n; e++) keys.add(v.getUint32(stss.body + 8 + 4 * e) - 1);
  const samples: Sample[] = sizes.map((size, i) => ({
    offset: offsets[i],
    size,
    key: stss ? keys.has(i) : true,
    cts: cts[i],
    dts: dts[i],
  }));
  return { codec, description, width, height, timescale, samples };
}

/**
 * Parses track run `run` of a movie fragment (`moof` + `mdat`: cpsl package version 6 holds a
 * segment's layer streams in one, stream k in run k; versions 4 and 5 wrote one fragment of one
 * run per stream) with the init segment (`ftyp` + `moov`) that goes before it. Sample offsets
 * are in `frag`; decoding times start at 0 with the run. H.264 and H.265 fragments carry their
 * parameter sets in band (`avc3`, `hev1`), so `annexB` is set: the samples are to be decoded
 * with start codes and no description.
 */
export function demuxFragment(init: ArrayBuffer, frag: ArrayBuffer, run = 0): Track {
  const iv = new DataView(init);
  const { timescale, codec, description, width, height } = videoTrack(iv, init);
  const top = { type: "", start: 0, end: init.byteLength, body: 0 };
  const trex = child(iv, top, ["moov", "mvex", "trex"]);
  const defaultDuration = iv.getUint32(trex.body + 12);
  const defaultFlags = iv.getUint32(trex.body + 20);

  const v = new DataView(frag);
  const all = [...boxes(v, 0, frag.byteLength)];
  const moof = all.find((b) => b.type === "moof");
  if (!moof) throw new Error("mp4: no movie fragment ('moof')");
  const traf = child(v, moof, ["traf"]);
  const tfhd = child(v, traf, ["tfhd"]);
  const tfFlags = v.getUint32(tfhd.body) & 0xffffff;
  let at = tfhd.body + 8;
  let base = moof.start;
  if (tfFlags & 0x1) {
    base = Number(v.getBigUint64(at));
    at += 8;
  }
  if (tfFlags & 0x2) at += 4;
  const duration = tfFlags & 0x8 ? v.getUint32(at) : defaultDuration;
  if (tfFlags & 0x8) at += 4;
  if (tfFlags & 0x10) at += 4;
  const flagsDefault = tfFlags & 0x20 ? v.getUint32(at) : defaultFlags;
  const samples: Sample[] = [];
  let next = base;
  const runs = [...boxes(v, traf.body, traf.end)].filter((b) => b.type === "trun");
  if (run >= runs.length) throw new Error(`mp4: stream ${run} asked for, the fragment holds ${runs.length}`);
  for (const [r, trun] of runs.entries()) {
    let dts = 0;
    const head = v.getUint32(trun.body);
    const [version, flags] = [head >>> 24, head & 0xffffff];
    const count = v.getUint32(trun.body + 4);
    let p = trun.body + 8;
    if (flags & 0x1) {
      next = base + v.getInt32(p);
      p += 4;
    }
    let first: number | null = null;
    if (flags & 0x4) {
      first = v.getUint32(p);
      p += 4;
    }
    const per = [0x100, 0x200, 0x400, 0x800].filter((f) => flags & f).length * 4;
    if (!(flags & 0x200)) throw new Error("mp4: a track run without sample sizes");
    if (p + count * per > trun.end) throw new Error(`mp4: a track run of ${count} samples is cut`);
    for (let i = 0; i < count; i++) {
      const d = flags & 0x100 ? v.getUint32((p += 4) - 4) : duration;
      const size = v.getUint32((p += 4) - 4);
      const f = flags & 0x400 ? v.getUint32((p += 4) - 4) : i === 0 && first !== null ? first : flagsDefault;
      const off = flags & 0x800 ? (version ? v.getInt32((p += 4) - 4) : v.getUint32((p += 4) - 4)) : 0;
      if (next + size > frag.byteLength) throw new Error(`mp4: sample ${i} of run ${r} lies past the end of the fragment`);
      if (r === run) samples.push({ offset: next, size, key: (f & 0x10000) === 0, cts: dts + off, dts });
      next += size;
      dts += d;
    }
  }
  if (!samples.length) throw new Error(`mp4: run ${run} of the fragment has no samples`);
  const annexB = codec.startsWith("avc") || codec.startsWith("hev") || codec.startsWith("hvc");
  return { codec, description: annexB ? undefined : description, width, height, timescale, samples, annexB };
}

/** A sample of 4-byte length-prefixed NAL units with start codes instead (same length). */
export function toAnnexB(sample: Uint8Array): Uint8Array {
  const out = sample.slice();
  const v = new DataView(out.buffer, out.byteOffset, out.byteLength);
  for (let p = 0; p + 4 <= out.length; ) {
    const len = v.getUint32(p);
    v.setUint32(p, 1);
    p += 4 + len;
  }
  return out;
}
