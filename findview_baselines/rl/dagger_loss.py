"""The imitation loss of DAgger: :func:`set_nll`, the (weighted) negative log-likelihood of the set of
actions the expert accepts (the plain cross-entropy for a one-action set)."""

from __future__ import annotations

import torch

__all__ = ["set_nll"]


def set_nll(
    logits: torch.Tensor,
    accepted: torch.Tensor,
    class_weights: torch.Tensor | None = None,
    row_weights: torch.Tensor | None = None,
) -> torch.Tensor:
    """Mean negative log-likelihood of the accepted actions: ``-log sum_{a in set} softmax(logits)_a``.

    Args:
        logits: (B, 5) action logits.
        accepted: (B, 5) bool, at least one true per row (a one-hot row gives the plain cross-entropy).
        class_weights: optional (5,) weights; a row weighs the largest weight among its accepted actions
            (so ``stop_weight`` applies to rows whose answer is ``stop``); the mean is weighted, as in
            ``torch.nn.functional.cross_entropy``.
        row_weights: optional (B,) weights multiplying each row's weight (e.g. ``search_weight`` on the
            no-overlap rows).
    """
    log_probs = torch.log_softmax(logits, dim=-1)
    nll = -torch.logsumexp(log_probs.masked_fill(~accepted, float("-inf")), dim=-1)
    if class_weights is None and row_weights is None:
        return nll.mean()
    w = (accepted.float() * class_weights).amax(dim=-1) if class_weights is not None else torch.ones_like(nll)
    if row_weights is not None:
        w = w * row_weights
    return (w * nll).sum() / w.sum()
