#!/usr/bin/env python3
"""An independent SfM reconstruction of the fox's frames (pycolmap, PyPI; no poses read), as
the oracle of issue 29's depth target: writes, per registered frame, every 3-D point it sees
as its camera coordinates (x/z, y/z, z), and its camera path, for `cpsl eval-track
--depth-points` (which also scores that path against the fox's poses, as the floor of the
rotation target: two reconstructions of the same frames disagree by about as much).

    python fox_sfm_points.py DATA_DIR OUT.json [--work DIR]

Features are SIFT at up to 1600 px, matched exhaustively, and mapped incrementally with one
shared camera with lens distortion (OpenCV's model, all estimated), so the points' directions
are the reconstruction's own. About 5 minutes on 2 cores.
"""
import argparse
import json
import pathlib
import shutil
import time

import pycolmap


def main():
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("data", type=pathlib.Path)
    ap.add_argument("out", type=pathlib.Path)
    ap.add_argument("--work", type=pathlib.Path, default=pathlib.Path("out/fox-sfm"))
    a = ap.parse_args()
    images = a.data / "instant_ngp_fox_video_frames" / "images"
    if not images.is_dir():
        raise SystemExit(f"no fox frames in {images}")
    shutil.rmtree(a.work, ignore_errors=True)
    a.work.mkdir(parents=True)
    db = a.work / "database.db"
    t0 = time.time()
    reader = pycolmap.ImageReaderOptions()
    reader.camera_model = "OPENCV"
    extraction = pycolmap.FeatureExtractionOptions()
    extraction.max_image_size = 1600
    pycolmap.extract_features(db, images, camera_mode=pycolmap.CameraMode.SINGLE,
                              reader_options=reader, extraction_options=extraction,
                              device=pycolmap.Device.cpu)
    pycolmap.match_exhaustive(db, device=pycolmap.Device.cpu)
    maps = pycolmap.incremental_mapping(db, images, a.work)
    if not maps:
        raise SystemExit("pycolmap reconstructed nothing")
    rec = max(maps.values(), key=lambda r: r.num_reg_images())
    frames, poses = {}, {}
    for image in rec.images.values():
        if not image.has_pose:
            continue
        cam_from_world = image.cam_from_world()
        r = cam_from_world.rotation.matrix()
        # Camera-to-world, OpenCV axes (as `cpsl track` writes it): rotation and centre.
        poses[image.name] = {"rotation": r.T.tolist(),
                             "centre": (-r.T @ cam_from_world.translation).tolist()}
        pts = []
        for p2d in image.points2D:
            if not p2d.has_point3D():
                continue
            x, y, z = cam_from_world * rec.points3D[p2d.point3D_id].xyz
            if z > 0:
                pts.append([float(x / z), float(y / z), float(z)])
        frames[image.name] = pts
    cam = next(iter(rec.cameras.values()))
    out = {
        "tool": f"pycolmap {pycolmap.__version__}",
        "camera": {"model": cam.model.name, "width": cam.width, "height": cam.height,
                   "params": [float(v) for v in cam.params]},
        "registered": rec.num_reg_images(),
        "points": rec.num_points3D(),
        "seconds": round(time.time() - t0, 1),
        "frames": frames,
        "poses": poses,
    }
    a.out.parent.mkdir(parents=True, exist_ok=True)
    a.out.write_text(json.dumps(out))
    print(f"{rec.num_reg_images()} frames registered, {rec.num_points3D()} points, "
          f"{out['seconds']} s -> {a.out}")


if __name__ == "__main__":
    main()
