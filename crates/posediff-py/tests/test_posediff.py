"""`import posediff` against the CLI, the official conversions and bad input.

The estimations run through the same library function as the CLI, so the files they write
must be the CLI's byte for byte.
"""

from __future__ import annotations

import json
import struct
import threading
import time
from pathlib import Path

import numpy as np
import pytest

import posediff
from conftest import SETS, SHARED, images_of, run_cli

# The files whose bytes do not depend on timings (run.json has seconds in it).
EXACT = [
    "cameras.json",
    "sparse/0/cameras.txt",
    "sparse/0/images.txt",
    "sparse/0/points3D.txt",
    "transforms.json",
    "sparse_pc.ply",
    "pytorch3d.json",
]


def same_files(a: Path, b: Path) -> None:
    for f in EXACT:
        assert (a / f).read_bytes() == (b / f).read_bytes(), f"{f} differs between {a} and {b}"


@pytest.mark.parametrize("name", SETS)
def test_shared_sets_give_the_cli_files(name: str, cli: Path, tmp_path: Path) -> None:
    run_cli(cli, "estimate", images_of(name), "--out", tmp_path / "cli", "--quiet", "--no-view")
    rec = posediff.estimate(images_of(name), progress=False)
    written = rec.write(tmp_path / "py")
    assert "cameras.json" in written["files"] and written["points"] > 1000
    same_files(tmp_path / "cli", tmp_path / "py")
    # The objects say what the files say.
    cams = rec.cameras
    on_disk = posediff.read_cameras(tmp_path / "py" / "cameras.json")
    assert [c.name for c in cams] == [c.name for c in on_disk]
    for c, d in zip(cams, on_disk):
        assert c.estimated and d.estimated
        np.testing.assert_allclose(c.K, d.K, rtol=1e-12)
        np.testing.assert_allclose(c.R, d.R, atol=1e-12)
        np.testing.assert_allclose(c.t, d.t, atol=1e-12)
        np.testing.assert_allclose(c.center, -c.R.T @ c.t, atol=1e-12)
        assert c.R.dtype == np.float64 and c.t.shape == (3,)
        assert abs(np.linalg.det(c.R) - 1) < 1e-9
    pts = rec.points
    assert pts is not None and pts["xyz"].shape == (written["points"], 3)
    assert pts["rgb"].dtype == np.uint8 and pts["error"].max() <= 4.0
    report = json.loads((tmp_path / "py" / "run.json").read_text())
    assert report["schema"] == rec.report["schema"] and report["method"] == "geometric"


def test_arrays_give_the_files_results(tmp_path: Path) -> None:
    folder = images_of("middlebury_templeSR")
    files = sorted(folder.glob("*.png"))
    arrays = [posediff.read_image(f) for f in files]
    assert arrays[0].dtype == np.uint8 and arrays[0].shape == (480, 640, 3)
    from_files = posediff.estimate(folder, progress=False)
    from_arrays = posediff.estimate(arrays, names=[f.name for f in files], progress=False)
    from_files.write(tmp_path / "files")
    from_arrays.write(tmp_path / "arrays")
    for f in ["cameras.json", "sparse/0/points3D.txt", "sparse_pc.ply"]:
        assert (tmp_path / "files" / f).read_bytes() == (tmp_path / "arrays" / f).read_bytes(), f
    # Array inputs are copied into out/images (their temporary files do not outlive the
    # result), so the COLMAP model and transforms.json resolve.
    images = tmp_path / "arrays" / "images"
    assert images.is_dir() and not images.is_symlink()
    assert posediff.read_image(images / files[3].name).tobytes() == arrays[3].tobytes()
    unnamed = posediff.estimate(arrays[:4], progress=False)
    assert [c.name for c in unnamed.cameras] == [f"image_{i:03}.png" for i in range(4)]
    with pytest.raises(ValueError, match="temporary folder"):
        unnamed.write(tmp_path / "linked", images="link")
    # The arrays' PNG files live exactly as long as their result.
    folder = Path(unnamed.report["images"][0]).parent
    assert folder.is_dir() and folder.name.startswith("posediff-arrays-")
    del unnamed
    import gc

    gc.collect()
    assert not folder.exists()


def read_safetensors(path: Path) -> dict[str, np.ndarray]:
    raw = path.read_bytes()
    (n,) = struct.unpack("<Q", raw[:8])
    header = json.loads(raw[8 : 8 + n])
    dtypes = {"F32": np.float32, "F64": np.float64, "I64": np.int64}
    out = {}
    for key, meta in header.items():
        if key == "__metadata__":
            continue
        start, end = meta["data_offsets"]
        data = np.frombuffer(raw[8 + n + start : 8 + n + end], dtype=dtypes[meta["dtype"]])
        out[key] = data.reshape(meta["shape"]).astype(np.float64)
    return out


def test_conversions_agree_with_the_official_fixtures() -> None:
    fx = read_safetensors(SHARED / "reference" / "full" / "geometry_io.safetensors")
    enc = fx["pose_encoding"][0]
    for suffix, hw in [("224", (224, 224)), ("h180w320", (180, 320))]:
        K, R, t = posediff.pose_encoding_to_cameras(enc, image_size=hw)
        np.testing.assert_allclose(R, fx[f"opencv_R_{suffix}"], atol=1e-6, rtol=0)
        np.testing.assert_array_equal(t, fx[f"opencv_t_{suffix}"])
        np.testing.assert_allclose(K, fx[f"opencv_K_{suffix}"], rtol=1e-6, atol=0)
        for i in range(len(enc)):
            p3d = posediff.opencv_to_pytorch3d(K[i], R[i], t[i], hw)
            # The official pose_encoding_to_camera's PyTorch3D camera (principal point 0).
            np.testing.assert_allclose(p3d["R"], fx["R"][i], atol=1e-6, rtol=0)
            np.testing.assert_allclose(p3d["T"], fx["T"][i], atol=1e-6, rtol=0)
            np.testing.assert_allclose(p3d["focal_length"], fx["focal_length"][i], rtol=1e-6)
            np.testing.assert_allclose(p3d["principal_point"], 0, atol=1e-12)


def test_conversions_round_trip_off_centre_and_non_square() -> None:
    rng = np.random.default_rng(7)
    for _ in range(20):
        h, w = int(rng.integers(100, 900)), int(rng.integers(100, 900))
        K = np.array([[rng.uniform(200, 900), 0, rng.uniform(0, w)],
                      [0, rng.uniform(200, 900), rng.uniform(0, h)],
                      [0, 0, 1]])
        q, _ = np.linalg.qr(rng.normal(size=(3, 3)))
        R = q * np.sign(np.linalg.det(q))
        t = rng.normal(size=3)
        p3d = posediff.opencv_to_pytorch3d(K, R, t, (h, w))
        K2, R2, t2 = posediff.pytorch3d_to_opencv(
            p3d["R"], p3d["T"], p3d["focal_length"], p3d["principal_point"], (h, w))
        np.testing.assert_allclose(K2, K, rtol=1e-12, atol=1e-9)
        np.testing.assert_allclose(R2, R, atol=1e-12)
        np.testing.assert_allclose(t2, t, atol=1e-12)
        # PyTorch3D's projection of a point equals OpenCV's (row vectors, +X left, +Y up,
        # NDC scaled by min(H, W) / 2 about the image centre).
        x = rng.normal(size=3) + np.array([0, 0, 8.0])
        xw = R.T @ (x - t)
        cv = K @ (R @ xw + t)
        cv = cv[:2] / cv[2]
        cam = xw @ p3d["R"] + p3d["T"]
        ndc = p3d["focal_length"] * cam[:2] / cam[2] + p3d["principal_point"]
        s = min(h, w) / 2
        px = np.array([w / 2 - ndc[0] * s, h / 2 - ndc[1] * s])
        np.testing.assert_allclose(px, cv, atol=1e-6)


def test_bad_inputs_raise_the_right_exceptions(tmp_path: Path) -> None:
    temple = sorted(images_of("middlebury_templeSR").glob("*.png"))
    fountain = sorted(images_of("strecha_fountainP11").glob("*"))
    with pytest.raises(FileNotFoundError, match="no such file or directory"):
        posediff.estimate(tmp_path / "nope", progress=False)
    with pytest.raises(ValueError, match="need at least 2 images"):
        posediff.estimate([temple[0]], progress=False)
    with pytest.raises(FileNotFoundError, match="cargo xtask weights"):
        posediff.estimate(
            temple, matcher="aliked-lightglue", weights_dir=tmp_path / "none", progress=False
        )
    with pytest.raises(ValueError, match="aliked-lightglue"):
        posediff.estimate(temple, matcher="superglue", progress=False)
    with pytest.raises(ValueError, match="refine must be"):
        posediff.estimate(temple, refine="fast", progress=False)
    with pytest.raises(ValueError, match="H×W×3"):
        posediff.estimate([np.zeros((8, 8), np.uint8)] * 2, progress=False)
    with pytest.raises(TypeError, match='unexpected keyword argument "focal"'):
        posediff.estimate(temple, focal=800.0, progress=False)
    with pytest.raises(ValueError, match="^seed: "):
        posediff.estimate(temple, seed="zero", progress=False)
    with pytest.raises(ValueError, match="--focal-px must be a positive"):
        posediff.estimate(temple, focal_px=-3.0, progress=False)
    with pytest.raises(ValueError, match="same name"):
        posediff.estimate([temple[0], temple[0]], progress=False)
    broken = tmp_path / "broken"
    broken.mkdir()
    for f in temple[:2]:
        (broken / f.name).write_bytes(f.read_bytes())
    (broken / "zz.png").write_bytes(temple[2].read_bytes()[:-40])
    with pytest.raises(ValueError, match="unusable image"):
        posediff.estimate(broken, progress=False)
    with pytest.raises(FileNotFoundError):
        posediff.estimate(temple, init=tmp_path / "missing.json", progress=False)
    with pytest.raises(FileNotFoundError):
        posediff.Estimator(tmp_path / "missing.pth")
    with pytest.raises(ValueError, match="needs weights"):
        posediff.estimate(temple, device="cuda", progress=False)
    # Valid input the estimation cannot use: posediff.Error, not a crash.
    with pytest.raises(posediff.Error, match="do not overlap"):
        posediff.estimate([temple[0], fountain[0]], progress=False)
    assert issubclass(posediff.Error, Exception)


def test_a_video_gives_keyframes_and_cameras(cli: Path, tmp_path: Path) -> None:
    """A video in, as the CLI takes it: keyframes named by frame and time, one camera for the
    video, the masks applied, the keyframes written with the results."""
    run_cli(cli, "synth-video", "--out", tmp_path / "v", "--size", "320x240", "--fps", "15",
            "--seconds", "3", "--distractor", "--seed", "3")
    video = next((tmp_path / "v").glob("capture.*"))
    rec = posediff.estimate(video, masks=tmp_path / "v" / "masks", max_frames=40, progress=False)
    report = rec.report
    frames = report["video"]["keyframes"]
    assert 8 <= len(frames) <= 40
    assert report["options"]["video"]["max_frames"] == 40
    assert report["video"]["videos"][0]["masked_keyframes"] == len(frames)
    assert [c.name for c in rec.cameras] == [f["image"] for f in frames]
    assert all(c.estimated for c in rec.cameras)
    assert len({round(float(c.K[0, 0]), 6) for c in rec.cameras}) == 1
    rec.write(tmp_path / "out")
    for f in frames:
        assert (tmp_path / "out" / "images" / f["image"]).is_file()
    with pytest.raises(ValueError, match="videos or images"):
        posediff.estimate([video, images_of("middlebury_templeSR") / "templeSR0001.png"],
                          progress=False)
    empty = tmp_path / "empty.mp4"
    empty.write_bytes(b"")
    with pytest.raises(ValueError, match="empty"):
        posediff.estimate(empty, progress=False)


def test_the_options_tree_from_python_is_the_clis(cli: Path, tmp_path: Path) -> None:
    """``config=`` and ``options=`` set the tree as ``--config`` and ``--set`` do: the same
    decision (the pair plan), the same files, the tree in the report; a misspelt key is a
    ValueError naming it."""
    folder = tmp_path / "fountain"
    folder.mkdir()
    for f in sorted(images_of("strecha_fountainP11").glob("*"))[:4]:
        (folder / f.name).write_bytes(f.read_bytes())
    config = tmp_path / "opts.toml"
    config.write_text("[pairs.auto]\nexhaustive_up_to = 2\nsequential = 1\nretrieval = 1\n")
    rec = posediff.estimate(
        folder,
        config=config,
        options={"orientation.strong_pair": 120, "mapper": {"focal_prior": 1.5}},
        progress=False,
    )
    report = rec.report
    assert report["report"]["pair_selection"] == "sequential:1,retrieval:1"
    assert report["options"]["orientation"]["strong_pair"] == 120
    assert report["options"]["mapper"]["focal_prior"] == 1.5
    assert report["options"]["mapper"]["focal_starts"] == [0.4, 0.6, 0.9, 1.35, 2.0, 3.0]
    rec.write(tmp_path / "py")
    run_cli(
        cli, "estimate", folder, "--out", tmp_path / "cli", "--quiet", "--no-view",
        "--config", config, "--set", "orientation.strong_pair=120",
        "--set", "mapper.focal_prior=1.5",
    )
    same_files(tmp_path / "py", tmp_path / "cli")
    cli_report = json.loads((tmp_path / "cli" / "run.json").read_text())
    assert cli_report["options"] == report["options"]
    with pytest.raises(ValueError, match="orientation.strong_pairs"):
        posediff.estimate(folder, options={"orientation.strong_pairs": 1}, progress=False)
    with pytest.raises(ValueError, match="options must be a dict"):
        posediff.estimate(folder, options=["orientation.strong_pair"], progress=False)


def test_a_database_from_python_is_the_clis_store(cli: Path, tmp_path: Path) -> None:
    """``database=`` keeps the store as ``--database`` does: a second call reads every feature
    and pair back and gives the same cameras; ``posediff map`` on it gives them too; a
    database made with another matcher is a ValueError naming it."""
    folder = tmp_path / "fountain"
    folder.mkdir()
    for f in sorted(images_of("strecha_fountainP11").glob("*"))[:4]:
        (folder / f.name).write_bytes(f.read_bytes())
    db = tmp_path / "d.db"
    first = posediff.estimate(folder, database=db, progress=False)
    assert db.is_file()
    second = posediff.estimate(folder, database=db, progress=False)
    assert all(a.estimated for a in first.cameras)
    for a, b in zip(first.cameras, second.cameras):
        np.testing.assert_array_equal(a.R, b.R)
        np.testing.assert_array_equal(a.t, b.t)
        np.testing.assert_array_equal(a.K, b.K)
    second.write(tmp_path / "py")
    run_cli(cli, "map", "--database", db, "--images", folder, "--out", tmp_path / "cli",
            "--quiet", "--no-view")
    assert (tmp_path / "py" / "cameras.json").read_bytes() == \
        (tmp_path / "cli" / "cameras.json").read_bytes()
    with pytest.raises(ValueError, match="matcher sift"):
        posediff.estimate(folder, database=db, matcher="orb", progress=False)


def test_the_gil_is_released_while_estimating() -> None:
    folder = images_of("middlebury_templeSR")
    result: dict[str, object] = {}

    def work() -> None:
        result["rec"] = posediff.estimate(folder, progress=False)

    worker = threading.Thread(target=work)
    ticks = 0
    start = time.perf_counter()
    worker.start()
    while worker.is_alive():
        ticks += 1
        time.sleep(0.001)
    seconds = time.perf_counter() - start
    assert isinstance(result.get("rec"), posediff.Reconstruction)
    # The estimation takes seconds; with the GIL held this thread could not have run.
    assert seconds > 0.5 and ticks > 100, (seconds, ticks)


def test_progress_reaches_a_callback() -> None:
    calls: list[tuple[str, int, int, bool]] = []
    posediff.estimate(images_of("middlebury_templeSR"), progress=lambda *a: calls.append(a))
    assert calls[0] == ("geometry", 0, 0, False) and calls[-1][3] is True
    # The geometric path's own stages follow, in order (SIFT: not counted).
    stages = [c[0] for i, c in enumerate(calls) if i == 0 or c[0] != calls[i - 1][0]]
    assert stages[:4] == ["geometry", "features", "matching", "mapping"], stages


def test_score_is_the_cli_score(cli: Path, tmp_path: Path) -> None:
    name = "middlebury_templeSR"
    gt = SHARED / "data" / name / "cameras.json"
    rec = posediff.estimate(images_of(name), progress=False)
    rec.write(tmp_path / "out", ["cameras"])
    assert sorted(p.name for p in (tmp_path / "out").iterdir()) == ["cameras.json", "run.json"]
    run_cli(cli, "score", tmp_path / "out" / "cameras.json", "--gt", gt, "--out", tmp_path / "s.json")
    from_cli = json.loads((tmp_path / "s.json").read_text())
    ours = posediff.score(rec, gt)
    assert ours == posediff.score(tmp_path / "out" / "cameras.json", gt)
    assert ours["cc_10"] == from_cli["cc_10"]
    for k, v in from_cli["scores"].items():
        assert ours[k] == v, k
    assert ours["rra"][1] > 0.9


def test_an_estimator_serves_many_calls_as_the_cli(cli: Path, tmp_path: Path) -> None:
    weights = SHARED / "reference" / "tiny" / "model_tiny.safetensors"
    files = sorted(images_of("co3d_apple_posediffusion").glob("*.jpg"))[:6]
    est = posediff.Estimator(weights)
    a = est.estimate(files, seed=3, progress=False)
    b = est.estimate(files, seed=4, progress=False)
    a.write(tmp_path / "py")
    run_cli(cli, "estimate", *files, "--weights", weights, "--seed", 3,
            "--out", tmp_path / "cli", "--quiet", "--no-view")
    same_files(tmp_path / "cli", tmp_path / "py")
    assert a.report["method"] == "posediffusion" and a.report["seed"] == 3
    assert not np.allclose(a.cameras[1].R, b.cameras[1].R), "another seed, another sample"


def test_the_readme_example_runs(tmp_path: Path) -> None:
    import subprocess
    import sys

    from conftest import REPO

    script = REPO / "examples" / "python" / "estimate_and_export.py"
    out = tmp_path / "temple"
    r = subprocess.run([sys.executable, str(script), str(images_of("middlebury_templeSR")), str(out)],
                       capture_output=True, text=True)
    assert r.returncode == 0, r.stderr
    assert "16/16 cameras" in r.stdout
    for f in ["cameras.json", "transforms.json", "sparse_pc.ply", "sparse/0/points3D.txt"]:
        assert (out / f).is_file(), f
