"""The learned stop check (findview_baselines/agents/stop_offsets.py, findview_baselines/training/stop_offsets.py,
tools/train_stop_offsets.py): the correlation volume peaks at a hand-made shift, a net trained on a few hundred
rendered pairs tells a view on its target from one a degree off and which way, the refinement follows a net's
answer within its move budget, a net trained with far pairs refuses views elsewhere on a panorama it never saw and
the agent searches on from a refused stop, and files and settings are checked."""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import cv2
import pytest
import torch

from _tools import load_tool
from findview.dataset import generate_panorama
from findview_baselines.agents.base import DOWN, LEFT, RIGHT, STOP, UP
from findview_baselines.agents.stop_offsets import (
    FEATURES,
    NEAR_DEGREES,
    SHIFTS,
    StopOffsetNet,
    StopOffsetsError,
    load_stop_offsets,
    ncc_volume,
    pair_features,
    save_stop_offsets,
)
from findview_baselines.agents.stop_refine import StopRefiner
from findview_baselines.training.stop_offsets import accuracy, fit, sample_pairs

ROOT = Path(__file__).resolve().parents[1]
SIZE, FOV = 160, 90.0


def _smooth_noise(seed: int, h: int, w: int) -> torch.Tensor:
    g = torch.Generator().manual_seed(seed)
    x = torch.rand(1, 1, h // 4, w // 4, generator=g)
    return torch.nn.functional.interpolate(x, size=(h, w), mode="bicubic", align_corners=False)[0, 0]


def test_ncc_volume_peaks_at_the_shift_between_the_images() -> None:
    """target(y, x) = view(y - 3, x + 2): the view's square moved 3 pixels up and 2 right matches the target's
    square exactly, so the volume is 1 at [SHIFTS - 3, SHIFTS + 2] and below 1 elsewhere."""
    view = _smooth_noise(0, 200, 200)
    target = torch.roll(view, shifts=(3, -2), dims=(0, 1))
    vol = ncc_volume(view[None], target[None])[0]
    assert vol.shape == (2 * SHIFTS + 1, 2 * SHIFTS + 1)
    assert vol[SHIFTS - 3, SHIFTS + 2].item() == pytest.approx(1.0, abs=1e-4)
    flat = vol.flatten().clone()
    flat[(SHIFTS - 3) * (2 * SHIFTS + 1) + SHIFTS + 2] = -1
    assert flat.max().item() < 0.99
    with pytest.raises(ValueError, match="smaller than"):
        ncc_volume(view[None, :100, :100], target[None, :100, :100])


def test_pair_features_of_identical_images() -> None:
    """Identical view and target: each of the three volumes is 1 at zero shift, the log energy ratios are 0, the
    measured residual is about 0 with a peak near 1."""
    img = (torch.stack([_smooth_noise(s, SIZE, SIZE) for s in (1, 2, 3)]) * 255).to(torch.uint8)[None]
    f = pair_features(img, img, FOV)[0]
    assert f.shape == (FEATURES,) and torch.isfinite(f).all()
    n = (2 * SHIFTS + 1) ** 2
    centre = SHIFTS * (2 * SHIFTS + 1) + SHIFTS
    for band in range(3):
        assert f[band * n + centre].item() == pytest.approx(1.0, abs=1e-4)
    assert f[3 * n + 8:3 * n + 16].abs().max().item() < 1e-4
    assert f[-3:-1].abs().max().item() < 0.05 and f[-1].item() > 0.9


@pytest.fixture(scope="module")
def panoramas() -> list[torch.Tensor]:
    return [torch.from_numpy(generate_panorama(seed, kind, 1024)).permute(2, 0, 1).contiguous()
            for seed, kind in ((5, "room"), (6, "village"), (7, "room"))]


@pytest.fixture(scope="module")
def trained(panoramas) -> tuple:
    """A net trained on 600 clean pairs of two panoramas, and 300 val pairs of the third."""
    torch.manual_seed(0)
    train = sample_pairs(panoramas[:2], 600, FOV, SIZE, seed=1, clean_fraction=1.0)
    val = sample_pairs(panoramas[2:], 300, FOV, SIZE, seed=2, clean_fraction=1.0)
    return fit(train, FOV, SIZE, epochs=15, seed=0), val


def test_sampled_pairs_have_the_documented_offsets(panoramas) -> None:
    pairs = sample_pairs(panoramas[:1], 200, FOV, SIZE, seed=3, corruptions=("fog", "glass_blur"))
    assert pairs.features.shape == (200, FEATURES)
    assert set(pairs.dpitch.tolist()) <= {-3, -2, -1, 0, 1, 2, 3} and set(pairs.dyaw.tolist()) <= {-3, -2, -1, 0, 1, 2, 3}
    assert 0.25 < (pairs.dpitch == 0).float().mean().item() < 0.55
    assert set(pairs.corruption.tolist()) <= {-1, 14, 2}  # clean, fog, glass_blur
    again = sample_pairs(panoramas[:1], 200, FOV, SIZE, seed=3, corruptions=("fog", "glass_blur"))
    assert torch.equal(again.features, pairs.features)
    with pytest.raises(ValueError, match="expected names"):
        sample_pairs(panoramas[:1], 10, FOV, SIZE, seed=3, corruptions=("haze",))


def test_a_net_trained_on_rendered_pairs_tells_on_target_from_one_degree_off(trained) -> None:
    """On a panorama it never saw: at least 90% of views on their target are left alone and at least 80% of views
    one degree off are first moved towards it (clean targets; a content matcher reads these shifts exactly, so
    the margins hold on any seed and thread count)."""
    net, val = trained
    report = accuracy(net, val, min_stay=0.3)["clean"]
    assert report["stay"] >= 0.9, report
    assert report["one_off"] >= 0.8, report


def _fixed_net(pitch_class: int, yaw_class: int, near: bool | None = None, size: int = SIZE) -> StopOffsetNet:
    """A net whose answer is always (pitch_class - 2, yaw_class - 2) degrees, surely; with ``near`` given it has
    the near output, surely ``near``."""
    net = StopOffsetNet(FOV, size, hidden=8, near=near is not None)
    last = net.mlp[-1]
    with torch.no_grad():
        last.weight.zero_()
        last.bias.fill_(-20.0)
        last.bias[pitch_class] = 20.0
        last.bias[5 + yaw_class] = 20.0
        if near is not None:
            last.bias[10] = 20.0 if near else -20.0
    return net.eval()


@pytest.mark.parametrize(
    "pitch_class, yaw_class, first",
    [(2, 3, LEFT), (2, 1, RIGHT), (3, 2, DOWN), (1, 2, UP), (1, 4, LEFT), (2, 2, STOP)],
)
def test_refiner_follows_the_net(pitch_class: int, yaw_class: int, first: int) -> None:
    """The net's offset is the view's from the target: a view 1 degree right of it (yaw class 3) turns LEFT, one
    above it (pitch class 3) moves DOWN; the larger offset goes first; "no offset" stops. After ``max_moves``
    moves the slot stops whatever the net says."""
    img = (torch.rand(2, 3, SIZE, SIZE, generator=torch.Generator().manual_seed(0)) * 255).to(torch.uint8)
    refiner = StopRefiner(2, FOV, max_moves=2, offsets=_fixed_net(pitch_class, yaw_class))
    ids = torch.tensor([0, 1])
    actions = [refiner.decide(ids, img, img).tolist() for _ in range(3)]
    assert actions[0] == [first, first]
    expected_last = STOP
    assert actions[2] == [expected_last, expected_last]
    assert refiner.refining.tolist() == [False, False]


def test_far_pairs_leave_the_near_pairs_as_they_were(panoramas) -> None:
    """``far_fraction`` moves about that share of the views elsewhere (offsets beyond ``NEAR_DEGREES``, yaw wrapped
    to -180..180) and leaves every other pair as ``far_fraction=0`` draws it, features included."""
    plain = sample_pairs(panoramas[:1], 200, FOV, SIZE, seed=3, corruptions=("fog", "glass_blur"))
    mixed = sample_pairs(panoramas[:1], 200, FOV, SIZE, seed=3, corruptions=("fog", "glass_blur"), far_fraction=0.3)
    moved = (mixed.dpitch != plain.dpitch) | (mixed.dyaw != plain.dyaw)
    assert 40 <= int(moved.sum()) <= 80
    assert not mixed.near[moved].any() and plain.near.all()
    assert int(mixed.dyaw.abs().max()) <= 180 and int(mixed.dyaw.abs().max()) > 30  # some anywhere on the panorama
    assert torch.equal(mixed.corruption, plain.corruption) and torch.equal(mixed.severity, plain.severity)
    torch.testing.assert_close(mixed.features[~moved], plain.features[~moved], rtol=0, atol=1e-5)
    with pytest.raises(ValueError, match="far_fraction"):
        sample_pairs(panoramas[:1], 10, FOV, SIZE, seed=3, far_fraction=1.0)


def test_lookalike_far_views_are_the_repeats_of_a_repeating_panorama(panoramas) -> None:
    """A panorama that repeats every 90 degrees of yaw: with ``lookalike=128`` most views put anywhere are at a
    repeat of their target (pitch within 10 degrees, yaw within 10 of 90 or 180 degrees away; about 3% of uniform
    poses are; 71-91% over seeds 3-8), with ``lookalike=1`` few are (0-11%); the near pairs and the far pairs near
    their target are as without it."""
    tile = panoramas[0][:, :, :256]
    repeating = [tile.repeat(1, 1, 4).contiguous()]

    def at_repeat(pairs) -> torch.Tensor:
        off = pairs.dyaw.abs()
        return (pairs.dpitch.abs() <= 10) & (((off - 90).abs() <= 10) | ((off - 180).abs() <= 10))

    kw = dict(corruptions=("fog",), clean_fraction=1.0, far_fraction=0.9)
    plain = sample_pairs(repeating, 120, FOV, SIZE, seed=3, **kw)
    alike = sample_pairs(repeating, 120, FOV, SIZE, seed=3, lookalike=128, **kw)
    moved = (alike.dpitch != plain.dpitch) | (alike.dyaw != plain.dyaw)
    assert 30 <= int(moved.sum()) <= 80  # the far views put anywhere, about half of the far ones
    assert at_repeat(alike)[moved].float().mean().item() >= 0.5
    assert at_repeat(plain)[moved].float().mean().item() <= 0.25
    assert not alike.near[moved].any()
    torch.testing.assert_close(alike.features[~moved], plain.features[~moved], rtol=0, atol=1e-5)
    with pytest.raises(ValueError, match="lookalike"):
        sample_pairs(repeating, 10, FOV, SIZE, seed=3, lookalike=0)


def test_a_net_trained_with_far_pairs_refuses_views_elsewhere(panoramas) -> None:
    """Trained on 600 pairs of two panoramas, a third of them far (clean targets): on the third panorama at least
    90% of views within 2 degrees of their target are kept and at least 75% of far views refused (the misses are
    mostly views 4-6 degrees off), and views on their target are still left alone. Measured: keep 1.00, refuse
    0.82-0.91 over three seeds at 1 and 2 threads."""
    train = sample_pairs(panoramas[:2], 600, FOV, SIZE, seed=4, clean_fraction=1.0, far_fraction=0.33)
    val = sample_pairs(panoramas[2:], 300, FOV, SIZE, seed=5, clean_fraction=1.0, far_fraction=0.33)
    net = fit(train, FOV, SIZE, epochs=15, seed=0)
    assert net.near
    report = accuracy(net, val, min_stay=0.3, min_near=0.5)["clean"]
    assert report["keep"] >= 0.9 and report["refuse"] >= 0.75, report
    assert report["stay"] >= 0.9, report


def test_refiner_refuses_the_stops_the_net_finds_far() -> None:
    img = (torch.rand(3, 3, SIZE, SIZE, generator=torch.Generator().manual_seed(0)) * 255).to(torch.uint8)
    far = StopRefiner(3, FOV, offsets=_fixed_net(2, 2, near=False), min_near=0.5)
    near = StopRefiner(3, FOV, offsets=_fixed_net(2, 2, near=True), min_near=0.5)
    assert far.refuse(img, img).tolist() == [True] * 3 and near.refuse(img, img).tolist() == [False] * 3
    with pytest.raises(ValueError, match="near output"):
        StopRefiner(3, FOV, offsets=_fixed_net(2, 2), min_near=0.5)
    with pytest.raises(ValueError, match="near output"):
        StopRefiner(3, FOV, min_near=0.5)
    with pytest.raises(ValueError, match="min_near"):
        StopRefiner(3, FOV, offsets=_fixed_net(2, 2, near=True), min_near=1.0)
    with pytest.raises(StopOffsetsError, match="no near output"):
        _fixed_net(2, 2).near_prob(img, img)


def test_a_second_net_answers_the_near_check_and_the_first_keeps_the_moves() -> None:
    """With ``near_offsets`` the near check is the second net's (far here, near there) whatever the first says, and
    the moves stay the first net's (1 degree right of the target: LEFT). A first net without the near output is
    enough then; a second net without it, or one without ``min_near``, is refused."""
    img = (torch.rand(2, 3, SIZE, SIZE, generator=torch.Generator().manual_seed(0)) * 255).to(torch.uint8)
    mover = _fixed_net(2, 3)  # no near output
    far = StopRefiner(2, FOV, offsets=mover, min_near=0.5, near_offsets=_fixed_net(2, 2, near=False))
    assert far.refuse(img, img).tolist() == [True, True]
    assert far.decide(torch.tensor([0, 1]), img, img).tolist() == [LEFT, LEFT]
    near = StopRefiner(2, FOV, offsets=_fixed_net(2, 3, near=False), min_near=0.5,
                       near_offsets=_fixed_net(2, 2, near=True))
    assert near.refuse(img, img).tolist() == [False, False]
    assert near.near_prob(img, img).min().item() > 0.99
    with pytest.raises(ValueError, match="near_offsets has no near output"):
        StopRefiner(2, FOV, offsets=mover, min_near=0.5, near_offsets=_fixed_net(2, 2))
    with pytest.raises(ValueError, match="needs offsets and min_near"):
        StopRefiner(2, FOV, offsets=mover, near_offsets=_fixed_net(2, 2, near=True))
    with pytest.raises(ValueError, match="needs offsets and min_near"):
        StopRefiner(2, FOV, min_near=0.5, near_offsets=_fixed_net(2, 2, near=True))


def _fixed_policy(probs: list[float]):
    """A 32x32 ``direct`` policy whose action probabilities (UP, DOWN, LEFT, RIGHT, STOP) are ``probs`` whatever it
    sees (zero actor weights, log-probability biases)."""
    from findview_baselines.rl.policy import Policy

    policy = Policy(32, 32, "direct", hidden_size=8)
    with torch.no_grad():
        policy.actor.weight.zero_()
        policy.actor.bias.copy_(torch.log(torch.tensor(probs)))
    return policy


def _same_view_and_target() -> dict[str, torch.Tensor]:
    """One 160x160 uint8 noise image as both view and target."""
    pixels = (torch.rand(1, 3, 160, 160, generator=torch.Generator().manual_seed(1)) * 255).to(torch.uint8)
    return {"view": pixels, "target": pixels.clone()}

def test_agent_searches_on_from_a_stop_the_net_refuses() -> None:
    """A policy fixed at P = (0.1, 0.05, 0.15, 0.2, 0.5) for (UP, DOWN, LEFT, RIGHT, STOP) stops at once; with a
    net that finds every view far and ``min_near`` the stop is refused for its most likely move, RIGHT, and with
    ``stop_by`` the agent never walks back to a refused view (none counts as stop-like), so it never stops; with
    a net that finds the view near, the stop stands. A policy that never answers STOP walks back and stops by T
    only where the net finds the view near."""
    from findview.episode import Episode
    from findview_baselines.agents.ppo_agent import PPOAgent

    policy = _fixed_policy([0.1, 0.05, 0.15, 0.2, 0.5])
    obs = _same_view_and_target()

    def actions(steps: int, near: bool, **kw) -> list[int]:
        refiner = StopRefiner(1, FOV, offsets=_fixed_net(2, 2, near=near, size=160), min_near=0.5)
        agent = PPOAgent(policy, 1, refiner=refiner, fov=FOV, **kw)
        agent.reset([0], [Episode("e", "x.jpg", 0, 0, 0, 10, difficulty="easy", seed=1)])
        return [int(agent.act(obs)[0]) for _ in range(steps)]

    assert actions(1, near=True) == [STOP]
    assert actions(1, near=False) == [RIGHT]
    walked = actions(30, near=False, revisit_penalty=16.0, stop_by=30)
    assert STOP not in walked
    # a policy that never says STOP (0.3 < RIGHT's 0.4) walks back to its most stop-like view by T = 30 only if
    # the net finds a view near
    with torch.no_grad():
        policy.actor.bias.copy_(torch.log(torch.tensor([0.1, 0.1, 0.1, 0.4, 0.3])))
    assert STOP in actions(30, near=True, revisit_penalty=16.0, stop_by=30)
    assert STOP not in actions(30, near=False, revisit_penalty=16.0, stop_by=30)


def test_agent_stops_on_a_half_sure_view_the_net_finds_near() -> None:
    """``stop_near_prob``: a policy fixed at P = (0.1, 0.1, 0.1, 0.4, 0.3) for (UP, DOWN, LEFT, RIGHT, STOP) moves
    RIGHT. With ``stop_near_prob`` at or below its 0.3 and a net that finds the view near it stops at once, also
    under a ``stop_min_prob`` of 0.8 that refuses its STOP; a net that finds the view far, or a threshold above
    0.3, leaves it moving. Over three slots the net judges each slot's own view. ``stop_near_min_near`` raises the
    bar of these stops only: a view the net finds near at 0.71 is a half-sure STOP at the refiner's 0.5 but not at
    0.75, where the policy's own STOP on it still stands. The option needs the net's near check and a threshold
    below ``stop_prob``."""
    from findview.episode import Episode
    from findview_baselines.agents.ppo_agent import PPOAgent
    from findview_baselines.config import PPOAgentConfig

    policy = _fixed_policy([0.1, 0.1, 0.1, 0.4, 0.3])
    obs = _same_view_and_target()

    def first_action(near: bool, **kw) -> int:
        refiner = StopRefiner(1, FOV, offsets=_fixed_net(2, 2, near=near, size=160), min_near=0.5)
        agent = PPOAgent(policy, 1, refiner=refiner, fov=FOV, **kw)
        agent.reset([0], [Episode("e", "x.jpg", 0, 0, 0, 10, difficulty="easy", seed=1)])
        return int(agent.act(obs)[0])

    assert first_action(near=True) == RIGHT
    assert first_action(near=True, stop_near_prob=0.29) == STOP
    assert first_action(near=True, stop_near_prob=0.29, stop_min_prob=0.8, revisit_penalty=16.0) == STOP
    assert first_action(near=True, stop_near_prob=0.31) == RIGHT
    assert first_action(near=False, stop_near_prob=0.29) == RIGHT
    # three slots, the net's near probability per view its shade / 255 (200: 0.78, 50: 0.20, 180: 0.71): the
    # bright ones stop, and the net is asked once per slot (the stop check after it does not ask again about a
    # view already found near)
    asked: list[int] = []

    def shade_net(slots: int) -> StopRefiner:
        refiner = StopRefiner(slots, FOV, offsets=_fixed_net(2, 2, near=True, size=160), min_near=0.5)

        def near_prob(view: torch.Tensor, target: torch.Tensor) -> torch.Tensor:
            asked.extend(view[:, 0, 0, 0].tolist())
            return view[:, 0, 0, 0].float() / 255

        refiner.near_prob = near_prob
        return refiner

    def three_slots(policy: torch.nn.Module, **kw) -> list[int]:
        agent = PPOAgent(policy, 3, refiner=shade_net(3), fov=FOV, **kw)
        agent.reset([0, 1, 2], [Episode(f"e{i}", "x.jpg", 0, 0, 0, 10, difficulty="easy", seed=i) for i in range(3)])
        shades = torch.tensor([200, 50, 180], dtype=torch.uint8)[:, None, None, None].expand(3, 3, 160, 160)
        return agent.act({"view": shades.clone(), "target": shades.clone()}).tolist()

    assert three_slots(policy, stop_near_prob=0.29) == [STOP, RIGHT, STOP]
    assert sorted(asked) == [50, 180, 200]
    assert three_slots(policy, stop_near_prob=0.29, stop_near_min_near=0.75) == [STOP, RIGHT, RIGHT]
    sure_policy = _fixed_policy([0.1, 0.1, 0.1, 0.2, 0.5])  # its own STOPs: the refiner's 0.5 bar, not 0.75
    assert three_slots(sure_policy, stop_near_prob=0.29, stop_near_min_near=0.75) == [STOP, RIGHT, STOP]
    with pytest.raises(ValueError, match="stop_near_min_near must be in \\[min_near, 1\\)"):
        PPOAgent(policy, 1, refiner=shade_net(1), fov=FOV, stop_near_prob=0.3, stop_near_min_near=0.4)
    with pytest.raises(ValueError, match="stop_near_min_near=0.9 .*off"):
        PPOAgent(policy, 1, refiner=shade_net(1), fov=FOV, stop_near_min_near=0.9)
    with pytest.raises(ValueError, match="stop_near_prob=0.3.*min_near"):
        PPOAgent(policy, 1, stop_near_prob=0.3)
    near_refiner = StopRefiner(1, FOV, offsets=_fixed_net(2, 2, near=True, size=160), min_near=0.5)
    with pytest.raises(ValueError, match="stop_near_prob must be in"):
        PPOAgent(policy, 1, refiner=near_refiner, fov=FOV, stop_near_prob=1.5)
    with pytest.raises(ValueError, match="stop_near_prob=0.3.*below stop_prob|expected stop_near_prob < stop_prob"):
        PPOAgent(policy, 1, refiner=near_refiner, fov=FOV, stop_near_prob=0.3, stop_prob=0.3)
    with pytest.raises(ValueError, match="agent.stop_near_prob.*agent.refine_min_near"):
        PPOAgentConfig(stop_near_prob=0.3)
    with pytest.raises(ValueError, match="agent.stop_near_prob"):
        PPOAgentConfig(refine_stop=True, refine_model="x.pth", refine_min_near=0.5, stop_near_prob=0.0)
    with pytest.raises(ValueError, match="agent.stop_near_prob=0.4: expected below agent.stop_prob=0.4"):
        PPOAgentConfig(refine_stop=True, refine_model="x.pth", refine_min_near=0.5, stop_near_prob=0.4, stop_prob=0.4)
    with pytest.raises(ValueError, match="agent.stop_near_min_near=0.4: expected .*agent.refine_min_near=0.5"):
        PPOAgentConfig(refine_stop=True, refine_model="x.pth", refine_min_near=0.5, stop_near_prob=0.3, stop_near_min_near=0.4)
    with pytest.raises(ValueError, match="agent.stop_near_min_near"):
        PPOAgentConfig(refine_stop=True, refine_model="x.pth", refine_min_near=0.5, stop_near_min_near=0.9)
    PPOAgentConfig(refine_stop=True, refine_model="x.pth", refine_min_near=0.5, stop_near_prob=0.3, stop_near_min_near=0.99)

    # revisit_near_until: the near probabilities the stop check measures end a slot's near visits at 0.75 and above
    # (slot 0's 0.78; not slot 2's 0.71, nor slot 1's 0.20, which is never measured: STOP below 0.3 everywhere)
    from findview_baselines.rl.search_memory import NearVisits

    def found(until: float, **kw) -> list[bool]:
        agent = PPOAgent(policy, 3, refiner=shade_net(3), fov=FOV, revisit_penalty=16.0,
                         revisit_near=NearVisits(4, 2.0, until=until), **kw)
        agent.reset([0, 1, 2], [Episode(f"e{i}", "x.jpg", 0, 0, 0, 10, difficulty="easy", seed=i) for i in range(3)])
        shades = torch.tensor([200, 50, 180], dtype=torch.uint8)[:, None, None, None].expand(3, 3, 160, 160)
        agent.act({"view": shades.clone(), "target": shades.clone()})
        return agent.revisits.near_found.tolist()

    assert found(0.75, stop_near_prob=0.29, stop_near_min_near=0.99) == [True, False, False]
    assert found(0.6, stop_near_prob=0.29, stop_near_min_near=0.99) == [True, False, True]
    assert found(0.6) == [False, False, False]  # no stop-like pose, nothing measured
    with pytest.raises(ValueError, match="revisit_near.until=0.6 .*min_near"):
        PPOAgent(policy, 1, fov=FOV, revisit_penalty=16.0, revisit_near=NearVisits(4, 2.0, until=0.6))
    with pytest.raises(ValueError, match="agent.revisit_near_until=0.6: expected .*agent.refine_min_near"):
        PPOAgentConfig(revisit_near_until=0.6)
    PPOAgentConfig(refine_stop=True, refine_model="x.pth", refine_min_near=0.5, revisit_near_until=0.6)


def test_files_round_trip_and_bad_files_are_named(trained, tmp_path) -> None:
    net, val = trained
    path = save_stop_offsets(tmp_path / "net.pth", net, {"note": "test"})
    state = torch.load(path, weights_only=True)
    assert state["meta"] == {"note": "test"} and state["fov"] == FOV and state["size"] == SIZE
    again = load_stop_offsets(path, fov=FOV, size=SIZE)
    assert torch.equal(again(val.features[:5])[0], net(val.features[:5])[0])
    with pytest.raises(StopOffsetsError, match="FoV 90.*FoV 60"):
        load_stop_offsets(path, fov=60.0)
    with pytest.raises(StopOffsetsError, match="160x160 views.*256"):
        load_stop_offsets(path, size=256)
    junk = tmp_path / "junk.pth"
    torch.save({"format": "findview-ppo"}, junk)
    with pytest.raises(StopOffsetsError, match="junk.pth: not a stop-offset net"):
        load_stop_offsets(junk)
    with pytest.raises(StopOffsetsError, match="missing.pth: stop-offset net not found"):
        load_stop_offsets(tmp_path / "missing.pth")
    with pytest.raises(StopOffsetsError, match="160x160 views got"):
        again.offsets(torch.zeros(1, 3, 64, 64, dtype=torch.uint8), torch.zeros(1, 3, 64, 64, dtype=torch.uint8))
    # a version-1 file (before the near output) still loads, without it; an unknown version is named
    state["version"] = 1
    del state["near"]
    torch.save(state, tmp_path / "v1.pth")
    v1 = load_stop_offsets(tmp_path / "v1.pth", fov=FOV, size=SIZE)
    assert not v1.near and torch.equal(v1(val.features[:5])[1], net(val.features[:5])[1])
    state["version"] = 7
    torch.save(state, tmp_path / "v7.pth")
    with pytest.raises(StopOffsetsError, match="v7.pth: stop-offset net version 7"):
        load_stop_offsets(tmp_path / "v7.pth")
    near = save_stop_offsets(tmp_path / "near.pth", _fixed_net(1, 3, near=True), {})
    assert load_stop_offsets(near).near


def test_config_checks_the_refine_model_settings() -> None:
    from findview_baselines.config import PPOAgentConfig

    with pytest.raises(ValueError, match="agent.refine_model.*refine_stop=true"):
        PPOAgentConfig(refine_model="x.pth")
    with pytest.raises(ValueError, match="agent.refine_min_stay"):
        PPOAgentConfig(refine_stop=True, refine_min_stay=0.0)
    with pytest.raises(ValueError, match="min_stay"):
        StopRefiner(1, FOV, min_stay=1.5)
    with pytest.raises(ValueError, match="agent.refine_min_near.*agent.refine_model"):
        PPOAgentConfig(refine_stop=True, refine_min_near=0.5)
    with pytest.raises(ValueError, match="agent.refine_min_near"):
        PPOAgentConfig(refine_stop=True, refine_model="x.pth", refine_min_near=0.0)
    with pytest.raises(ValueError, match="agent.refine_near_model.*agent.refine_min_near"):
        PPOAgentConfig(refine_stop=True, refine_model="x.pth", refine_near_model="y.pth")


def test_agent_refiner_loads_the_net_for_its_views(trained, tmp_path) -> None:
    from findview_baselines.agents.ppo_agent import _refiner
    from findview_baselines.config import PPOAgentConfig

    net, _ = trained
    path = save_stop_offsets(tmp_path / "net.pth", net, {})
    cfg = PPOAgentConfig(refine_stop=True, refine_model=str(path), refine_min_stay=0.4, fov=FOV)
    refiner = _refiner(cfg, 3, SIZE)
    assert refiner.offsets is not None and refiner.min_stay == 0.4
    with pytest.raises(StopOffsetsError, match="made for 160x160 views"):
        _refiner(cfg, 3, 256)
    assert _refiner(PPOAgentConfig(refine_stop=True), 3, SIZE).offsets is None
    with pytest.raises(ValueError, match="near output"):  # this net was trained without far pairs
        _refiner(PPOAgentConfig(refine_stop=True, refine_model=str(path), refine_min_near=0.5, fov=FOV), 3, SIZE)
    near = save_stop_offsets(tmp_path / "near.pth", _fixed_net(2, 2, near=True), {})
    refiner = _refiner(PPOAgentConfig(refine_stop=True, refine_model=str(near), refine_min_near=0.6, fov=FOV), 3, SIZE)
    assert refiner.min_near == 0.6 and refiner.offsets.near
    # a refinement net without the near output beside a second net that has it: each keeps its job
    both = _refiner(PPOAgentConfig(refine_stop=True, refine_model=str(path), refine_near_model=str(near),
                                   refine_min_near=0.6, fov=FOV), 3, SIZE)
    assert not both.offsets.near and both.near_offsets.near and both.min_near == 0.6
    wrong = save_stop_offsets(tmp_path / "wrong.pth", _fixed_net(2, 2, near=True, size=128), {})
    with pytest.raises(StopOffsetsError, match="made for 128x128 views"):
        _refiner(PPOAgentConfig(refine_stop=True, refine_model=str(path), refine_near_model=str(wrong),
                                refine_min_near=0.6, fov=FOV), 3, SIZE)


def test_tool_refuses_bad_input(tmp_path) -> None:
    tool = [sys.executable, str(ROOT / "tools" / "train_stop_offsets.py")]
    splits = tmp_path / "splits.json"
    splits.write_text(json.dumps({"root": str(tmp_path), "splits": {"train": [], "val": []}}))
    out = tmp_path / "o.pth"
    run = subprocess.run(tool + ["--splits", str(splits), "--root", str(tmp_path), "--out", str(out)],
                         capture_output=True, text=True)
    assert run.returncode == 2 and "'train' split is empty" in run.stderr and not out.exists()
    run = subprocess.run(tool + ["--splits", str(splits), "--root", str(tmp_path), "--out", str(out),
                                 "--blur-corruptions", "haze"], capture_output=True, text=True)
    assert run.returncode == 2 and "haze" in run.stderr
    run = subprocess.run(tool + ["--splits", str(splits), "--root", str(tmp_path), "--out", str(out),
                                 "--far-fraction", "1.5"], capture_output=True, text=True)
    assert run.returncode == 2 and "--far-fraction in [0, 1) (got 1.5)" in run.stderr
    out.write_bytes(b"x")
    run = subprocess.run(tool + ["--splits", str(splits), "--root", str(tmp_path), "--out", str(out)],
                         capture_output=True, text=True)
    assert run.returncode == 2 and "--overwrite" in run.stderr and out.read_bytes() == b"x"


def test_tool_pools_several_splits_files(panoramas, tmp_path, capsys) -> None:
    """Two splits files (say indoor and outdoor) pool their panoramas: 2 + 1 train and 1 + 1 val; a bad second
    file is named. In process (the tool's ``main``), to spare the suite two interpreter starts."""
    tool = load_tool("train_stop_offsets")
    root, first = _panorama_folder(panoramas, tmp_path)  # train p0, p1; val p2
    second = tmp_path / "other" / "splits.json"
    second.parent.mkdir()
    second.write_text(json.dumps({"root": str(root), "splits": {"train": [{"image": "p2.png", "label": "x"}],
                                                                 "val": [{"image": "p0.png", "label": "x"}]}}))
    out = tmp_path / "net.pth"
    args = ["--root", str(root), "--out", str(out)]
    empty = tmp_path / "empty" / "splits.json"
    empty.parent.mkdir()
    empty.write_text(json.dumps({"root": str(root), "splits": {"train": [], "val": []}}))
    threads = torch.get_num_threads()
    try:  # the tool sets torch's threads to its --threads, even on the way to an error
        assert tool.main(args + ["--splits", str(first), str(second), "--size", str(SIZE), "--pairs", "30",
                                 "--blur-pairs", "0", "--val-pairs", "20", "--epochs", "1"]) == 0
        assert "3 train and 2 val panoramas" in capsys.readouterr().out
        assert torch.load(out, weights_only=True)["meta"]["splits"] == f"{first} {second}"
        assert tool.main(args + ["--splits", str(first), str(empty), "--overwrite"]) == 2
        assert f"{empty}: the 'train' split is empty" in capsys.readouterr().err
    finally:  # later tests' runs depend on the process's thread count (a training's results among them)
        torch.set_num_threads(threads)


def _panorama_folder(panoramas, tmp_path) -> tuple[Path, Path]:
    """The panoramas as PNGs under ``tmp_path/panos`` and a splits.json naming the first two train, the third val."""
    root = tmp_path / "panos"
    root.mkdir()
    entries = []
    for i, pano in enumerate(panoramas):
        cv2.imwrite(str(root / f"p{i}.png"), cv2.cvtColor(pano.permute(1, 2, 0).numpy(), cv2.COLOR_RGB2BGR))
        entries.append({"image": f"p{i}.png", "label": "x"})
    splits = tmp_path / "splits.json"
    splits.write_text(json.dumps({"root": str(root), "splits": {"train": entries[:2], "val": entries[2:]}}))
    return root, splits


def test_tool_trains_a_file_the_agent_loads(panoramas, tmp_path) -> None:
    """End to end on two tiny panorama folders: the tool writes a file with its settings and val report."""
    root, splits = _panorama_folder(panoramas, tmp_path)
    out = tmp_path / "net.pth"
    run = subprocess.run(
        [sys.executable, str(ROOT / "tools" / "train_stop_offsets.py"), "--splits", str(splits), "--root", str(root),
         "--out", str(out), "--size", str(SIZE), "--pairs", "60", "--blur-pairs", "20", "--val-pairs", "40",
         "--epochs", "1"], capture_output=True, text=True)
    assert run.returncode == 0, run.stderr[-2000:]
    state = torch.load(out, weights_only=True)
    assert state["meta"]["pairs"] == 60 and "clean" in state["meta"]["val"] and state["meta"]["far_fraction"] == 0.25
    loaded = load_stop_offsets(out, fov=FOV, size=SIZE)
    assert loaded.size == SIZE and loaded.near  # the default far pairs give it the near output
    assert {"keep", "refuse"} <= set(state["meta"]["val"]["clean"])


def _report_rows(stdout: str, model: Path, bar: float) -> dict[str, list[float]]:
    """The rows of ``tools/report_stop_offsets.py``'s block for ``model`` at ``bar``: name -> [n, columns...]."""
    lines = stdout.splitlines()
    start = lines.index(f"{model}, min_near {bar:g}") + 2
    rows = {}
    for line in lines[start:]:
        if not line.strip():
            break
        name, *values = line.split()
        rows[name] = [float(v) for v in values]
    return rows


def test_report_tool_scores_each_net_on_the_same_pairs(panoramas, tmp_path) -> None:
    """Two nets of fixed answers (on target, surely near / surely far) on 60 val pairs, a quarter far: the near
    one keeps every view within 2 degrees and refuses no far view, the far one the opposite, at both bars; both
    leave every view on its target alone; every row counts its pairs and ``all`` counts them all."""
    root, splits = _panorama_folder(panoramas, tmp_path)
    near = save_stop_offsets(tmp_path / "near.pth", _fixed_net(2, 2, near=True), {})
    far = save_stop_offsets(tmp_path / "far.pth", _fixed_net(2, 2, near=False), {})
    tool = [sys.executable, str(ROOT / "tools" / "report_stop_offsets.py"), "--splits", str(splits), "--root",
            str(root)]
    run = subprocess.run(tool + ["--models", str(near), str(far), "--pairs", "60", "--min-near", "0.5", "0.99"],
                         capture_output=True, text=True)
    assert run.returncode == 0, run.stderr[-2000:]
    for model, keep, refuse in ((near, 1.0, 0.0), (far, 0.0, 1.0)):
        for bar in (0.5, 0.99):
            rows = _report_rows(run.stdout, model, bar)
            assert rows["all"][:2] == [60, 1.0]  # n, stay
            assert rows["all"][3:] == [keep, refuse]
            assert sum(r[0] for name, r in rows.items() if name != "all") == 60
    other = save_stop_offsets(tmp_path / "other.pth", _fixed_net(2, 2, near=True, size=192), {})
    run = subprocess.run(tool + ["--models", str(near), str(other)], capture_output=True, text=True)
    assert run.returncode == 2 and "other.pth: made for FoV 90 and 192x192 views" in run.stderr
    run = subprocess.run(tool + ["--models", str(near), "--min-near", "1.5"], capture_output=True, text=True)
    assert run.returncode == 2 and "--min-near bars in (0, 1) (got [1.5])" in run.stderr
