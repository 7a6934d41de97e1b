"""The shipped files in pretrained/: small, loadable without pickle, documented; the agents act, the stop-offset nets
(``stop_offsets_*.pth``, agent.refine_model) answer for their views."""

from __future__ import annotations

from pathlib import Path

import pytest
import torch

from findview_baselines.agents.ppo_agent import PPOAgent

REPO = Path(__file__).resolve().parents[1]
SHIPPED = sorted(p for p in (REPO / "pretrained").glob("*.pth") if not p.name.startswith("stop_offsets_"))
STOP_OFFSETS = sorted((REPO / "pretrained").glob("stop_offsets_*.pth"))
CARD = REPO / "pretrained" / "README.md"


def test_at_least_one_agent_ships() -> None:
    assert SHIPPED, "pretrained/ holds no *.pth (the shipped agents are tracked in git)"


@pytest.mark.parametrize("path", SHIPPED, ids=[p.name for p in SHIPPED])
def test_shipped_agent_is_small_documented_and_acts(path: Path) -> None:
    assert path.stat().st_size < 5 * 1024 * 1024, f"{path.name} is over 5 MB"
    assert f"`{path.name}`" in CARD.read_text(), f"{path.name} has no model card in pretrained/README.md"
    payload = torch.load(path, map_location="cpu", weights_only=True)
    assert {"signature", "policy"} <= set(payload)
    agent = PPOAgent.from_checkpoint(path, num_envs=2)
    sig = payload["signature"]
    obs = {
        "view": torch.randint(0, 256, (2, 3, sig["height"], sig["width"]), dtype=torch.uint8),
        "target": torch.randint(0, 256, (2, 3, sig["height"], sig["width"]), dtype=torch.uint8),
    }
    agent.reset([0, 1], [None, None])
    actions = agent.act(obs)
    assert actions.shape == (2,) and actions.dtype == torch.long and bool(((actions >= 0) & (actions < 5)).all())


@pytest.mark.parametrize("path", STOP_OFFSETS, ids=[p.name for p in STOP_OFFSETS])
def test_shipped_stop_offsets_are_small_documented_and_answer(path: Path) -> None:
    from findview_baselines.agents.stop_offsets import load_stop_offsets

    assert path.stat().st_size < 5 * 1024 * 1024, f"{path.name} is over 5 MB"
    assert f"`{path.name}`" in CARD.read_text(), f"{path.name} has no card in pretrained/README.md"
    net = load_stop_offsets(path)
    assert f"fov{net.fov:g}_{net.size}" in path.name, f"{path.name} is for FoV {net.fov:g}, {net.size}x{net.size} views"
    views = torch.randint(0, 256, (2, 3, net.size, net.size), dtype=torch.uint8)
    dpitch, dyaw, stay = net.offsets(views, views)
    assert bool((stay > 0.5).all()), "a view identical to its target should be left alone"
    assert dpitch.tolist() == [0, 0] and dyaw.tolist() == [0, 0]
    if net.near:  # a file with the near output (agent.refine_min_near) keeps a stop on the target itself
        assert bool((net.near_prob(views, views) > 0.5).all()), "a view identical to its target should be near it"
