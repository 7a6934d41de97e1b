"""Find the distinct images of a batch, so that work depending on one image alone runs once per image.

A PPO update re-encodes a whole rollout, ``T * N`` rows, but the target of an environment is the same on
every step of an episode: a 16 x 16 rollout holds about 16-30 distinct targets among 256 rows. A target-only
encoder run on the distinct rows and gathered back gives the same features, and the same gradients (the
gather's backward sums the duplicates' gradients, which is what running every row would sum), at a tenth
of the cost.

The grouping is exact: rows are grouped by a probe of a few pixels, and every row is then compared in full
with its group's first row; if any differs (two images that agree on every probed pixel), no grouping is
used. Works on any device; on CUDA ``torch.unique`` synchronises with the host.
"""

from __future__ import annotations

import torch

__all__ = ["PROBE_PIXELS", "distinct_rows", "regroup"]

#: values sampled per row (evenly spaced over the flattened image) to group rows before the full comparison
PROBE_PIXELS = 256


def distinct_rows(images: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor] | None:
    """Group identical images of a batch.

    Args:
        images: (B, ...) any dtype.

    Returns:
        ``(first, inverse)``: ``first`` (U,) long, the index of the first row of each distinct image, in
        order of first appearance; ``inverse`` (B,) long, for each row the position in ``first`` of its
        image, so ``images[first][inverse]`` equals ``images``. ``None`` when every row is distinct (or
        when two different rows agree on every probed value), i.e. when grouping saves nothing.
    """
    batch = images.shape[0]
    if batch < 2:
        return None
    flat = images.reshape(batch, -1)
    probe_at = torch.linspace(0, flat.shape[1] - 1, min(PROBE_PIXELS, flat.shape[1]), device=flat.device).long()
    _, key = torch.unique(flat[:, probe_at], dim=0, return_inverse=True)
    rows = torch.arange(batch, device=flat.device)
    # first row of each key, then renumber the keys in order of first appearance
    first_of_key = torch.full((batch,), batch, device=flat.device, dtype=torch.long).scatter_reduce(
        0, key, rows, reduce="amin"
    )
    num_keys = int(key.max()) + 1
    if num_keys == batch:
        return None
    first_of_key = first_of_key[:num_keys]
    order = torch.argsort(first_of_key)
    first = first_of_key[order]
    rank = torch.empty_like(order)
    rank[order] = torch.arange(num_keys, device=flat.device)
    inverse = rank[key]
    if not bool((flat == flat[first[inverse]]).all()):
        return None
    return first, inverse


def regroup(per_distinct: torch.Tensor, inverse: torch.Tensor | None) -> torch.Tensor:
    """Results computed once per distinct row, ``(U, ...)``, back to one per row, ``(B, ...)``
    (``inverse`` from :func:`distinct_rows`; ``None``: they already are one per row).

    ``index_select``, not ``[inverse]``: its backward (``index_add``) sums the duplicates in a fixed order;
    the advanced-indexing backward accumulates with atomic adds on a multi-threaded CPU (not reproducible).
    """
    return per_distinct if inverse is None else per_distinct.index_select(0, inverse)
