"""CPU load immunity: every CPU path timed alone and next to a competing CPU load, and the slowdown.

    python benchmarks/bench_load.py                      # both import orders, the library's thread policy
    python benchmarks/bench_load.py --order torch --load 2 --rounds 3
    OMP_WAIT_POLICY=ACTIVE python benchmarks/bench_load.py --torch-threads 2    # a user's own settings

Import orders (``--order``, default ``both``: one fresh process each): ``findview`` imports findview
before torch (its environment defaults, ``OMP_WAIT_POLICY=PASSIVE`` and ``OPENBLAS_NUM_THREADS=1``, reach
the runtimes); ``torch`` imports torch, numpy and cv2 first, as most scripts and notebooks do (those
defaults come too late). Neither calls ``configure_threads`` unless ``--torch-threads`` is given: the
thread counts are the ones the library's scopes choose (``findview/runtime.py``).

Paths (each a fixed amount of work, timed in seconds):

- ``control``: a pure Python loop (no torch, no OpenCV): the slowdown that the scheduler's fair share
  alone gives, the floor for every other path;
- ``first_reset``: a fresh simulator + ``FindViewEnv`` of 16 envs at 256x256, first ``reset()``
  (panoramas decoded beforehand: this is the per-pitch grid build plus 32 renders);
- ``env_step``: 16 envs at 256x256, random moves (env steps/s);
- ``agent:<name>``: one env at 256x256, the agent's ``act`` plus ``env.step`` per decision, the way
  ``tools/eval.py`` plays (decisions/s), for the agents random, orb, sift, rotation;
- ``ppo_update``: a PPO rollout + update built from ``build_policy`` (early fusion, GRU 512),
  ``PPO`` and ``RolloutStorage`` (env steps/s, ``--ppo-size`` views, ``--ppo-envs`` x ``--ppo-steps``);
- ``dagger_update``: one ``DAggerTrainer.train_update`` of the CPU recipe's network (``robust``, 64x64, 16 envs,
  the default ``trainer.dagger`` settings) (env steps/s).

The competing load is ``--load`` processes running ``while True: pass`` (default 2, one per core of a
2-core machine), started as another job would be: in their own session (``--same-session`` starts
them in this one; see :class:`CpuLoad` about Linux's per-session scheduling). Quiet and loaded runs
alternate ``--rounds`` times and the median of each is reported. ``slowdown = loaded time / quiet
time``; the last column divides it by the ``control`` path's (1.00: the path loses its fair share of
the CPU and nothing more). Competing thread by thread, a single-threaded path sharing 2 cores with 2
busy processes gets 2/3 of a core, so 1.5x is the floor on an otherwise idle machine; the goal is no
path above 2x. Panoramas: the SUN360 images of ``$FINDVIEW_SUN360_MINI`` (or
``$FINDVIEW_SUN360_MINI``), else procedural ones.
"""

from __future__ import annotations

import argparse
import os
import statistics
import subprocess
import sys
import tempfile
import time
from collections.abc import Callable
from pathlib import Path

# findview is imported in main(), after torch / numpy / cv2 when --order torch (see the module docstring)

REPO = Path(__file__).resolve().parents[1]
AGENTS = ("random", "orb", "sift", "rotation")


def panorama_files(tmp: Path, n: int = 16) -> list[str]:
    """sun360_mini panoramas if present, else ``n`` procedural 1024x512 ones written to ``tmp``."""
    mini = Path(os.environ.get("FINDVIEW_SUN360_MINI", "") or "/nonexistent")  # the sun360_mini folder, if you have it
    files = sorted(mini.rglob("*.jpg")) if mini.is_dir() else []
    if files:
        return [str(f) for f in files]
    import cv2

    from findview.dataset import generate_panorama

    out = []
    for i in range(n):
        path = tmp / f"synth_{i}.png"
        cv2.imwrite(str(path), cv2.cvtColor(generate_panorama(i, ("room", "landscape", "village")[i % 3], 1024), cv2.COLOR_RGB2BGR))
        out.append(str(path))
    return out


def episodes(files: list[str], n: int, seed: int = 0):
    import numpy as np

    from findview.episode import Episode

    rng = np.random.default_rng(seed)
    return [
        Episode(str(i), files[i % len(files)], int(rng.integers(-60, 61)), int(rng.integers(-179, 181)),
                int(rng.integers(-60, 61)), int(rng.integers(-179, 181)))
        for i in range(n)
    ]


def make_env(files: list[str], num_envs: int, size: int, n_episodes: int = 4000, max_steps: int = 5000, bank=None):
    from findview.sim import PanoramaBank, Simulator
    from findview.task import FindViewEnv, StaticEpisodeSource

    bank = bank or PanoramaBank("cpu", 1024, min_slots=num_envs, max_panoramas=len(files), prefetch_workers=0)
    sim = Simulator(bank, 90, size, size)
    return FindViewEnv(sim, StaticEpisodeSource(episodes(files, n_episodes)), num_envs, max_steps=max_steps, prefetch=0)


# ------------------------------------------------------------------------------------------- paths
def path_control(n: int = 2_000_000) -> Callable[[], tuple[float, float]]:
    """Pure Python arithmetic, one thread, no torch / OpenCV: the scheduler's fair share (the floor)."""

    def run() -> tuple[float, float]:
        t = time.perf_counter()
        acc = 0
        for i in range(n):
            acc += i & 7
        return n / 1e6, time.perf_counter() - t

    return run


def path_first_reset(files: list[str]) -> Callable[[], tuple[float, float]]:
    from findview.sim import PanoramaBank

    bank = PanoramaBank("cpu", 1024, min_slots=16, max_panoramas=len(files), prefetch_workers=0)
    for f in files[:16]:
        bank.release(bank.acquire(f))  # decoded once, outside the timing
    eps = episodes(files[:16], 16)

    def run() -> tuple[float, float]:
        from findview.sim import Simulator
        from findview.task import FindViewEnv, StaticEpisodeSource

        t = time.perf_counter()
        env = FindViewEnv(Simulator(bank, 90, 256, 256), StaticEpisodeSource(eps), 16, prefetch=0)
        env.reset()
        dt = time.perf_counter() - t
        env.close()
        return 1.0, dt

    return run


def path_env_step(files: list[str], steps: int) -> Callable[[], tuple[float, float]]:
    import torch

    env = make_env(files, 16, 256)
    env.reset()
    gen = torch.Generator().manual_seed(0)
    acts = [torch.randint(0, 4, (16,), generator=gen) for _ in range(64)]
    for i in range(30):  # warm: every grid the moves reach, the bank
        env.step(acts[i % 64])
    env.sim.build_all_grids(env.sim.bank.slots.shape[1])

    def run() -> tuple[float, float]:
        t = time.perf_counter()
        for i in range(steps):
            env.step(acts[i % 64])
        return steps * 16.0, time.perf_counter() - t

    return run


def path_agent(files: list[str], name: str, decisions: int) -> Callable[[], tuple[float, float]]:
    from findview_baselines.agents import make_agent

    env = make_env(files, 1, 256, max_steps=300)
    agent = make_agent(name, None, 1, "cpu", 0)
    state = {"obs": env.reset()}

    def play(n: int) -> None:
        obs = state["obs"]
        for _ in range(n):
            if bool(env.new_episode[0]):
                agent.reset([0], [env.episodes[0]])
            actions = agent.act(obs)
            obs, _, _, _ = env.step(actions)
        state["obs"] = obs

    play(20)  # warm: agent pools, target features

    def run() -> tuple[float, float]:
        t = time.perf_counter()
        play(decisions)
        return float(decisions), time.perf_counter() - t

    return run


def path_ppo(files: list[str], size: int, num_envs: int, steps: int) -> Callable[[], tuple[float, float]]:
    import torch

    from findview_baselines.rl.policy import build_policy
    from findview_baselines.config import PPOAgentConfig
    from findview_baselines.rl.ppo import PPO, PPOConfig
    from findview_baselines.rl.storage import RolloutStorage

    torch.manual_seed(0)
    torch.distributions.Distribution.set_default_validate_args(False)
    env = make_env(files, num_envs, size)
    policy = build_policy(PPOAgentConfig(hidden_size=512), size, size)
    cfg = PPOConfig(rollout_steps=steps, ppo_epochs=2)
    ppo = PPO(policy, cfg)
    storage = RolloutStorage(steps, num_envs, size, size, 512)
    storage.set_initial(env.reset())

    def update() -> None:
        for _ in range(steps):
            obs, hidden, masks = storage.current()
            with torch.no_grad():
                actions, log_probs, values, new_hidden = policy.act(obs, hidden, masks)
            next_obs, rewards, _, _ = env.step(actions)
            storage.insert(next_obs, new_hidden, actions, log_probs, values, rewards.float(), (~env.new_episode).float())
        with torch.no_grad():
            next_value = policy.get_value(*storage.current())
        storage.compute_returns(next_value, cfg.gamma, cfg.gae_lambda)
        ppo.update(storage)
        storage.after_update()

    update()  # warm-up

    def run() -> tuple[float, float]:
        t = time.perf_counter()
        update()
        return float(steps * num_envs), time.perf_counter() - t

    return run


def path_dagger(files: list[str], size: int, num_envs: int) -> Callable[[], tuple[float, float]]:
    """One DAgger update (rollout with the oracle's labels + training on the buffer) of the shipped CPU recipe's
    network (``robust``, hidden 128, fine cost pyramid 2 x 4 levels) at ``size`` x ``size``."""
    import torch

    from findview_baselines.config import PPOAgentConfig
    from findview_baselines.rl.dagger import DAggerTrainer
    from findview_baselines.rl.dagger_config import DAggerConfig
    from findview_baselines.rl.policy import build_policy

    torch.manual_seed(0)
    env = make_env(files, num_envs, size)
    policy = build_policy(PPOAgentConfig(variant="robust", hidden_size=128, fine_shifts=2, fine_scales=4), size, size)
    trainer = DAggerTrainer(env, policy, DAggerConfig(), total_updates=1000)
    trainer.start()
    trainer.train_update()  # warm-up

    def run() -> tuple[float, float]:
        t = time.perf_counter()
        trainer.train_update()
        return float(trainer.steps_per_update), time.perf_counter() - t

    return run


# -------------------------------------------------------------------------------------------- load
class CpuLoad:
    """``n`` processes spinning ``while True: pass`` (started and stopped by this object only).

    ``new_session``: start them in their own session, like another job on the machine. On Linux with
    ``kernel.sched_autogroup_enabled=1`` the scheduler shares the CPU fairly between sessions first, so
    the load then takes the cores this process does not use; in the same session (or without
    autogroup) it competes thread by thread.
    """

    def __init__(self, n: int, new_session: bool = True) -> None:
        self.n = n
        self.new_session = new_session
        self.procs: list[subprocess.Popen] = []

    def __enter__(self) -> "CpuLoad":
        self.procs = [
            subprocess.Popen([sys.executable, "-c", "while True: pass"], start_new_session=self.new_session)
            for _ in range(self.n)
        ]
        time.sleep(0.3)  # let them get scheduled
        return self

    def __exit__(self, *exc) -> None:
        for p in self.procs:
            p.terminate()
        for p in self.procs:
            try:
                p.wait(timeout=5)
            except subprocess.TimeoutExpired:
                p.kill()
                p.wait()
        self.procs = []


def run_both_orders(argv: list[str]) -> None:
    """Run this script once per import order (fresh processes) and print both tables, then each order's worst."""
    worst: dict[str, str] = {}
    for order in ORDERS:
        proc = subprocess.run([sys.executable, __file__, *argv, "--order", order], capture_output=True, text=True)
        sys.stdout.write(f"\n## import order: {order} first\n\n{proc.stdout}")
        if proc.returncode != 0:
            sys.stderr.write(proc.stderr)
            raise SystemExit(f"bench_load.py --order {order} failed (exit {proc.returncode})")
        lines = [line for line in proc.stdout.splitlines() if line.startswith("worst slowdown")]
        worst[order] = lines[-1] if lines else "(no result)"
    print("\n" + "\n".join(f"{order} first: {line}" for order, line in worst.items()))


#: import orders: ``findview`` (findview, then torch), ``torch`` (torch, numpy and cv2 first, as most scripts do)
ORDERS = ("findview", "torch")


def main(argv: list[str] | None = None) -> dict[str, dict[str, float]]:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--order", choices=(*ORDERS, "both"), default="both",
                    help="import order of this process: findview first, torch (+ numpy, cv2) first, or both "
                         "(one fresh process each; default)")
    ap.add_argument("--load", type=int, default=2, help="competing busy-loop processes (default 2)")
    ap.add_argument("--rounds", type=int, default=2, help="quiet / loaded alternations (default 2)")
    ap.add_argument("--same-session", action="store_true", help="run the load in this process's session (see CpuLoad)")
    ap.add_argument("--torch-threads", type=int, default=None,
                    help="call configure_threads(n) first (default: not called; the library's scopes decide)")
    ap.add_argument("--opencv-threads", type=int, default=None, help="cv2.setNumThreads (default: left as is)")
    ap.add_argument("--paths", nargs="+", default=None, help="subset: control first_reset env_step agent:<name> ppo_update dagger_update")
    ap.add_argument("--env-steps", type=int, default=40, help="env_step: steps of 16 envs per timing")
    ap.add_argument("--decisions", type=int, default=60, help="agents: decisions per timing")
    ap.add_argument("--ppo-size", type=int, default=128, help="ppo_update: view size (square)")
    ap.add_argument("--ppo-envs", type=int, default=4)
    ap.add_argument("--ppo-steps", type=int, default=16)
    argv = sys.argv[1:] if argv is None else argv
    args = ap.parse_args(argv)
    if args.order == "both":
        run_both_orders(argv)
        return {}
    if args.order == "torch":
        import cv2  # noqa: F401
        import numpy  # noqa: F401
        import torch  # noqa: F401
    import findview  # noqa: F401
    from findview.runtime import blas_threads, compute_threads, configure_threads, wait_policy_effective

    import cv2
    import torch

    if args.torch_threads is not None or args.opencv_threads is not None:
        configure_threads(args.torch_threads, args.opencv_threads)
    autogroup = Path("/proc/sys/kernel/sched_autogroup_enabled")
    autogroup = autogroup.read_text().strip() if autogroup.is_file() else "n/a"
    print(
        f"# CPU load immunity, {args.order} imported first: {os.cpu_count()} cores, torch {torch.__version__}, "
        f"torch threads {torch.get_num_threads()} (heavy work: {compute_threads()}), OpenBLAS threads "
        f"{blas_threads() or 'n/a'}, OMP_WAIT_POLICY={os.environ.get('OMP_WAIT_POLICY', '(unset)')} (effective: "
        f"{wait_policy_effective()}), {cv2.getNumThreads()} OpenCV thread(s), load = {args.load} x 'while True: pass' "
        f"in {'this' if args.same_session else 'its own'} session (sched_autogroup_enabled={autogroup}), "
        f"{args.rounds} rounds"
    )
    with tempfile.TemporaryDirectory() as tmp:
        files = panorama_files(Path(tmp))
        builders: dict[str, Callable[[], Callable[[], tuple[float, float]]]] = {
            "control": path_control,
            "first_reset": lambda: path_first_reset(files),
            "env_step": lambda: path_env_step(files, args.env_steps),
            **{f"agent:{a}": (lambda a=a: path_agent(files, a, args.decisions)) for a in AGENTS},
            "ppo_update": lambda: path_ppo(files, args.ppo_size, args.ppo_envs, args.ppo_steps),
            "dagger_update": lambda: path_dagger(files, 64, 16),
        }
        units = {"control": "M loop iterations/s", "first_reset": "s", "env_step": "env steps/s", "ppo_update": "env steps/s",
                 "dagger_update": "env steps/s"}
        wanted = args.paths or list(builders)
        unknown = [p for p in wanted if p not in builders]
        if unknown:
            raise SystemExit(f"unknown path {unknown[0]!r}; valid: {', '.join(builders)}")
        results: dict[str, dict[str, float]] = {}
        print("| path | quiet | loaded | unit | slowdown | slowdown / control's |")
        print("|---|---|---|---|---|---|")
        for name in wanted:
            run = builders[name]()
            quiet, loaded = [], []
            work = 1.0
            for _ in range(args.rounds):
                work, dt = run()
                quiet.append(dt)
                with CpuLoad(args.load, new_session=not args.same_session):
                    work, dt = run()
                loaded.append(dt)
            q, lo = statistics.median(quiet), statistics.median(loaded)
            unit = units.get(name, "decisions/s")
            fmt = (lambda t: f"{t:.3f}") if unit == "s" else (lambda t: f"{work / t:.1f}")
            results[name] = {"quiet_s": q, "loaded_s": lo, "slowdown": lo / q, "work": work}
            flag = "" if lo / q <= 2.0 else " (> 2x)"
            rel = f"{(lo / q) / results['control']['slowdown']:.2f}" if "control" in results else "-"
            print(f"| {name} | {fmt(q)} | {fmt(lo)} | {unit} | {lo / q:.2f}x{flag} | {rel} |", flush=True)
    others = {k: v for k, v in results.items() if k != "control"}
    if others:
        worst_name = max(others, key=lambda k: others[k]["slowdown"])
        line = f"\nworst slowdown: {others[worst_name]['slowdown']:.2f}x ({worst_name}; goal: at most 2x)"
        if "control" in results:
            line += f"; pure-Python control: {results['control']['slowdown']:.2f}x"
        print(line)
    return results


if __name__ == "__main__":
    main()
