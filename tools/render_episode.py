#!/usr/bin/env python
"""Draw one episode like the paper's Figure 2 (Hydra; config ``configs/render_episode.yaml``).

The panorama (``pano_height`` x twice that, default twice the view height) shows the initial view's
outline (red) and the target view's (yellow), projected with the simulator's exact mapping; the two
perspective views (initial above target) sit to its right. Picture size:
``max(pano_height, 2 H) x (2 pano_height + W)`` for ``H x W`` views.

Examples::

    python tools/render_episode.py dataset=synthetic split=test episode_index=3 out=episode.png
    python tools/render_episode.py image=pano.jpg init=[0,0] target=[10,-40] out=episode.png

The PNG is written atomically.
"""

from __future__ import annotations

import logging
from pathlib import Path

from findview_baselines.cli import ToolContext, run_tool
from findview_baselines.config import RenderEpisodeConfig

log = logging.getLogger("findview.render_episode")


def render(cfg: RenderEpisodeConfig, run_dir: Path, choices: dict, overrides: list[str]) -> Path:
    """Make the picture of the validated config; returns the PNG path (a composed ``DictConfig`` is validated
    first)."""
    from findview_baselines.config import typed_config

    from findview.imageio import load_panorama
    from findview.geometry import wrap_yaw
    from findview_baselines.evaluation.evaluate import EvalError, resolve_episodes
    from findview_baselines.rl.checkpoint import check_writable
    from findview_baselines.evaluation.viz import episode_figure, parse_rotation, write_png

    cfg = typed_config(cfg)
    fov, height, width = float(cfg.sim.fov), cfg.sim.height, cfg.sim.width
    pitch_bound = cfg.task.pitch_bound
    explicit = {"image": cfg.image, "init": cfg.init, "target": cfg.target}
    if any(v is not None for v in explicit.values()):
        missing = [k for k, v in explicit.items() if v is None]
        if missing:
            raise EvalError(f"explicit mode needs image=, init= and target=; missing: {', '.join(missing)}")
        image = str(Path(str(cfg.image)).expanduser())
        init, target = parse_rotation(cfg.init, "init"), parse_rotation(cfg.target, "target")
        name = Path(image).stem
    else:
        episodes, path, _ = resolve_episodes(cfg, choices.get("dataset"), overrides, logger=log, episodes_file=cfg.episodes)
        k = cfg.episode_index
        if not 0 <= k < len(episodes):
            raise EvalError(f"episode_index={k} is out of range: {path} holds {len(episodes)} episodes")
        ep = episodes[k]
        image, init, target, name = ep.image, (ep.init_pitch, ep.init_yaw), (ep.target_pitch, ep.target_yaw), ep.episode_id
    for what, (p, _) in (("init", init), ("target", target)):
        if abs(p) > pitch_bound:
            raise EvalError(f"{what} pitch {p} is outside [-{pitch_bound}, {pitch_bound}] (task.pitch_bound)")
    init = (init[0], int(wrap_yaw(init[1])))
    target = (target[0], int(wrap_yaw(target[1])))
    try:
        pano = load_panorama(image)
    except OSError as err:  # PanoramaError (a bad image) is a user error of its own
        raise EvalError(f"{image}: {err.strerror or err}") from err
    fig = episode_figure(
        pano, init, target, fov, height, width, cfg.sim.mode, cfg.pano_height, cfg.labels
    )
    safe = "".join(c if c.isalnum() or c in "-_." else "_" for c in name)
    out = Path(cfg.out).expanduser() if cfg.out else run_dir / f"{safe}.png"
    if out.suffix.lower() != ".png":
        raise EvalError(f"out= must name a .png file, got {out}")
    check_writable(out.parent, "output folder of out=" if cfg.out else "run folder (hydra.run.dir)")

    write_png(out, fig)
    log.info("episode %s: init %s, target %s -> %s (%dx%d)", name, init, target, out, fig.shape[1], fig.shape[0])
    return out


def main(cfg: RenderEpisodeConfig, ctx: ToolContext) -> None:
    """Draw the episode and print the PNG path."""
    print(render(cfg, ctx.run_dir, ctx.choices, ctx.overrides))


if __name__ == "__main__":
    run_tool("render_episode", main)
