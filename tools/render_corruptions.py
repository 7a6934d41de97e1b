#!/usr/bin/env python
"""One target view under all 16 corruptions at one severity (Hydra; ``configs/render_corruptions.yaml``).

The picture of the paper's appendix figures: a grid with one row per category (blur, noise,
digital, weather) and one column per corruption, each tile captioned with its name, after a first
column holding the clean view ("clear"). Tiles are the simulator's ``sim.height x sim.width`` view;
the picture is ``4 H x 5 W`` pixels.

Examples::

    python tools/render_corruptions.py dataset=synthetic split=test episode_index=0 severity=3
    python tools/render_corruptions.py image=pano.jpg target=[0,90] severity=5 out=corruptions.png

The PNG is written atomically.
"""

from __future__ import annotations

import logging
from pathlib import Path

import numpy as np
from omegaconf import DictConfig

from findview_baselines.cli import ToolContext, run_tool

log = logging.getLogger("findview.render")


def corruption_grid(view: np.ndarray, severity: int, seed: int = 0, labels: bool = True) -> np.ndarray:
    """The grid picture for one RGB view ``(H, W, 3)`` uint8 -> ``(4 H, 5 W, 3)`` uint8.

    Row ``r`` shows the four corruptions of category ``r`` (in the paper's order) in columns 1-4;
    column 0 holds the clean view in row 0 and is black below. All corruptions draw from one
    ``torch.Generator`` seeded with ``seed``, in the order of ``findview.corruptions.NAMES``.
    """
    import cv2
    import torch

    from findview.corruptions import CATEGORIES, check_severity, corrupt

    severity = check_severity(severity)
    h, w = view.shape[:2]
    x = torch.from_numpy(np.ascontiguousarray(view)).permute(2, 0, 1)[None]
    g = torch.Generator().manual_seed(int(seed))
    grid = np.zeros((4 * h, 5 * w, 3), np.uint8)

    def put(tile: np.ndarray, row: int, col: int, text: str) -> None:
        tile = np.ascontiguousarray(tile)
        if labels:
            scale = max(0.3, h / 400.0)
            org = (4, 4 + int(14 * scale))
            cv2.putText(tile, text, org, cv2.FONT_HERSHEY_SIMPLEX, scale, (0, 0, 0), 3, cv2.LINE_AA)
            cv2.putText(tile, text, org, cv2.FONT_HERSHEY_SIMPLEX, scale, (255, 255, 255), 1, cv2.LINE_AA)
        grid[row * h : (row + 1) * h, col * w : (col + 1) * w] = tile

    put(view.copy(), 0, 0, "clear")
    for row, names in enumerate(CATEGORIES.values()):
        for col, name in enumerate(names, start=1):
            y = corrupt(x, name, severity, g)[0].permute(1, 2, 0).numpy()
            put(y, row, col, f"{name} {severity}")
    return grid


def render(cfg: DictConfig, run_dir: Path, choices: dict, overrides: list[str]) -> Path:
    """Render the target view, corrupt it 16 ways and write the grid; returns the PNG path."""

    from findview.geometry import wrap_yaw
    from findview.imageio import load_panorama
    from findview_baselines.evaluation.evaluate import EvalError, resolve_episodes
    from findview_baselines.evaluation.viz import parse_rotation, render_views, write_png

    severity = int(cfg.severity)
    if cfg.get("image") is not None or cfg.get("target") is not None:
        if cfg.get("image") is None or cfg.get("target") is None:
            raise EvalError("explicit mode needs both image= and target=")
        image = str(Path(str(cfg.image)).expanduser())
        target = parse_rotation(cfg.target, "target")
        name = Path(image).stem
    else:
        episodes, path, _ = resolve_episodes(cfg, choices.get("dataset"), overrides)
        k = int(cfg.episode_index)
        if not 0 <= k < len(episodes):
            raise EvalError(f"episode_index={k} is out of range: {path} holds {len(episodes)} episodes")
        ep = episodes[k]
        image, target, name = ep.image, (ep.target_pitch, ep.target_yaw), ep.episode_id
    bound = int(cfg.task.pitch_bound)
    if abs(target[0]) > bound:
        raise EvalError(f"target pitch {target[0]} is outside [-{bound}, {bound}] (task.pitch_bound)")
    target = (target[0], int(wrap_yaw(target[1])))
    try:
        pano = load_panorama(image)
    except (OSError, ValueError) as err:
        raise EvalError(str(err)) from err
    sim = cfg.sim
    view = render_views(pano, [target], float(sim.fov), int(sim.height), int(sim.width), str(sim.mode))[0]
    grid = corruption_grid(view, severity, int(cfg.seed))
    out = Path(str(cfg.out)).expanduser() if cfg.get("out") else run_dir / f"corruptions_s{severity}.png"
    if out.suffix.lower() != ".png":
        raise EvalError(f"out= must name a .png file, got {out}")

    write_png(out, grid)
    log.info("%s: target %s under 16 corruptions at severity %d -> %s (%dx%d)", name, target, severity, out,
             grid.shape[1], grid.shape[0])
    return out


def main(cfg: DictConfig, ctx: ToolContext) -> None:
    print(render(cfg, ctx.run_dir, ctx.choices, ctx.overrides))


if __name__ == "__main__":
    run_tool("render_corruptions", main)
