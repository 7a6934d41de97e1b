"""The PPO update at the paper's setting, timed and profiled (torch.profiler): where its time goes.

    python benchmarks/profile_ppo_update.py                  # 2 timed updates, then the operator table
    python benchmarks/profile_ppo_update.py --threads 1 --rounds 1 --no-profile

The network is ``goal_encoder`` (28.18M parameters, 256x256 views); the rollout is 16 envs x 16 steps of
random uint8 views, each env's target kept from step to step and replaced with probability 1/16 per step (a
new episode: about 30 distinct targets per rollout, as in training); 4 PPO epochs, 1 mini-batch. No
environment: the figures are the network's (rollout forward passes and the update). Prints per round the
seconds of the rollout's forward passes and of the update, then the top operators by self CPU time.
"""

from __future__ import annotations

import argparse
import time

import findview  # noqa: F401  (before torch: findview.runtime's environment defaults)
import torch

from findview.runtime import configure_threads
from findview_baselines.config import PPOAgentConfig
from findview_baselines.rl.policy import build_policy
from findview_baselines.rl.ppo import PPO, PPOConfig
from findview_baselines.rl.storage import RolloutStorage


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--threads", type=int, default=2, help="torch threads of the network (configure_threads)")
    ap.add_argument("--rounds", type=int, default=2, help="timed rollout + update rounds after a warm-up one")
    ap.add_argument("--no-profile", action="store_true", help="skip the torch.profiler table")
    ap.add_argument("--size", type=int, default=256)
    ap.add_argument("--envs", type=int, default=16)
    ap.add_argument("--steps", type=int, default=16)
    args = ap.parse_args()
    configure_threads(args.threads)
    torch.manual_seed(0)
    torch.distributions.Distribution.set_default_validate_args(False)
    size, envs, steps = args.size, args.envs, args.steps
    policy = build_policy(PPOAgentConfig(variant="goal_encoder", hidden_size=512), size, size)
    cfg = PPOConfig(rollout_steps=steps)
    ppo = PPO(policy, cfg)
    storage = RolloutStorage(steps, envs, size, size, 512)
    gen = torch.Generator().manual_seed(0)
    targets = torch.randint(0, 256, (envs, 3, size, size), dtype=torch.uint8, generator=gen)

    def observation() -> dict[str, torch.Tensor]:
        new = torch.rand(envs, generator=gen) < 1 / 16
        targets[new] = torch.randint(0, 256, (int(new.sum()), 3, size, size), dtype=torch.uint8, generator=gen)
        view = torch.randint(0, 256, (envs, 3, size, size), dtype=torch.uint8, generator=gen)
        return {"view": view, "target": targets.clone()}

    def rollout() -> float:
        forward = 0.0
        for _ in range(steps):
            obs, hidden, masks = storage.current()
            t = time.perf_counter()
            with torch.no_grad():
                actions, log_probs, values, new_hidden = policy.act(obs, hidden, masks)
            forward += time.perf_counter() - t
            storage.insert(observation(), new_hidden, actions, log_probs, values, torch.rand(envs), torch.ones(envs))
        with torch.no_grad():
            storage.compute_returns(policy.get_value(*storage.current()), cfg.gamma, cfg.gae_lambda)
        return forward

    storage.set_initial(observation())
    print(f"# goal_encoder, {sum(p.numel() for p in policy.parameters()) / 1e6:.2f}M parameters, {size}x{size}, "
          f"{envs} envs x {steps} steps, {cfg.ppo_epochs} epochs, {cfg.num_mini_batches} mini-batch, "
          f"{args.threads} thread(s), torch {torch.__version__}")
    for r in range(args.rounds + 1):
        forward = rollout()
        t = time.perf_counter()
        ppo.update(storage)
        update = time.perf_counter() - t
        storage.after_update()
        if r:  # round 0 warms up
            print(f"round {r}: rollout forward {forward:.2f} s, update {update:.2f} s, "
                  f"{envs * steps / (forward + update):.2f} env steps/s (network only)", flush=True)
    if not args.no_profile:
        from torch.profiler import ProfilerActivity, profile

        rollout()
        with profile(activities=[ProfilerActivity.CPU]) as prof:
            ppo.update(storage)
        print(prof.key_averages().table(sort_by="self_cpu_time_total", row_limit=15))


if __name__ == "__main__":
    main()
