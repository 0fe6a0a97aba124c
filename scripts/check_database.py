#!/usr/bin/env python3
"""Maps the database of a `posediff estimate --database D` run with pycolmap 4.2.1.

- pycolmap opens D (--database; default out/database.db): its images, cameras and verified pairs must be run.json's
  (every image; every pair run.json lists with matches); every match's keypoints must lie
  inside their images;
- pycolmap's global mapper (GLOMAP's) and incremental mapper reconstruct from it with the
  images of out/images, and each registered camera's relative rotations are scored against
  --gt (a cameras.json, OpenCV x_cam = R x_world + t): the fraction of pairs within 5°.

Prints one JSON line of what it found; exits non-zero with the reason on any mismatch.
"""
import argparse
import json
import pathlib
import sys

import numpy as np
import pycolmap


def fail(msg):
    print(f"check_database: {msg}", file=sys.stderr)
    sys.exit(1)


def rra5(rec, gt):
    names = {img.name: img for img in rec.images.values() if img.has_pose}
    common = [n for n in gt if n in names]
    rot = {n: names[n].cam_from_world().rotation.matrix() for n in common}
    ok = total = 0
    for i, a in enumerate(common):
        for b in common[i + 1:]:
            rel_gt = gt[b] @ gt[a].T
            rel = rot[b] @ rot[a].T
            c = (np.trace(rel_gt @ rel.T) - 1) / 2
            ok += np.degrees(np.arccos(np.clip(c, -1, 1))) < 5
            total += 1
    return len(common), ok / max(total, 1)


def main():
    ap = argparse.ArgumentParser()
    ap.add_argument("out", type=pathlib.Path)
    ap.add_argument("--gt", type=pathlib.Path, required=True)
    ap.add_argument("--database", type=pathlib.Path)
    args = ap.parse_args()
    run = json.loads((args.out / "run.json").read_text())
    db_path = args.database or args.out / "database.db"
    db = pycolmap.Database.open(str(db_path))
    images = db.read_all_images()
    cameras = db.read_all_cameras()
    if len(images) != len(run["images"]):
        fail(f"{len(images)} images in the database, run.json has {len(run['images'])}")
    pairs = [p for p in run["matches_per_pair"] if p["matches"] > 0]
    # Pairs tried and verified too few are stored as DEGENERATE geometries without inliers.
    _, inliers = db.read_two_view_geometry_num_inliers()
    verified = sum(1 for n in inliers if n > 0)
    if verified != len(pairs):
        fail(f"{verified} verified pairs in the database, run.json has {len(pairs)} with matches")
    size = {c.camera_id: (c.width, c.height) for c in cameras}
    for image in images:
        kp = db.read_keypoints(image.image_id)
        w, h = size[image.camera_id]
        if len(kp) and (kp[:, 0].min() < 0 or kp[:, 0].max() > w or kp[:, 1].min() < 0
                        or kp[:, 1].max() > h):
            fail(f"{image.name}: keypoints outside the image")
    # Each pair's F as pycolmap reads it must fit its inliers (x2ᵀ F x1 = 0, within 1 px).
    for p in pairs:
        g = db.read_two_view_geometry(image_id1=p["first"] + 1, image_id2=p["second"] + 1)
        m = g.inlier_matches
        k1 = db.read_keypoints(p["first"] + 1)[:, :2][m[:, 0]]
        k2 = db.read_keypoints(p["second"] + 1)[:, :2][m[:, 1]]
        x1 = np.c_[k1, np.ones(len(m))]
        x2 = np.c_[k2, np.ones(len(m))]
        fx1 = x1 @ g.F.T
        d = np.abs(np.sum(x2 * fx1, 1)) / np.hypot(fx1[:, 0], fx1[:, 1])
        if np.median(d) > 1.0:
            fail(f"pair {p['first']}-{p['second']}: F fits its inliers to {np.median(d):.2f} px")
    # COLMAP's `matches` table holds a pair's matches before verification: its inliers are
    # among them.
    for p in pairs:
        raw = {tuple(r) for r in db.read_matches(p["first"] + 1, p["second"] + 1).tolist()}
        g = db.read_two_view_geometry(image_id1=p["first"] + 1, image_id2=p["second"] + 1)
        if not all(tuple(r) in raw for r in g.inlier_matches.tolist()):
            fail(f"pair {p['first']}-{p['second']}: inliers that its matches lack")
    matches = sum(db.read_two_view_geometry(image_id1=p["first"] + 1,
                                            image_id2=p["second"] + 1).inlier_matches.shape[0]
                  for p in pairs)
    if matches != sum(p["matches"] for p in pairs):
        fail(f"{matches} inlier matches in the database, run.json has "
             f"{sum(p['matches'] for p in pairs)}")
    db.close()
    gt = {r["image"].split("/")[-1]: np.array(r["R"]) for r in json.loads(args.gt.read_text())}
    result = {"images": len(images), "cameras": len(cameras), "pairs": verified,
              "matches": matches}
    for name, mapper in [("global", pycolmap.global_mapping),
                         ("incremental", pycolmap.incremental_mapping)]:
        out = args.out / f"pycolmap-{name}"
        out.mkdir(exist_ok=True)
        recs = mapper(str(db_path), str(args.out / "images"), str(out))
        if not recs:
            fail(f"pycolmap's {name} mapper reconstructed nothing from our database")
        best = max(recs.values(), key=lambda r: r.num_reg_images())
        registered, rra = rra5(best, gt)
        result[name] = {"registered": registered, "rra_5": rra, "points": best.num_points3D(),
                        "cameras": len(best.cameras)}
    print(json.dumps(result))


if __name__ == "__main__":
    main()
