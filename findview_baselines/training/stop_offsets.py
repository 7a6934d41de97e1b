"""Training of a stop-offset net (:mod:`findview_baselines.agents.stop_offsets`) on the simulator's exact geometry.

A pair is a target rendered at a random pose of a panorama (pitch -50..50, yaw -179..180 degrees), corrupted as the
robust agents train (each corruption equally likely, severity 1-5; a ``clean_fraction`` left clean), and a view
rendered ``(dpitch, dyaw)`` degrees from it: each axis 0 with probability 0.4, else +-1, +-2 or +-3 equally. The
label is the offset per axis, clipped to -2..2. With ``far_fraction`` some views are put far from their target
instead (half anywhere on the panorama, half 4-30 degrees off on one axis and up to 30 on the other): the negatives
of the net's near output (a view within :data:`~findview_baselines.agents.stop_offsets.NEAR_DEGREES` on both axes
is near). With ``lookalike`` = k > 1 each view put anywhere is the most alike of k such poses instead (the highest
normalised correlation of grey 32x32 renders of view and clean target, poses within 10 degrees of the target on both
axes excluded): the look-alike parts of a panorama (a forest's trees, a hall's windows) the near output must refuse.
Only the features of a pair are kept (:func:`pair_features`), so memory grows by about 3 KB a pair.

:func:`split_panoramas` loads the panoramas of a split (:func:`pooled_panoramas`: of several splits files),
:func:`sample_pairs` makes the pairs, :func:`fit` trains the MLP (Adam, cosine learning rate, cross-entropy of both
axes) and :func:`accuracy` reports what the refinement needs:
how often a view on its target is left alone, and how often a view one degree off is sent the right way.
``tools/train_stop_offsets.py`` is the command; ``tools/report_stop_offsets.py`` scores nets on the same pairs.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path
from typing import Sequence

import numpy as np
import torch
import torch.nn.functional as F
from tqdm import tqdm

from findview.corruptions import NAMES, corrupt
from findview.dataset.splits import SPLITS_FILE, load_split
from findview.imageio import load_panorama
from findview.sim.equi2pers import equi2pers
from findview_baselines.agents.stop_offsets import (
    FEATURES,
    NEAR_DEGREES,
    OFFSET_CLASSES,
    StopOffsetNet,
    pair_features,
)
from findview_baselines.agents.stop_refine import gray, move_towards

__all__ = ["Pairs", "split_panoramas", "pooled_panoramas", "sample_pairs", "fit", "accuracy"]

_CHUNK = 500
_MID = OFFSET_CLASSES // 2


@dataclass
class Pairs:
    """Features ``(N, FEATURES)`` float32 of view / target pairs, their offsets ``dpitch`` / ``dyaw`` ``(N,)`` long
    (degrees, the view's from the target's, before clipping), ``corruption`` ``(N,)`` long (index in
    :data:`findview.corruptions.NAMES`, -1 clean) and ``severity`` ``(N,)`` long (1-5)."""

    features: torch.Tensor
    dpitch: torch.Tensor
    dyaw: torch.Tensor
    corruption: torch.Tensor
    severity: torch.Tensor

    def __len__(self) -> int:
        return len(self.dpitch)

    @property
    def near(self) -> torch.Tensor:
        """``(N,)`` bool: the view is within ``NEAR_DEGREES`` of its target on both axes."""
        return (self.dpitch.abs() <= NEAR_DEGREES) & (self.dyaw.abs() <= NEAR_DEGREES)

    @staticmethod
    def cat(parts: Sequence["Pairs"]) -> "Pairs":
        return Pairs(*(torch.cat([getattr(p, k) for p in parts]) for k in
                       ("features", "dpitch", "dyaw", "corruption", "severity")))


def split_panoramas(splits: Path, root: Path, split: str) -> list[torch.Tensor]:
    """The panoramas of ``split`` in the splits file ``splits`` (tools/make_dataset.py's, images under ``root``),
    each ``(3, He, 2 He)`` uint8. Raises ``ValueError`` naming the file for another file or an empty split, and
    :class:`~findview.dataset.splits.MissingDataFile` for a missing one."""
    if splits.name != SPLITS_FILE:
        raise ValueError(f"{splits}: expected the {SPLITS_FILE} of tools/make_dataset.py")
    entries = load_split(splits.parent, split, root=root)
    if not entries:
        raise ValueError(f"{splits}: the {split!r} split is empty")
    return [torch.from_numpy(load_panorama(e.path)).permute(2, 0, 1).contiguous() for e in entries]


def pooled_panoramas(splits: Sequence[Path], root: Path, split: str) -> list[torch.Tensor]:
    """The panoramas of ``split`` in every splits file of ``splits`` (say the indoor and the outdoor one), in order;
    :func:`split_panoramas` of each, with its errors."""
    return [pano for path in splits for pano in split_panoramas(Path(path), root, split)]


def _axis_offsets(rng: np.random.Generator, n: int) -> np.ndarray:
    magnitude = rng.integers(1, 4, n) * np.where(rng.random(n) < 0.5, -1, 1)
    return np.where(rng.random(n) < 0.4, 0, magnitude)


def _far_offsets(seed: int, n: int, pitch: np.ndarray, yaw: np.ndarray, far_fraction: float
                 ) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Which of ``n`` pairs get a far view, its offsets ``(dpitch, dyaw)`` from the target (degrees, yaw wrapped
    to -180..180), and which of them are anywhere: half at a uniform pose (pitch -60..60), half 4-30 degrees off on
    one axis and 0-30 on the other, either sign. Drawn from their own stream so that ``far_fraction=0`` leaves the
    near pairs as they were."""
    rng = np.random.default_rng([seed, 1])
    far = rng.random(n) < far_fraction
    anywhere = rng.random(n) < 0.5
    major = rng.integers(4, 31, n) * np.where(rng.random(n) < 0.5, -1, 1)  # one axis 4-30 off, the other 0-30
    minor = rng.integers(0, 31, n) * np.where(rng.random(n) < 0.5, -1, 1)
    pitch_major = rng.random(n) < 0.5
    near_p, near_y = np.where(pitch_major, major, minor), np.where(pitch_major, minor, major)
    any_p = rng.integers(-60, 61, n) - pitch
    any_y = (rng.integers(-179, 181, n) - yaw + 180) % 360 - 180
    return far, np.where(anywhere, any_p, near_p), np.where(anywhere, any_y, near_y), far & anywhere


_THUMB = 32  # side of the renders that pick look-alike views, pixels
_APART = 10  # a look-alike candidate is at least this far from its target on one axis, degrees


def _thumbnails(equi: torch.Tensor, pitch: np.ndarray, yaw: np.ndarray, fov: float) -> torch.Tensor:
    """``(len(pitch), THUMB * THUMB)`` grey renders of one panorama ``(3, He, 2 He)`` at the poses (degrees), each
    zero-mean and unit-norm (their dot product is the normalised correlation)."""
    views = equi2pers(equi[None].expand(len(pitch), -1, -1, -1), torch.as_tensor(pitch, dtype=torch.float32),
                      torch.as_tensor(yaw, dtype=torch.float32), fov, _THUMB, _THUMB)
    grey = gray(views).flatten(1)
    grey = grey - grey.mean(1, keepdim=True)
    return grey / grey.norm(dim=1, keepdim=True).clamp_min(1e-6)


def _lookalike_offsets(seed: int, panoramas: Sequence[torch.Tensor], pano: np.ndarray, pitch: np.ndarray,
                       yaw: np.ndarray, rows: np.ndarray, k: int, fov: float) -> tuple[np.ndarray, np.ndarray]:
    """For the pairs ``rows``: the offsets ``(dpitch, dyaw)`` (degrees, yaw wrapped) of the most alike of ``k``
    uniform poses (pitch -60..60) at least ``_APART`` degrees from the target on one axis, its own stream."""
    rng = np.random.default_rng([seed, 2])
    cand_p = rng.integers(-60, 61, (len(rows), k))
    cand_y = rng.integers(-179, 181, (len(rows), k))
    dp = cand_p - pitch[rows, None]
    dy = (cand_y - yaw[rows, None] + 180) % 360 - 180
    score = np.full((len(rows), k), -np.inf)
    for m in np.unique(pano[rows]):
        sel = np.flatnonzero(pano[rows] == m)
        for a in range(0, len(sel), _CHUNK):
            part = sel[a:a + _CHUNK]
            target = _thumbnails(panoramas[m], pitch[rows[part]], yaw[rows[part]], fov)
            cand = _thumbnails(panoramas[m], cand_p[part].ravel(), cand_y[part].ravel(), fov).view(len(part), k, -1)
            score[part] = torch.einsum("nd,nkd->nk", target, cand).numpy()
    score[(np.abs(dp) < _APART) & (np.abs(dy) < _APART)] = -np.inf
    best = np.argmax(score, axis=1)  # every row has an allowed candidate unless all k fall within _APART
    pick = np.arange(len(rows))
    return dp[pick, best], dy[pick, best]


def sample_pairs(panoramas: Sequence[torch.Tensor], n: int, fov: float, size: int, seed: int,
                 corruptions: Sequence[str] = NAMES, clean_fraction: float = 0.2, progress: bool = False,
                 far_fraction: float = 0.0, lookalike: int = 1) -> Pairs:
    """``n`` pairs from ``panoramas`` (each ``(3, He, 2 He)`` uint8), views ``size x size`` pixels over ``fov``
    degrees, targets corrupted by one of ``corruptions`` (or clean, ``clean_fraction``), a ``far_fraction`` of the
    views far from their target, those put anywhere the most alike of ``lookalike`` poses (module docstring);
    reproducible from ``seed``."""
    unknown = [c for c in corruptions if c not in NAMES]
    if unknown or not corruptions:
        raise ValueError(f"corruptions {list(corruptions)}: expected names from {', '.join(NAMES)}")
    if not 0.0 <= far_fraction < 1.0:
        raise ValueError(f"far_fraction must be in [0, 1), got {far_fraction}")
    if int(lookalike) < 1:
        raise ValueError(f"lookalike must be a number of candidate poses >= 1 (1: a uniform pose), got {lookalike}")
    if not panoramas:
        raise ValueError("sample_pairs: no panoramas")
    rng = np.random.default_rng(seed)
    gen = torch.Generator().manual_seed(seed)
    pitch = rng.integers(-50, 51, n)
    yaw = rng.integers(-179, 181, n)
    dpitch, dyaw = _axis_offsets(rng, n), _axis_offsets(rng, n)
    pano = rng.integers(0, len(panoramas), n)
    names = np.array([NAMES.index(c) for c in corruptions])
    corruption = np.where(rng.random(n) < clean_fraction, -1, names[rng.integers(0, len(names), n)])
    severity = rng.integers(1, 6, n)
    if far_fraction > 0:
        far, far_p, far_y, anywhere = _far_offsets(seed, n, pitch, yaw, far_fraction)
        if int(lookalike) > 1 and anywhere.any():
            rows = np.flatnonzero(anywhere)
            far_p[rows], far_y[rows] = _lookalike_offsets(seed, panoramas, pano, pitch, yaw, rows, int(lookalike), fov)
        dpitch, dyaw = np.where(far, far_p, dpitch), np.where(far, far_y, dyaw)
    features = []
    with tqdm(total=n, unit="pair", disable=not progress, dynamic_ncols=True) as bar:
        for a in range(0, n, _CHUNK):
            b = min(n, a + _CHUNK)
            views = torch.empty(b - a, 3, size, size, dtype=torch.uint8)
            targets = torch.empty_like(views)
            for k in np.unique(pano[a:b]):  # one batched render per panorama of the chunk
                rows = np.flatnonzero(pano[a:b] == k)
                equi = panoramas[k][None].expand(len(rows), -1, -1, -1)
                p, y = torch.as_tensor(pitch[a + rows], dtype=torch.float32), torch.as_tensor(yaw[a + rows], dtype=torch.float32)
                targets[rows] = equi2pers(equi, p, y, fov, size, size)
                views[rows] = equi2pers(equi, p + torch.as_tensor(dpitch[a + rows], dtype=torch.float32),
                                        y + torch.as_tensor(dyaw[a + rows], dtype=torch.float32), fov, size, size)
            for c in np.unique(corruption[a:b]):
                for s in range(1, 6):
                    rows = np.flatnonzero((corruption[a:b] == c) & (severity[a:b] == s))
                    if c >= 0 and len(rows):
                        targets[rows] = corrupt(targets[rows], NAMES[c], s, generator=gen)
            features.append(pair_features(views, targets, fov))
            bar.update(b - a)
    as_long = lambda x: torch.as_tensor(x, dtype=torch.long)  # noqa: E731
    return Pairs(torch.cat(features), as_long(dpitch), as_long(dyaw), as_long(corruption), as_long(severity))


def _labels(offsets: torch.Tensor) -> torch.Tensor:
    return offsets.clamp(-_MID, _MID) + _MID  # far pairs' labels are never used


def fit(train: Pairs, fov: float, size: int, epochs: int = 30, seed: int = 0, hidden: int = 256,
        batch: int = 256, lr: float = 1e-3) -> StopOffsetNet:
    """Train a :class:`StopOffsetNet` on ``train`` (its normaliser from ``train``'s features); returns it in eval
    mode. Pairs with far views give the net its near output (binary cross-entropy on all pairs); the offsets are
    learned from the near pairs only."""
    if len(train) == 0 or train.features.shape[1] != FEATURES:
        raise ValueError(f"fit: expected pairs with {FEATURES} features, got {tuple(train.features.shape)}")
    near = train.near
    with_far = bool((~near).any())
    if not near.any():
        raise ValueError("fit: every pair is far; the offsets need near pairs")
    torch.manual_seed(seed)
    net = StopOffsetNet(fov, size, hidden, near=with_far)
    net.mean.copy_(train.features.mean(0))
    net.std.copy_(train.features.std(0).clamp_min(1e-4))
    opt = torch.optim.Adam(net.mlp.parameters(), lr, weight_decay=1e-4)
    sched = torch.optim.lr_scheduler.CosineAnnealingLR(opt, epochs)
    y_pitch, y_yaw = _labels(train.dpitch), _labels(train.dyaw)
    shuffle = torch.Generator().manual_seed(seed)
    net.train()
    for _ in range(epochs):
        order = torch.randperm(len(train), generator=shuffle)
        for i in range(0, len(order), batch):
            rows = order[i:i + batch]
            pitch_logits, yaw_logits, near_logit = net.outputs(train.features[rows])
            on = near[rows]
            loss = F.binary_cross_entropy_with_logits(near_logit, on.float()) if near_logit is not None else 0.0
            if on.any():
                loss = (loss + F.cross_entropy(pitch_logits[on], y_pitch[rows][on])
                        + F.cross_entropy(yaw_logits[on], y_yaw[rows][on]))
            opt.zero_grad()
            loss.backward()
            opt.step()
        sched.step()
    return net.eval()


@torch.no_grad()
def accuracy(net: StopOffsetNet, pairs: Pairs, min_stay: float, min_near: float = 0.5) -> dict[str, dict[str, float]]:
    """Per corruption (``clean`` and each name in ``pairs``): ``stay``, the share of views on their target the
    refinement leaves alone, and ``one_off``, the share of views one degree off (on one axis or both) whose first
    move goes towards the target, with the refinement's rule (move while P(on target) < ``min_stay``, on the axis
    with the larger predicted offset, yaw on ties). With the near output: ``keep``, the share of views at most 2
    degrees off on each axis whose P(near) is at least ``min_near`` (a stop there is kept), and ``refuse``, the
    share of far views below it (a stop there is refused). The last entry, ``all``, is the same over every pair."""
    pitch_logits, yaw_logits, near_logit = net.outputs(pairs.features)  # one pass for the offsets and the near output
    move_pitch, move_yaw = move_towards(*net.reading(pitch_logits, yaw_logits), min_stay)
    kept = torch.sigmoid(near_logit) >= min_near if near_logit is not None else None
    close = (pairs.dpitch.abs() <= 2) & (pairs.dyaw.abs() <= 2)
    stay = (move_pitch == 0) & (move_yaw == 0)
    right_way = torch.where(move_yaw != 0, move_yaw == -pairs.dyaw.sign(), move_pitch == -pairs.dpitch.sign())
    on = (pairs.dpitch == 0) & (pairs.dyaw == 0)
    one_off = ~on & (pairs.dpitch.abs() <= 1) & (pairs.dyaw.abs() <= 1)
    groups = [("clean" if c < 0 else NAMES[c], pairs.corruption == c) for c in [-1, *range(len(NAMES))]]
    out = {}
    for name, rows in groups + [("all", torch.ones_like(on))]:
        if not rows.any():
            continue
        a, b = rows & on, rows & one_off
        out[name] = {
            "stay": float(stay[a].float().mean()) if a.any() else float("nan"),
            "one_off": float((~stay & right_way)[b].float().mean()) if b.any() else float("nan"),
            "pairs": int(rows.sum()),
        }
        if kept is not None:
            c_rows, f_rows = rows & close, rows & ~pairs.near
            out[name]["keep"] = float(kept[c_rows].float().mean()) if c_rows.any() else float("nan")
            out[name]["refuse"] = float((~kept[f_rows]).float().mean()) if f_rows.any() else float("nan")
    return out
