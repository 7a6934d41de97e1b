"""Views rendered larger than the network takes them (findview_baselines/rl/observations.py): the block
average by hand, the size rule, a training environment whose observations come averaged down, and the
learned agent on views four times its network's size (the same actions as on views averaged beforehand)."""

from __future__ import annotations

import copy

import pytest
import torch

from _training import blob_panorama, write_panoramas
from findview.dataset import EpisodeSampler, ImageEntry
from findview.sim import PanoramaBank, Simulator
from findview.task import FindViewEnv
from findview.task.sources import SampledEpisodeSource
from findview_baselines.agents.ppo_agent import PPOAgent
from findview_baselines.rl.dagger import DAggerConfig, DAggerTrainer
from findview_baselines.rl.observations import DownsampledEnv, area_downsample, downsample_factor
from findview_baselines.rl.policy import Policy


def test_area_downsample_by_hand():
    img = torch.zeros(1, 3, 4, 4, dtype=torch.uint8)
    img[0, 0] = torch.tensor([[0, 2, 10, 10], [1, 2, 10, 10], [255, 255, 0, 0], [255, 254, 0, 1]], dtype=torch.uint8)
    img[0, 1] = torch.tensor([[1, 2, 2, 3], [1, 2, 2, 3], [3, 4, 0, 0], [3, 4, 0, 0]], dtype=torch.uint8)
    out = area_downsample(img, 2)
    assert out.dtype == torch.uint8 and out.shape == (1, 3, 2, 2)
    # block means 1.25, 10, 254.75, 0.25 -> rounded to the nearest level
    assert out[0, 0].tolist() == [[1, 10], [255, 0]]
    # ties 1.5, 2.5, 3.5 -> the even level: 2, 2, 4
    assert out[0, 1].tolist() == [[2, 2], [4, 0]]
    assert out[0, 2].eq(0).all()
    assert area_downsample(img, 1) is img


@pytest.mark.parametrize("size,net,k", [((256, 256), (64, 64), 4), ((64, 64), (64, 64), 1), ((192, 256), (48, 64), 4),
                                        ((256, 192), (64, 64), None), ((100, 100), (64, 64), None),
                                        ((32, 32), (64, 64), None)])
def test_downsample_factor(size, net, k):
    assert downsample_factor(size, net) == k


@pytest.fixture(scope="module")
def images(tmp_path_factory) -> list[ImageEntry]:
    return write_panoramas(tmp_path_factory.mktemp("obs_panoramas"), blob_panorama, range(40, 43), "blobs")


def _env(images, num_envs: int, size: int) -> FindViewEnv:
    bank = PanoramaBank("cpu", prefetch_workers=0, max_panoramas=len(images), min_slots=num_envs)
    sim = Simulator(bank, fov=90, height=size, width=size, pitch_bound=20)
    sampler = EpisodeSampler(images, 90, seed=3, pitch_bound=20, max_steps=200)
    return FindViewEnv(sim, SampledEpisodeSource(sampler, level=1), num_envs, max_steps=200, pitch_bound=20)


def test_downsampled_env_feeds_a_trainer_averaged_views(images):
    """Every observation of the wrapped env is the block average of the rendered one; poses and the rest are
    the env's own; a DAgger rollout that follows the oracle (beta = 1) on it ends every episode exactly."""
    env = DownsampledEnv(_env(images, 3, 64), 2)
    obs = env.reset()
    assert obs["view"].shape == (3, 3, 32, 32) and torch.equal(obs["view"], area_downsample(env.env.view, 2))
    assert torch.equal(env.target, area_downsample(env.env.target, 2))
    assert {k: v.shape for k, v in env.observations.items()} == {"view": (3, 3, 32, 32), "target": (3, 3, 32, 32)}
    assert torch.equal(env.observations["target"], obs["target"])
    assert env.num_envs == 3 and env.pitch is env.env.pitch
    assert copy.copy(env).num_envs == 3  # attribute fall-through survives a copy (no recursion on `env`)
    obs, _, _, _ = env.step(torch.tensor([0, 1, 2]))
    assert torch.equal(obs["view"], area_downsample(env.env.view, 2))

    torch.manual_seed(0)
    trainer = DAggerTrainer(env, Policy(32, 32, variant="direct", hidden_size=16),
                            DAggerConfig(rollout_steps=24, seq_len=8, buffer_size=500, batch_sequences=4, beta_end=1.0),
                            total_updates=4)
    trainer.start()
    records = []
    for _ in range(3):
        records += trainer.train_update()["episodes"]
    assert records and all(r["called_stop"] and r["eps"] == 0 for r in records)


def test_learned_agent_averages_larger_views_itself(images):
    """A 32x32 policy acting on 128x128 views takes the actions (and keeps the GRU states) it takes on the
    same views averaged down beforehand; a size that is not a multiple is refused, naming both sizes."""
    torch.manual_seed(1)
    policy = Policy(32, 32, variant="direct", hidden_size=16)
    env = _env(images, 4, 128)
    obs = env.reset()
    big, small = PPOAgent(policy, 4, "cpu", 0), PPOAgent(policy, 4, "cpu", 0)
    big.reset(range(4), env.episodes)
    small.reset(range(4), env.episodes)
    for _ in range(5):
        a = big.act(obs)
        b = small.act({k: area_downsample(v, 4) for k, v in obs.items()})
        assert torch.equal(a, b) and torch.equal(big.hidden, small.hidden)
        obs, _, _, _ = env.step(a)
    with pytest.raises(ValueError, match=r"\(100, 100\).*32x32"):
        PPOAgent(policy, 1, "cpu", 0).act({"view": torch.zeros(1, 3, 100, 100, dtype=torch.uint8),
                                           "target": torch.zeros(1, 3, 100, 100, dtype=torch.uint8)})
