"""The correlation policy's fine photometric cost map (``agent.fine_shifts``) and its checkpoint signature."""

from __future__ import annotations

import pytest
import torch

from findview_baselines.agents.ppo_agent import PPOAgent
from findview_baselines.rl.policy import (
    DIRECT_COARSE,
    DIRECT_COARSE_SHIFTS,
    CorrelationEncoder,
    DirectEncoder,
    Policy,
    check_signature,
    pyramid_costs,
)


pytestmark = pytest.mark.usefixtures("one_torch_thread")


def images(n: int = 3, size: int = 32, seed: int = 0) -> torch.Tensor:
    return torch.rand(n, 3, size, size, generator=torch.Generator().manual_seed(seed))


def test_zero_shift_cost_is_exactly_zero_on_the_target() -> None:
    enc = CorrelationEncoder(32, 32, 16, fine_shifts=2)
    x = images()
    costs = enc.fine_costs(x, x.clone())
    assert costs.shape == (3, 25)
    assert torch.all(costs[:, 12] == 0.0)  # centre entry: shift (0, 0)
    assert torch.all(costs[:, torch.arange(25) != 12] > 0.0)  # random texture differs under any shift


@pytest.mark.parametrize("dy, dx", [(0, 1), (-2, 0), (1, -1), (2, 2)])
def test_cost_map_minimum_lies_at_the_pixel_shift(dy: int, dx: int) -> None:
    # target[y, x] = view[y + dy, x + dx] (a whole-image translation): the entry of (dy, dx) is exactly 0
    k = 2
    view = images(2, 32, seed=1)
    target = torch.roll(view, shifts=(-dy, -dx), dims=(2, 3))
    costs = CorrelationEncoder(32, 32, 16, fine_shifts=k).fine_costs(view, target)
    index = (dy + k) * (2 * k + 1) + (dx + k)
    assert torch.all(costs[:, index] < 1e-7)
    assert torch.equal(costs.argmin(dim=1), torch.full((2,), index))
    # the hand-computed entry for the zero shift: mean |grey(view) - grey(target)| over the central pixels
    grey_v, grey_t = view.mean(dim=1), target.mean(dim=1)
    expected = (grey_v[:, k:-k, k:-k] - grey_t[:, k:-k, k:-k]).abs().mean(dim=(1, 2))
    torch.testing.assert_close(costs[:, 12], expected)


def test_fine_shifts_changes_the_fuse_input_and_validates() -> None:
    off = Policy(32, 32, "correlation", 16)
    on = Policy(32, 32, "correlation", 16, fine_shifts=1)
    grown = on.encoder.fuse[0].in_features - off.encoder.fuse[0].in_features
    assert grown == 3 * 9  # three scalings of the 3x3 cost map
    obs = {"view": torch.randint(0, 256, (4, 3, 32, 32), dtype=torch.uint8)}
    obs["target"] = obs["view"].clone()
    dist, values, hidden = on(obs, on.initial_hidden(4), torch.ones(4))
    assert dist.logits.shape == (4, 5) and torch.isfinite(dist.logits).all() and hidden.shape == (4, 16)
    with pytest.raises(ValueError, match=r"fine_shifts=1 needs one of the variants \(.*'phase'\), got 'early_fusion'"):
        Policy(64, 64, "early_fusion", 16, fine_shifts=1)
    with pytest.raises(ValueError, match="fine_shifts=9"):
        CorrelationEncoder(32, 32, 16, fine_shifts=9)


def test_signature_carries_fine_shifts_and_old_checkpoints_still_load() -> None:
    off = Policy(32, 32, "correlation", 16)
    on = Policy(32, 32, "correlation", 16, fine_shifts=2)
    assert "fine_shifts" not in off.model_signature()  # an older reader can still load it
    assert on.model_signature()["fine_shifts"] == 2
    check_signature(off.model_signature(), off.model_signature())
    check_signature({"variant": "correlation", "hidden_size": 16, "height": 32, "width": 32}, off.model_signature())
    with pytest.raises(ValueError, match="fine_shifts is 0 in the checkpoint but 2"):
        check_signature(off.model_signature(), on.model_signature())


def test_agent_rebuilds_the_fine_policy_from_a_checkpoint(tmp_path) -> None:
    policy = Policy(32, 32, "correlation", 16, fine_shifts=2)
    path = tmp_path / "fine.pth"
    torch.save({"signature": policy.model_signature(), "policy": policy.state_dict()}, path)
    agent = PPOAgent.from_checkpoint(path, num_envs=2)
    assert agent.policy.fine_shifts == 2
    obs = {"view": torch.randint(0, 256, (2, 3, 32, 32), dtype=torch.uint8)}
    obs["target"] = obs["view"].clone()
    agent.reset([0, 1], [None, None])
    with torch.no_grad():
        a = policy.act(obs, policy.initial_hidden(2), torch.ones(2), deterministic=True)[0]
        b = agent.policy.act(obs, agent.policy.initial_hidden(2), torch.ones(2), deterministic=True)[0]
    assert torch.equal(a, b)


def test_pyramid_level_sees_shifts_of_twice_the_pixels() -> None:
    # a 4-pixel translation is out of reach of level 0 (k = 2) but exactly 2 pixels on level 1
    big = torch.rand(1, 1, 40, 40, generator=torch.Generator().manual_seed(4))
    view, target = big[..., :32, :32], big[..., 4:36, 0:32]  # target[y, x] = view[y + 4, x]
    costs = pyramid_costs(view, target, shifts=2, levels=2)
    level1 = costs[0, 25:]
    assert int(level1.argmin()) == (2 + 2) * 5 + (0 + 2) and float(level1.min()) < 1e-6
    assert float(costs[0, :25].min()) > 0.05  # no level-0 shift matches


def test_direct_global_costs_find_a_coarse_translation() -> None:
    # thumbnails cut from one larger random grid, so no wrap-around: target[y, x] = view[y + 2, x - 3]
    c, s = DIRECT_COARSE, DIRECT_COARSE_SHIFTS
    grid = torch.rand(2, 1, c + 6, c + 6, generator=torch.Generator().manual_seed(5))
    view, target = grid[..., 0:c, 3:3 + c], grid[..., 2:2 + c, 0:c]
    enc = DirectEncoder(64, 64, 16)
    costs = enc.global_costs(view, target)
    n = 2 * s + 1
    assert costs.shape == (2, n * n)
    best = (2 + s) * n + (-3 + s)
    assert torch.equal(costs.argmin(dim=1), torch.full((2,), best)) and float(costs[:, best].max()) < 1e-6
    # the zero shift: the plain mean absolute difference of the two thumbnails
    torch.testing.assert_close(costs[:, s * n + s], (view - target).abs().mean(dim=(1, 2, 3)))


def test_direct_policy_runs_and_has_no_image_convolutions_to_train() -> None:
    policy = Policy(64, 64, "direct", 32, fine_shifts=2, fine_scales=4)
    assert policy.model_signature() == {
        "variant": "direct", "hidden_size": 32, "height": 64, "width": 64, "fine_shifts": 2, "fine_scales": 4,
    }
    convs = [m for m in policy.modules() if isinstance(m, torch.nn.Conv2d)]
    assert all(m.in_channels <= 16 for m in convs)  # only the small head on the 13 x 13 cost volume
    obs = {"view": torch.randint(0, 256, (3, 3, 64, 64), dtype=torch.uint8)}
    obs["target"] = obs["view"].clone()
    dist, values, hidden = policy(obs, policy.initial_hidden(3), torch.ones(3))
    assert dist.logits.shape == (3, 5) and torch.isfinite(dist.logits).all() and values.shape == (3,)
    with pytest.raises(ValueError, match="fine_scales=6"):
        DirectEncoder(64, 64, 16, fine_shifts=2, fine_scales=6)


def test_direct_weights_initialise_a_robust_policy_but_never_stand_in_for_it() -> None:
    direct = Policy(32, 32, "direct", 16, fine_shifts=1, fine_scales=2)
    robust = Policy(32, 32, "robust", 16, fine_shifts=1, fine_scales=2)
    check_signature(direct.model_signature(), robust.model_signature(), transfer=True)  # init_from
    robust.load_state_dict(direct.state_dict())  # same parameter names and shapes
    with pytest.raises(ValueError, match="variant is 'direct' in the checkpoint but 'robust'"):
        check_signature(direct.model_signature(), robust.model_signature())  # eval / resume
    corr = Policy(32, 32, "correlation", 16, fine_shifts=1, fine_scales=2)
    with pytest.raises(ValueError, match="variant is 'direct' in the checkpoint but 'correlation'"):
        check_signature(direct.model_signature(), corr.model_signature(), transfer=True)
