#!/usr/bin/env python
"""One target view under all 16 corruptions at one severity (Hydra; ``configs/render_corruptions.yaml``).

The picture of the paper's appendix figures: a grid with one row per category (blur, noise,
digital, weather) and one column per corruption, each tile captioned with its name, after a first
column holding the clean view in every row ("clear (<category>)"). Tiles are the simulator's ``sim.height x sim.width`` view;
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

from findview_baselines.cli import ToolContext, run_tool
from findview_baselines.config import RenderCorruptionsConfig

log = logging.getLogger("findview.render_corruptions")


def _label(tile: np.ndarray, text: str) -> np.ndarray:
    """``tile`` with ``text`` in white on a dark box in its top-left corner (a box, not an outline: a thick
    outline fills the gap between words, "blur 3" read "blur3")."""
    import cv2

    h = tile.shape[0]
    scale = max(0.3, h / 400.0)
    thickness = 1 if h < 300 else 2
    (tw, th), base = cv2.getTextSize(text, cv2.FONT_HERSHEY_SIMPLEX, scale, thickness)
    pad = max(2, int(round(4 * scale)))
    x1, y1 = min(tile.shape[1], tw + 2 * pad), min(h, th + base + 2 * pad)
    tile[:y1, :x1] = (tile[:y1, :x1].astype(np.float32) * 0.35).astype(np.uint8)  # dark, the view shows through
    cv2.putText(tile, text, (pad, pad + th), cv2.FONT_HERSHEY_SIMPLEX, scale, (255, 255, 255), thickness, cv2.LINE_AA)
    return tile


def corruption_grid(view: np.ndarray, severity: int, seed: int = 0, labels: bool = True) -> np.ndarray:
    """The grid picture for one RGB view ``(H, W, 3)`` uint8 -> ``(4 H, 5 W, 3)`` uint8.

    Row ``r`` shows the four corruptions of category ``r`` (in the paper's order) in columns 1-4;
    column 0 holds the clean view in every row (captioned ``clear (<category>)``), the
    reference to compare each row with (the grid has 20 tiles for 16 corruptions: no tile is left
    black). All corruptions draw from one ``torch.Generator`` seeded with ``seed``, in the order of
    ``findview.corruptions.NAMES``.
    """
    import torch

    from findview.corruptions import CATEGORIES, check_severity, corrupt

    severity = check_severity(severity)
    h, w = view.shape[:2]
    x = torch.from_numpy(np.ascontiguousarray(view)).permute(2, 0, 1)[None]
    g = torch.Generator().manual_seed(int(seed))
    grid = np.zeros((4 * h, 5 * w, 3), np.uint8)

    def put(tile: np.ndarray, row: int, col: int, text: str) -> None:
        tile = np.ascontiguousarray(tile).copy()
        grid[row * h : (row + 1) * h, col * w : (col + 1) * w] = _label(tile, text) if labels else tile

    for row, (category, names) in enumerate(CATEGORIES.items()):
        put(view, row, 0, f"clear  ({category})")
        for col, name in enumerate(names, start=1):
            y = corrupt(x, name, severity, g)[0].permute(1, 2, 0).numpy()
            put(y, row, col, f"{name}  {severity}")  # two spaces: Hershey spaces are narrow
    return grid


def render(cfg: RenderCorruptionsConfig, run_dir: Path, choices: dict, overrides: list[str]) -> Path:
    """Render the target view, corrupt it 16 ways and write the grid; returns the PNG path (a composed
    ``DictConfig`` is validated first)."""
    from findview_baselines.config import typed_config

    from findview.geometry import wrap_yaw
    from findview.imageio import load_panorama
    from findview_baselines.evaluation.evaluate import EvalError, resolve_episodes
    from findview_baselines.rl.checkpoint import check_writable
    from findview_baselines.evaluation.viz import parse_rotation, render_views, write_png

    cfg = typed_config(cfg)
    severity = cfg.severity
    if cfg.image is not None or cfg.target is not None:
        if cfg.image is None or cfg.target is None:
            raise EvalError("explicit mode needs both image= and target=")
        image = str(Path(str(cfg.image)).expanduser())
        target = parse_rotation(cfg.target, "target")
        name = Path(image).stem
    else:
        episodes, path, _ = resolve_episodes(cfg, choices.get("dataset"), overrides, logger=log)
        k = cfg.episode_index
        if not 0 <= k < len(episodes):
            raise EvalError(f"episode_index={k} is out of range: {path} holds {len(episodes)} episodes")
        ep = episodes[k]
        image, target, name = ep.image, (ep.target_pitch, ep.target_yaw), ep.episode_id
    bound = cfg.task.pitch_bound
    if abs(target[0]) > bound:
        raise EvalError(f"target pitch {target[0]} is outside [-{bound}, {bound}] (task.pitch_bound)")
    target = (target[0], int(wrap_yaw(target[1])))
    try:
        pano = load_panorama(image)
    except OSError as err:  # PanoramaError (a bad image) is a user error of its own
        raise EvalError(f"{image}: {err.strerror or err}") from err
    sim = cfg.sim
    view = render_views(pano, [target], float(sim.fov), sim.height, sim.width, sim.mode)[0]
    grid = corruption_grid(view, severity, cfg.seed)
    out = Path(cfg.out).expanduser() if cfg.out else run_dir / f"corruptions_s{severity}.png"
    if out.suffix.lower() != ".png":
        raise EvalError(f"out= must name a .png file, got {out}")
    check_writable(out.parent, "output folder of out=" if cfg.out else "run folder (hydra.run.dir)")

    write_png(out, grid)
    log.info("%s: target %s under 16 corruptions at severity %d -> %s (%dx%d)", name, target, severity, out,
             grid.shape[1], grid.shape[0])
    return out


def main(cfg: RenderCorruptionsConfig, ctx: ToolContext) -> None:
    """Draw the corruption grid and print the PNG path."""
    print(render(cfg, ctx.run_dir, ctx.choices, ctx.overrides))


if __name__ == "__main__":
    run_tool("render_corruptions", main)
