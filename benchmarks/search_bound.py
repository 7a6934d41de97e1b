"""How much SPL can a search reach on hard episodes when nothing in the view tells which side the target is on?

On a ``hard`` start the view and the target share nothing (``|dpitch| > fov`` or ``|dyaw| > fov``), so an agent
must pick a side to pan before it sees the target. :func:`findview.metrics.blind_search_spl` gives the SPL of
an ideal blind searcher: it pans right (or left) and turns straight to the target in the first view that
overlaps it. With a fair coin for the side that is the most any such agent can expect; a fixed side may be
lucky or unlucky on one small set of episodes. Comparing an agent's hard SPL with this bound tells how much of
its shortfall is search (recognising the target late, detours) and how much is the side it cannot know.

    python benchmarks/search_bound.py data/sun360_mini_indoor/episodes/test_fov90.json   # an episode file
    python benchmarks/search_bound.py outputs/eval/<run>                                  # an eval run folder

An eval run folder (``episodes.jsonl`` and ``run.json`` from ``tools/eval.py``) adds the agent's own SPL per
difficulty, its share of exact stops, and the share of exact stops made on the first pass: within the longer
side's blind path (+10 steps), i.e. without passing the target and going round again. Several inputs print one
table each.
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from findview.episode import DIFFICULTIES  # noqa: E402
from findview.metrics import aggregate, blind_search_path, blind_search_spl  # noqa: E402

#: steps of slack over a blind path for a stop to count as found "on the way" (a few moves to centre the view)
SLACK_STEPS = 10


def on_blind_path(record: dict, fov: float) -> bool:
    """Whether an exact stop took at most the longer side's blind path (+ :data:`SLACK_STEPS`): the agent found
    the target on its first pass, whichever side it panned, instead of passing it and going round again."""
    if not (record["called_stop"] and record["eps"] == 0):
        return False
    pose = (record["init_pitch"], record["init_yaw"], record["target_pitch"], record["target_yaw"])
    longer = max(blind_search_path(*pose, fov, "right"), blind_search_path(*pose, fov, "left"))
    return int(record["steps"]) <= longer + SLACK_STEPS


def _load(path: Path, fov: float | None) -> tuple[list[dict], float, bool]:
    """``(episodes or records, fov, has_agent_records)`` of an episode file or an eval run folder."""
    if path.is_dir():
        records_file, run_file = path / "episodes.jsonl", path / "run.json"
        if not records_file.is_file():
            raise SystemExit(f"{path} is a folder without episodes.jsonl (expected a tools/eval.py run folder)")
        records = [json.loads(line) for line in records_file.read_text().splitlines() if line.strip()]
        if fov is None:
            if not run_file.is_file():
                raise SystemExit(f"{path} has no run.json to read the FoV from; pass --fov DEGREES")
            fov = float(json.loads(run_file.read_text())["fov"])
        return records, fov, True
    if not path.is_file():
        raise SystemExit(f"{path}: no such episode file or eval run folder")
    try:
        doc = json.loads(path.read_text())
    except json.JSONDecodeError as err:
        raise SystemExit(f"{path} is not JSON ({err}); expected a findview episode file") from None
    if not isinstance(doc, dict) or "episodes" not in doc:
        raise SystemExit(f"{path} is not a findview episode file (no 'episodes')")
    if fov is None:
        if "fov" not in doc:
            raise SystemExit(f"{path} records no 'fov'; pass --fov DEGREES")
        fov = float(doc["fov"])
    return list(doc["episodes"]), fov, False


def table(path: Path, fov: float | None = None) -> str:
    """The markdown table of one input: per difficulty the blind-search SPL (right, left, coin) and, for an eval
    run, the agent's SPL, the share of its episodes that ended exactly on the target and the share that did so on
    the first pass (:func:`on_blind_path`)."""
    items, fov, has_agent = _load(path, fov)
    head = "| difficulty | episodes | blind, pan right | blind, pan left | blind, coin |"
    rule = "|---|---|---|---|---|"
    if has_agent:
        head += " agent SPL | agent exact stops | exact, first pass |"
        rule += "---|---|---|"
    lines = [f"{path} (FoV {fov:g})", "", head, rule]
    for difficulty in DIFFICULTIES:
        group = [e for e in items if e.get("difficulty") == difficulty]
        if not group:
            continue
        b = blind_search_spl(group, fov)
        row = f"| {difficulty} | {b['episodes']} | {100 * b['right']:.1f}% | {100 * b['left']:.1f}% | {100 * b['coin']:.1f}% |"
        if has_agent:
            m = aggregate(group)
            exact = m["omega_stop"] * m["omega_perf"]  # stopped, and of those exact: the share of exact stops
            first = sum(on_blind_path(r, fov) for r in group) / len(group)
            row += f" {100 * m['spl']:.1f}% | {100 * exact:.1f}% | {100 * first:.1f}% |"
        lines.append(row)
    return "\n".join(lines)


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(
        prog="python benchmarks/search_bound.py",
        description="The SPL a blind search can reach per difficulty (findview.metrics.blind_search_spl), for "
        "episode files and tools/eval.py run folders (which add the agent's SPL).",
        formatter_class=argparse.ArgumentDefaultsHelpFormatter,
    )
    parser.add_argument("inputs", nargs="+", type=Path, help="episode files (.json) or eval run folders")
    parser.add_argument("--fov", type=float, default=None,
                        help="horizontal FoV in degrees (default: the episode file's or run.json's)")
    args = parser.parse_args(argv)
    print("\n\n".join(table(p, args.fov) for p in args.inputs))


if __name__ == "__main__":
    main()
