"""Imitation of the oracle with DAgger (dataset aggregation) for the recurrent policies of ``policy.py``.

The simulator knows the shortest-path action at every state, so every observation the learner visits can
be labelled for free (``findview.task.oracle``; the privileged rotations are never shown to the policy).
One update of :class:`DAggerTrainer`::

    beta = beta_start -> beta_end, linearly over beta_decay_updates updates
    for rollout_steps steps (N environments):
        oracle = oracle_actions_for(env, order, search_prior)        # before env.step: the expert's action
        label  = the set of actions the expert accepts: {oracle} (labels=action) or every shortest-path
                 action (labels=set, optimal_action_mask_for)
        learner action from policy.act (argmax unless sample_actions)
        execute the oracle's action with probability beta (per env, per step), else the learner's
    cut the T x N rollout into chunks of seq_len steps (GRU state at each chunk start, episode masks)
    push the chunks into a FIFO buffer of buffer_size steps (the oldest chunks drop out)
    ceil(epochs * new_chunks / batch_sequences) Adam steps, each on batch_sequences chunks drawn uniformly
        (without replacement) from the buffer: weighted negative log-likelihood of the label set,
        -log sum_{a in set} pi(a | obs) (the cross-entropy for a one-action set), + aux_coef * auxiliary
        rotation loss; gradient norm clipped at max_grad_norm

Labels (``labels``): ``"action"`` (default) imitates the oracle's one action (its axis order); ``"set"``
accepts any action on a shortest path (both axes while both are off), so the learner may fix whichever
axis it sees best first instead of having to tell which remaining distance the order picks.

Search prior (``search_prior``): ``"oracle"`` labels every state with the true shortest path, also where the view
and the target share nothing, so a learner must guess the direction there; ``"pan"`` (default) replaces
the labels of no-overlap states by "pan right until the views overlap" (``findview.task.oracle.pan_actions``),
which a learner can follow from images alone (it only has to tell whether the views overlap;
``search_pitch_band`` < 1 first moves the pitch to within that fraction of a FoV of the target's, which asks the
learner to tell from the images whether the target lies above or below; ``search_yaw_band`` < 1 keeps the pan
labels until the target is that fraction of a FoV to the side, not where it shows only a strip of a few degrees;
``search_yaw_band_after`` > 0 applies that band only once the search memory has seen that many FoVs of the current
row, so a target half out of view at the episode's start or on a row just reached is still turned to);
``"sweep"`` first matches the pitch, then pans right (``sweep_actions``); a learner cannot read the
target's pitch from a view that shares nothing with it and a greedy one ends in ``UP``/``DOWN`` two-cycles.

Recurrent training: a chunk starts from the GRU state the learner had at that step during the rollout
(stale once the weights move on, as in recurrent PPO), and ``masks == 0`` zero the state where an episode
starts inside a chunk.

A stop request during the rollout (``train_update(should_stop)``) abandons the update with
``UpdateAbandoned`` before anything reaches the buffer, and :meth:`DAggerTrainer.state_dict` then describes
the state before that update, as for ``PPOTrainer`` (both are a :class:`~findview_baselines.rl.trainer_base.Trainer`,
``kind = "dagger"`` here).

Resume: :meth:`DAggerTrainer.state_dict` holds the policy, the optimizer, the environment (running
episodes), the current observation / GRU state, every RNG and (``save_buffer``) the buffer, so N updates
and N/2 + resume + N/2 give the same weights on CPU. The buffer takes ``2 * buffer_size * 3 * H * W``
bytes of uint8 images (about 400 MB for 16384 steps of 64x64 views) in memory and in ``latest.pth``; with
``save_buffer=false`` the checkpoint stays small and a resumed run refills the buffer (not exact).

Fixed encoder inputs (``cache_fixed_features``, on by default): the ``direct`` / ``robust`` / ``phase`` policies
begin with parameter-free comparisons of view and target (``Policy.fixed_features``). The learner computes them
once per step to act in the rollout, the buffer keeps them (about 5 KB per step for ``phase``) and every gradient
step starts from them, instead of recomputing them about ``epochs`` times per step: the same loss, and 3.4x
faster updates of the robust preset on one CPU thread (``benchmarks/bench_dagger.py``). A resumed buffer
rebuilds them from its images.

Overlapped updates (``overlap_rollout``, off by default): on a CPU, an update of the 64x64 robust preset is about
0.7 s of rollout (many small ops) and 1.0 s of gradient steps, one after the other on one core. With the option the
rollout runs in a second thread, acting with a copy of the weights from before the update's gradient steps, while
this thread trains on the buffer; its chunks enter the buffer when both have ended. Each gradient step then samples
from every rollout but the one collected beside it, so the weights differ from those of the sequential schedule,
but not from run to run. The first update (empty buffer) runs sequentially. Two cores run an update in about the
time of its gradient steps (``benchmarks/bench_dagger.py --overlap``).

The pieces live in modules of their own: the hyper-parameters and the beta schedule in ``dagger_config.py``
(:class:`DAggerConfig`, :func:`beta_at`), the loss in ``dagger_loss.py`` (:func:`set_nll`) and the buffer
in ``sequence_buffer.py`` (:class:`SequenceBuffer`); this module holds the trainer and re-exports them.
"""

from __future__ import annotations

import copy
import math
import threading
import time
from typing import Any, Callable, Mapping

import torch
from torch import nn

from findview.runtime import scoped
from findview.task import NUM_ACTIONS, Action
from findview.task.oracle import (
    optimal_action_mask_for,
    oracle_actions_for,
    overlap_mask,
    rotation_labels,
)
from findview_baselines.rl import distributed
from findview_baselines.rl.aux_head import AuxHead, aux_loss
from findview_baselines.rl.dagger_config import LABEL_MODES, DAggerConfig, beta_at
from findview_baselines.rl.dagger_loss import set_nll
from findview_baselines.rl.policy import Policy
from findview_baselines.rl.scheduler import DifficultyScheduler
from findview_baselines.rl.search_memory import SEARCH_ROWS, NearVisits, RowSearch, make_revisit_penalty, memory_band
from findview_baselines.rl.sequence_buffer import SequenceBuffer
from findview_baselines.rl.storage import AUX_SIZE
from findview_baselines.rl.trainer_base import TIMING_KEYS, Trainer, never, no_distribution_validation

__all__ = [
    "DAggerConfig", "DAggerTrainer", "SequenceBuffer", "STAT_KEYS", "TIMING_KEYS", "beta_at", "set_nll",
    "LABEL_MODES",
]

# scalar entries of train_update()'s stats (besides update / env_steps / level / episodes)
STAT_KEYS = (
    "policy_loss", "accuracy", "stop_accuracy", "entropy", "grad_norm", "lr", "beta", "buffer_steps",
    "oracle_share", "rollout_agreement",
)
AUX_STAT_KEYS = ("aux_loss", "aux_rotation_loss", "aux_overlap_accuracy")
STOP = NUM_ACTIONS - 1


def search_row_moves(memory: torch.Tensor, offset: torch.Tensor, side: torch.Tensor, band: int) -> torch.Tensor:
    """``row_done_labels=rows``: the pitch move (``UP`` / ``DOWN``, (N,) long; -1 where none is left) towards the next
    search row the memory has not looked around.

    ``memory``: (N, MEMORY_FEATURES) ``RevisitPenalty.memory_features`` (columns 2-5: rows ``+s, -s, +2s, -2s`` done,
    ``s = band + 1`` steps from the start); ``offset``: (N,) the pitch offset from the start, steps; ``side``: (N,) +1
    or -1, the ring's first row when neither of its two is done (the target's side of the start). A ring whose two
    rows are done passes to the next; when every ring is done there is no move.
    """
    step = int(band) + 1
    column = {k: 2 + i for i, k in enumerate(SEARCH_ROWS)}  # memory_features' "done" column of each search row
    rings = sorted({abs(k) for k in SEARCH_ROWS})
    row = torch.zeros_like(offset)
    left = torch.zeros_like(offset, dtype=torch.bool)  # a row not looked around is left
    for ring in reversed(rings):  # the nearest ring decides last
        done_up, done_down = memory[:, column[ring]] > 0.5, memory[:, column[-ring]] > 0.5
        target = torch.where(~done_up & ~done_down, side * ring * step, torch.where(done_up, -ring * step, ring * step))
        open_ring = ~(done_up & done_down)
        row = torch.where(open_ring, target, row)
        left = left | open_ring
    move = torch.where(row > offset, int(Action.UP), int(Action.DOWN))
    return torch.where(~left | (row == offset), torch.full_like(move, -1), move)


# --------------------------------------------------------------------------------------------------
# Trainer
# --------------------------------------------------------------------------------------------------


class DAggerTrainer(Trainer):
    """DAgger on a batched FindView environment, with the public interface of ``PPOTrainer``.

    Args:
        env: a batched, auto-resetting :class:`~findview.task.FindViewEnv` (its privileged ``pitch, yaw,
            target_pitch, target_yaw`` and ``sim.fov`` give the labels).
        policy: the :class:`Policy` (already on its device).
        cfg: :class:`DAggerConfig`.
        total_updates: updates of the whole run (lr decay, scheduler).
        scheduler, set_level: optional difficulty curriculum, as for ``PPOTrainer``.
        seed: seeds the trainer's own generators (beta mixing, buffer sampling); learner action sampling
            (``sample_actions``) uses torch's global RNG.

    :meth:`start` for a fresh run or :meth:`load_state_dict` to resume; then :meth:`train_update` repeatedly.
    """

    kind = "dagger"
    title = "DAgger"
    cfg: DAggerConfig

    def __init__(
        self,
        env: Any,
        policy: Policy,
        cfg: DAggerConfig,
        total_updates: int,
        scheduler: DifficultyScheduler | None = None,
        set_level: Callable[[int], None] | None = None,
        seed: int = 0,
        revisit_penalty: float = 0.0,
        revisit_rows: RowSearch = RowSearch(),
        revisit_near: NearVisits = NearVisits(),
    ) -> None:
        super().__init__(env, policy, cfg, total_updates, scheduler, set_level)
        self.aux_head: AuxHead | None = AuxHead(policy.feature_size).to(self.device) if cfg.aux_coef > 0 else None
        self.params = self._trained_parameters(policy, cfg.train_only) + (list(self.aux_head.parameters()) if self.aux_head else [])
        self.optimizer = torch.optim.Adam(self.params, lr=cfg.lr, eps=cfg.adam_eps)
        self.lr = cfg.lr
        n, dev = env.num_envs, self.device
        # the encoder's parameter-free part of each buffered step, computed once (cache_fixed_features)
        self.fixed_size = policy.fixed_feature_size if cfg.cache_fixed_features else 0
        self.buffer = SequenceBuffer(
            max(1, cfg.buffer_size // cfg.seq_len), cfg.seq_len, policy.height, policy.width,
            policy.hidden_size, dev, with_aux=self.aux_head is not None, fixed_size=self.fixed_size,
            memory_size=policy.memory_inputs, with_penalty=cfg.penalised_loss != "none",
        )
        weights = torch.ones(NUM_ACTIONS, device=dev)
        weights[STOP] = cfg.stop_weight
        self.class_weights = weights
        self.mix_generator = torch.Generator().manual_seed(seed)
        self.sample_generator = torch.Generator().manual_seed(seed + 1)
        # current observation (a copy: the env's buffers change in place), GRU state and masks
        self.view = torch.zeros(n, 3, policy.height, policy.width, dtype=torch.uint8, device=dev)
        self.target = torch.zeros_like(self.view)
        self.hidden = policy.initial_hidden(n, dev)
        self.masks = torch.zeros(n, device=dev)
        # the learner acts in rollouts as the evaluated agent will (agent.revisit_penalty: its search memory)
        self.revisits = make_revisit_penalty(n, dev, revisit_penalty, revisit_rows, revisit_near)
        self._all_slots = torch.arange(n, device=dev)
        # a policy that reads its search memory (memory_inputs): the memory's row band, half a FoV
        self.memory_band = 0
        if policy.memory_inputs:
            if self.revisits is None:
                raise ValueError("a policy with memory inputs reads the search memory: it needs revisit_penalty > 0")
            if int(getattr(env, "step_deg", 1)) != 1:
                raise ValueError(f"memory inputs need 1-degree actions (the search memory's grid), got "
                                 f"task.step_deg={env.step_deg}")
            self.memory_band = memory_band(float(env.sim.fov))
        if cfg.penalised_loss != "none" and self.revisits is None:
            raise ValueError(f"trainer.dagger.penalised_loss={cfg.penalised_loss} trains against the search memory's "
                             f"penalty: it needs agent.revisit_penalty > 0, got {revisit_penalty}")
        # overlap_rollout: the weights the rollout acts with while the gradient steps change self.policy
        self._acting: Policy | None = None
        if cfg.overlap_rollout:
            if distributed.is_active():
                raise ValueError("trainer.dagger.overlap_rollout=true is not supported under torchrun (its collectives "
                                 "would run in two threads); set it to false")
            self._acting = copy.deepcopy(policy).requires_grad_(False)
        if cfg.search_yaw_band_after > 0 and not self.memory_band:
            raise ValueError(f"trainer.dagger.search_yaw_band_after={cfg.search_yaw_band_after} reads how much of the "
                             f"row the search memory has seen: it needs agent.memory_inputs=true")
        if cfg.penalised_loss == "rows" and not self.memory_band:  # no memory inputs: no step ever leaves a done row
            raise ValueError("trainer.dagger.penalised_loss=rows penalises the steps that leave a looked-around row: "
                             "it needs agent.memory_inputs=true")

    # ---------------------------------------------------------------------------------------------

    @staticmethod
    def _trained_parameters(policy: nn.Module, train_only: list[str] | None) -> list[nn.Parameter]:
        """The policy's parameters the optimiser moves: all, or those of the modules ``train_only`` names
        (``trainer.dagger.train_only``); a name that matches no parameter is an error naming the modules there are."""
        if train_only is None:
            return list(policy.parameters())
        named = dict(policy.named_parameters())
        chosen: dict[int, nn.Parameter] = {}  # by identity: a module named twice (or inside another) counts once
        for name in train_only:
            prefix = name.rstrip(".") + "."
            found = [p for key, p in named.items() if key.startswith(prefix)]
            if not found:
                modules = sorted({key.split(".")[0] for key in named})
                raise ValueError(f"trainer.dagger.train_only: the policy has no module {name!r} with weights; "
                                 f"its modules: {', '.join(modules)}")
            chosen.update((id(p), p) for p in found)
        return list(chosen.values())

    def _set_obs(self, obs: Mapping[str, torch.Tensor]) -> None:
        self.view.copy_(obs["view"])
        self.target.copy_(obs["target"])

    def start(self) -> None:
        """Fresh run: set the difficulty level for ``self.update`` and reset the environments."""
        self._step_level(force=True)
        self._set_obs(self.env.reset())
        self.hidden.zero_()
        self.masks.copy_(self._masks())
        self.episode_returns.zero_()

    def extra_modules(self) -> list[nn.Module]:
        """The auxiliary rotation head when ``aux_coef > 0``, else nothing."""
        return [self.aux_head] if self.aux_head is not None else []

    def collect_rollout(
        self, beta: float, should_stop: Callable[[], bool] = never
    ) -> tuple[list[dict[str, Any]], dict[str, float]]:
        """Run ``rollout_steps`` mixed steps and push the labelled chunks into the buffer.

        Returns the finished episodes' records (with ``"return"``) and rollout stats (``oracle_share``:
        share of executed oracle actions; ``rollout_agreement``: share of steps where the learner's action
        was in the label set). Raises ``UpdateAbandoned`` (buffer untouched) when ``should_stop()`` turns
        true before a step.
        """
        records, stats, chunks = self._collect(beta, self.policy, should_stop)
        self._push(chunks)
        return records, stats

    def _push(self, chunks: list[tuple[Any, ...]]) -> None:
        """Add a rollout's chunks (:meth:`_collect`) to the buffer."""
        for chunk in chunks:
            self.buffer.add(*chunk)

    @torch.no_grad()
    def _collect(
        self, beta: float, policy: Policy, should_stop: Callable[[], bool] = never
    ) -> tuple[list[dict[str, Any]], dict[str, float], list[tuple[Any, ...]]]:
        """:meth:`collect_rollout` acting with ``policy`` (``self.policy`` or, with ``overlap_rollout``, a copy of
        its weights), without touching the buffer: also returns the rollout's chunks, ``SequenceBuffer.add``'s
        arguments. Touches only the rollout's state (environment, observation, GRU state, search memory,
        ``mix_generator``), never the trainable weights, the optimizer or the buffer."""
        cfg, env, dev = self.cfg, self.env, self.device
        T, n = cfg.rollout_steps, env.num_envs
        views = torch.empty(T, *self.view.shape, dtype=torch.uint8, device=dev)
        targets = torch.empty_like(views)
        hiddens = torch.empty(T // cfg.seq_len, *self.hidden.shape, device=dev)
        masks = torch.empty(T, n, device=dev)
        labels = torch.empty(T, n, NUM_ACTIONS, dtype=torch.bool, device=dev)
        weights = torch.ones(T, n, device=dev)
        aux = torch.empty(T, n, AUX_SIZE, device=dev) if self.aux_head is not None else None
        # the fixed encoder inputs the learner computes to act are the ones the buffer caches
        fixed = torch.empty(T, n, self.fixed_size, device=dev) if self.fixed_size else None
        memory = torch.empty(T, n, self.policy.memory_inputs, device=dev) if self.memory_band else None
        penalty = torch.empty(T, n, 4, device=dev) if cfg.penalised_loss != "none" else None
        records: list[dict[str, Any]] = []
        agree = torch.zeros((), device=dev)
        executed_oracle = 0
        policy.eval()
        t_forward = t_env = 0.0
        start = time.perf_counter()
        for t in range(T):
            if should_stop():
                raise self._abandoned()
            views[t].copy_(self.view)
            targets[t].copy_(self.target)
            masks[t].copy_(self.masks)
            if t % cfg.seq_len == 0:
                hiddens[t // cfg.seq_len].copy_(self.hidden * self.masks[:, None])
            if self.revisits is not None:  # the memory sees this step's arrival before the policy reads it
                self._memory_arrive()
            if memory is not None:
                memory[t] = self.revisits.memory_features(self._all_slots, self.memory_band)
            oracle, label, searching, leave = self._labels(None if memory is None else memory[t])
            if penalty is not None:  # "rows": only the steps that leave a looked-around row read the penalty
                pen = self.revisits.move_penalties(self._all_slots)
                penalty[t] = pen if cfg.penalised_loss == "moves" else pen * leave[:, None].to(pen.dtype)
            labels[t].copy_(label)
            weights[t].masked_fill_(searching, cfg.search_weight)
            if cfg.first_steps:  # the episode's first moves weigh first_steps_weight times as much
                weights[t].mul_(torch.where(env.steps.to(dev) < cfg.first_steps, cfg.first_steps_weight, 1.0))
            if aux is not None:
                aux[t].copy_(rotation_labels(env).to(dev))
            t0 = time.perf_counter()
            obs = {"view": self.view, "target": self.target}
            if fixed is not None:
                fixed[t] = policy.fixed_features(obs)
            learner, new_hidden = self._learner_step(
                policy, obs, None if fixed is None else fixed[t], None if memory is None else memory[t]
            )
            t1 = time.perf_counter()
            use_oracle = torch.rand(n, generator=self.mix_generator) < beta
            executed_oracle += int(use_oracle.sum())
            agree += label.gather(1, learner[:, None]).sum()
            actions = torch.where(use_oracle.to(dev), oracle, learner)
            if self.revisits is not None:
                self.revisits.moved(self._all_slots, actions)  # what was executed, oracle or learner
            next_obs, rewards, done, infos = env.step(actions)
            t2 = time.perf_counter()
            t_forward += t1 - t0
            t_env += t2 - t1
            self._set_obs(next_obs)
            self.hidden = new_hidden
            self.masks = self._masks()
            records += self._track_returns(rewards, done, infos)

        L = cfg.seq_len
        chunks = []
        for k in range(T // L):
            s = slice(k * L, (k + 1) * L)
            chunks.append((
                views[s], targets[s], hiddens[k], masks[s], labels[s], None if aux is None else aux[s], weights[s],
                None if fixed is None else fixed[s], None if memory is None else memory[s],
                None if penalty is None else penalty[s],
            ))
        self.env_steps += distributed.global_steps(T * n)  # all ranks under torchrun
        self._add_rollout_timings(t_forward, t_env, time.perf_counter() - start)
        stats = {"oracle_share": executed_oracle / (T * n), "rollout_agreement": float(agree) / (T * n)}
        return records, stats, chunks

    def _labels(self, memory: torch.Tensor | None) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor, torch.Tensor]:
        """This step's oracle: the action to execute (N,) long, the label set (N, NUM_ACTIONS) bool, the steps
        that weigh ``search_weight`` (N,) bool: searches with no overlap of view and target, except the steps that
        leave a finished row, and those steps (N,) bool. ``memory``: this step's (N, memory_inputs) features, for a
        policy that reads them."""
        cfg, env, dev = self.cfg, self.env, self.device
        fov = float(env.sim.fov)
        row_done = memory[:, 0] > 0.5 if memory is not None and cfg.search_prior == "pan" else None
        towards = row_done if cfg.row_done_labels == "target" else None  # the prior's own "row done" labels
        band: float | torch.Tensor = cfg.search_yaw_band
        if memory is not None and cfg.search_yaw_band_after > 0:  # band 1 until the row's search is under way
            before = memory[:, 1] * 360.0 < cfg.search_yaw_band_after * fov
            band = torch.where(before, 1.0, cfg.search_yaw_band).to(env.pitch.device)
        oracle = oracle_actions_for(env, cfg.order, cfg.search_prior, cfg.search_pitch_band, towards,
                                    cfg.row_done_band, band).to(dev)
        if cfg.labels == "set":
            label = optimal_action_mask_for(env, cfg.search_prior, cfg.search_pitch_band, towards,
                                            cfg.row_done_band, band).to(dev)
        else:
            label = nn.functional.one_hot(oracle, NUM_ACTIONS).bool()
        searching = ~overlap_mask(env.pitch, env.yaw, env.target_pitch, env.target_yaw, fov, band).to(dev)
        if cfg.first_steps_turn:  # the first steps' label is the turn towards an overlapping target alone
            move = oracle_actions_for(env, "yaw_first").to(dev)  # LEFT / RIGHT while the yaw is off
            turned = (move == Action.LEFT) | (move == Action.RIGHT)
            turn = (env.steps.to(dev) < cfg.first_steps) & ~searching & turned
            oracle = torch.where(turn, move, oracle)
            label = torch.where(turn[:, None], nn.functional.one_hot(move, NUM_ACTIONS).bool(), label)
        if row_done is None:
            return oracle, label, searching, torch.zeros_like(searching)
        if cfg.row_done_labels == "rows":  # to the next search row instead, and those steps weigh fully
            start_pitch = env.pitch.to(dev) - self.revisits.pitch.to(dev)  # the dead-reckoned start row
            side = torch.where(env.target_pitch.to(dev) >= start_pitch, 1, -1)
            move = search_row_moves(memory, self.revisits.pitch.to(dev), side, self.memory_band)
            leave = row_done & searching & (move >= 0)
            oracle = torch.where(leave, move, oracle)
            label = torch.where(leave[:, None], nn.functional.one_hot(move.clamp(min=0), NUM_ACTIONS).bool(), label)
        else:  # the steps towards the target's pitch from a finished row weigh fully
            leave = row_done & ((env.target_pitch - env.pitch).abs().to(dev) > cfg.row_done_band * fov)
        return oracle, label, searching & ~leave, leave

    def _memory_arrive(self) -> None:
        """The search memory: slots whose episode starts now forget (with memory inputs, ``memory_warm_start`` of
        them then count their start row as looked around), then every slot arrives at its pose."""
        starts = torch.nonzero(self.masks == 0).flatten()
        if len(starts):
            self.revisits.reset(starts)
            if self.memory_band and self.cfg.memory_warm_start > 0:  # some episodes start as if the start row had been looked around
                warm = torch.rand(len(starts), generator=self.mix_generator) < self.cfg.memory_warm_start
                if bool(warm.any()):
                    self.revisits.mark_row_seen(starts[warm.to(starts.device)])
        self.revisits.arrive(self._all_slots, self.view)

    def _learner_step(
        self, policy: Policy, obs: Mapping[str, torch.Tensor], fixed: torch.Tensor | None,
        memory: torch.Tensor | None,
    ) -> tuple[torch.Tensor, torch.Tensor]:
        """The actions of ``policy`` (``self.policy``, or its acting copy with ``overlap_rollout``), under the search
        memory when there is one (after :meth:`_memory_arrive`, as ``PPOAgent`` acts at evaluation), and its new GRU
        state; ``fixed``: the observation's fixed encoder inputs, when cached; ``memory``: the memory's features
        (N, memory_inputs), for a policy that reads them."""
        dist, _, new_hidden, _ = policy.forward_features(obs, self.hidden, self.masks, fixed=fixed, memory=memory)
        logits = dist.logits
        if self.revisits is not None:
            logits = self.revisits.penalise(self._all_slots, logits)
        if self.cfg.sample_actions:
            return torch.distributions.Categorical(logits=logits).sample(), new_hidden
        return logits.argmax(dim=-1), new_hidden

    def _train(self, new_chunks: int) -> dict[str, float]:
        """Gradient steps on the buffer; mean stats over them."""
        cfg = self.cfg
        steps = max(1, math.ceil(cfg.epochs * new_chunks / cfg.batch_sequences))
        totals: dict[str, float] = {}
        self.policy.train()
        # with the cached fixed inputs the network never reads the images: they are not gathered
        cached = self.buffer.fixed is not None
        for _ in range(steps):
            b = self.buffer.batch(self.buffer.sample(cfg.batch_sequences, self.sample_generator), images=not cached)
            obs = None if cached else {"view": b["view"], "target": b["target"]}
            dist, _, _, features = self.policy.forward_features(
                obs, b["hidden0"], b["masks"], fixed=b.get("fixed"), memory=b.get("memory")
            )
            logits = dist.logits
            labels = b["labels"]
            if "penalty" in b:  # the move logits the agent acts on, except where the label is STOP
                moves = logits[:, :4] - b["penalty"] * (~labels[:, STOP])[:, None].to(logits.dtype)
                logits = torch.cat([moves, logits[:, 4:]], dim=1)
            ce = set_nll(logits, labels, self.class_weights, b["weights"])
            loss = ce
            terms = {"policy_loss": ce}
            if self.aux_head is not None:
                aux_terms = aux_loss(self.aux_head(features), b["aux"])
                loss = loss + cfg.aux_coef * aux_terms["loss"]
                terms.update(
                    aux_loss=aux_terms["loss"], aux_rotation_loss=aux_terms["rotation_loss"],
                    aux_overlap_accuracy=aux_terms["overlap_accuracy"],
                )
            if not bool(torch.isfinite(loss)) and not distributed.is_active():  # distributed: caught below
                raise FloatingPointError(f"non-finite DAgger loss: {loss.item()}")
            self.optimizer.zero_grad(set_to_none=True)
            loss.backward()
            distributed.allreduce_gradients(self.params)  # under torchrun: average over ranks, before clipping
            grad_norm = nn.utils.clip_grad_norm_(self.params, cfg.max_grad_norm)
            if not torch.isfinite(grad_norm):
                raise FloatingPointError(f"non-finite gradient norm: {grad_norm.item()}")
            self.optimizer.step()
            with torch.no_grad():
                pred = logits.argmax(dim=-1)
                is_stop = labels[:, STOP]
                terms["accuracy"] = labels.gather(1, pred[:, None]).float().mean()
                terms["stop_accuracy"] = (
                    (pred[is_stop] == STOP).float().mean() if bool(is_stop.any()) else torch.tensor(float("nan"))
                )
                terms["entropy"] = dist.entropy().mean()
                terms["grad_norm"] = grad_norm
            for key, value in terms.items():
                v = float(value.detach()) if isinstance(value, torch.Tensor) else float(value)
                if key == "stop_accuracy" and math.isnan(v):
                    continue
                totals[key] = totals.get(key, 0.0) + v
                totals[f"_n_{key}"] = totals.get(f"_n_{key}", 0.0) + 1.0
        return {k: v / totals[f"_n_{k}"] for k, v in totals.items() if not k.startswith("_n_")}

    @scoped(lambda self: self.policy.heavy)
    def train_update(self, should_stop: Callable[[], bool] = never) -> dict[str, Any]:
        """One mixed rollout + training on the buffer; returns the stats (:data:`STAT_KEYS`, plus
        :data:`AUX_STAT_KEYS` with aux on), ``update``, ``env_steps``, ``level`` and ``episodes``.

        ``should_stop`` is polled before every rollout step (see ``PPOTrainer.train_update``; with
        ``overlap_rollout`` once, before the update). Raises ``FloatingPointError`` when the loss, the gradient or
        the updated weights are not finite.
        """
        self._begin_update()
        cfg = self.cfg
        if cfg.linear_decay and self.total_updates > 0:
            self.lr = cfg.lr * max(0.0, 1.0 - self.update / self.total_updates)
        else:
            self.lr = cfg.lr
        for group in self.optimizer.param_groups:
            group["lr"] = self.lr
        beta = beta_at(cfg, self.update)

        new_chunks = (cfg.rollout_steps // cfg.seq_len) * self.env.num_envs
        if self._acting is not None and len(self.buffer) > 0:
            stats, records, rollout_stats = self._overlapped_update(beta, new_chunks, should_stop)
        else:
            with no_distribution_validation():
                records, rollout_stats = self.collect_rollout(beta, should_stop)
            self._before_update = None
            with self._timed_update():
                with no_distribution_validation():
                    stats = self._train(new_chunks)
                self._check_weights(self.params)
        self.update += 1
        stats.setdefault("stop_accuracy", float("nan"))
        stats.update(rollout_stats)
        stats["lr"] = self.lr
        stats["beta"] = beta
        stats["buffer_steps"] = len(self.buffer) * cfg.seq_len
        return self._finish_stats(stats, records)

    def _overlapped_update(
        self, beta: float, new_chunks: int, should_stop: Callable[[], bool]
    ) -> tuple[dict[str, Any], list[dict[str, Any]], dict[str, float]]:
        """``overlap_rollout``: the rollout in a second thread, acting with a copy of the weights, while this thread
        runs the gradient steps on the buffer; the rollout's chunks join the buffer after both end. Returns the
        training stats, the rollout's records and its stats. ``should_stop`` is read once, before anything starts."""
        if should_stop():
            raise self._abandoned()
        self._before_update = None
        self._acting.load_state_dict(self.policy.state_dict())
        outcome: dict[str, Any] = {}

        def collect() -> None:  # the global switch of the distributions' checks is this thread's, below
            try:
                outcome["rollout"] = self._collect(beta, self._acting)
            except BaseException as error:  # re-raised in the training thread below
                outcome["error"] = error

        with no_distribution_validation():  # around both threads: entered and left once
            worker = threading.Thread(target=collect, name="findview-dagger-rollout", daemon=True)
            worker.start()
            try:
                with self._timed_update():
                    stats: dict[str, Any] = self._train(new_chunks)
                    self._check_weights(self.params)
            finally:
                worker.join()
        if "error" in outcome:
            raise outcome["error"]
        records, rollout_stats, chunks = outcome["rollout"]
        self._push(chunks)
        return stats, records, rollout_stats

    # ---------------------------------------------------------------------------------------------
    # Resume state (the common parts: Trainer)
    # ---------------------------------------------------------------------------------------------

    def _learner_parts(self) -> dict[str, Any]:
        """The aux head, optimizer, lr, buffer sampling generator and (``save_buffer``) the buffer."""
        return {
            "aux_head": self.aux_head.state_dict() if self.aux_head is not None else None,
            "optimizer": self.optimizer.state_dict(),
            "lr": self.lr,
            "sample_rng": self.sample_generator.get_state(),
            "buffer": self.buffer.state_dict() if self.cfg.save_buffer else None,
        }

    def _rollout_parts(self) -> dict[str, Any]:
        """``current``: observation (N, 3, H, W) uint8, GRU state, masks; ``mix_rng``; the search memory."""
        return {
            "current": {
                "view": self.view.cpu().clone(),
                "target": self.target.cpu().clone(),
                "hidden": self.hidden.cpu().clone(),
                "masks": self.masks.cpu().clone(),
            },
            "mix_rng": self.mix_generator.get_state(),
            "revisits": self.revisits.state_dict() if self.revisits is not None else None,
        }

    def _check_state(self, state: Mapping[str, Any]) -> None:
        if (self.aux_head is None) != (state.get("aux_head") is None):
            raise ValueError(
                "saved DAgger state and this run disagree on the auxiliary loss (aux_coef > 0 in one only)"
            )

    def _load_learner_parts(self, state: Mapping[str, Any]) -> None:
        if self.aux_head is not None:
            self.aux_head.load_state_dict(state["aux_head"])
        self.optimizer.load_state_dict(state["optimizer"])
        self.lr = float(state["lr"])
        self.sample_generator.set_state(state["sample_rng"])
        if state.get("buffer") is not None:
            self.buffer.load_state_dict(state["buffer"])
            self.buffer.recompute_fixed(self.policy.fixed_features)

    def _load_rollout_parts(self, state: Mapping[str, Any]) -> None:
        cur = state.get("current")
        if cur is not None:
            self.view.copy_(cur["view"])
            self.target.copy_(cur["target"])
            self.hidden = cur["hidden"].to(self.device).clone()
            self.masks = cur["masks"].to(self.device).clone()
        self.mix_generator.set_state(state["mix_rng"])
        if self.revisits is not None and state.get("revisits") is not None:
            self.revisits.load_state_dict(state["revisits"])
