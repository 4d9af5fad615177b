// The cpsl browser player: loads a package (or a set of bitrate variants), decodes its layer
// streams frame-locked with WebCodecs, renders them with WebGL2 from the viewer's pose, and
// lets the viewer move (mouse / touch drag, wheel, keys, device orientation), play, pause
// and seek. URL parameters: `src` (package folder or variants.json URL; default: the first
// package `cpsl serve` lists), `frame`, `pose` (`tx,ty,tz,rx,ry,rz` as `cpsl render --pose`),
// `paused=1`, `dps=0`, `fill=0` (black where the layers leave the view uncovered instead of
// the push-pull fill), `filter=cubic` (Catmull-Rom resampling, sharper, 4x the texel reads;
// bilinear by default), `variant` (index: fixed, no adaptation).

import { SegmentDecoder } from "./decode.js";
import { checkManifest, type Manifest, packageBitrate, parseSide, segmentFiles, type SideFrame } from "./package.js";
import { type Pose, parsePose, poseFromEuler } from "./pose.js";
import { Renderer } from "./render.js";

interface Variant {
  base: URL;
  manifest: Manifest;
  bitrate: number;
}

interface LoadedSegment {
  index: number;
  variant: number;
  decoder: SegmentDecoder;
  side: SideFrame[];
  /** Downscale factor per stream. */
  scales: number[];
}

const $ = <T extends HTMLElement>(id: string) => document.getElementById(id) as T;

async function fetchOk(url: URL | string): Promise<Response> {
  const r = await fetch(url);
  if (!r.ok) throw new Error(`${url}: HTTP ${r.status}`);
  return r;
}

/** The time (ms) covered by the union of the intervals `spans` (concurrent downloads count once). */
function coveredTime(spans: [number, number][]): number {
  let total = 0;
  let end = -Infinity;
  for (const [a, b] of [...spans].sort((x, y) => x[0] - y[0])) {
    if (b <= end) continue;
    total += b - Math.max(a, end);
    end = b;
  }
  return total;
}

/** The packages behind `src`: one package folder, or every package of a variant set. */
async function loadVariants(src: string): Promise<Variant[]> {
  const url = new URL(src, location.href);
  const one = async (base: URL): Promise<Variant> => {
    const manifest = checkManifest(await (await fetchOk(new URL("manifest.json", base))).json());
    return { base, manifest, bitrate: packageBitrate(manifest) };
  };
  if (!url.pathname.endsWith(".json")) {
    if (!url.pathname.endsWith("/")) url.pathname += "/";
    return [await one(url)];
  }
  const set = await (await fetchOk(url)).json();
  if (set.format !== "cpsl-variants" || !Array.isArray(set.variants) || !set.variants.length)
    throw new Error(`${url}: not a cpsl variant set`);
  const all = await Promise.all(set.variants.map((p: string) => one(new URL(p.replace(/\/?$/, "/"), url))));
  const first = all[0].manifest;
  for (const v of all) {
    const m = v.manifest;
    const aligned =
      m.frames === first.frames &&
      m.camera.width === first.camera.width &&
      m.camera.height === first.camera.height &&
      m.segments.length === first.segments.length &&
      m.segments.every((s: { start: number; frames: number }, i: number) => s.start === first.segments[i].start && s.frames === first.segments[i].frames);
    if (!aligned) throw new Error(`${v.base}: its frames or segments differ from the set's first variant`);
  }
  return all.sort((a, b) => a.bitrate - b.bitrate);
}

class Player {
  private variants: Variant[];
  private renderer: Renderer;
  private canvas: HTMLCanvasElement;
  private current: LoadedSegment | null = null;
  private next: Promise<LoadedSegment> | null = null;
  /** Measured download throughput, bits per second (exponential average). */
  private throughput = 0;
  /** Init segments by URL, fetched once and checked against their manifest entries. */
  private inits = new Map<string, Promise<ArrayBuffer>>();
  private fixedVariant: number | null;
  variant = 0;
  frame = 0;
  playing = true;
  stereo = false;
  eyeSeparation = 0.06;
  // Orbit / pan / dolly state of the viewer.
  yaw = 0;
  pitch = 0;
  pan: [number, number] = [0, 0];
  dolly = 0;
  explicitPose: Pose | null = null;
  private shownFrame = -1;
  private lastTick = 0;
  private frameTimes: number[] = [];
  /** Frames decoded and uploaded so far. */
  shown = 0;
  private showTimes: number[] = [];
  private busy = false;
  private drawn = "";
  private queue: Promise<void> = Promise.resolve();
  error: string | null = null;

  constructor(canvas: HTMLCanvasElement, variants: Variant[], fixedVariant: number | null) {
    this.canvas = canvas;
    this.variants = variants;
    this.fixedVariant = fixedVariant;
    this.variant = fixedVariant ?? 0;
    const m = variants[0].manifest;
    canvas.width = m.camera.width;
    canvas.height = m.camera.height;
    this.renderer = new Renderer(canvas, m.camera, m.layout.coded_height);
  }

  get manifest(): Manifest {
    return this.variants[this.variant].manifest;
  }

  segmentOf(frame: number): number {
    const segs = this.manifest.segments;
    let i = segs.length - 1;
    while (i > 0 && segs[i].start > frame) i--;
    return i;
  }

  /** The depth the viewer orbits around: the middle layer's. */
  private pivot(): number {
    const side = this.current?.side[0];
    if (!side) return 1;
    return side.layers[Math.floor(side.layers.length / 2)].depth;
  }

  pose(eye = 0): Pose {
    if (this.explicitPose && eye === 0) return this.explicitPose;
    const base = this.explicitPose;
    if (base) {
      const t = base.translation;
      const r = base.rotation;
      const e = eye * this.eyeSeparation * 0.5;
      return { rotation: r, translation: [t[0] + r[0][0] * e, t[1] + r[1][0] * e, t[2] + r[2][0] * e] };
    }
    // Orbit about (0, 0, pivot): the viewer looks at the pivot from its rotated position.
    const zc = this.pivot();
    const p = poseFromEuler([0, 0, 0], -this.pitch, this.yaw, 0);
    const r = p.rotation;
    const back = zc - this.dolly;
    const e = eye * this.eyeSeparation * 0.5;
    const local = [this.pan[0] + e, this.pan[1], -back];
    const t: [number, number, number] = [0, 0, zc];
    for (let i = 0; i < 3; i++) t[i] += r[i][0] * local[0] + r[i][1] * local[1] + r[i][2] * local[2];
    return { rotation: r, translation: t };
  }

  resetView() {
    this.yaw = this.pitch = this.dolly = 0;
    this.pan = [0, 0];
    this.explicitPose = null;
  }

  /** Downloads segment `i` of variant `v` (measuring throughput) and opens its decoders. */
  private async load(i: number, v: number): Promise<LoadedSegment> {
    const variant = this.variants[v];
    const seg = variant.manifest.segments[i];
    const files = segmentFiles(seg);
    // Each file's body time runs from its headers to its last byte: the link's rate, without the
    // round trips before the first byte (which dominate small segments on any link). The
    // browser's Resource Timing says when the bytes arrived; where it does not (a cross-origin
    // server without Timing-Allow-Origin), the time until the body has been read here stands in,
    // which a busy page stretches.
    const bodies: [number, number][] = [];
    const bufs = await Promise.all(
      files.map(async (f) => {
        const url = new URL(f.path, variant.base);
        const r = await fetchOk(url);
        const t = performance.now();
        const b = await r.arrayBuffer();
        const timing = performance.getEntriesByName(url.href).pop() as PerformanceResourceTiming | undefined;
        bodies.push(timing && timing.responseStart > 0 && timing.responseEnd >= timing.responseStart ? [timing.responseStart, timing.responseEnd] : [t, performance.now()]);
        return b;
      }),
    );
    performance.clearResourceTimings();
    for (const [k, b] of bufs.entries())
      if (b.byteLength !== files[k].bytes) throw new Error(`${files[k].path}: ${b.byteLength} bytes, the manifest says ${files[k].bytes}`);
    const secs = Math.max(coveredTime(bodies) / 1000, 1e-3);
    const bits = bufs.reduce((a, b) => a + b.byteLength * 8, 0);
    const rate = bits / secs;
    this.throughput = this.throughput ? 0.7 * this.throughput + 0.3 * rate : rate;
    const side = await parseSide(bufs[bufs.length - 1]);
    if (side.length !== seg.frames) throw new Error(`segment ${i}: side stream has ${side.length} frames, the manifest ${seg.frames}`);
    const inits = await Promise.all(seg.streams.map((s) => this.initOf(variant, s.init)));
    // Version 6: the streams are the track runs of the segment's one fragment.
    const data = seg.fragment ? seg.streams.map(() => bufs[0]) : bufs.slice(0, -1);
    const runs = seg.fragment ? seg.streams.map((_, k) => k) : [];
    const decoder = await SegmentDecoder.open(data, seg.frames, inits, runs);
    return { index: i, variant: v, decoder, side, scales: seg.streams.map((s) => s.scale ?? 1) };
  }

  /** The init segment `path` of `variant` (none for self-contained streams). */
  private initOf(variant: Variant, path?: string): Promise<ArrayBuffer | undefined> {
    if (!path) return Promise.resolve(undefined);
    const entry = variant.manifest.inits?.find((f) => f.path === path);
    if (!entry) return Promise.reject(new Error(`init segment ${path} is not in the manifest`));
    const url = new URL(path, variant.base).href;
    let p = this.inits.get(url);
    if (!p) {
      p = fetchOk(url).then(async (r) => {
        const b = await r.arrayBuffer();
        if (b.byteLength !== entry.bytes) throw new Error(`${path}: ${b.byteLength} bytes, the manifest says ${entry.bytes}`);
        return b;
      });
      p.catch(() => this.inits.delete(url));
      this.inits.set(url, p);
    }
    return p;
  }

  /** Adaptive choice: the best variant whose bitrate fits 70 % of the measured throughput. */
  private chooseVariant(): number {
    if (this.fixedVariant !== null) return this.fixedVariant;
    let best = 0;
    for (const [i, v] of this.variants.entries()) if (v.bitrate <= 0.7 * this.throughput) best = i;
    return best;
  }

  private async segmentFor(frame: number): Promise<LoadedSegment> {
    const i = this.segmentOf(frame);
    if (this.current?.index === i) return this.current;
    let seg: LoadedSegment | null = null;
    if (this.next) {
      const n = await this.next.catch(() => null);
      this.next = null;
      if (n && n.index === i) seg = n;
      else n?.decoder.close();
    }
    if (!seg) seg = await this.load(i, this.chooseVariant());
    this.current?.decoder.close();
    this.current = seg;
    this.variant = seg.variant;
    // Prefetch the following segment while this one plays.
    if (i + 1 < this.manifest.segments.length) this.next = this.load(i + 1, this.chooseVariant());
    return seg;
  }

  /** Decodes and uploads `frame`, after any show already under way (seeks, keys and the
   * playback clock may ask at once; decoders take one request at a time). */
  show(frame: number): Promise<void> {
    const run = this.queue.then(() => this.showNow(frame));
    this.queue = run.catch(() => undefined);
    return run;
  }

  /** Decodes and uploads `frame`; a frame before the last one restarts its segment. */
  private async showNow(frame: number) {
    const t0 = performance.now();
    const i = this.segmentOf(frame);
    if (this.current && this.current.index === i && frame < this.shownFrame) {
      // Seeking backwards inside a segment: decode it again from its I-frame.
      this.current.decoder.close();
      this.current = null;
    }
    const seg = await this.segmentFor(frame);
    const local = frame - this.manifest.segments[i].start;
    const pictures = await seg.decoder.frame(local);
    await this.renderer.upload(pictures, seg.side[local], seg.scales);
    this.shownFrame = frame;
    this.frame = frame;
    this.shown++;
    this.showTimes.push(performance.now() - t0);
    if (this.showTimes.length > 60) this.showTimes.shift();
  }

  draw() {
    const t0 = performance.now();
    const { width: w, height: h } = this.canvas;
    if (this.stereo) {
      this.renderer.render(this.pose(-1));
      this.renderer.show(0, 0, w / 2, h);
      this.renderer.render(this.pose(1));
      this.renderer.show(w / 2, 0, w / 2, h);
    } else {
      this.renderer.render(this.pose());
      this.renderer.show(0, 0, w, h);
    }
    this.renderer.gl.finish();
    this.frameTimes.push(performance.now() - t0);
    if (this.frameTimes.length > 60) this.frameTimes.shift();
  }

  pixels(): Uint8Array {
    this.renderer.render(this.pose());
    return this.renderer.pixels();
  }

  set dps(on: boolean) {
    this.renderer.dpsEnabled = on;
  }

  set fill(on: boolean) {
    this.renderer.fillEnabled = on;
  }

  set cubic(on: boolean) {
    this.renderer.cubic = on;
  }

  /** Median time of the last 60 draws (render and present), milliseconds. */
  medianDrawMs(): number {
    return median(this.frameTimes);
  }

  /** Median time of the last 60 frame changes (fetch, decode, upload), milliseconds. */
  medianShowMs(): number {
    return median(this.showTimes);
  }

  status(): string {
    const med = this.medianDrawMs();
    const v = this.variants[this.variant];
    return (
      `frame ${this.frame + 1}/${this.manifest.frames} · render ${med.toFixed(1)} ms` +
      ` · ${(v.bitrate / 1e6).toFixed(2)} Mbit/s` +
      (this.variants.length > 1 ? ` (variant ${this.variant + 1}/${this.variants.length}, link ${(this.throughput / 1e6).toFixed(1)} Mbit/s)` : "")
    );
  }

  /** One animation tick: advance when playing and the next frame is due, then draw. */
  async tick(now: number) {
    if (this.busy) return;
    this.busy = true;
    try {
      const due = now - this.lastTick >= 1000 / this.manifest.frame_rate;
      if (this.playing && due) {
        this.lastTick = now;
        await this.show((this.frame + 1) % this.manifest.frames);
      }
      // Draw only when the picture or the view changed.
      const key = JSON.stringify([this.shown, this.pose(-1), this.pose(1), this.stereo]);
      if (key !== this.drawn) {
        this.drawn = key;
        this.draw();
      }
    } finally {
      this.busy = false;
    }
  }
}

function median(v: number[]): number {
  const s = [...v].sort((a, b) => a - b);
  return s.length ? s[Math.floor(s.length / 2)] : 0;
}

function controls(player: Player, canvas: HTMLCanvasElement) {
  let drag: { x: number; y: number; button: number } | null = null;
  const pointers = new Map<number, { x: number; y: number }>();
  canvas.addEventListener("pointerdown", (e) => {
    canvas.setPointerCapture(e.pointerId);
    pointers.set(e.pointerId, { x: e.clientX, y: e.clientY });
    drag = { x: e.clientX, y: e.clientY, button: e.shiftKey ? 2 : e.button };
    player.explicitPose = null;
  });
  canvas.addEventListener("pointermove", (e) => {
    if (!drag) return;
    const scale = 1 / canvas.clientWidth;
    const dx = (e.clientX - drag.x) * scale;
    const dy = (e.clientY - drag.y) * scale;
    if (pointers.size >= 2) {
      // Two fingers: dolly.
      player.dolly += -dy * player.manifest.camera.fx * 0.002;
    } else if (drag.button === 2 || drag.button === 1) {
      player.pan = [player.pan[0] - dx * 0.5, player.pan[1] - dy * 0.5];
    } else {
      player.yaw += dx * 20;
      player.pitch -= dy * 20;
    }
    drag = { ...drag, x: e.clientX, y: e.clientY };
    pointers.set(e.pointerId, { x: e.clientX, y: e.clientY });
  });
  const end = (e: PointerEvent) => {
    pointers.delete(e.pointerId);
    if (!pointers.size) drag = null;
  };
  canvas.addEventListener("pointerup", end);
  canvas.addEventListener("pointercancel", end);
  canvas.addEventListener("contextmenu", (e) => e.preventDefault());
  canvas.addEventListener(
    "wheel",
    (e) => {
      e.preventDefault();
      player.explicitPose = null;
      player.dolly += -e.deltaY * 0.0005;
    },
    { passive: false },
  );
  canvas.addEventListener("dblclick", () => player.resetView());
  const seek = $("seek") as HTMLInputElement;
  seek.max = String(player.manifest.frames - 1);
  seek.addEventListener("input", () => {
    player.playing = false;
    player.show(Number(seek.value)).catch(fail);
  });
  const play = $("play") as HTMLButtonElement;
  const toggle = () => {
    player.playing = !player.playing;
  };
  play.addEventListener("click", toggle);
  ($("stereo") as HTMLInputElement).addEventListener("change", (e) => {
    player.stereo = (e.target as HTMLInputElement).checked;
  });
  ($("eye") as HTMLInputElement).addEventListener("input", (e) => {
    player.eyeSeparation = Number((e.target as HTMLInputElement).value);
  });
  window.addEventListener("keydown", (e) => {
    const step = 0.02;
    if (e.key === " ") toggle();
    else if (e.key === "r") player.resetView();
    else if (e.key === "ArrowLeft") player.pan[0] -= step;
    else if (e.key === "ArrowRight") player.pan[0] += step;
    else if (e.key === "ArrowUp") player.dolly += step;
    else if (e.key === "ArrowDown") player.dolly -= step;
    else if (e.key === ",") player.show(Math.max(player.frame - 1, 0)).catch(fail);
    else if (e.key === ".") player.show(Math.min(player.frame + 1, player.manifest.frames - 1)).catch(fail);
    else return;
    e.preventDefault();
  });
  // Device orientation (phones, tablets): tilting looks around from the starting attitude.
  let origin: { beta: number; gamma: number } | null = null;
  const orient = (e: DeviceOrientationEvent) => {
    if (e.beta === null || e.gamma === null) return;
    origin ??= { beta: e.beta, gamma: e.gamma };
    player.explicitPose = null;
    player.yaw = Math.max(-15, Math.min(15, (e.gamma - origin.gamma) * 0.5));
    player.pitch = Math.max(-15, Math.min(15, (origin.beta - e.beta) * 0.5));
  };
  $("orient").addEventListener("click", async () => {
    const D = DeviceOrientationEvent as unknown as { requestPermission?: () => Promise<string> };
    if (D.requestPermission && (await D.requestPermission()) !== "granted") return;
    origin = null;
    window.addEventListener("deviceorientation", orient);
  });
  const status = $("status");
  const loop = async (now: number) => {
    try {
      await player.tick(now);
      play.textContent = player.playing ? "pause" : "play";
      seek.value = String(player.frame);
      status.textContent = player.status();
    } catch (err) {
      fail(err);
      return;
    }
    requestAnimationFrame(loop);
  };
  requestAnimationFrame(loop);
}

function fail(err: unknown) {
  const msg = err instanceof Error ? err.message : String(err);
  $("status").textContent = `error: ${msg}`;
  (window as unknown as { cpsl: Record<string, unknown> }).cpsl.error = msg;
  console.error(err);
}

async function main() {
  const api: Record<string, unknown> = { ready: false, error: null };
  (window as unknown as { cpsl: Record<string, unknown> }).cpsl = api;
  const q = new URLSearchParams(location.search);
  let src = q.get("src");
  if (!src) {
    const list = await (await fetchOk("/api/packages")).json();
    src = list.variant_sets?.[0] ?? list.packages?.[0]?.url;
    if (!src) throw new Error("no package to play: pass ?src=<package folder URL>");
  }
  $("title").textContent = src;
  if (!("VideoDecoder" in window)) throw new Error("this browser has no WebCodecs VideoDecoder");
  const variants = await loadVariants(src);
  const fixed = q.has("variant") ? Math.min(Number(q.get("variant")), variants.length - 1) : null;
  const canvas = $("view") as HTMLCanvasElement;
  const player = new Player(canvas, variants, fixed);
  if (q.has("pose")) player.explicitPose = parsePose(q.get("pose")!);
  if (q.get("dps") === "0") player.dps = false;
  if (q.get("fill") === "0") player.fill = false;
  if (q.get("filter") === "cubic") player.cubic = true;
  player.playing = q.get("paused") !== "1";
  const start = Math.min(Math.max(Number(q.get("frame") ?? 0), 0), player.manifest.frames - 1);
  await player.show(start);
  player.draw();
  Object.assign(api, {
    ready: true,
    player,
    /** The current render as base64 premultiplied RGBA rows (top first). */
    pixels: () => {
      const px = player.pixels();
      let s = "";
      for (let i = 0; i < px.length; i += 0x8000) s += String.fromCharCode(...px.subarray(i, i + 0x8000));
      return btoa(s);
    },
  });
  controls(player, canvas);
}

main().catch(fail);
