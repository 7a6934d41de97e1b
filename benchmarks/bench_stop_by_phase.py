"""What ``agent.stop_by_phase`` costs a learned agent per step, against the same agent without it, in the same run.

    python benchmarks/bench_stop_by_phase.py [--checkpoint pretrained/findview_sun360mini_indoor_robust.pth]
        [--slots 16] [--size 256] [--steps 100] [--threads 1] [--device cpu]

The agent acts on random views and targets (``--size`` pixels square; the network averages them down to its own
size), so its STOP probability stays below 0.1 and every slot measures phase correlation every step: the option's
worst case. Prints ms per ``act`` (median of ``--steps`` calls after 5 warm-up calls) with the option off (the
reference) and on, and their ratio; figures go to benchmarks/RESULTS.md.
"""

from __future__ import annotations

from act_timing import act_options, median_act_ms

from findview_baselines.agents.ppo_agent import PPOAgent
from findview_baselines.agents.stop_refine import StopRefiner


def ms_per_act(checkpoint: str, slots: int, size: int, steps: int, device: str, phase: bool) -> float:
    """Median milliseconds of one ``act`` of ``slots`` slots on ``size``-pixel views."""
    agent = PPOAgent.from_checkpoint(
        checkpoint, slots, device, height=size, width=size, refiner=StopRefiner(slots, 90.0), fov=90.0,
        stop_by=100_000, stop_by_phase=phase,
    )
    return median_act_ms(agent, slots, size, steps, device)


def main() -> None:
    args = act_options(__doc__)
    off = ms_per_act(args.checkpoint, args.slots, args.size, args.steps, args.device, phase=False)
    on = ms_per_act(args.checkpoint, args.slots, args.size, args.steps, args.device, phase=True)
    print(f"{args.slots} slots, {args.size}x{args.size} views, {args.threads} thread(s), {args.device}")
    print("| agent.stop_by_phase | ms per act | ratio |")
    print("|---|---|---|")
    print(f"| off (reference) | {off:.1f} | 1.00 |")
    print(f"| on | {on:.1f} | {on / off:.2f} |")


if __name__ == "__main__":
    main()
