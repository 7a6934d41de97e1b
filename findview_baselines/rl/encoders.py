"""The image encoders of the learned policy (``policy.py``): each maps a (view, target) pair to the
features that enter the GRU.

- :class:`ConvEncoder`: three conv layers + one FC layer (Nature-DQN style); the ``early_fusion``,
  ``goal_encoder`` and ``siamese`` variants.
- :class:`CorrelationEncoder`: a siamese CNN + a global correlation volume (the ``correlation`` variant).
- :class:`DirectEncoder`: fixed photometric comparisons + a small learned head (``direct``, ``robust`` and
  ``phase``); :class:`PhaseCorrelation`: the ``phase`` variant's band-limited phase correlation.
- The fixed photometric helpers they share: :func:`pyramid_costs` (local cost maps on an image pyramid),
  :func:`cost_features` (their three scalings), :func:`standardize` and :func:`highpass` (the ``robust``
  variant's normalisations), and the size constants of each encoder.
"""

from __future__ import annotations

import math

import torch
from torch import nn
from torch.nn import functional as F

from findview_baselines.rl.distinct import regroup

__all__ = [
    "CONV_LAYERS",
    "conv_output_size",
    "ConvEncoder",
    "CORR_GRID",
    "DIFF_GRID",
    "SOFT_SHIFT_TEMPERATURE",
    "SOFT_SHIFT_SIZE",
    "CorrelationEncoder",
    "pyramid_costs",
    "cost_features",
    "DIRECT_COARSE",
    "DIRECT_COARSE_SHIFTS",
    "DIRECT_CONTEXT",
    "DIRECT_SOFTMIN_TEMPERATURE",
    "standardize",
    "highpass",
    "phase_setup",
    "STANDARDIZE_SCALE",
    "STANDARDIZE_FLOOR",
    "PHASE_SIDE",
    "PHASE_BANDWIDTHS",
    "PHASE_SCALARS",
    "PhaseCorrelation",
    "DirectEncoder",
]

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

    def forward_pair(
        self, view: torch.Tensor, target: torch.Tensor, inverse: torch.Tensor | None = None
    ) -> torch.Tensor:
        """:meth:`forward` of the channel stack ``[view, target]`` without building it.

        The first convolution is linear in its input channels, so its output is the view's channels
        convolved with their weights plus the target's channels with theirs; the target's part is computed
        once per distinct target and gathered back (the same numbers up to float rounding).

        Args:
            view: (B, Cv, H, W) float.
            target: (U, Ct, H, W) float with ``Cv + Ct`` the encoder's input channels; U = B when
                ``inverse`` is None.
            inverse: (B,) long, row ``i`` uses ``target[inverse[i]]`` (see ``rl/distinct.py``).

        Returns:
            (B, out_size).
        """
        first = self.convs[0]
        assert isinstance(first, nn.Conv2d)
        split = view.shape[1]
        out = F.conv2d(view, first.weight[:, :split], first.bias, first.stride)
        target_part = F.conv2d(target, first.weight[:, split:], None, first.stride)
        out = out + regroup(target_part, inverse)
        return self.fc(self.convs[1:](out).flatten(1))


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

# the phase variant: views are first averaged over p x p blocks, p = min(H, W) // PHASE_SIDE (64x64 -> 32x32: a
# quarter of the cost, nearly the same accuracy); Gaussian weights (sigma, cycles per pixel of those images) on the
# normalised cross-power spectrum, one correlation surface each: 0.3 keeps most of the band (sharp peaks, survives
# noise, fog, contrast, JPEG), 0.1 only the low frequencies (some of what the blurs leave; fog and frost mislead
# it). The widest band comes first: the 3 x 3 centre scalars are read from surface 0.
PHASE_SIDE = 32
PHASE_BANDWIDTHS = (0.3, 0.1)
#: scalars of the phase variant: per bandwidth the peak and zero-shift heights and the peak's (dy, dx); the
#: 3 x 3 neighbourhood of zero shift on the sharpest surface
PHASE_SCALARS = 4 * len(PHASE_BANDWIDTHS) + 9


def phase_setup(height: int, width: int, bandwidths: tuple[float, ...]) -> tuple[int, int, int, torch.Tensor, torch.Tensor]:
    """What a phase correlation of ``height x width`` images needs (shared by :class:`PhaseCorrelation` and the
    pitch warps, ``rl/pitch_warps.py``).

    Returns ``(pool, h, w, window, weights)``: the block size ``p = min(H, W) // PHASE_SIDE`` (at least 1), the
    averaged size ``h x w = (H // p) x (W // p)`` pixels, the 2-D Hann ``window`` (h, w), and per bandwidth ``sigma``
    (cycles per pixel) the Gaussian weight ``exp(-|f|^2 / (2 sigma^2))`` on the rfft of the 2h x 2w zero-padded
    images, ``weights`` (len(bandwidths), 2h, w + 1).
    """
    pool = max(1, min(int(height), int(width)) // PHASE_SIDE)
    h, w = int(height) // pool, int(width) // pool
    window = torch.hann_window(h, periodic=False)[:, None] * torch.hann_window(w, periodic=False)[None, :]
    fy = torch.fft.fftfreq(2 * h)[:, None]
    fx = torch.fft.rfftfreq(2 * w)[None, :]
    weights = torch.stack([torch.exp(-(fy ** 2 + fx ** 2) / (2 * sigma ** 2)) for sigma in bandwidths])
    return pool, h, w, window, weights


class PhaseCorrelation(nn.Module):
    """Band-limited phase correlation of view and target: shift-resolved, blind to intensity changes.

    For grey images ``v``, ``t`` (B, 1, H, W), each averaged over ``p x p`` blocks (``p = min(H, W) //
    PHASE_SIDE``, at least 1) to ``h x w`` pixels: both are mean-removed, Hann-windowed and zero-padded to
    2h x 2w (so shifts do not wrap); the cross-power spectrum ``V conj(T)`` is normalised to unit magnitude
    (only the phase is kept, so a change of the intensities by a positive gain and an offset leaves it
    alone), weighted by ``exp(-|f|^2 / (2 sigma^2))`` for each ``sigma`` of :data:`PHASE_BANDWIDTHS` and
    transformed back. Entry ``(dy, dx)`` of a surface is high where ``v[y + dy, x + dx] ~ t[y, x]``: content of
    the target found ``dy`` rows down and ``dx`` columns right in the view (pixels of the ``h x w`` images).
    Each surface is standardised over its shifts (z-scores, divided by 10). On the wide band (0.3) identical images read
    exactly 5.67 at zero shift whatever the image (the normalised spectrum is all ones: the clean stop); views
    10-20 degrees apart (64x64, FoV 90) 1.8-3.5 at their peak, unrelated views about 0.6-1.2. The low band is
    flatter (2.27 for identical images).

    Returns ``(surfaces, scalars)``:
    ``surfaces`` (B, len(bandwidths), 2s+1, 2s+1): the maximum over the shifts around each cell shift of the
    coarse cost volume (s = ``shifts`` cells of ``H / cells`` x ``W / cells`` pixels), so it lines up with
    :meth:`DirectEncoder.global_costs`;
    ``scalars`` (B, :data:`PHASE_SCALARS`), by quantity then surface: ``[peak_k..., zero_k..., dy_k / h...,
    dx_k / w...]`` (peak height, height at zero shift, the peak's shift as a fraction of the averaged image), then
    surface 0 around zero shift, 3 x 3, dy-major (entry 4 is zero shift, 7 is (+1, 0)): evidence for the stop.
    Nothing here is learned; it is computed under ``torch.no_grad``.
    """

    def __init__(self, height: int, width: int, cells: int, shifts: int) -> None:
        super().__init__()
        self.pool, self.height, self.width, window, weights = phase_setup(height, width, PHASE_BANDWIDTHS)
        self.cells, self.shifts = int(cells), int(shifts)
        self.register_buffer("window", window, persistent=False)
        self.register_buffer("weights", weights, persistent=False)  # (K, 2h, w + 1)
        # the shifts of the coarse volume's bins: +-(s + 1/2) cells around zero, max-pooled to 2s + 1 bins a side
        self.bins = 2 * self.shifts + 1
        self.reach_y = min(self.height - 1, int(round((self.shifts + 0.5) * self.height / self.cells)))
        self.reach_x = min(self.width - 1, int(round((self.shifts + 0.5) * self.width / self.cells)))

    @torch.no_grad()
    def forward(self, grey_view: torch.Tensor, grey_target: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        h, w = self.height, self.width
        b = grey_view.shape[0]

        def spectrum(grey: torch.Tensor) -> torch.Tensor:
            g = grey.float()
            g = nn.functional.avg_pool2d(g, self.pool)[:, 0, :h, :w] if self.pool > 1 else g[:, 0]
            g = (g - g.mean(dim=(1, 2), keepdim=True)) * self.window
            return torch.fft.rfft2(g, s=(2 * h, 2 * w))

        cross = spectrum(grey_view) * spectrum(grey_target).conj()
        cross = cross / cross.abs().clamp_min(1e-9)
        corr = torch.fft.irfft2(cross[:, None] * self.weights, s=(2 * h, 2 * w))  # (B, K, 2h, 2w), shift 0 at [0, 0]
        corr = torch.fft.fftshift(corr, dim=(-2, -1))  # shift 0 at [h, w]
        flat = corr.flatten(2)
        z = (corr - flat.mean(dim=2)[..., None, None]) / flat.std(dim=2).clamp_min(1e-9)[..., None, None] / 10.0
        ry, rx = self.reach_y, self.reach_x
        surfaces = nn.functional.adaptive_max_pool2d(z[..., h - ry:h + ry + 1, w - rx:w + rx + 1], self.bins)
        peak, where = z.flatten(2).max(dim=2)
        peak_y = (where // (2 * w) - h).float() / h
        peak_x = (where % (2 * w) - w).float() / w
        zero = z[..., h, w]
        centre = z[:, 0, h - 1:h + 2, w - 1:w + 2].reshape(b, 9)
        scalars = torch.cat([peak, zero, peak_y, peak_x, centre], dim=1)
        return surfaces, scalars


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

    ``phase=True`` (the ``phase`` variant, normalised too) adds :class:`PhaseCorrelation`: two band-limited
    phase-correlation surfaces of the grey images (averaged over ``min(H, W) // 32`` blocks: 64x64 -> 32x32),
    max-pooled onto the coarse volume's 13 x 13 shift bins as two more channels of its conv head, and their
    peak, zero-shift and centre values as 17 more scalars. Phase correlation ignores a change of the
    intensities by a positive gain and an offset and finds the shift by the structure of the whole image; its
    wide band survives the corruptions that defeat the photometric costs (fog, contrast, noise), its low band
    some of the blur.

    Nothing before the head is learned, so training touches only about 0.3M parameters and no image
    convolution: a CPU trains it an order of magnitude faster than the ``correlation`` variant. The global
    volume tells the direction to any target that shares content with the view (shifts up to about
    ``6 * 11 = 66`` degrees at FoV 90); the fine pyramid resolves the last pixels (the zero-shift cost is
    exactly 0 on a clean target: the stop cue). A corrupted target is never matched exactly, so an agent
    meant for corrupted targets must be trained with them (``corruption.*``) to learn a softer stop rule.
    """

    def __init__(
        self, height: int, width: int, out_size: int, fine_shifts: int = 2, fine_scales: int = 4,
        normalized: bool = False, phase: bool = False,
    ) -> None:
        super().__init__()
        self.normalized = bool(normalized)
        if phase and not normalized:
            raise ValueError("phase=True (the phase variant) needs normalized=True")
        self.phase = PhaseCorrelation(height, width, DIRECT_COARSE, DIRECT_COARSE_SHIFTS) if phase else None
        phase_channels = len(PHASE_BANDWIDTHS) if phase else 0
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
            nn.Conv2d(3 + phase_channels, 16, 3, padding=1), nn.ReLU(),
            nn.Conv2d(16, 32, 3, stride=2, padding=1), nn.ReLU(),
        )
        head_out = 32 * ((n + 1) // 2) ** 2
        self.head_fc = nn.Sequential(nn.Linear(head_out, out_size), nn.LayerNorm(out_size), nn.ReLU())
        fine_size = 3 * self.fine_scales * (2 * self.fine_shifts + 1) ** 2 if self.fine_shifts else 0
        context_size = 2 * 3 * DIRECT_CONTEXT * DIRECT_CONTEXT
        self.volume_channels = 3 + phase_channels
        self.fixed_scalars = 3 + fine_size + context_size + 2 + (PHASE_SCALARS if phase else 0)
        self.fuse = nn.Sequential(
            nn.Linear(out_size + self.fixed_scalars, out_size),
            nn.LayerNorm(out_size), nn.ReLU(),
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

    @property
    def fixed_size(self) -> int:
        """Width of :meth:`fixed_inputs`: the coarse volume's channels x (2s+1)^2 bins, then the fixed scalars."""
        return self.volume_channels * self.volume_size**2 + self.fixed_scalars

    def fixed_inputs(self, view: torch.Tensor, target: torch.Tensor) -> torch.Tensor:
        """Everything before the learned head: ``view``, ``target`` (B, 3, H, W) float in [0, 1] ->
        (B, :attr:`fixed_size`): the coarse volume (B, C, 2s+1, 2s+1) flattened, then the fixed scalars (soft
        argmin, lowest cost, fine pyramid features, colour thumbnails, exact-match cue, phase scalars) in the
        order the head's ``fuse`` layer reads them. No parameters: a trainer may compute it once per
        observation and reuse it for every gradient step (:meth:`head_forward`)."""
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
        phase_scalars = None
        if self.phase is not None:
            surfaces, phase_scalars = self.phase(grey_v, grey_t)
            volume = torch.cat([volume, surfaces.to(volume.dtype)], dim=1)
        weights = torch.softmax(-shape * DIRECT_SOFTMIN_TEMPERATURE, dim=1)
        parts = [volume.flatten(1), weights @ self.shift_coords, low * 4.0]
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
        if phase_scalars is not None:
            parts.append(phase_scalars.to(residual.dtype))
        return torch.cat(parts, dim=1)

    def head_forward(self, fixed: torch.Tensor) -> torch.Tensor:
        """The learned part: :meth:`fixed_inputs` (B, :attr:`fixed_size`) -> (B, out_size)."""
        n, split = self.volume_size, self.volume_channels * self.volume_size**2
        if fixed.shape[-1] != self.fixed_size:
            raise ValueError(f"fixed inputs of width {fixed.shape[-1]}, this encoder reads {self.fixed_size}")
        volume = fixed[:, :split].view(-1, self.volume_channels, n, n)
        coarse = self.head_fc(self.head(volume).flatten(1))
        return self.fuse(torch.cat([coarse, fixed[:, split:]], dim=1))

    def forward(self, view: torch.Tensor, target: torch.Tensor) -> torch.Tensor:
        """``view``, ``target`` (B, 3, H, W) float in [0, 1] -> (B, out_size)."""
        return self.head_forward(self.fixed_inputs(view, target))
