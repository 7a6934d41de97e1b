"""Shared fixtures. Tests that need the real panoramas use ``sun360_mini``: under ``CI=true`` a missing
folder is a failure, elsewhere a skip."""

from __future__ import annotations

import os
from pathlib import Path

import pytest
import torch

REPO = Path(__file__).resolve().parents[1]
SUN360_MINI = Path(os.environ.get("FINDVIEW_SUN360_MINI", REPO.parent / "shared" / "data" / "sun360_mini"))
FROST_DIR = REPO.parent / "shared" / "data" / "frost"

torch.set_num_threads(max(1, min(2, os.cpu_count() or 1)))


def _need(path: Path, what: str) -> Path:
    if not path.is_dir():
        msg = f"{what} not found at {path}"
        if os.environ.get("CI", "").lower() == "true":
            pytest.fail(msg + " (CI=true: this data must be present)")
        pytest.skip(msg)
    return path


@pytest.fixture(scope="session")
def sun360_mini() -> Path:
    """Root of the 36 real SUN360 panoramas (SUN360 layout)."""
    return _need(SUN360_MINI, "sun360_mini")


@pytest.fixture(scope="session")
def sun360_mini_files(sun360_mini: Path) -> list[Path]:
    files = sorted(sun360_mini.rglob("pano_*.jpg"))
    assert len(files) == 36, f"expected 36 panoramas under {sun360_mini}, found {len(files)}"
    return files


@pytest.fixture(scope="session")
def repo_root() -> Path:
    return REPO
