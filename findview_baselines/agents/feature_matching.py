"""The paper's rule-based agents ``orb`` and ``sift`` (SPEC section 9, paper appendix D).

One step of a slot:

1. grayscale the current view (the target's keypoints/descriptors are computed once per episode, on
   the first observation after ``reset``);
2. detect up to ``n_features`` keypoints and their descriptors (ORB or SIFT);
3. fewer than ``min_keypoints`` keypoints in either image -> repeat the previous action;
4. brute-force 2-NN matching of current -> target descriptors (Hamming for ORB, L2 for SIFT) with
   Lowe's ratio test (``ratio``, 0.7); fewer than ``min_matches`` matches -> repeat the previous action;
5. drop matches whose descriptor distance is above ``d_thresh`` (the paper's pseudocode writes the
   comparison the other way round; SPEC section 9 keeps matches with ``distance <= d_thresh``; ``inf``
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

Runtime: everything runs on the host with OpenCV; the target features are cached per slot; slots are
processed by ``threads`` worker threads (OpenCV releases the GIL), with ``cv2_threads`` OpenCV threads.
"""

from __future__ import annotations

import contextlib
import math
import threading
from collections import deque
from collections.abc import Callable, Iterable, Iterator, Mapping, Sequence
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass
from typing import Any, TypeVar

import cv2
import numpy as np
import torch

from findview.episode import DIFFICULTIES, Episode
from findview_baselines.agents.base import (
    DOWN,
    LEFT,
    NUM_ACTIONS,
    RIGHT,
    STOP,
    UP,
    Agent,
    check_keys,
    episode_rng,
    rgb_to_gray,
    to_plain_dict,
)

__all__ = [
    "DETECTORS",
    "Features",
    "detect",
    "knn2",
    "match_features",
    "displacement_votes",
    "vote_action",
    "is_oscillating",
    "parse_d_thresh",
    "ParallelRunner",
    "cv2_num_threads",
    "FeatureMatchingAgent",
]

DETECTORS = ("orb", "sift")
OSC_RULES = ("alternating", "mixed")
_T = TypeVar("_T")
_R = TypeVar("_R")


# --------------------------------------------------------------------------------------------------
# features and matching
# --------------------------------------------------------------------------------------------------
@dataclass
class Features:
    """Keypoints of one image.

    Attributes:
        pts: ``(K, 2)`` float32 keypoint positions ``(x, y)`` in pixels (x = column to the right,
            y = row downwards; OpenCV convention, pixel centres at integer coordinates).
        des: ``(K, 32)`` uint8 (ORB) or ``(K, 128)`` float32 (SIFT) descriptors; ``None`` when ``K == 0``.
    """

    pts: np.ndarray
    des: np.ndarray | None

    def __len__(self) -> int:
        return int(self.pts.shape[0])


_local = threading.local()


def _detector(kind: str, n_features: int) -> cv2.Feature2D:
    """A per-thread cached OpenCV detector (Feature2D objects are not shared between threads)."""
    cache = getattr(_local, "detectors", None)
    if cache is None:
        cache = _local.detectors = {}
    key = (kind, int(n_features))
    det = cache.get(key)
    if det is None:
        if kind == "orb":
            det = cv2.ORB_create(nfeatures=int(n_features))
        elif kind == "sift":
            det = cv2.SIFT_create(nfeatures=int(n_features))
        else:
            raise ValueError(f"unknown detector {kind!r}; expected one of {DETECTORS}")
        cache[key] = det
    return det


def norm_type(kind: str) -> int:
    """OpenCV norm of the descriptors of ``kind``: Hamming for ORB, L2 for SIFT."""
    if kind == "orb":
        return cv2.NORM_HAMMING
    if kind == "sift":
        return cv2.NORM_L2
    raise ValueError(f"unknown detector {kind!r}; expected one of {DETECTORS}")


def detect(kind: str, gray: np.ndarray, n_features: int = 500) -> Features:
    """Detect keypoints and compute descriptors on a ``(H, W)`` uint8 gray image."""
    kps, des = _detector(kind, n_features).detectAndCompute(gray, None)
    if not kps or des is None:
        return Features(np.zeros((0, 2), np.float32), None)
    pts = np.array([kp.pt for kp in kps], dtype=np.float32).reshape(-1, 2)
    return Features(pts, des)


def knn2(des_query: np.ndarray, des_train: np.ndarray, kind: str) -> tuple[np.ndarray, np.ndarray]:
    """Brute-force 2 nearest neighbours of each query descriptor among the train descriptors.

    ORB (Hamming): ``cv2.batchDistance``, the kernel behind ``cv2.BFMatcher.knnMatch`` (same distances,
    same neighbours), without building ``DMatch`` objects. SIFT (L2): the exhaustive distance matrix
    ``|q|^2 + |t|^2 - 2 q.t`` as one float32 matrix product (3-4x faster than OpenCV's loop on 2
    cores; distances agree with ``BFMatcher`` to ~1e-4 relative, so only exact ties may differ).

    Returns:
        ``dist (Q, 2)`` float32 descriptor distances (Hamming bit count or L2 norm), ascending, and
        ``idx (Q, 2)`` int32 train indices; with a single train descriptor the second column is
        ``inf`` / ``-1``.
    """
    q = len(des_query)
    if q == 0 or len(des_train) == 0:
        return np.zeros((q, 2), np.float32) + np.inf, np.full((q, 2), -1, np.int32)
    k = min(2, len(des_train))
    if kind == "sift":
        a = torch.from_numpy(np.ascontiguousarray(des_query, dtype=np.float32))
        b = torch.from_numpy(np.ascontiguousarray(des_train, dtype=np.float32))
        d2 = (a * a).sum(1, keepdim=True) + (b * b).sum(1)[None, :] - 2.0 * (a @ b.T)
        top = torch.topk(d2, k, dim=1, largest=False, sorted=True)
        dist = top.values.clamp_min_(0.0).sqrt_().numpy()
        idx = top.indices.to(torch.int32).numpy()
    else:
        dist, idx = cv2.batchDistance(des_query, des_train, -1, normType=norm_type(kind), K=k)
        dist = dist.astype(np.float32, copy=False)
    if k == 1:
        dist = np.concatenate([dist, np.full((q, 1), np.inf, np.float32)], axis=1)
        idx = np.concatenate([idx, np.full((q, 1), -1, np.int32)], axis=1)
    return dist, idx


def match_features(
    cur: Features, tgt: Features, kind: str, ratio: float
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """2-NN matching with Lowe's ratio test.

    Returns:
        ``cur_idx (M,)``, ``tgt_idx (M,)`` int indices of the kept matches and their descriptor
        ``distance (M,)`` float32 (nearest neighbour), for the ``M`` matches with
        ``d1 < ratio * d2``.
    """
    if len(cur) == 0 or len(tgt) == 0:
        e = np.zeros(0, np.int64)
        return e, e, np.zeros(0, np.float32)
    dist, idx = knn2(cur.des, tgt.des, kind)  # type: ignore[arg-type]
    good = dist[:, 0] < ratio * dist[:, 1]
    q = np.flatnonzero(good)
    return q, idx[q, 0].astype(np.int64), dist[q, 0]


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


@contextlib.contextmanager
def cv2_num_threads(n: int | None) -> Iterator[None]:
    """Run the block with ``cv2.setNumThreads(n)`` and restore the previous value (``None``: no change).

    OpenCV's setting is process-wide; scoping it to the agent's ``act`` keeps e.g. the simulator's
    OpenCV remaps multi-threaded.
    """
    if n is None:
        yield
        return
    prev = cv2.getNumThreads()
    cv2.setNumThreads(int(n))
    try:
        yield
    finally:
        cv2.setNumThreads(prev)


class ParallelRunner:
    """Maps a function over slots with a small thread pool (serial for 1 thread or 1 item)."""

    def __init__(self, threads: int) -> None:
        self.threads = max(1, int(threads))
        self._pool: ThreadPoolExecutor | None = None

    def map(self, fn: Callable[[_T], _R], items: Sequence[_T]) -> list[_R]:
        if self.threads <= 1 or len(items) <= 1:
            return [fn(x) for x in items]
        if self._pool is None:
            self._pool = ThreadPoolExecutor(max_workers=self.threads, thread_name_prefix="findview-agent")
        return list(self._pool.map(fn, items))

    def close(self) -> None:
        if self._pool is not None:
            self._pool.shutdown(wait=True)
            self._pool = None


# --------------------------------------------------------------------------------------------------
# the agent
# --------------------------------------------------------------------------------------------------
@dataclass
class _SlotState:
    difficulty: str | None = None
    target: Features | None = None  # None: compute on the next act
    prev: int = RIGHT
    history: deque | None = None
    done: bool = False


class FeatureMatchingAgent(Agent):
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
        threads: worker threads over slots (2).
        cv2_threads: OpenCV threads while the agent acts on several slots (1: the slot threads do the
            parallel work; ``None`` leaves OpenCV's setting alone). Restored after each ``act``; a step
            with a single slot to process keeps OpenCV's own setting.
    """

    name = "feature"
    CONFIG_KEYS = (
        "detector",
        "n_features",
        "ratio",
        "d_thresh",
        "min_keypoints",
        "min_matches",
        "stop_px",
        "osc_window",
        "osc_rule",
        "threads",
        "cv2_threads",
    )

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
        threads: int = 2,
        cv2_threads: int | None = 1,
    ) -> None:
        super().__init__(num_envs, device, seed)
        if detector not in DETECTORS:
            raise ValueError(f"unknown detector {detector!r}; expected one of {DETECTORS}")
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
        self.cv2_threads = None if cv2_threads is None else int(cv2_threads)
        self.runner = ParallelRunner(threads)
        self._rng = np.random.default_rng(self.seed)
        self.states = [self._fresh_state(None) for _ in range(self.num_envs)]

    @classmethod
    def from_config(
        cls, cfg: Any, num_envs: int, device: str | torch.device, seed: int, detector: str | None = None
    ) -> "FeatureMatchingAgent":
        c = to_plain_dict(cfg)
        check_keys(detector or "feature", c, cls.CONFIG_KEYS)
        kw = {k: c[k] for k in cls.CONFIG_KEYS if k in c}
        if detector is not None:
            if kw.get("detector", detector) != detector:
                raise ValueError(f"agent {detector!r}: config sets detector={kw['detector']!r}")
            kw["detector"] = detector
        return cls(num_envs, device, seed, **kw)

    # state ---------------------------------------------------------------------------------------
    def _fresh_state(self, ep: Episode | None) -> _SlotState:
        rng = episode_rng(self.seed, ep, self._rng)
        return _SlotState(
            difficulty=None if ep is None else ep.difficulty,
            target=None,
            prev=LEFT if rng.integers(0, 2) == 0 else RIGHT,
            history=deque(maxlen=max(1, self.osc_window - 1)),
            done=False,
        )

    def reset(self, env_ids: Sequence[int], episodes: Sequence[Episode | None]) -> None:
        """Start ``episodes`` in slots ``env_ids``; a ``None`` episode idles the slot (STOP, no work)."""
        super().reset(env_ids, episodes)
        for i, ep in zip(env_ids, episodes):
            self.states[int(i)] = self._fresh_state(ep)
            self.states[int(i)].done = ep is None

    def threshold(self, i: int) -> float:
        """``d_thresh`` of slot ``i`` (its episode's difficulty)."""
        d = self.states[i].difficulty
        return self.d_thresh.get(d, self.d_thresh["default"]) if d is not None else self.d_thresh["default"]

    # acting --------------------------------------------------------------------------------------
    def decide(self, i: int, cur: Features) -> int:
        """The action of slot ``i`` given its current-view features (updates the slot's history)."""
        st = self.states[i]
        tgt = st.target
        assert tgt is not None
        a: int | None = None
        if len(tgt) >= self.min_keypoints and len(cur) >= self.min_keypoints:
            ci, ti, dist = match_features(cur, tgt, self.detector, self.ratio)
            if len(ci) >= self.min_matches:
                keep = dist <= self.threshold(i)
                disp = tgt.pts[ti[keep]] - cur.pts[ci[keep]]
                a = vote_action(disp, self.stop_px)
                if a is not None and a != STOP and is_oscillating(st.history, a, self.osc_window, self.osc_rule):
                    a = STOP
        if a is None:
            a = st.prev
        st.history.append(a)
        st.prev = a
        if a == STOP:
            st.done = True
        return a

    def act(self, obs: Mapping[str, torch.Tensor]) -> torch.Tensor:
        view, target = self._check_obs(obs)
        actions = np.full(self.num_envs, STOP, dtype=np.int64)
        work = [i for i, st in enumerate(self.states) if not st.done]
        if work:
            need_t = [i for i in work if self.states[i].target is None]
            gv = rgb_to_gray(view[work] if len(work) < self.num_envs else view)
            gt = rgb_to_gray(target[need_t]) if need_t else None
            pos_t = {i: k for k, i in enumerate(need_t)}

            def step(k_i: tuple[int, int]) -> int:
                k, i = k_i
                st = self.states[i]
                if st.target is None:
                    st.target = detect(self.detector, gt[pos_t[i]], self.n_features)  # type: ignore[index]
                cur = detect(self.detector, gv[k], self.n_features)
                return self.decide(i, cur)

            # one slot: let OpenCV parallelise inside it; several: one slot per worker thread
            with cv2_num_threads(self.cv2_threads if len(work) > 1 else None):
                results = self.runner.map(step, list(enumerate(work)))
            for i, a in zip(work, results):
                actions[i] = a
        return self._as_actions(actions, view.device)

    def close(self) -> None:
        """Stop the worker threads."""
        self.runner.close()
