// Shared by the browser tests and benchmarks: `cpsl serve` on an ephemeral loopback port, and
// headless Debian Chromium with the flags of ../shared/STACK.md (never `npx playwright
// install`; Playwright gives every launch a fresh temporary profile).
import { chromium } from "playwright-core";
import { spawn } from "node:child_process";

/** Starts `cpsl serve DIR` and resolves to { child, url } once it listens. */
export async function startServer(bin, dir) {
  const child = spawn(bin, ["serve", dir, "--addr", "127.0.0.1:0"], { stdio: ["ignore", "pipe", "inherit"] });
  const url = await new Promise((ok, fail) => {
    let out = "";
    child.stdout.on("data", (d) => {
      out += d;
      const m = out.match(/on (http:\/\/127\.0\.0\.1:\d+)\//);
      if (m) ok(m[1]);
    });
    child.on("exit", (c) => fail(new Error(`cpsl serve exited with ${c}`)));
  });
  return { child, url };
}

/** Headless Chromium (CHROMIUM, default /usr/bin/chromium), WebGL2 through SwiftShader. */
export function launchChromium() {
  return chromium.launch({
    executablePath: process.env.CHROMIUM ?? "/usr/bin/chromium",
    headless: true,
    args: [
      "--headless",
      "--no-sandbox",
      "--disable-gpu",
      "--disable-quic",
      "--no-first-run",
      "--disable-background-networking",
      "--disable-component-update",
      "--disable-sync",
      "--use-angle=swiftshader",
      "--enable-unsafe-swiftshader",
    ],
  });
}

/** Waits until the player on `page` is ready, or throws its error. */
export async function playerReady(page) {
  await page.waitForFunction(() => window.cpsl && (window.cpsl.ready || window.cpsl.error), null, { timeout: 60000 });
  const err = await page.evaluate(() => window.cpsl.error);
  if (err) throw new Error(`player: ${err}`);
}
