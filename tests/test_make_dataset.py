"""tools/make_dataset.py: the command-line contract (run as a subprocess, like a user would)."""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import cv2
import numpy as np

from findview.dataset import DIFFICULTIES, episode_file, load_episodes, load_split, satisfies

REPO = Path(__file__).resolve().parents[1]
TOOL = REPO / "tools" / "make_dataset.py"


def _run(*overrides: str, cwd: Path) -> subprocess.CompletedProcess:
    return subprocess.run(
        [sys.executable, str(TOOL), "progress=false", *overrides],
        cwd=cwd, capture_output=True, text=True, timeout=240,
    )


def _panos(root: Path, names: list[str]) -> list[Path]:
    rng = np.random.default_rng(0)
    out = []
    for name in names:
        p = root / name
        p.parent.mkdir(parents=True, exist_ok=True)
        assert cv2.imwrite(str(p), rng.integers(0, 256, (128, 256, 3), dtype=np.uint8))
        out.append(p)
    return out


def test_folder_all_in_test_with_k_episodes(tmp_path: Path) -> None:
    root = tmp_path / "panos"
    files = _panos(root, ["a.jpg", "kitchen/k1.jpg", "kitchen/k2.png", "street/s1.jpg", "street/s2.jpg"])
    K = 2
    res = _run(
        "dataset=folder", f"dataset.root={root}", "dataset.out_dir=out", "dataset.split=[0,0,1]",
        f"dataset.episodes_per_image={K}", cwd=tmp_path,
    )
    assert res.returncode == 0, res.stderr
    out = tmp_path / "out"  # relative out_dir resolves against the launch directory
    assert not (tmp_path / "outputs").exists() and not (tmp_path / ".hydra").exists()
    test = load_split(out, "test")
    assert sorted(Path(e.path) for e in test) == sorted(files)
    assert load_split(out, "train") == [] and load_split(out, "val") == []
    assert {Path(e.path).name: e.label for e in test}["k1.jpg"] == "kitchen"
    for fov in (90, 60):
        eps = load_episodes(episode_file(out, "test", fov))
        assert len(eps) == len(files) * K * len(DIFFICULTIES)
        for f in files:
            for d in DIFFICULTIES:
                assert sum(e.image == str(f) and e.difficulty == d for e in eps) == K
        assert all(satisfies(e.init_pitch, e.init_yaw, e.target_pitch, e.target_yaw, e.difficulty, fov) for e in eps)
        assert load_episodes(episode_file(out, "val", fov)) == []
    doc = json.loads((out / "splits.json").read_text())
    assert doc["root"] == str(root) and doc["ratios"] == [0.0, 0.0, 1.0]
    assert "test" in res.stdout and str(episode_file(out, "test", 90)) in res.stdout


def test_invalid_images_fail_with_the_file_names(tmp_path: Path) -> None:
    root = tmp_path / "panos"
    _panos(root, ["ok1.jpg", "sub/ok2.jpg"])
    assert cv2.imwrite(str(root / "sub" / "wrong_size.png"), np.zeros((200, 300, 3), np.uint8))
    ok, buf = cv2.imencode(".jpg", np.random.default_rng(1).integers(0, 256, (128, 256, 3), dtype=np.uint8))
    (root / "truncated.jpg").write_bytes(buf.tobytes()[: len(buf) // 2])
    res = _run("dataset=folder", f"dataset.root={root}", f"dataset.out_dir={tmp_path / 'out'}", cwd=tmp_path)
    assert res.returncode == 2
    assert "Traceback" not in res.stderr
    last = res.stderr.strip().splitlines()[-1]
    assert last.startswith("make_dataset: error: 2 invalid panoramas")
    assert "wrong_size.png" in last and "300x200" in last and "truncated.jpg" in last
    assert not (tmp_path / "out" / "splits.json").exists()


def test_missing_root(tmp_path: Path) -> None:
    res = _run("dataset=sun360_indoor", "dataset.root=null", cwd=tmp_path)
    assert res.returncode == 2 and "Traceback" not in res.stderr
    assert "dataset.root is not set" in res.stderr and "dataset.root=" in res.stderr


def test_episode_settings_are_dataset_keys(tmp_path: Path) -> None:
    """The static episodes follow dataset.episode_pitch_bound / episode_max_steps (no task.* settings)."""
    root = tmp_path / "panos"
    _panos(root, ["a/p1.jpg", "a/p2.jpg", "b/p3.jpg"])
    res = _run(
        "dataset=folder", f"dataset.root={root}", "dataset.out_dir=out", "dataset.split=[0,0,1]",
        "dataset.episode_fovs=[90]", "dataset.episode_pitch_bound=20", "dataset.episode_max_steps=150", cwd=tmp_path,
    )
    assert res.returncode == 0, res.stderr
    path = episode_file(tmp_path / "out", "test", 90)
    eps = load_episodes(path)
    assert len(eps) == 3 * len(DIFFICULTIES)
    for e in eps:
        assert max(abs(e.init_pitch), abs(e.target_pitch)) <= 20
        l1 = abs(e.init_pitch - e.target_pitch) + min(abs(e.init_yaw - e.target_yaw) % 360,
                                                      360 - abs(e.init_yaw - e.target_yaw) % 360)
        assert 10 < l1 < 150
    header = json.loads(path.read_text())
    assert header["pitch_bound"] == 20 and header["max_steps"] == 150
