"""A final refinement of a learned agent's stop: the residual rotation between view and target, measured.

A learned agent that stops one degree off the target (64-pixel views over 90 degrees: 0.56 pixel per
degree at the centre) cannot see the difference well in its own features. Phase correlation can: the
normalised cross-power spectrum of two images shifted by ``d`` pixels is a pure phase ramp whose inverse
transform peaks at ``d``, with sub-pixel accuracy from a parabola through the peak and its neighbours.
Near the centre of a perspective view a small rotation is close to a translation of ``f * tan(angle)``
pixels, ``f = (W / 2) / tan(fov / 2)``.

When the policy answers STOP and the measured residual is at least ``min_shift`` degrees on an axis (and
the correlation peak is clear, ``>= min_peak``: a stop far from the target gives no clear peak and is left
as it is), the slot moves one degree towards the target instead, and keeps refining (without the policy)
until the residual is below ``min_shift`` or ``max_moves`` moves were made; then it stops.

With a learned stop-offset net (``offsets``, :mod:`findview_baselines.agents.stop_offsets`) the net decides
instead of the measured residual: the slot moves one degree towards the target while the net's probability that
the view is on the target is below ``min_stay`` (at most ``max_moves`` moves). No peak threshold applies: under
glass blur the peak of a view on its target is about 0.05, below ``min_peak``, which is why the residual never
refines those stops. It learned the offsets that
corruptions such as glass blur put between a target's content and its pose, which the measured shift reads as a
rotation.

A net with the near output (trained with far pairs) and ``min_near`` also checks that a stop is on the target at
all: :meth:`StopRefiner.refuse` says which stops are on views the net finds far from their target, and the agent
searches on from those (``agent.refine_min_near``). A second net (``near_offsets``, ``agent.refine_near_model``)
can answer that question instead, so a net trained against look-alikes checks the stops while the first keeps
deciding the refinement's moves.

Batched over environments, on any device (``torch.fft``).
"""

from __future__ import annotations

import math

import torch

from typing import TYPE_CHECKING

from findview_baselines.agents.base import DOWN, LEFT, RIGHT, STOP, UP

if TYPE_CHECKING:
    from findview_baselines.agents.stop_offsets import StopOffsetNet

__all__ = ["gray", "residual_rotation", "phase_spectrum", "rotation_between", "move_towards", "StopRefiner"]

_GRAY = (0.299, 0.587, 0.114)


def gray(images: torch.Tensor) -> torch.Tensor:
    """(N, 3, H, W) uint8 or float -> (N, H, W) float32 gray."""
    x = images.float()
    return x[:, 0] * _GRAY[0] + x[:, 1] * _GRAY[1] + x[:, 2] * _GRAY[2]


def _subpixel(left: torch.Tensor, mid: torch.Tensor, right: torch.Tensor) -> torch.Tensor:
    """Vertex offset in [-0.5, 0.5] of the parabola through (-1, left), (0, mid), (1, right).

    Biased away from 0 for shifts under a pixel (a one-degree rotation of a 64-pixel view, 0.56 pixel, reads
    0.8 pixel), but a shift of 0 reads about 0 on the other axis, which is what the stop decision needs.
    """
    denom = left - 2 * mid + right
    offset = torch.where(denom.abs() > 1e-12, 0.5 * (left - right) / denom, torch.zeros_like(mid))
    return offset.clamp(-0.5, 0.5)


def phase_spectrum(images: torch.Tensor, block: int = 1) -> torch.Tensor:
    """The spectrum phase correlation compares: ``(N, h, w // 2 + 1)`` complex, the real FFT of the grey image
    ``(N, 3, H, W)`` (uint8 or float), averaged over ``block x block`` pixel blocks (``h = H / block``, ``w = W /
    block``; H and W multiples of it), its mean removed, under a Hann window."""
    if images.shape[-2] % block or images.shape[-1] % block:
        raise ValueError(f"phase_spectrum: {tuple(images.shape[-2:])} pixels are not blocks of {block}")
    if block > 1:  # grey and block mean in one pass over the pixels, channels last (the environment's layout)
        n, _, hh, ww = images.shape
        x = images.permute(0, 2, 3, 1).float().reshape(n, hh // block, block, ww // block, block * 3).sum(dim=2)
        g = x @ (torch.tensor(_GRAY, device=images.device).repeat(block) / (block * block))
    else:
        g = gray(images)
    h, w = g.shape[-2:]
    window = torch.hann_window(h, periodic=False, device=g.device)[:, None] * torch.hann_window(w, periodic=False, device=g.device)[None, :]
    g = g - g.mean(dim=(1, 2), keepdim=True)
    return torch.fft.rfft2(g * window)


def rotation_between(
    view_spectrum: torch.Tensor, target_spectrum: torch.Tensor, fov: float, width: int
) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """:func:`residual_rotation` from the two images' :func:`phase_spectrum` (``(N, h, w // 2 + 1)``; ``width``:
    ``w``, the pixels the spectra were taken over; ``fov``: the views' horizontal field of view, degrees). Returns
    ``dyaw``, ``dpitch`` ``(N,)`` degrees and ``peak`` ``(N,)``, as :func:`residual_rotation`."""
    n, h, w = view_spectrum.shape[0], view_spectrum.shape[1], int(width)
    cross = view_spectrum * target_spectrum.conj()
    cross = cross / cross.abs().clamp_min(1e-9)
    corr = torch.fft.irfft2(cross, s=(h, w))  # peak at d where view(x) ~ target(x - d)
    flat = corr.reshape(n, -1)
    peak, where = flat.max(dim=1)
    py, px = where // w, where % w
    rows = torch.arange(n, device=corr.device)
    dy = _subpixel(corr[rows, (py - 1) % h, px], peak, corr[rows, (py + 1) % h, px])
    dx = _subpixel(corr[rows, py, (px - 1) % w], peak, corr[rows, py, (px + 1) % w])
    shift_y = torch.where(py > h // 2, py - h, py).float() + dy
    shift_x = torch.where(px > w // 2, px - w, px).float() + dx
    focal = (w / 2.0) / math.tan(math.radians(fov) / 2.0)
    # content displaced to the right in the view (shift_x > 0) is where the target is: turn right;
    # displaced upwards (shift_y < 0, image rows grow downwards): look up
    dyaw = torch.rad2deg(torch.atan(shift_x / focal))
    dpitch = torch.rad2deg(torch.atan(-shift_y / focal))
    return dyaw, dpitch, peak


def residual_rotation(
    view: torch.Tensor, target: torch.Tensor, fov: float
) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """The rotation from the view to the target, measured by phase correlation.

    Args:
        view, target: (N, 3, H, W) images (uint8 or float), same size.
        fov: horizontal field of view of the views, degrees.

    Returns:
        ``dyaw`` (N,) degrees, positive when the target lies to the right (turn RIGHT);
        ``dpitch`` (N,) degrees, positive when the target lies above (move UP);
        ``peak`` (N,) the correlation peak in [0, 1] (about 1 for a pure shift of the same content, a few
        hundredths for unrelated images).
    """
    return rotation_between(phase_spectrum(view), phase_spectrum(target), fov, view.shape[-1])


def move_towards(view_pitch: torch.Tensor, view_yaw: torch.Tensor, stay: torch.Tensor,
                 min_stay: float) -> tuple[torch.Tensor, torch.Tensor]:
    """The refinement's rule on a stop-offset net's reading (``StopOffsetNet.read``: the view's offset from the
    target, degrees, and the probability of none; ``(B,)`` each): the one-degree move towards the target,
    ``dpitch``, ``dyaw`` ``(B,)`` long in {-1, 0, 1} (up / right positive), on the axis with the larger offset (yaw
    on ties); ``(0, 0)``, stay, where ``stay >= min_stay`` or no offset is read."""
    still = stay >= min_stay
    yaw_first = view_yaw.abs() >= view_pitch.abs()
    dyaw = torch.where(still | ~yaw_first, torch.zeros_like(view_yaw), -view_yaw.sign())
    dpitch = torch.where(still | yaw_first, torch.zeros_like(view_pitch), -view_pitch.sign())
    return dpitch, dyaw


class StopRefiner:
    """Per-slot state of the stop refinement (see the module docstring).

    Args:
        num_envs: slots.
        fov: horizontal field of view of the views, degrees.
        max_moves: refinement moves allowed per episode before the slot stops where it is.
        min_shift: residual (degrees, per axis) below which the slot stops.
        min_peak: correlation peak needed to trust the measured residual.
        offsets: a learned stop-offset net that decides the moves instead of the residual (see the module
            docstring); ``None``: the residual decides.
        min_stay: with ``offsets``, the net's probability of "on the target" below which the slot moves.
        min_near: with ``offsets`` that have the near output (or ``near_offsets``): :meth:`refuse` refuses a stop
            whose view the net gives a probability of being near the target below this (``None``: every stop is
            refined, none refused).
        near_offsets: with ``offsets`` and ``min_near``: a second stop-offset net with the near output that answers
            :meth:`near_prob` instead of ``offsets`` (which keeps deciding the moves); ``None``: ``offsets`` answers.
    """

    def __init__(self, num_envs: int, fov: float, max_moves: int = 4, min_shift: float = 0.5,
                 min_peak: float = 0.15, offsets: "StopOffsetNet | None" = None, min_stay: float = 0.3,
                 min_near: float | None = None, near_offsets: "StopOffsetNet | None" = None) -> None:
        if max_moves < 1:
            raise ValueError(f"max_moves must be >= 1, got {max_moves}")
        if not 0 < fov < 180:
            raise ValueError(f"fov must be in (0, 180) degrees, got {fov}")
        if not 0 < min_stay <= 1:
            raise ValueError(f"min_stay must be a probability in (0, 1], got {min_stay}")
        self.fov, self.max_moves, self.min_shift, self.min_peak = float(fov), int(max_moves), float(min_shift), float(min_peak)
        if near_offsets is not None:
            if offsets is None or min_near is None:
                raise ValueError("near_offsets is the near check of a refinement by a stop-offset net: it needs "
                                 "offsets and min_near")
            if not near_offsets.near:
                raise ValueError("near_offsets has no near output (tools/train_stop_offsets.py --far-fraction > 0)")
        if min_near is not None:
            if not 0 < min_near < 1:
                raise ValueError(f"min_near must be a probability in (0, 1) or None, got {min_near}")
            if offsets is None or not (offsets.near or near_offsets is not None):
                raise ValueError("min_near needs a stop-offset net with the near output "
                                 "(tools/train_stop_offsets.py --far-fraction > 0)")
        self.offsets, self.min_stay = offsets, float(min_stay)
        self.near_offsets = offsets if near_offsets is None else near_offsets
        self.min_near = None if min_near is None else float(min_near)
        self.refining = torch.zeros(num_envs, dtype=torch.bool)
        self.moves = torch.zeros(num_envs, dtype=torch.long)

    def reset(self, env_ids: list[int]) -> None:
        self.refining[env_ids] = False
        self.moves[env_ids] = 0

    def near_prob(self, view: torch.Tensor, target: torch.Tensor) -> torch.Tensor:
        """``(B,)`` float on the views' device: the net's probability that each view ``(B, 3, H, W)`` is near its
        target (within 3 degrees on each axis), from ``near_offsets`` if given, else ``offsets``; needs
        ``min_near``."""
        if self.min_near is None:
            raise ValueError("StopRefiner.near_prob: no min_near given (a stop-offset net with the near output)")
        return self.near_offsets.to(view.device).near_prob(view, target)

    def refuse(self, view: torch.Tensor, target: torch.Tensor) -> torch.Tensor:
        """``(B,)`` bool on the views' device: the stops to refuse, where the net's probability that the view
        ``(B, 3, H, W)`` is near its target is below ``min_near`` (a look-alike part of the panorama)."""
        return self.near_prob(view, target) < self.min_near

    def decide(self, env_ids: torch.Tensor, view: torch.Tensor, target: torch.Tensor) -> torch.Tensor:
        """Actions (len(env_ids),) for slots that want to stop or are refining: one degree towards the
        target, or STOP. ``view`` / ``target``: those slots' observations."""
        ids = env_ids.cpu()
        if self.offsets is None:
            dyaw, dpitch, peak = (t.cpu() for t in residual_rotation(view, target, self.fov))
            trusted = (peak >= self.min_peak) & (self.moves[ids] < self.max_moves)
            off = torch.maximum(dyaw.abs(), dpitch.abs()) >= self.min_shift
        else:  # the net's one-degree move towards the target (no peak needed)
            trusted = self.moves[ids] < self.max_moves
            reading = (t.cpu() for t in self.offsets.to(view.device).offsets(view, target))
            dpitch, dyaw = move_towards(*reading, self.min_stay)
            off = (dyaw != 0) | (dpitch != 0)
        yaw_first = dyaw.abs() >= dpitch.abs()
        move = torch.where(
            yaw_first,
            torch.where(dyaw > 0, torch.tensor(RIGHT), torch.tensor(LEFT)),
            torch.where(dpitch > 0, torch.tensor(UP), torch.tensor(DOWN)),
        )
        go = trusted & off
        actions = torch.where(go, move, torch.tensor(STOP))
        self.refining[ids] = go
        self.moves[ids] += go.long()
        return actions.to(env_ids.device)
