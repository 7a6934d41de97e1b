"""Pitch-warped phase correlation: is the target above or below the view? (``agent.pitch_warps``)

A target straight above or below the view (pitch offsets of a sixth to a half of the FoV) shares a band of
content with it, but a pitch rotation is not a shift of the image: lines converge differently and a plain phase
correlation of the two (:class:`~findview_baselines.rl.encoders.PhaseCorrelation`) peaks little higher than for
an unrelated view. Here the target is first warped by the exact homography of each hypothesised pitch offset
``dp`` (the camera geometry of docs/TASK.md, world: the target camera is the view camera pitched by ``dp``,
exact when their yaws agree), so where the hypothesis is right the shared content lines up by a shift again,
and the phase correlation of the view with each warped target is computed as in ``PhaseCorrelation`` (grey,
block-averaged to about 32x32, Hann-windowed, wide band ``sigma = 0.3``, z-scores / 10).

Measured on the indoor training panoramas (64x64 views at FoV 90, 80 related pairs with ``|dp|`` 20-45 degrees
and yaw offsets up to 40 degrees against 80 unrelated pairs; benchmarks/RESULTS.md, session 22): the best warped
peak separates related from unrelated pairs with an AUC of 0.85 clean and 0.76-0.85 under fog, spatter, glass blur
and snow at severity 3 (the plain peak: 0.61-0.71), and its hypothesis has the right sign in 82-88% of the pairs.

Nothing here is learned (computed under ``torch.no_grad``); the policy reads the scalars through a small layer
that starts at zero (``Policy.warp_proj``), so an agent without them initialises one with them unchanged.
"""

from __future__ import annotations

import math

import torch
from torch import nn

from findview_baselines.rl.encoders import phase_setup, standardize

__all__ = ["WARP_FRACTIONS", "WARP_FEATURES", "warp_grids", "PitchWarpedPhase"]

#: hypothesised pitch offsets of the target relative to the view, as fractions of the horizontal FoV
#: (FoV 90: -45, -30, -15, +15, +30, +45 degrees; + means the target is above the view)
WARP_FRACTIONS = (-1 / 2, -1 / 3, -1 / 6, 1 / 6, 1 / 3, 1 / 2)
#: scalars per pair: per hypothesis the peak height, then per hypothesis the peak's (dy, dx) as fractions of the image
WARP_FEATURES = 3 * len(WARP_FRACTIONS)
# the Gaussian weight (cycles per pixel) on the normalised cross-power spectrum: PhaseCorrelation's wide band
WARP_BANDWIDTH = 0.3


def warp_grids(height: int, width: int, fov: float, offsets_deg: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """Sampling grids that warp a target image into the frame of a view ``dp`` degrees below it.

    Args:
        height, width: image size in pixels (square pixels; the focal length is ``width / (2 tan(fov / 2))``).
        fov: horizontal field of view in degrees.
        offsets_deg: (K,) pitch offsets ``dp`` of the target relative to the view, degrees (+ = target above).

    Returns:
        ``grid`` (K, height, width, 2) for ``grid_sample`` (``align_corners=False``; x, y in [-1, 1]): view pixel
        ``(i, j)`` reads the target where the same world direction falls in the target camera;
        ``valid`` (K, 1, height, width) float: 1 where that direction lies inside the target image and in front.
    """
    f = width / (2.0 * math.tan(math.radians(fov) / 2.0))
    jj, ii = torch.meshgrid(torch.arange(height, dtype=torch.float64) + 0.5 - height / 2,
                            torch.arange(width, dtype=torch.float64) + 0.5 - width / 2, indexing="ij")
    x, y, z = ii / f, -jj / f, torch.ones_like(ii)
    # the target camera is the view camera pitched by dp: d_target = pitch(-dp) d_view (docs/TASK.md, world, step 2)
    a = torch.deg2rad(offsets_deg.to(torch.float64))[:, None, None]
    y_t = y * torch.cos(a) - z * torch.sin(a)
    z_t = y * torch.sin(a) + z * torch.cos(a)
    u = x / z_t * f  # pixels right of the target's centre
    v = -y_t / z_t * f  # pixels below it
    valid = (z_t > 0) & (u.abs() < width / 2) & (v.abs() < height / 2)
    grid = torch.stack([u / (width / 2), v / (height / 2)], dim=-1)
    grid = torch.where(valid[..., None], grid, torch.full_like(grid, 2.0))  # outside: sampled as zero
    return grid.float(), valid[:, None].float()


class PitchWarpedPhase(nn.Module):
    """Phase correlation of the view with the target warped by each hypothesised pitch offset.

    ``forward(view, target)``: (B, 3, H, W) float in [0, 1] each -> (B, :data:`WARP_FEATURES`): the peak height
    of each hypothesis's surface (z-scores / 10, as ``PhaseCorrelation``), then the peak's row shift ``dy / h``
    per hypothesis, then its column shift ``dx / w`` (``h x w``: the block-averaged size). Hypotheses in the order
    of :data:`WARP_FRACTIONS` times ``fov``.
    """

    def __init__(self, height: int, width: int, fov: float) -> None:
        super().__init__()
        if not 0 < fov < 180:
            raise ValueError(f"pitch warps need a field of view in (0, 180) degrees, got {fov}")
        self.fov = float(fov)
        self.pool, self.height, self.width, window, weights = phase_setup(height, width, (WARP_BANDWIDTH,))
        offsets = torch.tensor(WARP_FRACTIONS, dtype=torch.float64) * self.fov
        grid, valid = warp_grids(self.height, self.width, self.fov, offsets)
        self.register_buffer("grid", grid, persistent=False)  # (K, h, w, 2)
        self.register_buffer("valid", valid, persistent=False)  # (K, 1, h, w)
        self.register_buffer("window", window, persistent=False)
        self.register_buffer("weights", weights[0], persistent=False)  # (2h, w + 1)

    def _grey(self, image: torch.Tensor) -> torch.Tensor:
        """(B, 3, H, W) -> (B, 1, h, w): standardised grey, block-averaged."""
        grey = standardize(image.float()).mean(dim=1, keepdim=True)
        return nn.functional.avg_pool2d(grey, self.pool)[..., :self.height, :self.width] if self.pool > 1 else grey

    def _spectrum(self, grey: torch.Tensor, mask: torch.Tensor) -> torch.Tensor:
        """(..., h, w) grey and mask -> the rfft of the masked, mean-removed (over the mask), windowed image."""
        mean = (grey * mask).sum(dim=(-2, -1), keepdim=True) / mask.sum(dim=(-2, -1), keepdim=True).clamp_min(1.0)
        return torch.fft.rfft2((grey - mean) * mask * self.window, s=(2 * self.height, 2 * self.width))

    @torch.no_grad()
    def forward(self, view: torch.Tensor, target: torch.Tensor) -> torch.Tensor:
        b, k = view.shape[0], self.grid.shape[0]
        h, w = self.height, self.width
        grey_v, grey_t = self._grey(view), self._grey(target)
        # every hypothesis at once: (B*K, 1, h, w) warped targets
        warped = nn.functional.grid_sample(
            grey_t.repeat_interleave(k, dim=0), self.grid.repeat(b, 1, 1, 1), mode="bilinear",
            padding_mode="zeros", align_corners=False,
        ).view(b, k, h, w)
        cross = self._spectrum(grey_v[:, 0], torch.ones_like(self.window))[:, None] \
            * self._spectrum(warped, self.valid[:, 0]).conj()
        cross = cross / cross.abs().clamp_min(1e-9)
        corr = torch.fft.irfft2(cross * self.weights, s=(2 * h, 2 * w)).flatten(2)  # (B, K, 4hw), shift 0 at 0
        z = (corr - corr.mean(dim=2, keepdim=True)) / corr.std(dim=2, keepdim=True).clamp_min(1e-9) / 10.0
        peak, where = z.max(dim=2)
        dy = where // (2 * w)
        dx = where % (2 * w)
        dy = torch.where(dy >= h, dy - 2 * h, dy).float() / h  # unshifted surface: index >= h is a negative shift
        dx = torch.where(dx >= w, dx - 2 * w, dx).float() / w
        return torch.cat([peak, dy, dx], dim=1)
