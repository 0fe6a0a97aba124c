"""Extraction and matching as Ray tasks, the mapper on the driver.

The images are split into ``parts`` shards: each Ray task extracts one contiguous run of
images into a database of its own (the CLI's ``posediff features --shard K/N``); the driver
merges them into one COLMAP database (``--from``) and selects the pairs once, storing the
selection in it (``posediff match --select-only``); each task then matches every
``parts``-th pair of that selection on a copy of it (``posediff match --shard K/N``), and the
driver merges those and maps. The merged database is COLMAP's ``database.db``, resumable like
``--database``'s, and the cameras are byte-identical to a single process's ``posediff estimate --database``::

    import ray
    import posediff.distributed

    ray.init()                                  # or ray.init(address="auto") on a cluster
    rec = posediff.distributed.estimate("scene/images", work_dir="scene/work")
    rec.write("scene/out")

On a cluster the images must be readable at the same path on every node (a shared file
system), and the workers need posediff: ``ray.init(runtime_env={"pip": ["posediff"]})`` or a
``py_modules``/wheel entry. The databases travel through Ray's object store unless
``transfer="paths"`` says ``work_dir`` is shared too.

A task whose worker dies is run again by Ray (``max_retries``); its work is lost, nothing else.
"""

from __future__ import annotations

import os
import shutil
import sqlite3
import tempfile
import time
from pathlib import Path
from typing import TYPE_CHECKING, Any, Callable, Dict, List, Optional, Sequence, Tuple, Union

from . import _native

if TYPE_CHECKING:
    from os import PathLike

    from ._native import Reconstruction

__all__ = ["estimate", "fill_database"]

_Path = Union[str, "PathLike[str]"]

#: Keywords the distributed run sets itself.
_OWN_OPTIONS = ("database", "shard", "import_from")


def _ray() -> Any:
    try:
        import ray
    except ImportError as e:  # pragma: no cover - the message is the point
        raise ImportError(
            "posediff.distributed needs Ray: pip install 'posediff[distributed]' (or ray)"
        ) from e
    return ray


def _images_arg(images: Union[_Path, Sequence[_Path]]) -> Union[str, List[str]]:
    """Absolute paths (the workers run elsewhere, in other folders)."""
    if isinstance(images, (str, os.PathLike)):
        return str(Path(images).resolve())
    return [str(Path(p).resolve()) for p in images]


def _strip_features(db: Path) -> None:
    """Leaves a matching task's database with its pairs only (the driver has every image's
    features already): what travels back is the pairs' size, not the whole store's."""
    con = sqlite3.connect(db)
    try:
        con.execute("DELETE FROM keypoints")
        con.execute("DELETE FROM descriptors")
        con.commit()
        con.execute("VACUUM")
    finally:
        con.close()


def _part(
    stage: str,
    images: Union[str, List[str]],
    index: int,
    parts: int,
    options: Dict[str, Any],
    source: Any,
    out_dir: Optional[str],
    before_task: Optional[Callable[[str, int], Any]],
) -> Tuple[Union[str, bytes], Dict[str, Any]]:
    """One task: `stage` ("features" or "matching") of shard `index`/`parts` in a folder of
    its own; returns the database's path under `out_dir` (renamed there once complete), or
    its bytes when there is no shared `out_dir`, with the stage's summary."""
    if before_task is not None:
        before_task(stage, index)
    if isinstance(source, list):  # a reference inside a list is not resolved by Ray
        source = _ray().get(source[0])
    scratch = Path(tempfile.mkdtemp(prefix=f"posediff-{stage}-{index}-", dir=out_dir))
    try:
        db = scratch / "part.db"
        opts = dict(options, database=str(db), shard=f"{index}/{parts}")
        if stage == "matching":
            if isinstance(source, bytes):
                db.write_bytes(source)
            else:
                shutil.copyfile(source, db)
        done = _native.run_stages(images, stage, opts)
        if stage == "matching":
            _strip_features(db)
        if out_dir is None:
            return db.read_bytes(), done
        final = Path(out_dir) / f"{stage}-{index}-of-{parts}.db"
        os.replace(db, final)
        return str(final), done
    finally:
        shutil.rmtree(scratch, ignore_errors=True)


def fill_database(
    images: Union[_Path, Sequence[_Path]],
    database: _Path,
    *,
    parts: Optional[int] = None,
    options: Optional[Dict[str, Any]] = None,
    transfer: str = "auto",
    threads_per_task: int = 1,
    max_retries: int = 3,
    before_task: Optional[Callable[[str, int], Any]] = None,
) -> Dict[str, Any]:
    """Features and the first matching pass of `images` into `database` (COLMAP's
    database.db) as Ray tasks: the distributed ``posediff features`` + ``posediff match``.

    ``parts``: shards of each stage (default: the cluster's CPUs over ``threads_per_task``).
    ``options``: :class:`posediff.EstimateOptions` (matcher, pairs, masks, options, …) but
    not ``database``, ``shard`` or ``import_from``, which this sets. ``transfer``: ``"paths"``
    when the database's folder is visible to every worker (one machine, or a shared file
    system), ``"objects"`` to send the databases through Ray's object store, ``"auto"``: paths
    on a one-node cluster. ``threads_per_task``: CPUs each task holds (and its Rust threads).
    ``before_task``: called in the worker as ``before_task(stage, index)`` before each task.
    Returns the counts (``images``, ``pairs``, ``verified``, ``selection``; ``imported_images``
    and ``imported_pairs``: what came from the tasks), ``parts``, ``transfer`` and the seconds of
    each step (``seconds``).
    """
    ray = _ray()
    if not ray.is_initialized():
        ray.init()
    options = dict(options or {})
    for key in _OWN_OPTIONS:
        if key in options:
            raise ValueError(f"{key}: posediff.distributed sets it (give fill_database's arguments)")
    if transfer not in ("auto", "paths", "objects"):
        raise ValueError(f'transfer must be "auto", "paths" or "objects", got {transfer!r}')
    if threads_per_task < 1:
        raise ValueError(f"threads_per_task must be at least 1, got {threads_per_task}")
    cpus = int(ray.cluster_resources().get("CPU", 1))
    parts = parts if parts is not None else max(1, cpus // threads_per_task)
    if parts < 1:
        raise ValueError(f"parts must be at least 1, got {parts}")
    if transfer == "auto":
        transfer = "paths" if len(ray.nodes()) == 1 else "objects"
    database = Path(database).resolve()
    if not database.parent.is_dir():
        raise FileNotFoundError(f"{database.parent}: the database's folder does not exist")
    if database.exists() and not database.is_file():
        raise ValueError(f"{database}: is a folder; the database is a file (e.g. work/database.db)")
    images = _images_arg(images)
    # The options' checks before any task (a wrong option fails here, not in every worker).
    _native.check_options(dict(options, database=str(database)))
    work = Path(tempfile.mkdtemp(prefix="posediff-parts-", dir=database.parent))
    out_dir = str(work) if transfer == "paths" else None
    task = ray.remote(_part).options(
        num_cpus=threads_per_task,
        max_retries=max_retries,
        runtime_env={"env_vars": {"RAYON_NUM_THREADS": str(threads_per_task)}},
    )
    seconds: Dict[str, float] = {}
    tasks: Dict[str, List[Dict[str, Any]]] = {"features": [], "matching": []}

    def landed(
        results: List[Tuple[Union[str, bytes], Dict[str, Any]]], stage: str
    ) -> List[str]:
        paths = []
        for k, (r, done) in enumerate(results):
            tasks[stage].append(done)
            if isinstance(r, bytes):
                p = work / f"{stage}-{k}-of-{parts}.db"
                p.write_bytes(r)
                r = str(p)
            paths.append(r)
        return paths

    def stage(name: str, source: Any) -> Dict[str, Any]:
        """The tasks of `name`, then the driver's import of their databases."""
        clock = time.perf_counter()
        refs = [
            task.remote(name, images, k, parts, options, source, out_dir, before_task)
            for k in range(parts)
        ]
        done = landed(ray.get(refs), name)
        seconds[f"{name}_tasks"] = time.perf_counter() - clock
        clock = time.perf_counter()
        imported = _native.run_stages(
            images, "import", dict(options, database=str(database), import_from=done)
        )
        seconds[f"{name}_merge"] = time.perf_counter() - clock
        return imported

    try:
        merged = stage("features", None)
        # The pairs selected once, on the driver, and stored: the tasks match them.
        clock = time.perf_counter()
        _native.run_stages(images, "selection", dict(options, database=str(database)))
        seconds["selection"] = time.perf_counter() - clock
        pairs = stage(
            "matching",
            str(database) if transfer == "paths" else [ray.put(database.read_bytes())],
        )
    finally:
        shutil.rmtree(work, ignore_errors=True)
    summary = {
        "images": sum(t["images"] for t in tasks["features"]),
        "pairs": sum(t["pairs"] for t in tasks["matching"]),
        "verified": sum(t["verified"] for t in tasks["matching"]),
        "selection": tasks["matching"][0]["selection"].replace(f",shard:0/{parts}", ""),
        "imported_images": merged["imported_images"],
        "imported_pairs": pairs["imported_pairs"],
    }
    summary["parts"] = parts
    summary["transfer"] = transfer
    summary["seconds"] = seconds
    return summary


def estimate(
    images: Union[_Path, Sequence[_Path]],
    *,
    work_dir: _Path,
    parts: Optional[int] = None,
    options: Optional[Dict[str, Any]] = None,
    transfer: str = "auto",
    threads_per_task: int = 1,
    max_retries: int = 3,
    before_task: Optional[Callable[[str, int], Any]] = None,
) -> "Reconstruction":
    """Cameras (and points) of `images` with extraction and matching as Ray tasks
    (:func:`fill_database` into ``work_dir/database.db``) and the mapper on the driver:
    :func:`posediff.estimate` with ``database`` set, so the same images give the same bytes."""
    work_dir = Path(work_dir)
    work_dir.mkdir(parents=True, exist_ok=True)
    database = work_dir / "database.db"
    fill_database(
        images,
        database,
        parts=parts,
        options=options,
        transfer=transfer,
        threads_per_task=threads_per_task,
        max_retries=max_retries,
        before_task=before_task,
    )
    return _native.estimate(_images_arg(images), dict(options or {}, database=str(database)))
