"""Typed config schemas of the baselines and of the tools (Hydra ConfigStore).

- Agents (``agent`` group): :class:`RandomAgentConfig`, :class:`OracleAgentConfig`,
  :class:`FeatureAgentConfig` (orb, sift), :class:`RotationAgentConfig`, :class:`PPOAgentConfig`
  (the learned policy: model + PPO hyper-parameters).
- Training: :class:`TrainerConfig` (``trainer`` group: the run loop and the algorithm, ``ppo`` or
  ``dagger``), :class:`SchedulerConfig` (``scheduler``).
- One primary schema per tool: :class:`TrainConfig`, :class:`EvalConfig`, :class:`MakeDatasetConfig`,
  :class:`RenderEpisodeConfig`, :class:`RenderCorruptionsConfig`.

:func:`register_configs` stores them all (and the core schemas of :mod:`findview.config`); every YAML
file names its schema in its defaults list, so a wrong type or an unknown key anywhere, presets
included, fails when Hydra composes the config. Range checks run in ``__post_init__`` when
:func:`findview_baselines.cli.validate_config` turns the config into objects.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from dataclasses import fields as dataclass_fields
from pathlib import Path
from typing import Any, Optional, Sequence

from omegaconf import MISSING, DictConfig, OmegaConf

from findview_baselines.rl.dagger_config import DAggerConfig
from findview_baselines.rl.ppo import PPOConfig

from findview.config import (
    ConfigError,
    CorruptionConfig,
    DatasetConfig,
    SimConfig,
    TaskConfig,
    check,
    register_core_configs,
)

__all__ = [
    "RandomAgentConfig",
    "OracleAgentConfig",
    "FeatureAgentConfig",
    "RotationAgentConfig",
    "PPOAgentConfig",
    "DAggerConfig",
    "TrainerConfig",
    "SchedulerConfig",
    "TrainConfig",
    "EvalConfig",
    "MakeDatasetConfig",
    "RenderEpisodeConfig",
    "RenderCorruptionsConfig",
    "register_configs",
    "typed_config",
    "compose_config",
    "register_resolvers",
    "CONFIG_DIR",
    "config_error_line",
    "MOVED_KEYS",
]

DIFFICULTY_NAMES = ("easy", "medium", "hard")


# ------------------------------------------------------------------------------------------------
# Agents
# ------------------------------------------------------------------------------------------------


@dataclass
class RandomAgentConfig:
    """Uniformly random actions over up / down / left / right / stop (one seeded stream per episode)."""

    name: str = "random"
    """Agent name (make_agent key)."""


@dataclass
class OracleAgentConfig:
    """The shortest path from the episode's privileged rotations (eps 0, SPL 1 by construction)."""

    name: str = "oracle"
    """Agent name (make_agent key)."""
    order: str = "pitch_first"
    """pitch_first | yaw_first: which axis to close first (both are shortest paths)."""
    pitch_bound: int = 60
    """Pitch clamp of the task, degrees (must match task.pitch_bound)."""
    step_deg: int = 1
    """Degrees per move (must match task.step_deg)."""

    def __post_init__(self) -> None:
        check(self.order in ("pitch_first", "yaw_first"), "agent.order", self.order, "pitch_first | yaw_first")


def _check_d_thresh(value: Any) -> None:
    """``d_thresh``: one number (or ``inf``) for every difficulty, or ``{easy, medium, hard}`` numbers."""
    items = dict(value) if isinstance(value, dict) else {"all": value}
    for key, v in items.items():
        ok = (key == "all" or key in DIFFICULTY_NAMES) and isinstance(v, (int, float)) and not isinstance(v, bool)
        ok = ok and (v >= 0 or math.isinf(v))
        check(ok, "agent.d_thresh", value, "a descriptor distance >= 0 (or inf), or {easy, medium, hard} of them")


@dataclass
class FeatureAgentConfig:
    """The paper's rule-based agents (``orb`` and ``sift``): match features of view and target, each
    match votes for the move that reduces its displacement (docs/TASK.md, section Rule-based agents)."""

    name: str = MISSING
    """orb | sift (the detector)."""
    n_features: int = 500
    """Keypoints per image."""
    ratio: float = 0.7
    """Lowe ratio test on the 2 nearest neighbours."""
    d_thresh: Any = field(default_factory=lambda: {"easy": math.inf, "medium": math.inf, "hard": math.inf})
    """Max descriptor distance of a voting match, per difficulty ({easy, medium, hard}) or one value for
    all (``agent.d_thresh=50``); tuned on val among 10, 20, ..., 100, inf."""
    min_keypoints: int = 10
    """Fewer keypoints in view or target: repeat the previous action."""
    min_matches: int = 10
    """Fewer ratio-test matches: repeat the previous action."""
    stop_px: float = 1.0
    """A match votes stop when |dx| and |dy| are both below this, pixels."""
    osc_window: int = 4
    """Last N actions (this one included) checked for oscillation; < 2 disables."""
    osc_rule: str = "alternating"
    """alternating (L,R,L,R / U,D,U,D) | mixed (one axis, both directions)."""
    cache_views: int = 400
    """Views per slot whose vote (detection and matching against the target) is remembered for the episode (a
    slot that repeats its move circles and sees them again every 360 moves); 0 = off. Results do not depend on
    it, only speed (a hit costs a hash of the view); memory: a key and a vote per view."""
    threads: int = 2
    """Environment slots processed in parallel (OpenCV releases the GIL)."""
    cv2_threads: Optional[int] = 1
    """OpenCV threads while the agent acts, restored afterwards (null: leave OpenCV's setting)."""

    def __post_init__(self) -> None:
        check(self.name in ("orb", "sift"), "agent.name", self.name, "orb | sift")
        _check_d_thresh(self.d_thresh)
        check(self.n_features >= 1, "agent.n_features", self.n_features, "a positive number of keypoints")
        check(0 < self.ratio <= 1, "agent.ratio", self.ratio, "a ratio in (0, 1]")
        check(self.osc_rule in ("alternating", "mixed"), "agent.osc_rule", self.osc_rule, "alternating | mixed")
        check(self.cache_views >= 0, "agent.cache_views", self.cache_views, "0 (off) or a number of views")
        check(self.threads >= 1, "agent.threads", self.threads, "a positive number of threads")


@dataclass
class RotationAgentConfig:
    """The exact geometric agent (beyond the paper): relative-rotation estimates from feature matches (keypoints
    on locally contrast-normalised images), dead reckoning, a structure and colour check before every stop
    (blind to fog and contrast), a one-degree refinement of every stop that is not byte-identical to the
    target, a covering search of the sphere (findview_baselines/agents/rotation.py)."""

    name: str = "rotation"
    """Agent name (make_agent key)."""
    fov: float = 90.0
    """Field of view of the rendered views, degrees (must match sim.fov)."""
    detector: str = "sift"
    """sift | orb."""
    n_features: int = 500
    """Keypoints per image."""
    ratio: float = 0.8
    """Lowe ratio for candidate matches (RANSAC removes outliers)."""
    inlier_px: float = 2.0
    """RANSAC inlier tolerance, pixels at the image centre."""
    ransac_iters: int = 200
    """RANSAC hypotheses."""
    min_inliers: int = 4
    """Inliers needed to trust an estimate (a wrong one costs a detour: every stop is verified)."""
    pitch_bound: int = 60
    """Pitch clamp of the task, degrees (must match task.pitch_bound)."""
    pitch_tol: float = 10.0
    """Estimated absolute pitches beyond pitch_bound + pitch_tol are rejected, degrees."""
    reestimate_every: int = 4
    """Fewest moves between estimates while walking to a candidate (always on arrival)."""
    sweep_check_every: Optional[int] = None
    """Moves between estimates while searching (null: round(fov / 8))."""
    sweep_pitch: Optional[float] = None
    """Pitch between search rows, degrees (null: 0.8 x the vertical field of view)."""
    search_scale: float = 0.5
    """The search detects keypoints on views downsampled by this factor (1: full size)."""
    max_arrivals: int = 6
    """Arrivals that still ask for moves before the candidate is decided where it is."""
    verify_thresh: float = 0.3
    """Content check: correlation of the locally contrast-normalised gray view and target (1/4 size) needed to stop, in [-1, 1]."""
    verify_thresh_geo: float = 0.1
    """... or this much when the estimate at the view puts the target there with verify_inliers inliers (with such an estimate, an opponent-colour score of verify_opponent also passes the content check)."""
    verify_inliers: int = 12
    """Inliers of an estimate rounding to (0, 0) for the lower content thresholds."""
    verify_chroma: float = 1.0
    """Largest difference of the mean chromaticity r / (r + g + b) (any channel) to stop (1: off; fog greys colours, verify_hue covers hue)."""
    verify_hue: float = 64.0
    """Largest distance of the mean opponent colours (R - G, G - B), after the best gain in [0.2, 4], to stop (grey levels)."""
    verify_colour: float = 0.35
    """Colour correlation of the high-passed view and target (1/4 size) that makes the colours match, in [-1, 1]."""
    verify_opponent: float = 0.8
    """... or this correlation of their high-passed colour differences (R - G, G - B), which fog and contrast only scale; with the estimate's verify_inliers it also stands in for the structure score."""
    lcn_sigma: Optional[float] = 4.0
    """Local contrast normalisation window before keypoint detection, pixels (null: detect on raw gray)."""
    refine: bool = True
    """Hill-climb the structure score over one-degree neighbours whenever a verified stop is not byte-identical to the target."""
    reject_radius: int = 3
    """Estimates within this many degrees (each axis) of a rejected candidate are ignored."""
    threads: int = 2
    """Environment slots processed in parallel."""
    cv2_threads: Optional[int] = 1
    """OpenCV threads while the agent acts (null: leave OpenCV's setting)."""

    def __post_init__(self) -> None:
        check(self.detector in ("sift", "orb"), "agent.detector", self.detector, "sift | orb")
        check(0 < self.fov < 180, "agent.fov", self.fov, "a field of view in (0, 180) degrees")
        check(self.min_inliers >= 3, "agent.min_inliers", self.min_inliers, "at least 3 inliers")
        check(0 < self.search_scale <= 1, "agent.search_scale", self.search_scale, "a factor in (0, 1]")
        check(-1 <= self.verify_thresh <= 1, "agent.verify_thresh", self.verify_thresh, "a score in [-1, 1]")
        check(self.reject_radius >= 0, "agent.reject_radius", self.reject_radius, "0 or more degrees")


from findview_baselines.rl.policy import FINE_VARIANTS, PRECISIONS as POLICY_PRECISIONS  # noqa: E402  (one list each)
from findview_baselines.rl.policy import VARIANTS as POLICY_VARIANTS  # noqa: E402


@dataclass
class PPOAgentConfig:
    """The learned agent: its network and how it acts at validation / evaluation. How it is trained lives in
    the ``trainer`` section (``trainer.ppo.*`` for PPO, ``trainer.dagger.*`` for DAgger)."""

    name: str = "ppo"
    """Agent name."""
    variant: str = "early_fusion"
    """Network: one of ``findview_baselines.rl.policy.VARIANTS`` (early_fusion, the paper's, is the default)."""
    hidden_size: int = 512
    """Encoder feature size and GRU state size."""
    fine_shifts: int = 0
    """correlation / direct / robust / phase only: fine photometric cost map of view vs target for pixel shifts -k..k per
    axis at the full input resolution (k = fine_shifts pixels; 0 = off). Part of the checkpoint signature."""
    fine_scales: int = 1
    """Pyramid levels of that cost map (2x average pooling per level; level s covers k * 2^s pixels);
    1 = full resolution only. Part of the checkpoint signature."""
    downsample: int = 1
    """Training: the network takes the rendered views (``sim.height x sim.width``) averaged over ``k x k`` blocks
    (findview_baselines/rl/observations.py), so it is built for ``sim.height / k x sim.width / k`` images while
    targets are corrupted at the rendered size, as for every other agent. 1 = the views as rendered. (A learned
    agent evaluated on views an integer multiple of its network's size averages them down by itself.)"""
    sample: bool = False
    """Draw actions from the policy at validation / evaluation time instead of taking the argmax."""
    revisit_penalty: float = 0.0
    """Search memory at validation / evaluation time (and in DAgger's rollouts): logit units subtracted from a
    move per earlier visit of the pose it leads to (poses dead-reckoned from the agent's own moves; breaks
    left/right loops). 0 = off, the plain policy. See findview_baselines/rl/search_memory.py."""
    revisit_row_stride: int = 0
    """With the search memory on: once the agent has looked around a full turn near its row, it moves to the next
    search row, this many 1-step moves above / below its start (alternately: +s, -s, +2s, -2s, ...). 0 = off."""
    revisit_row_after: int = 0
    """With ``revisit_row_stride``: the row search acts from this step of an episode on (0: from its first step).
    Before it the policy searches alone; an episode still searching then is taken through the search rows, a
    safety net under a learned search (findview_baselines/rl/search_memory.py, "Row search")."""
    revisit_row_budget: int = 0
    """With ``revisit_row_stride``: steps at one search row after which the row search moves on to the next even if
    that row is not looked around (a learned agent unsure which row is next can zigzag up and down a column at a
    time and never finish one). 0 = no limit."""
    revisit_row_hold: bool = False
    """With ``revisit_row_stride``: once on its search row, the agent may not move more than half a stride above or
    below it until the row search moves on (a policy that paces a column walks off a row as soon as it is brought
    there; findview_baselines/rl/search_memory.py, ``RowSearch.hold``)."""
    revisit_near_rows: int = 0
    """With the search memory on: a move also pays ``revisit_near_penalty`` per visit of the most visited cell near
    its destination (a yaw move: its column within this many rows; a pitch move: its column up to this many rows
    beyond it), counting visits at least ``revisit_near_age`` steps old, so that going back over yaw it has seen, one
    row off its old path, costs too. 0 = off (the memory every shipped agent trained with). See
    findview_baselines/rl/search_memory.py, "Near visits"."""
    revisit_near_penalty: float = 4.0
    """With ``revisit_near_rows``: logit units per near visit."""
    revisit_near_age: int = 1
    """With ``revisit_near_rows``: steps since a near cell's last visit before that visit counts (1: every earlier
    visit; larger ages leave the recent path free, which at FoV 90 gave back all of the gain on hard episodes)."""
    revisit_near_since: int = 0
    """With ``revisit_near_rows``: visits made before this step of an episode never count as near ones (0: all count).
    The path out of the first steps stays free to walk back along one row off it (the policy correcting its first
    guess of the side); a search going round again later pays."""
    revisit_near_until: Optional[float] = None
    """With ``revisit_near_rows`` and ``refine_min_near`` (a stop-offset net with the near output): once the net finds
    an episode's view near its target with at least this probability (at a pose the agent checks: a STOP, a new most
    stop-like pose, a half-sure STOP), that episode's near visits stop counting. A search hovering by a target it cannot
    yet stop on (a corrupted one) is not pushed away from it. null = they count to the end."""
    memory_inputs: bool = False
    """The network reads its search memory (needs ``revisit_penalty > 0`` and 1-degree actions): per step, whether it
    has looked at 90% of a full turn of yaw cells near its current row, how much of a turn, whether the rows above / below have been, and its pitch
    offset from the start (findview_baselines/rl/search_memory.py, ``memory_features``). With DAgger's ``pan``
    search prior the labels then leave a finished row towards the target. Part of the checkpoint signature."""
    pitch_warps: bool = False
    """The network also reads the phase correlation of the view with the target warped by six pitch offsets (+-1/6,
    1/3, 1/2 of ``fov``): a cue that the target is straight above or below (findview_baselines/rl/pitch_warps.py),
    through a layer that starts at zero (``init_from`` an agent without it starts unchanged). direct / robust /
    phase variants only. Part of the checkpoint signature."""
    wide_match: bool = False
    """The network also reads the zero-normalised cross-correlation of view and target over their overlap at every
    shift, without a window (findview_baselines/rl/wide_match.py): which way a target lies that only overlaps the
    edge of the view (45-70 degrees to the side at FoV 90), where the phase correlation's window hides it. Through a
    layer that starts at zero (``init_from`` an agent without it starts unchanged). direct / robust / phase variants
    only. Part of the checkpoint signature. The FoV-90 robust file reads it since session 40 (its stage 4,
    configs/experiment/robust_wide.yaml), in each episode's first 10 steps (``wide_match_steps``)."""
    wide_match_steps: int = 0
    """At evaluation (as ``mirror_steps``), with a network that reads the wide match: it speaks only in the first this
    many policy steps of an episode, where it tells which way a target at the edge of the view lies; later steps add
    nothing from it (for a network of which only the wide match's layer trained, ``train_only=[wide_proj]``: the
    network it started from, with the GRU state those first steps left). 0 = every step."""
    wide_match_min_peak: float = 0.0
    """With a network that reads the wide match, in evaluation and in training (the trainer's network gets it too):
    the wide match speaks only for a view whose wide-match peak (the best ZNCC of view and target over the shifts
    with enough overlap, in [-1, 1]) is at least this, i.e. when the target overlaps the view with some confidence;
    for a target outside the view (a hard episode's start) the peak is low and the network acts as the one it
    started from. Combines with ``wide_match_steps``. 0 = no threshold. tools/eval.py takes the checkpoint's
    training value unless the command line sets it."""
    wide_match_turn: float = 0.0
    """At evaluation, with ``wide_match_steps`` > 0: the episode's first yaw move goes the way the wide match points
    when it is sure. In the first ``wide_match_steps`` policy steps, a view whose wide-match peak (the best ZNCC of
    view and target, in [-1, 1]) is at least this and whose best column shift is at least
    ``findview_baselines.agents.ppo_agent.TURN_MIN_SHIFT`` of the width sets the episode's side (the last such view
    decides); until the agent's first LEFT or RIGHT, the yaw move away from that side is ruled out. A hand-written
    rule on a parameter-free input: the network decides everything else, including when to turn and every later
    move. It mends the network's first turn where the target overlaps only the view's edge (40-65 degrees to the
    side at FoV 90), where a wrong first turn costs a full circle (benchmarks/RESULTS.md, "Session 52"). 0 = off."""
    refine_stop: bool = False
    """At evaluation (tools/eval.py, the benchmarks; the trainer's validation plays without it): check each stop
    of the policy by phase correlation of view and target, and when the target is measured at least half a degree
    away move towards it (one degree per step, at most
    ``refine_moves`` moves) before stopping. It measures on the views as rendered (on 256x256 views of a 64x64
    network: the full-size ones); its peak threshold was chosen on 64x64 views. See
    findview_baselines/agents/stop_refine.py."""
    refine_moves: int = 4
    """Most refinement moves per episode (with ``refine_stop``)."""
    refine_model: Optional[str] = None
    """With ``refine_stop``: a learned stop-offset net (a file of tools/train_stop_offsets.py, e.g.
    pretrained/stop_offsets_fov90_256.pth) decides the refinement's moves instead of the measured residual: it
    learned the offsets corruptions put between a target's content and its pose (glass blur, motion blur). Made
    for one view size and FoV (its file says which). null = the phase-correlation residual. See
    findview_baselines/agents/stop_offsets.py."""
    refine_min_stay: float = 0.3
    """With ``refine_model``: the net's probability that the view is on the target below which the stop moves."""
    refine_min_near: Optional[float] = None
    """With ``refine_model`` (a net with the near output, tools/train_stop_offsets.py ``--far-fraction`` > 0): a STOP
    of the policy whose view the net gives a probability of being near the target (within 3 degrees on each axis)
    below this is refused, as ``stop_min_prob`` refuses one: the slot takes its most likely move and searches on.
    With ``stop_by`` a view becomes the most stop-like pose (the walk's goal) only if the net finds it near. A stop
    on a look-alike part of the panorama then does not end the episode. null = off."""
    refine_near_model: Optional[str] = None
    """With ``refine_min_near``: a second stop-offset file with the near output (same FoV and view size) that answers
    every near check (``refine_min_near``, ``stop_near_prob``, ``revisit_near_until``) while ``refine_model``'s net
    keeps deciding the refinement's moves, e.g. a net trained against look-alikes
    (tools/train_stop_offsets.py ``--far-lookalike``) beside a refinement net without the near output.
    null = ``refine_model``'s net answers both."""
    stop_prob: Optional[float] = None
    """At evaluation (as ``refine_stop``): STOP whenever the policy gives STOP at least this probability, even when a
    move has more (a learned stop that hesitates on corrupted targets); null = the argmax (or the sample) decides."""
    stop_min_prob: Optional[float] = None
    """At evaluation (as ``refine_stop``): refuse a STOP the policy gives less than this probability; the slot takes
    its most likely move instead (after the search memory's penalty), so an unsure stop on a look-alike view does not end the
    episode. Use it with ``stop_by``: a slot that finds nothing surer walks back to its most stop-like pose at the end.
    null = every STOP of the argmax (or the sample) stands. At most ``stop_prob``."""
    stop_near_prob: Optional[float] = None
    """With ``refine_min_near``: STOP also whenever the policy gives STOP at least this probability (even when a move
    is more likely, or ``stop_min_prob`` would refuse it) and the stop-offset net (``refine_model``) gives the view at
    least ``refine_min_near`` of being near the target (within 3 degrees on each axis), so a target the network
    recognises only half-heartedly (a blurred one) is stopped on when first seen instead of at the end by
    ``stop_by``'s walk back. null = off."""
    stop_near_min_near: Optional[float] = None
    """With ``stop_near_prob``: the stop-offset net's near probability its half-sure STOPs need, in
    [``refine_min_near``, 1): a stricter bar than the one the policy's own STOPs pass, so a look-alike part of the
    panorama the net finds near at 0.6-0.95 does not end an episode on a half-sure STOP. null = ``refine_min_near``."""
    stop_by: int = 0
    """At evaluation, with the search memory on: the step by which the agent stops (set it to T, task.max_steps).
    A slot that has not stopped when the steps left are just enough walks back to the (dead-reckoned) pose where the
    policy's STOP probability was highest and stops there, instead of running out of steps wherever it is; episodes
    the agent ends by itself are unchanged. 0 = off. See findview_baselines/agents/give_up.py."""
    stop_by_phase: bool = False
    """With ``stop_by``: a slot whose STOP probability never reached 0.1 (a target the stop head does not recognise,
    e.g. under heavy fog) walks instead to the pose that phase correlation of view and target pointed at most clearly
    over its search (measured every step on the grey views averaged over k x k blocks, k = width // 128 where it
    divides the size, 256 -> 128 pixels; the pose where it was measured plus the rotation measured there) and stops
    there. Episodes that stop by themselves, or whose STOP
    probability reached 0.1, are unchanged. false = off."""
    mirror_steps: int = 0
    """At evaluation (as ``refine_stop``): for the first this many policy steps of an episode the network also plays
    the episode's left-right mirror (view and target flipped, a second GRU state) and the agent acts on the mean of
    the two log-probabilities, the mirror's LEFT and RIGHT swapped: a network that finds targets on one side better
    than on the other picks the side of a target in view as well on both (the task is the same in a mirror). Where
    one play would turn back against the last yaw move and the other go on, the one going on leads (a network that
    learned to search turning one way searches the other way in its mirror). Up to twice the network's work per
    step. 0 = off; ``task.max_steps``: every step. See findview_baselines/agents/ppo_agent.py, ``mirror_mean``."""
    fov: float = 90.0
    """Horizontal field of view of the views, degrees (the refinement's pixels-to-degrees; configs/agent/ppo.yaml
    sets it to ${sim.fov})."""
    precision: str = "fp32"
    """Encoder compute dtype while training: fp32 | bf16 (torch.autocast on the policy's device, CPU or
    CUDA; the GRU, the heads and the weights stay float32, so checkpoints do not depend on it)."""
    channels_last: bool = False
    """Conv weights and encoder inputs in channels-last (NHWC) memory format (faster convolutions on
    recent GPUs and CPUs; results equal up to float rounding)."""
    compile: bool = False
    """torch.compile the encoder (pays on CUDA for long runs; the first updates compile, seconds to a
    minute). Checkpoint keys are unchanged."""

    def __post_init__(self) -> None:
        check(self.variant in POLICY_VARIANTS, "agent.variant", self.variant, " | ".join(POLICY_VARIANTS))
        check(self.precision in POLICY_PRECISIONS, "agent.precision", self.precision, " | ".join(POLICY_PRECISIONS))
        check(self.hidden_size >= 1, "agent.hidden_size", self.hidden_size, "a positive size")
        check(self.downsample >= 1, "agent.downsample", self.downsample, "a positive integer factor")
        check(
            self.fine_shifts == 0 or (self.fine_shifts > 0 and self.variant in FINE_VARIANTS),
            "agent.fine_shifts", self.fine_shifts,
            "0 (off), or a positive number of pixels with variant=" + " | ".join(FINE_VARIANTS),
        )
        check(self.fine_scales >= 1, "agent.fine_scales", self.fine_scales, "a positive number of pyramid levels")
        check(self.revisit_row_stride >= 0, "agent.revisit_row_stride", self.revisit_row_stride, "0 (off) or a number of steps")
        # (that they need the row search is checked where it is built: the stride may come from a checkpoint's run)
        check(self.revisit_row_after >= 0, "agent.revisit_row_after", self.revisit_row_after, "0 or a number of steps")
        check(self.revisit_row_budget >= 0, "agent.revisit_row_budget", self.revisit_row_budget, "0 or a number of steps")
        check(self.revisit_near_rows >= 0, "agent.revisit_near_rows", self.revisit_near_rows, "0 (off) or a number of rows")
        check(self.revisit_near_penalty > 0, "agent.revisit_near_penalty", self.revisit_near_penalty, "a positive number of logit units")
        check(self.revisit_near_age >= 1, "agent.revisit_near_age", self.revisit_near_age, "a number of steps >= 1")
        check(self.revisit_near_since >= 0, "agent.revisit_near_since", self.revisit_near_since, "0 or a number of steps")
        check(self.revisit_near_until is None or (0 < self.revisit_near_until < 1 and self.refine_min_near is not None),
              "agent.revisit_near_until", self.revisit_near_until,
              "null, or a probability in (0, 1) with agent.refine_min_near (the stop-offset net's near check)")
        check(self.refine_moves >= 1, "agent.refine_moves", self.refine_moves, "a positive number of moves")
        check(self.refine_model is None or self.refine_stop, "agent.refine_model", self.refine_model,
              "null, or a stop-offset file with agent.refine_stop=true")
        check(0 < self.refine_min_stay <= 1, "agent.refine_min_stay", self.refine_min_stay, "a probability in (0, 1]")
        check(self.refine_min_near is None or (0 < self.refine_min_near < 1 and self.refine_model is not None),
              "agent.refine_min_near", self.refine_min_near,
              "null, or a probability in (0, 1) with agent.refine_model (a stop-offset net with the near output)")
        check(self.refine_near_model is None or self.refine_min_near is not None, "agent.refine_near_model",
              self.refine_near_model, "null, or a stop-offset file with the near output with agent.refine_min_near")
        check(self.stop_prob is None or 0 < self.stop_prob <= 1, "agent.stop_prob", self.stop_prob,
              "null or a probability in (0, 1]")
        check(self.stop_min_prob is None or 0 < self.stop_min_prob <= 1, "agent.stop_min_prob", self.stop_min_prob,
              "null or a probability in (0, 1]")
        check(self.stop_min_prob is None or self.stop_prob is None or self.stop_min_prob <= self.stop_prob,
              "agent.stop_min_prob", self.stop_min_prob, f"at most agent.stop_prob={self.stop_prob}")
        check(self.stop_near_prob is None or (0 < self.stop_near_prob <= 1 and self.refine_min_near is not None),
              "agent.stop_near_prob", self.stop_near_prob,
              "null, or a probability in (0, 1] with agent.refine_min_near (the stop-offset net's near check)")
        check(self.stop_near_prob is None or self.stop_prob is None or self.stop_near_prob < self.stop_prob,
              "agent.stop_near_prob", self.stop_near_prob, f"below agent.stop_prob={self.stop_prob}")
        check(self.stop_near_min_near is None or (self.stop_near_prob is not None
                                                 and self.refine_min_near <= self.stop_near_min_near < 1),
              "agent.stop_near_min_near", self.stop_near_min_near,
              f"null, or a probability in [agent.refine_min_near={self.refine_min_near}, 1) with agent.stop_near_prob")
        check(self.stop_by >= 0, "agent.stop_by", self.stop_by, "0 (off) or a step number (T)")
        check(not self.stop_by_phase or self.stop_by > 0, "agent.stop_by", self.stop_by,
              "a step number (T) with agent.stop_by_phase=true")
        check(self.mirror_steps >= 0, "agent.mirror_steps", self.mirror_steps, "0 (off) or a number of policy steps")
        check(self.wide_match_steps >= 0, "agent.wide_match_steps", self.wide_match_steps,
              "0 (every step) or a number of policy steps")
        check(0.0 <= self.wide_match_min_peak < 1.0, "agent.wide_match_min_peak", self.wide_match_min_peak,
              "a ZNCC in [0, 1) (0 = no threshold)")
        check(0.0 <= self.wide_match_turn < 1.0, "agent.wide_match_turn", self.wide_match_turn,
              "a ZNCC in [0, 1) (0 = off)")
        check(not self.wide_match_turn or self.wide_match_steps > 0, "agent.wide_match_steps", self.wide_match_steps,
              f"a number of policy steps > 0 with agent.wide_match_turn={self.wide_match_turn} (the rule reads the "
              f"wide match in an episode's first steps only)")
        check(0 < self.fov < 180, "agent.fov", self.fov, "degrees in (0, 180)")
        check(self.revisit_penalty >= 0, "agent.revisit_penalty", self.revisit_penalty, "0 (off) or a positive number of logit units")
        check(not self.memory_inputs or self.revisit_penalty > 0, "agent.revisit_penalty", self.revisit_penalty,
              "a positive number of logit units with agent.memory_inputs=true (the network reads the search memory)")


#: keys that moved: the old spelling -> the new key (a one-line message names the new one)
MOVED_KEYS: dict[str, str] = {f"agent.{f.name}": f"trainer.ppo.{f.name}" for f in dataclass_fields(PPOConfig)}


# ------------------------------------------------------------------------------------------------
# Training
# ------------------------------------------------------------------------------------------------


ALGORITHMS = ("ppo", "dagger")


@dataclass
class TrainerConfig:
    """The training run (``trainer`` group): algorithm, size, validation, checkpoints, logging."""

    algorithm: str = "ppo"
    """ppo (hyper-parameters: trainer.ppo) | dagger (trainer.dagger). The section of the algorithm that does not
    run must keep its defaults (a value set there would silently do nothing, so it is refused)."""
    num_updates: int = 30000
    """Total updates ("full" = 30000, "half" = 15000); drives lr / clip decay and the scheduler."""
    num_envs: int = 16
    """Environments stepped together."""
    seed: int = 0
    """Seeds torch / numpy / random, the episode sampler and the mini-batch shuffles."""
    val_interval: int = 1000
    """Validate every this many updates (0: only at the end, see val_at_end)."""
    val_at_end: bool = True
    """Validate after the last update."""
    val_episodes: Optional[int] = None
    """Cap on val episodes (spread evenly over the difficulties); null = all."""
    val_num_envs: Optional[int] = None
    """Environments for validation; null = num_envs."""
    val_max_steps: Optional[int] = None
    """Step limit T of validation episodes; null = task.max_steps."""
    log_interval: int = 10
    """TensorBoard scalars every this many updates."""
    checkpoint_interval: int = 100
    """Write checkpoints/latest.pth every this many updates (and at every validation and the end)."""
    keep_val_checkpoints: bool = False
    """Also keep the weights of every validation as checkpoints/val_u<update>.pth (to choose among them on a
    larger val set than the trainer's; about 4 MB each for the robust preset)."""
    resume: bool = True
    """Continue from checkpoints/latest.pth of the run folder if it exists."""
    stop_after: Optional[int] = None
    """Stop this session after this many updates (latest.pth written; re-run to continue)."""
    progress: bool = True
    """tqdm progress bar."""
    torch_threads: Optional[int] = None
    """CPU threads for torch (null: findview's policy, see findview.runtime)."""
    ppo: PPOConfig = field(default_factory=PPOConfig)
    """PPO hyper-parameters (used when algorithm=ppo)."""
    dagger: DAggerConfig = field(default_factory=DAggerConfig)
    """DAgger hyper-parameters (used when algorithm=dagger)."""
    distributed: bool = False
    """Train with several processes started by torchrun (DD-PPO: gradients averaged over ranks; num_envs is
    per rank, rank r of K takes train images r::K; rank 0 writes every file). See docs/CLUSTER.md."""
    dist_backend: str = "auto"
    """torch.distributed backend of trainer.distributed: auto (nccl on CUDA, gloo on CPU) | nccl | gloo."""
    dist_timeout_min: float = 60.0
    """Minutes a rank may wait for the others (rank 0 validates alone meanwhile) before the job fails."""
    preempt_fraction: float = 0.0
    """DD-PPO straggler preemption (PPO under torchrun): once this fraction of the ranks has collected its
    rollout, the others stop collecting (after at least 25% of it); 0 = off, e.g. 0.6."""

    def __post_init__(self) -> None:
        check(self.algorithm in ALGORITHMS, "trainer.algorithm", self.algorithm, " | ".join(ALGORITHMS))
        self._check_idle_section()
        check(self.num_updates >= 1, "trainer.num_updates", self.num_updates, "a positive number of updates")
        check(self.num_envs >= 1, "trainer.num_envs", self.num_envs, "a positive number of environments")
        for key in ("val_interval", "log_interval", "checkpoint_interval"):
            value = getattr(self, key)
            check(value >= 0, f"trainer.{key}", value, "0 or a positive number of updates")
        check(self.dist_backend in ("auto", "nccl", "gloo"), "trainer.dist_backend", self.dist_backend,
              "auto | nccl | gloo")
        check(self.dist_timeout_min > 0, "trainer.dist_timeout_min", self.dist_timeout_min, "a positive number of minutes")
        check(0.0 <= self.preempt_fraction <= 1.0, "trainer.preempt_fraction", self.preempt_fraction,
              "a fraction of the ranks in [0, 1] (0 = off)")
        for key in ("val_episodes", "val_num_envs", "val_max_steps", "stop_after", "torch_threads"):
            value = getattr(self, key)
            check(value is None or value >= 1, f"trainer.{key}", value, "null or a positive integer")


    def _check_idle_section(self) -> None:
        """Refuse a value set in the section of the algorithm that does not run (``trainer.ppo.*`` with
        ``algorithm=dagger`` and the other way round), naming the first such key."""
        idle = "dagger" if self.algorithm == "ppo" else "ppo"
        section, default = getattr(self, idle), type(getattr(self, idle))()
        for f in dataclass_fields(default):
            value = getattr(section, f.name)
            if value != getattr(default, f.name):
                other = f"trainer.{self.algorithm}.{f.name}" if hasattr(getattr(self, self.algorithm), f.name) else \
                    f"trainer.{self.algorithm}.*"
                raise ConfigError(
                    f"trainer.{idle}.{f.name}={value!r} is set but trainer.algorithm={self.algorithm} does not use "
                    f"trainer.{idle}.*: drop it, set {other}, or train with trainer={idle}"
                )


@dataclass
class SchedulerConfig:
    """Difficulty curriculum (``scheduler``): level up every num_updates / num_levels updates."""

    mode: str = "unbounded"
    """unbounded (paper: level k mixes the first k difficulties) | bounded (level k: only the k-th)."""
    num_levels: int = 3
    """Levels (1: easy only; 3: easy -> medium -> hard)."""
    start_level: int = 1
    """The level of the first update (a run from `init_from` can start at 3: hard episodes from the first
    update); the remaining levels share the updates equally."""

    def __post_init__(self) -> None:
        check(self.mode in ("unbounded", "bounded"), "scheduler.mode", self.mode, "unbounded | bounded")
        check(1 <= self.num_levels <= 3, "scheduler.num_levels", self.num_levels, "1, 2 or 3")
        check(1 <= self.start_level <= self.num_levels, "scheduler.start_level", self.start_level,
              f"a level from 1 to scheduler.num_levels={self.num_levels}")


# ------------------------------------------------------------------------------------------------
# Tools
# ------------------------------------------------------------------------------------------------


@dataclass
class TrainConfig:
    """``tools/train.py``."""

    dataset: DatasetConfig = MISSING
    sim: SimConfig = MISSING
    task: TaskConfig = MISSING
    corruption: CorruptionConfig = MISSING
    agent: Any = MISSING
    trainer: TrainerConfig = MISSING
    scheduler: SchedulerConfig = field(default_factory=SchedulerConfig)
    init_from: Optional[str] = None
    """Checkpoint to start from: weights only (model signature checked), fresh optimizer."""


@dataclass
class EvalConfig:
    """``tools/eval.py``."""

    dataset: DatasetConfig = MISSING
    sim: SimConfig = MISSING
    task: TaskConfig = MISSING
    corruption: CorruptionConfig = MISSING
    agent: Any = MISSING
    split: str = "test"
    """val | test: runs <dataset.out_dir>/episodes/<split>_fov<sim.fov>.json."""
    episodes: Optional[str] = None
    """An explicit episode file instead (dataset.out_dir and split are then ignored)."""
    difficulty: Optional[str] = None
    """null = easy, medium and hard; or one of easy | medium | hard."""
    max_episodes: Optional[int] = None
    """Only the first N episodes (after the difficulty filter)."""
    num_envs: int = 16
    """Episodes run in parallel (results do not depend on it)."""
    seed: int = 0
    """Agent seed (agents derive one random stream per episode from it)."""
    checkpoint: Optional[str] = None
    """A learned-agent checkpoint to evaluate (implies agent=ppo; view size, FoV and model come from it
    unless overridden on the command line)."""
    video: int = 0
    """Render the first N episodes as MP4 (current view | target | panorama)."""
    video_fps: float = 30.0
    """Frames per second of the videos."""
    video_pano_height: Optional[int] = None
    """Panorama strip height in the videos, pixels (null: the view height)."""
    trace: bool = False
    """Also write traces.jsonl beside episodes.jsonl, one line per episode in the same order: {"episode_id", "pitch",
    "yaw", "action", "stop_prob"}, each a list with one entry per step: the pose before the step's action (integer
    degrees), the action (UP=0, DOWN=1, LEFT=2, RIGHT=3, STOP=4) and the probability the agent's network gave STOP
    (null for agents without one, the rule-based ones). For the learned agent that is softmax(logits)[STOP] of the
    network's own distribution, before the search memory: the distribution it acted from when
    agent.revisit_penalty=0; with the memory on, the one that decides STOP (the memory lowers only the moves and
    keeps the network's STOP decision, giving STOP probability 0 or 1 itself), the one agent.stop_prob and
    agent.stop_by compare. null at a step the network did not decide (a stop being refined, a stop_by walk back).
    Costs one device-to-host copy per step."""
    progress: bool = True
    """tqdm progress bar (counts episodes and steps)."""
    torch_threads: Optional[int] = None
    """CPU threads for torch (null: findview's policy, see findview.runtime)."""

    def __post_init__(self) -> None:
        check(self.split in ("train", "val", "test"), "split", self.split, "val | test (or train)")
        check(self.difficulty in (None, *DIFFICULTY_NAMES), "difficulty", self.difficulty, "null | easy | medium | hard")
        check(self.max_episodes is None or self.max_episodes >= 1, "max_episodes", self.max_episodes, "null or >= 1")
        check(self.num_envs >= 1, "num_envs", self.num_envs, "a positive number of environments")
        check(self.video >= 0, "video", self.video, "0 or a number of episodes")
        check(self.torch_threads is None or self.torch_threads >= 1, "torch_threads", self.torch_threads, "null or >= 1")


@dataclass
class MakeDatasetConfig:
    """``tools/make_dataset.py``."""

    dataset: DatasetConfig = MISSING
    sim: SimConfig = MISSING
    force: bool = True
    """Rebuild splits and episodes even when matching files exist."""
    progress: bool = True
    """tqdm progress bars."""


@dataclass
class RenderEpisodeConfig:
    """``tools/render_episode.py``."""

    dataset: DatasetConfig = MISSING
    sim: SimConfig = MISSING
    task: TaskConfig = MISSING
    split: str = "test"
    """Episode file <dataset.out_dir>/episodes/<split>_fov<sim.fov>.json."""
    episodes: Optional[str] = None
    """Or an explicit episode file."""
    episode_index: int = 0
    """Which episode of the file (0-based)."""
    image: Optional[str] = None
    """Explicit mode: a panorama file ..."""
    init: Optional[list[int]] = None
    """... with [pitch, yaw] of the initial view, degrees ..."""
    target: Optional[list[int]] = None
    """... and [pitch, yaw] of the target view, degrees."""
    out: Optional[str] = None
    """PNG path (null: <run folder>/<episode id>.png)."""
    pano_height: Optional[int] = None
    """Panorama height in the picture, pixels (null: twice the view height)."""
    labels: bool = True
    """Caption the two views."""


@dataclass
class RenderCorruptionsConfig:
    """``tools/render_corruptions.py``: one target image under all 16 corruptions."""

    dataset: DatasetConfig = MISSING
    sim: SimConfig = MISSING
    task: TaskConfig = MISSING
    split: str = "test"
    """Episode file to take the target from."""
    episode_index: int = 0
    """Which episode's target (0-based)."""
    image: Optional[str] = None
    """Or a panorama file ..."""
    target: Optional[list[int]] = None
    """... and the [pitch, yaw] of the view to corrupt, degrees."""
    severity: int = 3
    """Severity 1-5."""
    seed: int = 0
    """Seed of the random corruptions."""
    out: Optional[str] = None
    """PNG path (null: <run folder>/corruptions_s<severity>.png)."""

    def __post_init__(self) -> None:
        check(1 <= self.severity <= 5, "severity", self.severity, "an integer 1-5")


def _describe_expected(msg: str) -> str:
    """Turn OmegaConf's wording into "expected ..." (for the one-line error)."""
    low = msg.lower()
    for word, text in (
        ("integer", "an integer"),
        ("float", "a number"),
        ("bool", "true or false"),
        ("enum", "one of the allowed names"),
        ("string", "a string"),
    ):
        if f"converted to {word}" in low or f"to {word}" in low:
            return text
    return ""


def config_error_line(err: BaseException) -> str:
    """One line naming the key, the value and what was expected, from a Hydra / OmegaConf error chain."""
    from omegaconf.errors import ConfigKeyError, OmegaConfBaseException, ValidationError

    chain: list[BaseException] = []
    e: BaseException | None = err
    while e is not None and len(chain) < 8:
        chain.append(e)
        e = e.__cause__ or e.__context__
    for e in chain:
        if isinstance(e, ConfigError):
            return str(e)
        missing = getattr(e, "missing_cfg_file", None)
        if missing is not None and getattr(e, "options", None) is not None:  # hydra MissingConfigException
            group, _, name = str(missing).rpartition("/")
            valid = sorted(o for o in e.options if not o.startswith("base_"))
            return f"unknown {group or 'config'} {name!r}; valid: {', '.join(valid)}"
    for e in chain:
        if isinstance(e, OmegaConfBaseException):
            key = getattr(e, "full_key", None) or ""
            first = str(e).strip().splitlines()[0] if str(e).strip() else type(e).__name__
            if isinstance(e, ConfigKeyError) or "not in" in first:
                if key in MOVED_KEYS:
                    return f"{key} is now {MOVED_KEYS[key]} (the trainer section holds how the agent is trained)"
                parent = key.rsplit(".", 1)[0] if "." in key else "the config"
                return f"unknown key {key!r}: not a key of {parent} (check the spelling; the schemas in findview/config.py and findview_baselines/config.py list every key)"
            if isinstance(e, ValidationError):
                value = None
                if "'" in first:
                    parts = first.split("'")
                    value = parts[1] if len(parts) > 2 else None
                expected = _describe_expected(first)
                if key and value is not None and expected:
                    return f"{key}={value!r}: expected {expected}"
                return f"{key}: {first}" if key else first
            return f"{key}: {first}" if key and key not in first else first
    text = " ".join(str(err).split())
    return text or type(err).__name__


CONFIG_DIR = Path(__file__).resolve().parents[1] / "configs"


def run_name_from_checkpoint(path: str) -> str:
    """A folder name for a checkpoint: ``<run folder>-<file stem>`` for ``<run>/checkpoints/<f>.pth``,
    else the file stem (``pretrained/cpu_agent.pth`` -> ``cpu_agent``)."""
    p = Path(str(path))
    if p.parent.name == "checkpoints" and p.parent.parent.name:
        return f"{p.parent.parent.name}-{p.stem}"
    return p.stem


def _eval_run_name(agent_choice: Any, checkpoint: Any) -> str:
    return run_name_from_checkpoint(str(checkpoint)) if checkpoint not in (None, "", "None") else str(agent_choice)


def register_resolvers() -> None:
    """OmegaConf resolvers used by the tool configs (idempotent)."""
    if not OmegaConf.has_resolver("eval_run_name"):
        OmegaConf.register_new_resolver("eval_run_name", _eval_run_name)


def compose_config(config_name: str, overrides: Sequence[str] = (), return_hydra_config: bool = False) -> DictConfig:
    """Compose a tool's config like the tool does (for tests, notebooks and the pre-check)."""
    from hydra import compose, initialize_config_dir

    register_configs()
    register_resolvers()
    with initialize_config_dir(str(CONFIG_DIR), version_base="1.3"):
        return compose(config_name, overrides=list(overrides), return_hydra_config=return_hydra_config)


def typed_config(cfg: Any) -> Any:
    """The validated object tree of a composed config (its ``hydra`` node dropped): the schemas' dataclasses,
    their range checks run. An object tree is returned as it is.

    Raises:
        ConfigError: a wrong value, naming the key (one line).
    """
    from omegaconf import DictConfig, OmegaConf

    if not isinstance(cfg, DictConfig):
        return cfg
    if "hydra" in cfg:
        from omegaconf import open_dict

        cfg = cfg.copy()  # dropped from a copy: the primary schema (the type of the tree's root) stays
        with open_dict(cfg):
            del cfg["hydra"]
    try:
        return OmegaConf.to_object(cfg)
    except ConfigError:
        raise
    except Exception as err:  # an interpolation or conversion problem: name the key
        raise ConfigError(config_error_line(err)) from None


_REGISTERED = False


def register_configs() -> None:
    """Store every schema in Hydra's ConfigStore. Idempotent; called by the tools before composing.

    The group schemas go to the root as ``base_<name>`` (not options of their group, so ``--help`` and
    the "valid:" lists show only the YAML files); the group files name them as ``/base_<name>@_here_``."""
    global _REGISTERED
    if _REGISTERED:
        return
    from hydra.core.config_store import ConfigStore

    register_core_configs()
    cs = ConfigStore.instance()
    cs.store(name="base_random", node=RandomAgentConfig)
    cs.store(name="base_oracle", node=OracleAgentConfig)
    cs.store(name="base_feature", node=FeatureAgentConfig)
    cs.store(name="base_rotation", node=RotationAgentConfig)
    cs.store(name="base_ppo", node=PPOAgentConfig)
    cs.store(name="base_trainer", node=TrainerConfig)
    cs.store(name="train_schema", node=TrainConfig)
    cs.store(name="eval_schema", node=EvalConfig)
    cs.store(name="make_dataset_schema", node=MakeDatasetConfig)
    cs.store(name="render_episode_schema", node=RenderEpisodeConfig)
    cs.store(name="render_corruptions_schema", node=RenderCorruptionsConfig)
    _REGISTERED = True


__all__ += ["ConfigError"]
