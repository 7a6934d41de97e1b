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

Auxiliary rotation loss (any variant, training only): :class:`AuxHead` regresses ``(dpitch, dyaw) / fov``
and classifies overlap from the features before the GRU (``Policy.forward_features``); see
:func:`aux_loss`. The head is owned by the optimiser (PPO / DAgger), not by the policy, so policy
checkpoints are the same with and without it.

Recurrent-state convention (shared with ``storage.py``): ``masks[t] == 0`` means the observation at step
``t`` starts a new episode, so the hidden state entering step ``t`` is zeroed before the GRU runs.
"""

from __future__ import annotations

import math
from typing import Any, Mapping

import torch
from torch import nn
from torch.distributions import Categorical

NUM_ACTIONS = 5  # up, down, left, right, stop (findview.task.Action)
VARIANTS = ("early_fusion", "goal_encoder", "siamese", "correlation")

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
    """

    def __init__(self, height: int, width: int, out_size: int, channels: int = 32) -> None:
        super().__init__()
        if height < 16 or width < 16:
            raise ValueError(f"image {height}x{width} is too small for the correlation encoder (needs at least 16x16)")
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
            nn.Linear(out_size + SOFT_SHIFT_SIZE + 2 * DIFF_GRID * DIFF_GRID + 2 * channels, out_size),
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
        return self.fuse(torch.cat([corr, self.soft_shift(volume), diff_feats, context], dim=1))


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


# --------------------------------------------------------------------------------------------------
# Policy
# --------------------------------------------------------------------------------------------------


class Policy(nn.Module):
    """Encoder(s) + single-layer GRU + actor/critic heads.

    Args:
        height, width: size of the view and target images (both the same).
        variant: one of :data:`VARIANTS`.
        hidden_size: size of the encoder features and of the GRU state (512 in the paper).

    ``feature_size`` is the width ``F`` of the features entering the GRU (see :meth:`encode`).
    """

    def __init__(self, height: int, width: int, variant: str = "early_fusion", hidden_size: int = 512) -> None:
        super().__init__()
        if variant not in VARIANTS:
            raise ValueError(f"unknown policy variant {variant!r}; choose one of {VARIANTS}")
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
        else:  # correlation
            self.encoder = CorrelationEncoder(height, width, hidden_size)
            feature_size = hidden_size
        self.feature_size = feature_size

        self.gru = nn.GRU(feature_size, hidden_size, num_layers=1)
        self.actor = nn.Linear(hidden_size, NUM_ACTIONS)
        self.critic = nn.Linear(hidden_size, 1)
        self._init_weights()

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
        return {"variant": self.variant, "hidden_size": self.hidden_size, "height": self.height, "width": self.width}

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
        if view.shape[-2:] != (self.height, self.width):
            raise ValueError(
                f"policy was built for {self.height}x{self.width} images, got {tuple(view.shape[-2:])}"
            )
        if self.variant == "early_fusion":
            return self.encoder(torch.cat([view, target], dim=1))
        if self.variant == "goal_encoder":
            fused = self.encoder(torch.cat([view, target], dim=1))
            return torch.cat([fused, self.goal_encoder(target)], dim=1)
        if self.variant == "correlation":
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
        features = self.encode(obs)
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
        out, _ = self.run_gru(self.encode(obs), hidden, masks)
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
    """Policy from the ``agent`` config (``variant``, ``hidden_size``) and the view size of ``sim``."""
    return Policy(
        height=int(height),
        width=int(width),
        variant=str(agent_cfg.get("variant", "early_fusion")),
        hidden_size=int(agent_cfg.get("hidden_size", 512)),
    )
