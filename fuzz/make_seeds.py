#!/usr/bin/env python3
"""Writes the seeds of every fuzz target into fuzz/seeds/<target>/ (small, synthetic files
made here, none copied from ../shared): run once with numpy and pillow
(`target/client-venv/bin/pip install pillow`), the seeds are committed. The fuzzers read them
and keep what they find in fuzz/corpus/<target>/ (minimised)."""
import gzip
import io
import json
import pathlib
import pickle
import struct
import sys
import types
import zipfile

import numpy as np
from PIL import Image

ROOT = pathlib.Path(__file__).resolve().parent / "seeds"


def put(target, name, data):
    d = ROOT / target
    d.mkdir(parents=True, exist_ok=True)
    (d / name).write_bytes(data)


def safetensors(tensors):
    header, blobs, offset = {}, [], 0
    for name, a in tensors.items():
        b = a.astype("<f4").tobytes()
        header[name] = {"dtype": "F32", "shape": list(a.shape), "data_offsets": [offset, offset + len(b)]}
        blobs.append(b)
        offset += len(b)
    h = json.dumps(header).encode()
    return struct.pack("<Q", len(h)) + h + b"".join(blobs)


def torch_zip(tensors):
    """A PyTorch >= 1.6 zip checkpoint written without torch: the same pickle opcodes (a
    persistent id per storage, torch._utils._rebuild_tensor_v2) and archive layout."""
    torch = types.ModuleType("torch")
    utils = types.ModuleType("torch._utils")

    def _rebuild_tensor_v2(*args):
        raise NotImplementedError

    _rebuild_tensor_v2.__module__ = "torch._utils"
    _rebuild_tensor_v2.__qualname__ = "_rebuild_tensor_v2"
    utils._rebuild_tensor_v2 = _rebuild_tensor_v2

    class FloatStorage:
        pass

    FloatStorage.__module__ = "torch"
    FloatStorage.__qualname__ = "FloatStorage"
    torch.FloatStorage = FloatStorage
    torch._utils = utils
    sys.modules["torch"], sys.modules["torch._utils"] = torch, utils

    class Storage:
        def __init__(self, key, n):
            self.key, self.n = key, n

    class Tensor:
        def __init__(self, key, shape):
            self.key, self.shape = key, shape

        def __reduce__(self):
            stride, s = [], 1
            for d in reversed(self.shape):
                stride.insert(0, s)
                s *= d
            import collections
            return (_rebuild_tensor_v2, (Storage(self.key, s), 0, tuple(self.shape), tuple(stride), False, collections.OrderedDict()))

    class P(pickle.Pickler):
        def persistent_id(self, obj):
            if isinstance(obj, Storage):
                return ("storage", FloatStorage, obj.key, "cpu", obj.n)
            return None

    import collections
    state = collections.OrderedDict((name, Tensor(str(k), a.shape)) for k, (name, a) in enumerate(tensors.items()))
    buf = io.BytesIO()
    P(buf, protocol=2).dump(state)
    out = io.BytesIO()
    with zipfile.ZipFile(out, "w", zipfile.ZIP_STORED) as z:
        z.writestr("archive/data.pkl", buf.getvalue())
        z.writestr("archive/version", "3\n")
        for k, (_, a) in enumerate(tensors.items()):
            z.writestr(f"archive/data/{k}", a.astype("<f4").tobytes())
    return out.getvalue()


def main():
    rng = np.random.default_rng(0)
    t = {"a.weight": rng.standard_normal((2, 3)), "b.bias": rng.standard_normal(4)}
    put("checkpoint", "small.safetensors", safetensors(t))
    put("checkpoint", "small.pth", torch_zip(t))

    cams = []
    for k in range(3):
        a = 0.4 * k
        R = [[np.cos(a), 0, np.sin(a)], [0, 1, 0], [-np.sin(a), 0, np.cos(a)]]
        cams.append({"image": f"images/{k:04d}.jpg", "width": 64, "height": 48,
                     "K": [[60.0, 0, 31.5], [0, 61.0, 23.5], [0, 0, 1]], "R": R, "t": [0.1 * k, 0, 2.0]})
    put("cameras_json", "three.json", json.dumps(cams, indent=1).encode())
    partial = cams[:1] + [{"image": "x.jpg", "width": 10, "height": 10, "K": None, "R": None, "t": None, "estimated": False}]
    put("cameras_json", "partial.json", json.dumps(partial).encode())

    cameras_txt = "# c\n1 PINHOLE 64 48 60 61 32 24\n2 SIMPLE_RADIAL 64 48 60 32 24 0.01\n"
    images_txt = ("# i\n1 1 0 0 0 0 0 2 1 a.jpg\n10 20 1 11 21 -1\n"
                  "2 0.98 0 0.19 0 -0.4 0 2 2 b.jpg\n12 22 1\n")
    points_txt = "1 0.1 0.2 3.0 255 0 10 0.5 1 0 2 0\n"
    put("colmap_text", "model.txt", "\0".join([cameras_txt, images_txt, points_txt]).encode())

    cb = struct.pack("<Q", 1) + struct.pack("<IiQQ", 1, 1, 64, 48) + struct.pack("<4d", 60, 61, 32, 24)
    ib = struct.pack("<Q", 1) + struct.pack("<I", 1) + struct.pack("<7d", 1, 0, 0, 0, 0, 0, 2) + struct.pack("<I", 1)
    ib += b"a.jpg\0" + struct.pack("<Q", 2) + struct.pack("<ddQ", 10, 20, 1) + struct.pack("<ddQ", 11, 21, 2**64 - 1)
    pb = struct.pack("<Q", 1) + struct.pack("<Q", 1) + struct.pack("<3d", 0.1, 0.2, 3.0) + bytes([255, 0, 10])
    pb += struct.pack("<d", 0.5) + struct.pack("<Q", 1) + struct.pack("<II", 1, 0)
    put("colmap_binary", "model.bin", cb + b"POSEDIFF" + ib + b"POSEDIFF" + pb)

    frame = {"filepath": "apple/1/images/frame000001.jpg", "bbox": [1.0, 2.0, 30.0, 40.0],
             "R": [[1, 0, 0], [0, 1, 0], [0, 0, 1]], "T": [0.0, 0.0, 5.0],
             "focal_length": [2.0, 2.0], "principal_point": [0.0, 0.0]}
    put("co3d_annotations", "one.jgz", gzip.compress(json.dumps({"1_2_3": [frame, frame]}).encode()))

    img = Image.fromarray((rng.random((12, 16, 3)) * 255).astype(np.uint8))
    for fmt, name in [("JPEG", "small.jpg"), ("PNG", "small.png")]:
        b = io.BytesIO()
        img.save(b, fmt)
        put("image", name, b.getvalue())
    b = io.BytesIO()
    img.save(b, "JPEG", progressive=True)
    put("image", "progressive.jpg", b.getvalue())


if __name__ == "__main__":
    main()
