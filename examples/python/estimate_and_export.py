"""From a folder of photos to a folder that nerfstudio, gsplat and COLMAP tools load.

    python examples/python/estimate_and_export.py ../shared/data/strecha_fountainP11/images out/fountain

Then, for example:
    ns-train splatfacto --data out/fountain                 # nerfstudio reads transforms.json + sparse_pc.ply
    python gsplat/examples/simple_trainer.py default --data_dir out/fountain   # COLMAP sparse/0 + images/
"""

from __future__ import annotations

import sys

import numpy as np

import posediff


def main(images: str, out: str) -> None:
    rec = posediff.estimate(images)
    estimated = [c for c in rec.cameras if c.estimated]
    print(f"{len(estimated)}/{len(rec.cameras)} cameras, "
          f"{0 if rec.points is None else len(rec.points['xyz'])} points")
    for cam in rec.cameras:
        if not cam.estimated:
            print(f"  {cam.name}: not estimated ({cam.reason})")
    # Camera-to-world matrices in OpenCV axes, as most PyTorch training code wants them.
    c2w = np.stack([np.block([[c.R.T, c.center[:, None]], [np.zeros((1, 3)), np.ones((1, 1))]])
                    for c in estimated])
    print("first camera-to-world:\n", c2w[0].round(4))
    written = rec.write(out)
    print("wrote", ", ".join(written["files"]), "to", out)


if __name__ == "__main__":
    if len(sys.argv) != 3:
        sys.exit(__doc__)
    main(sys.argv[1], sys.argv[2])
