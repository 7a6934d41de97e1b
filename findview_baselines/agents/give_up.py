"""An anytime answer for a learned agent that has not stopped: go back to its most target-like view and stop.

A learned agent whose stop head hesitates (a target under fog, spatter or noise it never becomes sure of) walks
until the episode's step limit ``T`` ends it wherever it happens to be. Its own stop head has usually come
closest to stopping near the target. :class:`GiveUp` remembers, per slot, the pose where the policy's STOP
probability was highest so far (poses dead-reckoned by the search memory,
:class:`~findview_baselines.rl.search_memory.RevisitPenalty`: offsets in 1-step moves from the start pose),
and when the steps left before ``stop_by`` (set it to ``T``) are just enough for the walk back (``|dpitch| +
|dyaw|`` moves, plus ``margin`` for the stop refinement's moves), it takes the slot back there, pitch first, then
yaw the short way round, and answers STOP (which the stop refinement, when on, checks as any other stop).
A slot whose best STOP probability is below ``min_prob`` does not walk back: a stop head that was never even a
little sure has no view worth returning to (on the robust agent's corrupted val episodes, best probabilities
of 0.16-0.42, and one of 0.08, led to within 2 degrees of the target; 0.053 and less to views 39-192 degrees
away).

With ``phase=True`` a slot whose STOP probability never reached ``min_prob`` still has somewhere to go: every step it
also measures the view against the target by phase correlation (:meth:`GiveUp.measure`, with
:func:`~findview_baselines.agents.stop_refine.phase_spectrum`; the agent passes the views as rendered) and keeps the
pose the clearest correlation peak pointed at
(the pose where it was measured plus the rotation measured there). A target under heavy fog that the stop head
never recognises is often still found this way: on the FoV-90 robust file's outdoor fog val episodes that never
stopped, that pose was the target or within 8 degrees of it in all 8, against 18-232 degrees where they ran out
of steps.

It changes nothing but the end of episodes that would otherwise run out of steps: until its last walk home the
agent acts as without it.

Batched over slots, on any device; the walk is capped at ``max_walk`` moves (a dead reckoning that went wrong
in a textureless region cannot keep a slot walking).
"""

from __future__ import annotations

import torch

from findview_baselines.agents.base import DOWN, LEFT, RIGHT, STOP, UP
from findview_baselines.agents.stop_refine import phase_spectrum, rotation_between

__all__ = ["GiveUp"]


class GiveUp:
    """Per-slot best pose and the walk back to it.

    Args:
        num_envs: slots ``N``.
        stop_by: the step by which every slot answers STOP (``T``, ``>= 1``).
        yaw_cells: yaw cells of a full turn (360 at 1 degree per step).
        device: where the state lives (the policy's device).
        margin: steps kept free after the walk's STOP (the stop refinement's moves, plus one).
        min_prob: the least best STOP probability worth walking back to (``[0, 1]``).
        max_walk: most moves of the walk back before the slot stops where it is.
        phase: a slot whose best STOP probability stays below ``min_prob`` walks to the pose its clearest phase
            correlation pointed at (:meth:`measure`, :meth:`observe_phase`) instead of running out of steps.
        fov: the views' horizontal field of view, degrees (needed by :meth:`measure`).
    """

    def __init__(self, num_envs: int, stop_by: int, yaw_cells: int, device: str | torch.device = "cpu",
                 margin: int = 1, min_prob: float = 0.1, max_walk: int = 400, phase: bool = False,
                 fov: float | None = None) -> None:
        if int(stop_by) < 1:
            raise ValueError(f"stop_by must be >= 1 steps, got {stop_by}")
        if int(max_walk) < 1 or int(margin) < 0:
            raise ValueError(f"need max_walk >= 1 moves and margin >= 0 steps, got {max_walk}, {margin}")
        if not 0.0 <= float(min_prob) <= 1.0:
            raise ValueError(f"min_prob must be a probability in [0, 1], got {min_prob}")
        self.min_prob = float(min_prob)
        self.phase = bool(phase)
        self.fov = None if fov is None else float(fov)
        self.stop_by, self.yaw_cells, self.max_walk, self.margin = int(stop_by), int(yaw_cells), int(max_walk), int(margin)
        self.device = torch.device(device)
        n = int(num_envs)
        self.steps = torch.zeros(n, dtype=torch.long, device=self.device)  # acts since the episode started
        self.best = torch.full((n,), -1.0, device=self.device)  # highest STOP probability seen
        self.best_pitch = torch.zeros(n, dtype=torch.long, device=self.device)  # its dead-reckoned pose, steps
        self.best_yaw = torch.zeros(n, dtype=torch.long, device=self.device)
        self.returning = torch.zeros(n, dtype=torch.bool, device=self.device)
        self.walked = torch.zeros(n, dtype=torch.long, device=self.device)
        self.phase_peak = torch.full((n,), -1.0, device=self.device)  # clearest phase-correlation peak seen (phase)
        self.phase_pitch = torch.zeros(n, dtype=torch.long, device=self.device)  # the pose it pointed at, steps
        self.phase_yaw = torch.zeros(n, dtype=torch.long, device=self.device)
        self.target_spectra: torch.Tensor | None = None  # (N, h, w // 2 + 1) complex, taken once per episode (measure)
        self.spectrum_fresh = torch.zeros(n, dtype=torch.bool, device=self.device)

    def reset(self, env_ids: torch.Tensor) -> None:
        """Slots ``env_ids`` (long tensor) start a new episode."""
        ids = env_ids.to(self.device)
        self.steps[ids] = 0
        self.best[ids] = -1.0
        self.best_pitch[ids] = 0
        self.best_yaw[ids] = 0
        self.returning[ids] = False
        self.walked[ids] = 0
        self.phase_peak[ids] = -1.0
        self.phase_pitch[ids] = 0
        self.phase_yaw[ids] = 0
        self.spectrum_fresh[ids] = False

    def measure(self, idx: torch.Tensor, pitch: torch.Tensor, yaw: torch.Tensor, view: torch.Tensor,
                target: torch.Tensor) -> None:
        """Phase correlation of the rendered ``view`` / ``target`` ``(N, 3, H, W)`` (every slot's) for the slots of
        ``idx`` ``(K,)``, sorted, at poses ``(pitch, yaw)`` ``(K,)`` whose STOP probability has not yet reached
        ``min_prob`` (the others never walk by it), fed to :meth:`observe_phase` in moves (degrees per move = 360 /
        ``yaw_cells``). Measured on the grey images averaged over ``k x k`` blocks, ``k = W // 128`` where it divides
        ``H`` and ``W`` (else 1; 256 -> 128 pixels: as good as full size on the fog val episodes, and cheaper); a
        slot's target spectrum is taken once per episode."""
        if self.fov is None:
            raise ValueError("GiveUp.measure needs the views' fov (GiveUp(..., fov=...))")
        idx = idx.to(self.device)
        mask = self.best[idx] < self.min_prob
        need = idx[mask]
        if len(need) == 0:
            return
        h, w = view.shape[-2:]
        k = max(1, w // 128)
        k = k if h % k == 0 and w % k == 0 else 1
        if self.target_spectra is None or self.target_spectra.shape[1:] != (h // k, w // k // 2 + 1):
            self.target_spectra = torch.zeros((len(self.best), h // k, w // k // 2 + 1), dtype=torch.complex64, device=self.device)
            self.spectrum_fresh.zero_()
        new = need[~self.spectrum_fresh[need]]
        if len(new):
            self.target_spectra[new] = phase_spectrum(target.to(self.device)[new], k)
            self.spectrum_fresh[new] = True
        view = view.to(self.device)
        view = view if len(need) == view.shape[0] else view[need]  # need is sorted: all slots = all in order (no copy)
        dyaw, dpitch, peak = rotation_between(phase_spectrum(view, k), self.target_spectra[need], self.fov, w // k)
        step = 360.0 / self.yaw_cells  # degrees per move
        self.observe_phase(need, peak, pitch[mask], yaw[mask], dpitch / step, dyaw / step)

    def observe_phase(self, idx: torch.Tensor, peak: torch.Tensor, pitch: torch.Tensor, yaw: torch.Tensor,
                      dpitch: torch.Tensor, dyaw: torch.Tensor) -> None:
        """Slots ``idx`` ``(K,)`` at poses ``(pitch, yaw)`` (``(K,)`` offsets, steps) measured the target at
        ``(dpitch, dyaw)`` (``(K,)`` float, steps; positive: up / right) with correlation peak ``peak`` ``(K,)``;
        keep the pose the clearest peak so far points at (rounded to the step grid)."""
        idx = idx.to(self.device)
        p = peak.to(self.device, torch.float32)
        better = p > self.phase_peak[idx]
        goal_pitch = pitch.to(self.device) + torch.round(dpitch.to(self.device)).long()
        goal_yaw = (yaw.to(self.device) + torch.round(dyaw.to(self.device)).long()) % self.yaw_cells
        self.phase_peak[idx] = torch.where(better, p, self.phase_peak[idx])
        self.phase_pitch[idx] = torch.where(better, goal_pitch, self.phase_pitch[idx])
        self.phase_yaw[idx] = torch.where(better, goal_yaw, self.phase_yaw[idx])

    def by_phase(self, idx: torch.Tensor) -> torch.Tensor:
        """``(K,)`` bool: slots ``idx`` whose walk goes to the phase-correlation pose (``phase`` on, STOP probability
        never at ``min_prob``, a peak measured)."""
        if not self.phase:
            return torch.zeros(len(idx), dtype=torch.bool, device=self.device)
        return (self.best[idx] < self.min_prob) & (self.phase_peak[idx] >= 0)

    def observe(self, idx: torch.Tensor, stop_prob: torch.Tensor, pitch: torch.Tensor, yaw: torch.Tensor) -> torch.Tensor:
        """Slots ``idx`` ``(K,)`` asked the policy at poses ``(pitch, yaw)`` (``(K,)`` offsets, steps) and got
        ``stop_prob`` ``(K,)``; count the step, keep the best pose. Returns ``(K,)`` bool: the slots that give up
        now (their best STOP probability is at least ``min_prob``, or with ``phase`` a phase-correlation goal stands in
        for it (:meth:`by_phase`), and the walk to the goal and its STOP need the steps left before ``stop_by``; the
        caller starts their walk with :meth:`walk`)."""
        idx = idx.to(self.device)
        p = stop_prob.to(self.device, torch.float32)
        better = p > self.best[idx]
        self.best[idx] = torch.where(better, p, self.best[idx])
        self.best_pitch[idx] = torch.where(better, pitch.to(self.device), self.best_pitch[idx])
        self.best_yaw[idx] = torch.where(better, yaw.to(self.device), self.best_yaw[idx])
        self.steps[idx] += 1
        # this act is step `steps`; walking d moves from here, the walk's STOP is step steps + d
        due = self.steps[idx] + self.distance(idx, pitch, yaw) + self.margin >= self.stop_by
        return due & ((self.best[idx] >= self.min_prob) | self.by_phase(idx))

    def _delta(self, idx: torch.Tensor, pitch: torch.Tensor, yaw: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """Pitch and yaw steps ``(K,)`` from ``(pitch, yaw)`` to the goal (the best pose, or the phase-correlation
        pose, :meth:`by_phase`), yaw the short way round."""
        phase = self.by_phase(idx)
        dp = torch.where(phase, self.phase_pitch[idx], self.best_pitch[idx]) - pitch.to(self.device)
        dy = (torch.where(phase, self.phase_yaw[idx], self.best_yaw[idx]) - yaw.to(self.device)) % self.yaw_cells
        return dp, torch.where(dy > self.yaw_cells // 2, dy - self.yaw_cells, dy)

    def distance(self, idx: torch.Tensor, pitch: torch.Tensor, yaw: torch.Tensor) -> torch.Tensor:
        """Moves ``(K,)`` of the walk from ``(pitch, yaw)`` to the goal of slots ``idx`` (:meth:`_delta`)."""
        dp, dy = self._delta(idx.to(self.device), pitch, yaw)
        return dp.abs() + dy.abs()

    def walk(self, idx: torch.Tensor, pitch: torch.Tensor, yaw: torch.Tensor,
             blocked: torch.Tensor | None = None) -> torch.Tensor:
        """The next move ``(K,)`` of slots ``idx`` on their walk back from poses ``(pitch, yaw)`` (``(K,)``
        offsets, steps): UP / DOWN until the goal's pitch, then LEFT / RIGHT the short way round, STOP there
        (or after ``max_walk`` moves); a slot that answers STOP leaves the walk. ``blocked`` ``(K,)`` bool: the
        slot's last move did not change its view (the pitch limit: a phase-correlation goal can lie beyond it);
        with ``phase`` on, its walk keeps the pitch it has and goes on with the yaw (without ``phase`` it is ignored:
        the walk goes back to a visited pose, exactly as before the option existed)."""
        idx = idx.to(self.device)
        if blocked is not None and self.phase:
            stuck = blocked.to(self.device) & (self.walked[idx] > 0)
            here = pitch.to(self.device)
            self.best_pitch[idx] = torch.where(stuck, here, self.best_pitch[idx])
            self.phase_pitch[idx] = torch.where(stuck, here, self.phase_pitch[idx])
        dp, dy = self._delta(idx, pitch, yaw)
        full = lambda a: torch.full_like(dp, a)  # noqa: E731
        move = torch.where(dp > 0, full(UP), torch.where(dp < 0, full(DOWN),
                           torch.where(dy > 0, full(RIGHT), torch.where(dy < 0, full(LEFT), full(STOP)))))
        move = torch.where(self.walked[idx] >= self.max_walk, full(STOP), move)
        self.walked[idx] += (move != STOP).long()
        self.returning[idx] = move != STOP
        return move
