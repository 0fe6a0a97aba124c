"""The portable wheel's check (`cargo xtask wheel --portable`): run by the xtask in a fresh
venv where the wheel is installed, with the system's OpenCV libraries hidden from the loader.

Imports posediff, says which shared libraries its extension loaded, estimates the cameras of
a real set and checks every relative rotation against the set's ground truth. Exits non-zero
on any failure.

Usage: python portable_wheel_check.py SET_DIR (a folder with images/ and cameras.json)
"""

import json
import pathlib
import sys

import numpy as np

import posediff


def loaded_libraries():
    """The shared objects this process has mapped (Linux)."""
    names = set()
    for line in pathlib.Path("/proc/self/maps").read_text().splitlines():
        parts = line.split()
        if len(parts) >= 6 and ".so" in parts[-1]:
            names.add(pathlib.Path(parts[-1]).name)
    return sorted(names)


def main():
    root = pathlib.Path(sys.argv[1])
    truth = {pathlib.Path(c["image"]).name: c for c in json.loads((root / "cameras.json").read_text())}
    rec = posediff.estimate(str(root / "images"))
    opencv = [n for n in loaded_libraries() if "opencv" in n]
    if opencv:
        sys.exit(f"the portable module loaded the system's OpenCV: {opencv}")
    cams = [c for c in rec.cameras if c.estimated]
    if len(cams) != len(rec.cameras):
        sys.exit(f"{len(rec.cameras) - len(cams)} of {len(rec.cameras)} cameras not estimated")
    worst = 0.0
    for a in range(len(cams)):
        for b in range(a + 1, len(cams)):
            ga, gb = (np.array(truth[c.name]["R"]) for c in (cams[a], cams[b]))
            rel_est = cams[b].R @ cams[a].R.T
            rel_gt = gb @ ga.T
            cos = (np.trace(rel_est.T @ rel_gt) - 1.0) / 2.0
            worst = max(worst, float(np.degrees(np.arccos(np.clip(cos, -1.0, 1.0)))))
    print(f"posediff from {pathlib.Path(posediff.__file__).parent}: {len(cams)} cameras, "
          f"worst relative rotation error {worst:.3f} deg; no OpenCV library loaded")
    if worst > 1.0:
        sys.exit(f"worst relative rotation error {worst:.3f} deg > 1 deg")


if __name__ == "__main__":
    main()
