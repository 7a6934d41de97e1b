"""A trained PPO policy (``findview_baselines.rl``) behind the batched :class:`Agent` interface.

- The model is rebuilt from the checkpoint's own signature (``variant``, ``hidden_size``, ``height``,
  ``width``), so no model config is needed. The simulator may render the checkpoint's view size or an
  integer multiple ``k`` of it (e.g. 256x256 for a 64x64 network): the agent then averages each ``k x k``
  block of the view and the target (:func:`area_downsample`), so it sees the same images as an agent
  working at full size, corruptions included (a corruption's kernel is in pixels of the image it is
  applied to: at 64x64 the same severity destroys four times more of the picture). Another size fails
  with a message naming both.
- The GRU state of a slot is zeroed by ``reset(env_ids, ...)`` (a new episode starts there).
- Actions are greedy (argmax of the logits) by default; ``sample=True`` draws them from the policy's
  distribution with one random stream per episode (seeded from the agent seed and the episode's id),
  so a trajectory does not depend on which slot or batch the episode ran in.
- A slot that answered STOP keeps answering STOP without running the network until it is reset.
- ``refine_stop=true`` checks each stop: when phase correlation measures the target at least half a degree
  away, the agent moves towards it first (:mod:`findview_baselines.agents.stop_refine`). A refiner with a
  stop-offset net and ``min_near`` also refuses a policy STOP whose view the net finds far from the target: the
  slot takes its most likely move instead (greedy, also with ``sample``). With ``stop_by`` a view becomes the
  slot's most stop-like pose only if the net finds it near, so the walk back never ends on a refused view.
- ``revisit_penalty > 0`` switches on a search memory (:class:`~findview_baselines.rl.search_memory.RevisitPenalty`):
  each move's logit is lowered by that many logit units per earlier visit of the pose it leads to (poses
  dead-reckoned from the agent's own actions), which breaks left/right loops. 0 (the default) is the plain policy.
  A network built with ``memory_inputs`` (in its checkpoint signature) also reads that memory's features each step
  (:meth:`~findview_baselines.rl.search_memory.RevisitPenalty.memory_features`: has it looked around its row?), and
  needs the memory on and the views' ``fov``.
- ``stop_min_prob``: a STOP the policy answers with a probability below it is refused, and the slot takes its most
  likely move instead (after the search memory's penalty), so an unsure stop on a view that only looks like the
  target does not end the episode; with ``stop_by`` the slot still comes back to its most stop-like pose if it finds
  nothing surer.
- ``stop_near_prob`` (with a refiner with ``min_near``): the slot also STOPs whenever the policy gives STOP at least
  this probability (whatever its most likely action, also below ``stop_min_prob``) and the stop-offset net finds the
  view near the target (at least ``stop_near_min_near``, default ``min_near``): a blurred target the network
  recognises only half-heartedly is then stopped on when first seen, not at the end of the episode by ``stop_by``'s
  walk back.
- ``stop_by > 0`` (needs the search memory; set it to ``T``): a slot that has not stopped when the steps left are
  just enough walks back to the dead-reckoned pose where the policy's STOP probability was highest and stops
  there (:mod:`findview_baselines.agents.give_up`), instead of running out of steps wherever it is.
  ``stop_by_phase`` (with ``stop_by``): a slot whose STOP probability never reached the walk's threshold walks
  instead to where phase correlation of view and target pointed most clearly (measured each step on the grey views
  as rendered, averaged over ``k x k`` blocks, ``k = width // 128`` where it divides the size: 256 -> 128 pixels).
- :meth:`PPOAgent.step_stop_prob` gives the policy's STOP probability of the last ``act`` (for ``tools/eval.py
  trace=true``); it is computed only when asked.

Checkpoints are read with ``torch.load(..., weights_only=True)``; the layout is the one written by the
trainer (``{"signature": {...}, "policy": state_dict, ...}``, see ``findview_baselines.rl.checkpoint``).

Importing this module registers the agent as ``ppo`` for :func:`findview_baselines.agents.make_agent`
(which then needs ``checkpoint=``, and the view size as ``height=`` / ``width=``).
"""

from __future__ import annotations

import os
from collections.abc import Mapping, Sequence
from typing import TYPE_CHECKING, Any

import numpy as np
import torch

from findview.episode import Episode
from findview.runtime import scoped
from findview.task import Action
from findview_baselines.agents.base import STOP, Agent, episode_rng
from findview_baselines.agents.give_up import GiveUp
from findview_baselines.agents.stop_refine import StopRefiner
from findview_baselines.rl.observations import area_downsample, downsample_factor
from findview_baselines.rl.policy import WIDE_ON
from findview_baselines.rl.search_memory import NearVisits, RowSearch, make_revisit_penalty, memory_band
from findview_baselines.rl.wide_match import WIDE_PEAK

if TYPE_CHECKING:
    from torch.distributions import Categorical

    from findview_baselines.config import PPOAgentConfig

__all__ = ["PPOAgent", "load_ppo_checkpoint", "mirror_mean"]

#: ``wide_match_turn``: the smallest column shift of the wide match's peak, as a fraction of the width, that sets a
#: side: 10 of the 32 columns of a 64-pixel network's wide match, a target about 28 degrees or more to the side at
#: FoV 90. The wide match is there for targets at the edge of the view; nearer ones the network's own phase
#: correlation sees, and a look-alike peak a few columns off would override it (benchmarks/RESULTS.md, "Session 52")
TURN_MIN_SHIFT = 0.3
#: action ids as seen in the left-right mirror of an episode: LEFT and RIGHT change places
MIRRORED_ACTIONS = (Action.UP, Action.DOWN, Action.RIGHT, Action.LEFT, Action.STOP)


def mirror_mean(logits: torch.Tensor, count: int, heading: torch.Tensor | None = None) -> "Categorical":
    """The action distribution of an episode and its left-right mirror played together.

    ``logits``: (2K, 5), rows ``0..K-1`` the network on the episodes, rows ``K..2K-1`` on their mirrors (views and
    targets flipped left-right), ``K = count``. Returns the Categorical of the mean of the two log-probabilities per
    episode, the mirror's LEFT and RIGHT swapped (a normalised geometric mean of the two distributions).

    ``heading``: (K,) long, each episode's last yaw move (``Action.LEFT`` / ``Action.RIGHT``; any other value:
    none yet). Where one play prefers turning back against it to going on and the other prefers going on, the one
    going on leads: the episode gets that play's log-probabilities of the four moves, and STOP keeps the mean of the
    two (stopping needs both plays; the result is normalised). (A network that learned to search by turning one way,
    say right, searches left in the mirror: once the episode turns one way, the play that turns that way by itself
    searches as the network does, and the other, pulled the other way, would turn back and forth.)
    """
    from torch.distributions import Categorical

    if logits.shape[0] != 2 * count:
        raise ValueError(f"mirror_mean needs 2 x {count} rows of logits (episodes, then their mirrors), got {logits.shape[0]}")
    logp = torch.log_softmax(logits, dim=-1)
    order = torch.tensor([int(a) for a in MIRRORED_ACTIONS], device=logits.device)
    own, mirrored = logp[:count], logp[count:, order]
    fused = (own + mirrored) / 2
    if heading is not None:
        turning = (heading == Action.LEFT) | (heading == Action.RIGHT)
        on = heading.clamp(min=0).view(-1, 1)
        back = torch.where(on == Action.LEFT, int(Action.RIGHT), int(Action.LEFT))
        own_back = (own.gather(1, back) > own.gather(1, on)).squeeze(1)
        mirrored_back = (mirrored.gather(1, back) > mirrored.gather(1, on)).squeeze(1)
        fused = torch.where((turning & mirrored_back & ~own_back).view(-1, 1), own, fused)
        fused = torch.where((turning & own_back & ~mirrored_back).view(-1, 1), mirrored, fused)
        fused = fused.index_copy(1, torch.tensor([int(Action.STOP)], device=logits.device),
                                 (own[:, Action.STOP] + mirrored[:, Action.STOP]).view(-1, 1) / 2)
    return Categorical(logits=fused)


def load_ppo_checkpoint(path: str | os.PathLike) -> dict[str, Any]:
    """Read a learned-agent checkpoint safely (``weights_only=True``) on the CPU.

    Raises:
        FileNotFoundError: no such file.
        ValueError: not a loadable findview checkpoint (message names the file).
    """
    from findview_baselines.rl.checkpoint import load_checkpoint

    return load_checkpoint(path, map_location="cpu")


class PPOAgent(Agent):
    """Greedy (or sampling) actions of a recurrent PPO policy.

    Args:
        policy: a :class:`findview_baselines.rl.Policy` (moved to ``device``, put in eval mode).
        num_envs, device, seed: see :class:`Agent`; ``device`` is where the network runs.
        sample: draw actions from the policy instead of taking the argmax.
        revisit_penalty: logit units subtracted from a move per earlier visit of its destination pose
            (0: off; see :mod:`findview_baselines.rl.search_memory`).
        revisit_rows: with the memory on, its row search (:class:`~findview_baselines.rl.search_memory.RowSearch`:
            after a turn move to the next search row, ``stride`` 1-step moves up or down, alternately, growing;
            from step ``after`` on, at most ``budget`` steps per row; the default: off).
        revisit_near: with the memory on, its near visits (:class:`~findview_baselines.rl.search_memory.NearVisits`;
            the default: off). Its ``until`` needs a ``refiner`` with ``min_near``: every near probability the
            stop check measures (:meth:`_refuse_far`) at or above it ends that episode's near visits.
        refiner: a :class:`~findview_baselines.agents.stop_refine.StopRefiner` for the final refinement of the
            policy's stops (``None``: the policy's stops stand).
        stop_prob: STOP whenever the policy gives STOP at least this probability, even when a move has more
            (``None``: the argmax, or the sample, decides).
        stop_min_prob: refuse the policy's STOP when its probability is below this, and take the most likely move
            instead (``None``: every STOP of the argmax, or the sample, stands). At most ``stop_prob``.
        stop_near_prob: with a ``refiner`` with ``min_near``: STOP also whenever the policy gives STOP at least this
            probability and the refiner's stop-offset net finds the view near the target (its ``min_near``), even
            when a move is more likely or ``stop_min_prob`` would refuse it (``None``: off). In ``(0, 1]``, below
            ``stop_prob`` (which stops at and above it without the net).
        stop_near_min_near: with ``stop_near_prob``: the net's near probability such a half-sure STOP needs, at
            least the refiner's ``min_near`` and below 1 (``None``: ``min_near``). A stricter bar for these stops
            than for the policy's own: a look-alike part of the panorama the net finds near at 0.6-0.95 does not
            end the episode on a half-sure STOP.
        fov: the views' horizontal field of view, degrees; required when the policy reads its search memory
            (``memory_inputs``: the memory's row band is half a FoV, :func:`~findview_baselines.rl.search_memory.memory_band`).
        stop_by: the step by which a slot stops (``T``): when the steps left are just enough, a slot that has not
            stopped walks back to its most stop-like pose and stops (0: off; needs ``revisit_penalty > 0``, the
            memory's dead reckoning).
        stop_by_phase: with ``stop_by``, a slot whose STOP probability never reached 0.1 walks to the pose the
            clearest phase correlation of view and target pointed at (:class:`GiveUp`, ``phase``); needs ``fov``.
        mirror_steps: for the first ``mirror_steps`` policy steps of each episode the network also plays the episode's
            left-right mirror (view and target flipped, a GRU state of its own) and the agent acts on the mean of the
            two log-probabilities, the mirror's LEFT and RIGHT swapped (:func:`mirror_mean`); later steps are the
            network's alone. 0: off.
        wide_match_turn: with ``wide_match_steps`` > 0 and a network that reads the wide match: a ZNCC peak in (0, 1);
            a slot whose wide match, in its first ``wide_match_steps`` steps, peaks at least this with a column shift
            of at least :data:`TURN_MIN_SHIFT` of the width cannot make its first yaw move away from that shift's
            side (:meth:`_first_turn`). 0: off.
    """

    name = "ppo"

    def __init__(
        self,
        policy: torch.nn.Module,
        num_envs: int,
        device: str | torch.device = "cpu",
        seed: int = 0,
        sample: bool = False,
        revisit_penalty: float = 0.0,
        revisit_rows: RowSearch = RowSearch(),
        refiner: StopRefiner | None = None,
        stop_prob: float | None = None,
        fov: float | None = None,
        stop_by: int = 0,
        stop_min_prob: float | None = None,
        stop_by_phase: bool = False,
        revisit_near: NearVisits = NearVisits(),
        mirror_steps: int = 0,
        wide_match_steps: int = 0,
        wide_match_min_peak: float | None = None,
        stop_near_prob: float | None = None,
        stop_near_min_near: float | None = None,
        wide_match_turn: float = 0.0,
    ) -> None:
        if stop_prob is not None and not 0.0 < float(stop_prob) <= 1.0:
            raise ValueError(f"stop_prob must be in (0, 1] or None, got {stop_prob!r}")
        if stop_min_prob is not None and not 0.0 < float(stop_min_prob) <= 1.0:
            raise ValueError(f"stop_min_prob must be in (0, 1] or None, got {stop_min_prob!r}")
        if stop_prob is not None and stop_min_prob is not None and float(stop_min_prob) > float(stop_prob):
            raise ValueError(f"stop_min_prob={stop_min_prob} refuses stops that stop_prob={stop_prob} forces: "
                             f"expected stop_min_prob <= stop_prob")
        if stop_near_prob is not None:
            if not 0.0 < float(stop_near_prob) <= 1.0:
                raise ValueError(f"stop_near_prob must be in (0, 1] or None, got {stop_near_prob!r}")
            if refiner is None or refiner.min_near is None:
                raise ValueError(f"stop_near_prob={stop_near_prob} stops where the stop-offset net finds the view near "
                                 f"the target: it needs a refiner with min_near (a stop-offset net with the near "
                                 f"output), got {'no refiner' if refiner is None else 'min_near=None'}")
            if stop_prob is not None and float(stop_near_prob) >= float(stop_prob):
                raise ValueError(f"stop_near_prob={stop_near_prob} adds stops below stop_prob={stop_prob}, which "
                                 f"already stops at and above it: expected stop_near_prob < stop_prob")
        if stop_near_min_near is not None:
            if stop_near_prob is None:
                raise ValueError(f"stop_near_min_near={stop_near_min_near} is the bar of stop_near_prob's stops, "
                                 f"which is off (stop_near_prob=None)")
            if not refiner.min_near <= float(stop_near_min_near) < 1.0:
                raise ValueError(f"stop_near_min_near must be in [min_near, 1) = [{refiner.min_near}, 1), got "
                                 f"{stop_near_min_near!r}")
        super().__init__(num_envs, device, seed)
        self.stop_near_prob = None if stop_near_prob is None else float(stop_near_prob)
        self.stop_near_min_near = (None if stop_near_prob is None else
                                   float(refiner.min_near if stop_near_min_near is None else stop_near_min_near))
        self.stop_prob = None if stop_prob is None else float(stop_prob)
        self.stop_min_prob = None if stop_min_prob is None else float(stop_min_prob)
        self.policy = policy.to(self.device).eval()
        self.sample = bool(sample)
        self.hidden = policy.initial_hidden(self.num_envs, self.device)
        if int(mirror_steps) < 0:
            raise ValueError(f"mirror_steps must be >= 0 policy steps (0 = off), got {mirror_steps}")
        self.mirror_steps = int(mirror_steps)
        if int(wide_match_steps) < 0:
            raise ValueError(f"wide_match_steps must be >= 0 policy steps (0 = every step), got {wide_match_steps}")
        if int(wide_match_steps) and not getattr(policy, "wide_match", 0):
            raise ValueError(f"wide_match_steps={wide_match_steps} needs a network that reads the wide match "
                             f"(agent.wide_match, wide_match in its checkpoint signature); this one does not")
        self.wide_match_steps = int(wide_match_steps)
        if not 0.0 <= float(wide_match_turn) < 1.0:
            raise ValueError(f"wide_match_turn must be a ZNCC in [0, 1) (0 = off), got {wide_match_turn!r}")
        if float(wide_match_turn) and not self.wide_match_steps:
            raise ValueError(f"wide_match_turn={wide_match_turn} reads the wide match in an episode's first steps: it "
                             f"needs wide_match_steps > 0, got {wide_match_steps}")
        self.wide_match_turn = float(wide_match_turn)
        # each slot's side from the wide match (wide_match_turn): +1 right, -1 left, 0 none
        self.turn_side = torch.zeros(self.num_envs, dtype=torch.long, device=self.device)
        # the wide match's peak gate: None keeps the network's own (the trainer's validation plays the network it
        # trains, gate included, build_policy); a value sets it
        if wide_match_min_peak is not None:
            self.policy.set_wide_min_peak(wide_match_min_peak)
        # the mirrored episodes' GRU states (mirror_steps), None without them
        self.hidden_mirror = policy.initial_hidden(self.num_envs, self.device) if self.mirror_steps else None
        # each slot's policy steps so far in its episode, and its last yaw move (Action.LEFT / RIGHT; -1: none
        # yet), for the mirror's rule on turning back
        self.policy_steps = torch.zeros(self.num_envs, dtype=torch.long, device=self.device)
        self.heading = torch.full((self.num_envs,), -1, dtype=torch.long, device=self.device)
        self.done = np.zeros(self.num_envs, dtype=bool)
        self._fallback = np.random.default_rng(self.seed)
        self._rngs: list[np.random.Generator] = [np.random.default_rng([self.seed, i]) for i in range(self.num_envs)]
        self.revisits = make_revisit_penalty(self.num_envs, self.device, revisit_penalty, revisit_rows, revisit_near)
        self.refiner = refiner
        if float(revisit_near.until) and (refiner is None or refiner.min_near is None or not revisit_near.rows):
            raise ValueError(f"revisit_near.until={revisit_near.until} ends an episode's near visits once the "
                             f"stop-offset net finds its view near: it needs near visits (rows > 0, got "
                             f"{revisit_near.rows}) and a refiner with min_near, got "
                             f"{'no refiner' if refiner is None else f'min_near={refiner.min_near}'}")
        self.memory_band = 0  # rows of the search memory's band, when the network reads the memory
        if getattr(policy, "memory_inputs", 0):
            if self.revisits is None or fov is None:
                raise ValueError(
                    "this network reads its search memory (memory_inputs in its checkpoint signature): it needs "
                    f"revisit_penalty > 0 (got {revisit_penalty}) and the views' fov (got {fov})"
                )
            self.memory_band = memory_band(float(fov))
        self.give_up: GiveUp | None = None
        if int(stop_by) < 0:
            raise ValueError(f"stop_by must be >= 0 steps (0 = off), got {stop_by}")
        if int(stop_by) > 0:
            if self.revisits is None:
                raise ValueError(
                    f"stop_by={stop_by} walks back to a dead-reckoned pose: it needs the search memory "
                    f"(revisit_penalty > 0, got {revisit_penalty})"
                )
            margin = 1 + (refiner.max_moves if refiner is not None else 0)  # the refinement's moves after the walk
            self.give_up = GiveUp(self.num_envs, int(stop_by), self.revisits.yaw_cells, self.device, margin=margin,
                                  phase=bool(stop_by_phase), fov=fov)
        if stop_by_phase and (self.give_up is None or fov is None):
            raise ValueError(f"stop_by_phase walks to a pose measured in degrees: it needs stop_by > 0 (got {stop_by}) "
                             f"and the views' fov (got {fov})")
        # the last act's network outputs: (slots the policy decided for, their action distribution), or None
        self._last_policy: tuple[torch.Tensor, "Categorical"] | None = None

    # construction --------------------------------------------------------------------------------
    @classmethod
    def from_checkpoint(
        cls,
        path: str | os.PathLike,
        num_envs: int,
        device: str | torch.device = "cpu",
        seed: int = 0,
        sample: bool = False,
        height: int | None = None,
        width: int | None = None,
        revisit_penalty: float | None = None,
        revisit_rows: RowSearch = RowSearch(),
        refiner: StopRefiner | None = None,
        stop_prob: float | None = None,
        fov: float | None = None,
        stop_by: int = 0,
        stop_min_prob: float | None = None,
        stop_by_phase: bool = False,
        revisit_near: NearVisits = NearVisits(),
        mirror_steps: int = 0,
        wide_match_steps: int = 0,
        wide_match_min_peak: float | None = None,
        stop_near_prob: float | None = None,
        stop_near_min_near: float | None = None,
        wide_match_turn: float = 0.0,
    ) -> "PPOAgent":
        """Rebuild the policy from a checkpoint's signature and load its weights.

        Args:
            height, width: the simulator's view size: the checkpoint's, or the same integer multiple of its
                height and width (:func:`downsample_factor`); another size raises ``ValueError`` saying which.
            revisit_penalty, fov, wide_match_min_peak: ``None``: the values the checkpoint's run trained with
                (``agent.revisit_penalty``, ``sim.fov``, ``agent.wide_match_min_peak`` of its stored config; 0, none
                and 0 when it has none).
        """
        from findview_baselines.rl.policy import Policy
        from findview_baselines.rl.signature import check_signature

        state = load_ppo_checkpoint(path)
        sig = dict(state["signature"])
        run_conf = dict(state.get("config") or {})
        if revisit_penalty is None:
            revisit_penalty = float(dict(run_conf.get("agent") or {}).get("revisit_penalty", 0.0))
        if wide_match_min_peak is None:  # the gate the network trained with (0 when its run had none)
            wide_match_min_peak = float(dict(run_conf.get("agent") or {}).get("wide_match_min_peak", 0.0))
        if fov is None and "fov" in dict(run_conf.get("sim") or {}):
            fov = float(run_conf["sim"]["fov"])
        missing = [k for k in ("variant", "hidden_size", "height", "width") if k not in sig]
        if missing:
            raise ValueError(f"{path}: checkpoint model signature lacks {missing} (signature: {sig})")
        h, w = int(sig["height"]), int(sig["width"])
        sim_h, sim_w = int(height if height is not None else h), int(width if width is not None else w)
        if downsample_factor((sim_h, sim_w), (h, w)) is None:
            raise ValueError(
                f"checkpoint {path} was trained on {h}x{w} (height x width) views but the simulator renders "
                f"{sim_h}x{sim_w} (sim.height={sim_h}, sim.width={sim_w}); evaluate it with "
                f"sim.height={h} sim.width={w} or an integer multiple of both (the agent then area-averages "
                f"the views down to {h}x{w}), and the FoV it was trained with"
            )
        if sig.get("pitch_warps") and fov is None:
            raise ValueError(f"{path}: this network reads pitch-warped views (pitch_warps in its checkpoint signature) "
                             f"and needs the views' field of view (fov=), which neither the call nor its config gives")
        policy = Policy(
            height=h, width=w, variant=str(sig["variant"]), hidden_size=int(sig["hidden_size"]),
            fine_shifts=int(sig.get("fine_shifts", 0)), fine_scales=int(sig.get("fine_scales", 1)),
            memory_inputs=int(sig.get("memory_inputs", 0)), pitch_warps=int(sig.get("pitch_warps", 0)),
            warp_fov=90.0 if fov is None else fov, wide_match=int(sig.get("wide_match", 0)),
        )
        check_signature(sig, policy.model_signature())
        try:
            policy.load_state_dict(state["policy"])
        except RuntimeError as err:
            raise ValueError(f"{path}: weights do not fit the model of its signature {sig}: {err}") from err
        return cls(
            policy, num_envs, device, seed, sample, revisit_penalty, revisit_rows, refiner, stop_prob, fov,
            stop_by, stop_min_prob, stop_by_phase, revisit_near, mirror_steps, wide_match_steps, wide_match_min_peak,
            stop_near_prob=stop_near_prob, stop_near_min_near=stop_near_min_near, wide_match_turn=wide_match_turn,
        )

    @classmethod
    def from_config(
        cls,
        cfg: "PPOAgentConfig",
        num_envs: int,
        device: str | torch.device,
        seed: int,
        *,
        checkpoint: str | os.PathLike | None = None,
        height: int | None = None,
        width: int | None = None,
    ) -> "PPOAgent":
        """Factory for :func:`~findview_baselines.agents.make_agent`: the policy of ``checkpoint`` (required; its
        model comes from the checkpoint's signature), acting as the typed ``agent`` section says (``sample``,
        the search memory). ``height`` / ``width``: the simulator's view size, pixels (checked against the
        checkpoint's)."""
        if not checkpoint:
            raise ValueError("agent 'ppo' needs a checkpoint: pass checkpoint=<path to a .pth file>")
        return cls.from_checkpoint(
            checkpoint, num_envs, device, seed, cfg.sample, height=height, width=width,
            revisit_penalty=cfg.revisit_penalty, revisit_rows=RowSearch.of(cfg),
            refiner=_refiner(cfg, num_envs, width) if cfg.refine_stop else None,
            stop_prob=cfg.stop_prob, fov=cfg.fov, stop_by=cfg.stop_by, stop_min_prob=cfg.stop_min_prob,
            stop_by_phase=cfg.stop_by_phase, revisit_near=NearVisits.of(cfg), mirror_steps=cfg.mirror_steps,
            wide_match_steps=cfg.wide_match_steps, wide_match_min_peak=cfg.wide_match_min_peak,
            stop_near_prob=cfg.stop_near_prob, stop_near_min_near=cfg.stop_near_min_near,
            wide_match_turn=cfg.wide_match_turn,
        )

    # acting --------------------------------------------------------------------------------------
    def reset(self, env_ids: Sequence[int], episodes: Sequence[Episode | None]) -> None:
        super().reset(env_ids, episodes)
        ids = [int(i) for i in env_ids]
        if not ids:
            return
        self.hidden[torch.tensor(ids, device=self.hidden.device)] = 0.0
        if self.hidden_mirror is not None:
            self.hidden_mirror[torch.tensor(ids, device=self.hidden.device)] = 0.0
        self.policy_steps[torch.tensor(ids, device=self.device)] = 0
        self.heading[torch.tensor(ids, device=self.device)] = -1
        self.turn_side[torch.tensor(ids, device=self.device)] = 0
        if self.revisits is not None:
            self.revisits.reset(torch.tensor(ids, dtype=torch.long, device=self.device))
        if self.refiner is not None:
            self.refiner.reset(ids)
        if self.give_up is not None:
            self.give_up.reset(torch.tensor(ids, dtype=torch.long, device=self.device))
        for i, ep in zip(ids, episodes):
            self.done[i] = ep is None
            self._rngs[i] = episode_rng(self.seed, ep, self._fallback)

    @torch.no_grad()
    @scoped(lambda self: self.policy.heavy)
    def act(self, obs: Mapping[str, torch.Tensor]) -> torch.Tensor:
        view, target = self._check_obs(obs)
        k = downsample_factor(tuple(view.shape[-2:]), (self.policy.height, self.policy.width))
        if k is None:
            raise ValueError(
                f"{self.name}: views of {tuple(view.shape[-2:])} pixels; the policy takes "
                f"{self.policy.height}x{self.policy.width} or an integer multiple of it"
            )
        full_view, full_target = view, target  # the stop refinement measures on the views as rendered
        self._last_policy = None
        view, target = area_downsample(view, k), area_downsample(target, k)
        actions = torch.full((self.num_envs,), STOP, dtype=torch.long, device=self.device)
        work = np.flatnonzero(~self.done)
        refining = self.refiner.refining.numpy()[work] if self.refiner is not None else np.zeros(len(work), bool)
        walking = self.give_up.returning.cpu().numpy()[work] & ~refining if self.give_up is not None else np.zeros(len(work), bool)
        asked = work[~refining & ~walking]  # the slots the policy decides for (refining and walking slots no longer ask it)
        stops = np.zeros(0, dtype=np.int64)
        if len(asked):
            a_t = self._policy_actions(asked, view, target, (full_view, full_target))
            actions[torch.as_tensor(asked, device=self.device)] = a_t
            stops = asked[(a_t == STOP).cpu().numpy()]
        if walking.any():  # walking back to the best pose (stop_by): the memory keeps the pose, no network
            walkers = work[walking]
            idx = torch.as_tensor(walkers, device=self.device)
            self.revisits.arrive(idx, view.to(self.device)[idx])
            a_w = self.give_up.walk(idx, self.revisits.pitch[idx], self.revisits.yaw[idx], self.revisits.last_blocked[idx])
            self.revisits.moved(idx, a_w)
            actions[idx] = a_w
            stops = np.concatenate([stops, walkers[(a_w == STOP).cpu().numpy()]])
        if self.refiner is not None:
            check = np.concatenate([work[refining], stops])
            if len(check):
                idx = torch.as_tensor(check, device=self.device)
                v, t = full_view.to(self.device)[idx], full_target.to(self.device)[idx]
                actions[idx] = self.refiner.decide(idx, v, t)
        if len(work):
            self.done[work[(actions[torch.as_tensor(work, device=self.device)] == STOP).cpu().numpy()]] = True
        if self.mirror_steps or self.wide_match_turn:
            turned = (actions == Action.LEFT) | (actions == Action.RIGHT)
            self.heading = torch.where(turned, actions, self.heading)
        return actions.to(view.device)

    def step_stop_prob(self) -> torch.Tensor | None:
        """The policy network's STOP probability in the last :meth:`act`: ``(N,)`` float32 on the agent's device,
        ``NaN`` for the slots the network did not decide for that step (already stopped or idle, a stop being
        refined, a ``stop_by`` walk back).

        It is ``softmax(logits)[STOP]`` of the network's own distribution (with ``mirror_steps``, the one
        :func:`mirror_mean` fused from the two plays), before the search memory: without the
        memory (``revisit_penalty=0``) that is the distribution the agent acted from; with it, the memory lowers
        only the moves and leaves the STOP decision to the network (its distribution puts exactly 0 or 1 on STOP,
        1 where the network's argmax is STOP), so this is the probability that decided STOP either way, the one
        ``stop_prob`` and ``stop_by`` compare as well. Computed here, from references ``act`` keeps (no host copy
        and no extra work in ``act``)."""
        out = torch.full((self.num_envs,), float("nan"), dtype=torch.float32, device=self.device)
        if self._last_policy is not None:
            idx, dist = self._last_policy
            out[idx] = dist.probs[:, STOP].float()
        return out

    def _policy_actions(self, work: np.ndarray, view: torch.Tensor, target: torch.Tensor,
                        rendered: tuple[torch.Tensor, torch.Tensor]) -> torch.Tensor:
        """The policy's actions (len(work),) for the slots ``work``; their GRU states move on. ``view`` / ``target``:
        the network's size; ``rendered``: the views and targets as rendered (for ``stop_by_phase``)."""
        full = len(work) == self.num_envs
        idx = torch.as_tensor(work, device=self.device)
        v = view.to(self.device) if full else view.to(self.device)[idx]
        t = target.to(self.device) if full else target.to(self.device)[idx]
        h = self.hidden if full else self.hidden[idx]
        memory = None
        if self.memory_band:  # the network reads the memory after this step's arrival
            self.revisits.arrive(idx, v)
            memory = self.revisits.memory_features(idx, self.memory_band)
        dist, h_new = self._play(idx, v, t, h, memory)
        self._last_policy = (idx, dist)  # references only: step_stop_prob computes from them when asked
        if full:
            self.hidden = h_new
        else:
            self.hidden[idx] = h_new
        logits = dist.logits
        if self.wide_match_turn:
            logits = self._first_turn(idx, v, t, logits)
        if self.stop_min_prob is not None:  # an unsure STOP is no option: the moves decide (memory included)
            logits = logits.clone()
            logits[dist.probs[:, STOP] < self.stop_min_prob, STOP] = float("-inf")
        if self.memory_band:
            logits = self.revisits.penalise(idx, logits)
        elif self.revisits is not None:
            logits = self.revisits.adjust(idx, v, logits)
        if self.sample:
            p_t = dist.probs if logits is dist.logits else torch.softmax(logits, dim=-1)
            probs = p_t.double().cpu().numpy()
            cdf = np.cumsum(probs, axis=1)
            u = np.array([self._rngs[i].random() for i in work])
            a = np.minimum((cdf < (u * cdf[:, -1])[:, None]).sum(axis=1), probs.shape[1] - 1)
            a_t = torch.as_tensor(a, dtype=torch.long, device=self.device)
        else:
            a_t = logits.argmax(dim=-1)
        if self.stop_prob is not None:  # the policy's own STOP probability, before the search memory
            a_t = torch.where(dist.probs[:, STOP] >= self.stop_prob, torch.full_like(a_t, STOP), a_t)
        stop_like = dist.probs[:, STOP]
        if self.refiner is not None and self.refiner.min_near is not None:
            a_t, stop_like = self._refuse_far(idx, a_t, logits, stop_like, rendered)
        if self.give_up is not None:  # remember the most stop-like pose; walk back to it when the steps left are just enough
            pitch, yaw = self.revisits.pitch[idx], self.revisits.yaw[idx]
            if self.give_up.phase:
                self.give_up.measure(idx, pitch, yaw, *rendered)
            late = self.give_up.observe(idx, stop_like, pitch, yaw) & (a_t != STOP)
            if bool(late.any()):
                a_t = a_t.clone()
                a_t[late] = self.give_up.walk(idx[late], pitch[late], yaw[late])
        if self.revisits is not None:
            self.revisits.moved(idx, a_t)
        return a_t

    def _first_turn(self, idx: torch.Tensor, view: torch.Tensor, target: torch.Tensor, logits: torch.Tensor) -> torch.Tensor:
        """``wide_match_turn``: the slots ``idx`` (K,) in their first ``wide_match_steps`` policy steps whose wide match
        is sure (peak at least ``wide_match_turn``, column shift at least :data:`TURN_MIN_SHIFT` of the width) take its
        side; a slot with a side that has not yet moved LEFT or RIGHT gets the other yaw move's logit at ``-inf``.
        ``view`` / ``target``: (K, 3, h, w), the network's size; ``logits``: (K, 5). Returns the logits (a copy when
        any changed)."""
        early = self.policy_steps[idx] <= self.wide_match_steps
        if bool(early.any()):
            rows = torch.nonzero(early).flatten()
            match = self.policy.wide(self.policy._prepare(view[rows]), self.policy._prepare(target[rows]))
            peak, shift = match[:, WIDE_PEAK], match[:, WIDE_PEAK + 2]  # the peak's height and its column shift / w
            sure = (peak >= self.wide_match_turn) & (shift.abs() >= TURN_MIN_SHIFT)
            self.turn_side[idx[rows[sure]]] = torch.where(shift[sure] > 0, 1, -1)
        side = self.turn_side[idx]
        unturned = (self.heading[idx] != Action.LEFT) & (self.heading[idx] != Action.RIGHT)
        ruled_out = torch.where(side > 0, int(Action.LEFT), int(Action.RIGHT))
        block = unturned & (side != 0)
        if not bool(block.any()):
            return logits
        logits = logits.clone()
        logits[torch.nonzero(block).flatten(), ruled_out[block]] = float("-inf")
        return logits

    def _play(self, idx: torch.Tensor, view: torch.Tensor, target: torch.Tensor, hidden: torch.Tensor,
              memory: torch.Tensor | None) -> tuple["Categorical", torch.Tensor]:
        """One network step for the slots ``idx`` (K,): their views and targets (K, 3, h, w), GRU states (K, hidden)
        and memory features (or ``None``). Returns the action distribution (K rows) and the new GRU states. Slots in
        their first ``mirror_steps`` steps also play their mirror, in the same batch (the memory's features are the
        same in a mirror), and get :func:`mirror_mean`'s distribution; their mirror states move on."""
        from torch.distributions import Categorical

        count = len(idx)
        masks = torch.ones(count, device=self.device)
        self.policy_steps[idx] += 1
        obs = {"view": view, "target": target}
        if self.wide_match_steps:  # the wide match speaks in each episode's first wide_match_steps steps only
            obs[WIDE_ON] = self.policy_steps[idx] <= self.wide_match_steps
        if self.hidden_mirror is None:
            dist, _, h_new = self.policy(obs, hidden, masks, memory=memory)
            return dist, h_new
        rows = torch.nonzero(self.policy_steps[idx] <= self.mirror_steps).flatten()  # rows whose mirror plays
        both = {"view": torch.cat([view, view[rows].flip(-1)]), "target": torch.cat([target, target[rows].flip(-1)])}
        if WIDE_ON in obs:  # a mirror row is on the same step as its episode
            both[WIDE_ON] = torch.cat([obs[WIDE_ON], obs[WIDE_ON][rows]])
        dist, _, h_all = self.policy(both, torch.cat([hidden, self.hidden_mirror[idx[rows]]]), masks.new_ones(count + len(rows)),
                                     memory=None if memory is None else torch.cat([memory, memory[rows]]))
        logits = dist.logits[:count]
        if len(rows):
            fused = mirror_mean(torch.cat([logits[rows], dist.logits[count:]]), len(rows), self.heading[idx[rows]])
            logits = logits.index_copy(0, rows, fused.logits)
            self.hidden_mirror[idx[rows]] = h_all[count:]
        return Categorical(logits=logits), h_all[:count]

    def _refuse_far(self, idx: torch.Tensor, a_t: torch.Tensor, logits: torch.Tensor, stop_like: torch.Tensor,
                    rendered: tuple[torch.Tensor, torch.Tensor]) -> tuple[torch.Tensor, torch.Tensor]:
        """The stop check of ``min_near``: for the slots ``idx`` whose action ``a_t`` is STOP, or (with ``stop_by``)
        whose STOP probability ``stop_like`` would become their most stop-like pose, or (with ``stop_near_prob``)
        whose STOP probability reaches ``stop_near_prob`` while they move, ask the refiner's net whether the view is
        near the target, once per slot. A moving slot of ``stop_near_prob`` whose view the net finds near (at least
        ``stop_near_min_near``) STOPs (a half-sure STOP, whatever move the memory, the row search or a walk back due
        now would have made; it is then refined like any other). A refused STOP becomes the most likely move of ``logits``; a refused view's
        ``stop_like`` becomes 0, so the walk of ``stop_by`` never goes back to it. Returns the new ``(a_t,
        stop_like)``."""
        check = a_t == STOP
        if self.give_up is not None:
            check = check | ((stop_like > self.give_up.best[idx]) & (stop_like >= self.give_up.min_prob))
        half_sure = None
        if self.stop_near_prob is not None:
            half_sure = (a_t != STOP) & (stop_like >= self.stop_near_prob)
            check = check | half_sure
        rows = torch.nonzero(check).flatten()
        if not len(rows):
            return a_t, stop_like
        at = idx[rows]
        near = self.refiner.near_prob(rendered[0].to(self.device)[at], rendered[1].to(self.device)[at])
        far = near < self.refiner.min_near
        if self.revisits is not None:  # found near (near.until): the episode's near visits end
            self.revisits.found_near(at, near)
        if half_sure is not None:  # a half-sure view found near: STOP there
            sure = half_sure[rows] & (near >= self.stop_near_min_near)
            a_t = a_t.index_put((rows,), torch.where(sure, STOP, a_t[rows]))
        refused = rows[far]
        if not len(refused):
            return a_t, stop_like
        moves = logits[refused].clone()
        moves[:, STOP] = float("-inf")
        a_t, stop_like = a_t.clone(), stop_like.clone()
        a_t[refused] = torch.where(a_t[refused] == STOP, moves.argmax(dim=-1), a_t[refused])
        stop_like[refused] = 0.0
        return a_t, stop_like


def _refiner(cfg: "PPOAgentConfig", num_envs: int, width: int | None) -> StopRefiner:
    """The stop refinement of the ``agent`` section: by the measured residual, or by ``agent.refine_model``'s net,
    with ``agent.refine_near_model``'s net (if given) for the near check (each checked against the views' FoV and
    ``width``, pixels)."""
    offsets = near_offsets = None
    if cfg.refine_model is not None:
        from findview_baselines.agents.stop_offsets import load_stop_offsets

        offsets = load_stop_offsets(cfg.refine_model, fov=cfg.fov, size=width)
        if cfg.refine_near_model is not None:
            near_offsets = load_stop_offsets(cfg.refine_near_model, fov=cfg.fov, size=width)
    return StopRefiner(num_envs, cfg.fov, cfg.refine_moves, offsets=offsets, min_stay=cfg.refine_min_stay,
                       min_near=cfg.refine_min_near, near_offsets=near_offsets)


def _register() -> None:
    from findview_baselines.agents import AGENTS, register_agent

    if "ppo" not in AGENTS:
        register_agent("ppo", PPOAgent.from_config)


_register()
