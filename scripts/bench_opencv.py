#!/usr/bin/env python3
"""The same render as `cpsl bench render`, written the straightforward way with OpenCV.

Per layer: cv2.warpPerspective of the premultiplied 8-bit RGBA layer with the same inverse
homography (INTER_LINEAR, WARP_INVERSE_MAP, transparent border), then numpy front-to-back
compositing in float32 (paper eq. 2). Preparation (reading PNGs, premultiplying) is not timed,
as in cpsl where layers are prepared once. Prints JSON: per-frame times and the OpenCV version;
writes the last render (premultiplied RGB over black) to --out for an equality check.
"""
import argparse
import json
import os
import time

import cv2
import numpy as np


def main():
    ap = argparse.ArgumentParser()
    ap.add_argument("--layers", required=True, help="layer-set folder")
    ap.add_argument("--homographies", required=True, help="JSON list of 3x3 (or null) per layer")
    ap.add_argument("--frames", type=int, default=60)
    ap.add_argument("--out", required=True)
    a = ap.parse_args()

    manifest = json.load(open(os.path.join(a.layers, "manifest.json")))
    homs = json.load(open(a.homographies))
    w, h = manifest["camera"]["width"], manifest["camera"]["height"]
    layers = []
    for entry, hom in zip(manifest["layers"], homs):
        bgra = cv2.imread(os.path.join(a.layers, entry["file"]), cv2.IMREAD_UNCHANGED)
        rgba = cv2.cvtColor(bgra, cv2.COLOR_BGRA2RGBA).astype(np.float32)
        alpha = rgba[..., 3:4] / 255.0
        rgba[..., :3] = np.round(rgba[..., :3] * alpha)  # premultiply, as cpsl stores layers
        layers.append((rgba.astype(np.uint8), None if hom is None else np.array(hom, np.float64)))

    def render():
        acc = np.zeros((h, w, 4), np.float32)
        trans = np.ones((h, w, 1), np.float32)
        for img, hom in layers:
            if hom is None:
                continue
            warped = cv2.warpPerspective(
                img, hom, (w, h),
                flags=cv2.INTER_LINEAR | cv2.WARP_INVERSE_MAP,
                borderMode=cv2.BORDER_CONSTANT, borderValue=(0, 0, 0, 0),
            ).astype(np.float32) * (1.0 / 255.0)
            acc += trans * warped
            trans *= 1.0 - warped[..., 3:4]
        return acc

    for _ in range(3):
        out = render()
    times = []
    for _ in range(a.frames):
        t = time.perf_counter()
        out = render()
        times.append((time.perf_counter() - t) * 1e3)
    rgb = np.clip(out[..., :3] * 255.0 + 0.5, 0, 255).astype(np.uint8)
    cv2.imwrite(a.out, cv2.cvtColor(rgb, cv2.COLOR_RGB2BGR))
    print(json.dumps({"times_ms": times, "version": "cv2 " + cv2.__version__ + ", numpy " + np.__version__,
                      "threads": cv2.getNumThreads()}))


if __name__ == "__main__":
    main()
