"""The replay buffer of DAgger: :class:`SequenceBuffer`, a FIFO ring of labelled sequences (images, GRU
state at the sequence start, episode masks, accepted actions, loss weights, auxiliary targets) that the
trainer samples mini-batches of chunks from and stores in its checkpoints."""

from __future__ import annotations

from typing import Any, Callable, Mapping

import torch

from findview.task import NUM_ACTIONS
from findview_baselines.rl.storage import AUX_SIZE

__all__ = ["SequenceBuffer"]


class SequenceBuffer:
    """FIFO ring of ``capacity`` labelled sequences of ``seq_len`` steps on ``device``.

    Per chunk: view, target (L, 3, H, W) uint8; hidden0 (hidden,) the GRU state entering its first step;
    masks (L,) (0 where an episode starts); labels (L, 5) bool (the accepted actions); aux (L, 3) float
    (when ``with_aux``); fixed (L, fixed_size) float, the policy's parameter-free encoder output for each
    step (when ``fixed_size > 0``: computed once when the chunk arrives instead of at every gradient step;
    not saved by :meth:`state_dict`, :meth:`recompute_fixed` rebuilds it from the images); memory (L, memory_size)
    float, the search memory's features the policy read at each step (when ``memory_size > 0``; saved).
    """

    def __init__(
        self,
        capacity: int,
        seq_len: int,
        height: int,
        width: int,
        hidden_size: int,
        device: torch.device | str = "cpu",
        with_aux: bool = False,
        fixed_size: int = 0,
        memory_size: int = 0,
        with_penalty: bool = False,
    ) -> None:
        self.capacity, self.seq_len = int(capacity), int(seq_len)
        self.device = torch.device(device)
        c, L, kw = self.capacity, self.seq_len, {"device": self.device}
        self.view = torch.empty(c, L, 3, height, width, dtype=torch.uint8, **kw)
        self.target = torch.empty(c, L, 3, height, width, dtype=torch.uint8, **kw)
        self.hidden0 = torch.empty(c, hidden_size, **kw)
        self.masks = torch.empty(c, L, **kw)
        self.labels = torch.empty(c, L, NUM_ACTIONS, dtype=torch.bool, **kw)
        self.weights = torch.ones(c, L, **kw)
        self.aux = torch.empty(c, L, AUX_SIZE, **kw) if with_aux else None
        self.fixed = torch.empty(c, L, int(fixed_size), **kw) if fixed_size > 0 else None
        self.memory = torch.empty(c, L, int(memory_size), **kw) if memory_size > 0 else None
        self.penalty = torch.empty(c, L, 4, **kw) if with_penalty else None
        self.pos = 0  # next slot to write
        self.size = 0  # filled slots

    def __len__(self) -> int:
        return self.size

    def add(
        self,
        view: torch.Tensor,
        target: torch.Tensor,
        hidden0: torch.Tensor,
        masks: torch.Tensor,
        labels: torch.Tensor,
        aux: torch.Tensor | None = None,
        weights: torch.Tensor | None = None,
        fixed: torch.Tensor | None = None,
        memory: torch.Tensor | None = None,
        penalty: torch.Tensor | None = None,
    ) -> None:
        """Append ``n`` chunks given time-major: view / target (L, n, 3, H, W), hidden0 (n, hidden), masks
        (L, n), labels (L, n, 5) bool, aux (L, n, 3), weights (L, n) loss weights (default 1), fixed (L, n,
        fixed_size), memory (L, n, memory_size) and penalty (L, n, 4), the search memory's move penalties in logit units (each
        required when the buffer stores it). The oldest chunks are overwritten when full."""
        n = hidden0.shape[0]
        if n > self.capacity:  # keep the newest
            keep = slice(n - self.capacity, n)
            view, target, masks, labels = view[:, keep], target[:, keep], masks[:, keep], labels[:, keep]
            hidden0 = hidden0[keep]
            aux = None if aux is None else aux[:, keep]
            weights = None if weights is None else weights[:, keep]
            fixed = None if fixed is None else fixed[:, keep]
            memory = None if memory is None else memory[:, keep]
            penalty = None if penalty is None else penalty[:, keep]
            n = self.capacity
        slots = (torch.arange(n) + self.pos) % self.capacity
        slots = slots.to(self.device)
        self.view[slots] = view.transpose(0, 1).to(self.device)
        self.target[slots] = target.transpose(0, 1).to(self.device)
        self.hidden0[slots] = hidden0.to(self.device)
        self.masks[slots] = masks.transpose(0, 1).to(self.device, torch.float32)
        self.labels[slots] = labels.transpose(0, 1).to(self.device, torch.bool)
        self.weights[slots] = 1.0 if weights is None else weights.transpose(0, 1).to(self.device, torch.float32)
        if self.aux is not None:
            if aux is None:
                raise ValueError("this buffer stores aux targets; add() needs aux")
            self.aux[slots] = aux.transpose(0, 1).to(self.device, torch.float32)
        if self.fixed is not None:
            if fixed is None:
                raise ValueError("this buffer stores the fixed encoder inputs; add() needs fixed")
            self.fixed[slots] = fixed.transpose(0, 1).to(self.device, torch.float32)
        if self.memory is not None:
            if memory is None:
                raise ValueError("this buffer stores the search memory's features; add() needs memory")
            self.memory[slots] = memory.transpose(0, 1).to(self.device, torch.float32)
        if self.penalty is not None:
            if penalty is None:
                raise ValueError("this buffer stores the search memory's move penalties; add() needs penalty")
            self.penalty[slots] = penalty.transpose(0, 1).to(self.device, torch.float32)
        self.pos = (self.pos + n) % self.capacity
        self.size = min(self.capacity, self.size + n)

    def sample(self, count: int, generator: torch.Generator) -> torch.Tensor:
        """``min(count, size)`` distinct chunk indices, uniform (CPU ``generator``)."""
        if self.size == 0:
            raise ValueError("the DAgger buffer is empty")
        return torch.randperm(self.size, generator=generator)[: min(count, self.size)].to(self.device)

    def batch(self, index: torch.Tensor, images: bool = True) -> dict[str, torch.Tensor]:
        """The chunks ``index`` (b,), time-major flattened like a rollout: obs (L*b, 3, H, W) (only with ``images``:
        a trainer that reads the cached ``fixed`` rows does not need them, and gathering them is a tenth of a
        gradient step of the robust preset), masks (L*b,), labels (L*b, 5), weights (L*b,), aux (L*b, 3) or absent,
        fixed (L*b, fixed_size) or absent, hidden0 (b, hidden)."""

        def tm(x: torch.Tensor) -> torch.Tensor:
            return x[index].transpose(0, 1).flatten(0, 1)

        out = {"view": tm(self.view), "target": tm(self.target)} if images else {}
        out |= {
            "masks": tm(self.masks),
            "labels": tm(self.labels),
            "weights": tm(self.weights),
            "hidden0": self.hidden0[index],
        }
        if self.aux is not None:
            out["aux"] = tm(self.aux)
        if self.fixed is not None:
            out["fixed"] = tm(self.fixed)
        if self.memory is not None:
            out["memory"] = tm(self.memory)
        if self.penalty is not None:
            out["penalty"] = tm(self.penalty)
        return out

    def recompute_fixed(self, fixed_of: Callable[[dict[str, torch.Tensor]], torch.Tensor], chunks: int = 32) -> None:
        """Fill ``fixed`` of every stored chunk from its images: ``fixed_of({"view", "target"})`` maps (B, 3,
        H, W) uint8 to (B, fixed_size) (``Policy.fixed_features``), run ``chunks`` chunks at a time."""
        if self.fixed is None:
            return
        L = self.seq_len
        for start in range(0, self.size, chunks):
            idx = slice(start, min(self.size, start + chunks))
            k = idx.stop - idx.start
            obs = {"view": self.view[idx].flatten(0, 1), "target": self.target[idx].flatten(0, 1)}
            self.fixed[idx] = fixed_of(obs).view(k, L, -1)

    def state_dict(self) -> dict[str, Any]:
        """The filled part (CPU tensors) and the write position."""
        n = self.size
        state: dict[str, Any] = {
            "pos": self.pos,
            "size": n,
            "view": self.view[:n].cpu().clone(),
            "target": self.target[:n].cpu().clone(),
            "hidden0": self.hidden0[:n].cpu().clone(),
            "masks": self.masks[:n].cpu().clone(),
            "labels": self.labels[:n].cpu().clone(),
            "weights": self.weights[:n].cpu().clone(),
        }
        if self.aux is not None:
            state["aux"] = self.aux[:n].cpu().clone()
        if self.memory is not None:
            state["memory"] = self.memory[:n].cpu().clone()
        if self.penalty is not None:
            state["penalty"] = self.penalty[:n].cpu().clone()
        return state

    def load_state_dict(self, state: Mapping[str, Any]) -> None:
        n = int(state["size"])
        if n > self.capacity:
            raise ValueError(
                f"saved DAgger buffer holds {n} chunks, this one only {self.capacity} (dagger.buffer_size)"
            )
        if tuple(state["view"].shape[1:]) != tuple(self.view.shape[1:]):
            raise ValueError(
                f"saved DAgger buffer chunks are {tuple(state['view'].shape[1:])}, "
                f"expected {tuple(self.view.shape[1:])}"
            )
        for name in ("view", "target", "hidden0", "masks", "labels"):
            getattr(self, name)[:n] = state[name].to(self.device)
        self.weights[:n] = state["weights"].to(self.device) if state.get("weights") is not None else 1.0
        if self.aux is not None:
            if state.get("aux") is None:
                raise ValueError("saved DAgger buffer has no aux targets but dagger.aux_coef > 0")
            self.aux[:n] = state["aux"].to(self.device)
        if self.memory is not None:
            if state.get("memory") is None:
                raise ValueError("saved DAgger buffer has no search-memory features but the policy reads them (agent.memory_inputs)")
            self.memory[:n] = state["memory"].to(self.device)
        if self.penalty is not None:
            if state.get("penalty") is None:
                raise ValueError("saved DAgger buffer has no move penalties but trainer.dagger.penalised_loss is on")
            self.penalty[:n] = state["penalty"].to(self.device)
        self.size, self.pos = n, int(state["pos"]) % self.capacity
