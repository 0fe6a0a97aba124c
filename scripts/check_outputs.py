#!/usr/bin/env python3
"""Reads a `posediff estimate` output folder with the tools users feed it to.

- pycolmap reads out/sparse/0; the image, camera and point counts must match run.json, and the
  mean reprojection error recomputed from pycolmap's cameras, poses and 2-D points must be below
  --max-error px and equal to posediff's (run.json, and each point's stored ERROR) within 1e-6;
- plyfile reads out/sparse_pc.ply: as many vertices as points, each the COLMAP point moved by
  transforms.json's applied_transform, with its colour;
- every file_path and the ply_file_path of transforms.json exist relative to the file.

Prints one JSON line of what it found; exits non-zero with the reason on any mismatch.
"""
import argparse
import json
import pathlib
import sys

import numpy as np
import plyfile
import pycolmap


def fail(msg):
    print(f"check_outputs: {msg}", file=sys.stderr)
    sys.exit(1)


def main():
    ap = argparse.ArgumentParser()
    ap.add_argument("out", type=pathlib.Path)
    ap.add_argument("--max-error", type=float, default=1.0)
    ap.add_argument("--min-points", type=int, default=1)
    a = ap.parse_args()
    out = a.out
    run = json.loads((out / "run.json").read_text())
    cams = json.loads((out / "cameras.json").read_text())
    rec = pycolmap.Reconstruction(str(out / "sparse" / "0"))
    estimated = [c for c in cams if c.get("estimated", True)]
    if rec.num_reg_images() != len(estimated):
        fail(f"pycolmap has {rec.num_reg_images()} images, cameras.json {len(estimated)} estimated")
    distinct = {
        (c["width"], c["height"], json.dumps(c["K"]), c.get("model"), json.dumps(c.get("params")))
        for c in estimated
    }
    if rec.num_cameras() != len(distinct):
        fail(f"{rec.num_cameras()} COLMAP cameras for {len(distinct)} distinct intrinsics")
    n = rec.num_points3D()
    if n != run["outputs"]["points"]:
        fail(f"pycolmap has {n} points, run.json {run['outputs']['points']}")
    if n < a.min_points:
        fail(f"{n} points, fewer than {a.min_points}")
    # Each camera as pycolmap reads it matches cameras.json (OpenCV pixels = COLMAP − 0.5).
    by_name = {c["image"]: c for c in estimated}
    for image in rec.images.values():
        c = by_name.get(image.name)
        if c is None:
            fail(f"pycolmap image {image.name} is not in cameras.json")
        pose = image.cam_from_world()
        R = pose.rotation.matrix()
        if np.abs(R - np.array(c["R"])).max() > 1e-9 or np.abs(pose.translation - np.array(c["t"])).max() > 1e-9:
            fail(f"{image.name}: pose differs from cameras.json")
        K = image.camera.calibration_matrix()
        K[0, 2] -= 0.5
        K[1, 2] -= 0.5
        if np.abs(K - np.array(c["K"])).max() > 1e-9:
            fail(f"{image.name}: K differs from cameras.json")
        # The lens: cameras.json's model and params (PINHOLE when absent), COLMAP's principal
        # point half a pixel on.
        model = c.get("model", "PINHOLE")
        if image.camera.model.name != model:
            fail(f"{image.name}: pycolmap reads {image.camera.model.name}, cameras.json {model}")
        if "params" in c:
            params = np.array(c["params"], dtype=np.float64)
            centre = 1 if model in ("SIMPLE_PINHOLE", "SIMPLE_RADIAL", "RADIAL") else 2
            params[centre:centre + 2] += 0.5
            if np.abs(image.camera.params - params).max() > 1e-9:
                fail(f"{image.name}: params {image.camera.params} vs cameras.json {params}")
    errors, stored = [], []
    for pid, p in rec.points3D.items():
        d = []
        for el in p.track.elements:
            image = rec.images[el.image_id]
            uv = image.project_point(p.xyz)
            if uv is None:
                fail(f"point {pid} is behind image {image.name}")
            d.append(np.linalg.norm(uv - image.points2D[el.point2D_idx].xy))
        errors.append(np.mean(d))
        stored.append(p.error)
    errors, stored = np.array(errors), np.array(stored)
    worst = float(np.abs(errors - stored).max()) if n else 0.0
    if worst > 1e-6:
        fail(f"a point's stored error differs from the recomputed one by {worst}")
    mean = float(errors.mean()) if n else 0.0
    ours = run["outputs"]["mean_reprojection_error_px"] or 0.0
    if abs(mean - ours) > 1e-6:
        fail(f"mean reprojection error {mean} (pycolmap) vs {ours} (run.json)")
    if mean >= a.max_error:
        fail(f"mean reprojection error {mean} px is not below {a.max_error}")
    # transforms.json and the PLY.
    t = json.loads((out / "transforms.json").read_text())
    missing = [f["file_path"] for f in t["frames"] if not (out / f["file_path"]).is_file()]
    if missing:
        fail(f"transforms.json names {len(missing)} missing images, e.g. {missing[0]}")
    ply_path = out / t["ply_file_path"]
    ply = plyfile.PlyData.read(str(ply_path))
    v = ply["vertex"]
    if v.count != n:
        fail(f"{ply_path} has {v.count} vertices for {n} points")
    A = np.array(t["applied_transform"])
    xyz = np.stack([v["x"], v["y"], v["z"]], 1).astype(np.float64)
    rgb = np.stack([v["red"], v["green"], v["blue"]], 1)
    ids = sorted(rec.points3D.keys())
    ref = np.array([rec.points3D[i].xyz for i in ids]) @ A[:, :3].T + A[:, 3]
    col = np.array([rec.points3D[i].color for i in ids])
    if n and np.abs(xyz - ref).max() > 1e-4 * (1 + np.abs(ref).max()):
        fail("PLY positions are not the COLMAP points moved by applied_transform")
    if n and (rgb != col).any():
        fail("PLY colours differ from the COLMAP points'")
    print(json.dumps({
        "images": rec.num_reg_images(),
        "cameras": rec.num_cameras(),
        "points": n,
        "mean_reprojection_error_px": mean,
        "max_stored_error_difference": worst,
        "ply_vertices": v.count,
        "frames": len(t["frames"]),
    }))


if __name__ == "__main__":
    main()
