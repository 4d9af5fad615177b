// Playback benchmark of the browser player in headless Chromium: serves a folder with
// `cpsl serve`, plays its first package (or variant set) for a while and reports the frames
// shown per second (decode + upload + render, against the package's frame rate) and the
// median draw time.
//
//   node test/bench.mjs DIR [SECONDS]      (CPSL_BIN: the cpsl binary; QUERY: player URL
//                                          parameters, e.g. QUERY=fill=0)
//
// Headless Chromium without a GPU renders WebGL2 with SwiftShader on the CPU: numbers from
// such a machine measure the correctness path, not what a GPU browser does.
import { startServer, launchChromium, playerReady } from "./browser.mjs";
import { join, resolve, dirname } from "node:path";
import { fileURLToPath } from "node:url";

const here = dirname(fileURLToPath(import.meta.url));
const bin = resolve(process.env.CPSL_BIN ?? join(here, "../../target/release/cpsl"));
const dir = process.argv[2];
const seconds = Number(process.argv[3] ?? 10);
if (!dir) {
  console.error("usage: node test/bench.mjs DIR [SECONDS]");
  process.exit(2);
}
const { child, url } = await startServer(bin, dir);
const browser = await launchChromium();
try {
  const page = await browser.newPage({ viewport: { width: 1400, height: 900 } });
  await page.goto(`${url}/${process.env.QUERY ? `?${process.env.QUERY}` : ""}`);
  await playerReady(page);
  await page.waitForTimeout(2000); // warm up
  const a = await page.evaluate(() => ({ n: window.cpsl.player.shown, t: performance.now() }));
  await page.waitForTimeout(seconds * 1000);
  const b = await page.evaluate(() => ({
    n: window.cpsl.player.shown,
    t: performance.now(),
    draw: window.cpsl.player.medianDrawMs(),
    show: window.cpsl.player.medianShowMs(),
    fps: window.cpsl.player.manifest.frame_rate,
    size: `${window.cpsl.player.manifest.camera.width}x${window.cpsl.player.manifest.camera.height}`,
    layers: window.cpsl.player.manifest.layers,
    error: window.cpsl.error,
  }));
  if (b.error) throw new Error(b.error);
  const shown = (b.n - a.n) / ((b.t - a.t) / 1000);
  console.log(JSON.stringify({ size: b.size, layers: b.layers, package_fps: b.fps, shown_fps: +shown.toFixed(2), median_draw_ms: +b.draw.toFixed(2), median_decode_upload_ms: +b.show.toFixed(2) }));
} finally {
  await browser.close();
  child.kill("SIGTERM");
}
