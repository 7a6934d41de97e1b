"""The shipped agents in pretrained/: small, loadable without pickle, documented, and they act."""

from __future__ import annotations

from pathlib import Path

import pytest
import torch

from findview_baselines.agents.ppo_agent import PPOAgent

REPO = Path(__file__).resolve().parents[1]
SHIPPED = sorted((REPO / "pretrained").glob("*.pth"))
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
