#!/usr/bin/env python3
"""The same render as `cpsl bench render`, written the straightforward way with OpenCV.

Per layer: cv2.warpPerspective of the premultiplied 8-bit RGBA layer with the same inverse
homography (INTER_LINEAR, WARP_INVERSE_MAP, transparent border); for a depth-mesh layer,
cv2.remap with a per-pixel source map found by three fixed-point steps along each viewer ray
against the grid's inverse depth (affine over the same triangles as cpsl's); then numpy
front-to-back compositing in float32 (paper eq. 2). Preparation (reading PNGs, premultiplying) is not timed,
as in cpsl where layers are prepared once. Prints JSON: per-frame times and the OpenCV version;
writes the last render (premultiplied RGB over black) to --out for an equality check.
"""
import argparse
import json
import os
import time

import cv2
import numpy as np


def mesh_warp(m, w, h):
    """A function giving the source maps (map_x, map_y) of a mesh layer for the viewer, timed
    with the render: viewer rays (reference = R view + t) meet the grid's surface after
    three fixed-point steps."""
    s, cols, rows = m["step"], m["cols"], m["rows"]
    grid = np.array(m["inverse_depth"], np.float32).reshape(rows, cols)
    fx, fy, cx, cy = m["k"]
    r = np.array(m["r"], np.float32)
    t = np.array(m["t"], np.float32)
    ys, xs = np.mgrid[0:h, 0:w].astype(np.float32)
    # Ray directions in the reference frame.
    dx, dy = (xs - cx) / fx, (ys - cy) / fy
    d = [r[i, 0] * dx + r[i, 1] * dy + r[i, 2] for i in range(3)]
    w0 = float(np.median(grid))

    def inverse_depth(u, v):
        gx, gy = (u + 0.5) / s, (v + 0.5) / s
        ci = np.clip(np.floor(gx), 0, cols - 2).astype(np.int32)
        cj = np.clip(np.floor(gy), 0, rows - 2).astype(np.int32)
        x0 = np.minimum(ci * s, w) - 0.5
        x1 = np.minimum((ci + 1) * s, w) - 0.5
        y0 = np.minimum(cj * s, h) - 0.5
        y1 = np.minimum((cj + 1) * s, h) - 0.5
        fu = np.clip((u - x0) / (x1 - x0), 0, 1)
        fv = np.clip((v - y0) / (y1 - y0), 0, 1)
        a, b = grid[cj, ci], grid[cj, ci + 1]
        c, e = grid[cj + 1, ci], grid[cj + 1, ci + 1]
        return np.where(fu >= fv, a + (b - a) * fu + (e - b) * fv, a + (c - a) * fv + (e - c) * fu)

    def maps():
        inv = np.full((h, w), w0, np.float32)
        for _ in range(3):
            lam = (1.0 / inv - t[2]) / d[2]
            X, Y, Z = t[0] + lam * d[0], t[1] + lam * d[1], t[2] + lam * d[2]
            u, v = fx * X / Z + cx, fy * Y / Z + cy
            inv = inverse_depth(u, v).astype(np.float32)
        return u.astype(np.float32), v.astype(np.float32)

    return maps


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
        if isinstance(hom, dict):
            hom = mesh_warp(hom, w, h)
        elif hom is not None:
            hom = np.array(hom, np.float64)
        layers.append((rgba.astype(np.uint8), hom))

    def render():
        acc = np.zeros((h, w, 4), np.float32)
        trans = np.ones((h, w, 1), np.float32)
        for img, hom in layers:
            if hom is None:
                continue
            if callable(hom):
                mx, my = hom()
                warped = cv2.remap(img, mx, my, cv2.INTER_LINEAR,
                                   borderMode=cv2.BORDER_CONSTANT, borderValue=(0, 0, 0, 0))
            else:
                warped = cv2.warpPerspective(
                    img, hom, (w, h),
                    flags=cv2.INTER_LINEAR | cv2.WARP_INVERSE_MAP,
                    borderMode=cv2.BORDER_CONSTANT, borderValue=(0, 0, 0, 0),
                )
            warped = warped.astype(np.float32) * (1.0 / 255.0)
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
