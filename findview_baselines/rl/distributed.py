"""Decentralised distributed training (DD-PPO style) over ``torch.distributed``, started by ``torchrun``.

Every rank runs the whole training loop on its own environments (``trainer.num_envs`` per rank, on its
own shard of the train panoramas) and its own copy of the policy; after every backward pass the
gradients are averaged over the ranks (:func:`allreduce_gradients`), so the weights stay identical
everywhere without a parameter server. What a trainer calls (all are no-ops in a single-process run,
so that path stays exactly as it was):

* :func:`allreduce_gradients` between ``loss.backward()`` and the gradient clipping;
* :func:`mean_std` for statistics over the whole batch (PPO's advantage normalisation);
* :func:`global_steps` to count env steps of all ranks.

The run loop (:mod:`findview_baselines.training`) does the rest for any trainer: per-rank seeds
(``seed + rank``) and shards (rank ``r`` of ``K`` takes train images ``r::K``), rank 0's initial
weights for all (:func:`broadcast_modules`), :func:`reduce_stats` after every update, the agreement on a stop (:class:`AgreedStop`), and rank 0 alone writing
checkpoints, TensorBoard and the lock (:func:`gather_to_main` collects the other ranks' resume state).

Optional straggler preemption (``trainer.preempt_fraction``, PPO): :class:`Preemption`.

Backends: ``trainer.dist_backend=auto`` picks NCCL when the run's device is CUDA, else gloo. Control
traffic (stop flags, stats, resume state: small CPU objects) always goes over a separate gloo group, so
it never waits behind GPU work and needs no device copies.
"""

from __future__ import annotations

import datetime
import logging
import math
import os
from dataclasses import dataclass
from typing import Any, Callable, Iterable, Mapping, Sequence, TypeVar

import numpy as np
import torch

__all__ = [
    "DistInfo",
    "TORCHRUN_VARS",
    "launched_by_torchrun",
    "setup",
    "teardown",
    "is_active",
    "rank",
    "world_size",
    "local_rank",
    "is_main",
    "barrier",
    "allreduce_gradients",
    "broadcast_modules",
    "mean_std",
    "global_steps",
    "reduce_stats",
    "gather_to_main",
    "all_gather",
    "main_first",
    "shard",
    "reseed",
    "AgreedStop",
    "Preemption",
    "all_sum",
]

log = logging.getLogger(__name__)

T = TypeVar("T")

#: the environment variables torchrun sets for every worker
TORCHRUN_VARS = ("RANK", "WORLD_SIZE", "LOCAL_RANK", "MASTER_ADDR", "MASTER_PORT")
BACKENDS = ("auto", "nccl", "gloo")
#: rollout steps between two stop-flag all-reduces of :class:`AgreedStop` (a stop waits at most twice that)
STOP_POLL_STEPS = 4


@dataclass(frozen=True)
class DistInfo:
    """This process's place in the job."""

    rank: int
    world_size: int
    local_rank: int
    backend: str
    """Backend of the data group (gradients, advantage statistics): ``nccl`` or ``gloo``."""


class _State:
    info: DistInfo | None = None
    control: Any = None  # gloo process group for CPU objects / flags
    owns_group: bool = False  # setup() created the default group (teardown destroys it)


_state = _State()


def launched_by_torchrun(environ: Mapping[str, str] | None = None) -> bool:
    """Whether the torchrun variables (:data:`TORCHRUN_VARS`) are all set."""
    environ = os.environ if environ is None else environ
    return all(environ.get(k) for k in TORCHRUN_VARS)


def _resolve_backend(backend: str, device: torch.device) -> str:
    if backend not in BACKENDS:
        raise ValueError(f"trainer.dist_backend={backend!r}: expected one of {', '.join(BACKENDS)}")
    if backend == "auto":
        return "nccl" if device.type == "cuda" else "gloo"
    if backend == "nccl" and device.type != "cuda":
        raise ValueError(f"trainer.dist_backend=nccl needs a CUDA device, but the run's device is {device}; "
                         f"use trainer.dist_backend=gloo or auto")
    return backend


def setup(backend: str = "auto", device: torch.device | str = "cpu", timeout_min: float = 60.0) -> DistInfo:
    """Join the job described by torchrun's environment variables (``env://``).

    Args:
        backend: ``auto`` (NCCL for a CUDA ``device``, else gloo), ``nccl`` or ``gloo``.
        device: the run's device; for CUDA this rank uses ``cuda:LOCAL_RANK`` (set as current device).
        timeout_min: minutes a collective may wait for the slowest rank (rank 0 validates while the others
            wait) before the job fails.

    Raises:
        ValueError: torchrun's variables are missing (one line naming them), or a bad backend.
    """
    import torch.distributed as dist

    if _state.info is not None:
        return _state.info
    missing = [k for k in TORCHRUN_VARS if not os.environ.get(k)]
    if missing:
        raise ValueError(
            f"trainer.distributed=true but {', '.join(missing)} {'is' if len(missing) == 1 else 'are'} not set: "
            f"start the run with torchrun --nproc_per_node=K tools/train.py ... (see docs/CLUSTER.md), "
            f"or drop trainer.distributed"
        )
    device = torch.device(device)
    name = _resolve_backend(backend, device)
    local = int(os.environ["LOCAL_RANK"])
    if device.type == "cuda":
        torch.cuda.set_device(local)  # one GPU per rank (also for "cuda" without an index)
    timeout = datetime.timedelta(minutes=float(timeout_min))
    owns = False
    if not dist.is_initialized():
        dist.init_process_group(backend=name, init_method="env://", timeout=timeout)
        owns = True
    control = dist.new_group(backend="gloo", timeout=timeout) if name != "gloo" else dist.new_group(timeout=timeout)
    _state.info = DistInfo(dist.get_rank(), dist.get_world_size(), local, name)
    _state.control, _state.owns_group = control, owns
    log.info("rank %d of %d (local rank %d, backend %s, pid %d)", _state.info.rank, _state.info.world_size,
             local, name, os.getpid())
    return _state.info


def teardown() -> None:
    """Leave the job (destroys the process groups that :func:`setup` made)."""
    import torch.distributed as dist

    if _state.info is None:
        return
    if _state.owns_group and dist.is_initialized():
        dist.destroy_process_group()
    _state.info, _state.control, _state.owns_group = None, None, False


def is_active() -> bool:
    """:func:`setup` ran in this process (and :func:`teardown` did not)."""
    return _state.info is not None


def rank() -> int:
    """This process's rank (0 in a single-process run)."""
    return _state.info.rank if _state.info is not None else 0


def world_size() -> int:
    """Number of processes (1 in a single-process run)."""
    return _state.info.world_size if _state.info is not None else 1


def local_rank() -> int:
    """Rank on this machine (0 in a single-process run)."""
    return _state.info.local_rank if _state.info is not None else 0


def is_main() -> bool:
    """Rank 0 (or a single-process run): the one that writes files."""
    return rank() == 0


def barrier() -> None:
    """Wait for every rank (over the control group; no-op in a single-process run)."""
    if _state.info is not None:
        import torch.distributed as dist

        dist.barrier(group=_state.control)


# --------------------------------------------------------------------------------------------------
# What trainers call
# --------------------------------------------------------------------------------------------------


def allreduce_gradients(params: Iterable[torch.nn.Parameter]) -> None:
    """Average the ``.grad`` of ``params`` over all ranks, in place (call before clipping the norm).

    Every rank must pass the same parameters in the same order. A parameter without a gradient counts
    as a zero gradient (and gets one), so ranks never disagree on the set. One flat all-reduce per call.
    No-op in a single-process run.
    """
    if _state.info is None or _state.info.world_size == 1:
        return
    import torch.distributed as dist

    params = list(params)
    grads = []
    for p in params:
        if p.grad is None:
            p.grad = torch.zeros_like(p)
        grads.append(p.grad)
    if not grads:
        return
    flat = torch.cat([g.reshape(-1) for g in grads])
    dist.all_reduce(flat, op=dist.ReduceOp.SUM)
    flat.div_(_state.info.world_size)
    offset = 0
    for g in grads:
        n = g.numel()
        g.copy_(flat[offset:offset + n].view_as(g))
        offset += n


def broadcast_modules(modules: Iterable[torch.nn.Module | None], src: int = 0) -> None:
    """Copy rank ``src``'s parameters and buffers of ``modules`` (``None`` entries skipped) to every rank.

    The run loop calls it once after building the policy: every rank seeds its own RNGs (``seed + rank``),
    so their freshly initialised weights differ until rank 0's are broadcast. No-op in a single process."""
    if _state.info is None or _state.info.world_size == 1:
        return
    import torch.distributed as dist

    for module in modules:
        if module is None:
            continue
        with torch.no_grad():
            for tensor in [*module.parameters(), *module.buffers()]:
                dist.broadcast(tensor.data, src=src)


def mean_std(x: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """Mean and (unbiased, ``n - 1``) standard deviation of ``x`` over the elements of all ranks.

    Single process: exactly ``x.mean(), x.std()``. Distributed: two all-reduces (count and sum, then the
    sum of squared deviations from the global mean), so the result equals one process holding every
    rank's ``x`` up to float rounding. Returns 0-d tensors on ``x.device``.
    """
    if _state.info is None or _state.info.world_size == 1:
        return x.mean(), x.std()
    import torch.distributed as dist

    acc = torch.stack([torch.tensor(float(x.numel()), device=x.device, dtype=torch.float64),
                       x.detach().double().sum()])
    dist.all_reduce(acc, op=dist.ReduceOp.SUM)
    count, total = acc[0], acc[1]
    mean = total / count
    sq = ((x.detach().double() - mean) ** 2).sum()
    dist.all_reduce(sq, op=dist.ReduceOp.SUM)
    std = (sq / (count - 1)).clamp_min(0).sqrt()
    return mean.to(x.dtype), std.to(x.dtype)


def global_steps(local_steps: int) -> int:
    """Env steps of all ranks for ``local_steps`` on this one (every rank steps as many envs)."""
    return int(local_steps) * world_size()


# --------------------------------------------------------------------------------------------------
# What the run loop calls
# --------------------------------------------------------------------------------------------------


def _control() -> Any:
    return _state.control


def all_gather(obj: T) -> list[T]:
    """Every rank's ``obj`` (picklable), in rank order, on every rank (``[obj]`` in a single process)."""
    if _state.info is None:
        return [obj]
    import torch.distributed as dist

    out: list[Any] = [None] * _state.info.world_size
    dist.all_gather_object(out, obj, group=_control())
    return out


def gather_to_main(obj: T) -> list[T] | None:
    """Every rank's ``obj`` in rank order on rank 0, ``None`` elsewhere (``[obj]`` in a single process).

    Used for the per-rank resume state (environments, RNGs, storage), which can be megabytes."""
    if _state.info is None:
        return [obj]
    import torch.distributed as dist

    out: list[Any] | None = [None] * _state.info.world_size if _state.info.rank == 0 else None
    dist.gather_object(obj, out, dst=0, group=_control())
    return out


def main_first(fn: Callable[[], T]) -> T:
    """Run ``fn`` on rank 0, then (if it succeeded) on the other ranks; for steps that create shared files
    (making the data set). When rank 0 fails, the others raise ``ValueError`` naming the problem instead
    of waiting for it."""
    if _state.info is None or _state.info.world_size == 1:
        return fn()
    error: BaseException | None = None
    result: Any = None
    if is_main():
        try:
            result = fn()
        except BaseException as err:  # noqa: BLE001 - re-raised below, after telling the others
            error = err
    message = all_gather(None if error is None else f"{type(error).__name__}: {error}")[0]
    if error is not None:
        raise error
    if message is not None:
        raise ValueError(f"rank 0 failed ({message})")
    return result if is_main() else fn()


def reduce_stats(stats: Mapping[str, Any]) -> dict[str, Any]:
    """One update's stats of all ranks, as one process would report them for the whole batch.

    Float scalars are averaged over the ranks (NaN entries, e.g. a rank without any ``stop`` label, are
    left out of the mean); ``episodes`` (lists of finished-episode records) are concatenated in rank
    order; everything else (``update``, ``env_steps``, ``level``, ``lr``, ...) is rank 0's value (it is
    the same on every rank). Single process: ``stats`` itself, unchanged.
    """
    if _state.info is None or _state.info.world_size == 1:
        return stats  # type: ignore[return-value]
    keys = sorted(k for k, v in stats.items() if isinstance(v, float))
    values = [float(stats[k]) for k in keys]
    parts = all_gather((keys, values, list(stats.get("episodes", []))))
    out = dict(stats)
    if any(p[0] != keys for p in parts):
        raise RuntimeError(f"ranks report different stats: {[p[0] for p in parts]}")
    table = np.array([p[1] for p in parts], dtype=np.float64).reshape(len(parts), len(keys))
    for j, key in enumerate(keys):
        column = table[:, j][~np.isnan(table[:, j])]
        out[key] = float(column.mean()) if column.size else math.nan
    if "episodes" in stats:
        out["episodes"] = [record for p in parts for record in p[2]]
    return out


def shard(items: Sequence[T], rank_: int, world: int, what: str = "train images") -> list[T]:
    """Rank ``rank_``'s share ``items[rank_::world]`` (disjoint, sizes differ by at most one).

    Raises ``ValueError`` when there are fewer items than ranks."""
    items = list(items)
    if world <= 1:
        return items
    if len(items) < world:
        raise ValueError(f"{len(items)} {what} cannot be shared by {world} ranks (each needs at least one); "
                         f"use fewer processes or a larger data set")
    return items[rank_::world]


def reseed(seed: int, rank_: int, update: int) -> int:
    """A deterministic seed for rank ``rank_`` of a run resumed at ``update`` with another number of ranks
    (its saved per-rank RNG / environment states do not map onto the new ranks)."""
    return int(np.random.SeedSequence([int(seed) % 2**32, int(rank_), int(update), 0xD1]).generate_state(1)[0])


def all_sum(values: Sequence[float]) -> list[float]:
    """Element-wise sum of ``values`` over all ranks (control group, float64); ``values`` in one process."""
    if _state.info is None:
        return [float(v) for v in values]
    import torch.distributed as dist

    t = torch.tensor([float(v) for v in values], dtype=torch.float64)
    dist.all_reduce(t, op=dist.ReduceOp.SUM, group=_control())
    return t.tolist()


class Preemption:
    """DD-PPO's straggler preemption (``trainer.preempt_fraction``).

    Once ``ceil(fraction * K)`` ranks have collected their whole rollout, the ranks still collecting stop
    (each after at least ``min_share`` of its ``rollout_steps``) and the update goes on with the shorter
    rollouts: a slow rank no longer holds the others up. The ranks count finished rollouts in torchrun's
    key-value store (no collective call, so the ranks never wait for each other while they collect).

    A shortened rollout is a complete one of fewer steps: GAE bootstraps from the value of the observation
    where it stopped, and that observation starts the next rollout. Every rank's loss is the mean over its
    own samples, so the ranks weigh equally in the averaged gradient whatever their rollout length.
    Preempted runs are not reproducible (who is preempted depends on timing).
    """

    def __init__(self, fraction: float, min_share: float = 0.25) -> None:
        if _state.info is None:
            raise ValueError("trainer.preempt_fraction needs trainer.distributed=true (torchrun)")
        if not 0.0 < fraction <= 1.0 or not 0.0 < min_share <= 1.0:
            raise ValueError(f"preemption: fraction {fraction} and min_share {min_share} must be in (0, 1]")
        from torch.distributed import distributed_c10d

        self.needed = max(1, math.ceil(fraction * _state.info.world_size))
        self.min_share = float(min_share)
        self.store = distributed_c10d._get_default_store()  # torchrun's rendezvous store (env://)
        # a key prefix of this session, so that counts of an earlier attempt in the same store never count
        self.prefix = f"findview/{all_gather(os.urandom(8).hex())[0]}/"

    def min_steps(self, rollout_steps: int) -> int:
        """Steps every rank collects before it may be preempted."""
        return max(1, math.ceil(self.min_share * rollout_steps))

    def finished(self, update: int) -> None:
        """This rank has collected its whole rollout of ``update``."""
        self.store.add(f"{self.prefix}done/{update}", 1)

    def preempted(self, update: int) -> bool:
        """Enough ranks have finished the rollout of ``update``: stop collecting (one store round trip)."""
        return self.store.add(f"{self.prefix}done/{update}", 0) >= self.needed

    def publish_stop(self, signum: int) -> None:
        """Tell the other ranks (through the store) that this one got a signal."""
        self.store.add(f"{self.prefix}stop", int(signum))

    def stop_published(self) -> bool:
        """Some rank got a signal (through the store; no collective)."""
        return self.store.add(f"{self.prefix}stop", 0) > 0


# --------------------------------------------------------------------------------------------------
# Stopping together
# --------------------------------------------------------------------------------------------------


class AgreedStop:
    """All ranks stop at the same safe point when any of them got a signal.

    Wraps this rank's :class:`~findview_baselines.rl.safety.StopOnSignal` and has its interface
    (``requested``, ``signum``, ``__call__`` as the trainers' ``should_stop``, ``agree()``):

    * ``agree()`` (between updates): a blocking all-reduce (max) of the local signal number; every rank
      gets the same answer.
    * ``__call__()`` (the trainers poll it before every rollout step): every ``every``-th poll starts an
      all-reduce and reads the one started ``every`` polls earlier, so the rollout neither waits on the
      network nor runs in lock-step with the other ranks (they may drift ``every`` steps apart). Every
      rank polls the same number of times, so every rank abandons the rollout at the same step, at most
      ``2 * every`` steps after the signal.

    With straggler preemption (:class:`Preemption`) the rollout polls go through the store instead, and
    the trainer makes the ranks agree after the rollout.

    The agreed signal number is the largest one raised on any rank (SIGTERM 15 > SIGUSR1 10 > SIGINT 2),
    so every rank exits with the same status.
    """

    def __init__(self, signals: Any, every: int = STOP_POLL_STEPS, preemption: Preemption | None = None) -> None:
        self.signals = signals
        self.every = max(1, int(every))
        self.preemption = preemption
        self._published = False
        self._polls = 0
        self._agreed = 0
        self._pending: tuple[Any, torch.Tensor] | None = None

    def _local(self) -> torch.Tensor:
        return torch.tensor([int(self.signals.signum or 0)], dtype=torch.int64)

    def _finish(self) -> None:
        if self._pending is not None:
            work, flag = self._pending
            self._pending = None
            work.wait()
            self._agreed = max(self._agreed, int(flag.item()))

    @property
    def signum(self) -> int | None:
        """The agreed signal, or ``None``."""
        return self._agreed or None

    @property
    def requested(self) -> bool:
        return self._agreed != 0

    def __call__(self) -> bool:
        import torch.distributed as dist

        if self.preemption is not None:
            # ranks poll different numbers of times when some are preempted: no collective here; the
            # trainer agrees on abandoning after the rollout (all_sum) and learn() on the signal (agree)
            if self.signals.signum and not self._published:
                self.preemption.publish_stop(self.signals.signum)
                self._published = True
            return bool(self.signals.signum) or self.preemption.stop_published()
        self._polls += 1
        if (self._polls - 1) % self.every:
            return self.requested
        self._finish()
        flag = self._local()
        self._pending = (dist.all_reduce(flag, op=dist.ReduceOp.MAX, group=_control(), async_op=True), flag)
        return self.requested

    def agree(self) -> bool:
        """Blocking agreement (between updates); True when some rank asked to stop."""
        import torch.distributed as dist

        self._finish()
        flag = self._local()
        dist.all_reduce(flag, op=dist.ReduceOp.MAX, group=_control())
        self._agreed = max(self._agreed, int(flag.item()))
        return self.requested

    def close(self) -> None:
        """Complete a pending poll (every rank calls it at the same point, at the end of the loop)."""
        self._finish()

