#!/usr/bin/env python3
"""Container overhead of a cpsl package's layer streams: for every stream of every segment,
the file's bytes minus its coded pictures' (the sample sizes of its MP4 `stsz` or its
fragment's `trun`; from version 6, where a segment's streams share one fragment, that
fragment's bytes beyond its pictures divided by its streams), and the init segments' bytes
(fetched once per package).

    python3 scripts/container-overhead.py clip.cpsl
"""
import json
import struct
import sys
from pathlib import Path


def boxes(b, start, end):
    at = start
    while at + 8 <= end:
        size, kind = struct.unpack(">I4s", b[at : at + 8])
        body = at + 8
        if size == 1:
            size = struct.unpack(">Q", b[at + 8 : at + 16])[0]
            body += 8
        elif size == 0:
            size = end - at
        yield kind.decode("latin-1"), body, at + size
        at += size


def find(b, start, end, path):
    for kind, body, stop in boxes(b, start, end):
        if kind == path[0]:
            return (body, stop) if len(path) == 1 else find(b, body, stop, path[1:])
    return None


def sample_bytes(b):
    """Sum of the sample sizes of a progressive MP4 or of a movie fragment."""
    moof = find(b, 0, len(b), ["moof"])
    if moof:
        total = 0
        traf = find(b, *moof, ["traf"])
        for kind, body, stop in boxes(b, *traf):
            if kind != "trun":
                continue  # every run: a version 6 fragment has one per stream
            flags = struct.unpack(">I", b[body : body + 4])[0] & 0xFFFFFF
            count = struct.unpack(">I", b[body + 4 : body + 8])[0]
            at = body + 8 + 4 * bool(flags & 1) + 4 * bool(flags & 4)
            fields = [f for f in (0x100, 0x200, 0x400, 0x800) if flags & f]
            for _ in range(count):
                for f in fields:
                    if f == 0x200:
                        total += struct.unpack(">I", b[at : at + 4])[0]
                    at += 4
        return total
    for kind, body, stop in boxes(b, 0, len(b)):
        if kind == "moov":
            for k2, b2, s2 in boxes(b, body, stop):
                if k2 == "trak":
                    stsz = find(b, b2, s2, ["mdia", "minf", "stbl", "stsz"])
                    fixed, count = struct.unpack(">II", b[stsz[0] + 4 : stsz[0] + 12])
                    if fixed:
                        return fixed * count
                    return sum(struct.unpack(f">{count}I", b[stsz[0] + 12 : stsz[0] + 12 + 4 * count]))
    raise ValueError("neither a fragment nor an MP4 file")


def main(pkg):
    root = Path(pkg)
    m = json.loads((root / "manifest.json").read_text())
    over = []
    for s in m["segments"]:
        if "fragment" in s:
            b = (root / s["fragment"]["path"]).read_bytes()
            n = len(s["streams"])
            share = (len(b) - sample_bytes(b)) / n
            over.extend([(round(share), s["frames"])] * n)
            continue
        for t in s["streams"]:
            b = (root / t["file"]["path"]).read_bytes()
            over.append((len(b) - sample_bytes(b), s["frames"]))
    inits = sum(f["bytes"] for f in m.get("inits", []))
    n = len(over)
    mean = sum(o for o, _ in over) / n
    print(
        f"{pkg}: version {m['version']}, {n} streams in {len(m['segments'])} segments: "
        f"{mean:.0f} B of container per stream and segment (min {min(o for o, _ in over)}, "
        f"max {max(o for o, _ in over)}); init segments {inits} B "
        f"({len(m.get('inits', []))})"
    )


if __name__ == "__main__":
    for p in sys.argv[1:]:
        main(p)
