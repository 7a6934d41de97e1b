"""A learned check of a stop: how far, in whole degrees, the view is from the target, under corruption.

Phase correlation (:mod:`findview_baselines.agents.stop_refine`) measures the residual rotation between view
and target as the shift of their content. Some corruptions move the content themselves: glass blur's pixel
shuffle drags it about 2 pixels down and to the right at severity 3 on 256x256 views (about 0.9 degree at FoV
90), and motion blur's one-sided kernel moves it along the blur. A matcher of content then stops one degree
off, on the view the corrupted target looks like. This module learns the offset from the simulator's exact
geometry instead: pairs of a view rendered ``(dpitch, dyaw)`` degrees from a target, the target corrupted as in
training (every corruption, severity 1-5, some clean), labelled with the offset.

Features of a pair (:func:`pair_features`, ``(B, FEATURES)``): normalised cross-correlation of the grey view
and target over pixel shifts ``-R..R`` on three bands (the image, a blurred copy, a high-pass copy), each a
``(2R+1)^2`` volume; gradient energies along four directions of the target, and their ratio to the view's (how
blurred, and along which direction, the target is); and the phase-correlation residual with its peak. A small
MLP (:class:`StopOffsetNet`) maps them to two 5-way classifications, the view's pitch and yaw offset from the
target clipped to ``-2..2`` degrees, and (files of version 2 made with far pairs) a third output, whether the view
is near the target at all (within :data:`NEAR_DEGREES` on both axes) or on another part of the panorama: a check
that a stop is on the target, not on a look-alike.

A :class:`~findview_baselines.agents.stop_refine.StopRefiner` given such a net (``agent.refine_model``) moves
one degree towards the target while the net's probability of "no offset" is below ``min_stay``; the net is for
the view size and field of view it was trained on (stored in its file). ``tools/train_stop_offsets.py`` makes
one. With ``agent.refine_min_near`` the agent also refuses a STOP whose view the net finds far from the target
(:meth:`StopOffsetNet.near_prob`) and searches on.
"""

from __future__ import annotations

import math
import os
from pathlib import Path

import torch
import torch.nn as nn
import torch.nn.functional as F

from findview.utils import atomic_write
from findview_baselines.agents.stop_refine import gray, residual_rotation

__all__ = [
    "SHIFTS",
    "CROP",
    "OFFSET_CLASSES",
    "NEAR_DEGREES",
    "FEATURES",
    "ncc_volume",
    "pair_features",
    "StopOffsetNet",
    "save_stop_offsets",
    "load_stop_offsets",
    "StopOffsetsError",
]

SHIFTS = 7
"""Pixel shifts ``-SHIFTS..SHIFTS`` of the correlation volumes, on each axis."""
CROP = 128
"""Side of the target's central square that is correlated, pixels."""
OFFSET_CLASSES = 5
"""Classes per axis: offsets -2, -1, 0, 1, 2 degrees (larger offsets are labelled +-2)."""
NEAR_DEGREES = 3
"""A view is *near* its target when it is at most this many degrees off on each axis (the offsets the net was
trained to read); farther views are the near output's negatives."""
_BANDS = 3
_STATS = 16
FEATURES = _BANDS * (2 * SHIFTS + 1) ** 2 + _STATS + 3
"""Length of a :func:`pair_features` row."""

_FORMAT = "findview-stop-offsets"
_VERSION = 2
_READS = (1, 2)  # version 1: no near output
_MID = OFFSET_CLASSES // 2


class StopOffsetsError(ValueError):
    """A file given as a stop-offset net that is not one, or one for other views; the message names it."""


def _grey(images: torch.Tensor) -> torch.Tensor:
    """(B, 3, H, W) uint8 or float (0-255) -> (B, H, W) float32, standardised per image (zero mean, unit std)."""
    g = gray(images) / 255.0
    return (g - g.mean(dim=(1, 2), keepdim=True)) / g.std(dim=(1, 2), keepdim=True).clamp_min(1e-3)


def _blur(x: torch.Tensor, sigma: float) -> torch.Tensor:
    """Separable Gaussian blur of (B, H, W), edges replicated."""
    k = int(math.ceil(3 * sigma))
    t = torch.arange(-k, k + 1, dtype=x.dtype, device=x.device)
    w = torch.exp(-t * t / (2 * sigma * sigma))
    w = w / w.sum()
    y = F.conv2d(F.pad(x[:, None], (k, k, 0, 0), mode="replicate"), w.view(1, 1, 1, -1))
    return F.conv2d(F.pad(y, (0, 0, k, k), mode="replicate"), w.view(1, 1, -1, 1))[:, 0]


def _window_sums(x: torch.Tensor, n: int) -> torch.Tensor:
    """Sums of (B, H, W) over every n x n window: (B, H - n + 1, W - n + 1) (summed-area table in float64)."""
    ii = F.pad(x.double().cumsum(1).cumsum(2), (1, 0, 1, 0))
    return (ii[:, n:, n:] - ii[:, :-n, n:] - ii[:, n:, :-n] + ii[:, :-n, :-n]).float()


def ncc_volume(view: torch.Tensor, target: torch.Tensor, shifts: int = SHIFTS, crop: int = CROP) -> torch.Tensor:
    """Normalised cross-correlation of ``target``'s central ``crop x crop`` square with ``view``'s windows.

    Args:
        view, target: ``(B, H, W)`` float grey images, ``H, W >= crop + 2 * shifts``.
    Returns:
        ``(B, 2 * shifts + 1, 2 * shifts + 1)`` in [-1, 1]; entry ``[shifts + dy, shifts + dx]`` compares the
        target's square with the view's square moved ``dy`` pixels down and ``dx`` right, so a view whose
        content sits ``(dy, dx)`` pixels down-right of the target's peaks there.
    """
    b, h, w = view.shape
    if min(h, w) < crop + 2 * shifts:
        raise ValueError(f"ncc_volume: views of {h}x{w} pixels are smaller than {crop + 2 * shifts}")
    oy, ox = (h - crop) // 2, (w - crop) // 2
    t = target[:, oy:oy + crop, ox:ox + crop]
    t = t - t.mean(dim=(1, 2), keepdim=True)
    t_norm = t.pow(2).sum(dim=(1, 2)).clamp_min(1e-6).sqrt()
    v = view[:, oy - shifts:oy + crop + shifts, ox - shifts:ox + crop + shifts]
    size = 2 * crop + 2 * shifts
    corr = torch.fft.irfft2(torch.fft.rfft2(v, s=(size, size)) * torch.fft.rfft2(t, s=(size, size)).conj(), s=(size, size))
    corr = corr[:, :2 * shifts + 1, :2 * shifts + 1]
    s1, s2 = _window_sums(v, crop), _window_sums(v * v, crop)
    var = (s2 - s1 * s1 / (crop * crop)).clamp_min(1e-6)
    return corr / (t_norm[:, None, None] * var.sqrt())


def _gradient_energy(x: torch.Tensor) -> torch.Tensor:
    """(B, H, W) -> (B, 4): mean squared difference of neighbours along x, y and the two diagonals."""
    diffs = (x[:, :, 1:] - x[:, :, :-1], x[:, 1:] - x[:, :-1], x[:, 1:, 1:] - x[:, :-1, :-1], x[:, 1:, :-1] - x[:, :-1, 1:])
    return torch.stack([d.pow(2).mean(dim=(1, 2)) for d in diffs], dim=1)


def pair_features(view: torch.Tensor, target: torch.Tensor, fov: float) -> torch.Tensor:
    """Features of view / target pairs for :class:`StopOffsetNet`.

    Args:
        view, target: ``(B, 3, H, W)`` uint8 (or float 0-255) images as rendered, ``H, W >= CROP + 2 * SHIFTS``.
        fov: the views' horizontal field of view, degrees.
    Returns:
        ``(B, FEATURES)`` float32: three NCC volumes (image, blurred sigma 1.5 px, high-pass sigma 3 px),
        log gradient energies of the target and their log ratio to the view's (raw and blurred), and the
        phase-correlation residual ``dyaw, dpitch`` (degrees) and peak.
    """
    gv, gt = _grey(view), _grey(target)
    lv, lt = _blur(gv, 1.5), _blur(gt, 1.5)
    hv, ht = gv - _blur(gv, 3.0), gt - _blur(gt, 3.0)
    volumes = [ncc_volume(a, b).flatten(1) for a, b in ((gv, gt), (lv, lt), (hv, ht))]
    energy_t = torch.cat([_gradient_energy(gt), _gradient_energy(lt)], dim=1).clamp_min(1e-6)
    energy_v = torch.cat([_gradient_energy(gv), _gradient_energy(lv)], dim=1).clamp_min(1e-6)
    stats = torch.cat([energy_t.log(), (energy_t / energy_v).log()], dim=1)
    dyaw, dpitch, peak = residual_rotation(view, target, fov)
    return torch.cat(volumes + [stats, torch.stack([dyaw, dpitch, peak], dim=1).float()], dim=1)


class StopOffsetNet(nn.Module):
    """MLP from :func:`pair_features` to the view's offset from the target, per axis.

    Args:
        fov: the field of view (degrees) and ``size`` the square view side (pixels) it is for.
        hidden: width of its two hidden layers.
        near: whether it has the near output (trained with far pairs).
    ``forward(features (B, FEATURES)) -> (pitch_logits (B, 5), yaw_logits (B, 5))``, classes = offsets -2..2
    degrees of the view from the target (pitch up +, yaw right +). The feature normaliser (``mean``, ``std``)
    is part of its state. :meth:`outputs` gives the near output's logit (``(B,)``) as well.
    """

    def __init__(self, fov: float, size: int, hidden: int = 256, dropout: float = 0.2, near: bool = False) -> None:
        super().__init__()
        self.fov, self.size, self.hidden, self.near = float(fov), int(size), int(hidden), bool(near)
        self.register_buffer("mean", torch.zeros(FEATURES))
        self.register_buffer("std", torch.ones(FEATURES))
        self.mlp = nn.Sequential(
            nn.Dropout(dropout), nn.Linear(FEATURES, hidden), nn.ReLU(),
            nn.Dropout(dropout), nn.Linear(hidden, hidden), nn.ReLU(),
            nn.Linear(hidden, 2 * OFFSET_CLASSES + int(self.near)),
        )

    def forward(self, features: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        pitch_logits, yaw_logits, _ = self.outputs(features)
        return pitch_logits, yaw_logits

    def outputs(self, features: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor | None]:
        """``(pitch_logits (B, 5), yaw_logits (B, 5), near_logit (B,) or None without the near output)``."""
        out = self.mlp((features - self.mean) / self.std)
        near = out[:, 2 * OFFSET_CLASSES] if self.near else None
        return out[:, :OFFSET_CLASSES], out[:, OFFSET_CLASSES:2 * OFFSET_CLASSES], near

    @torch.no_grad()
    def read(self, features: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
        """:func:`pair_features` rows ``(B, FEATURES)`` -> the most likely ``dpitch``, ``dyaw`` (``(B,)`` long, degrees,
        the view's offset from the target, -2..2) and the probability of no offset on either axis (``(B,)``)."""
        return self.reading(*self(features))

    @staticmethod
    def reading(pitch_logits: torch.Tensor, yaw_logits: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
        """:meth:`read` from the offset logits ``(B, 5)`` each (of :meth:`outputs`)."""
        p_pitch, p_yaw = pitch_logits.softmax(dim=1), yaw_logits.softmax(dim=1)
        return p_pitch.argmax(dim=1) - _MID, p_yaw.argmax(dim=1) - _MID, p_pitch[:, _MID] * p_yaw[:, _MID]

    def offsets(self, view: torch.Tensor, target: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
        """:meth:`read` of rendered pairs ``(B, 3, size, size)``."""
        self._check_size(view)
        return self.read(pair_features(view, target, self.fov))

    @torch.no_grad()
    def near_prob(self, view: torch.Tensor, target: torch.Tensor) -> torch.Tensor:
        """The probability ``(B,)`` that each rendered view ``(B, 3, size, size)`` is near its target (within
        :data:`NEAR_DEGREES` on both axes), not on another part of the panorama. Needs the near output."""
        if not self.near:
            raise StopOffsetsError("this stop-offset net has no near output (made without far pairs: "
                                   "tools/train_stop_offsets.py --far-fraction)")
        self._check_size(view)
        return torch.sigmoid(self.outputs(pair_features(view, target, self.fov))[2])

    def _check_size(self, view: torch.Tensor) -> None:
        if tuple(view.shape[-2:]) != (self.size, self.size):
            raise StopOffsetsError(
                f"stop-offset net for {self.size}x{self.size} views got {tuple(view.shape[-2:])} pixels")



def save_stop_offsets(path: str | os.PathLike, net: StopOffsetNet, meta: dict) -> Path:
    """Write ``net`` (weights, normaliser, fov, size, hidden) and ``meta`` (plain values: how it was made, its val
    accuracy) to ``path`` atomically; loads with ``torch.load(..., weights_only=True)``."""
    state = {
        "format": _FORMAT, "version": _VERSION, "fov": net.fov, "size": net.size, "hidden": net.hidden,
        "near": net.near, "features": FEATURES, "net": {k: v.detach().cpu() for k, v in net.state_dict().items()},
        "meta": dict(meta),
    }
    return atomic_write(path, lambda tmp: torch.save(state, tmp))


def load_stop_offsets(path: str | os.PathLike, fov: float | None = None, size: int | None = None) -> StopOffsetNet:
    """Load a :func:`save_stop_offsets` file (eval mode). ``fov`` / ``size``: the views it will see (degrees,
    pixels); a net made for others raises :class:`StopOffsetsError` naming both."""
    path = Path(path)
    if not path.is_file():
        raise StopOffsetsError(f"{path}: stop-offset net not found (make one with tools/train_stop_offsets.py)")
    try:
        state = torch.load(path, map_location="cpu", weights_only=True)
    except Exception as err:  # noqa: BLE001 - any unreadable file gets the same one-line error
        raise StopOffsetsError(f"{path}: not a readable torch file ({type(err).__name__}: {err})") from err
    if not isinstance(state, dict) or state.get("format") != _FORMAT:
        raise StopOffsetsError(f"{path}: not a stop-offset net (expected format {_FORMAT!r}, "
                               f"made by tools/train_stop_offsets.py)")
    if state.get("version") not in _READS or state.get("features") != FEATURES:
        raise StopOffsetsError(f"{path}: stop-offset net version {state.get('version')} with "
                               f"{state.get('features')} features; this findview reads versions "
                               f"{', '.join(map(str, _READS))} with {FEATURES}")
    near = bool(state.get("near", False)) if state["version"] >= 2 else False
    net = StopOffsetNet(float(state["fov"]), int(state["size"]), int(state["hidden"]), near=near)
    net.load_state_dict(state["net"])
    if fov is not None and abs(float(fov) - net.fov) > 1e-6:
        raise StopOffsetsError(f"{path}: made for FoV {net.fov:g} degrees, the views have FoV {float(fov):g}")
    if size is not None and int(size) != net.size:
        raise StopOffsetsError(f"{path}: made for {net.size}x{net.size} views, the views are {int(size)} pixels wide")
    return net.eval()
