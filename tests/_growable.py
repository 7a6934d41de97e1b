"""Shared check of the policy's zero-started extra inputs (``agent.pitch_warps``, ``agent.wide_match``): a policy
grown by one of them starts as the saved policy without it."""

from __future__ import annotations

from pathlib import Path

import pytest
import torch
from torch import nn

from findview_baselines.rl.checkpoint import CheckpointError, load_policy, save_checkpoint
from findview_baselines.rl.policy import Policy


def check_grows_from_a_checkpoint_without_it(tmp_path: Path, plain: Policy, grown: Policy, field: str, width: int,
                                             projection: nn.Sequential) -> None:
    """``grown`` is ``plain``'s model plus the input ``field`` (``width`` fixed features, read by ``projection``, an
    MLP whose last layer starts at zero). Loading ``plain``'s checkpoint into ``grown`` is refused for evaluation and
    accepted for ``init_from``; then both give the same logits and values, the cached fixed features give what the
    observations give, and once the projection's last layer has weights the input reaches the logits."""
    path = save_checkpoint(tmp_path / "plain.pth", {"signature": plain.model_signature(), "policy": plain.state_dict()})
    assert grown.model_signature()[field] == width
    assert grown.fixed_feature_size == plain.fixed_feature_size + width
    with pytest.raises(CheckpointError, match=f"{field} is 0 in the checkpoint but {width}"):
        load_policy(path, grown)  # evaluating / resuming needs the same model
    load_policy(path, grown, transfer=True)  # init_from: the projection's last layer starts at zero
    size = plain.height
    gen = torch.Generator().manual_seed(1)
    obs = {k: torch.randint(0, 256, (4, 3, size, size), dtype=torch.uint8, generator=gen) for k in ("view", "target")}
    hidden, masks = torch.zeros(4, plain.hidden_size), torch.ones(4)
    with torch.no_grad():
        d0, v0, _ = plain(obs, hidden, masks)
        d1, v1, _ = grown(obs, hidden, masks)
        f_obs = grown.features(obs)
        f_fixed = grown.features(None, fixed=grown.fixed_features(obs))
    assert torch.allclose(d0.logits, d1.logits) and torch.allclose(v0, v1)
    torch.testing.assert_close(f_obs, f_fixed)
    with torch.no_grad():
        projection[-1].weight.fill_(0.5)
        d2, _, _ = grown(obs, hidden, masks)
    assert not torch.allclose(d1.logits, d2.logits)
