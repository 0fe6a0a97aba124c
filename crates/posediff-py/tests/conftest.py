"""Shared paths of the Python tests: the repository, ../shared and the posediff binary."""

from __future__ import annotations

import os
import subprocess
from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parents[3]
SHARED = Path(os.environ.get("POSEDIFF_SHARED", REPO.parent / "shared"))
SETS = ["strecha_fountainP11", "co3d_apple_posediffusion", "middlebury_templeSR"]


def images_of(name: str) -> Path:
    return SHARED / "data" / name / "images"


@pytest.fixture(scope="session")
def cli() -> Path:
    """The posediff binary of the same build (`POSEDIFF_BIN`, set by `cargo xtask ci`)."""
    path = os.environ.get("POSEDIFF_BIN")
    assert path, "set POSEDIFF_BIN to the posediff binary (cargo xtask py-test does)"
    binary = Path(path)
    assert binary.is_file(), f"POSEDIFF_BIN={binary} is not a file"
    return binary


def run_cli(binary: Path, *args: object) -> subprocess.CompletedProcess[str]:
    r = subprocess.run([str(binary), *map(str, args)], capture_output=True, text=True)
    assert r.returncode == 0, r.stderr
    return r
