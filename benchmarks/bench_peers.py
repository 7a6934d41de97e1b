"""Side-by-side speed of findview and the authors' original code (look_around), row by row.

    git clone <the authors' look_around repository> ../look_around
    python benchmarks/bench_peers.py --look-around ../look_around --theirs-python ../la_venv/bin/python
    python benchmarks/bench_peers.py --look-around ../look_around --theirs-python ../la_venv/bin/python \\
        --rows orb sift env1 --rounds 5 --json peers.json
    python benchmarks/bench_peers.py --look-around ../look_around --theirs-python ../la_venv/bin/python \\
        --rows ppo --rounds 1 --updates 1          # a quick check of the slowest row

``--theirs-python`` is an interpreter with look_around's requirements (mmengine, gymnasium, pyequilib 0.5.8,
numba, scikit-image, imageio; a venv made with ``--system-site-packages`` reuses the installed torch);
this script itself and ``peers/ours.py`` run with the current interpreter. Panoramas: ``--panoramas DIR``
(default ``$FINDVIEW_SUN360_MINI``), the same files on both sides. No network access.

Rows (256x256 views, FoV 90, on the CPU; both sides through their own public classes, see
``peers/theirs.py`` and ``peers/ours.py`` for exactly which):

- ``orb`` / ``sift``: decisions/s of the ORB / SIFT feature-matching agent, 1 env: ``act`` + ``env.step``
  per decision (the next episode's reset included when one ends), the same static episodes, T = 300.
- ``ppo``: PPO env steps/s, 16 envs, rollout of 16 steps, 4 epochs, 1 mini-batch, the 28.18M-parameter
  network with a separate target encoder on both sides (theirs ``FindViewBaselinePolicy``, ours
  ``build_policy(variant="goal_encoder")``): rollout (policy forward + env step) + update, per update,
  after one warm-up update; the details give the env / network split.
- ``env16``: env steps/s of 16 envs (their default vectorized env, ``threaded``; our batched env), random moves.
- ``env1``: env steps/s of 1 env, random moves.
- ``reset16``: seconds to build 16 envs and reset them the first time (lower is better).

Each round runs every row as three fresh processes: theirs, ours with ``torch, cv2, numpy`` imported
before findview ("torch first", what most user scripts do), ours with ``import findview`` first
("findview first"); the order of the three rotates from round to round. Neither of ours sets thread counts:
each measures what the library gives by itself. The table shows the median of each column and, in
parentheses, the median over rounds of the per-round ratio ours / theirs (theirs / ours for ``reset16``):
above 1 means findview is faster. The 1-minute load average is recorded around every process; the
machine, its load range and the torch version are printed under the table.
"""

from __future__ import annotations

import argparse
import importlib.metadata
import json
import os
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

HERE = Path(__file__).resolve().parent
REPO = HERE.parent
PEERS = HERE / "peers"
sys.path.insert(0, str(PEERS))
from peerlib import ROWS, PeerError, panorama_files  # noqa: E402  (standard library only)

VARIANTS = ("theirs", "torch", "findview")  # columns: theirs, ours torch first, ours findview first
PASS_THROUGH = ("decisions", "warmup_decisions", "env_steps", "env1_steps", "warmup_steps", "updates", "rollout_steps")


def check_look_around(path: str) -> Path:
    la = Path(path).expanduser().resolve()
    if not (la / "LookAround" / "FindView" / "sim.py").is_file() or not (la / "findview_baselines").is_dir():
        raise PeerError(f"--look-around {la}: not a look_around checkout (no LookAround/FindView/sim.py or "
                        "findview_baselines/ there); git clone the authors' repository and pass its folder")
    return la


def check_theirs_python(python: str) -> None:
    probe = "import mmengine, gymnasium, equilib, numba, skimage, imageio, torch, cv2"
    try:
        out = subprocess.run([python, "-c", probe], capture_output=True, text=True, timeout=300)
    except (OSError, subprocess.TimeoutExpired) as e:
        raise PeerError(f"--theirs-python {python}: cannot run it ({e})") from None
    if out.returncode != 0:
        last = (out.stderr.strip().splitlines() or ["?"])[-1]
        raise PeerError(f"--theirs-python {python}: lacks look_around's requirements ({last}); "
                        "see benchmarks/peers/theirs.py for the venv it needs")


def machine() -> dict:
    model = "unknown CPU"
    try:
        for line in Path("/proc/cpuinfo").read_text().splitlines():
            if line.lower().startswith("model name"):
                model = line.split(":", 1)[1].strip()
                break
    except OSError:
        pass
    try:
        torch_version = importlib.metadata.version("torch")  # not imported: this process sets nothing for them
    except importlib.metadata.PackageNotFoundError:
        torch_version = "not installed"
    return {"cpu": model, "cores": os.cpu_count(), "torch_ours": torch_version, "python": sys.version.split()[0]}


def command(variant: str, row: str, args) -> list[str]:
    common = ["--row", row, "--panoramas", str(args.panoramas)]
    for name in PASS_THROUGH:
        value = getattr(args, name)
        if value is not None:
            common += [f"--{name.replace('_', '-')}", str(value)]
    if variant == "theirs":
        cmd = [args.theirs_python, str(PEERS / "theirs.py"), "--look-around", str(args.look_around), *common]
        if args.vec_type:
            cmd += ["--vec-type", args.vec_type]
        if args.baselines_rev:
            cmd += ["--baselines-rev", args.baselines_rev]
        if args.theirs_torch_threads:
            cmd += ["--torch-threads", str(args.theirs_torch_threads)]
        return cmd
    return [sys.executable, str(PEERS / "ours.py"), "--order", variant, *common]


def run_one(variant: str, row: str, args, cwd: str) -> dict:
    env = dict(os.environ)
    if variant != "theirs":  # ours: this checkout's findview first on the path (theirs has its own findview_baselines)
        env["PYTHONPATH"] = os.pathsep.join([str(REPO), *filter(None, [env.get("PYTHONPATH")])])
    load0 = os.getloadavg()[0]
    t0 = time.perf_counter()
    try:
        out = subprocess.run(command(variant, row, args), capture_output=True, text=True, cwd=cwd, env=env,
                             timeout=args.timeout)
        rc, stdout, stderr = out.returncode, out.stdout, out.stderr
    except subprocess.TimeoutExpired as e:
        rc, stdout, stderr = "timeout", e.stdout or "", e.stderr or ""
        stdout = stdout.decode(errors="replace") if isinstance(stdout, bytes) else stdout
        stderr = stderr.decode(errors="replace") if isinstance(stderr, bytes) else stderr
    wall = time.perf_counter() - t0
    load1 = os.getloadavg()[0]
    result = None
    for line in reversed(stdout.splitlines()):
        if line.startswith("{"):
            try:
                parsed = json.loads(line)
            except json.JSONDecodeError:
                continue
            if parsed.get("row") == row:
                result = parsed
                break
    rec = {"variant": variant, "row": row, "rc": rc, "wall_s": wall, "load_before": load0, "load_after": load1}
    if result is None or rc != 0:
        tail = "\n".join((stderr or stdout).strip().splitlines()[-8:])
        rec["error"] = f"exit {rc}: {tail}"
    else:
        rec["result"] = result
    return rec


def ratio(row: str, ours: float, theirs: float) -> float:
    _, higher_better = ROWS[row]
    if higher_better:
        return ours / theirs if theirs > 0 else float("inf")
    return theirs / ours if ours > 0 else float("inf")


def fmt(value: float, unit: str) -> str:
    if unit == "s":
        return f"{value:.2f} s"
    return f"{value:.1f}" if value < 1000 else f"{value:.0f}"


def summarize(records: list[dict], rows: list[str]) -> dict:
    summary = {}
    for row in rows:
        by_round: dict[int, dict[str, float]] = {}
        for r in records:
            if r["row"] == row and "result" in r:
                by_round.setdefault(r["round"], {})[r["variant"]] = r["result"]["value"]
        s: dict = {"unit": ROWS[row][0]}
        for v in VARIANTS:
            vals = [d[v] for d in by_round.values() if v in d]
            s[v] = statistics.median(vals) if vals else None
            s[f"{v}_n"] = len(vals)
        for v in ("torch", "findview"):
            rs = [ratio(row, d[v], d["theirs"]) for d in by_round.values() if v in d and "theirs" in d]
            s[f"ratio_{v}"] = statistics.median(rs) if rs else None
        summary[row] = s
    return summary


def details(records: list[dict], row: str) -> list[str]:
    """Per-variant extras of the last successful run of ``row`` worth a line under the table."""
    out = []
    for v in VARIANTS:
        res = [r["result"] for r in records if r["row"] == row and r["variant"] == v and "result" in r]
        if not res:
            continue
        r = res[-1]
        bits = []
        if "params" in r:
            bits.append(f"{r['params'] / 1e6:.2f}M params")
        if "env_s" in r:
            n = max(1, r.get("updates", 1))
            bits.append(f"per update: env {r['env_s'] / n:.2f} s, network {r['net_s'] / n:.2f} s "
                        f"(update {r['update_s'] / n:.2f} s, "
                        f"rollout forward + bookkeeping {r['rollout_net_s'] / n:.2f} s)")
        if "vec_env" in r:
            bits.append(f"vec env {r['vec_env']}")
        if "torch_threads" in r:
            bits.append(f"torch threads {r['torch_threads']}")
        if "cv2_threads" in r:
            bits.append(f"OpenCV threads {r['cv2_threads']}")
        label = {"theirs": "theirs", "torch": "ours torch first", "findview": "ours findview first"}[v]
        out.append(f"  - {row}, {label}: {r.get('classes', '')}; " + "; ".join(bits))
    return out


def main(argv: list[str] | None = None) -> dict:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0], epilog=__doc__.split("\n\n", 1)[1],
                                 formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--look-around", required=True, help="folder of a clone of the authors' look_around repository")
    ap.add_argument("--theirs-python", default="python",
                    help="interpreter with look_around's requirements (default: python)")
    ap.add_argument("--panoramas", default=os.environ.get("FINDVIEW_SUN360_MINI"),
                    help="folder of panoramas, both sides (default: $FINDVIEW_SUN360_MINI)")
    ap.add_argument("--rows", nargs="+", default=list(ROWS), choices=list(ROWS), metavar="ROW",
                    help=f"subset of: {' '.join(ROWS)}")
    ap.add_argument("--rounds", type=int, default=3)
    ap.add_argument("--json", default=None, metavar="OUT", help="also write every run and the summary here")
    ap.add_argument("--timeout", type=float, default=1800, help="seconds per process (default 1800)")
    g = ap.add_argument_group("work per process (the same on both sides; defaults: the scripts' own)")
    g.add_argument("--decisions", type=int, help="orb / sift: timed decisions (default 200, after 20)")
    g.add_argument("--warmup-decisions", type=int)
    g.add_argument("--env-steps", type=int, help="env16: timed steps of the 16 envs (default 60)")
    g.add_argument("--env1-steps", type=int, help="env1: timed steps (default 300)")
    g.add_argument("--warmup-steps", type=int, help="env16 / env1: untimed steps first (default 5)")
    g.add_argument("--updates", type=int, help="ppo: timed updates after one warm-up update (default 2)")
    g.add_argument("--rollout-steps", type=int, help="ppo: steps per env per update (default 16)")
    g = ap.add_argument_group("their side")
    g.add_argument("--vec-type", default=None,
                   help="their vec env for env16 / reset16 / ppo: threaded | mp | equilib (default: the config's, "
                        "threaded)")
    g.add_argument("--baselines-rev", default=None, help="see peers/theirs.py (default ad2abbb)")
    g.add_argument("--theirs-torch-threads", type=int, default=None,
                   help="torch.set_num_threads(N) on their side once their envs are built (their env factories "
                        "set 1 for the whole process, which also runs their PPO update); default: their setting")
    args = ap.parse_args(argv)

    args.look_around = check_look_around(args.look_around)
    files = panorama_files(args.panoramas)
    args.panoramas = Path(args.panoramas).expanduser().resolve()
    if args.rounds < 1:
        raise PeerError("--rounds must be at least 1")
    check_theirs_python(args.theirs_python)
    info = machine()
    print(f"# bench_peers: {len(files)} panoramas from {args.panoramas}, rows {' '.join(args.rows)}, "
          f"{args.rounds} round(s); theirs: {args.theirs_python}", file=sys.stderr, flush=True)

    records: list[dict] = []
    with tempfile.TemporaryDirectory(prefix="bench_peers_") as cwd:
        for rnd in range(args.rounds):
            order = VARIANTS[rnd % 3:] + VARIANTS[: rnd % 3]  # rotate who goes first
            for row in args.rows:
                for variant in order:
                    rec = run_one(variant, row, args, cwd)
                    rec["round"] = rnd
                    records.append(rec)
                    if "result" in rec:
                        msg = f"{rec['result']['value']:.3f} {rec['result']['unit']}"
                    else:
                        msg = "FAILED\n" + rec["error"]
                    print(f"  round {rnd + 1}/{args.rounds} {row:<7} {variant:<8} {msg}  "
                          f"(load {rec['load_before']:.2f} -> {rec['load_after']:.2f}, {rec['wall_s']:.0f} s)",
                          file=sys.stderr, flush=True)

    summary = summarize(records, args.rows)
    theirs_torch = sorted({r["result"].get("torch", "?") for r in records
                           if r["variant"] == "theirs" and "result" in r})
    loads = [x for r in records for x in (r["load_before"], r["load_after"])]
    lines = [
        "| row | theirs | ours torch first (ratio) | ours findview first (ratio) |",
        "|---|---|---|---|",
    ]
    for row in args.rows:
        s = summary[row]
        unit = s["unit"]
        cells = [f"{row} ({'s, lower is better' if unit == 's' else unit})",
                 fmt(s["theirs"], unit) if s["theirs"] is not None else "failed"]
        for v in ("torch", "findview"):
            if s[v] is None:
                cells.append("failed")
            else:
                r = s[f"ratio_{v}"]
                cells.append(fmt(s[v], unit) + (f" ({r:.2f}x)" if r is not None else ""))
        lines.append("| " + " | ".join(cells) + " |")
    lines.append("")
    lines.append(f"Medians of {args.rounds} round(s); ratio: median of per-round ours / theirs "
                 "(theirs / ours for reset16), above 1 = findview faster.")
    lines.append(f"Machine: {info['cpu']}, {info['cores']} cores; torch {info['torch_ours']} (ours), "
                 f"{', '.join(theirs_torch) or '?'} (theirs); Python {info['python']}.")
    if loads:
        lines.append(f"1-minute load average around the runs: {min(loads):.2f} to {max(loads):.2f}.")
    extra = [d for row in args.rows for d in details(records, row)]
    if extra:
        lines.append("Details (last run of each):")
        lines += extra
    failed = [r for r in records if "error" in r]
    if failed:
        first = failed[0]
        lines.append(f"{len(failed)} run(s) failed; first: {first['row']} / {first['variant']}: {first['error']}")
    print("\n".join(lines))

    out = {"machine": info, "args": {k: str(v) for k, v in vars(args).items()}, "summary": summary, "runs": records}
    if args.json:
        Path(args.json).write_text(json.dumps(out, indent=2))
    return out


if __name__ == "__main__":
    main()
