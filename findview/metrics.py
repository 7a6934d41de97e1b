"""Per-episode records and the paper's aggregate metrics (docs/TASK.md, Metrics).

An *episode record* is a plain dict (JSON-serialisable) with the keys listed in ``RECORD_KEYS``
(see docs/ARCHITECTURE.md, "Episode record")::

    episode_id, image, label, difficulty, init_pitch, init_yaw, target_pitch, target_yaw,
    final_pitch, final_yaw, steps, called_stop, eps, shortest_path

Angles are integer degrees. ``steps`` counts every action taken, the ``stop`` action included.
``eps`` is the localization error ``|dpitch| + dyaw`` at the end (wrapped yaw difference, degrees) and
``shortest_path`` is ``L* = |dpitch0| + dyaw0 + 1`` (the shortest path from the start plus the stop).

Aggregates per difficulty (:func:`summarize`), all fractions in ``[0, 1]``:

- ``eps``: mean localization error over the episodes (degrees);
- ``omega_stop``: share of episodes ended by the agent's ``stop`` (forced stops at ``T`` do not count);
- ``omega_perf``: among the episodes ended by ``stop``, the share with ``eps == 0``. When no episode of a
  group was ended by ``stop`` the ratio is undefined; we report ``0.0`` (nothing was localized by a stop);
- ``spl``: ``mean_i S_i * L*_i / max(L_i, L*_i)`` with ``S_i = called_stop and eps == 0``;
- ``episodes``: the number of episodes in the group.
"""

from __future__ import annotations

import math
from collections.abc import Iterable, Mapping
from typing import Any

from findview.episode import DIFFICULTIES, Episode
from findview.geometry import l1_distance, yaw_diff

__all__ = [
    "RECORD_KEYS",
    "METRIC_KEYS",
    "make_record",
    "episode_spl",
    "blind_search_path",
    "blind_search_spl",
    "aggregate",
    "summarize",
    "format_table",
]

RECORD_KEYS = (
    "episode_id",
    "image",
    "label",
    "difficulty",
    "init_pitch",
    "init_yaw",
    "target_pitch",
    "target_yaw",
    "final_pitch",
    "final_yaw",
    "steps",
    "called_stop",
    "eps",
    "shortest_path",
)
METRIC_KEYS = ("eps", "omega_stop", "omega_perf", "spl", "episodes")


def make_record(
    episode: Episode, final_pitch: int, final_yaw: int, steps: int, called_stop: bool
) -> dict[str, Any]:
    """Build the record of a finished episode.

    Args:
        episode: the episode that was run.
        final_pitch, final_yaw: the camera rotation at the end (integer degrees).
        steps: number of actions taken, the final ``stop`` included (a forced stop at ``T`` has
            ``steps == T``).
        called_stop: ``True`` iff the agent ended the episode with ``stop``.

    Returns:
        A dict with the keys of :data:`RECORD_KEYS`; ``eps = |dpitch| + dyaw`` at the end and
        ``shortest_path = |dpitch0| + dyaw0 + 1`` (degrees / steps, ints).
    """
    final_pitch, final_yaw, steps = int(final_pitch), int(final_yaw), int(steps)
    if steps < 0:
        raise ValueError(f"steps must be >= 0, got {steps}")
    eps = l1_distance(final_pitch, final_yaw, episode.target_pitch, episode.target_yaw)
    shortest = l1_distance(episode.init_pitch, episode.init_yaw, episode.target_pitch, episode.target_yaw) + 1
    return {
        "episode_id": episode.episode_id,
        "image": episode.image,
        "label": episode.label,
        "difficulty": episode.difficulty,
        "init_pitch": int(episode.init_pitch),
        "init_yaw": int(episode.init_yaw),
        "target_pitch": int(episode.target_pitch),
        "target_yaw": int(episode.target_yaw),
        "final_pitch": final_pitch,
        "final_yaw": final_yaw,
        "steps": steps,
        "called_stop": bool(called_stop),
        "eps": int(eps),
        "shortest_path": int(shortest),
    }


def _record_eps(r: Mapping[str, Any]) -> float:
    if "eps" in r and r["eps"] is not None:
        return float(r["eps"])
    try:
        return float(
            l1_distance(int(r["final_pitch"]), int(r["final_yaw"]), int(r["target_pitch"]), int(r["target_yaw"]))
        )
    except KeyError as e:
        raise KeyError(f"episode record {r.get('episode_id', '?')!r} has no 'eps' and no {e} to compute it") from e


def _record_shortest(r: Mapping[str, Any]) -> float:
    if "shortest_path" in r and r["shortest_path"] is not None:
        return float(r["shortest_path"])
    try:
        return float(
            l1_distance(int(r["init_pitch"]), int(r["init_yaw"]), int(r["target_pitch"]), int(r["target_yaw"])) + 1
        )
    except KeyError as e:
        raise KeyError(
            f"episode record {r.get('episode_id', '?')!r} has no 'shortest_path' and no {e} to compute it"
        ) from e


def episode_spl(record: Mapping[str, Any]) -> float:
    """``S * L* / max(L, L*)`` of one record (``S = called_stop and eps == 0``), in ``[0, 1]``."""
    if not bool(record["called_stop"]) or _record_eps(record) != 0:
        return 0.0
    shortest = _record_shortest(record)
    steps = float(record["steps"])
    return shortest / max(steps, shortest)


def blind_search_path(
    init_pitch: int, init_yaw: int, target_pitch: int, target_yaw: int, fov: float, direction: str = "right"
) -> int:
    """Steps (the stop included) of a *blind search* from ``(init_pitch, init_yaw)`` to the target (degrees).

    The blind searcher knows nothing of where the target lies until its view overlaps the target's (the
    overlap rule of the difficulties: ``|dpitch| <= fov`` and ``|dyaw| <= fov``, ``fov`` the horizontal field
    of view in degrees); it recognises the target in the first overlapping view and then takes a shortest
    path. Until then it pans one way (``direction``: ``"right"`` or ``"left"``). Its yaw travel is the yaw
    distance to the target in that direction (``360 - |dyaw|`` the wrong way round) and its pitch travel
    ``|dpitch|``; a start that already overlaps takes the shortest path ``L*``. Where ``|dpitch| > fov`` no
    pan overlaps and the pitch would have to be searched too, so the count is a lower bound there.

    Every agent that does not know the target's side before the views overlap (the ``hard`` starts) needs at
    least these steps, so ``L* / blind_search_path`` bounds its SPL from above on average over the sides.
    """
    if direction not in ("right", "left"):
        raise ValueError(f"direction must be 'right' or 'left', got {direction!r}")
    dp = abs(int(target_pitch) - int(init_pitch))
    if dp <= fov and yaw_diff(int(target_yaw), int(init_yaw)) <= fov:
        return l1_distance(init_pitch, init_yaw, target_pitch, target_yaw) + 1
    turn = int(target_yaw) - int(init_yaw)  # RIGHT raises the yaw
    return dp + (turn if direction == "right" else -turn) % 360 + 1


def blind_search_spl(episodes: Iterable[Episode | Mapping[str, Any]], fov: float) -> dict[str, float | int]:
    """Mean SPL of the blind search (:func:`blind_search_path`) over ``episodes``, panning right, panning left
    and choosing the side by a fair coin (the mean of the two per episode): ``{"right", "left", "coin",
    "episodes"}``, fractions in ``[0, 1]`` (NaN for no episodes). ``episodes``: :class:`Episode` objects or
    records with ``init_pitch, init_yaw, target_pitch, target_yaw``.

    An agent with no cue to the target's side before the views overlap cannot expect more than ``coin`` on
    such episodes; one fixed side can do better or worse on one particular set of episodes.
    """
    right = left = 0.0
    n = 0
    for e in episodes:
        d = e.to_dict() if isinstance(e, Episode) else e
        pose = (int(d["init_pitch"]), int(d["init_yaw"]), int(d["target_pitch"]), int(d["target_yaw"]))
        shortest = l1_distance(*pose) + 1
        right += shortest / blind_search_path(*pose, fov, "right")
        left += shortest / blind_search_path(*pose, fov, "left")
        n += 1
    if n == 0:
        nan = float("nan")
        return {"right": nan, "left": nan, "coin": nan, "episodes": 0}
    return {"right": right / n, "left": left / n, "coin": (right + left) / (2 * n), "episodes": n}


def aggregate(records: Iterable[Mapping[str, Any]]) -> dict[str, float | int]:
    """Metrics of one group of records: ``{"eps", "omega_stop", "omega_perf", "spl", "episodes"}``.

    ``eps`` is the mean error in degrees; the other three are fractions in ``[0, 1]``. An empty group
    gives NaN for ``eps``/``omega_stop``/``spl``, ``0.0`` for ``omega_perf`` and ``episodes = 0``.
    ``omega_perf`` is ``0.0`` when no episode of the group was ended by ``stop``.
    """
    records = list(records)
    n = len(records)
    if n == 0:
        nan = float("nan")
        return {"eps": nan, "omega_stop": nan, "omega_perf": 0.0, "spl": nan, "episodes": 0}
    eps = [_record_eps(r) for r in records]
    stopped = [bool(r["called_stop"]) for r in records]
    n_stop = sum(stopped)
    n_perf = sum(1 for e, s in zip(eps, stopped) if s and e == 0)
    return {
        "eps": sum(eps) / n,
        "omega_stop": n_stop / n,
        "omega_perf": (n_perf / n_stop) if n_stop else 0.0,
        "spl": sum(episode_spl(r) for r in records) / n,
        "episodes": n,
    }


def summarize(
    records: Iterable[Mapping[str, Any]], include_all: bool = False, by: str = "difficulty"
) -> dict[str, dict[str, float | int]]:
    """Aggregate records per difficulty (docs/TASK.md, Metrics).

    Args:
        records: episode records (see module docstring).
        include_all: also add an ``"all"`` entry over every record.
        by: the record key to group on (``"difficulty"``; e.g. ``"label"`` for per-category tables).

    Returns:
        ``{group: {"eps", "omega_stop", "omega_perf", "spl", "episodes"}}``. Difficulties come in the
        order easy, medium, hard, then any other group names sorted; only groups present are listed.
    """
    groups: dict[str, list[Mapping[str, Any]]] = {}
    for r in records:
        if by not in r:
            raise KeyError(f"episode record {r.get('episode_id', '?')!r} has no {by!r} key")
        groups.setdefault(str(r[by]), []).append(r)
    order = [d for d in DIFFICULTIES if d in groups] + sorted(g for g in groups if g not in DIFFICULTIES)
    out = {g: aggregate(groups[g]) for g in order}
    if include_all:
        out["all"] = aggregate([r for g in order for r in groups[g]])
    return out


def _fmt_eps(x: float) -> str:
    if x is None or (isinstance(x, float) and math.isnan(x)):
        return "-"
    return f"{x:.2f}"


def _fmt_pct(x: float) -> str:
    if x is None or (isinstance(x, float) and math.isnan(x)):
        return "-"
    return f"{100.0 * x:.1f}%"


def _is_summary(obj: Mapping[str, Any]) -> bool:
    """True when ``obj`` maps group names straight to metric dicts (one agent's summary)."""
    return all(isinstance(v, Mapping) and "eps" in v for v in obj.values())


def format_table(
    results: Mapping[str, Any], difficulties: Iterable[str] | None = None, row_label: str | None = None
) -> str:
    """Render metrics as a markdown table in the paper's layout.

    Two inputs are accepted:

    - one agent's :func:`summarize` output ``{difficulty: metrics}``: one row per difficulty, columns
      ``eps | omega_stop | omega_perf | SPL | episodes``;
    - several agents ``{agent: {difficulty: metrics}}``: one row per agent and, for each difficulty, the
      four columns ``eps / omega_stop % / omega_perf % / SPL %`` (the paper's Tables 2-7).

    Args:
        results: see above.
        difficulties: the column groups (agents layout) or rows (single layout) to show, in order;
            default: every group present (easy, medium, hard first).
        row_label: header of the first column (default ``"difficulty"`` or ``"agent"``).

    Returns:
        The table as a markdown string (no trailing newline). eps with 2 decimals, shares in percent.
    """
    if not results:
        return "(no results)"
    if _is_summary(results):
        rows = list(difficulties) if difficulties is not None else list(results)
        head = row_label or "difficulty"
        lines = [
            f"| {head} | eps | omega_stop | omega_perf | SPL | episodes |",
            "|---|---|---|---|---|---|",
        ]
        for g in rows:
            m = results.get(g)
            if m is None:
                lines.append(f"| {g} | - | - | - | - | 0 |")
                continue
            lines.append(
                f"| {g} | {_fmt_eps(m['eps'])} | {_fmt_pct(m['omega_stop'])} | {_fmt_pct(m['omega_perf'])} "
                f"| {_fmt_pct(m['spl'])} | {int(m.get('episodes', 0))} |"
            )
        return "\n".join(lines)

    for name, summ in results.items():
        if not isinstance(summ, Mapping) or not _is_summary(summ):
            raise ValueError(f"format_table: entry {name!r} is not a summarize() output")
    if difficulties is None:
        present: list[str] = []
        for summ in results.values():
            present.extend(g for g in summ if g not in present)
        cols = [d for d in DIFFICULTIES if d in present] + [g for g in present if g not in DIFFICULTIES]
    else:
        cols = list(difficulties)
    head = row_label or "agent"
    header = f"| {head} | " + " | ".join(f"{d} eps | {d} stop | {d} perf | {d} SPL" for d in cols) + " |"
    sep = "|---|" + "---|" * (4 * len(cols))
    lines = [header, sep]
    for name, summ in results.items():
        cells = []
        for d in cols:
            m = summ.get(d)
            if m is None:
                cells.extend(["-"] * 4)
            else:
                cells.extend(
                    [_fmt_eps(m["eps"]), _fmt_pct(m["omega_stop"]), _fmt_pct(m["omega_perf"]), _fmt_pct(m["spl"])]
                )
        lines.append(f"| {name} | " + " | ".join(cells) + " |")
    return "\n".join(lines)
