"""One row of ``benchmarks/bench_peers.py`` on findview (this repository), through its public API only.

    python benchmarks/peers/ours.py --row orb --order torch --panoramas DIR
    python benchmarks/peers/ours.py --row ppo --order findview --updates 1

Prints one JSON line ``{"row", "value", "unit", ...}``. ``--order`` is the import order of the script:
``torch`` imports ``torch, cv2, numpy`` before anything of findview (as most user scripts do), ``findview``
imports ``findview`` first (which sets ``OMP_WAIT_POLICY=PASSIVE`` / ``OPENBLAS_NUM_THREADS=1`` while
torch / numpy are not loaded yet). Neither calls ``findview.runtime.configure_threads`` nor
``torch.set_num_threads``: the row measures what the library gives as it is. No network access.

- ``orb`` / ``sift``: ``findview.build.build_static_env`` (1 env, the same episodes as the authors' side,
  T = 300) + ``findview_baselines.agents.make_agent(name)`` (the schema's default config), the loop of
  ``tools/eval.py``: ``agent.reset`` for a new episode, ``agent.act`` + ``env.step``; decisions/s.
- ``ppo``: the training path of ``tools/train.py``: ``EpisodeSampler`` + ``build_sampled_env`` (16 envs),
  ``build_policy(PPOAgentConfig(variant="goal_encoder", hidden_size=512), 256, 256)`` (28.18M parameters),
  ``PPOTrainer`` with ``PPOConfig(rollout_steps=16, ppo_epochs=4, num_mini_batches=1)``; env steps/s of
  ``train_update`` (rollout + update) over ``--updates`` updates after one warm-up update, with the
  trainer's own timings for the env / network split.
- ``env16`` / ``env1``: ``EpisodeSampler`` + ``build_sampled_env`` with 16 / 1 envs, random moves; env steps/s.
- ``reset16``: seconds for ``EpisodeSampler`` + ``build_sampled_env`` (16 envs, panorama bank, simulator) and
  the first ``env.reset()`` (panoramas decoded in it: nothing is loaded beforehand).
"""

from __future__ import annotations

import os
import sys

_THREAD_VARS = ("OMP_WAIT_POLICY", "OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS")
ENV_AT_START = {k: os.environ.get(k) for k in _THREAD_VARS}  # before any import below


def _order(argv: list[str]) -> str:
    for i, a in enumerate(argv):
        if a == "--order" and i + 1 < len(argv):
            return argv[i + 1]
        if a.startswith("--order="):
            return a.split("=", 1)[1]
    return "torch"


ORDER = _order(sys.argv[1:])
if ORDER == "torch":
    import torch  # noqa: F401
    import cv2  # noqa: F401
    import numpy  # noqa: F401

    import findview  # noqa: F401
elif ORDER == "findview":
    import findview  # noqa: F401

    import torch  # noqa: F401
    import cv2  # noqa: F401
    import numpy  # noqa: F401

import argparse  # noqa: E402
from pathlib import Path  # noqa: E402

sys.path.insert(0, str(Path(__file__).resolve().parent))
from peerlib import (  # noqa: E402
    AGENT_MAX_STEPS,
    FOV,
    PITCH_BOUND,
    VIEW,
    Timer,
    emit,
    episode_tuples,
    panorama_files,
    rate,
    thread_env,
)

ENV_AFTER_IMPORTS = thread_env()  # what `import findview` set (it sets only variables the user has not)


def _sim_cfg():
    from findview.config import SimConfig

    return SimConfig(fov=FOV, height=VIEW, width=VIEW, device="cpu")


def _sampled_env(files: list[str], num_envs: int):
    from findview.build import build_sampled_env
    from findview.config import TaskConfig
    from findview.dataset import EpisodeSampler

    task = TaskConfig(pitch_bound=PITCH_BOUND)
    sampler = EpisodeSampler(files, FOV, seed=0, pitch_bound=task.pitch_bound, max_steps=task.max_steps)
    return build_sampled_env(_sim_cfg(), task, sampler, num_envs)


def _threads() -> dict:
    return {"torch_threads": torch.get_num_threads(), "cv2_threads": cv2.getNumThreads()}


# -------------------------------------------------------------------------------------------------- rows
def row_agent(name: str, files: list[str], args) -> dict:
    from findview.build import build_static_env
    from findview.config import TaskConfig
    from findview.episode import Episode
    from findview_baselines.agents import make_agent

    eps = [Episode(str(i), img, ip, iy, tp, ty) for i, (img, ip, iy, tp, ty) in enumerate(episode_tuples(files, 4000))]
    env = build_static_env(_sim_cfg(), TaskConfig(max_steps=AGENT_MAX_STEPS, pitch_bound=PITCH_BOUND), eps, 1)
    agent = make_agent(name, None, 1, "cpu", 0)
    state = {"obs": env.reset(), "episodes": 0}

    def play(n: int) -> None:
        obs = state["obs"]
        for _ in range(n):
            if bool(env.new_episode[0]):
                agent.reset([0], [env.episodes[0]])
                state["episodes"] += 1
            actions = agent.act(obs)
            obs, _, _, _ = env.step(actions)
        state["obs"] = obs

    play(args.warmup_decisions)
    with Timer() as t:
        play(args.decisions)
    env.close()
    return {"value": rate(args.decisions, t.s), "seconds": t.s, "decisions": args.decisions,
            "episodes_started": state["episodes"], "classes": f"build_static_env + make_agent({name!r})", **_threads()}


def row_env(files: list[str], num_envs: int, steps: int, args) -> dict:
    env = _sampled_env(files, num_envs)
    env.reset()
    gen = torch.Generator().manual_seed(0)
    acts = [torch.randint(0, 4, (num_envs,), generator=gen) for _ in range(64)]  # up, down, left, right
    for i in range(args.warmup_steps):
        env.step(acts[i % 64])
    with Timer() as t:
        for i in range(steps):
            env.step(acts[i % 64])
    env.close()
    return {"value": rate(steps * num_envs, t.s), "seconds": t.s, "steps": steps, "num_envs": num_envs,
            "classes": f"EpisodeSampler + build_sampled_env ({type(env).__name__}, batched)", **_threads()}


def row_reset16(files: list[str], args) -> dict:
    import findview.build  # noqa: F401  (modules imported before the clock starts, as on their side)
    import findview.dataset  # noqa: F401
    import findview.sim  # noqa: F401
    import findview.task  # noqa: F401

    with Timer() as t:
        env = _sampled_env(files, 16)
        env.reset()
    env.close()
    return {"value": t.s, "seconds": t.s, "num_envs": 16,
            "classes": "EpisodeSampler + build_sampled_env + reset (panoramas decoded in it)", **_threads()}


def row_ppo(files: list[str], args) -> dict:
    from findview_baselines.config import PPOAgentConfig
    from findview_baselines.rl.policy import build_policy
    from findview_baselines.rl.ppo import PPOConfig
    from findview_baselines.rl.ppo_trainer import PPOTrainer

    torch.manual_seed(0)
    env = _sampled_env(files, 16)
    policy = build_policy(PPOAgentConfig(variant="goal_encoder", hidden_size=512), VIEW, VIEW).to(env.device)
    params = sum(p.numel() for p in policy.parameters())
    cfg = PPOConfig(rollout_steps=args.rollout_steps, ppo_epochs=4, num_mini_batches=1)
    trainer = PPOTrainer(env, policy, cfg, total_updates=1 + args.updates, seed=0)
    trainer.start()
    trainer.train_update()  # warm-up
    trainer.pop_timings()
    with Timer() as t:
        for _ in range(args.updates):
            trainer.train_update()
    tm = trainer.pop_timings()
    steps = args.updates * cfg.rollout_steps * env.num_envs
    env.close()
    return {"value": rate(steps, t.s), "seconds": t.s, "updates": args.updates, "env_steps": steps,
            "env_s": tm["env_step"], "net_s": t.s - tm["env_step"], "update_s": tm["update"],
            "rollout_net_s": t.s - tm["env_step"] - tm["update"], "params": params,
            "network": "Policy(variant='goal_encoder', hidden 512)",
            "classes": "PPOTrainer + build_policy(goal_encoder) + EpisodeSampler/build_sampled_env", **_threads()}


def main(argv: list[str] | None = None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--row", required=True, choices=["orb", "sift", "ppo", "env16", "env1", "reset16"])
    ap.add_argument("--order", required=True, choices=["torch", "findview"], help="import order (see above)")
    ap.add_argument("--panoramas", default=os.environ.get("FINDVIEW_SUN360_MINI"),
                    help="folder of panoramas (default: $FINDVIEW_SUN360_MINI)")
    ap.add_argument("--decisions", type=int, default=200)
    ap.add_argument("--warmup-decisions", type=int, default=20)
    ap.add_argument("--env-steps", type=int, default=60, help="env16: steps of the 16 envs")
    ap.add_argument("--env1-steps", type=int, default=300)
    ap.add_argument("--warmup-steps", type=int, default=5)
    ap.add_argument("--updates", type=int, default=2, help="ppo: timed updates (after one warm-up update)")
    ap.add_argument("--rollout-steps", type=int, default=16)
    args = ap.parse_args(argv)
    files = panorama_files(args.panoramas)
    if args.row in ("orb", "sift"):
        res = row_agent(args.row, files, args)
    elif args.row == "env16":
        res = row_env(files, 16, args.env_steps, args)
    elif args.row == "env1":
        res = row_env(files, 1, args.env1_steps, args)
    elif args.row == "reset16":
        res = row_reset16(files, args)
    else:
        res = row_ppo(files, args)
    value = res.pop("value")
    emit(args.row, value, side="ours", order=args.order, torch=torch.__version__, panoramas=len(files),
         env_at_start=ENV_AT_START,
         env_after_imports=ENV_AFTER_IMPORTS, **res)


if __name__ == "__main__":
    main()
