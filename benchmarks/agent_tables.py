"""Gather ``tools/eval.py`` runs laid out as ``<root>/<setting>/<agent>/summary.json`` into markdown
tables (the paper's layout: eps / omega_stop / omega_perf / SPL per difficulty, plus agent FPS).

    python benchmarks/agent_tables.py outputs/bench

``benchmarks/run_agent_benchmarks.sh`` produces that layout for the sun360_mini test splits.
"""

from __future__ import annotations

import json
import sys
from pathlib import Path

AGENT_ORDER = ["random", "oracle", "orb", "sift", "rotation", "ppo"]


def cell(m: dict) -> str:
    return f"{m['eps']:.2f} / {100 * m['omega_stop']:.0f}% / {100 * m['omega_perf']:.0f}% / {100 * m['spl']:.1f}%"


def main(root: Path) -> None:
    for setting in sorted(p for p in root.iterdir() if p.is_dir()):
        runs = {p.parent.name: json.loads(p.read_text()) for p in setting.glob("*/summary.json")}
        if not runs:
            continue
        n = {d: next((r[d]["episodes"] for r in runs.values() if d in r), 0) for d in ("easy", "medium", "hard")}
        print(f"\n### {setting.name} (episodes: easy {n['easy']}, medium {n['medium']}, hard {n['hard']})\n")
        print("| agent | easy eps / stop / perf / SPL | medium | hard | agent FPS |")
        print("|---|---|---|---|---|")
        for agent in sorted(runs, key=lambda a: (AGENT_ORDER.index(a) if a in AGENT_ORDER else 99, a)):
            r = runs[agent]
            cells = [cell(r[d]) if d in r else "-" for d in ("easy", "medium", "hard")]
            print(f"| {agent} | " + " | ".join(cells) + f" | {r['runtime']['agent_fps']:.0f} |")


if __name__ == "__main__":
    main(Path(sys.argv[1] if len(sys.argv) > 1 else "outputs/bench"))
