"""Benchmark of issue 42: features + matches of a synthetic orbit through Ray on this machine
against the single process, the database written and read back, and a projection to 100,000
images (``cargo xtask bench-distributed``; JSON + Markdown in --out).

Steps, each timed by wall clock on the same images in one run:
1. single process: ``posediff features`` then ``posediff match`` into single.db;
2. Ray (a local cluster of --cpus CPUs, started before the clock): ``posediff.distributed
   .fill_database`` into ray.db, --parts shards of one thread each;
3. the two databases compared by image names: every keypoint list and every pair's matches
   equal, or the run fails;
4. the store written and read back: ``features``/``match --from single.db`` into a new
   database (everything read from one and written to the other), then both commands again on
   it (everything read back, nothing extracted or matched).
"""

from __future__ import annotations

import argparse
import hashlib
import json
import os
import platform
import sqlite3
import subprocess
import time
from pathlib import Path


def run(*args: object) -> float:
    clock = time.perf_counter()
    r = subprocess.run([str(a) for a in args], capture_output=True, text=True)
    if r.returncode != 0:
        raise SystemExit(f"{' '.join(map(str, args))}: {r.stderr}")
    return time.perf_counter() - clock


def digest(db: Path) -> dict:
    """Keypoints and pairs keyed by image names (ids differ between writers)."""
    con = sqlite3.connect(db)
    names = dict(con.execute("SELECT image_id, name FROM images"))
    kp = hashlib.sha256()
    for image_id, rows, data in sorted(
        con.execute("SELECT image_id, rows, data FROM keypoints"), key=lambda r: names[r[0]]
    ):
        kp.update(names[image_id].encode() + str(rows).encode() + (data or b""))
    pairs = []
    for pair_id, rows, data in con.execute("SELECT pair_id, rows, data FROM two_view_geometries"):
        a, b = divmod(pair_id, 2147483647)
        pairs.append((names[a], names[b], rows, hashlib.sha256(data or b"").hexdigest()))
    pairs.sort()
    con.close()
    return {
        "images": len(names),
        "keypoints_sha256": kp.hexdigest(),
        "pairs": len(pairs),
        "verified": sum(1 for p in pairs if p[2] > 0),
        "pairs_sha256": hashlib.sha256(json.dumps(pairs).encode()).hexdigest(),
    }


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("--images", type=Path, required=True)
    ap.add_argument("--posediff", type=Path, required=True)
    ap.add_argument("--out", type=Path, required=True)
    ap.add_argument("--cpus", type=int, default=os.cpu_count() or 1)
    ap.add_argument("--parts", type=int, default=None)
    ap.add_argument("--target-images", type=int, default=100_000)
    a = ap.parse_args()
    a.out.mkdir(parents=True, exist_ok=True)
    work = a.out / "work"
    work.mkdir(exist_ok=True)
    for f in work.glob("*.db*"):
        f.unlink()
    images = a.images.resolve()
    n = len([p for p in images.iterdir() if p.suffix.lower() in (".png", ".jpg", ".jpeg")])
    pd = a.posediff.resolve()

    single = work / "single.db"
    t_feat = run(pd, "features", images, "--database", single, "--quiet")
    t_match = run(pd, "match", images, "--database", single, "--quiet")
    print(f"single process: features {t_feat:.1f} s, matching {t_match:.1f} s", flush=True)

    import ray

    import posediff.distributed as distributed

    os.environ.setdefault("RAY_ACCEL_ENV_VAR_OVERRIDE_ON_ZERO", "0")
    clock = time.perf_counter()
    ray.init(num_cpus=a.cpus, include_dashboard=False, logging_level="ERROR")
    t_ray_init = time.perf_counter() - clock
    clock = time.perf_counter()
    summary = distributed.fill_database(images, work / "ray.db", parts=a.parts)
    t_ray = time.perf_counter() - clock
    ray.shutdown()
    print(f"ray: {t_ray:.1f} s ({summary['seconds']})", flush=True)

    d_single, d_ray = digest(single), digest(work / "ray.db")
    if d_single != d_ray:
        raise SystemExit(f"the databases differ: single {d_single}, ray {d_ray}")

    copy = work / "copy.db"
    t_write = run(pd, "features", images, "--database", copy, "--from", single, "--quiet")
    t_write += run(pd, "match", images, "--database", copy, "--from", single, "--quiet")
    t_read = run(pd, "features", images, "--database", copy, "--quiet")
    t_read += run(pd, "match", images, "--database", copy, "--quiet")
    if digest(copy) != d_single:
        raise SystemExit("the copied database differs")

    single_total = t_feat + t_match
    s = summary["seconds"]
    pairs = d_single["pairs"]
    # Projection: tasks scale with workers; the driver's merges are serial.
    per_image = t_feat / n * a.cpus  # one CPU's seconds per image
    per_pair = t_match / pairs * a.cpus
    merge_per_image = (s["features_merge"] + s["matching_merge"]) / n
    pairs_per_image = pairs / n
    projection = []
    for workers in (16, 64, 256, 1024):
        m = a.target_images
        tasks = (m * per_image + m * pairs_per_image * per_pair) / workers
        projection.append(
            {
                "workers": workers,
                "task_seconds": tasks,
                "driver_merge_seconds": m * merge_per_image,
                "total_hours": (tasks + m * merge_per_image) / 3600,
            }
        )
    result = {
        "host": platform.processor() or platform.machine(),
        "cpus": a.cpus,
        "images": n,
        "database": d_single,
        "single": {"features_s": t_feat, "matching_s": t_match, "total_s": single_total},
        "ray": {
            "init_s": t_ray_init,
            "total_s": t_ray,
            "parts": summary["parts"],
            "transfer": summary["transfer"],
            "steps_s": s,
            "overhead": t_ray / single_total - 1.0,
        },
        "store": {"write_s": t_write, "read_back_s": t_read, "total_s": t_write + t_read},
        "projection": {
            "images": a.target_images,
            "cpu_seconds_per_image": per_image,
            "cpu_seconds_per_pair": per_pair,
            "pairs_per_image": pairs_per_image,
            "driver_merge_seconds_per_image": merge_per_image,
            "rows": projection,
        },
    }
    (a.out / "bench_distributed.json").write_text(json.dumps(result, indent=2))
    md = [
        f"# Ray against the single process ({n} images, {a.cpus} CPUs)\n",
        "| run | features s | matching s | merges s | total s |",
        "|---|---:|---:|---:|---:|",
        f"| single process | {t_feat:.1f} | {t_match:.1f} | — | {single_total:.1f} |",
        f"| Ray, {summary['parts']} parts ({summary['transfer']}) | {s['features_tasks']:.1f} | "
        f"{s['matching_tasks']:.1f} | {s['features_merge'] + s['matching_merge']:.1f} | {t_ray:.1f} |",
        "",
        f"Ray overhead: {100 * (t_ray / single_total - 1):+.1f} % (ray.init {t_ray_init:.1f} s "
        "before the clock). Databases equal by image name: "
        f"{d_single['images']} images, {pairs} pairs ({d_single['verified']} verified).",
        "",
        f"Store: written (import of every feature and pair) {t_write:.1f} s, read back "
        f"{t_read:.1f} s, total {t_write + t_read:.1f} s.",
        "",
        f"## Projection to {a.target_images:,} images",
        "",
        f"Per image {per_image:.3f} CPU s of extraction, {pairs_per_image:.1f} pairs per image at "
        f"{per_pair:.4f} CPU s each, {merge_per_image * 1000:.1f} ms per image of serial driver "
        "merge; workers of one CPU each, the same pair density, no network or file-system limit.",
        "",
        "| workers | tasks h | driver merges h | total h |",
        "|---:|---:|---:|---:|",
    ]
    for row in projection:
        md.append(
            f"| {row['workers']} | {row['task_seconds'] / 3600:.2f} | "
            f"{row['driver_merge_seconds'] / 3600:.2f} | {row['total_hours']:.2f} |"
        )
    (a.out / "bench_distributed.md").write_text("\n".join(md) + "\n")
    print("\n".join(md))


if __name__ == "__main__":
    main()
