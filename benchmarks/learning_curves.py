"""Learning curves of training runs from their TensorBoard scalars: a CSV and a PNG.

For every run folder given as ``NAME=PATH`` (``PATH`` holds the run's ``tb/`` folder, as written by
``tools/train.py``) this reads the validation scalars ``val/<difficulty>/{eps,spl,omega_stop}`` and
``perf/env_steps``, and writes one CSV row per validation: run, update, env steps (environment steps
collected by then), wall time in seconds since the run's first logged scalar, difficulty, eps (mean
localization error in degrees), omega_stop and SPL (fractions). The PNG plots val eps and SPL of the
``all`` row against env steps and against wall time, one colour per run (drawn with OpenCV, no
plotting library needed).

    python benchmarks/learning_curves.py ppo=outputs/train/a dagger=outputs/train/b \\
        dagger_ppo=outputs/train/c@64000,367 --out benchmarks/learning_curves

``NAME=PATH@STEPS,SECONDS`` shifts a run by the env steps and wall seconds spent before it (e.g. the
imitation stage a fine-tuning run started from), so that every curve counts all of its compute.
"""

from __future__ import annotations

import argparse
import csv
import io
import math
import sys
from pathlib import Path
from typing import Any

import cv2
import numpy as np

from findview.utils import atomic_write, write_text

DIFFICULTIES = ("easy", "medium", "hard", "all")
COLOURS = ((200, 60, 40), (40, 140, 40), (40, 60, 200), (160, 40, 160), (20, 150, 170))  # BGR


def read_run(tb_dir: Path) -> list[dict[str, Any]]:
    """Validation rows of one run's TensorBoard folder (see the module docstring for the columns)."""
    from tensorboard.backend.event_processing.event_accumulator import EventAccumulator

    if not tb_dir.is_dir():
        raise FileNotFoundError(f"no TensorBoard folder {tb_dir} (expected <run>/tb as written by tools/train.py)")
    acc = EventAccumulator(str(tb_dir), size_guidance={"scalars": 0})
    acc.Reload()
    tags = set(acc.Tags().get("scalars", []))
    if "val/all/eps" not in tags:
        raise ValueError(f"{tb_dir} has no validation scalars (val/all/eps); did the run validate?")
    start = min(e.wall_time for tag in tags for e in acc.Scalars(tag))
    steps_at = {e.step: e.value for e in acc.Scalars("perf/env_steps")} if "perf/env_steps" in tags else {}

    def env_steps(update: int) -> float:
        # perf/env_steps is logged every log_interval updates: take the last value at or before update
        before = [u for u in steps_at if u <= update]
        return steps_at[max(before)] if before else float("nan")

    rows = []
    for diff in DIFFICULTIES:
        if f"val/{diff}/eps" not in tags:
            continue
        spl = {e.step: e.value for e in acc.Scalars(f"val/{diff}/spl")}
        stop = {e.step: e.value for e in acc.Scalars(f"val/{diff}/omega_stop")}
        for e in acc.Scalars(f"val/{diff}/eps"):
            rows.append({
                "update": e.step, "env_steps": env_steps(e.step), "wall_s": round(e.wall_time - start, 1),
                "difficulty": diff, "eps": e.value, "omega_stop": stop.get(e.step, float("nan")),
                "spl": spl.get(e.step, float("nan")),
            })
    return rows


def plot(runs: dict[str, list[dict[str, Any]]], path: Path) -> None:
    """2 x 2 panels: val eps and SPL (difficulty ``all``) against env steps and against wall time."""
    w, h, margin = 420, 300, 50
    canvas = np.full((2 * h, 2 * w, 3), 255, np.uint8)
    panels = [("eps", "env_steps"), ("eps", "wall_s"), ("spl", "env_steps"), ("spl", "wall_s")]
    for k, (ykey, xkey) in enumerate(panels):
        ox, oy = (k % 2) * w, (k // 2) * h
        pts = {name: [(r[xkey], r[ykey]) for r in rows if r["difficulty"] == "all" and not math.isnan(r[xkey])]
               for name, rows in runs.items()}
        xs = [x for p in pts.values() for x, _ in p] or [0.0, 1.0]
        ys = [y for p in pts.values() for _, y in p] or [0.0, 1.0]
        x1 = max(xs) or 1.0
        y0, y1 = (0.0, 1.0) if ykey == "spl" else (0.0, max(ys) * 1.05 or 1.0)

        def to_px(x: float, y: float) -> tuple[int, int]:
            px = ox + margin + int((w - 1.5 * margin) * x / x1)
            py = oy + h - margin + int(-(h - 1.5 * margin) * (y - y0) / (y1 - y0))
            return px, py

        cv2.rectangle(canvas, to_px(0, y0), to_px(x1, y1), (0, 0, 0), 1)
        label = f"val {ykey} (all) vs {'env steps' if xkey == 'env_steps' else 'wall time, s'}"
        cv2.putText(canvas, label, (ox + margin, oy + 20), cv2.FONT_HERSHEY_SIMPLEX, 0.45, (0, 0, 0), 1)
        cv2.putText(canvas, f"{x1:.0f}", to_px(x1, y0), cv2.FONT_HERSHEY_SIMPLEX, 0.35, (0, 0, 0), 1)
        cv2.putText(canvas, f"{y1:.2f}", (ox + 5, to_px(0, y1)[1] + 5), cv2.FONT_HERSHEY_SIMPLEX, 0.35, (0, 0, 0), 1)
        for i, (name, p) in enumerate(pts.items()):
            colour = COLOURS[i % len(COLOURS)]
            line = [to_px(x, y) for x, y in sorted(p)]
            for a, b in zip(line[:-1], line[1:]):
                cv2.line(canvas, a, b, colour, 2)
            for q in line:
                cv2.circle(canvas, q, 3, colour, -1)
            cv2.putText(canvas, name, (ox + w - 140, oy + 40 + 16 * i), cv2.FONT_HERSHEY_SIMPLEX, 0.45, colour, 1)
    ok, data = cv2.imencode(".png", canvas)
    if not ok:
        raise RuntimeError(f"could not encode {path}")
    atomic_write(path, lambda tmp: Path(tmp).write_bytes(data.tobytes()))


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("runs", nargs="+", help="NAME=RUN_FOLDER[@STEPS,SECONDS] (the folder that holds tb/)")
    parser.add_argument("--out", default="benchmarks/learning_curves", help="output path without suffix")
    args = parser.parse_args(argv)
    runs: dict[str, list[dict[str, Any]]] = {}
    for item in args.runs:
        name, sep, folder = item.partition("=")
        folder, _, offset = folder.partition("@")
        if not sep or not name or not folder:
            parser.error(f"run {item!r}: expected NAME=RUN_FOLDER[@STEPS,SECONDS]")
        try:
            steps0, seconds0 = (float(x) for x in offset.split(",")) if offset else (0.0, 0.0)
        except ValueError:
            parser.error(f"run {item!r}: the offset after @ must be STEPS,SECONDS (two numbers)")
        rows = read_run(Path(folder) / "tb")
        for row in rows:
            row["env_steps"] += steps0
            row["wall_s"] = round(row["wall_s"] + seconds0, 1)
        runs[name] = rows
    out = Path(args.out)
    buf = io.StringIO()
    fields = ["run", "update", "env_steps", "wall_s", "difficulty", "eps", "omega_stop", "spl"]
    writer = csv.DictWriter(buf, fieldnames=fields, lineterminator="\n")
    writer.writeheader()
    for name, rows in runs.items():
        for row in rows:
            writer.writerow({"run": name, **row})
    write_text(out.with_suffix(".csv"), buf.getvalue())
    plot(runs, out.with_suffix(".png"))
    print(f"wrote {out.with_suffix('.csv')} and {out.with_suffix('.png')}")
    return 0


if __name__ == "__main__":
    try:
        sys.exit(main())
    except (FileNotFoundError, ValueError) as err:
        print(f"learning_curves: error: {err}", file=sys.stderr)
        sys.exit(2)
