"""Search memory for learned agents: penalise moves back to poses the agent has already visited.

A recurrent policy that is unsure which way the target lies can settle into a loop: left, right, left,
right, ... until the episode is forced to end at ``T``. :class:`RevisitPenalty` breaks such loops without
any privileged information. The agent dead-reckons its own moves: it keeps, per environment slot, its
offset from the episode's start pose on the 1-step action grid (``UP`` = +1 pitch step, ``DOWN`` = -1,
``RIGHT`` = +1 yaw step, ``LEFT`` = -1; yaw wraps after ``360 / step_deg`` steps) and counts the visits
of every offset. Before the argmax, each move's logit is lowered by ``penalty x visits(destination)``:

- a move the policy prefers by a wide margin is still taken the first times;
- in a 2-cycle the visit counts of both poses grow by one per round, so after a few rounds another
  move (the policy's next choice) wins and the agent leaves the loop;
- the stop decision is the policy's own: where its argmax is ``STOP`` the agent stops, and nowhere else
  (penalised moves never make ``STOP`` win by default).

A move that leaves the view unchanged (``UP`` / ``DOWN`` against the simulator's pitch limit) does not
move the dead-reckoned pose, and the cell it aimed at gains a visit, so pressing into the limit loses its
appeal like a loop does. (A move in a textureless region can leave a small view unchanged too; it is then
taken for a blocked one, so the dead reckoning is approximate there, where the view cannot tell poses apart.)

**Near visits** (:class:`NearVisits`, ``rows > 0``): a search that pans back over the yaw it has seen, one row higher or
lower each time, visits new cells on every pass, so exact-cell counts never stop it; a learned agent drawn to a region
that looks like its target does this for thousands of steps. With ``rows = r``, a move also pays ``penalty`` per visit of
the most visited cell near its destination: for ``LEFT`` / ``RIGHT`` the cells of the destination's column within
``r`` rows of it, for ``UP`` / ``DOWN`` those of its column 1 to ``r`` rows beyond it in the move's direction. Only
visits at least ``age`` steps old count (1: every earlier visit; a larger age leaves recent ones free, such as
the staircase of pitch and yaw moves onto a target just passed); with ``since = s`` the visits of an episode's first
``s - 1`` steps never count as near ones (a turn back over that path, one row off it, is the policy correcting its
first guess of the side, not a search going round again); with ``until = u`` an episode's near visits stop counting
once its agent finds the view near the target with probability at least ``u`` (:meth:`RevisitPenalty.found_near`,
called by an agent with a stop-offset net): a search hovering by a target it cannot yet stop on is not pushed away
from it. A penalty below the memory's own keeps it a nudge:
going back over ground a few rows off the old path costs less than an exact revisit, and a move the policy prefers by
a wide margin (its last moves onto a target it sees) is still taken.

**Row search** (:class:`RowSearch`, ``stride > 0``): the memory alone leaves a finished row one step at a time, so a target far
above or below is found late or never. With a stride ``s`` (in steps; 45 = half of a 90-degree FoV), once the
rows within 2 steps of the current one hold ``row_cover`` of a full turn of yaw cells, the agent's moves are
replaced by pitch moves to the next search row, at offsets ``+s, -s, +2s, -2s, ...`` from its start row; there
the policy acts again. A forced move that is blocked (the pitch limit) skips to the next row, and later rows
beyond a limit the episode has met are skipped without a move (before, each was walked to across the whole pitch
range and blocked again: 121 steps a row for a FoV-90 view); rows beyond ``max_pitch_steps``, or beyond the
limits on both sides, end the search. ``STOP`` still wins wherever it is the policy's argmax.

Two settings make the row search a **safety net** for a learned search. ``after = a`` (steps): the rows are
forced only from the ``a``-th step of an episode on; before it the policy searches alone, so the episodes it
finishes in time are untouched. ``budget = b`` (steps): once the search has chosen a row (or, for the first, once
it starts), it moves on to the next after ``b`` steps even if the band is not looked around. A learned agent unsure
which row to search next can zigzag up and down, one yaw column per pass, or pace between two rows it has looked
around (each of them a row of visited cells that costs ``penalty`` to step into): every cell it visits is new, no
band ever fills, and without a budget the search never takes it anywhere else. ``hold``: a policy that paces a
column walks off a row the moment the search has brought it there; with the hold a pitch move more than ``s // 2``
steps from the current row is barred until the search moves on (the best move left takes its logit, so ``STOP``
never wins by it), and the agent moves along the row instead.

Visit counts live in one ``(N, 2 * max_pitch_steps + 1, 360 / step_deg)`` int16 tensor (260 KB per slot at
1 degree) on the policy's device, beside a running per-column count of the seen cells below each row (the same
size), so the band sums of :meth:`RevisitPenalty.memory_features` are a few gathers, not a pass over the grid (with
near visits, one int32 tensor of the same shape holds each cell's last-visit step, 520 KB per slot);
every operation is batched over the slots (no Python loop over environments).
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import torch

__all__ = ["MEMORY_FEATURES", "NearVisits", "RowSearch", "SEARCH_ROWS", "RevisitPenalty", "make_revisit_penalty",
           "memory_band"]

#: the search rows of :meth:`RevisitPenalty.memory_features`, in units of ``band + 1`` steps from the start row
SEARCH_ROWS = (1, -1, 2, -2)
#: columns of :meth:`RevisitPenalty.memory_features` (the input width of a policy that reads the search memory)
MEMORY_FEATURES = 3 + len(SEARCH_ROWS)


def memory_band(fov: float, step_deg: int = 1) -> int:
    """Half-height, in steps, of the row band one view covers for :meth:`RevisitPenalty.memory_features`:
    ``round(fov / 2 / step_deg) - 1`` (at least 1): after half a FoV of pitch moves the band no longer holds the
    row the agent looked around. ``fov`` in degrees."""
    return max(1, int(round(float(fov) / 2.0 / int(step_deg))) - 1)


@dataclass(frozen=True)
class NearVisits:
    """The near-visit settings of a search memory (module docstring, "Near visits"; ``rows = 0``: off).

    Attributes:
        rows: rows (1-degree steps) of a move's near cells.
        penalty: logit units per visit of the most visited near cell.
        age: steps since a near cell's last visit before that visit counts.
        since: visits made before this step of an episode never count as near ones (0: every visit counts). The
            path out of an episode's first steps stays free to walk back along, one row off it: a policy that
            corrects its first guess of the side (a medium target seen at the edge of the view after a few steps
            the wrong way) turns back over it; a search that goes round again later is charged.
        until: an agent whose stop-offset net finds an episode's view near its target with at least this probability
            (in (0, 1)) stops counting that episode's near visits (0: they count to the end). The memory only keeps
            the flag (:meth:`RevisitPenalty.found_near`); the agent measures.
    """

    rows: int = 0
    penalty: float = 0.0
    age: int = 1
    since: int = 0
    until: float = 0.0

    def __post_init__(self) -> None:
        if (int(self.rows) < 0 or (int(self.rows) > 0 and not float(self.penalty) > 0) or int(self.age) < 1
                or int(self.since) < 0 or not 0.0 <= float(self.until) < 1.0):
            raise ValueError(f"near visits: need rows >= 0, penalty > 0 logit units when rows > 0, age >= 1 step, "
                             f"since >= 0 steps, 0 <= until < 1 (a probability, 0 = off); got rows={self.rows}, "
                             f"penalty={self.penalty}, age={self.age}, since={self.since}, until={self.until}")

    @classmethod
    def of(cls, agent: Any) -> "NearVisits":
        """The settings of a learned agent's typed config (``revisit_near_rows``, ``_penalty``, ``_age``, ``_since``,
        ``_until``; a null ``_until`` is 0, off)."""
        return cls(int(agent.revisit_near_rows), float(agent.revisit_near_penalty), int(agent.revisit_near_age),
                   int(agent.revisit_near_since), float(agent.revisit_near_until or 0.0))


@dataclass(frozen=True)
class RowSearch:
    """The row-search settings of a search memory (module docstring, "Row search"; ``stride = 0``: off).

    Attributes:
        stride: steps between search rows (45 = half of a 90-degree FoV at 1 degree per step).
        after: the step of an episode from which the row search acts (0: from its first step).
        budget: steps at one search row after which the search moves on though the row is not looked around
            (0: no limit).
        hold: once on its search row (the start row first), the agent may not move more than ``stride // 2``
            steps above or below it until the search moves on: a policy that paces a column walks off a row as soon
            as it is brought there; every pitch is within ``stride // 2`` of some row, so a target the row shows
            can still be reached. Only from ``after`` on, like the rest of the search.

    Raises:
        ValueError: a negative setting, or ``after`` / ``budget`` / ``hold`` without a row search (``stride`` 0).
    """

    stride: int = 0
    after: int = 0
    budget: int = 0
    hold: bool = False

    def __post_init__(self) -> None:
        for name in ("stride", "after", "budget"):  # stored as ints once, so the hot path reads them as they are
            object.__setattr__(self, name, int(getattr(self, name)))
        object.__setattr__(self, "hold", bool(self.hold))
        if self.stride < 0 or self.after < 0 or self.budget < 0:
            raise ValueError(f"row search: need stride, after and budget >= 0 steps, got stride={self.stride}, "
                             f"after={self.after}, budget={self.budget}")
        if (self.after or self.budget or self.hold) and not self.stride:
            raise ValueError(f"row search: after={self.after}, budget={self.budget} steps and hold={self.hold} need a "
                             f"row search (agent.revisit_row_stride > 0), got stride=0")

    @classmethod
    def of(cls, agent: Any) -> "RowSearch":
        """The settings of a learned agent's typed config (``revisit_row_stride``, ``_after``, ``_budget``, ``_hold``)."""
        return cls(agent.revisit_row_stride, agent.revisit_row_after, agent.revisit_row_budget, agent.revisit_row_hold)


def make_revisit_penalty(
    num_envs: int, device: str | torch.device, revisit_penalty: float = 0.0, rows: RowSearch = RowSearch(),
    near: NearVisits = NearVisits(),
) -> "RevisitPenalty | None":
    """The search memory of ``num_envs`` slots, or ``None`` when ``revisit_penalty`` is 0 (off); ``rows``: its row
    search (:class:`RowSearch`); ``near``: its near visits (:class:`NearVisits`).

    Raises:
        ValueError: a negative or NaN penalty.
    """
    penalty = float(revisit_penalty)
    if penalty < 0 or penalty != penalty:
        raise ValueError(f"revisit_penalty must be >= 0 logit units per visit (0 = off), got {revisit_penalty}")
    if penalty == 0:
        return None
    return RevisitPenalty(num_envs, penalty, device, rows=rows, near=near)

#: (pitch, yaw) grid steps of UP, DOWN, LEFT, RIGHT (STOP does not move)
_MOVES = ((1, 0), (-1, 0), (0, -1), (0, 1))


class RevisitPenalty:
    """Dead-reckoned visit counts per slot, and the logit penalty they imply.

    Args:
        num_envs: number of environment slots ``N``.
        penalty: logit units subtracted per earlier visit of a move's destination (``> 0``).
        device: where the counts live (the policy's device).
        step_deg: degrees per action (the yaw grid has ``360 / step_deg`` cells).
        max_pitch_steps: pitch offsets are clamped to ``[-max_pitch_steps, max_pitch_steps]`` steps
            (180 degrees covers any start and target).
        rows: the row search (:class:`RowSearch`; the default: off; see the module docstring).
        row_cover: share of a full turn of yaw cells seen near the current row that counts it as looked around
            (0 < x <= 1; the row search and :meth:`memory_features`).
        near: the near visits a move also pays for (:class:`NearVisits`; the default: off; see the module docstring).
    """

    def __init__(
        self, num_envs: int, penalty: float, device: str | torch.device = "cpu", step_deg: int = 1,
        max_pitch_steps: int | None = None, rows: RowSearch = RowSearch(), row_cover: float = 0.9,
        near: NearVisits = NearVisits(),
    ) -> None:
        if not penalty > 0:
            raise ValueError(f"revisit penalty must be > 0 logit units per visit, got {penalty}")
        if not 0.0 < float(row_cover) <= 1.0:
            raise ValueError(f"row_cover must be in (0, 1] (a share of a full turn), got {row_cover}")
        if int(step_deg) < 1 or 360 % int(step_deg):
            raise ValueError(f"step_deg must be a positive divisor of 360, got {step_deg}")
        self.penalty = float(penalty)
        self.device = torch.device(device)
        self.yaw_cells = 360 // int(step_deg)
        self.max_pitch = int(max_pitch_steps if max_pitch_steps is not None else 180 // int(step_deg))
        n = int(num_envs)
        self.visits = torch.zeros((n, 2 * self.max_pitch + 1, self.yaw_cells), dtype=torch.int16, device=self.device)
        # seen_below[k, r, y]: cells of column y with a visit in rows [0, r) (r = 0 .. rows), kept in step with visits
        self.seen_below = torch.zeros((n, self.visits.shape[1] + 1, self.yaw_cells), dtype=torch.int16, device=self.device)
        self._row_ids = torch.arange(self.visits.shape[1] + 1, device=self.device)
        self.pitch = torch.zeros(n, dtype=torch.long, device=self.device)  # offset in steps, 0 at the start
        self.yaw = torch.zeros(n, dtype=torch.long, device=self.device)  # offset in steps, in [0, yaw_cells)
        self.last_move = torch.full((n,), -1, dtype=torch.long, device=self.device)  # -1: none pending
        self.last_view: torch.Tensor | None = None
        self._moves = torch.tensor(_MOVES, dtype=torch.long, device=self.device)  # (4, 2)
        # near visits: per move, the row offsets of its near cells from its destination, (4, 2 * rows) (a pitch move's
        # `rows` cells beyond it, listed twice to fill the width; amax reads them once)
        self.near = near
        r = self.near_rows = int(near.rows)
        beyond, side = list(range(1, r + 1)), [k for k in range(-r, r + 1) if k]
        self._near_rows = torch.tensor([beyond + beyond, [-k for k in beyond] * 2, side, side],
                                       dtype=torch.long, device=self.device)
        # the step of each cell's last visit and each slot's steps since its reset (kept with near visits only)
        self.last_visit = torch.zeros(self.visits.shape if r else (n, 1, 1), dtype=torch.int32, device=self.device)
        self.clock = torch.zeros(n, dtype=torch.int32, device=self.device)
        self.near_found = torch.zeros(n, dtype=torch.bool, device=self.device)  # near visits no longer count (until)
        # row search (rows.stride > 0): after a turn, move to the next search row, start + s, - s, + 2s, - 2s, ...
        self.rows = rows
        self.cover_cells = max(1, int(round(float(row_cover) * self.yaw_cells)))
        self.row_k = torch.zeros(n, dtype=torch.long, device=self.device)  # index of the current search row
        self.row_target = torch.zeros(n, dtype=torch.long, device=self.device)  # its pitch offset, steps
        self.row_seek = torch.zeros(n, dtype=torch.bool, device=self.device)  # on the way to it
        self.row_started = torch.zeros(n, dtype=torch.int32, device=self.device)  # clock when the row was chosen
        # the pitch offsets (steps) where a forced move was blocked, above and below the start (the simulator's pitch
        # limits, as far as this episode has met them): rows beyond them are skipped, not walked to again
        self.row_reach_hi = torch.full((n,), self.max_pitch, dtype=torch.long, device=self.device)
        self.row_reach_lo = torch.full((n,), -self.max_pitch, dtype=torch.long, device=self.device)
        self.last_blocked = torch.zeros(n, dtype=torch.bool, device=self.device)

    def reset(self, env_ids: torch.Tensor) -> None:
        """Slots ``env_ids`` (long tensor) start a new episode at offset (0, 0) with no visits."""
        ids = env_ids.to(self.device)
        self.visits[ids] = 0
        self.last_visit[ids] = 0
        self.clock[ids] = 0
        self.near_found[ids] = False
        self.seen_below[ids] = 0
        self.pitch[ids] = 0
        self.yaw[ids] = 0
        self.last_move[ids] = -1
        self.row_k[ids] = 0
        self.row_target[ids] = 0
        self.row_seek[ids] = False
        self.row_started[ids] = 0
        self.row_reach_hi[ids] = self.max_pitch
        self.row_reach_lo[ids] = -self.max_pitch
        self.last_blocked[ids] = False

    def mark_row_seen(self, env_ids: torch.Tensor) -> None:
        """Slots ``env_ids`` (long tensor) count one visit in every yaw cell of their current row, as if they had
        looked around it a full turn (a training augmentation: the "row done" state from an episode's start)."""
        ids = env_ids.to(self.device)
        rows = self.pitch[ids] + self.max_pitch
        self.visits[ids, rows] = torch.clamp(self.visits[ids, rows], min=1)
        if self.near_rows:  # the turn it did not make lies in the past: older than any age
            self.last_visit[ids, rows] = -(2 ** 30)
        self._recount(ids)

    def _recount(self, ids: torch.Tensor) -> None:
        """Rebuild :attr:`seen_below` of slots ``ids`` from their visit counts (after a whole-row or bulk write)."""
        seen = (self.visits[ids] > 0).to(torch.int16)
        self.seen_below[ids] = torch.nn.functional.pad(seen.cumsum(dim=1, dtype=torch.int16), (0, 0, 1, 0))

    def _visit(self, slots: torch.Tensor, rows: torch.Tensor, cols: torch.Tensor) -> None:
        """Count one visit of cell ``(rows, cols)`` (grid indices) for each of ``slots`` (three ``(M,)`` long
        tensors, distinct slots); a cell seen for the first time adds one to its column's counts above it."""
        first = self.visits[slots, rows, cols] == 0
        self.visits[slots, rows, cols] += 1
        if self.near_rows:
            self.last_visit[slots, rows, cols] = self.clock[slots]
        above = (self._row_ids[None, :] > rows[:, None]) & first[:, None]  # (M, rows + 1)
        self.seen_below[slots, :, cols] += above.to(torch.int16)

    def _destinations(self, idx: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """Pitch row and yaw column of each move's destination: two ``(K, 4)`` long tensors."""
        p = (self.pitch[idx, None] + self._moves[None, :, 0]).clamp(-self.max_pitch, self.max_pitch) + self.max_pitch
        y = (self.yaw[idx, None] + self._moves[None, :, 1]) % self.yaw_cells
        return p, y

    def adjust(self, idx: torch.Tensor, view: torch.Tensor, logits: torch.Tensor) -> torch.Tensor:
        """Record the arrival of slots ``idx`` at their current pose; return penalised logits.

        Args:
            idx: ``(K,)`` long slot indices acting now.
            view: ``(K, 3, H, W)`` uint8, their current views (a move that left the view unchanged was blocked).
            logits: ``(K, 5)`` action logits (``UP, DOWN, LEFT, RIGHT, STOP``).

        Returns:
            ``(K, 5)`` logits: where the policy's argmax is ``STOP``, only ``STOP`` is finite; elsewhere ``STOP`` is
            ``-inf`` and each move has ``penalty x visits(destination)`` subtracted.

        The same as :meth:`arrive` followed by :meth:`penalise` (a policy that reads :meth:`memory_features`
        calls the two around its forward pass).
        """
        self.arrive(idx, view)
        return self.penalise(idx, logits)

    def arrive(self, idx: torch.Tensor, view: torch.Tensor) -> None:
        """Slots ``idx`` ``(K,)`` arrive at their current pose: apply their pending moves (unless ``view``
        ``(K, 3, H, W)`` shows a blocked one) and count the visit. Call once per step, before :meth:`penalise`."""
        idx = idx.to(self.device)
        self.clock[idx] += 1
        self._settle(idx, view.to(self.device))
        self._visit(idx, self.pitch[idx] + self.max_pitch, self.yaw[idx])

    def penalise(self, idx: torch.Tensor, logits: torch.Tensor) -> torch.Tensor:
        """The logits ``(K, 5)`` of slots ``idx`` after their :meth:`arrive`, penalised as :meth:`adjust` says."""
        idx = idx.to(self.device)
        rows = self.pitch[idx] + self.max_pitch
        out = logits.clone()
        out[:, :4] = out[:, :4] - self.move_penalties(idx).to(out.dtype)
        if self.rows.stride > 0:
            self._row_search(idx, rows, out)
        # the stop decision stays the policy's own: penalised moves must not make STOP win by default
        stop = logits.argmax(dim=-1) == 4
        out[:, 4] = torch.where(stop, logits[:, 4], torch.full_like(logits[:, 4], float("-inf")))
        out[stop] = torch.where(torch.arange(5, device=out.device) == 4, logits[stop], torch.full_like(logits[stop], float("-inf")))
        return out

    def move_penalties(self, idx: torch.Tensor) -> torch.Tensor:
        """``(K, 4)`` float32: the logit units :meth:`penalise` subtracts from UP, DOWN, LEFT, RIGHT of slots ``idx``
        (``penalty x`` earlier visits of each move's destination, plus ``near.penalty x`` the visits of its most
        visited near cell, module docstring "Near visits"). Call it after :meth:`arrive`."""
        idx = idx.to(self.device)
        p, y = self._destinations(idx)  # (K, 4) each
        out = self.penalty * self.visits[idx[:, None], p, y].to(torch.float32)
        if self.near_rows:
            rows = p[:, :, None] + self._near_rows[None]  # (K, 4, 2 * near.rows)
            inside = (rows >= 0) & (rows < self.visits.shape[1])
            cells = (idx[:, None, None], rows.clamp(0, self.visits.shape[1] - 1), y[:, :, None])
            old = self.clock[idx, None, None] - self.last_visit[cells] >= self.near.age
            if self.near.since:
                old = old & (self.last_visit[cells] >= self.near.since)
            if self.near.until:
                old = old & ~self.near_found[idx, None, None]
            near = torch.where(old & inside, self.visits[cells], 0).amax(dim=-1)
            out = out + self.near.penalty * near.to(torch.float32)
        return out

    def found_near(self, env_ids: torch.Tensor, near_prob: torch.Tensor) -> None:
        """Slots ``env_ids`` (``(M,)`` long) whose stop-offset net gave their view ``near_prob`` (``(M,)``) of being
        near the target: those at ``near.until`` or more no longer count near visits until their next reset. A
        no-op without ``near.until``."""
        if self.near.until:
            self.near_found[env_ids.to(self.device)[near_prob.to(self.device) >= self.near.until]] = True

    def memory_features(self, idx: torch.Tensor, band: int) -> torch.Tensor:
        """What the memory says about the search so far, as ``(K, MEMORY_FEATURES)`` float32 inputs for a policy.

        ``band`` (steps, >= 1) is the half-height of the row band a view covers (half a FoV less one step: the
        agents call it with :func:`memory_band`). With ``p`` the current pitch offset, a yaw cell counts as
        *seen* in a band of rows when any row of the band has a visit in that column; the columns are:

        0. ``1.0`` when the band ``[p - band, p + band]`` holds ``row_cover`` (default 0.9) of a full turn of seen cells
           (the current row has been looked around), else ``0.0``;
        1. the share of a full turn seen in that band (0..1);
        2.-5. the same "done" for the bands around the search rows ``+s, -s, +2s, -2s`` (``s = band + 1`` steps)
           from the start (rows fixed in the episode, so a search can be planned from them);
        6. ``p`` in units of 90 steps (signed: ``+`` above the start), clamped to ``[-2, 2]``.

        Call it after :meth:`arrive` (the current pose and its visit are counted).
        """
        band = int(band)
        if band < 1:
            raise ValueError(f"memory band must be >= 1 steps, got {band}")
        idx = idx.to(self.device)
        rows = self.pitch[idx] + self.max_pitch  # (K,) row of the current pose
        last = self.visits.shape[1]

        def cells(lo: torch.Tensor, hi: torch.Tensor) -> torch.Tensor:  # seen columns in rows [lo, hi]
            lo = lo.clamp(0, last)
            hi = (hi + 1).clamp(0, last)
            return ((self.seen_below[idx, hi] - self.seen_below[idx, lo]) > 0).sum(dim=-1)  # (K,)

        here = cells(rows - band, rows + band)
        cover = self.cover_cells
        columns = [(here >= cover).float(), here.float() / self.yaw_cells]
        start = torch.full_like(rows, self.max_pitch)
        for k in SEARCH_ROWS:  # the search rows +s, -s, +2s, -2s from the start
            centre = start + k * (band + 1)
            columns.append((cells(centre - band, centre + band) >= cover).float())
        columns.append((self.pitch[idx].float() / 90.0).clamp(-2.0, 2.0))
        return torch.stack(columns, dim=1)

    def _row_search(self, idx: torch.Tensor, rows: torch.Tensor, out: torch.Tensor) -> None:
        """Row search: once the band of +-2 rows around the current one holds ``row_cover`` of a turn (or the row's
        ``rows.budget`` is spent), force pitch moves to the next search row (offsets ``+s, -s, +2s, -2s, ...`` from the
        start, ``s = rows.stride``); a forced move that is blocked (the pitch limit) skips to the next row, and the
        offset where it was blocked bounds the rows on its side for the rest of the episode: a row beyond a limit met
        is skipped where it comes (the next, on the other side, is chosen at once), not walked to through every
        row in between. Nothing is forced before step ``rows.after``. Edits ``out`` (K, 5) in place."""
        after, budget = self.rows.after, self.rows.budget
        band = (rows[:, None] + torch.arange(-2, 3, device=self.device)[None]).clamp(0, 2 * self.max_pitch)  # (K, 5)
        coverage = (self.visits[idx[:, None], band] > 0).any(dim=1).sum(dim=-1)  # (K,) yaw cells seen in the band
        seek = self.row_seek[idx]
        pitch = self.pitch[idx]
        blocked = seek & self.last_blocked[idx]
        upward = self.row_target[idx] > pitch  # the way the blocked seek went
        hi = torch.where(blocked & upward, pitch, self.row_reach_hi[idx])
        lo = torch.where(blocked & ~upward, pitch, self.row_reach_lo[idx])
        self.row_reach_hi[idx], self.row_reach_lo[idx] = hi, lo
        seek = seek & (pitch != self.row_target[idx])  # arrived
        clock = self.clock[idx]
        done = coverage >= self.cover_cells
        if budget > 0:  # steps since the row was chosen (or since the search started)
            done = done | (clock - self.row_started[idx].clamp(min=after) > budget)
        live = clock > after
        advance = live & (blocked | (~seek & done))
        k = self.row_k[idx] + advance.long()
        target = self._row_offset(k)
        # a row beyond a limit met is skipped: the next row lies on the other side (+s, -s, +2s, -2s, ...)
        skip = advance & ((target > hi) | (target < lo))
        k = k + skip.long()
        target = torch.where(skip, self._row_offset(k), target)
        target = torch.where(advance, target, self.row_target[idx])
        seek = (seek | advance) & (target <= hi) & (target >= lo)  # none left on either side: the search ends
        self.row_k[idx] = k
        self.row_started[idx] = torch.where(advance, clock, self.row_started[idx])
        self.row_target[idx] = target
        self.row_seek[idx] = seek
        toward = torch.where(target > pitch, 0, 1)  # UP raises the pitch offset, DOWN lowers it
        forced = torch.full_like(out[:, :4], float("-inf"))
        forced.scatter_(1, toward[:, None], 0.0)
        if self.rows.hold:
            self._hold_row(live & ~seek, pitch, target, out)
        out[:, :4] = torch.where(seek[:, None], forced, out[:, :4])

    def _hold_row(self, held: torch.Tensor, pitch: torch.Tensor, target: torch.Tensor, out: torch.Tensor) -> None:
        """``RowSearch.hold``: for the slots ``held`` (K,), a pitch move more than ``stride // 2`` steps from the
        row ``target`` (K,) is barred. Where the policy's best move was barred, the best move left gets that move's
        logit, so barring never lets ``STOP`` win. Edits ``out`` (K, 5) in place."""
        half = self.rows.stride // 2
        barred = torch.stack([held & (pitch + 1 > target + half), held & (pitch - 1 < target - half)], dim=1)  # UP, DOWN
        moves = out[:, :4]
        top = moves.max(dim=1).values
        left = moves.clone()
        left[:, :2] = left[:, :2].masked_fill(barred, float("-inf"))
        best = left.max(dim=1)
        lift = best.values < top  # the barred move was the best
        left.scatter_(1, best.indices[:, None], torch.where(lift, top, best.values)[:, None])
        out[:, :4] = left

    def _row_offset(self, k: torch.Tensor) -> torch.Tensor:
        """Pitch offset (steps from the start row) of search row ``k``: 0, +s, -s, +2s, -2s, ... (``s`` the stride)."""
        m = (k + 1) // 2
        return torch.where(k % 2 == 1, m, -m) * self.rows.stride

    def moved(self, idx: torch.Tensor, actions: torch.Tensor) -> None:
        """Slots ``idx`` take ``actions`` ``(K,)``; their poses move at the next :meth:`adjust`."""
        self.last_move[idx.to(self.device)] = torch.where(actions < 4, actions, torch.full_like(actions, -1)).to(self.device)

    def _settle(self, idx: torch.Tensor, view: torch.Tensor) -> None:
        """Apply the pending moves of ``idx`` unless the view did not change (a blocked move)."""
        if self.last_view is None or self.last_view.shape[1:] != view.shape[1:]:
            self.last_view = torch.zeros((self.pitch.shape[0],) + tuple(view.shape[1:]), dtype=view.dtype, device=self.device)
        move = self.last_move[idx]
        changed = (self.last_view[idx] != view).flatten(1).any(dim=1)
        go = (move >= 0) & changed
        step = self._moves[move.clamp(min=0)]  # (K, 2)
        blocked = (move >= 0) & ~changed
        self.last_blocked[idx] = blocked
        if bool(blocked.any()):  # count the unreachable cell as visited, so the blocked move loses its appeal
            b = idx[blocked]
            p = (self.pitch[b] + step[blocked, 0]).clamp(-self.max_pitch, self.max_pitch) + self.max_pitch
            y = (self.yaw[b] + step[blocked, 1]) % self.yaw_cells
            self._visit(b, p, y)
        step = step * go[:, None].long()
        self.pitch[idx] = (self.pitch[idx] + step[:, 0]).clamp(-self.max_pitch, self.max_pitch)
        self.yaw[idx] = (self.yaw[idx] + step[:, 1]) % self.yaw_cells
        self.last_move[idx] = -1
        self.last_view[idx] = view

    # resume state (DAgger rollouts that act with the penalty resume exactly) -------------------------
    def state_dict(self) -> dict[str, Any]:
        """Counts, poses, pending moves and last views as CPU tensors (``weights_only=True`` loads them)."""
        return {
            "visits": self.visits.cpu().clone(),
            "pitch": self.pitch.cpu().clone(),
            "yaw": self.yaw.cpu().clone(),
            "last_move": self.last_move.cpu().clone(),
            "last_view": None if self.last_view is None else self.last_view.cpu().clone(),
            "row": torch.stack([self.row_k, self.row_target, self.row_seek.long(), self.last_blocked.long(),
                                self.row_started.long(), self.row_reach_hi, self.row_reach_lo]).cpu(),
            "last_visit": self.last_visit.cpu().clone(),
            "clock": self.clock.cpu().clone(),
            "near_found": self.near_found.cpu().clone(),
        }

    def load_state_dict(self, state: dict[str, Any]) -> None:
        """Restore :meth:`state_dict`; raises ``ValueError`` if it was saved for another number of slots or grid."""
        if tuple(state["visits"].shape) != tuple(self.visits.shape):
            raise ValueError(
                f"revisit state holds visit counts of shape {tuple(state['visits'].shape)}, this agent needs "
                f"{tuple(self.visits.shape)} (slots, pitch cells, yaw cells)"
            )
        self.visits.copy_(state["visits"])
        self._recount(torch.arange(self.visits.shape[0], device=self.device))
        self.pitch.copy_(state["pitch"])
        self.yaw.copy_(state["yaw"])
        self.last_move.copy_(state["last_move"])
        if state.get("row") is not None:
            row = state["row"].to(self.device)
            self.row_k.copy_(row[0])
            self.row_target.copy_(row[1])
            self.row_seek.copy_(row[2].bool())
            self.last_blocked.copy_(row[3].bool())
            self.row_started.copy_(row[4] if row.shape[0] > 4 else torch.zeros_like(row[0]))  # saved before row budgets
            if row.shape[0] > 6:  # the pitch limits the episodes had met
                self.row_reach_hi.copy_(row[5])
                self.row_reach_lo.copy_(row[6])
            else:  # saved before the limits were kept: none met
                self.row_reach_hi.fill_(self.max_pitch)
                self.row_reach_lo.fill_(-self.max_pitch)
        last = state.get("last_view")
        self.last_view = None if last is None else last.to(self.device).clone()
        if state.get("clock") is not None:  # the steps since each reset (near-visit ages, the row search's start)
            self.clock.copy_(state["clock"])
        self.near_found.copy_(state["near_found"] if state.get("near_found") is not None  # saved before the flag: none
                              else torch.zeros_like(self.near_found))
        if self.near_rows:  # the ages of the restored visits: a state saved without near visits has none
            saved = state.get("last_visit")
            if saved is None or tuple(saved.shape) != tuple(self.last_visit.shape):
                raise ValueError(f"revisit state was saved without near visits (last-visit steps of shape "
                                 f"{None if saved is None else tuple(saved.shape)}); this memory counts them "
                                 f"({self.near}): resume with the near-visit settings it was saved with")
            self.last_visit.copy_(saved)
