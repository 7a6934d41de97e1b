"""The CPU thread policy (findview.runtime): OMP_WAIT_POLICY=PASSIVE reaches torch when findview is
imported first, a user's value wins, and configure_threads sets the documented default."""

from __future__ import annotations

import json
import os
import subprocess
import sys

import pytest

PROBE = """
import json, logging, os, sys
logging.basicConfig(level=logging.WARNING, stream=sys.stderr)
order = sys.argv[1]
if order == "torch_first":
    import torch
import findview
from findview.runtime import configure_threads, wait_policy_effective
import torch
default = configure_threads()  # the documented default
print("-- default done", file=sys.stderr, flush=True)
n = configure_threads(2)
print(json.dumps({"policy": os.environ.get("OMP_WAIT_POLICY"), "effective": wait_policy_effective(),
                  "default": default, "threads": torch.get_num_threads(), "returned": n}))
"""


def probe(*args: str, env_extra: dict | None = None) -> tuple[dict, str]:
    env = {k: v for k, v in os.environ.items() if k not in ("OMP_WAIT_POLICY", "OMP_NUM_THREADS")}
    env.update(env_extra or {})
    proc = subprocess.run([sys.executable, "-c", PROBE, *args], capture_output=True, text=True, env=env, timeout=120)
    assert proc.returncode == 0, proc.stderr
    return json.loads(proc.stdout.strip().splitlines()[-1]), proc.stderr


def test_findview_first_sets_passive_wait_policy():
    """Default 1 torch thread; 2 threads on request, without a warning (the policy is in effect)."""
    out, err = probe("findview_first")
    assert out == {"policy": "PASSIVE", "effective": True, "default": 1, "threads": 2, "returned": 2}
    assert "spin-wait" not in err


def test_torch_first_is_not_effective_and_warns_for_several_threads():
    out, err = probe("torch_first")
    assert out["effective"] is False and out["default"] == 1 and out["threads"] == 2
    before, after = err.split("-- default done")
    assert "spin-wait" not in before  # one thread: nothing to warn about
    assert "OMP_WAIT_POLICY" in after and "spin-wait" in after


def test_user_value_wins():
    out, _ = probe("findview_first", env_extra={"OMP_WAIT_POLICY": "ACTIVE"})
    assert out["policy"] == "ACTIVE" and out["effective"] is False


def test_bad_thread_count():
    from findview.runtime import configure_threads

    with pytest.raises(ValueError, match="torch_threads"):
        configure_threads(-1)


# ------------------------------------------------------------------ thread counts chosen where the work is done
SCOPES_PROBE = """
import json, sys
import numpy, torch, cv2  # before findview, as most user scripts do: findview's environment defaults come too late
torch.set_num_threads(2)
import findview.runtime as runtime
from findview.runtime import blas_threads
blas_before = blas_threads()
for _, put in runtime._find_blas():
    put(2)
seen = {}

def spy(owner, name, key):
    real = getattr(owner, name)
    def wrapped(*a, **k):
        seen.setdefault(key, []).append((torch.get_num_threads(), blas_threads()))
        return real(*a, **k)
    setattr(owner, name, wrapped)

import numpy as np
from findview.episode import Episode
from findview.sim import PanoramaBank, Simulator
from findview.sim import simulator as sim_module
from findview.task import FindViewEnv, StaticEpisodeSource
import findview.corruptions as corruptions
from findview_baselines.rl import ppo as ppo_module
import cv2
path = sys.argv[1]
cv2.imwrite(path, np.random.default_rng(0).integers(0, 255, (128, 256, 3), dtype=np.uint8))
spy(sim_module.Simulator, "_render_opencv", "render")
real_blur = corruptions._OPS["motion_blur"]
def blur_spy(*a, **k):
    seen.setdefault("corrupt", []).append((torch.get_num_threads(), blas_threads()))
    return real_blur(*a, **k)
corruptions._OPS["motion_blur"] = blur_spy
spy(ppo_module.PPO, "_minibatch_terms", "ppo")
bank = PanoramaBank("cpu", 64, min_slots=2, prefetch_workers=0)
env = FindViewEnv(Simulator(bank, fov=90, height=40, width=40), StaticEpisodeSource(
    [Episode(str(i), path, 0, 10 * i, 0, 0) for i in range(4)]), 2)
env.reset(); env.step(torch.tensor([0, 2]))
from findview.corruptions import corrupt
corrupt(torch.zeros(2, 3, 40, 40, dtype=torch.uint8), "motion_blur", 3)
from findview_baselines.config import PPOAgentConfig
from findview_baselines.rl.policy import build_policy
from findview_baselines.rl.ppo import PPO, PPOConfig
from findview_baselines.rl.storage import RolloutStorage
policy = build_policy(PPOAgentConfig(hidden_size=16), 40, 40)
storage = RolloutStorage(2, 2, 40, 40, 16)
storage.set_initial(env.reset())
for _ in range(2):
    obs, hidden, masks = storage.current()
    with torch.no_grad():
        a, lp, v, h = policy.act(obs, hidden, masks)
    storage.insert(env.step(a)[0], h, a, lp, v, torch.zeros(2), torch.ones(2))
storage.compute_returns(torch.zeros(2), 0.99, 0.95)
PPO(policy, PPOConfig(rollout_steps=2, ppo_epochs=1)).update(storage)  # a small network: light work
seen["ppo_small"] = seen.pop("ppo")
big = build_policy(PPOAgentConfig(hidden_size=16), 128, 128)  # the paper's encoder on 128x128: heavy work
big_storage = RolloutStorage(2, 2, 128, 128, 16)
pixels = lambda: torch.randint(0, 256, (2, 3, 128, 128), dtype=torch.uint8)
big_storage.set_initial({"view": pixels(), "target": pixels()})
for _ in range(2):
    obs, hidden, masks = big_storage.current()
    with torch.no_grad():
        a, lp, v, h = big.act(obs, hidden, masks)
    big_storage.insert({"view": pixels(), "target": pixels()}, h, a, lp, v, torch.zeros(2), torch.ones(2))
big_storage.compute_returns(torch.zeros(2), 0.99, 0.95)
PPO(big, PPOConfig(rollout_steps=2, ppo_epochs=1)).update(big_storage)
print(json.dumps({"seen": seen, "after": [torch.get_num_threads(), blas_threads()],
                  "compute": runtime.compute_threads(), "blas_found": bool(runtime._find_blas())}))
"""


def test_hot_paths_choose_their_threads_whatever_the_import_order(tmp_path):
    """torch, numpy and cv2 imported first, torch and OpenBLAS at 2 threads: rendering, corruptions and the PPO
    update of a small network run on one torch and one BLAS thread, the update of the paper's network on 128x128
    views on compute_threads(); the user's counts are back afterwards."""
    env = {k: v for k, v in os.environ.items() if k not in ("OMP_WAIT_POLICY", "OPENBLAS_NUM_THREADS")}
    env["FINDVIEW_COMPUTE_THREADS"] = "3"
    proc = subprocess.run([sys.executable, "-c", SCOPES_PROBE, str(tmp_path / "pano.png")], capture_output=True,
                          text=True, env=env, timeout=300)
    assert proc.returncode == 0, proc.stderr
    out = json.loads(proc.stdout.strip().splitlines()[-1])
    blas_one = [1] * len(out["after"][1])
    assert out["seen"]["render"] and all(seen == [1, blas_one] for seen in out["seen"]["render"])
    assert out["seen"]["corrupt"] == [[1, blas_one]]
    assert out["compute"] == 3 and out["seen"]["ppo"] and all(seen[0] == 3 for seen in out["seen"]["ppo"])
    assert out["seen"]["ppo_small"] and all(seen == [1, blas_one] for seen in out["seen"]["ppo_small"])
    assert out["after"][0] == 2
    if out["blas_found"]:  # numpy's OpenBLAS (Linux wheels): its count is back to the user's
        assert out["after"][1] and set(out["after"][1]) == {2}


def test_scopes_nest_and_restore(monkeypatch):
    import numpy  # noqa: F401  (so that the BLAS controls can be found)
    import torch

    from findview import runtime

    monkeypatch.setenv(runtime.COMPUTE_THREADS_ENV, "2")
    before = torch.get_num_threads()
    with runtime.light_work():
        assert torch.get_num_threads() == 1 and set(runtime.blas_threads()) <= {1}
        with runtime.heavy_work():
            assert torch.get_num_threads() == 2
        assert torch.get_num_threads() == 1
    assert torch.get_num_threads() == before


def test_compute_threads_knobs(monkeypatch):
    import torch

    from findview import runtime

    monkeypatch.delenv(runtime.COMPUTE_THREADS_ENV, raising=False)
    assert runtime.compute_threads() == len(os.sched_getaffinity(0))
    monkeypatch.setenv(runtime.COMPUTE_THREADS_ENV, "5")
    assert runtime.compute_threads() == 5
    monkeypatch.setenv(runtime.COMPUTE_THREADS_ENV, "two")
    with pytest.raises(ValueError, match="FINDVIEW_COMPUTE_THREADS='two'"):
        runtime.compute_threads()
    before = torch.get_num_threads()
    try:
        assert runtime.configure_threads(3) == 3 and runtime.compute_threads() == 3  # the config wins
        runtime.configure_threads(None)
        assert torch.get_num_threads() == runtime.DEFAULT_TORCH_THREADS
        with pytest.raises(ValueError, match="two"):
            runtime.compute_threads()  # back to the environment variable
    finally:
        runtime.configure_threads(None)
        torch.set_num_threads(before)


def test_decorated_scopes_choose_per_call_and_heavy_work_yields_to_a_competing_load(monkeypatch):
    """A decorator made before the setting changes still follows it; unset, heavy work takes the cores that
    other runnable tasks leave (at least one, at most compute_threads())."""
    import torch

    from findview import runtime

    @runtime.heavy_work()
    def inside() -> int:
        return torch.get_num_threads()

    monkeypatch.setattr(runtime, "LOAD_LOOK_S", 0.0)
    monkeypatch.setenv(runtime.COMPUTE_THREADS_ENV, "3")
    assert inside() == 3
    monkeypatch.setenv(runtime.COMPUTE_THREADS_ENV, "1")
    assert inside() == 1
    monkeypatch.delenv(runtime.COMPUTE_THREADS_ENV)
    monkeypatch.setattr(runtime, "compute_threads", lambda: 4)
    for others, expected in ((0, 4), (1, 3), (3, 1), (9, 1), (None, 4)):
        monkeypatch.setattr(runtime, "runnable_elsewhere", lambda others=others: others)
        assert inside() == expected, others


def test_runnable_elsewhere_sees_a_busy_process():
    from findview import runtime

    if runtime.runnable_elsewhere() is None:
        pytest.skip("no /proc/loadavg here")
    busy = subprocess.Popen([sys.executable, "-c", "while True: pass"])
    try:
        import time

        seen = []
        for _ in range(40):  # a busy loop is runnable whenever it is looked at; other tasks come and go
            time.sleep(0.02)
            seen.append(runtime.runnable_elsewhere())
        assert min(seen) >= 1, seen
    finally:
        busy.kill()
        busy.wait()
