"""posediff.distributed on a real local Ray cluster (2 CPUs): extraction and matching as Ray
tasks give the single process's cameras byte for byte, through shared paths or Ray's object
store, and a worker killed mid-task costs only that task."""

from __future__ import annotations

import os
import signal
from pathlib import Path
from typing import Any, Callable, Iterator

import pytest

import posediff

from conftest import images_of

ray = pytest.importorskip("ray", reason="Ray is not installed (cargo xtask setup installs it)")
import posediff.distributed as distributed  # noqa: E402

OPTIONS = {"pairs": "exhaustive"}


@pytest.fixture(scope="module")
def cluster() -> Iterator[None]:
    # Ray 2.52's notice about a future default for GPU variables (no GPU here).
    os.environ.setdefault("RAY_ACCEL_ENV_VAR_OVERRIDE_ON_ZERO", "0")
    ray.init(num_cpus=2, include_dashboard=False, logging_level="ERROR")
    yield
    ray.shutdown()


@pytest.fixture(scope="module")
def folder(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """Six fountain photos (15 pairs)."""
    d = tmp_path_factory.mktemp("fountain6")
    for f in sorted(images_of("strecha_fountainP11").glob("*"))[:6]:
        (d / f.name).write_bytes(f.read_bytes())
    return d


@pytest.fixture(scope="module")
def single(folder: Path, tmp_path_factory: pytest.TempPathFactory) -> bytes:
    """The single process's cameras.json with a database of its own."""
    d = tmp_path_factory.mktemp("single")
    rec = posediff.estimate(folder, database=d / "d.db", progress=False, **OPTIONS)
    rec.write(d / "out")
    return (d / "out" / "cameras.json").read_bytes()


def cameras(rec: Any, out: Path) -> bytes:
    rec.write(out)
    return (out / "cameras.json").read_bytes()


def test_ray_tasks_give_the_single_process_bytes(
    cluster: None, folder: Path, single: bytes, tmp_path: Path
) -> None:
    work = tmp_path / "work"
    rec = distributed.estimate(folder, work_dir=work, parts=3, options=OPTIONS)
    assert cameras(rec, tmp_path / "out") == single
    summary = distributed.fill_database(
        folder, tmp_path / "objects.db", parts=2, options=OPTIONS, transfer="objects"
    )
    assert summary["transfer"] == "objects" and summary["parts"] == 2
    # Every image and pair came from the tasks; the driver only merged.
    assert summary["imported_images"] == 6 and summary["imported_pairs"] == 15
    assert summary["pairs"] == 15 and summary["verified"] >= 12
    again = posediff.estimate(folder, database=tmp_path / "objects.db", progress=False, **OPTIONS)
    assert cameras(again, tmp_path / "out2") == single
    # No part is left beside the database.
    assert sorted(p.name for p in work.iterdir()) == ["database.db"]


def kill_once(marker: Path) -> Callable[[str, int], None]:
    """A hook that SIGKILLs the worker running matching part 1, the first time only."""

    def hook(stage: str, index: int) -> None:
        if stage == "matching" and index == 1 and not marker.exists():
            marker.write_text(str(os.getpid()))
            os.kill(os.getpid(), signal.SIGKILL)

    return hook


def test_a_killed_worker_costs_only_its_task(
    cluster: None, folder: Path, single: bytes, tmp_path: Path
) -> None:
    marker = tmp_path / "killed"
    summary = distributed.fill_database(
        folder,
        tmp_path / "d.db",
        parts=2,
        options=OPTIONS,
        transfer="objects",
        before_task=kill_once(marker),
    )
    assert marker.is_file(), "the hook did not kill a worker"
    # Ray ran the killed task again: every pair still came from a task.
    assert summary["imported_pairs"] == 15
    rec = posediff.estimate(folder, database=tmp_path / "d.db", progress=False, **OPTIONS)
    assert cameras(rec, tmp_path / "out") == single
    # Without retries the loss is an error, not a silent gap.
    marker.unlink()
    with pytest.raises(ray.exceptions.RayError):
        distributed.fill_database(
            folder,
            tmp_path / "e.db",
            parts=2,
            options=OPTIONS,
            max_retries=0,
            before_task=kill_once(marker),
        )


def test_wrong_arguments_fail_before_any_task(cluster: None, folder: Path, tmp_path: Path) -> None:
    with pytest.raises(ValueError, match="database: posediff.distributed sets it"):
        distributed.fill_database(folder, tmp_path / "d.db", options={"database": "x.db"})
    with pytest.raises(ValueError, match="pairs"):
        distributed.fill_database(folder, tmp_path / "d.db", options={"pairs": "sideways"})
    with pytest.raises(ValueError, match="transfer"):
        distributed.fill_database(folder, tmp_path / "d.db", transfer="carrier-pigeon")
    with pytest.raises(FileNotFoundError, match="does not exist"):
        distributed.fill_database(folder, tmp_path / "missing" / "d.db")
    assert not (tmp_path / "d.db").exists()
