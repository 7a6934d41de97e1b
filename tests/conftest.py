"""Shared fixtures. Tests that need the real panoramas use ``sun360_mini``: under ``CI=true`` a missing
folder is a failure, elsewhere a skip."""

from __future__ import annotations

import os
from pathlib import Path

import findview  # noqa: F401  (first: sets OMP_WAIT_POLICY=PASSIVE before torch loads, see findview.runtime)
import pytest
import torch

REPO = Path(__file__).resolve().parents[1]
# the real panoramas: set FINDVIEW_SUN360_MINI to their folder (.ci/run does); without it those tests skip
SUN360_MINI = Path(os.environ.get("FINDVIEW_SUN360_MINI", "") or "/nonexistent/sun360_mini")

torch.set_num_threads(max(1, min(2, os.cpu_count() or 1)))
# heavy work (network updates) on a fixed thread count, so that runs compared bit for bit use the same one
# whatever else the machine runs (unset, findview.runtime.heavy_threads follows the competing load); the
# thread policy's own tests set or clear it themselves. Subprocesses (DD-PPO ranks, tools) inherit it.
os.environ.setdefault("FINDVIEW_COMPUTE_THREADS", "2" if (os.cpu_count() or 1) >= 2 else "1")


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
    return _need(SUN360_MINI, "sun360_mini (set FINDVIEW_SUN360_MINI to its folder)")


@pytest.fixture(scope="session")
def sun360_mini_files(sun360_mini: Path) -> list[Path]:
    files = sorted(sun360_mini.rglob("pano_*.jpg"))
    assert len(files) == 36, f"expected 36 panoramas under {sun360_mini}, found {len(files)}"
    return files


@pytest.fixture(scope="session")
def repo_root() -> Path:
    return REPO


# ---- the tiny training setup shared by test_train.py and test_run_safety.py ----------------------
import cv2  # noqa: E402

from _training import blob_panorama, make_config  # noqa: E402


@pytest.fixture(scope="session")
def panorama_folder(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """10 small textured panoramas (256x128) in one folder."""
    root = tmp_path_factory.mktemp("panoramas")
    for i in range(10):
        cv2.imwrite(str(root / f"pano_{i:03d}.png"), blob_panorama(100 + i))
    return root


@pytest.fixture(scope="session")
def dataset_out(tmp_path_factory: pytest.TempPathFactory) -> Path:
    return tmp_path_factory.mktemp("dataset_out")


@pytest.fixture()
def make_cfg(panorama_folder: Path, dataset_out: Path):
    return lambda **overrides: make_config(panorama_folder, dataset_out, **overrides)


@pytest.fixture(scope="session")
def reference_run(panorama_folder: Path, dataset_out: Path, tmp_path_factory: pytest.TempPathFactory) -> Path:
    """6 updates in one go (levels 1, 2, 3 at updates 0, 2, 4; validation at 3 and 6)."""
    from findview_baselines.training import train

    run_dir = tmp_path_factory.mktemp("run_full")
    result = train(make_config(panorama_folder, dataset_out), run_dir)
    assert result.completed and result.updates == 6 and result.env_steps == 6 * 8 * 2
    return run_dir




@pytest.fixture
def one_torch_thread():
    """Small networks run fastest on one torch thread, and a second one stalls on a busy machine."""
    previous = torch.get_num_threads()
    torch.set_num_threads(1)
    yield
    torch.set_num_threads(previous)
