"""Wide-shift matching of view and target: where is a target that only overlaps the edge of the view? (``agent.wide_match``)

The ``phase`` encoder's phase correlation (:class:`~findview_baselines.rl.encoders.PhaseCorrelation`) Hann-windows
both images, which weights their edges near zero. A target 45-70 degrees to the side of a FoV-90 view shares only
an edge band with it (the view's left edge, the target's right edge), so the window erases exactly what they
share: on the sun360_mini indoor val episodes' first views (64x64, FoV 90, clean) the sign of its peak's column shift is
right for 25 of 29 targets within 20 degrees of yaw but for only 29 of 63 at 45-65 degrees, a coin toss; the
coarse cost volume's 8x8 thumbnails are too coarse to do better. Without a direction the network turns its
habitual way and goes the long way round a third of the time.

This module measures the zero-normalised cross-correlation (ZNCC) of view and target over their overlap, for every
shift, with no window: for a shift ``(dy, dx)`` (pixels of the block-averaged ``h x w`` images) the overlap is
the set of target pixels ``(y, x)`` whose ``(y + dy, x + dx)`` lies in the view, and

    zncc(dy, dx) = sum (v - mean_v)(t - mean_t) / sqrt(sum (v - mean_v)^2 * sum (t - mean_t)^2)

with the means and sums over the overlap only (the view's content ``dy`` rows down and ``dx`` columns right of
the target's: the convention of ``PhaseCorrelation``). Six FFT cross-correlations give every shift at once (the
masked-correlation identity: the overlap's count, sums and sums of squares are correlations with an image of
ones). Shifts whose overlap is less than :data:`MIN_OVERLAP` of the image are left out (too few pixels to trust).
Measured on the same episodes: the peak's column shift has the right sign for 55 of 63 targets at 45-65 degrees
and 11 of 12 at 65-90; under brightness, contrast, frost, snow, noise and motion blur at severity 3 about as
often; fog defeats it (phase correlation's wide band holds there).

Nothing here is learned (computed under ``torch.no_grad``); the policy reads the features through a small
network whose last layer starts at zero (``Policy.wide_proj``), so an agent without them initialises one with
them unchanged (``init_from``).
"""

from __future__ import annotations

import torch
from torch import nn

from findview_baselines.rl.encoders import PHASE_SIDE, standardize

__all__ = ["MIN_OVERLAP", "WIDE_BINS", "WIDE_FEATURES", "WIDE_PEAK", "WideMatch", "overlap_zncc"]

#: the smallest overlap, as a fraction of the image's pixels, of a shift whose ZNCC counts (at FoV 90 a yaw
#: shift of up to 72 degrees; 0.3 was as good up to 65 degrees and worse beyond)
MIN_OVERLAP = 0.2
#: bins a side of the coarse ZNCC surface (max-pooled over every shift with enough overlap)
WIDE_BINS = 9
#: features per pair: the coarse surface (``WIDE_BINS`` squared, dy-major), then the peak's height and its
#: (dy, dx) as fractions of the image
WIDE_FEATURES = WIDE_BINS * WIDE_BINS + 3
#: the column of the peak's height (the best ZNCC over the shifts with enough overlap) among the features
WIDE_PEAK = WIDE_BINS * WIDE_BINS
# the score of a shift with too little overlap (below any ZNCC)
LOW = -1.0


def overlap_zncc(view: torch.Tensor, target: torch.Tensor, min_overlap: float = MIN_OVERLAP) -> torch.Tensor:
    """ZNCC of ``view`` and ``target`` over their overlap for every integer shift.

    Args:
        view, target: (B, h, w) float grey images.
        min_overlap: shifts whose overlap has fewer than ``min_overlap * h * w`` pixels score :data:`LOW` (-1).

    Returns:
        (B, 2h - 1, 2w - 1): entry ``(h - 1 + dy, w - 1 + dx)`` is the ZNCC of ``view[y + dy, x + dx]`` with
        ``target[y, x]`` over the pixels where both exist, in [-1, 1] (1: the overlaps are equal up to a positive
        gain and an offset); a flat overlap scores 0.
    """
    b, h, w = view.shape
    size = (2 * h, 2 * w)  # zero-padded: no shift wraps round

    def spectrum(x: torch.Tensor) -> torch.Tensor:
        return torch.fft.rfft2(x, s=size)

    ones = torch.ones(1, h, w, dtype=view.dtype, device=view.device)
    f_v, f_vv, f_t, f_tt, f_1 = spectrum(view), spectrum(view * view), spectrum(target), spectrum(target * target), spectrum(ones)

    def xcorr(f_a: torch.Tensor, f_b: torch.Tensor) -> torch.Tensor:
        """sum_x a[x + s] b[x] for every shift s, shift 0 at [h - 1, w - 1] after the crop below."""
        full = torch.fft.fftshift(torch.fft.irfft2(f_a * f_b.conj(), s=size), dim=(-2, -1))  # shift 0 at [h, w]
        return full[..., 1:, 1:]

    count = xcorr(f_1, f_1).round().clamp_min(1.0)
    sum_v, sum_t = xcorr(f_v, f_1), xcorr(f_1, f_t)
    var_v = (xcorr(f_vv, f_1) - sum_v * sum_v / count).clamp_min(0.0)
    var_t = (xcorr(f_1, f_tt) - sum_t * sum_t / count).clamp_min(0.0)
    cov = xcorr(f_v, f_t) - sum_v * sum_t / count
    scale = (var_v * var_t).sqrt()
    zncc = torch.where(scale > 1e-6 * count, cov / scale.clamp_min(1e-12), torch.zeros_like(cov)).clamp(-1.0, 1.0)
    return torch.where(count >= min_overlap * h * w, zncc, torch.full_like(zncc, LOW))


class WideMatch(nn.Module):
    """View-target ZNCC over every shift with enough overlap, as :data:`WIDE_FEATURES` scalars per pair.

    ``forward(view, target)``: (B, 3, H, W) float in [0, 1] each -> (B, :data:`WIDE_FEATURES`): the standardised
    grey images, block-averaged as the phase correlation's (``p = min(H, W) // 32``: 64x64 -> 32x32), their
    :func:`overlap_zncc`; the surface max-pooled to ``WIDE_BINS x WIDE_BINS`` bins over the shifts with at least
    :data:`MIN_OVERLAP` overlap (dy-major: bin ``(i, j)`` covers the i-th band of row shifts, up is first), then the
    peak's height and its ``(dy / h, dx / w)``. A target equal to the view reads 1 at zero shift; a peak at a
    positive ``dx`` means the target's content lies ``dx`` columns right in the view (the target is to the right),
    at a positive ``dy`` that it lies lower in the view (the target is below).
    """

    def __init__(self, height: int, width: int) -> None:
        super().__init__()
        self.pool = max(1, min(int(height), int(width)) // PHASE_SIDE)  # as the phase correlation's blocks
        self.height, self.width = int(height) // self.pool, int(width) // self.pool
        h, w = self.height, self.width
        # the shifts with enough overlap: |dy| <= ry, |dx| <= rx (a rectangle inside the region, pooled to bins)
        need = MIN_OVERLAP * h * w
        dy = torch.arange(-(h - 1), h)[:, None]
        dx = torch.arange(-(w - 1), w)[None, :]
        enough = (h - dy.abs()) * (w - dx.abs()) >= need
        self.reach_y = int(dy[enough.any(dim=1)].abs().max())
        self.reach_x = int(dx[:, enough.any(dim=0)].abs().max())

    def _grey(self, image: torch.Tensor) -> torch.Tensor:
        """(B, 3, H, W) -> (B, h, w): standardised grey, block-averaged."""
        grey = standardize(image.float()).mean(dim=1, keepdim=True)
        if self.pool > 1:
            grey = nn.functional.avg_pool2d(grey, self.pool)
        return grey[:, 0, :self.height, :self.width]

    @torch.no_grad()
    def forward(self, view: torch.Tensor, target: torch.Tensor) -> torch.Tensor:
        h, w = self.height, self.width
        z = overlap_zncc(self._grey(view), self._grey(target))  # (B, 2h - 1, 2w - 1)
        ry, rx = self.reach_y, self.reach_x
        surface = nn.functional.adaptive_max_pool2d(z[:, None, h - 1 - ry:h + ry, w - 1 - rx:w + rx], WIDE_BINS)
        peak, where = z.flatten(1).max(dim=1)
        peak_y = (where // (2 * w - 1) - (h - 1)).float() / h
        peak_x = (where % (2 * w - 1) - (w - 1)).float() / w
        return torch.cat([surface.flatten(1), peak[:, None], peak_y[:, None], peak_x[:, None]], dim=1)
