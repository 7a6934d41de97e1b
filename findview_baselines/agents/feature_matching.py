"""The paper's rule-based agents ``orb`` and ``sift`` (docs/TASK.md, rule-based agents; paper appendix D).

One step of a slot:

1. grayscale the current view (the target's keypoints/descriptors are computed once per episode, on
   the first observation after ``reset``);
2. detect up to ``n_features`` keypoints and their descriptors (ORB or SIFT);
3. fewer than ``min_keypoints`` keypoints in either image -> repeat the previous action;
4. brute-force 2-NN matching of current -> target descriptors (Hamming for ORB, L2 for SIFT) with
   Lowe's ratio test (``ratio``, 0.7); fewer than ``min_matches`` matches -> repeat the previous action;
5. drop matches whose descriptor distance is above ``d_thresh`` (the paper's pseudocode writes the
   comparison the other way round; the task keeps matches with ``distance <= d_thresh``; ``inf``
   keeps all). ``d_thresh`` can be set per difficulty; the slot uses its episode's difficulty;
6. each match votes: displacement ``(dx, dy) = target keypoint - current keypoint`` in pixels (x right,
   y down). Both ``|dx|, |dy| < stop_px`` -> STOP; else along the dominant axis: ``dx < 0`` -> RIGHT
   (turning right by +yaw moves scene content to the left of the image, so content that sits further
   left in the target than in the current view asks for a right turn), ``dx > 0`` -> LEFT, ``dy > 0`` ->
   UP (looking up moves content down the image), ``dy < 0`` -> DOWN. The mode of the votes is the
   action (ties go to the lowest action id); no vote left -> repeat the previous action;
7. oscillation: if the last ``osc_window`` actions (this one included) alternate left/right only or
   up/down only (``osc_rule="alternating"``; ``"mixed"``: any mix of the two opposite moves of one axis
   with both present), STOP instead.

The "previous action" of a fresh episode is a seeded choice of LEFT or RIGHT.

Runtime (:class:`~findview_baselines.agents.feature_base.FeatureAgent`): everything runs on the host
with OpenCV and numpy; the target features are computed once per episode; slots are processed by
``threads`` worker threads (OpenCV releases the GIL), with ``cv2_threads`` OpenCV threads.
"""

from __future__ import annotations

import math
from collections import deque
from collections.abc import Iterable, Mapping
from dataclasses import dataclass, field
from typing import TYPE_CHECKING, Any

import numpy as np
import torch

from findview.episode import DIFFICULTIES, Episode

if TYPE_CHECKING:
    from findview_baselines.config import FeatureAgentConfig
from findview_baselines.agents.base import DOWN, LEFT, NUM_ACTIONS, RIGHT, STOP, UP, gray_of
from findview_baselines.agents.feature_base import (
    DETECTORS,
    FeatureAgent,
    Features,
    ParallelRunner,
    Slot,
    ViewCache,
    cv2_num_threads,
    detect,
    knn2,
    match_features,
    norm_type,
)

__all__ = [
    "DETECTORS",
    "Features",
    "detect",
    "knn2",
    "match_features",
    "norm_type",
    "displacement_votes",
    "vote_action",
    "is_oscillating",
    "parse_d_thresh",
    "ParallelRunner",
    "cv2_num_threads",
    "FeatureMatchingAgent",
]

OSC_RULES = ("alternating", "mixed")


def displacement_votes(disp: np.ndarray, stop_px: float = 1.0) -> np.ndarray:
    """Per-match votes from pixel displacements.

    Args:
        disp: ``(M, 2)`` displacement ``target position - current position`` (pixels, x right, y down).
        stop_px: both ``|dx|`` and ``|dy|`` below this -> STOP vote.

    Returns:
        ``(M,)`` int64 actions (see the module docstring for the sign convention).
    """
    dx, dy = disp[:, 0], disp[:, 1]
    horiz = np.abs(dx) > np.abs(dy)
    a = np.where(horiz, np.where(dx > 0, LEFT, RIGHT), np.where(dy > 0, UP, DOWN))
    a = np.where((np.abs(dx) < stop_px) & (np.abs(dy) < stop_px), STOP, a)
    return a.astype(np.int64)


def vote_action(disp: np.ndarray, stop_px: float = 1.0) -> int | None:
    """The mode of :func:`displacement_votes` (ties: lowest action id); ``None`` without votes."""
    if disp.shape[0] == 0:
        return None
    counts = np.bincount(displacement_votes(disp, stop_px), minlength=NUM_ACTIONS)
    return int(np.argmax(counts))


_AXIS = {LEFT: "h", RIGHT: "h", UP: "v", DOWN: "v"}


def is_oscillating(history: Iterable[int], action: int, window: int = 4, rule: str = "alternating") -> bool:
    """Whether the last ``window`` actions (``history`` then ``action``) oscillate on one axis.

    ``rule="alternating"``: they are all left/right (or all up/down) and every action reverses the one
    before it. ``rule="mixed"``: they are all left/right (or all up/down) and both directions occur.
    A window shorter than ``window`` (episode start) never oscillates; ``window < 2`` disables the check.
    """
    if window < 2:
        return False
    seq = list(history)[-(window - 1):] + [int(action)]
    if len(seq) < window:
        return False
    axes = {_AXIS.get(a) for a in seq}
    if len(axes) != 1 or None in axes:
        return False
    if rule == "alternating":
        return all(a != b for a, b in zip(seq, seq[1:]))
    if rule == "mixed":
        return len(set(seq)) == 2
    raise ValueError(f"unknown oscillation rule {rule!r}; expected one of {OSC_RULES}")


def _as_threshold(v: Any, what: str) -> float:
    if v is None:
        return math.inf
    if isinstance(v, str):
        s = v.strip().lower()
        if s in ("inf", "+inf", "infinity", "none", "null", ""):
            return math.inf
        try:
            v = float(s)
        except ValueError as e:
            raise ValueError(f"{what}: expected a number or 'inf', got {v!r}") from e
    x = float(v)
    if math.isnan(x) or x < 0:
        raise ValueError(f"{what}: expected a non-negative number or inf, got {v!r}")
    return x


def parse_d_thresh(value: Any) -> dict[str, float]:
    """Descriptor-distance threshold per difficulty.

    ``value`` is a scalar (applies to every difficulty; ``inf``/``None``/``"inf"`` = no threshold) or a
    mapping ``{easy: .., medium: .., hard: ..}`` (missing difficulties, and unknown ones at run time,
    use the mapping's ``default`` entry, else ``inf``).

    Returns:
        ``{difficulty: threshold}`` with a ``"default"`` entry.
    """
    if isinstance(value, Mapping):
        out = {str(k): _as_threshold(v, f"d_thresh.{k}") for k, v in value.items()}
        unknown = sorted(set(out) - set(DIFFICULTIES) - {"default"})
        if unknown:
            raise ValueError(f"d_thresh: unknown difficulties {unknown}; expected {list(DIFFICULTIES)} or 'default'")
        out.setdefault("default", math.inf)
        for d in DIFFICULTIES:
            out.setdefault(d, out["default"])
        return out
    x = _as_threshold(value, "d_thresh")
    return {**{d: x for d in DIFFICULTIES}, "default": x}


# --------------------------------------------------------------------------------------------------
# the agent
# --------------------------------------------------------------------------------------------------
@dataclass
class _SlotState(Slot):
    """A slot of :class:`FeatureMatchingAgent`: ``target`` holds the target's :class:`Features`."""

    prev: int = RIGHT  # the action repeated when the rule has no vote
    history: deque = field(default_factory=deque)  # the last osc_window - 1 actions
    views: ViewCache = field(default_factory=lambda: ViewCache(0))  # the rule's vote on each view seen this episode


class FeatureMatchingAgent(FeatureAgent):
    """The paper's ``orb`` / ``sift`` rule-based agent (batched; per-slot state).

    Args:
        num_envs, device, seed: see :class:`~findview_baselines.agents.base.Agent`.
        detector: ``"orb"`` or ``"sift"``.
        n_features: keypoints per image (500).
        ratio: Lowe ratio (0.7).
        d_thresh: descriptor-distance threshold, scalar or per difficulty (see :func:`parse_d_thresh`).
        min_keypoints: fewer keypoints in the view or the target -> repeat the previous action (10).
        min_matches: fewer ratio-test matches -> repeat the previous action (10).
        stop_px: a match votes STOP when both displacements are below this many pixels (1.0).
        osc_window: actions in the oscillation window, this step's included (4; < 2 disables).
        osc_rule: ``"alternating"`` or ``"mixed"`` (see :func:`is_oscillating`).
        cache_views: views per slot whose vote (detection and matching against the target) is remembered
            for the episode (400, a turn and more; 0: off). Results are the same either way
            (:class:`~findview_baselines.agents.feature_base.ViewCache`).
        threads, cv2_threads: see :class:`~findview_baselines.agents.feature_base.FeatureAgent`.
    """

    name = "feature"

    def __init__(
        self,
        num_envs: int,
        device: str | torch.device = "cpu",
        seed: int = 0,
        detector: str = "orb",
        n_features: int = 500,
        ratio: float = 0.7,
        d_thresh: Any = math.inf,
        min_keypoints: int = 10,
        min_matches: int = 10,
        stop_px: float = 1.0,
        osc_window: int = 4,
        osc_rule: str = "alternating",
        cache_views: int = 400,
        threads: int = 2,
        cv2_threads: int | None = 1,
    ) -> None:
        if detector not in DETECTORS:
            raise ValueError(f"unknown detector {detector!r}; expected one of {DETECTORS}")
        if int(cache_views) < 0:
            raise ValueError(f"cache_views must be >= 0 views, got {cache_views!r}")
        if osc_rule not in OSC_RULES:
            raise ValueError(f"unknown osc_rule {osc_rule!r}; expected one of {OSC_RULES}")
        if not 0.0 < float(ratio) <= 1.0:
            raise ValueError(f"ratio must be in (0, 1], got {ratio!r}")
        self.name = detector
        self.detector = detector
        self.n_features = int(n_features)
        self.ratio = float(ratio)
        self.d_thresh = parse_d_thresh(d_thresh)
        self.min_keypoints = int(min_keypoints)
        self.min_matches = int(min_matches)
        self.stop_px = float(stop_px)
        self.osc_window = int(osc_window)
        self.osc_rule = osc_rule
        self.cache_views = int(cache_views)
        super().__init__(num_envs, device, seed, threads=threads, cv2_threads=cv2_threads)

    @classmethod
    def from_config(  # type: ignore[override]
        cls, cfg: "FeatureAgentConfig", num_envs: int, device: str | torch.device, seed: int
    ) -> "FeatureMatchingAgent":
        """Factory for :func:`~findview_baselines.agents.make_agent` from the typed ``agent`` section; its
        ``name`` (``orb`` | ``sift``) is the detector."""
        return cls(
            num_envs, device, seed, detector=cfg.name, n_features=cfg.n_features, ratio=cfg.ratio,
            d_thresh=cfg.d_thresh, min_keypoints=cfg.min_keypoints, min_matches=cfg.min_matches, stop_px=cfg.stop_px,
            osc_window=cfg.osc_window, osc_rule=cfg.osc_rule, cache_views=cfg.cache_views, threads=cfg.threads,
            cv2_threads=cfg.cv2_threads,
        )

    @property
    def states(self) -> list[_SlotState]:
        """The per-slot states (alias of ``slots``)."""
        return self.slots

    # state ---------------------------------------------------------------------------------------
    def new_slot(self, episode: Episode | None, rng: np.random.Generator) -> _SlotState:
        return _SlotState(
            rng=rng,
            difficulty=None if episode is None else episode.difficulty,
            prev=LEFT if rng.integers(0, 2) == 0 else RIGHT,
            history=deque(maxlen=max(1, self.osc_window - 1)),
            views=ViewCache(self.cache_views),
        )

    def prepare_target(self, slot: Slot, target: np.ndarray) -> Features:
        return detect(self.detector, gray_of(target), self.n_features)

    def threshold(self, i: int) -> float:
        """``d_thresh`` of slot ``i`` (its episode's difficulty)."""
        d = self.slots[i].difficulty
        return self.d_thresh.get(d, self.d_thresh["default"]) if d is not None else self.d_thresh["default"]

    # acting --------------------------------------------------------------------------------------
    def step(self, i: int, slot: Slot, view: np.ndarray | None) -> int:
        assert view is not None
        st: _SlotState = slot  # type: ignore[assignment]
        vote = st.views.get(view, lambda: self.vote(i, detect(self.detector, gray_of(view), self.n_features)))
        return self.decide(i, vote)

    def vote(self, i: int, cur: Features) -> int | None:
        """The matches' vote of slot ``i`` on a view with features ``cur`` (a move or STOP), ``None`` when
        there are too few keypoints or matches, or no majority. A function of the view alone once the
        episode's target (and so its features and threshold) is fixed."""
        tgt = self.slots[i].target
        assert tgt is not None
        if len(tgt) < self.min_keypoints or len(cur) < self.min_keypoints:
            return None
        ci, ti, dist = match_features(cur, tgt, self.detector, self.ratio)
        if len(ci) < self.min_matches:
            return None
        keep = dist <= self.threshold(i)
        return vote_action(tgt.pts[ti[keep]] - cur.pts[ci[keep]], self.stop_px)

    def decide(self, i: int, vote: int | None) -> int:
        """The action of slot ``i`` given its vote on the current view (updates the slot's history): an
        oscillating move becomes STOP, no vote repeats the previous action."""
        st = self.slots[i]
        a = vote
        if a is not None and a != STOP and is_oscillating(st.history, a, self.osc_window, self.osc_rule):
            a = STOP
        if a is None:
            a = st.prev
        st.history.append(a)
        st.prev = a
        if a == STOP:
            st.done = True
        return a
