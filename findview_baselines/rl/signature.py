"""The checkpoint signature of a policy: the fields a checkpoint must match to be loaded
(:data:`SIGNATURE_FIELDS`, :data:`OPTIONAL_SIGNATURE_FIELDS`) and :func:`check_signature`, which names the
first field that differs. The signature itself comes from ``Policy.model_signature``."""

from __future__ import annotations

from typing import Any, Mapping

__all__ = ["SIGNATURE_FIELDS", "OPTIONAL_SIGNATURE_FIELDS", "GROWABLE_FIELDS", "TRANSFERABLE_VARIANTS", "check_signature"]

SIGNATURE_FIELDS = ("variant", "hidden_size", "height", "width")
# signature fields added later, with the value a checkpoint that lacks them was trained with
OPTIONAL_SIGNATURE_FIELDS = {"fine_shifts": 0, "fine_scales": 1, "memory_inputs": 0, "pitch_warps": 0,
                             "wide_match": 0}
# optional fields whose added parameters start at zero, each with the policy module that holds them: a checkpoint
# without them (0) may initialise a model with them (``init_from``; the model then starts as the saved one)
GROWABLE_FIELDS = {"memory_inputs": "memory_proj", "pitch_warps": "warp_proj", "wide_match": "wide_proj"}
# variants with the same parameters (names and shapes) that differ only in how they prepare their inputs:
# weights of one may initialise the other (``init_from``), never be evaluated or resumed as the other
TRANSFERABLE_VARIANTS = (frozenset({"direct", "robust"}),)


def check_signature(saved: Mapping[str, Any], current: Mapping[str, Any], transfer: bool = False) -> None:
    """Raise ``ValueError`` naming the first field where a checkpoint's model signature differs.

    ``saved`` is the dict stored in the checkpoint, ``current`` the one of the policy being loaded into
    (both from :meth:`Policy.model_signature`). ``transfer=True`` (weights that only initialise a new run,
    ``init_from``) also accepts a variant of the same :data:`TRANSFERABLE_VARIANTS` family, and a checkpoint
    without the :data:`GROWABLE_FIELDS` a model with them needs (their parameters keep their zero start).
    """
    for key in SIGNATURE_FIELDS:
        if key not in saved:
            raise ValueError(f"checkpoint model signature has no field {key!r} (saved signature: {dict(saved)})")
        if key == "variant" and transfer and any({saved[key], current.get(key)} <= family
                                                 for family in TRANSFERABLE_VARIANTS):
            continue
        if saved[key] != current.get(key):
            raise ValueError(
                f"checkpoint does not fit this model: {key} is {saved[key]!r} in the checkpoint "
                f"but {current.get(key)!r} in the current config"
            )
    for key, default in OPTIONAL_SIGNATURE_FIELDS.items():
        if transfer and key in GROWABLE_FIELDS and saved.get(key, default) == default:
            continue
        if saved.get(key, default) != current.get(key, default):
            raise ValueError(
                f"checkpoint does not fit this model: {key} is {saved.get(key, default)!r} in the checkpoint "
                f"but {current.get(key, default)!r} in the current config"
            )
