"""What both sides of ``benchmarks/bench_peers.py`` share: the rows, the panorama list, the episodes.

Standard library only, and nothing heavy is imported at module level: ``ours.py --order findview`` must be
able to import ``findview`` before numpy / torch are loaded, so this module may be imported first.
"""

from __future__ import annotations

import json
import os
import random
import sys
import time
from pathlib import Path

#: row -> (unit, higher is better)
ROWS: dict[str, tuple[str, bool]] = {
    "orb": ("decisions/s", True),
    "sift": ("decisions/s", True),
    "ppo": ("env steps/s", True),
    "env16": ("env steps/s", True),
    "env1": ("env steps/s", True),
    "reset16": ("s", False),
}

VIEW = 256  # view height = width, pixels
FOV = 90.0  # horizontal field of view, degrees
PITCH_BOUND = 60  # both: pitch clamped to [-60, 60]
AGENT_MAX_STEPS = 300  # orb / sift rows: episode limit T (as benchmarks/bench_load.py's agent paths)
IMAGE_SUFFIXES = (".jpg", ".jpeg", ".png")
#: thread-related variables reported by each measurement (their value when the process started)
THREAD_VARS = ("OMP_WAIT_POLICY", "OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS")


class PeerError(SystemExit):
    """A setup error with a clear message (exit status 2)."""

    def __init__(self, msg: str) -> None:
        print(f"error: {msg}", file=sys.stderr)
        super().__init__(2)


def panorama_files(folder: str | os.PathLike | None) -> list[str]:
    """Every panorama under ``folder`` (recursive, sorted, absolute paths); a clear error when there is none."""
    if not folder:
        raise PeerError("no panorama folder: pass --panoramas DIR or set FINDVIEW_SUN360_MINI")
    root = Path(folder).expanduser()
    if not root.is_dir():
        raise PeerError(f"--panoramas {root}: not a directory")
    files = sorted(str(p.resolve()) for p in root.rglob("*") if p.suffix.lower() in IMAGE_SUFFIXES and p.is_file())
    if not files:
        raise PeerError(f"--panoramas {root}: no images ({', '.join(IMAGE_SUFFIXES)}) in it or below it")
    return files


def episode_tuples(files: list[str], n: int, seed: int = 0) -> list[tuple[str, int, int, int, int]]:
    """``n`` episodes ``(image, init_pitch, init_yaw, target_pitch, target_yaw)`` (integer degrees), images in
    turn, rotations uniform (pitch in [-60, 60], yaw in [-179, 180]); the same list on both sides."""
    rng = random.Random(seed)
    out = []
    for i in range(n):
        out.append((files[i % len(files)], rng.randint(-PITCH_BOUND, PITCH_BOUND), rng.randint(-179, 180),
                    rng.randint(-PITCH_BOUND, PITCH_BOUND), rng.randint(-179, 180)))
    return out


def shortest_steps(ip: int, iy: int, tp: int, ty: int) -> int:
    """L1 distance in 1-degree steps (yaw wraps around)."""
    dy = abs(iy - ty) % 360
    return abs(ip - tp) + min(dy, 360 - dy)


def thread_env() -> dict[str, str | None]:
    return {k: os.environ.get(k) for k in THREAD_VARS}


def emit(row: str, value: float, **extra) -> None:
    """Print the one JSON result line: ``{"row", "value", "unit", ...extra}``."""
    unit, _ = ROWS[row]
    print(json.dumps({"row": row, "value": value, "unit": unit, **extra}), flush=True)


def rate(work: float, seconds: float) -> float:
    return work / seconds if seconds > 0 else float("inf")


class Timer:
    """``with Timer() as t: ...`` then ``t.s``: wall-clock seconds."""

    def __enter__(self) -> "Timer":
        self.t0 = time.perf_counter()
        self.s = 0.0
        return self

    def __exit__(self, *exc) -> None:
        self.s = time.perf_counter() - self.t0
