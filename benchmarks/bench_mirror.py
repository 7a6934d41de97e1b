"""What ``agent.mirror_steps`` costs a learned agent per step, against the same agent without it, in the same run.

    python benchmarks/bench_mirror.py [--checkpoint pretrained/findview_sun360mini_indoor_robust.pth]
        [--slots 16] [--size 256] [--steps 100] [--threads 1] [--device cpu]

The agent (its search memory and the checkpoint's FoV, as its model card runs it) acts on random views and targets
(``--size`` pixels square; the network averages them down to its own size); with the option every slot plays its
mirror every step (``mirror_steps`` larger than ``--steps``), the option's worst case. Prints ms per ``act`` (median
of ``--steps`` calls after 5 warm-up calls) with the option off (the reference) and on, and their ratio; figures go
to benchmarks/RESULTS.md.
"""

from __future__ import annotations

from act_timing import act_options, median_act_ms

from findview_baselines.agents.ppo_agent import PPOAgent


def ms_per_act(checkpoint: str, slots: int, size: int, steps: int, device: str, mirror_steps: int) -> float:
    """Median milliseconds of one ``act`` of ``slots`` slots on ``size``-pixel views."""
    agent = PPOAgent.from_checkpoint(checkpoint, slots, device, height=size, width=size, mirror_steps=mirror_steps)
    return median_act_ms(agent, slots, size, steps, device)


def main() -> None:
    args = act_options(__doc__)
    off = ms_per_act(args.checkpoint, args.slots, args.size, args.steps, args.device, mirror_steps=0)
    on = ms_per_act(args.checkpoint, args.slots, args.size, args.steps, args.device, mirror_steps=args.steps + 10)
    print(f"{args.slots} slots, {args.size}x{args.size} views, {args.threads} thread(s), {args.device}")
    print("| agent.mirror_steps | ms per act | ratio |")
    print("|---|---|---|")
    print(f"| 0 (reference) | {off:.1f} | 1.00 |")
    print(f"| every step | {on:.1f} | {on / off:.2f} |")


if __name__ == "__main__":
    main()
