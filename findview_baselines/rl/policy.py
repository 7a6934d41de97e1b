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
- ``robust``: ``direct`` on photometrically normalised images (standardised colours, high-passed grey for
  the fine pyramid), for corrupted targets.
- ``phase``: ``robust`` plus band-limited phase correlation of view and target (two correlation surfaces
  on the coarse volume's shift bins, their peaks and the values around zero shift; see
  :class:`PhaseCorrelation`): a direction and a stop cue that ignore intensity changes.

Pitch warps (``pitch_warps``, the ``direct`` family only): the phase correlation of the view with the target
warped by six hypothesised pitch offsets (:class:`PitchWarpedPhase`, ``rl/pitch_warps.py``), a cue that the
target is straight above or below, enters through ``warp_proj`` (an MLP whose last layer starts at zero) added to
the encoder's features; its scalars are part of :meth:`Policy.fixed_features`.

Wide match (``wide_match``, the ``direct`` family only): the zero-normalised cross-correlation of view and target
over their overlap at every shift, without a window (:class:`WideMatch`, ``rl/wide_match.py``), a direction cue for
a target that only overlaps the view's edge, enters the same way through ``wide_proj``. An observation may gate it
per row (:data:`WIDE_ON`, ``agent.wide_match_steps``): rows marked off add nothing from it; so do rows whose
wide-match peak is below :attr:`Policy.wide_min_peak` (``agent.wide_match_min_peak``).

Auxiliary rotation loss (any variant, training only): :class:`AuxHead` regresses ``(dpitch, dyaw) / fov``
and classifies overlap from the features before the GRU (``Policy.forward_features``); see
:func:`aux_loss`. The head is owned by the optimiser (PPO / DAgger), not by the policy, so policy
checkpoints are the same with and without it.

Recurrent-state convention (shared with ``storage.py``): ``masks[t] == 0`` means the observation at step
``t`` starts a new episode, so the hidden state entering step ``t`` is zeroed before the GRU runs.

This module holds the policy itself (:class:`Policy`, :func:`build_policy`, the variant lists). The image
encoders live in ``encoders.py``, the auxiliary head in ``aux_head.py`` and the checkpoint signature check
in ``signature.py``; their names are re-exported here.
"""

from __future__ import annotations

import math
from typing import TYPE_CHECKING, Any, Callable, Mapping

import torch
from torch import nn
from torch.distributions import Categorical

from findview.runtime import scoped
from findview.task import NUM_ACTIONS  # up, down, left, right, stop (findview.task.Action)
from findview_baselines.rl.aux_head import AuxHead, aux_loss
from findview_baselines.rl.distinct import distinct_rows, regroup
from findview_baselines.rl.encoders import (
    CONV_LAYERS,
    CORR_GRID,
    DIFF_GRID,
    DIRECT_COARSE,
    DIRECT_COARSE_SHIFTS,
    DIRECT_CONTEXT,
    DIRECT_SOFTMIN_TEMPERATURE,
    SOFT_SHIFT_SIZE,
    SOFT_SHIFT_TEMPERATURE,
    STANDARDIZE_FLOOR,
    STANDARDIZE_SCALE,
    ConvEncoder,
    CorrelationEncoder,
    DirectEncoder,
    conv_output_size,
    cost_features,
    highpass,
    pyramid_costs,
    standardize,
)
from findview_baselines.rl.pitch_warps import WARP_FEATURES, PitchWarpedPhase
from findview_baselines.rl.search_memory import MEMORY_FEATURES
from findview_baselines.rl.wide_match import WIDE_FEATURES, WIDE_PEAK, WideMatch
from findview_baselines.rl.signature import OPTIONAL_SIGNATURE_FIELDS, SIGNATURE_FIELDS, check_signature

# width of the hidden layer that reads the pitch warps' scalars
WARP_HIDDEN = 64

if TYPE_CHECKING:  # the schema lives above rl/ (it lists rl's variants); only its fields are read here
    from findview_baselines.config import PPOAgentConfig

__all__ = [
    "NUM_ACTIONS",
    "VARIANTS",
    "FINE_VARIANTS",
    "PRECISIONS",
    "Obs",
    "Policy",
    "build_policy",
    # re-exported from encoders.py, aux_head.py and signature.py (the old import paths keep working)
    "CONV_LAYERS",
    "CORR_GRID",
    "DIFF_GRID",
    "DIRECT_COARSE",
    "DIRECT_COARSE_SHIFTS",
    "DIRECT_CONTEXT",
    "DIRECT_SOFTMIN_TEMPERATURE",
    "SOFT_SHIFT_SIZE",
    "SOFT_SHIFT_TEMPERATURE",
    "STANDARDIZE_FLOOR",
    "STANDARDIZE_SCALE",
    "ConvEncoder",
    "CorrelationEncoder",
    "DirectEncoder",
    "conv_output_size",
    "cost_features",
    "highpass",
    "pyramid_costs",
    "standardize",
    "AuxHead",
    "aux_loss",
    "SIGNATURE_FIELDS",
    "OPTIONAL_SIGNATURE_FIELDS",
    "check_signature",
]

#: the policy variants (``agent.variant``); ``robust`` is ``direct`` on photometrically normalised images,
#: ``phase`` is ``robust`` with phase-correlation surfaces
VARIANTS = ("early_fusion", "goal_encoder", "siamese", "correlation", "direct", "robust", "phase")
#: the variants with a fine cost pyramid (``agent.fine_shifts``)
FINE_VARIANTS = ("correlation", "direct", "robust", "phase")
#: the variants whose encoder is a stack of learned convolutions over the whole image
CONV_VARIANTS = ("early_fusion", "goal_encoder", "siamese")
#: views of at least this many pixels make a conv-encoder policy heavy work (Policy.heavy): 128 x 128
HEAVY_MIN_PIXELS = 128 * 128
PRECISIONS = ("fp32", "bf16")  # agent.precision: the encoder's compute dtype (see Policy.configure_speed)

Obs = Mapping[str, torch.Tensor]
WIDE_ON = "wide_on"
"""An optional observation key: (B,) bool, the rows whose wide match speaks (``agent.wide_match_steps``); the other
rows' wide-match contribution is zero. Absent: every row's speaks."""


def _to_float(image: torch.Tensor) -> torch.Tensor:
    """uint8 (B, 3, H, W) in [0, 255] -> float32 in [0, 1] (float inputs are taken as already scaled)."""
    if image.dtype == torch.uint8:
        return image.float().div_(255.0)
    return image.float()


# --------------------------------------------------------------------------------------------------
# Policy
# --------------------------------------------------------------------------------------------------


def _check_direct_input(name: str, width: int, expected: int, what: str, variant: str) -> None:
    """An optional input of the ``direct`` family (``pitch_warps``, ``wide_match``): ``width`` must be 0 (off) or
    ``expected`` (the width of ``what``), and on only with one of the variants direct, robust, phase."""
    if int(width) not in (0, expected):
        raise ValueError(f"{name} must be 0 (off) or {expected} (the width of {what}), got {width}")
    if width and variant not in ("direct", "robust", "phase"):
        raise ValueError(f"{name} needs one of the variants direct, robust, phase, got {variant!r}")


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
        memory_inputs: int = 0,
        pitch_warps: int = 0,
        warp_fov: float = 90.0,
        wide_match: int = 0,
    ) -> None:
        super().__init__()
        _check_direct_input("wide_match", wide_match, WIDE_FEATURES, "the wide match's features", variant)
        _check_direct_input("pitch_warps", pitch_warps, WARP_FEATURES, "the pitch-warped phase correlation's scalars",
                            variant)
        if int(memory_inputs) not in (0, MEMORY_FEATURES):
            raise ValueError(f"memory_inputs must be 0 (off) or {MEMORY_FEATURES} (the width of the search memory's "
                             f"features), got {memory_inputs}")
        if variant not in VARIANTS:
            raise ValueError(f"unknown policy variant {variant!r}; choose one of {VARIANTS}")
        if fine_shifts and variant not in FINE_VARIANTS:
            raise ValueError(f"fine_shifts={fine_shifts} needs one of the variants {FINE_VARIANTS}, got {variant!r}")
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
        elif variant in ("direct", "robust", "phase"):
            self.encoder = DirectEncoder(
                height, width, hidden_size, self.fine_shifts, self.fine_scales,
                normalized=variant in ("robust", "phase"), phase=variant == "phase",
            )
            feature_size = hidden_size
        else:  # correlation
            self.encoder = CorrelationEncoder(
                height, width, hidden_size, fine_shifts=self.fine_shifts, fine_scales=self.fine_scales
            )
            feature_size = hidden_size
        self.feature_size = feature_size

        # the search memory's features (search_memory.RevisitPenalty.memory_features), added to the encoder's
        # through a linear map that starts at zero: the policy starts as the one without them (init_from)
        self.memory_inputs = int(memory_inputs)
        self.memory_proj = nn.Linear(self.memory_inputs, feature_size) if self.memory_inputs else None
        # the pitch-warped phase correlation (rl/pitch_warps.py; parameter-free, for views of ``warp_fov`` degrees)
        # through a small MLP whose last layer starts at zero, added to the encoder's features like the memory's
        self.pitch_warps = int(pitch_warps)
        self.warp = PitchWarpedPhase(height, width, warp_fov) if self.pitch_warps else None
        self.warp_proj = nn.Sequential(
            nn.Linear(self.pitch_warps, WARP_HIDDEN), nn.ReLU(), nn.Linear(WARP_HIDDEN, feature_size),
        ) if self.pitch_warps else None
        # the wide match (rl/wide_match.py; parameter-free) through an MLP of the same shape, also starting at zero
        self.wide_match = int(wide_match)
        self.wide = WideMatch(height, width) if self.wide_match else None
        self.wide_proj = nn.Sequential(
            nn.Linear(self.wide_match, WARP_HIDDEN), nn.ReLU(), nn.Linear(WARP_HIDDEN, feature_size),
        ) if self.wide_match else None
        # a setting, not a weight (agent.wide_match_min_peak, set_wide_min_peak; build_policy sets it for training,
        # the agent for evaluation): rows whose wide-match peak is below it add nothing from the wide match (0: every
        # row adds it)
        self.wide_min_peak = 0.0
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

    def features(self, obs: Obs | None, distinct_targets: bool = False, fixed: torch.Tensor | None = None) -> torch.Tensor:
        """:meth:`encode` under the speed options: (B, F) float32 features entering the GRU. ``fixed``: the rows'
        :meth:`fixed_features`, computed earlier, instead of ``obs`` (only the encoder's learned head runs;
        ``agent.compile`` is not applied to it)."""
        if fixed is not None:
            def run() -> torch.Tensor:
                return self._direct_head(fixed)
            device = fixed.device
        elif obs is None:
            raise ValueError("features needs obs or fixed")
        else:
            encode = self._compiled_encode if self._compiled_encode is not None else self.encode
            def run() -> torch.Tensor:
                return encode(obs, distinct_targets)
            device = obs["view"].device
        if self.precision == "bf16":
            with torch.autocast(device_type=device.type, dtype=torch.bfloat16):
                return run().float()
        return run()

    @property
    def fixed_feature_size(self) -> int:
        """Width of :meth:`fixed_features` for the variants whose encoder begins with fixed, parameter-free
        comparisons (``direct``, ``robust``, ``phase``: :meth:`DirectEncoder.fixed_inputs`); 0 for the others."""
        if not isinstance(self.encoder, DirectEncoder):
            return 0
        return self.encoder.fixed_size + self.pitch_warps + self.wide_match

    def fixed_features(self, obs: Obs) -> torch.Tensor:
        """The encoder's parameter-free part: ``obs`` {"view", "target"} (B, 3, H, W) uint8 -> (B,
        :attr:`fixed_feature_size`) float32. It does not change while the weights train, so a trainer that
        reuses an observation for several gradient steps computes it once (``forward_features(fixed=...)``)."""
        if not self.fixed_feature_size:
            raise ValueError(f"the {self.variant!r} variant has no fixed encoder part (fixed_feature_size is 0)")
        self._check_size(obs["view"])
        with torch.no_grad():
            return self._direct_fixed(self._prepare(obs["view"]), self._prepare(obs["target"])).float()

    def _direct_fixed(self, view: torch.Tensor, target: torch.Tensor, skip_wide: bool = False) -> torch.Tensor:
        """The ``direct`` family's parameter-free inputs: view, target (B, 3, H, W) float in [0, 1] -> (B,
        :attr:`fixed_feature_size`): :meth:`DirectEncoder.fixed_inputs`, then the pitch warps' scalars if on, then
        the wide match's if on (zeros with ``skip_wide``: for rows whose wide match is gated off)."""
        fixed = self.encoder.fixed_inputs(view, target)
        parts = [fixed]
        if self.warp is not None:
            parts.append(self.warp(view, target).to(fixed.dtype))
        if self.wide is not None:
            parts.append(fixed.new_zeros(len(fixed), self.wide_match) if skip_wide else self.wide(view, target).to(fixed.dtype))
        return torch.cat(parts, dim=1) if len(parts) > 1 else fixed

    def _direct_head(self, fixed: torch.Tensor, wide_on: torch.Tensor | None = None) -> torch.Tensor:
        """The ``direct`` family's learned part: :meth:`_direct_fixed`'s (B, :attr:`fixed_feature_size`) -> (B, F):
        the encoder's head, plus the pitch warps through ``warp_proj`` and the wide match through ``wide_proj`` if on.
        ``wide_on``: (B,) bool, the rows that add the wide match (``None``: all of them; :data:`WIDE_ON`); with
        :attr:`wide_min_peak` > 0 only those of them whose ZNCC peak reaches it (a confident match)."""
        split = self.encoder.fixed_size
        out = self.encoder.head_forward(fixed[:, :split])
        if self.warp_proj is not None:
            out = out + self.warp_proj(fixed[:, split:split + self.pitch_warps])
        if self.wide_proj is not None:
            wide_in = fixed[:, split + self.pitch_warps:]
            wide = self.wide_proj(wide_in)
            if self.wide_min_peak > 0:  # a row gated off (zero columns) has peak 0 and stays off
                sure = wide_in[:, WIDE_PEAK] >= self.wide_min_peak
                wide_on = sure if wide_on is None else wide_on & sure
            out = out + (wide if wide_on is None else wide * wide_on[:, None].to(wide.dtype))
        return out

    def set_wide_min_peak(self, peak: float, name: str = "wide_match_min_peak") -> None:
        """Gate the wide match by its ZNCC peak (:attr:`wide_min_peak`; ``agent.wide_match_min_peak``): rows whose
        peak is below ``peak`` add nothing from it. ``peak`` in [0, 1), 0 = no gate; a gate needs a network that
        reads the wide match. ``name``: the setting named in the errors."""
        peak = float(peak)
        if not 0.0 <= peak < 1.0:
            raise ValueError(f"{name} must be a ZNCC in [0, 1) (0 = no threshold), got {peak}")
        if peak and not self.wide_match:
            raise ValueError(f"{name}={peak} needs a network that reads the wide match (agent.wide_match=true, "
                             f"wide_match in its checkpoint signature); this one does not")
        self.wide_min_peak = peak

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
        if self.memory_proj is not None:
            nn.init.zeros_(self.memory_proj.weight)
        if self.warp_proj is not None:
            nn.init.zeros_(self.warp_proj[-1].weight)
        if self.wide_proj is not None:
            nn.init.zeros_(self.wide_proj[-1].weight)

    # ---------------------------------------------------------------------------------------------

    def model_signature(self) -> dict[str, Any]:
        """What a checkpoint must match to be loaded into this policy (see :func:`check_signature`)."""
        sig: dict[str, Any] = {
            "variant": self.variant, "hidden_size": self.hidden_size, "height": self.height, "width": self.width
        }
        if self.fine_shifts:  # only when set, so older readers still load fine_shifts=0 checkpoints
            sig["fine_shifts"] = self.fine_shifts
            sig["fine_scales"] = self.fine_scales
        if self.memory_inputs:
            sig["memory_inputs"] = self.memory_inputs
        if self.pitch_warps:
            sig["pitch_warps"] = self.pitch_warps
        if self.wide_match:
            sig["wide_match"] = self.wide_match
        return sig

    @property
    def heavy(self) -> bool:
        """Whether running this network is heavy work (``findview.runtime.heavy_work``: every free core) rather
        than many small ops (one thread): a conv-encoder variant on views of at least
        :data:`HEAVY_MIN_PIXELS` pixels."""
        return self.variant in CONV_VARIANTS and self.height * self.width >= HEAVY_MIN_PIXELS

    def initial_hidden(self, num_envs: int, device: torch.device | str | None = None) -> torch.Tensor:
        """Zero recurrent state, (num_envs, hidden_size)."""
        return torch.zeros(num_envs, self.hidden_size, device=device)

    # ---------------------------------------------------------------------------------------------

    def encode(self, obs: Obs, distinct_targets: bool = False) -> torch.Tensor:
        """Observation features before the GRU.

        ``obs["view"]``, ``obs["target"]``: (B, 3, H, W) uint8 -> (B, F) with F = :attr:`feature_size`
        (hidden_size; 2 * hidden_size for ``goal_encoder``). ``distinct_targets``: run the target-only work
        once per distinct target (``rl/distinct.py``; worth it on a rollout of several steps, where each
        episode's target repeats; it costs a host read on CUDA, so acting one step does not ask for it).
        """
        self._check_size(obs["view"])
        view = self._prepare(obs["view"])
        if self.variant not in CONV_VARIANTS:  # the FINE_VARIANTS take both images together
            target = self._prepare(obs["target"])
            if isinstance(self.encoder, DirectEncoder):
                wide_on = obs.get(WIDE_ON)
                # no row's wide match speaks (wide_match_steps): on the CPU its columns stay zero, not computed;
                # on an accelerator it is computed and masked, which is cheap there, as asking would cost a host read
                skip_wide = (wide_on is not None and self.wide is not None and view.device.type == "cpu"
                             and not bool(wide_on.any()))
                return self._direct_head(self._direct_fixed(view, target, skip_wide), wide_on)
            return self.encoder(view, target)
        # the work that depends on the target alone runs once per distinct target (a rollout repeats each
        # episode's target on every step; see rl/distinct.py): the same features and gradients, less work
        groups = distinct_rows(obs["target"]) if distinct_targets else None
        target = self._prepare(obs["target"] if groups is None else obs["target"][groups[0]])
        inverse = None if groups is None else groups[1]
        if self.variant == "early_fusion":
            return self.encoder.forward_pair(view, target, inverse)
        if self.variant == "goal_encoder":
            goal = self.goal_encoder(target)
            fused = self.encoder.forward_pair(view, target, inverse)
            return torch.cat([fused, regroup(goal, inverse)], dim=1)
        # siamese: one encoder, the view and the distinct targets batched together
        both = self.encoder(torch.cat([view, target], dim=0))
        view_feat, target_feat = both[: view.shape[0]], both[view.shape[0]:]
        return self.fuse(torch.cat([view_feat, regroup(target_feat, inverse)], dim=1))

    def _check_size(self, images: torch.Tensor) -> None:
        if images.shape[-2:] != (self.height, self.width):
            raise ValueError(
                f"policy was built for {self.height}x{self.width} images, got {tuple(images.shape[-2:])}"
            )

    def _prepare(self, images: torch.Tensor) -> torch.Tensor:
        """Encoder input: float in [0, 1] (uint8 is scaled), in channels-last memory format when that is on."""
        images = _to_float(images)
        return images.contiguous(memory_format=torch.channels_last) if self.channels_last else images

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
        self, obs: Obs, hidden: torch.Tensor, masks: torch.Tensor, memory: torch.Tensor | None = None
    ) -> tuple[Categorical, torch.Tensor, torch.Tensor]:
        """Action distribution (batch T*N), values (T*N,) and the last state (N, hidden)."""
        dist, values, new_hidden, _ = self.forward_features(obs, hidden, masks, memory=memory)
        return dist, values, new_hidden

    def forward_features(
        self, obs: Obs | None, hidden: torch.Tensor, masks: torch.Tensor, fixed: torch.Tensor | None = None,
        memory: torch.Tensor | None = None,
    ) -> tuple[Categorical, torch.Tensor, torch.Tensor, torch.Tensor]:
        """:meth:`forward` plus the pre-GRU features (T*N, F) (input of an :class:`AuxHead`).

        Same inputs as :meth:`run_gru` (time-major ``T*N`` rows, ``hidden`` (N, hidden), masks (T*N,)).
        ``fixed``: the rows' :meth:`fixed_features` (T*N, D), computed earlier, instead of ``obs`` (the same
        result; the encoder's parameter-free part is skipped; ``agent.compile`` is not applied to the rest).
        ``memory``: (T*N, :attr:`memory_inputs`) float, the search memory's features of each row
        (``RevisitPenalty.memory_features``); required exactly when the policy was built with ``memory_inputs``.
        """
        several_steps = obs is not None and obs["view"].shape[0] > hidden.shape[0]
        features = self.features(obs, distinct_targets=several_steps, fixed=fixed)
        features = self._add_memory(features, memory)
        out, new_hidden = self.run_gru(features, hidden, masks)
        dist = Categorical(logits=self.actor(out))
        values = self.critic(out).squeeze(-1)
        return dist, values, new_hidden, features

    def _add_memory(self, features: torch.Tensor, memory: torch.Tensor | None) -> torch.Tensor:
        """``features`` (B, F) plus the projected search-memory features (B, memory_inputs), when the policy reads them."""
        if self.memory_proj is None:
            if memory is not None:
                raise ValueError("this policy was built without memory inputs (memory_inputs=0) but was given memory features")
            return features
        if memory is None or tuple(memory.shape) != (features.shape[0], self.memory_inputs):
            got = None if memory is None else tuple(memory.shape)
            raise ValueError(f"this policy reads the search memory: it needs memory features of shape "
                             f"({features.shape[0]}, {self.memory_inputs}), got {got} (agent.memory_inputs needs "
                             f"agent.revisit_penalty > 0)")
        return features + self.memory_proj(memory.to(features.dtype))

    # ---------------------------------------------------------------------------------------------
    # The API used by the trainer / evaluator
    # ---------------------------------------------------------------------------------------------

    @scoped(lambda self: self.heavy)
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

    @scoped(lambda self: self.heavy)
    def get_value(self, obs: Obs, hidden: torch.Tensor, masks: torch.Tensor) -> torch.Tensor:
        """Critic value (N,) of one step (same inputs as :meth:`act`)."""
        out, _ = self.run_gru(self._add_memory(self.features(obs), None), hidden, masks)
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


def build_policy(agent: "PPOAgentConfig", height: int, width: int) -> Policy:
    """Policy from the ``agent`` section (:class:`findview_baselines.config.PPOAgentConfig`: ``variant``,
    ``hidden_size``, ``fine_shifts``, ``fine_scales``, ``memory_inputs``, ``pitch_warps`` (for views of ``fov``
    degrees), ``wide_match`` (gated by ``wide_match_min_peak``); speed options ``precision``, ``channels_last``,
    ``compile``, see :meth:`Policy.configure_speed`) and the view size of ``sim`` (pixels)."""
    policy = Policy(height=int(height), width=int(width), variant=agent.variant, hidden_size=agent.hidden_size,
                    fine_shifts=agent.fine_shifts, fine_scales=agent.fine_scales,
                    memory_inputs=MEMORY_FEATURES if agent.memory_inputs else 0,
                    pitch_warps=WARP_FEATURES if agent.pitch_warps else 0, warp_fov=agent.fov,
                    wide_match=WIDE_FEATURES if agent.wide_match else 0)
    # the wide match's peak gate holds in training as in evaluation
    policy.set_wide_min_peak(agent.wide_match_min_peak, name="agent.wide_match_min_peak")
    return policy.configure_speed(precision=agent.precision, channels_last=agent.channels_last, compile=agent.compile)
