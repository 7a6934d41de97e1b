"""Privileged labels from the environment's state: the oracle's action and the relative rotation.

Everything here reads the true rotations (``pitch``, ``yaw``, ``target_pitch``, ``target_yaw``: integer
degrees, yaw in ``(-180, 180]``) that a batched :class:`~findview.task.FindViewEnv` keeps as ``(N,)``
long tensors on its device. These labels are for training only (imitation learning, auxiliary losses);
a policy must never see them as inputs.

Conventions (docs/TASK.md): ``+pitch`` looks up (action ``UP``), ``+yaw`` pans right (action ``RIGHT``).

- **Oracle action** (:func:`oracle_actions`): a shortest path. ``dpitch = target_pitch - pitch`` and
  ``dyaw = wrap(target_yaw - yaw)`` in ``(-180, 180]``; exactly 180 degrees apart counts as ``+180``, so
  the oracle pans **right** then (both ways are equally short). One axis is finished before the other
  (``order``: ``pitch_first`` (default, as the rule-based oracle agent), ``yaw_first`` or
  ``larger_first``: the axis with the larger remaining distance, pitch on ties). ``STOP`` once both
  remaining distances are below ``step_deg`` (0 for the default 1-degree steps).
- **Optimal action sets** (:func:`optimal_action_mask`): every action on *some* shortest path (``UP`` or
  ``DOWN`` while pitch is off, ``LEFT`` or ``RIGHT`` while yaw is off, both yaw moves at exactly 180
  degrees, ``STOP`` only on the target). An imitation learner trained on the set may pick either axis
  first, so it need not resolve which remaining distance is larger, or a 1-degree pitch offset while the
  target is still far to the side.
- **Overlap** (:func:`overlap_mask`): the view and the target overlap when ``|dpitch| <= fov`` and
  ``|dyaw| <= fov`` (``fov``: the horizontal field of view in degrees); this is the complement of the
  ``hard`` difficulty under the default ``hard_rule="or"`` (``|dpitch| > f OR dyaw > f``), so easy and
  medium starts always overlap and hard starts never do.
- **Sweep search prior** (:func:`sweep_actions`): what a learner can do without knowing where the target
  is. Where the views overlap it is the oracle's action; where they do not, it first matches the pitch
  (the target's pitch is partly visible in its content: sky, floor, ceiling), then pans ``RIGHT`` until the
  views overlap. This covers the sphere without loops (with ``|dpitch| <= fov`` a full turn always reaches
  an overlapping view) at the price of up to ``360 - 2 * fov`` extra degrees when the target lay to the left.
- **Pan search prior** (:func:`pan_actions`): like the sweep, but where the views do not overlap it pans
  ``RIGHT`` at the current pitch (a pitch move towards the target only while ``|dpitch| > fov``, where no
  pan can reach an overlapping view). A learner cannot read the target's pitch from a view that shares
  nothing with it, so the sweep's "match the pitch first" labels ask it to guess, and a greedy learner
  that guesses ends in ``UP``/``DOWN`` two-cycles; "pan right until the target shows up" asks only
  "do the views overlap?". ``pitch_band`` (a fraction of ``fov``, default 1) sets where the pitch move starts:
  with ``pitch_band = 0.5`` the prior moves the pitch towards the target while ``|dpitch| > fov / 2`` and pans
  only from there, so a pan passes the target with at least half of its height in view instead of a thin
  strip (at FoV 60 a target 50 degrees above shares 10 degrees with the panning view); the learner then has
  to read "is the target above or below?" from the two images (ceiling, floor, sky, horizon), and every such
  pitch move lies on a shortest path.
  **Row done** (``row_done``, per environment): the searcher's own record that it has looked around its current row
  without finding the target (e.g. a full turn in its dead-reckoned search memory), which happens when it pans past a
  target that shares only a thin strip with its view. Where it is set, the prior moves the pitch towards the target
  instead of panning on, while ``|dpitch| > row_done_band * fov`` (every such move lies on a shortest path; a band
  above 0 lets the learner pan again once the target's row is roughly reached, not exactly); a learner that sees the same record can learn
  "leave a finished row, towards where the target's content suggests", and from the record of the rows it has
  already looked around, "back the other way" when it guessed wrong.
  The two regions do not trap a learner at their border: at ``dyaw = -fov`` the oracle moves ``LEFT``
  (into the overlap), one degree further the pan moves ``RIGHT`` (away from it, round the sphere).
  **Yaw band** (``yaw_band``, a fraction of ``fov`` in ``(0, 1]``, default 1): the pan prior counts the target as in
  sight only while ``|dyaw| <= yaw_band * fov`` (and ``|dpitch| <= fov``); further to the side it pans ``RIGHT``. At
  ``|dyaw|`` near ``fov`` the two views share a strip of a few degrees, which a learner cannot tell from no overlap;
  the overlap labels then ask it to turn back towards a target it cannot see, and the pan labels of the views just
  beyond ask the opposite, so a learner that cannot separate them turns back and forth. With a band the labels
  change only where the target is well into the view. Panning right always brings ``dyaw`` into the band (it
  decreases by one a move), so no start is trapped; the border behaves as above. ``yaw_band`` is one number or an
  (N,) tensor, one band per environment (a trainer that widens the band at the start of a search).
"""

from __future__ import annotations

from typing import Any

import torch

from findview.geometry import wrap_yaw
from findview.task.actions import Action

__all__ = [
    "ORDERS",
    "SEARCH_PRIORS",
    "optimal_action_mask",
    "optimal_action_mask_for",
    "oracle_actions",
    "pan_action_mask",
    "pan_actions",
    "oracle_actions_for",
    "overlap_mask",
    "rotation_labels",
    "rotation_targets",
    "sweep_action_mask",
    "sweep_actions",
]

ORDERS = ("pitch_first", "yaw_first", "larger_first")
SEARCH_PRIORS = ("oracle", "sweep", "pan")


def _deltas(
    pitch: torch.Tensor, yaw: torch.Tensor, target_pitch: torch.Tensor, target_yaw: torch.Tensor
) -> tuple[torch.Tensor, torch.Tensor]:
    """Signed ``(dpitch, dyaw)`` in degrees, ``dyaw`` wrapped into ``(-180, 180]``; all (N,) long."""
    pitch, yaw = torch.as_tensor(pitch), torch.as_tensor(yaw)
    target_pitch = torch.as_tensor(target_pitch, device=pitch.device)
    target_yaw = torch.as_tensor(target_yaw, device=pitch.device)
    dp = (target_pitch - pitch).long()
    dy = wrap_yaw((target_yaw - yaw).long())
    return dp, dy


def oracle_actions(
    pitch: torch.Tensor,
    yaw: torch.Tensor,
    target_pitch: torch.Tensor,
    target_yaw: torch.Tensor,
    step_deg: int = 1,
    order: str = "pitch_first",
) -> torch.Tensor:
    """The shortest-path action for every environment, ``(N,)`` long on the inputs' device.

    Args:
        pitch, yaw: current rotation (N,), integer degrees.
        target_pitch, target_yaw: target rotation (N,), integer degrees.
        step_deg: degrees per move (the task's ``step_deg``); an axis counts as done when its remaining
            distance is below one step.
        order: which axis to finish first: ``pitch_first``, ``yaw_first`` or ``larger_first`` (larger
            remaining distance first, pitch on ties).

    Exactly 180 degrees of yaw apart, the oracle pans ``RIGHT`` (see the module docstring).
    """
    if order not in ORDERS:
        raise ValueError(f"oracle order must be one of {ORDERS}, got {order!r}")
    if int(step_deg) != step_deg or step_deg < 1:
        raise ValueError(f"step_deg must be a positive integer, got {step_deg!r}")
    dp, dy = _deltas(pitch, yaw, target_pitch, target_yaw)
    pitch_move = torch.where(dp > 0, int(Action.UP), int(Action.DOWN))
    yaw_move = torch.where(dy > 0, int(Action.RIGHT), int(Action.LEFT))
    need_p = dp.abs() >= step_deg
    need_y = dy.abs() >= step_deg
    if order == "pitch_first":
        pitch_now = need_p
    elif order == "yaw_first":
        pitch_now = need_p & ~need_y
    else:  # larger_first
        pitch_now = need_p & (dp.abs() >= dy.abs())
    stop = torch.full_like(dp, int(Action.STOP))
    return torch.where(pitch_now, pitch_move, torch.where(need_y, yaw_move, torch.where(need_p, pitch_move, stop)))


def optimal_action_mask(
    pitch: torch.Tensor,
    yaw: torch.Tensor,
    target_pitch: torch.Tensor,
    target_yaw: torch.Tensor,
    step_deg: int = 1,
) -> torch.Tensor:
    """(N, 5) bool, column ``a`` true when action ``a`` lies on a shortest path (see the module docstring).

    Every row has at least one true entry; ``STOP`` is true only where both remaining distances are below
    one step, and then alone.
    """
    if int(step_deg) != step_deg or step_deg < 1:
        raise ValueError(f"step_deg must be a positive integer, got {step_deg!r}")
    dp, dy = _deltas(pitch, yaw, target_pitch, target_yaw)
    need_p = dp.abs() >= step_deg
    need_y = dy.abs() >= step_deg
    mask = torch.zeros(dp.shape[0], len(Action), dtype=torch.bool, device=dp.device)
    mask[:, int(Action.UP)] = need_p & (dp > 0)
    mask[:, int(Action.DOWN)] = need_p & (dp < 0)
    mask[:, int(Action.RIGHT)] = need_y & (dy > 0)
    mask[:, int(Action.LEFT)] = need_y & ((dy < 0) | (dy == 180))  # 180 apart: both ways are as short
    mask[:, int(Action.STOP)] = ~need_p & ~need_y
    return mask


def sweep_action_mask(
    pitch: torch.Tensor,
    yaw: torch.Tensor,
    target_pitch: torch.Tensor,
    target_yaw: torch.Tensor,
    fov: float,
    step_deg: int = 1,
) -> torch.Tensor:
    """(N, 5) bool: :func:`optimal_action_mask` where the views overlap; elsewhere the sweep's moves
    (the pitch move towards the target while pitch is off, and ``RIGHT``)."""
    optimal = optimal_action_mask(pitch, yaw, target_pitch, target_yaw, step_deg)
    dp, _ = _deltas(pitch, yaw, target_pitch, target_yaw)
    search = torch.zeros_like(optimal)
    search[:, int(Action.UP)] = (dp.abs() >= step_deg) & (dp > 0)
    search[:, int(Action.DOWN)] = (dp.abs() >= step_deg) & (dp < 0)
    search[:, int(Action.RIGHT)] = True
    overlap = overlap_mask(pitch, yaw, target_pitch, target_yaw, fov)
    return torch.where(overlap[:, None], optimal, search)


def overlap_mask(
    pitch: torch.Tensor, yaw: torch.Tensor, target_pitch: torch.Tensor, target_yaw: torch.Tensor, fov: float,
    yaw_band: float | torch.Tensor = 1.0,
) -> torch.Tensor:
    """(N,) bool: ``|dpitch| <= fov`` and ``|dyaw| <= yaw_band * fov`` (degrees); with the default band 1, not
    ``hard`` under the "or" rule. ``yaw_band`` in ``(0, 1]``, one number or (N,) per environment (module docstring,
    "yaw band")."""
    dp, dy = _deltas(pitch, yaw, target_pitch, target_yaw)
    return (dp.abs() <= fov) & (dy.abs() <= _check_yaw_band(yaw_band) * fov)


def sweep_actions(
    pitch: torch.Tensor,
    yaw: torch.Tensor,
    target_pitch: torch.Tensor,
    target_yaw: torch.Tensor,
    fov: float,
    step_deg: int = 1,
    order: str = "pitch_first",
) -> torch.Tensor:
    """Oracle actions where the views overlap; elsewhere match the pitch, then pan ``RIGHT`` (N,) long.

    See the module docstring ("sweep search prior"). ``fov`` is the horizontal field of view in degrees.
    """
    oracle = oracle_actions(pitch, yaw, target_pitch, target_yaw, step_deg, order)
    dp, _ = _deltas(pitch, yaw, target_pitch, target_yaw)
    pitch_move = torch.where(dp > 0, int(Action.UP), int(Action.DOWN))
    search = torch.where(dp.abs() >= step_deg, pitch_move, torch.full_like(dp, int(Action.RIGHT)))
    return torch.where(overlap_mask(pitch, yaw, target_pitch, target_yaw, fov), oracle, search)


def _check_band(name: str, value: float, allow_zero: bool = True) -> float:
    """``value`` as a float after checking that it is a fraction of the FoV: in ``[0, 1]`` (``(0, 1]`` when not
    ``allow_zero``); the error names the argument ``name``."""
    band = float(value)
    if not (0.0 <= band if allow_zero else 0.0 < band) or band > 1.0:
        interval = "[0, 1]" if allow_zero else "(0, 1]"
        raise ValueError(f"{name} must be in {interval} (a fraction of the FoV), got {value!r}")
    return band


def _check_yaw_band(yaw_band: float | torch.Tensor) -> float | torch.Tensor:
    """``yaw_band`` after :func:`_check_band` (``(0, 1]``) of each of its values: a float, or the (N,) tensor itself."""
    if isinstance(yaw_band, torch.Tensor):
        for extreme in (yaw_band.min(), yaw_band.max()):
            _check_band("yaw_band", float(extreme), allow_zero=False)
        return yaw_band
    return _check_band("yaw_band", yaw_band, allow_zero=False)


def _pan_search(
    dp: torch.Tensor, fov: float, pitch_band: float = 1.0, row_done: torch.Tensor | None = None,
    row_done_band: float = 0.0,
) -> torch.Tensor:
    """(N,) long: the pan prior's move where the views do not overlap (pitch move while
    ``|dp| > pitch_band * fov`` or, where ``row_done`` (N,) bool is true, while ``|dp| > row_done_band * fov``;
    else ``RIGHT``)."""
    pitch_move = torch.where(dp > 0, int(Action.UP), int(Action.DOWN))
    move_pitch = dp.abs() > _check_band("pitch_band", pitch_band) * fov
    if row_done is not None:
        move_pitch = move_pitch | (row_done.to(dp.device).bool() & (dp.abs() > _check_band("row_done_band", row_done_band) * fov))
    return torch.where(move_pitch, pitch_move, torch.full_like(dp, int(Action.RIGHT)))


def pan_actions(
    pitch: torch.Tensor,
    yaw: torch.Tensor,
    target_pitch: torch.Tensor,
    target_yaw: torch.Tensor,
    fov: float,
    step_deg: int = 1,
    order: str = "pitch_first",
    pitch_band: float = 1.0,
    row_done: torch.Tensor | None = None,
    row_done_band: float = 0.0,
    yaw_band: float | torch.Tensor = 1.0,
) -> torch.Tensor:
    """Oracle actions where the views overlap; elsewhere pan ``RIGHT`` (N,) long (a pitch move towards the
    target only while ``|dpitch| > pitch_band * fov``). See the module docstring ("pan search prior"); ``fov``
    in degrees, ``pitch_band`` a fraction of it in ``[0, 1]``. ``row_done`` (N,) bool, the searcher's own
    record that it has looked around its current row (e.g. a dead-reckoned search memory): where it is true
    the prior moves the pitch towards the target while ``|dpitch| > row_done_band * fov`` instead of panning on
    (module docstring, "row done"). ``yaw_band`` in ``(0, 1]``: the oracle's moves only while ``|dyaw| <=
    yaw_band * fov`` (module docstring, "yaw band")."""
    oracle = oracle_actions(pitch, yaw, target_pitch, target_yaw, step_deg, order)
    dp, _ = _deltas(pitch, yaw, target_pitch, target_yaw)
    search = _pan_search(dp, fov, pitch_band, row_done, row_done_band)
    return torch.where(overlap_mask(pitch, yaw, target_pitch, target_yaw, fov, yaw_band), oracle, search)


def pan_action_mask(
    pitch: torch.Tensor,
    yaw: torch.Tensor,
    target_pitch: torch.Tensor,
    target_yaw: torch.Tensor,
    fov: float,
    step_deg: int = 1,
    pitch_band: float = 1.0,
    row_done: torch.Tensor | None = None,
    row_done_band: float = 0.0,
    yaw_band: float | torch.Tensor = 1.0,
) -> torch.Tensor:
    """(N, 5) bool: :func:`optimal_action_mask` where the views overlap; elsewhere the pan prior's one move
    (``pitch_band``, ``row_done``, ``row_done_band`` and ``yaw_band`` as in :func:`pan_actions`)."""
    optimal = optimal_action_mask(pitch, yaw, target_pitch, target_yaw, step_deg)
    dp, _ = _deltas(pitch, yaw, target_pitch, target_yaw)
    search = torch.nn.functional.one_hot(_pan_search(dp, fov, pitch_band, row_done, row_done_band), len(Action)).bool()
    overlap = overlap_mask(pitch, yaw, target_pitch, target_yaw, fov, yaw_band)
    return torch.where(overlap[:, None], optimal, search)


def _env_rotations(
    env: Any, search: str, row_done: torch.Tensor | None = None, yaw_band: float | torch.Tensor = 1.0
) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor, torch.Tensor, float, int]:
    """``(pitch, yaw, target_pitch, target_yaw, fov, step_deg)`` of ``env`` after checking ``search`` (and that
    ``row_done`` and a ``yaw_band`` below 1 come only with the ``pan`` prior)."""
    if search not in SEARCH_PRIORS:
        raise ValueError(f"search prior must be one of {SEARCH_PRIORS}, got {search!r}")
    if row_done is not None and search != "pan":
        raise ValueError(f"row_done (the searcher's memory) shapes the 'pan' search prior only, got search={search!r}")
    if bool(torch.as_tensor(_check_yaw_band(yaw_band)).lt(1.0).any()) and search != "pan":
        raise ValueError(f"yaw_band={yaw_band} shapes the 'pan' search prior only, got search={search!r}")
    step = int(getattr(env, "step_deg", 1))
    return env.pitch, env.yaw, env.target_pitch, env.target_yaw, float(env.sim.fov), step


def oracle_actions_for(
    env: Any, order: str = "pitch_first", search: str = "oracle", pitch_band: float = 1.0,
    row_done: torch.Tensor | None = None, row_done_band: float = 0.0, yaw_band: float | torch.Tensor = 1.0,
) -> torch.Tensor:
    """Labels for the environments' current observations, (N,) long on ``env.device``.

    Reads ``env.pitch, env.yaw, env.target_pitch, env.target_yaw`` (and ``env.step_deg``, ``env.sim.fov``).
    ``search="oracle"``: :func:`oracle_actions`; ``search="sweep"``: :func:`sweep_actions`; ``search="pan"``:
    :func:`pan_actions` (with ``pitch_band``, ``row_done``, ``row_done_band``, ``yaw_band``; the other priors refuse
    ``row_done`` and a ``yaw_band`` below 1). Call it before ``env.step`` to label the observation the policy acts on.
    """
    pitch, yaw, tp, ty, fov, step = _env_rotations(env, search, row_done, yaw_band)
    if search == "oracle":
        return oracle_actions(pitch, yaw, tp, ty, step, order)
    if search == "sweep":
        return sweep_actions(pitch, yaw, tp, ty, fov, step, order)
    return pan_actions(pitch, yaw, tp, ty, fov, step, order, pitch_band, row_done, row_done_band, yaw_band)


def optimal_action_mask_for(
    env: Any, search: str = "oracle", pitch_band: float = 1.0, row_done: torch.Tensor | None = None,
    row_done_band: float = 0.0, yaw_band: float | torch.Tensor = 1.0,
) -> torch.Tensor:
    """(N, 5) bool action sets of the environments' current observations (``search`` as in
    :func:`oracle_actions_for`: ``oracle`` -> :func:`optimal_action_mask`, ``sweep`` -> :func:`sweep_action_mask`,
    ``pan`` -> :func:`pan_action_mask` with ``pitch_band``, ``row_done``, ``row_done_band``, ``yaw_band``)."""
    pitch, yaw, tp, ty, fov, step = _env_rotations(env, search, row_done, yaw_band)
    if search == "oracle":
        return optimal_action_mask(pitch, yaw, tp, ty, step)
    if search == "sweep":
        return sweep_action_mask(pitch, yaw, tp, ty, fov, step)
    return pan_action_mask(pitch, yaw, tp, ty, fov, step, pitch_band, row_done, row_done_band, yaw_band)


def rotation_targets(
    pitch: torch.Tensor, yaw: torch.Tensor, target_pitch: torch.Tensor, target_yaw: torch.Tensor, fov: float
) -> torch.Tensor:
    """(N, 3) float32: ``dpitch / fov``, ``dyaw / fov`` (signed, dyaw wrapped) and overlap (1.0 / 0.0).

    ``dpitch > 0``: the target lies above (``UP`` reduces it); ``dyaw > 0``: to the right.
    """
    dp, dy = _deltas(pitch, yaw, target_pitch, target_yaw)
    overlap = (dp.abs() <= fov) & (dy.abs() <= fov)
    return torch.stack([dp.float() / float(fov), dy.float() / float(fov), overlap.float()], dim=1)


def rotation_labels(env: Any) -> torch.Tensor:
    """:func:`rotation_targets` of the environments' current observations, (N, 3) on ``env.device``.

    Call it before ``env.step`` and pass it as ``aux_targets`` to ``RolloutStorage.insert``.
    """
    return rotation_targets(env.pitch, env.yaw, env.target_pitch, env.target_yaw, float(env.sim.fov))
