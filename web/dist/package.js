/** A segment's files: its layer streams' (their own or the shared fragment), then its side stream. */
export function segmentFiles(s) {
    const streams = s.fragment ? [s.fragment] : s.streams.map((t) => t.file);
    return [...streams, s.side];
}
/** The downscale factors a stream may have in a package of `version` (as cpsl-package's
 * `scales_of`). */
function scalesOf(version) {
    return version <= 1 ? [1] : version === 2 ? [1, 2, 4] : [1, 2, 4, 8];
}
/** Checks what the player relies on; throws a readable error otherwise. */
export function checkManifest(m) {
    if (m.format !== "cpsl-package")
        throw new Error(`not a cpsl package (format '${m.format}')`);
    if (!(m.version >= 1 && m.version <= 6))
        throw new Error(`package version ${m.version}: this player reads versions 1 to 6`);
    if (m.layout?.kind !== "colour-over-alpha")
        throw new Error(`layout '${m.layout?.kind}' is not supported`);
    if (!m.segments?.length)
        throw new Error("the package has no segments");
    const inits = new Set((m.inits ?? []).map((f) => f.path));
    for (const [i, s] of m.segments.entries()) {
        if ((m.version >= 6) !== Boolean(s.fragment))
            throw new Error(`segment ${i}: version ${m.version} segments ${m.version >= 6 ? "hold their streams in one fragment" : "have no shared fragment"}`);
        for (const [k, t] of s.streams.entries()) {
            const name = `segment ${i} stream ${k}`;
            if ((m.version >= 6) === Boolean(t.file))
                throw new Error(`${name}: ${t.file ? "a version 6 stream has no file of its own" : "no file"}`);
            if (!scalesOf(m.version).includes(t.scale ?? 1))
                throw new Error(`${name}: scale ${t.scale} is not one of ${scalesOf(m.version).join(", ")} (version ${m.version} packages)`);
            if (m.version >= 4 && !(t.init && inits.has(t.init)))
                throw new Error(`${name}: no init segment listed for it`);
        }
    }
    return m;
}
/** Bits per second of a segment's files. */
export function segmentBitrate(m, i) {
    const s = m.segments[i];
    const bytes = segmentFiles(s).reduce((a, f) => a + f.bytes, 0);
    return (bytes * 8 * m.frame_rate) / s.frames;
}
/** Mean bits per second of a package. */
export function packageBitrate(m) {
    let bytes = 0;
    for (const s of m.segments)
        bytes += segmentFiles(s).reduce((a, f) => a + f.bytes, 0);
    return (bytes * 8 * m.frame_rate) / m.frames;
}
/** Steps per unit of log inverse depth in a mesh grid (side.rs `GRID_STEP` = 1 / 1024). */
const GRID_SCALE = 1024;
async function inflateRaw(bytes, expected) {
    const ds = new DecompressionStream("deflate-raw");
    const out = new Uint8Array(await new Response(new Blob([bytes]).stream().pipeThrough(ds)).arrayBuffer());
    if (out.length !== expected)
        throw new Error("side stream: compressed data inflates to the wrong length");
    return out;
}
/** Parses a side stream (`side.bin`, versions 1 and 2; see crates/6-coding/cpsl-package/src/side.rs). */
export async function parseSide(buf) {
    const b = new Uint8Array(buf);
    const v = new DataView(buf);
    const magic = String.fromCharCode(...b.subarray(0, 8));
    if (b.length < 40 || magic !== "CPSLSIDE")
        throw new Error("not a cpsl side stream");
    const version = v.getUint16(8, true);
    if (version !== 1 && version !== 2)
        throw new Error(`side stream version ${version}: this player reads versions 1 and 2`);
    const recordBytes = version >= 2 ? 28 : 16;
    const frames = v.getUint32(20, true);
    const streams = v.getUint16(24, true);
    let pos = 40;
    const out = [];
    for (let r = 0; r < frames; r++) {
        if (pos + 4 > b.length)
            throw new Error(`side stream truncated at record ${r}`);
        const len = v.getUint32(pos, true);
        const p = pos + 4;
        if (len < 12 || p + len + 4 > b.length)
            throw new Error(`side stream record ${r} truncated`);
        const index = v.getUint32(p, true);
        const n = b[p + 6];
        if (n === 0 || n > streams)
            throw new Error(`side stream record ${r}: ${n} layers`);
        const layers = [];
        const meshes = [];
        for (let i = 0; i < n; i++) {
            const o = p + 8 + i * recordBytes;
            let geometry = { kind: "plane" };
            if (b[o + 1] === 2 && version >= 2) {
                meshes.push(i);
            }
            else if (b[o + 1] === 1 && version >= 2) {
                const m = [0, 1, 2].map((j) => v.getFloat32(o + 16 + 4 * j, true));
                if (!m.every(Number.isFinite))
                    throw new Error(`side stream record ${r}: layer ${i} has a non-finite plane`);
                geometry = { kind: "slanted", m };
            }
            else if (b[o + 1] !== 0) {
                throw new Error(`side stream record ${r}: layer ${i} has unknown geometry ${b[o + 1]}`);
            }
            layers.push({ stream: b[o], depth: v.getFloat32(o + 4, true), geometry });
        }
        let e = p + 8 + n * recordBytes;
        // Mesh layers' grids follow the layer table (see side.rs: quantised log inverse depth,
        // each vertex predicted from the same vertex of a grid of the previous record, or from its
        // left neighbour, the first column's from above).
        const previous = out.length ? out[out.length - 1] : null;
        for (const i of meshes) {
            const [step, cols, rows, refIndex] = [0, 2, 4, 6].map((d) => v.getUint16(e + d, true));
            const glen = v.getUint32(e + 8, true);
            const count = cols * rows;
            let ref = null;
            if (refIndex > 0) {
                const g = previous?.layers[refIndex - 1]?.geometry;
                if (g?.kind !== "mesh" || g.grid.cols !== cols || g.grid.rows !== rows)
                    throw new Error(`side stream record ${r}: layer ${i}'s grid refers to a missing grid`);
                ref = Int16Array.from(g.grid.inv, (x) => Math.round(Math.log(x) * GRID_SCALE));
            }
            const planes = await inflateRaw(b.subarray(e + 12, e + 12 + glen), 2 * count);
            const inv = new Float32Array(count);
            const q = new Int16Array(count);
            for (let k = 0; k < count; k++) {
                const pred = ref ? ref[k] : k === 0 ? 0 : k % cols === 0 ? q[k - cols] : q[k - 1];
                q[k] = pred + (planes[k] | (planes[count + k] << 8));
                inv[k] = Math.exp(q[k] / GRID_SCALE);
            }
            layers[i].geometry = { kind: "mesh", grid: { step, cols, rows, inv } };
            e += 12 + glen;
        }
        const edcLen = v.getUint32(e, true);
        const c = e + 4;
        const step = v.getFloat32(c + 2, true);
        const samples = v.getUint32(c + 6, true);
        const planes = await inflateRaw(b.subarray(c + 10, c + edcLen), samples * 8);
        const acc = new Map();
        for (let i = 0; i < samples; i++) {
            const key = planes[4 * samples + i] * 256 + planes[5 * samples + i];
            const fo = ((planes[6 * samples + i] << 24) >> 24) * step;
            const bo = ((planes[7 * samples + i] << 24) >> 24) * step;
            const a = acc.get(key) ?? [0, 0, 0];
            acc.set(key, [a[0] + fo, a[1] + bo, a[2] + 1]);
        }
        const offsets = new Map();
        for (const [k, a] of acc)
            offsets.set(k, [a[0] / a[2], a[1] / a[2]]);
        out.push({ index, layers, offsets });
        pos = p + len + 4;
    }
    return out;
}
