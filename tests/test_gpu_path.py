"""The device-resident training path: host-device syncs per step, the streaming panorama bank and the
policy's speed options (agent.precision, agent.channels_last, agent.compile).

Everything runs on the CPU; the ``cuda`` cases run only with a GPU (``benchmarks/gpu_check.sh``).
"""

from __future__ import annotations

import random
import warnings

import cv2
import numpy as np
import pytest
import torch
from torch.distributions import Distribution

from findview.episode import Episode
from findview.sim import PanoramaBank, Simulator, equi2pers
from findview.task import FindViewEnv, StaticEpisodeSource
from findview.task.sources import SampledEpisodeSource
from findview_baselines.rl.policy import Policy, build_policy
from findview_baselines.config import PPOAgentConfig
from findview_baselines.rl.storage import RolloutStorage

CUDA = pytest.mark.skipif(not torch.cuda.is_available(), reason="no CUDA device")
DEVICES = ["cpu", pytest.param("cuda", marks=CUDA)]
EQUI_H = 64  # panorama height of the test panoramas (128x64)
SIZE = 48  # view size: the smallest the paper's encoder takes is 36


@pytest.fixture(scope="module")
def panos(tmp_path_factory) -> list[str]:
    """Six random-texture 128x64 panoramas (PNG)."""
    d = tmp_path_factory.mktemp("panos")
    rng = np.random.default_rng(1)
    paths = []
    for k in range(6):
        img = cv2.resize(rng.integers(0, 255, (8, 16, 3), dtype=np.uint8), (2 * EQUI_H, EQUI_H), interpolation=cv2.INTER_CUBIC)
        paths.append(str(d / f"p{k}.png"))
        cv2.imwrite(paths[-1], img)
    return paths


def load_rgb(path: str) -> torch.Tensor:
    """(1, 3, He, We) uint8 RGB."""
    return torch.from_numpy(cv2.cvtColor(cv2.imread(path), cv2.COLOR_BGR2RGB)).permute(2, 0, 1)[None]


class RandomEpisodes:
    """A ``sample_level`` sampler: endless random episodes over ``paths`` (enough for the sync count)."""

    def __init__(self, paths: list[str], seed: int = 0) -> None:
        self.paths, self.rng, self.n = paths, random.Random(seed), 0

    def sample_level(self, level: int) -> Episode:
        self.n += 1
        r = self.rng
        return Episode(f"e{self.n}", r.choice(self.paths), r.randint(-20, 20), r.randint(-179, 180),
                       r.randint(-20, 20), r.randint(-179, 180), difficulty="easy")


# --------------------------------------------------------------------------------------------------
# Host-device syncs per step
# --------------------------------------------------------------------------------------------------

# every Tensor method that copies device data to the host (each one is a sync on CUDA)
HOST_READS = ("item", "cpu", "tolist", "numpy", "__bool__", "__int__", "__float__", "__index__")


class HostReadCounter:
    """Counts calls of :data:`HOST_READS` while active (monkeypatched on ``torch.Tensor``)."""

    def __init__(self, monkeypatch: pytest.MonkeyPatch) -> None:
        self.count = 0
        for name in HOST_READS:
            original = getattr(torch.Tensor, name)

            def counted(self_, *args, __original=original, **kwargs):
                self.count += 1
                return __original(self_, *args, **kwargs)

            monkeypatch.setattr(torch.Tensor, name, counted)


def make_training_env(panos: list[str], num_envs: int, device: str, max_steps: int = 6) -> FindViewEnv:
    bank = PanoramaBank(device, 64, min_slots=num_envs, prefetch_workers=0)
    sim = Simulator(bank, fov=90, height=SIZE, width=SIZE, pitch_bound=60, backend="torch")
    sim.build_all_grids(EQUI_H)  # grids are built lazily on the CPU; here: none left to build while counting
    return FindViewEnv(sim, SampledEpisodeSource(RandomEpisodes(panos)), num_envs, max_steps=max_steps)


def per_step_host_reads(panos, num_envs: int, steps: int, monkeypatch) -> tuple[list[int], int]:
    """Host reads of each rollout step (policy.act + env.step + storage.insert) and the episodes ended."""
    torch.manual_seed(0)
    env = make_training_env(panos, num_envs, "cpu")
    policy = Policy(SIZE, SIZE, "early_fusion", hidden_size=16)
    storage = RolloutStorage(steps, num_envs, SIZE, SIZE, 16)
    storage.set_initial(env.reset(), (~env.new_episode).float())
    counts, ended = [], 0
    previous = Distribution._validate_args
    Distribution.set_default_validate_args(False)  # as in PPOTrainer (argument checks read the device)
    try:
        with monkeypatch.context() as m, torch.no_grad():
            counter = HostReadCounter(m)
            for _ in range(steps):
                before = counter.count
                obs, hidden, masks = storage.current()
                actions, log_probs, values, new_hidden = policy.act(obs, hidden, masks)
                next_obs, reward, done, infos = env.step(actions)
                storage.insert(next_obs, new_hidden, actions, log_probs, values, reward, (~env.new_episode).float())
                counts.append(counter.count - before)
                ended += sum(info is not None for info in infos)
    finally:
        Distribution.set_default_validate_args(previous)
    return counts, ended


def test_host_reads_per_step_are_few_and_do_not_grow_with_num_envs(panos, monkeypatch):
    # episodes of at most 6 steps: most steps end and start episodes, so the reset path is counted too
    few, ended_few = per_step_host_reads(panos, 2, 12, monkeypatch)
    many, ended_many = per_step_host_reads(panos, 24, 12, monkeypatch)
    assert ended_few >= 2 and ended_many >= 24  # the done / reset path ran
    # one packed device -> host copy per step plus reads of that host copy (its done / moved ids, the
    # finished episodes' records): a constant, far below one per env
    assert max(few) <= 5 and max(many) <= 5, (few, many)
    assert max(many) <= max(few) + 1


@CUDA
def test_cuda_rollout_step_syncs(panos):  # pragma: no cover - runs only with a GPU
    """With ``torch.cuda.set_sync_debug_mode("warn")`` every synchronising call warns: count them."""
    n, steps = 64, 16
    torch.manual_seed(0)
    env = make_training_env(panos, n, "cuda")
    policy = Policy(SIZE, SIZE, "early_fusion", hidden_size=16).cuda()
    storage = RolloutStorage(steps, n, SIZE, SIZE, 16, "cuda")
    storage.set_initial(env.reset(), (~env.new_episode).float())
    previous = Distribution._validate_args
    Distribution.set_default_validate_args(False)
    torch.cuda.synchronize()
    counts = []
    try:
        with torch.no_grad():
            for _ in range(steps):
                with warnings.catch_warnings(record=True) as caught:
                    warnings.simplefilter("always")
                    torch.cuda.set_sync_debug_mode("warn")
                    try:
                        obs, hidden, masks = storage.current()
                        actions, log_probs, values, new_hidden = policy.act(obs, hidden, masks)
                        next_obs, reward, done, _ = env.step(actions)
                        storage.insert(next_obs, new_hidden, actions, log_probs, values, reward, (~env.new_episode).float())
                    finally:
                        torch.cuda.set_sync_debug_mode("default")
                counts.append(sum("synchroniz" in str(w.message) for w in caught))
    finally:
        Distribution.set_default_validate_args(previous)
    print("CUDA syncs per rollout step:", counts)
    assert max(counts) <= 4, counts


# --------------------------------------------------------------------------------------------------
# Panorama bank smaller than the split
# --------------------------------------------------------------------------------------------------


@pytest.mark.parametrize("device", DEVICES)
def test_bank_streams_the_right_panoramas_within_its_bound(panos, device):
    per_mib = 2 * EQUI_H * EQUI_H * 3 / 2**20
    bound = 3.5 * per_mib  # room for 3 of the 6 panoramas
    bank = PanoramaBank(device, bound, prefetch_workers=1, max_panoramas=len(panos), min_slots=2)
    sim = Simulator(bank, fov=90, height=SIZE, width=SIZE, pitch_bound=60, backend="torch")
    order = [0, 1, 2, 3, 4, 5, 3, 0, 5, 1, 2, 4]
    episodes = [Episode(f"e{k}", panos[i], 0, 10 * k, (k % 5) - 2, -15 * k, difficulty="easy") for k, i in enumerate(order)]
    env = FindViewEnv(sim, StaticEpisodeSource(episodes), 2, prefetch=4)
    env.reset()
    seen = 0
    for _ in range(len(episodes) // 2):
        assert bank.slots.numel() <= bound * 2**20  # the slot tensor is all the bank allocates
        for i, ep in enumerate(env.episodes):
            ref = equi2pers(load_rgb(ep.image).to(device), float(ep.target_pitch), float(ep.target_yaw), 90, SIZE, SIZE,
                            backend="torch")
            assert (env.target[i].int() - ref[0].int()).abs().max() <= 1, ep  # the episode's own panorama
            seen += 1
        env.step(torch.tensor([4, 4], device=device))  # STOP: both slots start their next episodes
    assert seen == len(episodes)
    assert bank.capacity == 3 and bank.stats["evictions"] > 0 and bank.stats["prefetched"] > 0
    env.close()


def test_bank_holds_the_whole_split_when_it_fits(panos):
    bank = PanoramaBank("cpu", 100, prefetch_workers=0, max_panoramas=len(panos), min_slots=2)
    for p in panos * 2:
        bank.release(bank.acquire(p))
    assert bank.capacity == len(panos)  # sized to the split, not to the bound
    assert bank.stats["misses"] == len(panos) and bank.stats["evictions"] == 0  # each decoded once


# --------------------------------------------------------------------------------------------------
# Speed options of the policy
# --------------------------------------------------------------------------------------------------


def random_obs(batch: int, seed: int = 0) -> dict[str, torch.Tensor]:
    g = torch.Generator().manual_seed(seed)
    # smooth images (like renders): bf16 rounding of smooth inputs stays small
    small = torch.randint(0, 256, (2, batch, 3, 6, 6), generator=g).float()
    big = torch.nn.functional.interpolate(small.flatten(0, 1), size=(SIZE, SIZE), mode="bilinear").view(2, batch, 3, SIZE, SIZE)
    return {"view": big[0].round().to(torch.uint8), "target": big[1].round().to(torch.uint8)}


OPTIONS = {
    "channels_last": ({"channels_last": True}, 1e-5),
    "compile": ({"compile": True, "compile_backend": "eager"}, 1e-5),
    "bf16": ({"precision": "bf16"}, 0.05),
    "bf16+channels_last": ({"precision": "bf16", "channels_last": True}, 0.05),
}


@pytest.mark.parametrize("device", DEVICES)
@pytest.mark.parametrize("name", list(OPTIONS))
@pytest.mark.parametrize("variant", ["early_fusion", "phase"])
def test_speed_options_match_fp32(name, device, variant):
    opts, tol = OPTIONS[name]
    if device == "cuda" and opts.get("compile"):
        opts = {**opts, "compile_backend": "inductor"}
    torch.manual_seed(0)
    ref = Policy(SIZE, SIZE, variant, hidden_size=32).to(device)
    with torch.no_grad():  # a critic and actor on the scale of a trained policy's
        ref.actor.weight.mul_(100.0)
    fast = Policy(SIZE, SIZE, variant, hidden_size=32)
    fast.load_state_dict(ref.state_dict())
    fast = fast.configure_speed(**opts).to(device)
    T, N = 3, 4
    obs = {k: v.to(device) for k, v in random_obs(T * N).items()}
    hidden = torch.randn(N, 32, generator=torch.Generator().manual_seed(1)).to(device)
    masks = torch.ones(T * N, device=device)
    masks[N + 1] = 0
    with torch.no_grad():
        d0, v0, h0 = ref(obs, hidden, masks)
        d1, v1, h1 = fast(obs, hidden, masks)
    assert v1.dtype == torch.float32 and d1.logits.dtype == torch.float32 and h1.dtype == torch.float32
    scale = float(v0.abs().max()) + float(d0.logits.abs().max())
    assert torch.allclose(d1.probs, d0.probs, atol=tol)
    assert (v1 - v0).abs().max() <= tol * scale and (h1 - h0).abs().max() <= tol * 10
    if tol < 1e-3:  # exact options: the same greedy actions
        assert torch.equal(d1.logits.argmax(-1), d0.logits.argmax(-1))
    # the update path: gradients flow (bf16 under autocast too) and are finite
    log_probs, values, entropy = fast.evaluate_actions(obs, hidden, masks, d0.logits.argmax(-1))
    (log_probs.mean() + values.mean()).backward()
    grads = [p.grad for p in fast.parameters()]
    assert all(g is not None and torch.isfinite(g).all() for g in grads)


def test_checkpoints_with_speed_options_load_without_them(tmp_path):
    torch.manual_seed(0)
    cfg = PPOAgentConfig(hidden_size=32, precision="bf16", channels_last=True, compile=False)
    fast = build_policy(cfg, SIZE, SIZE)
    fast.configure_speed("bf16", channels_last=True, compile=True, compile_backend="eager")
    assert fast.encoder.convs[0].weight.is_contiguous(memory_format=torch.channels_last)
    plain = Policy(SIZE, SIZE, "early_fusion", hidden_size=32)
    assert list(fast.state_dict()) == list(plain.state_dict())  # no "_orig_mod." from torch.compile
    path = tmp_path / "policy.pth"
    torch.save(fast.state_dict(), path)
    plain.load_state_dict(torch.load(path, weights_only=True))  # strict
    back = Policy(SIZE, SIZE, "early_fusion", hidden_size=32).configure_speed("bf16", channels_last=True)
    back.load_state_dict(torch.load(path, weights_only=True))
    obs = random_obs(2)
    h, m = torch.zeros(2, 32), torch.ones(2)
    with torch.no_grad():
        assert torch.equal(plain(obs, h, m)[1], fast.configure_speed()(obs, h, m)[1])  # options off: identical


def test_bad_precision_is_a_one_line_error():
    with pytest.raises(ValueError, match="agent.precision must be one of fp32 | bf16, got 'fp16'"):
        Policy(SIZE, SIZE, hidden_size=8).configure_speed("fp16")
    from findview_baselines.config import ConfigError, PPOAgentConfig

    with pytest.raises(ConfigError, match="agent.precision"):
        PPOAgentConfig(precision="half")
    assert PPOAgentConfig().precision == "fp32" and not PPOAgentConfig().compile
