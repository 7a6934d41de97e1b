"""``rotation``: the exact geometric rule-based agent (beyond the paper).

It estimates the full relative rotation between its view and the target from feature matches with the
known pinhole geometry (docs/TASK.md, world), walks straight to the candidate pose this gives, checks
in structure and colour that the view there *is* the target before it calls STOP, refines the stop to
the best one-degree pose, and searches the sphere systematically when nothing matches. The target may
be corrupted (docs/TASK.md, corruptions; the view never is): keypoints are detected on locally
contrast-normalised images and every check is blind to what fog and contrast do to intensities.

Geometry (the relative rotation from feature matches, RANSAC + Kabsch, its decomposition into
``dpitch, dyaw``): ``rotation_geometry.py``; the photometric side (contrast normalisation for the
detector, the structure, colour and opponent-colour scores, the hue check): ``photometric.py``. This
module holds the agent and re-exports their names.

Dead reckoning. The agent never sees its rotation, but it knows every move it made: its pose relative
to the start, ``(pose_p, pose_y)`` degrees, is exact in yaw (moves never fail there) and in pitch up
to the clamp at the pitch bound. A pitch move into the bound leaves the view unchanged, byte for byte
(the renderer is deterministic): the agent compares the view after each pitch move with the one
before, and on a clamp it undoes the move in its reckoning and learns where the bounds lie relative
to the start (the bound is ``pitch_bound`` above and below the horizon, so the interval of reachable
relative pitches is ``2 * pitch_bound`` wide and holds every pitch it has visited).

Policy of a slot (states ``search``, ``goto``, ``refine``):

- ``goto`` a candidate pose (relative coordinates): one move per step along the axis with more moves
  left; a new estimate after half the moves the last one asked for (at least ``reestimate_every``)
  and on arrival replaces the candidate (``candidate = pose + round(estimate)``);
- **verify before stopping**: where the estimate rounds to ``(0, 0)`` (or on arrival without an
  estimate), :meth:`RotationAgent.verify` decides: the content must match (:func:`structure_score` of
  the locally contrast-normalised gray images at least ``verify_thresh``; less where the estimate
  vouches for the pose with ``verify_inliers`` inliers) and the colours must match (the high-passed
  colour correlation at least ``verify_colour``, or the high-passed opponent-colour correlation, which
  fog and contrast only scale, at least ``verify_opponent``; the mean colours the same hue up to a
  gain) -> refine and STOP; else the candidate is rejected: remembered, and estimates that point
  within ``reject_radius`` degrees of a rejected candidate are ignored from then on. After
  ``max_arrivals`` arrivals that each ask for more moves, the candidate is decided at the pose reached;
- **search** when no usable estimate exists: rows of constant pitch, each a yaw turn in one seeded
  direction, estimating every ``sweep_check_every`` moves from keypoints detected at ``search_scale``
  (a target in view is found at half size; the first look of an episode, the walk and the final
  checks use full-size views; when a whole row's worth of coarse looks in a row gave no valid estimate,
  e.g. a fogged target whose half-size keypoints are the fog's, the rest of the search looks at full
  size); a full-size look that gives no valid estimate looks again at ``search_scale`` (a blurred
  target keeps few fine keypoints: under motion blur at severity 3 full-size estimates are right on
  about a tenth of the poses where half-size ones are); a row turns ``360 - fov / 3`` degrees. The first row is at the start
  pitch; the next is ``sweep_pitch`` degrees above the highest row or below the lowest one, among
  those that can still hold uncovered target pitches (a row covers ``sweep_pitch / 2`` above and
  below it), bounded by what the agent knows of the pitch bounds: the nearer one while the horizon is
  unknown, and once a clamp has shown it, the one covering more of the task's target-pitch
  distribution (so a row planned beyond a bound is re-chosen when the clamp is met). A candidate
  interrupts the search; after a rejection the agent walks back to where it left the search and
  resumes it;
- **exact stop**: a view byte-identical to the target (a clean target) stops at once. A candidate
  that passes the check without being identical (a corrupted target, or an estimate off by one) is
  always refined (``refine``), however confident the estimate (blur biases it by a degree or two): the
  agent moves to its one-degree neighbours, scores each pose once with :func:`structure_score` at
  ``REFINE_SCALE`` (1 degree ~ 1 pixel), climbs to a better one while there is one and stops on the
  best (about 8 extra steps);
- when the search has covered every pitch, the agent walks to the best-scoring rejected candidate,
  refines there and stops; when no candidate came up at all, it searches once more with full-size
  views, then goes to the best-scoring view it checked (a featureless target, e.g. a clear sky),
  refines there and stops.

A valid estimate needs ``min_inliers`` inliers and plausible absolute pitches (within
``pitch_bound + pitch_tol``) when they are observable.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import Any

import cv2
import numpy as np
import torch

from findview.episode import Episode
from findview.geometry import focal_length
from findview_baselines.agents.base import DOWN, LEFT, RIGHT, STOP, UP, gray_of
from findview_baselines.agents.feature_base import (
    DETECTORS,
    FeatureAgent,
    Features,
    Slot,
    detect,
)
from findview_baselines.agents.photometric import (
    LCN_SIGMA,
    VERIFY_SCALE,
    VERIFY_SIGMA,
    colour_template,
    detection_image,
    hue_residual,
    mean_chromaticity,
    opponent_mean,
    opponent_template,
    photometric_score,
    photometric_template,
    structure_score,
    structure_template,
)
from findview_baselines.agents.rotation_geometry import (
    RotationEstimate,
    decompose_relative_rotation,
    estimate_from_features,
    estimate_from_images,
    estimate_relative_rotation,
    kabsch,
    pixel_bearings,
)

__all__ = [
    "RotationEstimate",
    "pixel_bearings",
    "kabsch",
    "decompose_relative_rotation",
    "estimate_relative_rotation",
    "estimate_from_features",
    "estimate_from_images",
    "photometric_template",
    "photometric_score",
    "mean_chromaticity",
    "structure_template",
    "structure_score",
    "opponent_mean",
    "hue_residual",
    "opponent_template",
    "detection_image",
    "RotationAgent",
    "VERIFY_SCALE",
    "VERIFY_SIGMA",
]


# --------------------------------------------------------------------------------------------------
# the agent
# --------------------------------------------------------------------------------------------------
REFINE_SCALE = 2  # the final one-degree refinement compares at this downsampling (1 degree ~ 1 pixel)
REFINE_SIGMA = 4.0  # ... of images locally contrast-normalised with this window (full-size pixels)
SEARCH, GOTO, REFINE = "search", "goto", "refine"


@dataclass
class _Target:
    features: Features
    template: np.ndarray  # structure_template of the target
    colour: np.ndarray  # colour_template of the target
    chroma: np.ndarray  # mean_chromaticity of the target
    opponent: np.ndarray  # opponent_mean of the target
    opp_layout: np.ndarray  # opponent_template of the target
    image: np.ndarray  # (3, H, W) uint8 copy: a view equal to it is the target
    coarse: Features | None = None  # keypoints at search_scale (computed on the first coarse estimate)
    fine: np.ndarray | None = None  # structure_template at REFINE_SCALE (computed when refining)


@dataclass
class _RotSlot(Slot):
    """State of one :class:`RotationAgent` slot (poses in degrees relative to the episode start)."""

    pose_p: int = 0
    pose_y: int = 0
    lo: int | None = None  # relative pitch of the lower bound, once a clamp showed it
    hi: int | None = None
    vis_min: int = 0  # lowest / highest relative pitch visited
    vis_max: int = 0
    last: int = -1  # previous action
    prev_view: np.ndarray | None = None  # the view before the last pitch move
    mode: str = SEARCH
    cand: tuple[int, int] | None = None
    since_est: int = 10**9  # moves since the last estimate
    est_left: int = 0  # moves to the candidate when it was last estimated
    looked: bool = False  # an estimate was made this episode
    arrivals: int = 0
    rejected: list = field(default_factory=list)  # [(pitch, yaw, score)]
    best_seen: tuple | None = None  # (pitch, yaw, score) of the best-scoring view checked while searching
    sweep_dir: int = RIGHT
    rows: list = field(default_factory=list)  # relative pitches of the rows swept
    row: int | None = None  # the row being swept
    row_moves: int = 0  # yaw moves made on it
    resume: tuple[int, int] | None = None  # where the search was left for a candidate
    scores: dict = field(default_factory=dict)  # refinement: {(pitch, yaw): fine score}
    queue: list = field(default_factory=list)  # refinement: poses still to score
    passes: int = 0  # completed searches of the whole sphere (a second one uses full-size views)
    blind: int = 0  # coarse search estimates in a row that found nothing valid
    full_search: bool = False  # the search estimates from full-size views (coarse ones found nothing for a row)
    exhausted: bool = False
    last_est: Any = None  # the last RotationEstimate (for inspection)


def _wrap(y: int) -> int:
    return 180 - ((180 - int(y)) % 360)


class RotationAgent(FeatureAgent):
    """Rotation estimation, verify-before-stop and a covering search (see the module docstring).

    Args:
        num_envs, device, seed: see :class:`~findview_baselines.agents.base.Agent`.
        fov: horizontal field of view of the views, degrees (must match the simulator).
        detector: ``"sift"`` (default) or ``"orb"``; n_features: keypoints per image (500).
        ratio: Lowe ratio for the candidate matches (0.8; RANSAC removes the outliers).
        inlier_px: RANSAC inlier tolerance, pixels at the image centre (2.0).
        ransac_iters: RANSAC hypotheses (200).
        min_inliers: inliers for a valid estimate (4; a wrong estimate costs a detour, not a wrong stop).
        pitch_bound: the task's pitch clamp, degrees (60); pitch_tol: slack on it for plausibility (10).
        reestimate_every: fewest moves between estimates while walking to a candidate (4); the next
            estimate comes after half the moves the last one asked for, at least this many, and on arrival.
        sweep_check_every: moves between estimates while searching (``None``: ``round(fov / 8)``).
        sweep_pitch: pitch between search rows, degrees (``None``: 0.8 x the vertical field of view).
        search_scale: the search detects keypoints on views downsampled by this factor (0.5; 1: full
            size); walking to a candidate and the final checks use full-size views, and look again at
            this scale when the full-size estimate is not valid.
        max_arrivals: arrivals that ask for more moves before the candidate is decided where it is (6).
        verify_thresh: :func:`structure_score` (content) needed to stop at a candidate (0.3).
        verify_thresh_geo: ... when the estimate at the view rounds to ``(0, 0)`` with at least
            ``verify_inliers`` (12) inliers (0.1); with such an estimate an opponent-colour score of
            ``verify_opponent`` also stands in for the content check.
        verify_colour: colour correlation (:func:`colour_template`) that makes the colours match (0.35).
        verify_opponent: ... or opponent-colour correlation (:func:`opponent_template`) (0.8).
        verify_hue: largest :func:`hue_residual` of the mean colours, grey levels (64).
        verify_chroma: largest difference of :func:`mean_chromaticity` (any channel) to stop (1.0: off).
        lcn_sigma: local contrast normalisation window before keypoint detection, pixels (4; ``None``:
            raw gray). See :meth:`RotationAgent.verify` for how the checks combine.
        reject_radius: estimates within this many degrees (each axis) of a rejected candidate are
            ignored (3).
        refine: after a candidate passes the check without being byte-identical to the target,
            hill-climb the structure score over its one-degree neighbours (moving there) and stop on
            the best (True).
        threads, cv2_threads: see :class:`~findview_baselines.agents.feature_base.FeatureAgent`.
    """

    name = "rotation"
    CONFIG_KEYS = (
        "fov",
        "detector",
        "n_features",
        "ratio",
        "inlier_px",
        "ransac_iters",
        "min_inliers",
        "pitch_bound",
        "pitch_tol",
        "reestimate_every",
        "sweep_check_every",
        "sweep_pitch",
        "search_scale",
        "max_arrivals",
        "verify_thresh",
        "verify_chroma",
        "verify_hue",
        "verify_colour",
        "verify_opponent",
        "verify_thresh_geo",
        "verify_inliers",
        "lcn_sigma",
        "reject_radius",
        "refine",
        "threads",
        "cv2_threads",
    )

    def __init__(
        self,
        num_envs: int,
        device: str | torch.device = "cpu",
        seed: int = 0,
        fov: float = 90.0,
        detector: str = "sift",
        n_features: int = 500,
        ratio: float = 0.8,
        inlier_px: float = 2.0,
        ransac_iters: int = 200,
        min_inliers: int = 4,
        pitch_bound: int = 60,
        pitch_tol: float = 10.0,
        reestimate_every: int = 4,
        sweep_check_every: int | None = None,
        sweep_pitch: int | None = None,
        search_scale: float = 0.5,
        max_arrivals: int = 6,
        verify_thresh: float = 0.3,
        verify_chroma: float = 1.0,
        verify_hue: float = 64.0,
        verify_colour: float = 0.35,
        verify_opponent: float = 0.8,
        verify_thresh_geo: float = 0.1,
        verify_inliers: int = 12,
        lcn_sigma: float | None = LCN_SIGMA,
        reject_radius: int = 3,
        refine: bool = True,
        threads: int = 2,
        cv2_threads: int | None = 1,
    ) -> None:
        if detector not in DETECTORS:
            raise ValueError(f"unknown detector {detector!r}; expected one of {DETECTORS}")
        focal_length(fov, 1)  # validates fov
        if not -1.0 <= float(verify_thresh) <= 1.0:
            raise ValueError(f"verify_thresh must be in [-1, 1], got {verify_thresh!r}")
        if int(pitch_bound) < 1:
            raise ValueError(f"pitch_bound must be >= 1 degree, got {pitch_bound!r}")
        self.fov = float(fov)
        self.detector = detector
        self.n_features = int(n_features)
        self.ratio = float(ratio)
        self.inlier_px = float(inlier_px)
        self.ransac_iters = int(ransac_iters)
        self.min_inliers = int(min_inliers)
        self.pitch_bound = int(pitch_bound)
        self.pitch_limit = float(pitch_bound) + float(pitch_tol)
        self.reestimate_every = max(1, int(reestimate_every))
        self.sweep_check_every = (
            max(1, int(round(self.fov / 8))) if sweep_check_every is None else max(1, int(sweep_check_every))
        )
        self.sweep_pitch = None if sweep_pitch is None else max(1, int(sweep_pitch))
        if not 0.0 < float(search_scale) <= 1.0:
            raise ValueError(f"search_scale must be in (0, 1], got {search_scale!r}")
        self.search_scale = float(search_scale)
        self.max_arrivals = int(max_arrivals)
        self.verify_thresh = float(verify_thresh)
        self.verify_chroma = float(verify_chroma)
        self.verify_hue = float(verify_hue)
        self.verify_colour = float(verify_colour)
        self.verify_opponent = float(verify_opponent)
        self.verify_thresh_geo = float(verify_thresh_geo)
        self.verify_inliers = int(verify_inliers)
        if lcn_sigma is not None and not float(lcn_sigma) > 0.0:
            raise ValueError(f"lcn_sigma must be > 0 pixels or None, got {lcn_sigma!r}")
        self.lcn_sigma = None if lcn_sigma is None else float(lcn_sigma)
        self.reject_radius = int(reject_radius)
        self.refine = bool(refine)
        super().__init__(num_envs, device, seed, threads=threads, cv2_threads=cv2_threads)

    # state ---------------------------------------------------------------------------------------
    def new_slot(self, episode: Episode | None, rng: np.random.Generator) -> _RotSlot:
        return _RotSlot(
            rng=rng,
            difficulty=None if episode is None else episode.difficulty,
            sweep_dir=LEFT if rng.integers(0, 2) == 0 else RIGHT,
        )

    def prepare_target(self, slot: Slot, target: np.ndarray) -> _Target:
        return _Target(
            features=self._features(gray_of(target), False),
            template=structure_template(target),
            colour=colour_template(target),
            chroma=mean_chromaticity(target),
            opponent=opponent_mean(target),
            opp_layout=opponent_template(target),
            image=np.array(target, copy=True),
        )

    def row_spacing(self, height: int, width: int) -> int:
        """Pitch between search rows, degrees: ``sweep_pitch``, else 0.8 x the vertical field of view."""
        if self.sweep_pitch is not None:
            return self.sweep_pitch
        vfov = 2.0 * math.degrees(math.atan(height / 2.0 / focal_length(self.fov, width)))
        return max(1, int(round(0.8 * vfov)))

    # estimates -----------------------------------------------------------------------------------
    def _detect(self, gray: np.ndarray, scale: float) -> Features:
        """Keypoints of a ``(H, W)`` gray image, detected on its local-contrast-normalised version
        (:func:`detection_image`, window ``lcn_sigma`` full-size pixels times ``scale``, the size of
        ``gray`` relative to the view) unless ``lcn_sigma`` is ``None``."""
        if self.lcn_sigma is not None:
            gray = detection_image(gray, max(1.0, self.lcn_sigma * scale))
        return detect(self.detector, gray, self.n_features)

    def _features(self, gray: np.ndarray, coarse: bool) -> Features:
        """Keypoints of a ``(H, W)`` gray image, in full-resolution pixel coordinates; ``coarse``:
        detected on the image downsampled by ``search_scale`` (area average)."""
        if not coarse or self.search_scale >= 1.0:
            return self._detect(gray, 1.0)
        h, w = gray.shape
        sw, sh = max(16, int(round(w * self.search_scale))), max(16, int(round(h * self.search_scale)))
        small = cv2.resize(gray, (sw, sh), interpolation=cv2.INTER_AREA)
        f = self._detect(small, self.search_scale)
        if len(f):
            scale = np.array([w / sw, h / sh], np.float32)
            f = Features((f.pts + 0.5) * scale - 0.5, f.des)
        return f

    def estimate(self, s: _RotSlot, view: np.ndarray, coarse: bool = False) -> RotationEstimate:
        """The target's rotation relative to ``view`` (``(3, H, W)`` uint8) from feature matches;
        ``coarse``: from keypoints detected at ``search_scale`` (cheaper; used while searching)."""
        _, h, w = view.shape
        tgt: _Target = s.target
        if coarse and self.search_scale < 1.0:
            if tgt.coarse is None:
                tgt.coarse = self._features(gray_of(tgt.image), True)
            ref, inlier_px = tgt.coarse, self.inlier_px / self.search_scale
        else:
            ref, inlier_px = tgt.features, self.inlier_px
        return estimate_from_features(
            self._features(gray_of(view), coarse),
            ref,
            self.fov,
            h,
            w,
            s.rng,
            detector=self.detector,
            ratio=self.ratio,
            inlier_px=inlier_px,
            iterations=self.ransac_iters,
            min_inliers=self.min_inliers,
            pitch_limit=self.pitch_limit,
        )

    def verify(self, s: _RotSlot, view: np.ndarray, est: RotationEstimate | None = None) -> tuple[bool, float]:
        """The check of ``view`` against the slot's target before a stop: ``(accept, score)``.

        Four pieces of evidence, each blind to what fog and contrast do to a picture:

        - *structure*: :func:`structure_score` (correlation of the locally contrast-normalised gray
          images, blind to gain, offset and smooth fields);
        - *colour*: :func:`photometric_score` of the high-passed colour images (:func:`colour_template`);
        - *opponent colour*: :func:`photometric_score` of the colour-difference layouts
          (:func:`opponent_template`), which a grey fog field cancels in exactly and fog / contrast only
          scale: about 1 for the target's own view under fog and contrast, at most ~0.6 elsewhere;
        - *geometry*: ``est`` (the estimate made at this view) puts the target here, rounded to ``(0, 0)``,
          with at least ``verify_inliers`` inliers.

        Accept when the colours match, i.e. colour at least ``verify_colour`` or opponent colour at least
        ``verify_opponent``, the mean colours are the same hue up to a gain (:func:`hue_residual` at most
        ``verify_hue``) and their chromaticities differ by at most ``verify_chroma`` (1: off), and the
        content matches: structure at least ``verify_thresh``; or, with the geometry, structure at least
        ``verify_thresh_geo``; or the geometry *and* opponent colour at least ``verify_opponent`` (two
        independent checks that a washed-out target, whose structure score falls to ~0.1, still passes).
        The colour correlation alone needs 0.35: the mirror faces of a flat-coloured cube (the same edges,
        other colours) reach 0.30 with up to 15 inliers, while their opponent colour stays below 0.45, so
        a fogged view whose colour correlation falls to 0.2-0.35 passes on its opponent colour instead.
        ``score`` ranks candidates (the structure score, minus 1 when the colours do not match)."""
        tgt: _Target = s.target
        score = structure_score(structure_template(view), tgt.template)
        opp_ok = photometric_score(opponent_template(view), tgt.opp_layout) >= self.verify_opponent
        colour_ok = (
            (opp_ok or photometric_score(colour_template(view), tgt.colour) >= self.verify_colour)
            and float(np.abs(mean_chromaticity(view) - tgt.chroma).max()) <= self.verify_chroma
            and hue_residual(tgt.opponent, opponent_mean(view)) <= self.verify_hue
        )
        here = est is not None and est.valid and est.inliers >= self.verify_inliers and est.rounded() == (0, 0)
        content_ok = score >= self.verify_thresh or (here and (score >= self.verify_thresh_geo or opp_ok))
        return (content_ok and colour_ok), (score if colour_ok else score - 1.0)

    def _pitch_range(self, s: _RotSlot) -> tuple[int, int]:
        """Relative pitches that may be reachable (exact once a clamp showed a bound)."""
        if s.lo is not None and s.hi is not None:
            return s.lo, s.hi
        return s.vis_max - 2 * self.pitch_bound, s.vis_min + 2 * self.pitch_bound

    def _usable(self, s: _RotSlot, cand: tuple[int, int]) -> bool:
        lo, hi = self._pitch_range(s)
        if not lo <= cand[0] <= hi:
            return False
        r = self.reject_radius
        return not any(
            abs(cand[0] - p) <= r and abs(_wrap(cand[1] - y)) <= r for p, y, _ in s.rejected
        )

    def _reject(self, s: _RotSlot, score: float) -> None:
        s.rejected.append((s.pose_p, s.pose_y, score))
        s.cand = None
        s.arrivals = 0
        s.mode = SEARCH

    # the rule ------------------------------------------------------------------------------------
    def step(self, i: int, slot: Slot, view: np.ndarray | None) -> int:
        s: _RotSlot = slot  # type: ignore[assignment]
        assert view is not None and s.target is not None
        self._account_last_move(s, view)
        a = self._decide(s, view)
        if a in (UP, DOWN):
            s.prev_view = np.array(view, copy=True)
            s.pose_p += 1 if a == UP else -1
            s.vis_min, s.vis_max = min(s.vis_min, s.pose_p), max(s.vis_max, s.pose_p)
        elif a in (LEFT, RIGHT):
            s.pose_y = _wrap(s.pose_y + (1 if a == RIGHT else -1))
        else:
            s.done = True
        if a != STOP:
            s.since_est += 1
        s.last = a
        return a

    def _account_last_move(self, s: _RotSlot, view: np.ndarray) -> None:
        """Dead reckoning: a pitch move that left the view unchanged hit the bound."""
        if s.last not in (UP, DOWN) or s.prev_view is None:
            return
        same = np.array_equal(view, s.prev_view)
        s.prev_view = None
        if not same or float(view[:, ::4, ::4].std()) < 1.0:  # a flat view cannot tell
            return
        up = s.last == UP
        s.pose_p += -1 if up else 1
        if up:
            s.hi, s.lo = s.pose_p, s.pose_p - 2 * self.pitch_bound
        else:
            s.lo, s.hi = s.pose_p, s.pose_p + 2 * self.pitch_bound
        s.queue = [q for q in s.queue if s.lo <= q[0] <= s.hi]
        if s.mode == GOTO and s.cand is not None and not s.lo <= s.cand[0] <= s.hi:
            s.cand, s.mode, s.arrivals = None, SEARCH, 0  # the candidate lies beyond the bound

    def _decide(self, s: _RotSlot, view: np.ndarray) -> int:
        tgt: _Target = s.target
        if np.array_equal(view, tgt.image):
            return STOP  # the exact target (clean targets)
        if s.mode == REFINE:
            return self._refine(s, view)
        if s.exhausted:
            return self._finish(s, view)
        arrived = s.mode == GOTO and s.cand == (s.pose_p, s.pose_y)
        if s.mode == GOTO and s.cand is not None:
            # re-estimate halfway to the candidate (estimates get better as the overlap grows)
            every = max(self.reestimate_every, s.est_left // 2)
        else:
            every = self.sweep_check_every
        if arrived or s.since_est >= every:
            s.since_est = 0
            # the first look of an episode is at full size (easy and medium targets are often in view)
            coarse = s.mode == SEARCH and s.looked and s.passes == 0 and not s.full_search
            est = self.estimate(s, view, coarse=coarse)
            if not coarse and not est.valid and self.search_scale < 1.0:
                # a blurred target keeps few fine keypoints; its half-size ones still match
                est = self.estimate(s, view, coarse=True)
            s.looked = True
            if coarse:  # a whole row of coarse looks without a valid estimate: search at full size
                s.blind = 0 if est.valid else s.blind + 1
                row_checks = -(-(360 - int(round(self.fov / 3))) // self.sweep_check_every)
                s.full_search = s.blind >= row_checks
            s.last_est = est
            if s.mode == SEARCH:  # remember the best-looking view, the answer if nothing matches
                score = self.verify(s, view)[1]
                if s.best_seen is None or score > s.best_seen[2]:
                    s.best_seen = (s.pose_p, s.pose_y, score)
            if est.valid:
                dp, dy = est.rounded()
                cand = (s.pose_p + dp, _wrap(s.pose_y + dy))
                if (dp, dy) == (0, 0):
                    if self._usable(s, cand) or arrived:
                        ok, score = self.verify(s, view, est)
                        if ok:
                            return self._refine(s, view, start=True)
                        self._reject(s, score)
                        arrived = False
                elif self._usable(s, cand):
                    if s.mode == SEARCH and s.resume is None:
                        s.resume = (s.pose_p, s.pose_y)
                    if arrived:
                        s.arrivals += 1
                    s.mode, s.cand = GOTO, cand
                    s.est_left = abs(dp) + abs(dy)
                    arrived = False
                    if s.arrivals >= self.max_arrivals:
                        arrived = True  # decide here
            if arrived:
                ok, score = self.verify(s, view, est)
                if ok:
                    return self._refine(s, view, start=True)
                self._reject(s, score)
        if s.mode == GOTO and s.cand is not None:
            return self._walk_to(s, s.cand)
        return self._search_move(s, view)

    def _refine(self, s: _RotSlot, view: np.ndarray, start: bool = False) -> int:
        """Verified, but the view is not the exact target (a corrupted target, or an estimate off by a
        degree; a byte-identical view stops before this is called): hill-climb a fine
        :func:`structure_score` (``REFINE_SCALE``: 1 degree ~ 1 pixel) over the one-degree neighbours,
        scoring every pose visited once, then stop on the best. A confident estimate is no reason to
        skip it: blur and a corrupted target bias estimates by a degree or two."""
        if start and not self.refine:
            return STOP
        tgt: _Target = s.target
        if tgt.fine is None:
            tgt.fine = structure_template(tgt.image, 1, REFINE_SIGMA, REFINE_SCALE)
        pose = (s.pose_p, s.pose_y)
        if start:
            s.mode, s.scores, s.queue = REFINE, {}, []
        if pose not in s.scores:
            s.scores[pose] = structure_score(structure_template(view, 1, REFINE_SIGMA, REFINE_SCALE), tgt.fine)
            best = max(s.scores, key=s.scores.get)
            if best == pose:  # a new best: score its neighbours
                lo, hi = self._pitch_range(s)
                p0, y0 = pose
                around = ((p0, _wrap(y0 + 1)), (p0, _wrap(y0 - 1)), (p0 + 1, y0), (p0 - 1, y0))
                s.queue = [q for q in around if lo <= q[0] <= hi and q not in s.scores]
        s.queue = [q for q in s.queue if q not in s.scores]
        goal = s.queue[0] if s.queue else max(s.scores, key=s.scores.get)
        a = self._walk_to(s, goal)
        return STOP if a < 0 else a

    def _walk_to(self, s: _RotSlot, goal: tuple[int, int]) -> int:
        dp = goal[0] - s.pose_p
        dy = _wrap(goal[1] - s.pose_y)
        if abs(dy) >= abs(dp) and dy != 0:
            return RIGHT if dy > 0 else LEFT
        if dp != 0:
            return UP if dp > 0 else DOWN
        return -1  # already there

    def _search_move(self, s: _RotSlot, view: np.ndarray) -> int:
        if s.resume is not None:
            a = self._walk_to(s, s.resume)
            if a >= 0:
                return a
            s.resume = None
        _, h, w = view.shape
        spacing = self.row_spacing(h, w)
        if s.row is None:
            s.row, s.row_moves = 0, 0
        lo, hi = self._pitch_range(s)
        if (s.row > hi or s.row < lo) and s.rows:  # a bound found on the way: choose the row again
            s.row = self._next_row(s, spacing)
            if s.row is None:
                return self._search_move(s, view) if self._exhaust(s) else self._finish(s, view)
        if s.row > hi or s.row < lo:
            s.row = min(max(s.row, lo), hi)
        if s.pose_p != s.row:
            return UP if s.row > s.pose_p else DOWN
        row_len = 360 - int(round(self.fov / 3))
        if s.row_moves < row_len:
            s.row_moves += 1
            return s.sweep_dir
        # row done: the next one
        s.rows.append(s.row)
        nxt = self._next_row(s, spacing)
        if nxt is None:
            return self._search_move(s, view) if self._exhaust(s) else self._finish(s, view)
        s.row, s.row_moves = nxt, 0
        return self._search_move(s, view)

    def _exhaust(self, s: _RotSlot) -> bool:
        """Every row is done. Nothing found at all: search again with full-size views (returns True);
        else the search is over (returns False)."""
        if not s.rejected and s.passes == 0 and self.search_scale < 1.0:
            s.passes, s.rows, s.row, s.row_moves = 1, [], 0, 0
            return True
        s.exhausted = True
        return False

    def _next_row(self, s: _RotSlot, spacing: int) -> int | None:
        """The next search row (relative pitch), ``None`` when the rows cover every reachable pitch.

        The candidates are one ``spacing`` above the highest row and below the lowest (within what is
        known of the bounds). Once a clamp has shown where the horizon is, the one that newly covers
        more of the task's target-pitch distribution (normal, std ``0.3 * pitch_bound`` about the
        horizon) wins; before that, the nearer one (up on a tie)."""
        lo, hi = self._pitch_range(s)
        half = spacing / 2.0
        top, bot = max(s.rows), min(s.rows)
        options = []
        if top + half < hi:
            options.append(min(top + spacing, hi))
        if bot - half > lo:
            options.append(max(bot - spacing, lo))
        options = [r for r in options if r not in s.rows]
        if not options:
            return None
        if s.lo is None:
            return min(options, key=lambda r: (abs(r - s.pose_p), -r))
        horizon = s.lo + self.pitch_bound  # relative pitch of the horizon
        sd = 0.3 * self.pitch_bound * math.sqrt(2.0)

        def cdf(x: float) -> float:
            return math.erf((x - horizon) / sd)

        def gain(r: int) -> float:  # new coverage beyond [bot - half, top + half]
            if r > top:
                return cdf(min(r + half, hi)) - cdf(top + half)
            return cdf(bot - half) - cdf(max(r - half, lo))

        return max(options, key=lambda r: (round(gain(r), 6), -abs(r - s.pose_p)))

    def _finish(self, s: _RotSlot, view: np.ndarray) -> int:
        """Search exhausted: go to the best-scoring rejected candidate or, when no candidate ever came
        up (e.g. a featureless sky), to the best-scoring view seen; refine there and stop."""
        options = s.rejected + ([s.best_seen] if s.best_seen is not None else [])
        if not options:
            return STOP
        best = max(options, key=lambda c: c[2])
        a = self._walk_to(s, (best[0], best[1]))
        if a >= 0:
            return a
        s.last_est = None
        return self._refine(s, view, start=True)
