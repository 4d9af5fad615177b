// Frame-locked decoding of one segment's layer streams with WebCodecs: one VideoDecoder per
// stream, fed in decoding order a few frames ahead of what is shown, outputs keyed by
// presentation index, so that frame i of every stream is available together.
import { demux, demuxFragment, toAnnexB } from "./mp4.js";
/** Frames fed beyond the one asked for (covers the encoder's reordering depth). */
const LOOKAHEAD = 6;
class StreamDecoder {
    decoder;
    track;
    data;
    /** Samples in decoding order with their presentation index. */
    order;
    fed = 0;
    flushed = false;
    ready = new Map();
    error = null;
    wake = null;
    /** `data`: a progressive MP4, or a movie fragment whose init segment is `init` (the stream
     * is its track run `run`). */
    constructor(data, init, run = 0) {
        this.data = data;
        this.track = init ? demuxFragment(init, data, run) : demux(data);
        const byCts = this.track.samples.map((s, i) => ({ i, cts: s.cts })).sort((a, b) => a.cts - b.cts);
        const rank = new Map();
        byCts.forEach((s, r) => rank.set(s.i, r));
        this.order = this.track.samples.map((_, i) => ({ sample: i, index: rank.get(i) }));
        this.decoder = new VideoDecoder({
            output: (f) => {
                this.ready.set(f.timestamp, f);
                this.poke();
            },
            error: (e) => {
                this.error = new Error(`decoder: ${e.message}`);
                this.poke();
            },
        });
        this.decoder.addEventListener("dequeue", () => this.poke());
    }
    get frames() {
        return this.track.samples.length;
    }
    config() {
        return {
            codec: this.track.codec,
            description: this.track.description,
            codedWidth: this.track.width,
            codedHeight: this.track.height,
            optimizeForLatency: true,
        };
    }
    async configure() {
        const cfg = this.config();
        const ok = await VideoDecoder.isConfigSupported(cfg);
        if (!ok.supported)
            throw new Error(`this browser cannot decode '${cfg.codec}' with WebCodecs`);
        this.decoder.configure(cfg);
    }
    poke() {
        const w = this.wake;
        this.wake = null;
        w?.();
    }
    waitEvent(ms) {
        return new Promise((resolve) => {
            const timer = setTimeout(() => {
                this.wake = null;
                resolve(false);
            }, ms);
            this.wake = () => {
                clearTimeout(timer);
                resolve(true);
            };
        });
    }
    /** The decoded frame of presentation index `i` (kept until released). */
    async frame(i) {
        let stalled = false;
        for (;;) {
            if (this.error)
                throw this.error;
            const f = this.ready.get(i);
            if (f)
                return f;
            if (this.fed < this.order.length && (this.fed <= i + LOOKAHEAD || stalled) && this.decoder.decodeQueueSize < 4) {
                const s = this.track.samples[this.order[this.fed].sample];
                const bytes = new Uint8Array(this.data, s.offset, s.size);
                this.decoder.decode(new EncodedVideoChunk({
                    type: s.key ? "key" : "delta",
                    timestamp: this.order[this.fed].index,
                    data: this.track.annexB ? toAnnexB(bytes) : bytes,
                }));
                this.fed++;
                stalled = false;
            }
            else if (this.fed === this.order.length && !this.flushed) {
                this.flushed = true;
                await this.decoder.flush();
            }
            else if (this.fed === this.order.length && this.flushed) {
                throw new Error(`frame ${i} was never decoded`);
            }
            else {
                stalled = !(await this.waitEvent(100));
            }
        }
    }
    /** Closes every frame before `i`. */
    release(i) {
        for (const [k, f] of this.ready)
            if (k < i) {
                f.close();
                this.ready.delete(k);
            }
    }
    close() {
        this.release(Infinity);
        if (this.decoder.state !== "closed")
            this.decoder.close();
    }
}
/** The layer streams of one segment, decoded in lock-step. */
export class SegmentDecoder {
    streams;
    constructor(streams) {
        this.streams = streams;
    }
    /** Demuxes and configures a decoder per stream: `data[k]` is stream k's MP4 or fragment,
     * `inits[k]` the fragment's init segment, `runs[k]` its track run there (0 if absent). */
    static async open(data, frames, inits = [], runs = []) {
        const streams = data.map((d, k) => new StreamDecoder(d, inits[k], runs[k] ?? 0));
        for (const [k, s] of streams.entries())
            if (s.frames !== frames)
                throw new Error(`layer stream ${k} has ${s.frames} frames, the segment ${frames}`);
        await Promise.all(streams.map((s) => s.configure()));
        return new SegmentDecoder(streams);
    }
    /** Frame `i` (within the segment) of every stream; earlier frames are closed. */
    async frame(i) {
        const out = await Promise.all(this.streams.map((s) => s.frame(i)));
        for (const s of this.streams)
            s.release(i);
        return out;
    }
    close() {
        for (const s of this.streams)
            s.close();
    }
}
