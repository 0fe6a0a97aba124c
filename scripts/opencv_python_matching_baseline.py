"""Reference timing for `cargo xtask bench-matching`: OpenCV-python SIFT + BFMatcher (L2,
cross-check = mutual nearest neighbours) on every pair of one image folder.

    python3 scripts/opencv_python_matching_baseline.py ../shared/data/co3d_apple_posediffusion/images

Prints one JSON line: images, pairs, matches, seconds (wall, reading + extraction + matching).
Needs `pip install opencv-python-headless`; the Rust workspace does not depend on it.
"""
import json
import sys
import time
from itertools import combinations
from pathlib import Path

import cv2

folder = Path(sys.argv[1])
paths = sorted(p for p in folder.iterdir() if p.suffix.lower() in {".jpg", ".jpeg", ".png"})
start = time.perf_counter()
sift = cv2.SIFT_create(nfeatures=4096)
features = []
for p in paths:
    grey = cv2.imread(str(p), cv2.IMREAD_GRAYSCALE)
    features.append(sift.detectAndCompute(grey, None))
matcher = cv2.BFMatcher(cv2.NORM_L2, crossCheck=True)
total = 0
for i, j in combinations(range(len(paths)), 2):
    di, dj = features[i][1], features[j][1]
    if di is not None and dj is not None:
        total += len(matcher.match(di, dj))
seconds = time.perf_counter() - start
print(json.dumps({"opencv": cv2.__version__, "images": len(paths), "pairs": len(paths) * (len(paths) - 1) // 2,
                  "matches": total, "seconds": seconds}))
