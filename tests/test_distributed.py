"""DD-PPO over torch.distributed on CPU with 2 gloo processes (findview_baselines.rl.distributed).

* the PPO update on fixed rollouts: both ranks end with identical weights, and these equal one process
  updating on the two ranks' rollouts side by side (float tolerance), stats included;
* the whole run loop (2 ranks spawned in-process): 2 + resume + 2 updates give the weights of 4 in one go;
* PPO and DAgger through the run loop: every rank ends with rank 0's weights, also when straggler
  preemption cuts the slow rank's rollouts short (``trainer.preempt_fraction``);
* a real ``torchrun ... tools/train.py trainer.distributed=true``: SIGTERM to rank 1 only stops both ranks
  (exit 143, latest.pth with both ranks' state), and one process without torchrun resumes from it;
* SIGUSR1 (SLURM's warning) stops a single-process run like SIGTERM.

Tiny setup: 40x40 views (the CNN's minimum is 36), 2 envs per rank, 8-step rollouts, GRU 32.
"""

from __future__ import annotations

import logging
import os
import signal
import socket
import subprocess
import sys
import time
from pathlib import Path
from typing import Any, Callable

import pytest
import torch
import torch.multiprocessing as mp

from _training import load, make_config

REPO = Path(__file__).resolve().parents[1]
SIZE = 40
HIDDEN = 32


def free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return int(s.getsockname()[1])


def _join(rank: int, world: int, port: int) -> None:
    """Set the variables torchrun would set for ``rank``."""
    os.environ.update(MASTER_ADDR="127.0.0.1", MASTER_PORT=str(port), RANK=str(rank), WORLD_SIZE=str(world),
                      LOCAL_RANK=str(rank), OMP_NUM_THREADS="1")
    torch.set_num_threads(1)


def spawn(fn: Callable[..., None], *args: Any, world: int = 2) -> None:
    """Run ``fn(rank, world, port, *args)`` in ``world`` fresh processes; fail on any non-zero exit."""
    mp.start_processes(fn, args=(world, free_port(), *args), nprocs=world, join=True, start_method="spawn")


# --------------------------------------------------------------------------------------------------
# The PPO update: identical weights, and the same step as one process on the combined batch
# --------------------------------------------------------------------------------------------------

T_STEPS, N_ALL = 4, 4  # rollout steps; environments of both ranks together (2 per rank)


def fixed_rollout(seed: int = 0) -> dict[str, torch.Tensor]:
    """A random but fixed rollout of ``N_ALL`` environments (what both ranks together collected)."""
    g = torch.Generator().manual_seed(seed)
    T, N = T_STEPS, N_ALL
    masks = (torch.rand(T + 1, N, generator=g) > 0.25).float()
    masks[0] = 0.0
    return {
        "view": torch.randint(0, 256, (T + 1, N, 3, SIZE, SIZE), generator=g, dtype=torch.uint8),
        "target": torch.randint(0, 256, (T + 1, N, 3, SIZE, SIZE), generator=g, dtype=torch.uint8),
        "masks": masks,
        "actions": torch.randint(0, 5, (T, N), generator=g),
        "log_probs": -1.6 + 0.2 * torch.randn(T, N, generator=g),
        "values": torch.randn(T + 1, N, generator=g),
        "rewards": torch.randn(T, N, generator=g),
    }


def ppo_step(envs: slice) -> tuple[dict[str, torch.Tensor], dict[str, float]]:
    """Weights and stats after one PPO update (2 epochs, 1 mini-batch) on ``fixed_rollout()[:, envs]``."""
    from findview_baselines.rl.policy import build_policy
    from findview_baselines.config import PPOAgentConfig
    from findview_baselines.rl.ppo import PPO, PPOConfig
    from findview_baselines.rl.storage import RolloutStorage

    data = fixed_rollout()
    torch.manual_seed(0)
    policy = build_policy(PPOAgentConfig(hidden_size=HIDDEN), SIZE, SIZE)
    cfg = PPOConfig(rollout_steps=T_STEPS, ppo_epochs=2, num_mini_batches=1, lr=1e-3)
    ppo = PPO(policy, cfg)
    n = len(range(N_ALL)[envs])
    storage = RolloutStorage(T_STEPS, n, SIZE, SIZE, HIDDEN)
    for name in ("view", "target", "masks", "actions", "log_probs", "values", "rewards"):
        getattr(storage, name).copy_(data[name][:, envs])
    storage.hidden.zero_()
    storage.compute_returns(data["values"][T_STEPS, envs], cfg.gamma, cfg.gae_lambda)
    stats = ppo.update(storage, torch.Generator().manual_seed(0))
    return {k: v.detach().clone() for k, v in policy.state_dict().items()}, stats


def fixed_initial_weights() -> dict[str, torch.Tensor]:
    from findview_baselines.config import PPOAgentConfig
    from findview_baselines.rl.policy import build_policy

    torch.manual_seed(0)
    return build_policy(PPOAgentConfig(hidden_size=HIDDEN), SIZE, SIZE).state_dict()


def test_advantage_statistics_and_helpers_are_plain_without_torchrun() -> None:
    """Outside a job the helpers are the single-process operations (the non-distributed path is unchanged)."""
    from findview_baselines.rl import distributed

    x = torch.randn(5, 3)
    mean, std = distributed.mean_std(x)
    assert torch.equal(mean, x.mean()) and torch.equal(std, x.std())
    stats = {"policy_loss": 1.0, "episodes": [{"eps": 3}]}
    assert distributed.reduce_stats(stats) is stats
    assert distributed.shard(list(range(7)), 1, 3) == [1, 4] and distributed.shard([1, 2], 0, 1) == [1, 2]
    with pytest.raises(ValueError, match="2 train images cannot be shared by 3 ranks"):
        distributed.shard([1, 2], 0, 3)
    assert distributed.global_steps(16) == 16 and distributed.world_size() == 1 and distributed.is_main()


def test_distributed_without_torchrun_is_a_one_line_error(monkeypatch: pytest.MonkeyPatch) -> None:
    from findview_baselines.rl import distributed

    for key in distributed.TORCHRUN_VARS:
        monkeypatch.delenv(key, raising=False)
    with pytest.raises(ValueError, match=r"trainer.distributed=true but RANK, WORLD_SIZE, .* not set: start the run "
                                         r"with torchrun"):
        distributed.setup("auto", "cpu")


def test_sigusr1_stops_a_single_process_run_like_sigterm(
    make_cfg, tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    """SLURM's warning signal: SIGUSR1 mid-rollout abandons the update, writes latest.pth and raises
    Interrupted(SIGUSR1) (exit 138 in the tools), without torchrun too."""
    from findview.task.env import FindViewEnv
    from findview_baselines.cli import Interrupted
    from findview_baselines.training import train

    original, calls = FindViewEnv.step, {"n": 0}

    def step(self, actions):
        calls["n"] += 1
        if calls["n"] == 8 + 3:  # inside update 2's rollout (8 steps per update)
            os.kill(os.getpid(), signal.SIGUSR1)
        return original(self, actions)

    monkeypatch.setattr(FindViewEnv, "step", step)
    before = signal.getsignal(signal.SIGUSR1)
    with pytest.raises(Interrupted) as info:
        train(make_cfg(**{"trainer.val_interval": 0, "trainer.val_at_end": False}), tmp_path)
    assert info.value.signum == signal.SIGUSR1 and "SIGUSR1: stopped at update 1" in str(info.value)
    assert load(tmp_path / "checkpoints" / "latest.pth")["update"] == 1
    assert signal.getsignal(signal.SIGUSR1) == before  # the previous handler is back


# --------------------------------------------------------------------------------------------------
# Two spawned ranks (one start-up for both checks): the PPO update, and the run loop's exact resume
# --------------------------------------------------------------------------------------------------


def _cfg(panorama_folder: Path, dataset_out: Path, **overrides: Any):
    tiny = {
        "sim.height": SIZE, "sim.width": SIZE, "trainer.distributed": True, "trainer.num_updates": 4,
        "trainer.val_interval": 2, "trainer.checkpoint_interval": 1, "trainer.dist_timeout_min": 2,
    }
    return make_config(panorama_folder, dataset_out, **{**tiny, **overrides})


def _two_rank_worker(rank: int, world: int, port: int, out: Path, panorama_folder: Path, dataset_out: Path) -> None:
    import findview_baselines.training.run as run
    from findview_baselines.rl import distributed
    from findview_baselines.training import train

    learn = run.learn

    def keep_weights(ctx: Any, *args: Any) -> None:  # this rank's final weights, per run folder
        learn(ctx, *args)
        torch.save(ctx.algo.policy.state_dict(), out / f"weights_{ctx.run_dir.name}_{rank}.pt")

    run.learn = keep_weights
    _join(rank, world, port)
    distributed.setup("gloo", "cpu", timeout_min=2)
    try:
        # 1. one PPO update on this rank's half of a fixed rollout
        per = N_ALL // world
        weights, stats = ppo_step(slice(rank * per, (rank + 1) * per))
        torch.save({"weights": weights, "stats": distributed.reduce_stats(stats)}, out / f"rank{rank}.pt")
        # 2. the run loop: 4 updates in one go; 2 updates, then a resume for 2 more
        train(_cfg(panorama_folder, dataset_out), out / "full")
        train(_cfg(panorama_folder, dataset_out, **{"trainer.stop_after": 2}), out / "split")
        torch.save(load(out / "split" / "checkpoints" / "latest.pth")["update"], out / f"split_at_{rank}.pt")
        train(_cfg(panorama_folder, dataset_out), out / "split")
        # 3. DAgger goes the same way
        quick = {"trainer.num_updates": 2, "trainer.val_interval": 0, "trainer.val_at_end": False}
        train(_cfg(panorama_folder, dataset_out, **{"trainer": "dagger", "trainer.dagger.rollout_steps": 16, **quick}),
              out / "dagger")
        # 4. straggler preemption: rank 1 steps slowly, so rank 0's finished rollout cuts rank 1's short
        if rank == 1:
            from findview.task.env import FindViewEnv

            step = FindViewEnv.step
            FindViewEnv.step = lambda self, actions: (time.sleep(0.4), step(self, actions))[1]  # type: ignore[method-assign]
        train(_cfg(panorama_folder, dataset_out, **{"trainer.preempt_fraction": 0.5, **quick}), out / "preempt")
    finally:
        distributed.teardown()


@pytest.fixture(scope="module")
def two_ranks(panorama_folder: Path, dataset_out: Path, tmp_path_factory: pytest.TempPathFactory) -> Path:
    out = tmp_path_factory.mktemp("two_ranks")
    spawn(_two_rank_worker, out, panorama_folder, dataset_out)
    return out


def test_two_ranks_match_each_other_and_one_process_on_the_combined_batch(two_ranks: Path) -> None:
    """One PPO update (2 epochs) on fixed rollouts: both ranks hold bit-identical weights afterwards, equal
    (float tolerance) to one process updating on both ranks' environments together; so are the stats."""
    r0, r1 = (torch.load(two_ranks / f"rank{r}.pt", weights_only=True) for r in (0, 1))
    reference, ref_stats = ppo_step(slice(0, N_ALL))  # one process, all 4 environments
    initial = fixed_initial_weights()
    moved = 0
    for name, ref in reference.items():
        assert torch.equal(r0["weights"][name], r1["weights"][name]), name
        torch.testing.assert_close(r0["weights"][name], ref, rtol=1e-4, atol=1e-6, msg=name)
        moved += int(not torch.equal(ref, initial[name]))
    assert moved > 0  # the update changed the weights
    # the losses are batch means: the mean of the two ranks' means is the whole batch's mean
    for key in ("policy_loss", "value_loss", "entropy", "approx_kl", "grad_norm"):
        assert r0["stats"][key] == pytest.approx(ref_stats[key], rel=1e-4, abs=1e-6), key


def test_two_rank_resume_gives_the_weights_of_one_go(two_ranks: Path) -> None:
    """4 updates on 2 ranks in one go == 2, then a resume for 2 more (same number of ranks): the same
    weights, every rank's environments where they were, disjoint image shards, one validation record."""
    assert torch.load(two_ranks / "split_at_0.pt") == torch.load(two_ranks / "split_at_1.pt") == 2
    full, split = (load(two_ranks / d / "checkpoints" / "latest.pth") for d in ("full", "split"))
    assert full["update"] == split["update"] == 4
    assert full["env_steps"] == split["env_steps"] == 4 * 8 * 2 * 2  # updates x steps x envs x ranks
    for name, tensor in full["policy"].items():
        assert torch.equal(tensor, split["policy"][name]), name
    assert full["trainer"]["world_size"] == 2 and len(full["trainer"]["rank_states"]) == 1
    rank1 = (full["trainer"]["rank_states"][0], split["trainer"]["rank_states"][0])
    for a, b in ((full["trainer"], split["trainer"]), rank1):
        assert a["env"]["episodes"] == b["env"]["episodes"]
        assert torch.equal(a["storage"]["hidden"], b["storage"]["hidden"])
    images = [{e["image"] for e in state["env"]["episodes"] if e} for state in (full["trainer"], rank1[0])]
    assert images[0] and images[1] and not images[0] & images[1]
    assert full["val"] == split["val"] and set(full["val"]) >= {"easy", "medium", "hard"}


@pytest.mark.parametrize("run", ["full", "dagger", "preempt"])
def test_every_rank_ends_with_rank_0s_weights(two_ranks: Path, run: str) -> None:
    """PPO and DAgger through the run loop: the ranks started from different seeds and saw different
    episodes, yet hold identical weights (broadcast once, then averaged gradients): rank 0's, as saved."""
    w0, w1 = (torch.load(two_ranks / f"weights_{run}_{r}.pt", weights_only=True) for r in (0, 1))
    saved = load(two_ranks / run / "checkpoints" / "latest.pth")
    assert saved["update"] == (4 if run == "full" else 2) and saved["trainer"]["world_size"] == 2
    if run == "preempt":  # rank 0: 2 x 8 steps x 2 envs; the slow rank 1: at least 2 (25%), fewer than 8 steps
        assert 2 * 8 * 2 + 2 * 2 * 2 <= saved["env_steps"] < 2 * 8 * 2 * 2
    for name in w0:
        assert torch.equal(w0[name], w1[name]) and torch.equal(w0[name], saved["policy"][name]), name


# --------------------------------------------------------------------------------------------------
# torchrun + tools/train.py: a signal to one rank stops both; resume with one process
# --------------------------------------------------------------------------------------------------


def _children(pid: int) -> list[int]:
    path = Path(f"/proc/{pid}/task/{pid}/children")
    return [int(p) for p in path.read_text().split()] if path.is_file() else []


def _rank_of(pid: int) -> int | None:
    try:
        env = Path(f"/proc/{pid}/environ").read_bytes().split(b"\0")
    except OSError:
        return None
    for item in env:
        if item.startswith(b"RANK="):
            return int(item[5:])
    return None


def _tool_args(panorama_folder: Path, dataset_out: Path, run_dir: Path, *extra: str) -> list[str]:
    return [
        str(REPO / "tools" / "train.py"), "dataset=folder", f"dataset.root={panorama_folder}",
        f"dataset.out_dir={dataset_out}", "dataset.name=testfolder", f"sim.height={SIZE}", f"sim.width={SIZE}",
        "sim.device=cpu", "sim.prefetch_workers=0", "task.max_steps=300", "agent.hidden_size=32",
        "trainer.ppo.rollout_steps=8", "trainer.ppo.ppo_epochs=2", "trainer.num_envs=2", "trainer.val_interval=0",
        "trainer.val_at_end=false", "trainer.log_interval=1", "trainer.checkpoint_interval=1",
        "trainer.progress=false", "trainer.torch_threads=1", "trainer.num_updates=100000",
        f"hydra.run.dir={run_dir}", *extra,
    ]


@pytest.mark.skipif(not Path(f"/proc/{os.getpid()}/task").is_dir(), reason="needs /proc to find rank 1's pid")
def test_sigterm_to_one_rank_stops_both_and_one_process_resumes(
    panorama_folder: Path, dataset_out: Path, tmp_path: Path, caplog: pytest.LogCaptureFixture
) -> None:
    """torchrun + tools/train.py with 2 gloo ranks: SIGTERM to rank 1 alone makes both write / wait for
    latest.pth and exit 143 at the same update; one process without torchrun then resumes from it."""
    run_dir = tmp_path / "run"
    env = {**os.environ, "PYTHONPATH": str(REPO), "OMP_NUM_THREADS": "1"}
    cmd = [sys.executable, "-m", "torch.distributed.run", "--standalone", "--nproc_per_node=2",
           *_tool_args(panorama_folder, dataset_out, run_dir, "trainer.distributed=true")]
    proc = subprocess.Popen(cmd, stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True, env=env)
    latest = run_dir / "checkpoints" / "latest.pth"
    try:
        deadline = time.time() + 120
        while not latest.is_file() and time.time() < deadline and proc.poll() is None:
            time.sleep(0.3)
        assert latest.is_file(), proc.stdout.read() if proc.poll() is not None else "no checkpoint in time"
        (rank1,) = [p for p in _children(proc.pid) if _rank_of(p) == 1]
        os.kill(rank1, signal.SIGTERM)  # one rank only
        out, _ = proc.communicate(timeout=120)
    finally:
        if proc.poll() is None:
            proc.kill()
    saved = load(latest)
    update = saved["update"]
    assert saved["trainer"]["world_size"] == 2 and len(saved["trainer"]["rank_states"]) == 1
    # both ranks stopped on their own with the SIGTERM status at the same update (torchrun reports exit 143)
    assert out.count(f"train: SIGTERM: stopped at update {update}; resume state written to {latest}") == 2, out[-3000:]
    assert "exitcode  : 143" in out and "exitcode  : -" not in out, out[-3000:]

    # the same folder, one process, no torchrun: continues from the saved update (re-sharded, re-seeded)
    from findview_baselines.training import train

    overrides = dict(a.split("=", 1) for a in _tool_args(panorama_folder, dataset_out, run_dir)[1:] if "hydra" not in a)
    with caplog.at_level(logging.INFO, logger="findview_baselines.training.run"):
        result = train(make_config(panorama_folder, dataset_out, **{**overrides, "trainer.stop_after": 1}), run_dir)
    assert result.updates == update + 1 and not result.completed
    assert f"resumed {run_dir} at update {update}" in caplog.text and "saved by 2 rank(s), now 1" in caplog.text
    after = load(latest)
    assert after["update"] == update + 1 and "world_size" not in after["trainer"]
    assert after["env_steps"] == saved["env_steps"] + 8 * 2  # one update of one rank
