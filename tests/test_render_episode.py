"""tools/render_episode.py and the view-outline geometry of findview_baselines.evaluation.viz."""

from __future__ import annotations

import os
import subprocess
import sys
from pathlib import Path

import cv2
import numpy as np
import pytest
import torch

from _tools import load_tool
REPO = Path(__file__).resolve().parents[1]


@pytest.fixture(scope="module", autouse=True)
def one_torch_thread():
    """Small tensors: one intra-op thread is faster (and much faster on a busy machine)."""
    before = torch.get_num_threads()
    torch.set_num_threads(1)
    yield
    torch.set_num_threads(before)


def _tool_module():
    return load_tool("render_episode")


@pytest.fixture(scope="module")
def small_pano(tmp_path_factory, sun360_mini_files) -> Path:
    path = tmp_path_factory.mktemp("pano") / "pano.jpg"
    img = cv2.imread(str(sun360_mini_files[0]), cv2.IMREAD_COLOR)
    cv2.imwrite(str(path), cv2.resize(img, (512, 256), interpolation=cv2.INTER_AREA))
    return path


@pytest.fixture(scope="module")
def one_image_ds(tmp_path_factory, small_pano) -> dict[str, Path]:
    """A folder data set of one panorama, test split only (3 episodes: easy, medium, hard)."""
    base = tmp_path_factory.mktemp("one_image_ds")
    root, out_dir = base / "images", base / "data"
    (root / "room").mkdir(parents=True)
    (root / "room" / "pano.jpg").write_bytes(small_pano.read_bytes())
    from findview.config import DatasetConfig
    from findview.dataset import prepare_dataset

    prepare_dataset(
        DatasetConfig(**{"name": "one", "kind": "folder", "root": str(root), "out_dir": str(out_dir), "split": [0, 0, 1],
         "episode_fovs": [90], "splits_to_make": ["test"]}),
        [90], progress=False,
    )
    return {"root": root, "out": out_dir}


@pytest.mark.parametrize("pitch,yaw", [(0, 0), (35, -170), (-60, 95), (60, 180)])
def test_outline_follows_the_renderer_mapping(pitch, yaw):
    """Projected pixel centres equal the simulator's sample points (same camera mapping, docs/TASK.md)."""
    from findview.sim.equi2pers import pitch_grid
    from findview_baselines.evaluation.viz import project_view_points

    H, W, He, fov = 24, 32, 128, 90
    u, v = pitch_grid(torch.tensor([float(pitch)], dtype=torch.float64), fov, H, W, He)
    jj, ii = np.meshgrid(np.arange(H), np.arange(W), indexing="ij")
    uv = project_view_points(ii.ravel() + 0.5, jj.ravel() + 0.5, pitch, yaw, fov, H, W, He)
    We = 2 * He
    du = np.remainder(uv[:, 0] - (u[0].numpy().ravel() + yaw / 360 * We) + We / 2, We) - We / 2
    assert np.abs(du).max() < 1e-6
    assert np.abs(uv[:, 1] - v[0].numpy().ravel()).max() < 1e-6


def test_outline_drawn_across_the_seam():
    from findview_baselines.evaluation.viz import draw_outline, view_outline

    He = 64
    img = np.zeros((He, 2 * He, 3), np.uint8)
    draw_outline(img, view_outline(0, 180, 90, 32, 32, He), He, (255, 255, 255), 1)
    cols = np.flatnonzero(img[..., 0].max(axis=0) > 0)
    assert cols.min() < 10 and cols.max() > 2 * He - 10  # both sides of the seam
    assert img[:, 40:88].max() == 0  # nothing near the panorama centre (yaw 0)


def test_episode_figure_size_and_boxes(small_pano):
    from findview.imageio import load_panorama
    from findview_baselines.evaluation.viz import INIT_COLOR, TARGET_COLOR, downscale_panorama, episode_figure

    pano = load_panorama(str(small_pano))
    fig = episode_figure(pano, (0, 0), (20, 90), 90, 48, 64)
    assert fig.shape == (96, 2 * 96 + 64, 3)
    drawn = np.abs(fig[:, : 2 * 96].astype(int) - downscale_panorama(pano, 96).astype(int)).sum(axis=-1) > 60
    assert drawn[:, 96 - 30 : 96 + 30].sum() > 20  # initial view (yaw 0) outlined around the centre
    assert drawn[:, 144 - 20 : 144 + 30].sum() > 20  # target (yaw 90) a quarter turn to the right
    assert drawn[:, :40].sum() == 0  # nothing behind the camera
    for color, rows in ((INIT_COLOR, slice(0, 48)), (TARGET_COLOR, slice(48, 96))):  # framed views
        assert np.abs(fig[rows, 2 * 96].astype(int) - np.array(color)).sum(axis=-1).min() < 10


def test_render_episode_tool_from_dataset(tmp_path, one_image_ds):
    """The CLI on a one-image folder data set: a PNG of the expected size, written atomically."""
    png = tmp_path / "fig" / "episode.png"
    proc = subprocess.run(
        [sys.executable, str(REPO / "tools" / "render_episode.py"), "dataset=folder", f"dataset.root={one_image_ds['root']}",
         f"dataset.out_dir={one_image_ds['out']}", "dataset.split=[0,0,1]", "split=test", "episode_index=2", "sim.height=64", "sim.width=64",
         f"out={png}", f"hydra.run.dir={tmp_path / 'run'}"],
        capture_output=True, text=True, cwd=REPO, env={**os.environ, "OMP_NUM_THREADS": "1"}, timeout=120,
    )
    assert proc.returncode == 0, proc.stderr
    img = cv2.imread(str(png), cv2.IMREAD_UNCHANGED)
    assert img is not None and img.shape == (128, 2 * 128 + 64, 3)
    assert not list(png.parent.glob(".*.tmp"))


def test_render_episode_index_out_of_range(tmp_path, one_image_ds):
    from findview_baselines.cli import compose_config

    from findview_baselines.evaluation.evaluate import EvalError

    cfg = compose_config(
        "render_episode",
        ["dataset=folder", f"dataset.root={one_image_ds['root']}", f"dataset.out_dir={one_image_ds['out']}",
         "dataset.split=[0,0,1]", "episode_index=99"],
    )
    with pytest.raises(EvalError, match=r"episode_index=99.*3 episodes"):
        _tool_module().render(cfg, tmp_path, {"dataset": "folder"}, [])


def test_render_episode_explicit_rotations(tmp_path, small_pano):
    from findview_baselines.cli import compose_config

    tool = _tool_module()
    out = tmp_path / "explicit.png"
    cfg = compose_config(
        "render_episode",
        [f"image={small_pano}", "init=[0,0]", "target=[10,-40]", f"out={out}", "sim.height=48", "sim.width=64"],
    )
    path = tool.render(cfg, tmp_path, {}, [])
    assert path == out
    img = cv2.imread(str(out))
    assert img.shape == (96, 2 * 96 + 64, 3)

    from findview_baselines.evaluation.evaluate import EvalError

    cfg = compose_config("render_episode", [f"image={small_pano}", "init=[0,0]"])
    with pytest.raises(EvalError, match="target"):
        tool.render(cfg, tmp_path, {}, [])
    cfg = compose_config("render_episode", [f"image={small_pano}", "init=[80,0]", "target=[0,0]"])
    with pytest.raises(EvalError, match="pitch 80"):
        tool.render(cfg, tmp_path, {}, [])


@pytest.mark.parametrize("size,shown", [((64, 64), (256, 256)), ((48, 64), (288, 384)), ((256, 256), (256, 256))])
def test_video_frames_show_views_at_least_256_high(tmp_path, small_pano, size, shown):
    """Small agent views are enlarged by a whole factor (nearest neighbour) to >= 256 px high; the panorama
    strip beside them has the shown view height. A 64 x 64 view gave 256 x 64 frames before."""
    from findview.imageio import load_panorama
    from findview_baselines.evaluation.viz import render_views, write_video

    pano = load_panorama(small_pano)
    h, w = size
    rots = [(0, 0), (0, 1), (1, 1)]
    path = write_video(tmp_path / "v.mp4", pano, rots, (5, 10), 90.0, h, w)
    cap = cv2.VideoCapture(str(path))
    frames = []
    while True:
        ok, frame = cap.read()
        if not ok:
            break
        frames.append(cv2.cvtColor(frame, cv2.COLOR_BGR2RGB))
    sh, sw = shown
    assert len(frames) == len(rots)
    assert frames[0].shape == (sh, 2 * sw + 2 * sh, 3)
    # the first tile is the first view, enlarged (compared loosely: mp4v is lossy)
    view = render_views(pano, rots[:1], 90.0, h, w, "bilinear")[0]
    big = cv2.resize(view, (sw, sh), interpolation=cv2.INTER_NEAREST).astype(np.float32)
    inner = (slice(4, sh - 4), slice(4, sw - 4))  # inside the coloured border
    assert np.abs(frames[0][inner].astype(np.float32) - big[inner]).mean() < 12
