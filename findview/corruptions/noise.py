"""Noise corruptions: Gaussian, impulse (salt and pepper), shot (Poisson) and speckle noise."""

from __future__ import annotations

import torch

# standard deviation of additive noise, in units of the full intensity range [0, 1]
GAUSSIAN_NOISE = (0.08, 0.12, 0.18, 0.26, 0.38)
# fraction of values (per pixel and channel) replaced by 0 or 1
IMPULSE_NOISE = (0.03, 0.06, 0.09, 0.17, 0.27)
# photon count at full intensity: values are Poisson(x * c) / c
SHOT_NOISE = (60, 25, 12, 5, 3)
# standard deviation of the multiplicative noise
SPECKLE_NOISE = (0.15, 0.2, 0.35, 0.45, 0.6)


def gaussian_noise(x: torch.Tensor, severity: int, g: torch.Generator) -> torch.Tensor:
    """``x + N(0, c^2)`` independently per pixel and channel."""
    c = GAUSSIAN_NOISE[severity - 1]
    return x + c * torch.randn(x.shape, generator=g, device=x.device, dtype=x.dtype)


def impulse_noise(x: torch.Tensor, severity: int, g: torch.Generator) -> torch.Tensor:
    """Salt and pepper: each channel of each pixel independently becomes 1 (prob. c/2) or 0 (c/2)."""
    c = IMPULSE_NOISE[severity - 1]
    u = torch.rand(x.shape, generator=g, device=x.device)
    out = torch.where(u < c, (u < 0.5 * c).to(x.dtype), x)
    return out


def shot_noise(x: torch.Tensor, severity: int, g: torch.Generator) -> torch.Tensor:
    """``Poisson(x * c) / c`` independently per pixel and channel."""
    c = float(SHOT_NOISE[severity - 1])
    return torch.poisson(x * c, generator=g) / c


def speckle_noise(x: torch.Tensor, severity: int, g: torch.Generator) -> torch.Tensor:
    """``x + x * N(0, c^2)`` independently per pixel and channel."""
    c = SPECKLE_NOISE[severity - 1]
    return x + x * (c * torch.randn(x.shape, generator=g, device=x.device, dtype=x.dtype))
