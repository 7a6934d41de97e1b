"""Rendering and environment throughput, with pyequilib's ``Equi2Pers`` measured in the same run.

    python benchmarks/bench_sim.py [--threads 2] [--iters 20] [--cuda-batch 1024]

Needs ``pip install 'findview[bench]'`` (pyequilib 0.5.8, the renderer the authors used) for the
reference column; real panoramas from ``$FINDVIEW_SUN360_MINI`` (or ``--data``).
Prints ms per view and ratios; figures go to benchmarks/RESULTS.md.
"""

from __future__ import annotations

import argparse
import os
import math
import time
from pathlib import Path

import cv2
import numpy as np
import torch

from findview.episode import Episode
from findview.imageio import load_panorama
from findview.sim import PanoramaBank, Simulator, equi2pers
from findview.build import build_static_env
from findview.config import SimConfig, TaskConfig

DEFAULT_DATA = Path(os.environ.get("FINDVIEW_SUN360_MINI", "") or "/nonexistent")  # a folder of SUN360 panoramas


def timeit(fn, iters: int) -> float:
    """Median seconds per call over ``iters`` calls (after one warm-up call)."""
    fn()
    times = []
    for _ in range(iters):
        t = time.perf_counter()
        fn()
        times.append(time.perf_counter() - t)
    return float(np.median(times))


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--data", type=Path, default=DEFAULT_DATA)
    ap.add_argument("--threads", type=int, default=2)
    ap.add_argument("--iters", type=int, default=20)
    ap.add_argument("--batch", type=int, default=16)
    ap.add_argument("--cuda-batch", type=int, default=1024)
    ap.add_argument("--env-steps", type=int, default=300)
    args = ap.parse_args()
    torch.set_num_threads(args.threads)
    cv2.setNumThreads(args.threads)
    files = sorted(args.data.rglob("*.jpg"))
    if not files:
        raise SystemExit(f"no panoramas under {args.data}")
    B = args.batch
    equi = torch.stack([torch.from_numpy(load_panorama(f)).permute(2, 0, 1) for f in files[:B]]).contiguous()
    rng = np.random.default_rng(0)
    rots = [(rng.integers(-60, 61, B), rng.integers(-179, 181, B)) for _ in range(8)]
    k = {"i": 0}

    def next_rot():
        k["i"] = (k["i"] + 1) % len(rots)
        p, y = rots[k["i"]]
        return torch.from_numpy(p).double(), torch.from_numpy(y).double()

    # warm the per-pitch grid cache over the integer pitches (what the task uses)
    for p in range(-60, 61):
        equi2pers(equi[:1], float(p), 0.0, 90, 256, 256)
    print(f"# equi2pers 256x256 FoV 90 from {equi.shape[3]}x{equi.shape[2]}, batch {B}, {args.threads} CPU threads")
    rows = []
    ours = timeit(lambda: equi2pers(equi, *next_rot(), 90, 256, 256), args.iters)
    rows.append(("findview equi2pers (NCHW uint8, integer rotations)", ours))
    cl = equi.contiguous(memory_format=torch.channels_last)
    rows.append(("findview equi2pers (channels-last uint8)", timeit(lambda: equi2pers(cl, *next_rot(), 90, 256, 256), args.iters)))
    frac = lambda: (torch.rand(B, dtype=torch.float64) * 120 - 60, torch.rand(B, dtype=torch.float64) * 360 - 180)  # noqa: E731
    rows.append(("findview equi2pers (non-integer rotations, cold grids)", timeit(lambda: equi2pers(equi, *frac(), 90, 256, 256), max(3, args.iters // 4))))
    rows.append(("findview equi2pers backend=torch (exact, float32 weights)", timeit(lambda: equi2pers(equi, *next_rot(), 90, 256, 256, backend="torch"), max(3, args.iters // 4))))
    try:
        from equilib import Equi2Pers

        e2p = Equi2Pers(height=256, width=256, fov_x=90.0, mode="bilinear")

        def ref_rots():
            p, y = next_rot()
            return [{"roll": 0.0, "pitch": math.radians(float(a)), "yaw": math.radians(float(b))} for a, b in zip(p, y)]

        ef = equi.float()
        t_torch = timeit(lambda: e2p(equi=ef, rots=ref_rots()), max(3, args.iters // 4))
        rows.append(("pyequilib Equi2Pers (torch backend, float input)", t_torch))
        en = equi.numpy()
        t_np = timeit(lambda: e2p(equi=en, rots=ref_rots()), 3)
        rows.append(("pyequilib Equi2Pers (numpy backend, uint8 input)", t_np))
        ref = min(t_torch, t_np)
    except ImportError:
        ref = None
        print("(pyequilib not installed: pip install 'findview[bench]' for the reference)")
    print("| renderer | ms per view | views/s | speed-up vs pyequilib (best backend) |")
    print("|---|---|---|---|")
    for name, t in rows:
        ratio = f"{ref / t:.1f}x" if ref else "n/a"
        print(f"| {name} | {1000 * t / B:.3f} | {B / t:.0f} | {ratio} |")

    # the batched environment
    n_envs = 16
    episodes = [
        Episode(str(i), str(files[i % len(files)]), int(rng.integers(-60, 61)), int(rng.integers(-179, 181)),
                int(rng.integers(-60, 61)), int(rng.integers(-179, 181)))
        for i in range(4000)
    ]
    for device in ["cpu"] + (["cuda"] if torch.cuda.is_available() else []):
        sim_cfg = SimConfig(fov=90, height=256, width=256, device=device, bank_mb=1024)
        env = build_static_env(sim_cfg, TaskConfig(), episodes, n_envs)
        env.reset()
        env.sim.build_all_grids(env.sim.bank.equi_height)  # grids are built on first use: keep that out of the timing
        gen = torch.Generator().manual_seed(0)
        acts = [torch.randint(0, 4, (n_envs,), generator=gen).to(device) for _ in range(64)]
        for i in range(20):
            env.step(acts[i % 64])
        if device == "cuda":
            torch.cuda.synchronize()
        t = time.perf_counter()
        for i in range(args.env_steps):
            env.step(acts[i % 64])
        if device == "cuda":
            torch.cuda.synchronize()
        dt = time.perf_counter() - t
        print(f"\n# FindViewEnv, {n_envs} envs, 256x256, random moves, {device}: {args.env_steps * n_envs / dt:.0f} env steps/s (observations included)")

    if torch.cuda.is_available():
        Bc = args.cuda_batch
        eq = equi.cuda()[torch.arange(Bc) % B]
        p = torch.randint(-60, 61, (Bc,), device="cuda").double()
        y = torch.randint(-179, 181, (Bc,), device="cuda").double()
        for q in range(-60, 61):
            equi2pers(eq[:1], float(q), 0.0, 90, 256, 256)
        torch.cuda.synchronize()

        def run():
            equi2pers(eq, p, y, 90, 256, 256)
            torch.cuda.synchronize()

        t = timeit(run, 10)
        print(f"\n# CUDA ({torch.cuda.get_device_name()}): equi2pers batch {Bc}: {Bc / t:.0f} views/s")
        bank = PanoramaBank("cuda", 4096, min_slots=Bc, max_panoramas=len(files))
        sim = Simulator(bank, 90, 256, 256)
        slots = torch.tensor([bank.acquire(str(files[i % len(files)])) for i in range(Bc)], device="cuda")
        out = sim.new_buffer(Bc)
        rows_ = torch.arange(Bc, device="cuda")
        pi = torch.randint(-60, 61, (Bc,), device="cuda")
        yi = torch.randint(-179, 181, (Bc,), device="cuda")

        def run_sim():
            sim.render_into(out, rows_, slots, pi, yi)
            torch.cuda.synchronize()

        t = timeit(run_sim, 10)
        print(f"# CUDA Simulator.render_into batch {Bc}: {Bc / t:.0f} views/s")


if __name__ == "__main__":
    main()
