"""Target-only work runs once per distinct target (rl/distinct.py, ConvEncoder.forward_pair): the
grouping is exact, and the policy's outputs and gradients are those of encoding every row."""

from __future__ import annotations

import pytest
import torch

import findview_baselines.rl.policy as policy_module
from findview_baselines.config import PPOAgentConfig
from findview_baselines.rl.distinct import PROBE_PIXELS, distinct_rows
from findview_baselines.rl.encoders import ConvEncoder
from findview_baselines.rl.policy import build_policy


def test_groups_repeated_rows_in_order_of_first_appearance() -> None:
    images = torch.randint(0, 256, (4, 3, 9, 9), dtype=torch.uint8, generator=torch.Generator().manual_seed(0))
    batch = images[[2, 0, 2, 1, 0, 3, 3]]
    first, inverse = distinct_rows(batch)
    assert first.tolist() == [0, 1, 3, 5]  # rows holding images 2, 0, 1, 3 first
    assert inverse.tolist() == [0, 1, 0, 2, 1, 3, 3]
    assert torch.equal(batch[first][inverse], batch)


def test_no_grouping_when_all_rows_differ_or_differ_off_the_probe() -> None:
    assert distinct_rows(torch.arange(12.0).view(4, 3)) is None
    assert distinct_rows(torch.zeros(1, 3, 8, 8)) is None
    # two flat images that differ in one pixel the probe does not sample: the full comparison catches it
    images = torch.zeros(3, 3, 64, 64, dtype=torch.uint8)
    size = images[0].numel()
    probed = set(torch.linspace(0, size - 1, PROBE_PIXELS).long().tolist())
    hidden = next(i for i in range(size) if i not in probed)
    images[1].view(-1)[hidden] = 7
    assert distinct_rows(images) is None
    images[2] = images[1]
    first, inverse = distinct_rows(images[[1, 2, 2]])
    assert first.tolist() == [0] and inverse.tolist() == [0, 0, 0]


def test_forward_pair_is_the_stacked_forward() -> None:
    torch.manual_seed(0)
    encoder = ConvEncoder(6, 48, 40, out_size=32)
    view, targets = torch.rand(5, 3, 48, 40), torch.rand(2, 3, 48, 40)
    inverse = torch.tensor([1, 0, 0, 1, 1])
    stacked = encoder(torch.cat([view, targets[inverse]], dim=1))
    torch.testing.assert_close(encoder.forward_pair(view, targets, inverse), stacked, rtol=1e-5, atol=1e-5)
    torch.testing.assert_close(encoder.forward_pair(view, targets[inverse]), stacked, rtol=1e-5, atol=1e-5)


@pytest.mark.parametrize("variant", ["early_fusion", "goal_encoder", "siamese"])
def test_rollout_outputs_and_gradients_match_encoding_every_row(variant: str, monkeypatch) -> None:
    """A rollout of T=6 steps, N=4 envs, each env changing target at step 3: log-probs, values and every
    parameter's gradient are those of the same policy encoding all 24 rows (grouping switched off)."""
    torch.manual_seed(0)
    policy = build_policy(PPOAgentConfig(variant=variant, hidden_size=32), 48, 48)
    steps, envs = 6, 4
    gen = torch.Generator().manual_seed(1)
    targets = torch.randint(0, 256, (2 * envs, 3, 48, 48), dtype=torch.uint8, generator=gen)
    which = torch.tensor([[i + (envs if t >= 3 else 0) for i in range(envs)] for t in range(steps)]).flatten()
    obs = {"view": torch.randint(0, 256, (steps * envs, 3, 48, 48), dtype=torch.uint8, generator=gen),
           "target": targets[which]}
    masks = torch.ones(steps * envs)
    masks[3 * envs: 4 * envs] = 0
    actions = torch.randint(0, 5, (steps * envs,), generator=gen)

    def run() -> tuple[torch.Tensor, torch.Tensor, list[torch.Tensor]]:
        policy.zero_grad()
        log_probs, values, entropy = policy.evaluate_actions(obs, torch.zeros(envs, 32), masks, actions)
        (log_probs.sum() + values.sum() + entropy.sum()).backward()
        return log_probs.detach(), values.detach(), [p.grad.clone() for p in policy.parameters()]

    calls: list[int | None] = []
    real = policy_module.distinct_rows
    monkeypatch.setattr(policy_module, "distinct_rows", lambda x: calls.append(len(real(x)[0])) or real(x))
    grouped = run()
    assert calls == [2 * envs]  # 8 distinct targets among 24 rows
    monkeypatch.setattr(policy_module, "distinct_rows", lambda x: None)
    every_row = run()
    torch.testing.assert_close(grouped[0], every_row[0], rtol=1e-5, atol=1e-5)
    torch.testing.assert_close(grouped[1], every_row[1], rtol=1e-5, atol=1e-5)
    for a, b in zip(grouped[2], every_row[2]):
        torch.testing.assert_close(a, b, rtol=1e-4, atol=1e-5)
