"""Corrupted FindView: the target (never the view) is corrupted once per episode from the episode's seed,
the same way for every agent and every number of environments, and records say which corruption ran."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from findview.build import build_simulator, build_static_env
from findview.config import CorruptionConfig, SimConfig, TaskConfig, as_section
from findview.episode import Episode
from findview.task.target_corruption import EpisodeCorruption

SIM = SimConfig(fov=90, height=32, width=32, device="cpu", prefetch_workers=0)
TASK = TaskConfig(max_steps=20)


@pytest.fixture(scope="module")
def episodes(tmp_path_factory) -> list[Episode]:
    import cv2

    rng = np.random.default_rng(0)
    path = tmp_path_factory.mktemp("pano") / "pano.png"
    cv2.imwrite(str(path), cv2.resize(rng.integers(0, 256, (16, 32, 3), dtype=np.uint8), (256, 128)))
    return [Episode(f"ep{i}", str(path), 0, 0, 0, 10 * (i + 1), difficulty="easy", seed=1000 + i) for i in range(6)]


def _targets(episodes, num_envs, corruption):
    """The targets each episode starts with, in episode order, for ``num_envs`` parallel slots."""
    sim = build_simulator(SIM, 60, [e.image for e in episodes], num_envs)
    env = build_static_env(SIM, TASK, episodes, num_envs, simulator=sim,
                           corruption_cfg=None if corruption is None else as_section(corruption, CorruptionConfig))
    out, views, records = {}, {}, []
    env.reset()
    while bool(env.active.any()):
        for i in torch.nonzero(env.new_episode & env.active).flatten().tolist():
            out[env.episodes[i].episode_id] = env.target[i].clone()
            views[env.episodes[i].episode_id] = env.view[i].clone()
        _, _, _, infos = env.step(torch.full((num_envs,), 4))  # stop at once
        records += [r for r in infos if r is not None]
    return out, views, records


def test_targets_are_corrupted_per_episode_the_same_for_any_num_envs(episodes) -> None:
    corruption = {"name": ["gaussian_noise", "fog", "contrast"], "severity": [1, 5]}
    clean, clean_views, _ = _targets(episodes, 2, None)
    one, views1, records = _targets(episodes, 1, corruption)
    three, _, _ = _targets(episodes, 3, corruption)
    for ep in episodes:
        assert torch.equal(one[ep.episode_id], three[ep.episode_id])  # independent of batching
        assert not torch.equal(one[ep.episode_id], clean[ep.episode_id])  # the target is corrupted
        assert torch.equal(views1[ep.episode_id], clean_views[ep.episode_id])  # the view stays clean
    chooser = EpisodeCorruption(["gaussian_noise", "fog", "contrast"], 1, 5)
    for rec, ep in zip(records, episodes):
        name, severity = chooser.choice(ep)
        assert (rec["corruption"], rec["severity"]) == (name, severity)
        assert name in ("gaussian_noise", "fog", "contrast") and 1 <= severity <= 5
    assert len({(r["corruption"], r["severity"]) for r in records}) > 1  # episodes draw different ones


def test_clean_records_say_none(episodes) -> None:
    _, _, records = _targets(episodes[:2], 2, {"name": "none", "severity": 3})
    assert [(r["corruption"], r["severity"]) for r in records] == [("none", 0), ("none", 0)]


def test_the_severity_ramp_bounds_the_drawn_severity(episodes) -> None:
    chooser = EpisodeCorruption(["fog"], 1, 5)
    chooser.max_severity = 1
    assert {chooser.choice(ep)[1] for ep in episodes} == {1}
    chooser.max_severity = 5
    assert max(chooser.choice(ep)[1] for ep in episodes) > 1


def test_weighted_draws_follow_the_weights_and_uniform_stays_as_before() -> None:
    names = ["gaussian_noise", "fog", "contrast"]
    eps = [Episode(f"w{i}", "p.png", 0, 0, 0, 10, seed=7 * i + 1) for i in range(3000)]
    uniform = EpisodeCorruption(names, 1, 5)
    # an empty mapping is the uniform draw, episode for episode
    assert [uniform.choice(e) for e in eps[:200]] == [EpisodeCorruption(names, 1, 5, weights={}).choice(e) for e in eps[:200]]
    weighted = EpisodeCorruption(names, 1, 5, weights={"fog": 3})  # fog 3 / 5, the others 1 / 5 each
    draws = [weighted.choice(e)[0] for e in eps]
    share = draws.count("fog") / len(draws)
    assert abs(share - 0.6) < 4 * (0.6 * 0.4 / len(draws)) ** 0.5  # four standard errors of a binomial share
    assert abs(draws.count("contrast") / len(draws) - 0.2) < 4 * (0.2 * 0.8 / len(draws)) ** 0.5
    never = EpisodeCorruption(names, 1, 5, weights={"fog": 0})
    assert "fog" not in {never.choice(e)[0] for e in eps[:500]}
    with pytest.raises(ValueError, match="corruption.weights"):
        EpisodeCorruption(names, 1, 5, weights={"snow": 2})  # snow is not drawn here


def test_weights_reach_the_environment_through_the_config() -> None:
    from findview.build import build_target_transform
    from findview.config import ConfigError

    cfg = as_section({"name": ["fog", "snow"], "severity": 3, "weights": {"snow": 0}}, CorruptionConfig)
    chooser = build_target_transform(cfg)
    eps = [Episode(f"c{i}", "p.png", 0, 0, 0, 10, seed=i) for i in range(100)]
    assert {chooser.choice(e) for e in eps} == {("fog", 3)}
    with pytest.raises(ConfigError, match="corruption.weights"):
        as_section({"name": "weather", "weights": {"contrast": 2}}, CorruptionConfig)  # contrast is digital
