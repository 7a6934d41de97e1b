"""Recurrent actor-critic policy of the FindView PPO baseline (docs/TASK.md, section PPO baseline).

Data flow for one step of ``N`` environments::

    obs {"view", "target"}: (N, 3, H, W) uint8
        -> fusion (variant-dependent, see below)   -> features (N, F)
        -> GRU(hidden_size), state reset where masks == 0 -> h (N, hidden)
        -> actor Linear -> 5 logits (Categorical)  and  critic Linear -> value (N,)

Variants (``variant`` in ``configs/agent/ppo.yaml``):

- ``early_fusion`` (paper default): view and target stacked on channels (6 channels) and encoded by one
  CNN encoder -> F = hidden_size.
- ``goal_encoder``: the early-fusion encoder plus a second encoder that sees the target alone; both
  feature vectors are concatenated -> F = 2 * hidden_size.
- ``siamese``: one 3-channel encoder shared by the view and the target (same weights), the two feature
  vectors are fused late by concat + Linear + ReLU -> F = hidden_size.
- ``correlation``: a small conv encoder shared by the view and the target (feature maps on a
  ``CORR_GRID x CORR_GRID`` grid, 8x8 for any image size), a global correlation volume between the two
  maps (every view cell against every target cell, binned by displacement: all shifts up to the full map
  size, so any overlap a 90-degree view can show), a conv head on that volume, plus the pooled absolute
  pixel difference of view and target (exactly 0 on the target: the stop cue) and the pooled features of
  both images (scene context for searching) -> F = hidden_size. See :class:`CorrelationEncoder`.
  ``fine_shifts = k > 0`` adds a local photometric cost map at full input resolution: the mean absolute
  grey-level difference of view and target for every pixel shift ``(dy, dx)`` in ``[-k, k]^2`` (see
  :meth:`CorrelationEncoder.fine_costs`), which resolves the last degrees (at 64x64 and FoV 90 one degree
  is about 0.6 pixel) and whose zero-shift entry is exactly 0 on the target (a clean target);
  ``fine_scales = S`` computes that map on ``S`` levels of an image pyramid (2x average pooling per level),
  so level ``s`` covers shifts of up to ``k * 2^s`` pixels: a fixed coarse-to-fine direct alignment the
  head only has to read.
- ``direct``: no learned image encoder at all. Fixed photometric comparisons of view and target (a global
  cost volume over every shift of ``DIRECT_COARSE x DIRECT_COARSE`` grey thumbnails, the fine cost pyramid
  of ``fine_shifts`` / ``fine_scales``, and a colour thumbnail of both images for the search) feed a small
  conv head and MLP -> F = hidden_size. Cheap to train on a CPU (no gradient through image convolutions);
  see :class:`DirectEncoder`.

Auxiliary rotation loss (any variant, training only): :class:`AuxHead` regresses ``(dpitch, dyaw) / fov``
and classifies overlap from the features before the GRU (``Policy.forward_features``); see
:func:`aux_loss`. The head is owned by the optimiser (PPO / DAgger), not by the policy, so policy
checkpoints are the same with and without it.

Recurrent-state convention (shared with ``storage.py``): ``masks[t] == 0`` means the observation at step
``t`` starts a new episode, so the hidden state entering step ``t`` is zeroed before the GRU runs.
"""

from __future__ import annotations

import math
from typing import Any, Callable, Mapping

import torch
from torch import nn
from torch.distributions import Categorical

from findview.task import NUM_ACTIONS  # up, down, left, right, stop (findview.task.Action)

#: the policy variants (``agent.variant``); ``robust`` is ``direct`` on photometrically normalised images
VARIANTS = ("early_fusion", "goal_encoder", "siamese", "correlation", "direct", "robust")
#: the variants with a fine cost pyramid (``agent.fine_shifts``)
FINE_VARIANTS = ("correlation", "direct", "robust")
PRECISIONS = ("fp32", "bf16")  # agent.precision: the encoder's compute dtype (see Policy.configure_speed)

Obs = Mapping[str, torch.Tensor]


# --------------------------------------------------------------------------------------------------
# Encoder
# --------------------------------------------------------------------------------------------------

# (out_channels, kernel, stride) of the three conv layers (docs/TASK.md, section PPO baseline)
CONV_LAYERS = ((32, 8, 4), (64, 4, 2), (32, 3, 1))


def conv_output_size(height: int, width: int) -> tuple[int, int]:
    """Spatial size ``(h, w)`` after the three conv layers (no padding) for an ``height x width`` input.

    Raises ``ValueError`` when the image is too small for the encoder (below 36 pixels on a side).
    """
    h, w = height, width
    for _, kernel, stride in CONV_LAYERS:
        h = (h - kernel) // stride + 1
        w = (w - kernel) // stride + 1
    if h < 1 or w < 1:
        raise ValueError(f"image {height}x{width} is too small for the CNN encoder (needs at least 36x36)")
    return h, w


class ConvEncoder(nn.Module):
    """Three conv layers + one FC layer (Nature-DQN style), ReLU everywhere.

    Input ``(B, C, H, W)`` float in ``[0, 1]``, output ``(B, out_size)``.
    """

    def __init__(self, in_channels: int, height: int, width: int, out_size: int = 512) -> None:
        super().__init__()
        layers: list[nn.Module] = []
        channels = in_channels
        for out_channels, kernel, stride in CONV_LAYERS:
            layers += [nn.Conv2d(channels, out_channels, kernel, stride), nn.ReLU()]
            channels = out_channels
        self.convs = nn.Sequential(*layers)
        h, w = conv_output_size(height, width)
        self.flat_size = channels * h * w
        self.fc = nn.Sequential(nn.Linear(self.flat_size, out_size), nn.ReLU())

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        """``x`` (B, C, H, W) float -> (B, out_size)."""
        return self.fc(self.convs(x).flatten(1))


# grid of the correlation variant's feature maps (cells per side) and of its pixel-difference map
CORR_GRID = 8
DIFF_GRID = 8
SOFT_SHIFT_TEMPERATURE = 10.0  # softmax sharpness over the mean-correlation bins (cosine units)
SOFT_SHIFT_SIZE = 3  # expected (dy, dx) shift and the best mean correlation


class CorrelationEncoder(nn.Module):
    """Siamese encoder + global correlation volume (the ``correlation`` variant).

    Data flow for ``B`` pairs (view, target), each (B, 3, H, W) float in [0, 1]::

        shared CNN (4 conv layers, 3 with stride 2, ReLU)   -> (B, C, H/8, W/8), pooled to (B, C, g, g)
        centred over the cells, L2-normalised over C
        corr[p, q] = <view cell p, target cell q>              -> (B, g*g, g*g)
        binned by displacement q - p: mean and max per shift  -> (B, 2, 2g-1, 2g-1) (+ log overlap count)
        conv head (3 stride-2 convs) + Linear                 -> (B, hidden)
        softmax-expected shift over the mean bins + best mean -> (B, 3)
        |view - target| (channel mean) pooled to DIFF_GRID^2 cells, and log of it  -> (B, 2 * DIFF_GRID^2)
        spatial means of both feature maps (scene context)    -> (B, 2C)
        concat -> Linear -> LayerNorm -> ReLU                 -> (B, hidden)

    ``g = CORR_GRID`` (8) cells per side (fewer for images under 64 pixels); with a 90-degree view a cell
    spans about 11 degrees, and the ``2g - 1`` shifts per axis cover every displacement at which the two
    views still share a cell.

    With ``fine_shifts = k > 0`` the fuse layer also gets the fine cost maps (:meth:`fine_costs`, ``K =
    (2k + 1)^2`` values per pyramid level, ``fine_scales`` levels) three ways: ``4 c``, ``log(c + 1e-3) / 7 + 1``
    and its shape per level ``(c - min c) / (mean c - min c + 1e-3)`` (scale-free: where the minimum lies and
    how sharp it is) -> ``3 K fine_scales`` more inputs.
    """

    def __init__(
        self, height: int, width: int, out_size: int, channels: int = 32, fine_shifts: int = 0, fine_scales: int = 1
    ) -> None:
        super().__init__()
        if height < 16 or width < 16:
            raise ValueError(f"image {height}x{width} is too small for the correlation encoder (needs at least 16x16)")
        if not 0 <= int(fine_shifts) <= min(height, width) // 4:
            raise ValueError(
                f"fine_shifts={fine_shifts} must be in [0, {min(height, width) // 4}] pixels for {height}x{width} images"
            )
        coarsest = min(height, width) >> (int(fine_scales) - 1) if fine_scales >= 1 else 0
        if fine_shifts and not (fine_scales >= 1 and coarsest > 2 * int(fine_shifts)):
            raise ValueError(
                f"fine_scales={fine_scales} must be >= 1 and leave more than 2 * fine_shifts={fine_shifts} pixels at "
                f"the coarsest level ({height}x{width} halved fine_scales - 1 times)"
            )
        self.fine_shifts = int(fine_shifts)
        self.fine_scales = int(fine_scales) if self.fine_shifts else 1
        fine_size = 3 * (2 * self.fine_shifts + 1) ** 2 * self.fine_scales if self.fine_shifts else 0
        self.cnn = nn.Sequential(
            nn.Conv2d(3, 16, 5, stride=2, padding=2), nn.ReLU(),
            nn.Conv2d(16, 32, 3, stride=2, padding=1), nn.ReLU(),
            nn.Conv2d(32, channels, 3, stride=2, padding=1), nn.ReLU(),
            nn.Conv2d(channels, channels, 3, stride=1, padding=1),
        )
        map_h, map_w = (height + 7) // 8, (width + 7) // 8
        gh, gw = min(CORR_GRID, map_h), min(CORR_GRID, map_w)
        self.grid = (gh, gw)
        sh, sw = 2 * gh - 1, 2 * gw - 1
        self.shifts = (sh, sw)
        py, px = torch.meshgrid(torch.arange(gh), torch.arange(gw), indexing="ij")
        py, px = py.flatten(), px.flatten()
        # bin of (view cell p, target cell q): displacement (qy - py, qx - px), offset to be >= 0
        index = ((py[None, :] - py[:, None] + gh - 1) * sw + (px[None, :] - px[:, None] + gw - 1)).flatten()
        counts = torch.bincount(index, minlength=sh * sw).float()
        self.register_buffer("shift_index", index, persistent=False)
        self.register_buffer("shift_counts", counts, persistent=False)
        self.register_buffer("log_counts", (counts.log() / math.log(gh * gw)).view(1, 1, sh, sw), persistent=False)
        # displacement of every bin in cells, scaled to [-1, 1] per axis (0 when the grid is one cell)
        dy, dx = torch.meshgrid(torch.arange(sh) - (gh - 1.0), torch.arange(sw) - (gw - 1.0), indexing="ij")
        coords = torch.stack([dy.flatten() / max(gh - 1, 1), dx.flatten() / max(gw - 1, 1)], dim=1)
        self.register_buffer("shift_coords", coords, persistent=False)
        self.head = nn.Sequential(
            nn.Conv2d(3, 32, 3, stride=2, padding=1), nn.ReLU(),
            nn.Conv2d(32, 32, 3, stride=2, padding=1), nn.ReLU(),
            nn.Conv2d(32, 32, 3, stride=1, padding=1), nn.ReLU(),
            nn.AdaptiveAvgPool2d(4),
        )
        # LayerNorm before the ReLUs keeps about half of the units alive (without it a large early step
        # can kill every unit and freeze the policy on one action)
        self.head_fc = nn.Sequential(nn.Linear(32 * 16, out_size), nn.LayerNorm(out_size), nn.ReLU())
        self.fuse = nn.Sequential(
            nn.Linear(out_size + SOFT_SHIFT_SIZE + 2 * DIFF_GRID * DIFF_GRID + 2 * channels + fine_size, out_size),
            nn.LayerNorm(out_size),
            nn.ReLU(),
        )

    def feature_maps(self, images: torch.Tensor) -> torch.Tensor:
        """(B, 3, H, W) float -> (B, C, g, g) feature maps (average-pooled to the grid when larger)."""
        maps = self.cnn(images)
        if tuple(maps.shape[-2:]) != self.grid:
            maps = nn.functional.adaptive_avg_pool2d(maps, self.grid)
        return maps

    def correlation(self, view_maps: torch.Tensor, target_maps: torch.Tensor) -> torch.Tensor:
        """Displacement-binned cosine correlation: (B, C, g, g) x 2 -> (B, 3, 2g-1, 2g-1).

        Channels: mean and max over the cell pairs of each shift, and the (constant) log pair count.
        """
        b = view_maps.shape[0]
        # centre each map over its cells (drops what every cell shares), then unit length per cell
        v = view_maps.flatten(2)
        t = target_maps.flatten(2)
        v = nn.functional.normalize(v - v.mean(dim=2, keepdim=True), dim=1)  # (B, C, P)
        t = nn.functional.normalize(t - t.mean(dim=2, keepdim=True), dim=1)
        corr = torch.bmm(v.transpose(1, 2), t).reshape(b, -1)  # (B, P*P): [p, q] = <v_p, t_q>
        n_bins = self.shifts[0] * self.shifts[1]
        mean = corr.new_zeros(b, n_bins).index_add_(1, self.shift_index, corr) / self.shift_counts
        peak = corr.new_full((b, n_bins), -1.0).scatter_reduce(
            1, self.shift_index.expand(b, -1), corr, reduce="amax", include_self=False
        )
        volume = torch.stack([mean, peak], dim=1).view(b, 2, *self.shifts)
        return torch.cat([volume, self.log_counts.expand(b, -1, -1, -1)], dim=1)

    def soft_shift(self, volume: torch.Tensor) -> torch.Tensor:
        """(B, 3, sh, sw) volume -> (B, 3): softmax-expected (dy, dx) displacement over the mean-correlation
        bins (in [-1, 1] of the map size) and the best mean correlation: a direction readout that works
        before the head has learnt anything."""
        mean = volume[:, 0].flatten(1)
        weights = torch.softmax(mean * SOFT_SHIFT_TEMPERATURE, dim=1)
        return torch.cat([weights @ self.shift_coords, mean.max(dim=1, keepdim=True).values], dim=1)

    def fine_costs(self, view: torch.Tensor, target: torch.Tensor) -> torch.Tensor:
        """Local photometric cost maps: (B, 3, H, W) x 2 float in [0, 1] -> (B, S * (2k+1)^2), ``k =
        fine_shifts``, ``S = fine_scales``.

        Level ``s`` (0 = full resolution) averages both grey images (channel mean, units of the [0, 1]
        intensity) over ``2^s x 2^s`` blocks; its entry ``s * (2k+1)^2 + (dy + k) * (2k + 1) + (dx + k)`` is
        the mean over the central ``(h - 2k) x (w - 2k)`` pixels of that level of ``|view[y + dy, x + dx] -
        target[y, x]|`` for integer shifts ``dy, dx`` in ``[-k, k]`` (level pixels, ``2^s`` input pixels
        each). The zero shift (the centre entry) is 0 when the view equals the target; near alignment a
        level's map is a bowl whose lowest side points to the remaining offset.
        """
        return pyramid_costs(view.mean(dim=1, keepdim=True), target.mean(dim=1, keepdim=True), self.fine_shifts,
                             self.fine_scales)

    def fine_features(self, view: torch.Tensor, target: torch.Tensor) -> torch.Tensor:
        """The three scalings of :meth:`fine_costs` fed to the fuse layer, (B, 3 S (2k+1)^2)."""
        return cost_features(self.fine_costs(view, target), self.fine_scales)

    def forward(self, view: torch.Tensor, target: torch.Tensor) -> torch.Tensor:
        """``view``, ``target`` (B, 3, H, W) float in [0, 1] -> (B, out_size)."""
        b = view.shape[0]
        maps = self.feature_maps(torch.cat([view, target], dim=0))
        view_maps, target_maps = maps[:b], maps[b:]
        volume = self.correlation(view_maps, target_maps)
        corr = self.head_fc(self.head(volume).flatten(1))
        diff = nn.functional.adaptive_avg_pool2d((view - target).abs().mean(dim=1, keepdim=True), DIFF_GRID).flatten(1)
        diff_feats = torch.cat([diff * 4.0, torch.log(diff + 1e-3) / 7.0 + 1.0], dim=1)
        context = torch.cat([view_maps.mean(dim=(2, 3)), target_maps.mean(dim=(2, 3))], dim=1)
        parts = [corr, self.soft_shift(volume), diff_feats, context]
        if self.fine_shifts:
            parts.append(self.fine_features(view, target))
        return self.fuse(torch.cat(parts, dim=1))


def pyramid_costs(grey_view: torch.Tensor, grey_target: torch.Tensor, shifts: int, levels: int) -> torch.Tensor:
    """Local photometric cost maps on an image pyramid: (B, 1, H, W) x 2 -> (B, levels * (2k+1)^2), k = shifts.

    Level ``s`` (0 = full resolution) averages both images over ``2^s x 2^s`` blocks; its entry ``s (2k+1)^2 +
    (dy + k)(2k + 1) + (dx + k)`` is the mean over the central ``(h - 2k) x (w - 2k)`` pixels of that level of
    ``|view[y + dy, x + dx] - target[y, x]|`` for integer shifts ``dy, dx`` in ``[-k, k]`` (level pixels).
    """
    k = shifts
    costs = []
    for level in range(levels):
        if level:
            grey_view = nn.functional.avg_pool2d(grey_view, 2, ceil_mode=True)
            grey_target = nn.functional.avg_pool2d(grey_target, 2, ceil_mode=True)
        h, w = grey_target.shape[-2:]
        core = grey_target[:, 0, k:h - k, k:w - k]
        costs += [
            (grey_view[:, 0, k + dy:h - k + dy, k + dx:w - k + dx] - core).abs().mean(dim=(1, 2))
            for dy in range(-k, k + 1)
            for dx in range(-k, k + 1)
        ]
    return torch.stack(costs, dim=1)


def cost_features(costs: torch.Tensor, groups: int) -> torch.Tensor:
    """(B, groups * K) costs -> (B, 3 groups K): ``4 c``, ``log(c + 1e-5) / 11.5 + 1`` (0 for an exact match,
    about 0.5 for the 1/255-level differences of a one-degree offset) and, per group of K, the scale-free
    shape ``(c - min c) / (mean c - min c + 1e-3)``."""
    b = costs.shape[0]
    per = costs.view(b, groups, -1)
    low = per.amin(dim=2, keepdim=True)
    shape = ((per - low) / (per.mean(dim=2, keepdim=True) - low + 1e-3)).flatten(1)
    return torch.cat([costs * 4.0, torch.log(costs + 1e-5) / 11.5 + 1.0, shape], dim=1)


# the direct variant: coarse thumbnail size (cells per side), its shifts per axis (-s..s cells), the colour
# context thumbnail (cells per side) and the softmax sharpness of its soft argmin
DIRECT_COARSE = 8
DIRECT_COARSE_SHIFTS = 6
DIRECT_CONTEXT = 4
DIRECT_SOFTMIN_TEMPERATURE = 5.0


def standardize(image: torch.Tensor) -> torch.Tensor:
    """Photometric normalisation of the ``robust`` variant: (B, 3, H, W) float -> (B, 3, H, W), each image
    and channel shifted to mean 0 and scaled to standard deviation ``STANDARDIZE_SCALE`` (a flat channel,
    std below ``STANDARDIZE_FLOOR``, keeps its deviations unscaled beyond that floor).

    An affine change of the intensities (brightness, contrast, much of fog) leaves the result unchanged, so the
    cost volumes computed on it compare structure, not exposure. Identical inputs still give identical
    outputs: a clean target still matches its view exactly."""
    mean = image.mean(dim=(2, 3), keepdim=True)
    centred = image - mean
    std = centred.square().mean(dim=(2, 3), keepdim=True).sqrt()
    return centred * (STANDARDIZE_SCALE / std.clamp_min(STANDARDIZE_FLOOR))


def highpass(grey: torch.Tensor) -> torch.Tensor:
    """(B, 1, H, W) -> (B, 1, H, W): the image minus its local mean over a box of about a quarter of the
    image side (odd, edges replicated): removes slowly varying haze (fog) and keeps local structure."""
    k = (min(grey.shape[-2:]) // 4) | 1
    padded = nn.functional.pad(grey, (k // 2,) * 4, mode="replicate")
    # the k x k box sums from running sums along each axis (6x faster on a CPU than avg_pool2d's k^2 window)
    running = nn.functional.pad(padded.cumsum(-1), (1, 0))
    rows = running[..., k:] - running[..., :-k]
    running = nn.functional.pad(rows.cumsum(-2), (0, 0, 1, 0))
    return grey - (running[..., k:, :] - running[..., :-k, :]) / (k * k)


# the robust variant: standard deviation of a standardised image (about that of a typical photo in [0, 1],
# so the cost scalings of the direct variant keep their range) and the smallest std that is scaled up
STANDARDIZE_SCALE = 0.2
STANDARDIZE_FLOOR = 0.02


class DirectEncoder(nn.Module):
    """Fixed photometric comparisons of view and target + a small learned head (the ``direct`` variant).

    Data flow for ``B`` pairs (view, target), each (B, 3, H, W) float in [0, 1]::

        grey = channel mean; thumbnails: grey averaged to c x c cells (c = DIRECT_COARSE = 8)
        global cost volume: mean |thumb_view[y + dy, x + dx] - thumb_target[y, x]| over the overlapping
            cells, every shift |dy|, |dx| <= s (s = DIRECT_COARSE_SHIFTS = 6 cells, about 8 px each)
            -> (B, 3, 2s+1, 2s+1): 4 cost, scale-free shape, overlap fraction (constant)
            -> conv head (2 convs) + Linear + LayerNorm + ReLU              -> (B, hidden)
        soft argmin of the shape (expected (dy, dx) / s) and the lowest cost -> (B, 3)
        fine cost pyramid (``fine_shifts`` k > 0, ``fine_scales`` levels; see :func:`pyramid_costs`),
            three scalings (:func:`cost_features`)                          -> (B, 3 * levels * (2k+1)^2)
        colour thumbnails of view and target (DIRECT_CONTEXT^2 cells, RGB, scaled to [-1, 1]) -> (B, 96)
        exact-match cue: ``d = mean |grey view - grey target|`` at full resolution, ``exp(-1000 d)`` and ``4 d``
            (1 and 0 only when the view is the target: a clean target is rendered bit for bit) -> (B, 2)
        concat -> (Linear -> LayerNorm -> ReLU) x 2                         -> (B, hidden)

    ``normalized=True`` (the ``robust`` variant) first passes view and target through :func:`standardize`
    (per image and channel: mean 0, fixed standard deviation), so brightness, contrast, snow and frost change
    the global costs little; the fine pyramid compares :func:`highpass` images (standardised), which fog's
    slowly varying haze leaves nearly alone; the colour thumbnails are the standardised colours (scaled by 0.5
    instead of mapped to [-1, 1]). A clean target still gives exactly zero cost at the true shift.

    Nothing before the head is learned, so training touches only about 0.3M parameters and no image
    convolution: a CPU trains it an order of magnitude faster than the ``correlation`` variant. The global
    volume tells the direction to any target that shares content with the view (shifts up to about
    ``6 * 11 = 66`` degrees at FoV 90); the fine pyramid resolves the last pixels (the zero-shift cost is
    exactly 0 on a clean target: the stop cue). A corrupted target is never matched exactly, so an agent
    meant for corrupted targets must be trained with them (``corruption.*``) to learn a softer stop rule.
    """

    def __init__(
        self, height: int, width: int, out_size: int, fine_shifts: int = 2, fine_scales: int = 4,
        normalized: bool = False,
    ) -> None:
        super().__init__()
        self.normalized = bool(normalized)
        if height < 16 or width < 16:
            raise ValueError(f"image {height}x{width} is too small for the direct encoder (needs at least 16x16)")
        coarsest = min(height, width) >> (int(fine_scales) - 1) if fine_scales >= 1 else 0
        if fine_shifts < 0 or (fine_shifts and not (fine_scales >= 1 and coarsest > 2 * int(fine_shifts))):
            raise ValueError(
                f"fine_shifts={fine_shifts} / fine_scales={fine_scales}: need fine_shifts >= 0 and fine_scales >= 1 "
                f"leaving more than 2 * fine_shifts pixels at the coarsest level of {height}x{width} images"
            )
        self.fine_shifts = int(fine_shifts)
        self.fine_scales = int(fine_scales) if self.fine_shifts else 1
        c, s = DIRECT_COARSE, DIRECT_COARSE_SHIFTS
        n = 2 * s + 1
        self.volume_size = n
        # overlap count of every shift on the c x c thumbnail and the displacement of every bin in [-1, 1]
        dy, dx = torch.meshgrid(torch.arange(n) - s, torch.arange(n) - s, indexing="ij")
        overlap = ((c - dy.abs()) * (c - dx.abs())).float().flatten()
        self.register_buffer("overlap_count", overlap, persistent=False)
        self.register_buffer("overlap_frac", (overlap / (c * c)).view(1, 1, n, n), persistent=False)
        self.register_buffer("shift_coords", torch.stack([dy.flatten(), dx.flatten()], dim=1).float() / s,
                             persistent=False)
        self.head = nn.Sequential(
            nn.Conv2d(3, 16, 3, padding=1), nn.ReLU(),
            nn.Conv2d(16, 32, 3, stride=2, padding=1), nn.ReLU(),
        )
        head_out = 32 * ((n + 1) // 2) ** 2
        self.head_fc = nn.Sequential(nn.Linear(head_out, out_size), nn.LayerNorm(out_size), nn.ReLU())
        fine_size = 3 * self.fine_scales * (2 * self.fine_shifts + 1) ** 2 if self.fine_shifts else 0
        context_size = 2 * 3 * DIRECT_CONTEXT * DIRECT_CONTEXT
        self.fuse = nn.Sequential(
            nn.Linear(out_size + 3 + fine_size + context_size + 2, out_size), nn.LayerNorm(out_size), nn.ReLU(),
            nn.Linear(out_size, out_size), nn.LayerNorm(out_size), nn.ReLU(),
        )

    def global_costs(self, thumb_view: torch.Tensor, thumb_target: torch.Tensor) -> torch.Tensor:
        """(B, 1, c, c) x 2 -> (B, (2s+1)^2): mean ``|view[y + dy, x + dx] - target[y, x]|`` over the cells
        where both exist, for every shift ``dy, dx`` in ``[-s, s]`` (entry ``(dy + s)(2s + 1) + (dx + s)``)."""
        s = DIRECT_COARSE_SHIFTS
        c = thumb_view.shape[-1]
        padded = nn.functional.pad(thumb_view, (s, s, s, s))
        valid = nn.functional.pad(torch.ones_like(thumb_view[:1]), (s, s, s, s))
        windows = nn.functional.unfold(padded, (c, c))  # (B, c*c, n*n): window (i, j) = shift (i - s, j - s)
        mask = nn.functional.unfold(valid, (c, c))  # (1, c*c, n*n)
        diff = (windows - thumb_target.flatten(1)[:, :, None]).abs() * mask
        return diff.sum(dim=1) / self.overlap_count

    def forward(self, view: torch.Tensor, target: torch.Tensor) -> torch.Tensor:
        """``view``, ``target`` (B, 3, H, W) float in [0, 1] -> (B, out_size)."""
        b, n = view.shape[0], self.volume_size
        if self.normalized:
            view, target = standardize(view), standardize(target)
        grey_v = view.mean(dim=1, keepdim=True)
        grey_t = target.mean(dim=1, keepdim=True)
        # the fine pyramid of the robust variant compares local structure: high-passed, standardised grey
        fine_v, fine_t = (standardize(highpass(grey_v)), standardize(highpass(grey_t))) if self.normalized else (grey_v, grey_t)
        thumb_v = nn.functional.adaptive_avg_pool2d(grey_v, DIRECT_COARSE)
        thumb_t = nn.functional.adaptive_avg_pool2d(grey_t, DIRECT_COARSE)
        costs = self.global_costs(thumb_v, thumb_t)  # (B, n*n)
        low = costs.amin(dim=1, keepdim=True)
        shape = (costs - low) / (costs.mean(dim=1, keepdim=True) - low + 1e-3)
        volume = torch.stack([costs * 4.0, shape], dim=1).view(b, 2, n, n)
        volume = torch.cat([volume, self.overlap_frac.expand(b, -1, -1, -1)], dim=1)
        coarse = self.head_fc(self.head(volume).flatten(1))
        weights = torch.softmax(-shape * DIRECT_SOFTMIN_TEMPERATURE, dim=1)
        parts = [coarse, weights @ self.shift_coords, low * 4.0]
        if self.fine_shifts:
            fine = pyramid_costs(fine_v, fine_t, self.fine_shifts, self.fine_scales)
            parts.append(cost_features(fine, self.fine_scales))
        context = torch.cat([
            nn.functional.adaptive_avg_pool2d(view, DIRECT_CONTEXT).flatten(1),
            nn.functional.adaptive_avg_pool2d(target, DIRECT_CONTEXT).flatten(1),
        ], dim=1)
        parts.append(context * (0.5 if self.normalized else 2.0) - (0.0 if self.normalized else 1.0))
        residual = (grey_v - grey_t).abs().mean(dim=(1, 2, 3))[:, None]
        parts += [torch.exp(-1000.0 * residual), residual * 4.0]
        return self.fuse(torch.cat(parts, dim=1))


class AuxHead(nn.Module):
    """Auxiliary relative-rotation head on the pre-GRU features: (B, F) -> (B, 3).

    Outputs: predicted ``dpitch / fov``, ``dyaw / fov`` and the overlap logit (targets from
    ``findview.task.oracle.rotation_labels``). Training only; see :func:`aux_loss`.
    """

    def __init__(self, feature_size: int, hidden: int = 64) -> None:
        super().__init__()
        self.net = nn.Sequential(nn.Linear(feature_size, hidden), nn.ReLU(), nn.Linear(hidden, 3))

    def forward(self, features: torch.Tensor) -> torch.Tensor:
        return self.net(features)


def aux_loss(prediction: torch.Tensor, targets: torch.Tensor) -> dict[str, torch.Tensor]:
    """Auxiliary rotation loss of (B, 3) predictions against (B, 3) ``rotation_labels`` targets.

    ``loss = rotation_loss + overlap_loss`` with ``rotation_loss`` the smooth-L1 error of ``(dpitch, dyaw) /
    fov`` averaged over the rows whose views overlap (0 when none do) and ``overlap_loss`` the binary cross
    entropy of the overlap logit. Also returns ``overlap_accuracy`` (no gradient).
    """
    overlap = targets[:, 2]
    per_row = nn.functional.smooth_l1_loss(prediction[:, :2], targets[:, :2], reduction="none", beta=0.1).sum(1)
    rotation = (per_row * overlap).sum() / overlap.sum().clamp(min=1.0)
    overlap_loss = nn.functional.binary_cross_entropy_with_logits(prediction[:, 2], overlap)
    with torch.no_grad():
        accuracy = ((prediction[:, 2] > 0).float() == overlap).float().mean()
    return {
        "loss": rotation + overlap_loss,
        "rotation_loss": rotation,
        "overlap_loss": overlap_loss,
        "overlap_accuracy": accuracy,
    }


def _to_float(image: torch.Tensor) -> torch.Tensor:
    """uint8 (B, 3, H, W) in [0, 255] -> float32 in [0, 1] (float inputs are taken as already scaled)."""
    if image.dtype == torch.uint8:
        return image.float().div_(255.0)
    return image.float()


# --------------------------------------------------------------------------------------------------
# Checkpoint signature
# --------------------------------------------------------------------------------------------------

SIGNATURE_FIELDS = ("variant", "hidden_size", "height", "width")
# signature fields added later, with the value a checkpoint that lacks them was trained with
OPTIONAL_SIGNATURE_FIELDS = {"fine_shifts": 0, "fine_scales": 1}


def check_signature(saved: Mapping[str, Any], current: Mapping[str, Any]) -> None:
    """Raise ``ValueError`` naming the first field where a checkpoint's model signature differs.

    ``saved`` is the dict stored in the checkpoint, ``current`` the one of the policy being loaded into
    (both from :meth:`Policy.model_signature`).
    """
    for key in SIGNATURE_FIELDS:
        if key not in saved:
            raise ValueError(f"checkpoint model signature has no field {key!r} (saved signature: {dict(saved)})")
        if saved[key] != current.get(key):
            raise ValueError(
                f"checkpoint does not fit this model: {key} is {saved[key]!r} in the checkpoint "
                f"but {current.get(key)!r} in the current config"
            )
    for key, default in OPTIONAL_SIGNATURE_FIELDS.items():
        if saved.get(key, default) != current.get(key, default):
            raise ValueError(
                f"checkpoint does not fit this model: {key} is {saved.get(key, default)!r} in the checkpoint "
                f"but {current.get(key, default)!r} in the current config"
            )


# --------------------------------------------------------------------------------------------------
# Policy
# --------------------------------------------------------------------------------------------------


class Policy(nn.Module):
    """Encoder(s) + single-layer GRU + actor/critic heads.

    Args:
        height, width: size of the view and target images (both the same).
        variant: one of :data:`VARIANTS`.
        hidden_size: size of the encoder features and of the GRU state (512 in the paper).
        fine_shifts: ``correlation`` / ``direct`` only: half-width ``k`` in pixels of the fine cost map (shifts ``-k..k``
            per axis, see :meth:`CorrelationEncoder.fine_costs`); 0 = off. Part of the checkpoint signature.
        fine_scales: pyramid levels of the fine cost map (1 = full resolution only); with fine_shifts > 0.

    ``feature_size`` is the width ``F`` of the features entering the GRU (see :meth:`encode`).

    Speed options (:meth:`configure_speed`; ``agent.precision``, ``agent.channels_last``,
    ``agent.compile``) change how the encoder runs, never the parameters: checkpoints are the same with
    and without them.
    """

    def __init__(
        self,
        height: int,
        width: int,
        variant: str = "early_fusion",
        hidden_size: int = 512,
        fine_shifts: int = 0,
        fine_scales: int = 1,
    ) -> None:
        super().__init__()
        if variant not in VARIANTS:
            raise ValueError(f"unknown policy variant {variant!r}; choose one of {VARIANTS}")
        if fine_shifts and variant not in FINE_VARIANTS:
            raise ValueError(f"fine_shifts={fine_shifts} needs variant 'correlation', 'direct' or 'robust', got {variant!r}")
        self.fine_shifts = int(fine_shifts)
        self.fine_scales = int(fine_scales) if self.fine_shifts else 1
        self.variant = variant
        self.hidden_size = hidden_size
        self.height = height
        self.width = width

        if variant == "early_fusion":
            self.encoder = ConvEncoder(6, height, width, hidden_size)
            feature_size = hidden_size
        elif variant == "goal_encoder":
            self.encoder = ConvEncoder(6, height, width, hidden_size)
            self.goal_encoder = ConvEncoder(3, height, width, hidden_size)
            feature_size = 2 * hidden_size
        elif variant == "siamese":
            self.encoder = ConvEncoder(3, height, width, hidden_size)
            self.fuse = nn.Sequential(nn.Linear(2 * hidden_size, hidden_size), nn.ReLU())
            feature_size = hidden_size
        elif variant in ("direct", "robust"):
            self.encoder = DirectEncoder(
                height, width, hidden_size, self.fine_shifts, self.fine_scales, normalized=variant == "robust"
            )
            feature_size = hidden_size
        else:  # correlation
            self.encoder = CorrelationEncoder(
                height, width, hidden_size, fine_shifts=self.fine_shifts, fine_scales=self.fine_scales
            )
            feature_size = hidden_size
        self.feature_size = feature_size

        self.gru = nn.GRU(feature_size, hidden_size, num_layers=1)
        self.actor = nn.Linear(hidden_size, NUM_ACTIONS)
        self.critic = nn.Linear(hidden_size, 1)
        self._init_weights()
        # speed options (configure_speed); the compiled encoder is a plain attribute, not a submodule, so
        # state_dict keys never get torch.compile's "_orig_mod." prefix
        self.precision = "fp32"
        self.channels_last = False
        self._compiled_encode: Callable[[Obs], torch.Tensor] | None = None

    def configure_speed(
        self, precision: str = "fp32", channels_last: bool = False, compile: bool = False,
        compile_backend: str = "inductor",
    ) -> "Policy":
        """Choose how the encoder runs (the GRU and the heads always run in float32).

        Args:
            precision: ``fp32`` | ``bf16``: ``bf16`` runs the encoder under ``torch.autocast`` (bfloat16)
                on the device of the observations (CPU or CUDA); features, logits and values are float32.
            channels_last: store the conv weights and feed the encoder its input in
                ``torch.channels_last`` memory format (NHWC; faster convolutions on recent GPUs / CPUs).
            compile: run the encoder through ``torch.compile`` (``compile_backend``); the first calls of
                each batch shape compile (seconds to a minute).

        Returns ``self``. Call it after construction; ``.to(device)`` afterwards keeps the memory format.
        """
        if precision not in PRECISIONS:
            raise ValueError(f"agent.precision must be one of {' | '.join(PRECISIONS)}, got {precision!r}")
        self.precision = precision
        self.channels_last = bool(channels_last)
        self.to(memory_format=torch.channels_last if self.channels_last else torch.contiguous_format)
        self._compiled_encode = torch.compile(self.encode, backend=compile_backend) if compile else None
        return self

    def features(self, obs: Obs) -> torch.Tensor:
        """:meth:`encode` under the speed options: (B, F) float32 features entering the GRU."""
        encode = self._compiled_encode if self._compiled_encode is not None else self.encode
        if self.precision == "bf16":
            with torch.autocast(device_type=obs["view"].device.type, dtype=torch.bfloat16):
                return encode(obs).float()
        return encode(obs)

    def _init_weights(self) -> None:
        """Orthogonal init: gain sqrt(2) for convs / hidden FCs, 0.01 for the actor, 1 for the critic."""
        for module in self.modules():
            if isinstance(module, (nn.Conv2d, nn.Linear)):
                nn.init.orthogonal_(module.weight, gain=math.sqrt(2))
                nn.init.zeros_(module.bias)
        for name, param in self.gru.named_parameters():
            if name.startswith("weight"):
                nn.init.orthogonal_(param)
            else:
                nn.init.zeros_(param)
        nn.init.orthogonal_(self.actor.weight, gain=0.01)
        nn.init.orthogonal_(self.critic.weight, gain=1.0)

    # ---------------------------------------------------------------------------------------------

    def model_signature(self) -> dict[str, Any]:
        """What a checkpoint must match to be loaded into this policy (see :func:`check_signature`)."""
        sig: dict[str, Any] = {
            "variant": self.variant, "hidden_size": self.hidden_size, "height": self.height, "width": self.width
        }
        if self.fine_shifts:  # only when set, so older readers still load fine_shifts=0 checkpoints
            sig["fine_shifts"] = self.fine_shifts
            sig["fine_scales"] = self.fine_scales
        return sig

    def initial_hidden(self, num_envs: int, device: torch.device | str | None = None) -> torch.Tensor:
        """Zero recurrent state, (num_envs, hidden_size)."""
        return torch.zeros(num_envs, self.hidden_size, device=device)

    # ---------------------------------------------------------------------------------------------

    def encode(self, obs: Obs) -> torch.Tensor:
        """Observation features before the GRU.

        ``obs["view"]``, ``obs["target"]``: (B, 3, H, W) uint8 -> (B, F) with F = :attr:`feature_size`
        (hidden_size; 2 * hidden_size for ``goal_encoder``).
        """
        view = _to_float(obs["view"])
        target = _to_float(obs["target"])
        if self.channels_last:
            view = view.contiguous(memory_format=torch.channels_last)
            target = target.contiguous(memory_format=torch.channels_last)
        if view.shape[-2:] != (self.height, self.width):
            raise ValueError(
                f"policy was built for {self.height}x{self.width} images, got {tuple(view.shape[-2:])}"
            )
        if self.variant == "early_fusion":
            fused = torch.cat([view, target], dim=1)
            if self.channels_last:
                fused = fused.contiguous(memory_format=torch.channels_last)
            return self.encoder(fused)
        if self.variant == "goal_encoder":
            fused = self.encoder(torch.cat([view, target], dim=1))
            return torch.cat([fused, self.goal_encoder(target)], dim=1)
        if self.variant in FINE_VARIANTS:
            return self.encoder(view, target)
        # siamese: one encoder, two passes batched together
        both = self.encoder(torch.cat([view, target], dim=0))
        view_feat, target_feat = both.chunk(2, dim=0)
        return self.fuse(torch.cat([view_feat, target_feat], dim=1))

    def run_gru(
        self, features: torch.Tensor, hidden: torch.Tensor, masks: torch.Tensor
    ) -> tuple[torch.Tensor, torch.Tensor]:
        """Run the GRU over ``T`` steps of ``N`` environments, zeroing the state where ``masks == 0``.

        Args:
            features: (T*N, F), time-major (row ``t*N + i`` is env ``i`` at step ``t``).
            hidden: (N, hidden) state entering step 0.
            masks: (T*N,) 0 where the observation starts a new episode, else 1.

        Returns:
            outputs (T*N, hidden) and the state after the last step (N, hidden).

        The sequence is cut at every step where at least one environment restarts; each chunk runs through
        ``nn.GRU`` in one call (fast), with the state multiplied by the masks at the chunk's first step.
        """
        num_envs = hidden.shape[0]
        steps = features.shape[0] // num_envs
        if steps * num_envs != features.shape[0]:
            raise ValueError(f"{features.shape[0]} feature rows are not a multiple of {num_envs} environments")
        x = features.view(steps, num_envs, -1)
        masks = masks.to(x.dtype).view(steps, num_envs)
        if steps == 1:  # acting: one GRU call, no search for restarts (no host-device sync)
            out, h = self.gru(x, (hidden * masks[0].view(num_envs, 1)).unsqueeze(0))
            return out.view(num_envs, -1), h.squeeze(0)

        # step indices where some env restarts (step 0 is always a chunk start)
        restarts = (masks[1:] == 0).any(dim=1).nonzero().flatten().add(1).tolist()
        bounds = [0, *restarts, steps]

        h = hidden.unsqueeze(0)  # (1, N, hidden): nn.GRU layout
        outputs = []
        for start, end in zip(bounds[:-1], bounds[1:]):
            h = h * masks[start].view(1, num_envs, 1)
            out, h = self.gru(x[start:end], h)
            outputs.append(out)
        return torch.cat(outputs, dim=0).view(steps * num_envs, -1), h.squeeze(0)

    def forward(
        self, obs: Obs, hidden: torch.Tensor, masks: torch.Tensor
    ) -> tuple[Categorical, torch.Tensor, torch.Tensor]:
        """Action distribution (batch T*N), values (T*N,) and the last state (N, hidden)."""
        dist, values, new_hidden, _ = self.forward_features(obs, hidden, masks)
        return dist, values, new_hidden

    def forward_features(
        self, obs: Obs, hidden: torch.Tensor, masks: torch.Tensor
    ) -> tuple[Categorical, torch.Tensor, torch.Tensor, torch.Tensor]:
        """:meth:`forward` plus the pre-GRU features (T*N, F) (input of an :class:`AuxHead`).

        Same inputs as :meth:`run_gru` (time-major ``T*N`` rows, ``hidden`` (N, hidden), masks (T*N,)).
        """
        features = self.features(obs)
        out, new_hidden = self.run_gru(features, hidden, masks)
        dist = Categorical(logits=self.actor(out))
        values = self.critic(out).squeeze(-1)
        return dist, values, new_hidden, features

    # ---------------------------------------------------------------------------------------------
    # The API used by the trainer / evaluator
    # ---------------------------------------------------------------------------------------------

    def act(
        self, obs: Obs, hidden: torch.Tensor, masks: torch.Tensor, deterministic: bool = False
    ) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor, torch.Tensor]:
        """One step for ``N`` environments.

        Args:
            obs: {"view", "target"} (N, 3, H, W) uint8.
            hidden: (N, hidden) state from the previous step.
            masks: (N,) 0 where ``obs`` starts a new episode (e.g. ``(~env.new_episode).float()``).
            deterministic: take the most likely action instead of sampling.

        Returns:
            actions (N,) long, log_probs (N,), values (N,), new_hidden (N, hidden).
        """
        dist, values, new_hidden = self(obs, hidden, masks)
        actions = dist.logits.argmax(dim=-1) if deterministic else dist.sample()
        return actions, dist.log_prob(actions), values, new_hidden

    def get_value(self, obs: Obs, hidden: torch.Tensor, masks: torch.Tensor) -> torch.Tensor:
        """Critic value (N,) of one step (same inputs as :meth:`act`)."""
        out, _ = self.run_gru(self.features(obs), hidden, masks)
        return self.critic(out).squeeze(-1)

    def evaluate_actions(
        self, obs: Obs, hidden0: torch.Tensor, masks: torch.Tensor, actions: torch.Tensor
    ) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
        """Re-run a rollout of ``T`` steps of ``N`` environments (time-major, flattened).

        Args:
            obs: {"view", "target"} (T*N, 3, H, W) uint8.
            hidden0: (N, hidden) state entering the first step.
            masks: (T*N,) 0 where the observation starts a new episode.
            actions: (T*N,) the actions taken.

        Returns:
            log_probs (T*N,), values (T*N,), entropy (T*N,).
        """
        dist, values, _ = self(obs, hidden0, masks)
        return dist.log_prob(actions.reshape(-1)), values, dist.entropy()


def build_policy(agent_cfg: Mapping[str, Any], height: int, width: int) -> Policy:
    """Policy from the ``agent`` config (``variant``, ``hidden_size``; speed options ``precision``,
    ``channels_last``, ``compile``, see :meth:`Policy.configure_speed`) and the view size of ``sim``."""
    policy = Policy(
        height=int(height),
        width=int(width),
        variant=str(agent_cfg.get("variant", "early_fusion")),
        hidden_size=int(agent_cfg.get("hidden_size", 512)),
        fine_shifts=int(agent_cfg.get("fine_shifts", 0) or 0),
        fine_scales=int(agent_cfg.get("fine_scales", 1) or 1),
    )
    return policy.configure_speed(
        precision=str(agent_cfg.get("precision", None) or "fp32"),
        channels_last=bool(agent_cfg.get("channels_last", False)),
        compile=bool(agent_cfg.get("compile", False)),
    )
