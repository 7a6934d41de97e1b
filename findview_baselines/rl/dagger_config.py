"""The hyper-parameters of DAgger (``trainer=dagger``): :class:`DAggerConfig` (validated on construction)
and the oracle-execution schedule :func:`beta_at` (the probability of executing the oracle's action at an
update). The trainer that uses them is ``dagger.py``."""

from __future__ import annotations

from dataclasses import dataclass
from typing import Optional

from findview.config import ConfigError
from findview.task.oracle import ORDERS, SEARCH_PRIORS

__all__ = ["DAggerConfig", "LABEL_MODES", "beta_at"]

LABEL_MODES = ("action", "set")
#: trainer.dagger.row_done_labels choices
ROW_DONE_LABELS = ("target", "rows")
#: trainer.dagger.penalised_loss choices
PENALISED_LOSSES = ("none", "moves", "rows")


@dataclass
class DAggerConfig:
    """DAgger hyper-parameters (``trainer=dagger``). Units: steps are environment steps of one env."""

    lr: float = 1e-3
    """Adam learning rate."""
    adam_eps: float = 1e-5
    """Adam epsilon."""
    max_grad_norm: float = 1.0
    """Gradient norm clip (over the policy and the aux head)."""
    linear_decay: bool = False
    """Decay the learning rate linearly to 0 over the run's ``total_updates``."""
    rollout_steps: int = 32
    """Steps per environment per update (a multiple of ``seq_len``)."""
    seq_len: int = 16
    """Length (steps) of the sequences the GRU trains on; chunks of the rollout go into the buffer."""
    buffer_size: int = 16384
    """Buffer capacity in labelled steps (``buffer_size // seq_len`` chunks, FIFO)."""
    epochs: float = 4.0
    """Gradient steps per update = ceil(epochs * new chunks / batch_sequences): on average each new chunk is
    used ``epochs`` times while it is the newest data (older chunks keep being sampled)."""
    batch_sequences: int = 16
    """Chunks per mini-batch (``batch_sequences * seq_len`` labelled steps)."""
    beta_start: float = 1.0
    """Probability (per env, per step) of executing the oracle's label instead of the learner's action at
    update 0."""
    beta_end: float = 0.0
    """That probability from update ``beta_decay_updates`` on."""
    beta_decay_updates: int = 60
    """Updates over which beta falls linearly from ``beta_start`` to ``beta_end`` (0: ``beta_end`` at once)."""
    stop_weight: float = 1.0
    """Cross-entropy class weight of ``stop`` (the four moves weigh 1): above 1 penalises missed stops more."""
    search_weight: float = 1.0
    """Loss weight of the steps where view and target do not overlap (the search prior's labels; 1 = as
    any step). Hard episodes are long, so at the last curriculum level most labelled steps are "pan right":
    below 1 keeps them from drowning the few steps that find and stop on the target."""
    search_prior: str = "pan"
    """Labels where view and target do not overlap: ``pan`` (pan right until they do), ``sweep`` (match
    pitch, then pan right) or ``oracle`` (the true shortest path, which a learner cannot see)."""
    search_pitch_band: float = 1.0
    """``pan`` prior: where the views do not overlap, move the pitch towards the target while ``|dpitch|`` exceeds
    this fraction of the FoV, and pan right from there (1: pan at any pitch the views can overlap at; 0.5: pan
    only within half a FoV of the target's pitch, so the pan meets the target with at least half of it in view)."""
    search_yaw_band: float = 1.0
    """``pan`` prior: the target counts as in sight (oracle labels) only while ``|dyaw|`` is at most this fraction of
    the FoV (and ``|dpitch| <= fov``); further to the side the labels pan right. 1: wherever the views overlap at all,
    also by a strip of a few degrees, where a learner cannot see the target and is asked to turn back towards it
    (``findview.task.oracle``, "yaw band"). The steps outside the band weigh ``search_weight``."""
    search_yaw_band_after: float = 0.0
    """With ``agent.memory_inputs`` and ``search_yaw_band`` < 1: the band applies only once the search is under way in
    the current row, i.e. once the search memory has seen at least this many FoVs of yaw there (its second input, the
    share of a turn seen around the current row, times 360 degrees); before that (the episode's start, a row just
    reached) the labels use band 1 and turn towards any target that overlaps the view. 0: the band applies
    everywhere. Measured once (0.5 with band 0.5, FoV 90, benchmarks/RESULTS.md "Session 26"): easy SPL back to band
    1's, but wrong stops on a clean forest panorama; no preset uses it."""
    row_done_band: float = 0.25
    """``pan`` prior with a policy that reads its search memory (``agent.memory_inputs``): once the memory says the
    current row has been looked around, the labels move the pitch towards the target while ``|dpitch|`` exceeds
    this fraction of the FoV (then pan again)."""
    row_done_labels: str = "target"
    """With ``agent.memory_inputs`` and the ``pan`` prior, the label where the current row is done and the views do not
    overlap: ``target`` moves the pitch towards the target (``row_done_band``); ``rows`` moves to the next search row
    the memory has not looked around, ``+s, -s, +2s, -2s`` from the start (``s`` half a FoV), the first of a ring on
    the target's side of the start: apart from that one side, the whole search is a function of the network's
    inputs."""
    first_steps: int = 0
    """The first ``first_steps`` steps of every episode (env steps 0 .. first_steps - 1) have their loss weight
    multiplied by ``first_steps_weight``. The first moves decide which way round the agent goes, and they are a
    handful of an episode's hundred-odd labelled steps; 0 = off."""
    first_steps_weight: float = 1.0
    """The factor on the first ``first_steps`` steps' loss weight (times ``search_weight`` where the views do not
    overlap)."""
    first_steps_turn: bool = False
    """With ``first_steps``: in those steps, where the views overlap and the target is off in yaw, the label is the
    yaw move towards it alone (``LEFT`` or ``RIGHT``), not every shortest-path move (``labels=set`` lets a first step
    move the pitch instead), and the oracle executes it: the network has to say which way round at the start, while
    the wide match speaks (``agent.wide_match_steps``)."""
    memory_warm_start: float = 0.0
    """With ``agent.memory_inputs``: the share of new training episodes whose search memory starts as if the agent
    had already looked around its start row a full turn, so the labels ask it to leave the row from the first step
    (a state a learner otherwise meets only after a missed turn, 300+ steps into an episode). 0 = off."""
    penalised_loss: str = "none"
    """With the search memory (``agent.revisit_penalty > 0``): which steps' loss reads the move logits as the agent
    acts on them, less the memory's penalty (``penalty x`` earlier visits of each move's destination), so that their
    label teaches a margin that beats the penalty. ``none``: no step (the loss reads the network's logits);
    ``moves``: every step not labelled STOP (STOP-labelled steps keep the network's logits: the agent's stop
    decision reads those); ``rows``: only the steps whose label leaves a looked-around row for the next search row
    (``row_done_labels=rows``), the moves that cross rows seen before. Measured once each (benchmarks/RESULTS.md,
    "Session 21"), neither helped: a fine-tune with ``moves`` stopped in 57-70% of the trainer's val episodes
    against 83-90% without (abandoned at update 300); one with ``rows`` ended worse on the corrupted val sets."""
    order: str = "pitch_first"
    """Axis order of the oracle's executed actions (and of the labels with ``labels=action``):
    ``pitch_first``, ``yaw_first`` or ``larger_first``."""
    labels: str = "action"
    """``action``: the oracle's one action (cross-entropy); ``set``: any shortest-path action is right
    (likelihood of the set)."""
    sample_actions: bool = False
    """The learner executes sampled actions (true) or its argmax, as at evaluation (false)."""
    aux_coef: float = 0.0
    """Weight of the auxiliary rotation / overlap loss (0 = off)."""
    train_only: Optional[list[str]] = None
    """Train only these parts of the policy: names of its modules (prefixes of parameter names, e.g. ``[wide_proj]``,
    ``[wide_proj, actor]``); the other weights keep the values ``init_from`` gave them. null = every weight. The
    auxiliary head (``aux_coef``) trains either way. For a zero-started input (``agent.wide_match``) added to a
    finished agent: a higher learning rate there cannot disturb what the rest has learned."""
    save_buffer: bool = True
    """Store the buffer in ``state_dict`` (exact resume, large checkpoints); false: a resume refills it."""
    cache_fixed_features: bool = True
    """Policies whose encoder begins with parameter-free comparisons (``direct``, ``robust``, ``phase``):
    compute that part once per step, when the learner acts in the rollout, and keep it in the buffer for every
    gradient step
    (the same loss; 3.4x faster updates of the robust preset on a CPU; 5 KB per buffered step). Ignored by the others."""
    overlap_rollout: bool = False
    """Collect each update's rollout in a second thread while its gradient steps train on the buffer (two CPU
    cores, or a GPU: both at once instead of one after the other). The rollout acts with the weights from before
    those gradient steps (as without overlap), and its chunks enter the buffer after them: an update's gradient
    steps see every rollout but its own (the first update, with an empty buffer, runs one after the other). A stop
    request is honoured before an update, not during its rollout. Deterministic (the same run gives the same
    weights), but not the weights of ``false``. The trainer's ``time/*`` phases then overlap (their sum exceeds the
    wall time). Not under torchrun."""

    def __post_init__(self) -> None:
        positive = ("lr", "rollout_steps", "seq_len", "buffer_size", "batch_sequences", "epochs")
        for name in positive:
            if not getattr(self, name) > 0:
                raise ConfigError(f"trainer.dagger.{name} must be positive, got {getattr(self, name)!r}")
        if self.rollout_steps % self.seq_len:
            raise ConfigError(
                f"trainer.dagger.rollout_steps ({self.rollout_steps}) must be a multiple of trainer.dagger.seq_len ({self.seq_len})"
            )
        if self.buffer_size < self.seq_len:
            raise ConfigError(
                f"trainer.dagger.buffer_size ({self.buffer_size}) must hold one sequence of {self.seq_len} steps"
            )
        for name in ("beta_start", "beta_end"):
            if not 0.0 <= getattr(self, name) <= 1.0:
                raise ConfigError(f"trainer.dagger.{name} must be in [0, 1], got {getattr(self, name)!r}")
        if self.beta_decay_updates < 0:
            raise ConfigError(f"trainer.dagger.beta_decay_updates must be >= 0, got {self.beta_decay_updates}")
        if self.search_weight <= 0:
            raise ConfigError(f"trainer.dagger.search_weight must be positive, got {self.search_weight!r}")
        if self.first_steps_turn and not self.first_steps:
            raise ConfigError("trainer.dagger.first_steps_turn=true labels an episode's first_steps steps: it needs "
                              "trainer.dagger.first_steps > 0, got 0")
        if self.first_steps < 0:
            raise ConfigError(f"trainer.dagger.first_steps must be >= 0 env steps (0 = off), got {self.first_steps!r}")
        for name in ("stop_weight", "max_grad_norm", "first_steps_weight"):
            if not getattr(self, name) > 0:
                raise ConfigError(f"trainer.dagger.{name} must be positive, got {getattr(self, name)!r}")
        if self.train_only is not None and (not self.train_only or not all(isinstance(n, str) and n for n in self.train_only)):
            raise ConfigError(f"trainer.dagger.train_only must be null (every weight) or a non-empty list of module names, "
                              f"got {self.train_only!r}")
        if self.aux_coef < 0:
            raise ConfigError(f"trainer.dagger.aux_coef must be 0 (off) or positive, got {self.aux_coef!r}")
        if self.search_prior not in SEARCH_PRIORS:
            raise ConfigError(f"trainer.dagger.search_prior must be one of {SEARCH_PRIORS}, got {self.search_prior!r}")
        if not 0.0 <= self.search_pitch_band <= 1.0:
            raise ConfigError(
                f"trainer.dagger.search_pitch_band must be in [0, 1] (a fraction of the FoV), got {self.search_pitch_band!r}"
            )
        if not 0.0 < self.search_yaw_band <= 1.0:
            raise ConfigError(
                f"trainer.dagger.search_yaw_band must be in (0, 1] (a fraction of the FoV), got {self.search_yaw_band!r}"
            )
        if self.search_yaw_band < 1.0 and self.search_prior != "pan":
            raise ConfigError(f"trainer.dagger.search_yaw_band={self.search_yaw_band} shapes the 'pan' search prior "
                              f"only, got search_prior={self.search_prior!r}")
        if not 0.0 <= self.search_yaw_band_after <= 4.0:
            raise ConfigError(f"trainer.dagger.search_yaw_band_after must be in [0, 4] (FoVs of yaw seen in the row), "
                              f"got {self.search_yaw_band_after!r}")
        if self.search_yaw_band_after > 0 and self.search_yaw_band == 1.0:
            raise ConfigError(f"trainer.dagger.search_yaw_band_after={self.search_yaw_band_after} delays the yaw band: "
                              f"it needs trainer.dagger.search_yaw_band < 1")
        for name in ("row_done_band", "memory_warm_start"):
            if not 0.0 <= getattr(self, name) <= 1.0:
                raise ConfigError(f"trainer.dagger.{name} must be in [0, 1], got {getattr(self, name)!r}")
        if self.penalised_loss not in PENALISED_LOSSES:
            raise ConfigError(f"trainer.dagger.penalised_loss must be one of {PENALISED_LOSSES}, got {self.penalised_loss!r}")
        if self.row_done_labels not in ROW_DONE_LABELS:
            raise ConfigError(f"trainer.dagger.row_done_labels must be one of {ROW_DONE_LABELS}, got {self.row_done_labels!r}")
        if self.labels not in LABEL_MODES:
            raise ConfigError(f"trainer.dagger.labels must be one of {LABEL_MODES}, got {self.labels!r}")
        if self.order not in ORDERS:
            raise ConfigError(f"trainer.dagger.order must be one of {ORDERS}, got {self.order!r}")


def beta_at(cfg: DAggerConfig, update: int) -> float:
    """Oracle-execution probability at ``update`` (0-based): linear from ``beta_start`` to ``beta_end``."""
    if cfg.beta_decay_updates <= 0:
        return cfg.beta_end
    frac = min(1.0, update / cfg.beta_decay_updates)
    return cfg.beta_start + (cfg.beta_end - cfg.beta_start) * frac
