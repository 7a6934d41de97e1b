"""The auxiliary relative-rotation head (training only): :class:`AuxHead` on the policy's pre-GRU
features and its loss :func:`aux_loss`. The head is owned by the optimiser (PPO / DAgger), not by the
policy, so policy checkpoints are the same with and without it."""

from __future__ import annotations

import torch
from torch import nn

__all__ = ["AuxHead", "aux_loss"]


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
