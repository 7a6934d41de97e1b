"""Checkpoint files of the PPO trainer and the state they need for an exact resume.

Every checkpoint is written atomically (temp file beside it + ``os.replace``) and holds only tensors and
plain Python values (dicts, lists, tuples, str, int, float, bool, None), so it loads with
``torch.load(path, weights_only=True)``. Layout (``format = "findview-ppo"``, ``version = 1``)::

    {
      "format": "findview-ppo", "version": 1,
      "signature": {"variant", "hidden_size", "height", "width"},   # Policy.model_signature()
      "policy": policy.state_dict(),
      "update": int, "env_steps": int,                             # updates / env steps done
      "config": {...},                                             # the resolved run config (plain dict)
      "val": {difficulty: {"eps", "omega_stop", "omega_perf", "spl", "episodes"}} | None,
      "best_val_eps": float | None,
      "trainer": {...} | None,                                     # resume state (latest.pth only)
    }

``trainer`` (see :meth:`findview_baselines.rl.ppo_trainer.PPOTrainer.state_dict`) carries the optimizer,
lr / clip, the difficulty scheduler, the environment (episodes, rotations, episode source and sampler
RNG), the rollout storage's initial observation / hidden state / masks and every RNG (torch CPU + CUDA,
numpy, Python ``random``, the mini-batch shuffle generator). ``best.pth`` leaves it out (``None``): it is
for evaluation and fine-tuning, not for resuming.
"""

from __future__ import annotations

import os
import random
import tempfile
from pathlib import Path
from typing import Any, Mapping, Sequence

import numpy as np
import torch

from findview.utils import atomic_write

CHECKPOINT_FORMAT = "findview-ppo"
CHECKPOINT_VERSION = 1

__all__ = [
    "CHECKPOINT_FORMAT",
    "CHECKPOINT_VERSION",
    "CheckpointError",
    "CheckpointNotFound",
    "OutputPathError",
    "save_checkpoint",
    "load_checkpoint",
    "average_checkpoints",
    "check_writable",
    "capture_rng_state",
    "restore_rng_state",
]


class CheckpointError(ValueError):
    """A file given as a checkpoint that is not a usable findview checkpoint; the message says what the
    file is and what was expected (the tools print it as one line, exit status 2)."""


class CheckpointNotFound(FileNotFoundError):
    """No file at the checkpoint path (the tools print the message as one line, exit status 2)."""


class OutputPathError(PermissionError):
    """An output folder that cannot be created or written (the tools print it as one line, exit status 2)."""


_EXPECTED = "expected a .pth written by tools/train.py"


def _describe_file(path: Path) -> str:
    """What a file that is not a findview checkpoint looks like, from its first bytes (for messages)."""
    try:
        with open(path, "rb") as f:
            head = f.read(4096)
    except OSError as err:
        return f"unreadable: {err.strerror or err}"
    if not head:
        return "an empty file"
    if head.startswith(b"PK\x03\x04"):
        return "a zip archive (a torch file of another program?)"
    if head[:1] == b"\x80":
        return "a pickle file (an old-style torch file of another program?)"
    if b"\x00" not in head:
        try:
            head.decode("utf-8")
            return "a text file"
        except UnicodeDecodeError as err:
            if err.start >= len(head) - 4:  # a multi-byte character cut by the 4096-byte window
                return "a text file"
    return "a binary file of another format"


def _not_checkpoint(label: str, what: str) -> CheckpointError:
    return CheckpointError(f"{label}: not a findview checkpoint ({what}; {_EXPECTED})")


# --------------------------------------------------------------------------------------------------
# Files
# --------------------------------------------------------------------------------------------------


def save_checkpoint(path: str | os.PathLike, state: Mapping[str, Any]) -> Path:
    """Write ``state`` to ``path`` atomically: a crash or Ctrl-C never leaves a half-written checkpoint.

    The temp file lives in the same folder (so the rename is atomic) and is removed on failure.
    """
    return atomic_write(path, lambda tmp: torch.save(dict(state), tmp))


def load_checkpoint(
    path: str | os.PathLike, map_location: torch.device | str | None = "cpu", key: str | None = None
) -> dict[str, Any]:
    """Load a findview PPO checkpoint with ``weights_only=True``.

    Args:
        path: the ``.pth`` file.
        map_location: as for ``torch.load``.
        key: the config key that named the file (``checkpoint``, ``init_from``); messages then start with
            ``<key>=<path>:`` instead of the path.

    Raises:
        CheckpointNotFound: no file at ``path``.
        CheckpointError: ``path`` is a folder, or a file that is not a findview checkpoint (the message says
            what it is and what was expected).
    """
    path = Path(path)
    label = f"{key}={path}" if key else str(path)
    if path.is_dir():
        raise CheckpointError(f"{label}: a folder, not a checkpoint file ({_EXPECTED}, e.g. "
                              f"<run folder>/checkpoints/best.pth)")
    if not path.is_file():
        card = path.parent / "README.md"
        hint = f" ({card} says how to make it: weights files are not kept in git)" if card.is_file() else ""
        raise CheckpointNotFound(f"checkpoint not found: {path}{hint}")
    try:
        state = torch.load(path, map_location=map_location, weights_only=True)
    except Exception as err:  # unpickling error, truncated file, foreign pickle, text, ...
        what = _describe_file(path)
        if what.startswith(("a zip", "a pickle")):
            what += f" that torch cannot load safely ({type(err).__name__})"
        raise _not_checkpoint(label, what) from err
    if not isinstance(state, dict):
        raise _not_checkpoint(label, f"a torch file holding a {type(state).__name__}")
    if "signature" not in state or "policy" not in state:
        raise _not_checkpoint(label, "a torch file without findview's 'signature' and 'policy' entries")
    return state


def checkpoint_payload(
    policy: torch.nn.Module,
    update: int,
    env_steps: int,
    config: Mapping[str, Any],
    val: Mapping[str, Any] | None,
    best_val_eps: float | None,
    trainer_state: Mapping[str, Any] | None,
) -> dict[str, Any]:
    """The checkpoint dict of the layout in the module docstring (the one place it is built; read back by
    :func:`load_checkpoint` and :func:`load_policy`). ``trainer_state=None`` for ``best.pth``."""
    return {
        "format": CHECKPOINT_FORMAT,
        "version": CHECKPOINT_VERSION,
        "signature": policy.model_signature(),  # type: ignore[operator]
        "policy": {k: v.detach().cpu() for k, v in policy.state_dict().items()},
        "update": int(update),
        "env_steps": int(env_steps),
        "config": dict(config),
        "val": val,
        "best_val_eps": best_val_eps,
        "trainer": None if trainer_state is None else dict(trainer_state),
    }


def average_checkpoints(paths: Sequence[str | os.PathLike]) -> dict[str, Any]:
    """The uniform average of the policy weights of one or more checkpoints of one model (a "model soup"; one
    checkpoint: its weights as they are, without its resume state, a file to ship).

    Meant for runs fine-tuned from one common checkpoint (the same network and the same starting weights), whose
    weights stay close enough for their mean to be a network of its own. Every floating-point tensor of
    ``policy`` becomes the sum over the inputs, in the order given, divided by their number (float32 arithmetic
    as stored); every other tensor (integer buffers) must be equal in all inputs and is kept. The rest of the
    payload (signature, config, update, env steps) is the first input's; ``val`` and ``best_val_eps`` are
    ``None`` (no validation measured these weights), ``trainer`` is ``None`` (not a resume point), and
    ``averaged_from`` lists the inputs as given (strings), with their updates.

    Raises:
        ValueError: no path.
        CheckpointNotFound, CheckpointError: an input is missing or not a findview checkpoint, or the inputs
            differ in signature, in their policy's tensor names, shapes or dtypes, or in a non-float tensor
            (the message names both files and the first difference).
    """
    if not paths:
        raise ValueError("averaging needs at least one checkpoint, got none")
    states = [load_checkpoint(p) for p in paths]
    first, name0 = states[0], str(paths[0])
    for path, state in zip(paths[1:], states[1:]):
        label = f"{path} against {name0}"
        if state["signature"] != first["signature"]:
            diff = sorted(k for k in set(state["signature"]) | set(first["signature"])
                          if state["signature"].get(k) != first["signature"].get(k))
            raise CheckpointError(f"{label}: other model signatures (differ in {', '.join(diff)}); "
                                  f"expected checkpoints of one network")
        if list(state["policy"]) != list(first["policy"]):
            missing = sorted(set(first["policy"]) ^ set(state["policy"]))
            raise CheckpointError(f"{label}: other policy tensors ({', '.join(missing[:5]) or 'another order'}); "
                                  f"expected checkpoints of one network")
        for key, ref in first["policy"].items():
            other = state["policy"][key]
            if other.shape != ref.shape or other.dtype != ref.dtype:
                raise CheckpointError(f"{label}: policy tensor {key} is {tuple(other.shape)} {other.dtype}, "
                                      f"expected {tuple(ref.shape)} {ref.dtype} as in the first checkpoint")
            if not ref.is_floating_point() and not torch.equal(other, ref):
                raise CheckpointError(f"{label}: the non-float policy tensor {key} differs; "
                                      f"expected equal integer buffers")
    policy: dict[str, torch.Tensor] = {}
    for key, ref in first["policy"].items():
        if ref.is_floating_point():
            total = ref.clone()
            for state in states[1:]:
                total = total + state["policy"][key]
            policy[key] = total / len(states)
        else:
            policy[key] = ref.clone()
    out = dict(first)
    out.update(policy=policy, val=None, best_val_eps=None, trainer=None,
               averaged_from=[{"path": str(p), "update": int(s["update"])} for p, s in zip(paths, states)])
    return out


def load_policy(path: str | os.PathLike, policy: torch.nn.Module, transfer: bool = False,
                key: str | None = None) -> dict[str, Any]:
    """Load the weights of a checkpoint into ``policy`` after checking its signature; returns the checkpoint.

    ``transfer=True`` (``init_from``) also accepts a checkpoint of a variant with the same parameters
    (``rl/signature.py: TRANSFERABLE_VARIANTS``, e.g. a ``direct`` agent initialising a ``robust`` one).

    Raises:
        CheckpointNotFound, CheckpointError: no such file, not a checkpoint, or one whose model differs
            (naming the file and the first differing model field).
    """
    from findview_baselines.rl.signature import GROWABLE_FIELDS, check_signature

    state = load_checkpoint(path, map_location=next(policy.parameters()).device, key=key)
    label = f"{key}={path}" if key else str(path)
    try:
        check_signature(state["signature"], policy.model_signature(), transfer=transfer)  # type: ignore[operator]
    except ValueError as err:
        raise CheckpointError(f"{label}: {err} (use a checkpoint of the same agent.variant / agent.hidden_size / "
                              f"view size)") from None
    # a GROWABLE_FIELDS part the saved model lacks keeps its zero start (init_from only); anything else must fit
    grown = tuple(f"{module}." for field, module in GROWABLE_FIELDS.items()
                  if transfer and not state["signature"].get(field) and policy.model_signature().get(field))
    try:
        missing, unexpected = policy.load_state_dict(state["policy"], strict=not grown)
    except RuntimeError as err:
        raise CheckpointError(f"{label}: weights do not fit this model ({err})") from None
    missing = [k for k in missing if not k.startswith(grown)] if grown else missing
    if missing or unexpected:
        raise CheckpointError(f"{label}: weights do not fit this model (missing {missing}, unexpected {unexpected})")
    return state


def check_writable(folder: str | os.PathLike, what: str = "output folder") -> Path:
    """Create ``folder`` (with parents) and prove a file can be written in it; fail early otherwise.

    Works for root too (a path below a regular file can never be created). Returns the absolute path.

    Raises:
        OutputPathError: (a ``PermissionError``) naming the folder, the OS error and what to do.
    """
    folder = Path(folder).expanduser().absolute()
    try:
        folder.mkdir(parents=True, exist_ok=True)
        fd, probe = tempfile.mkstemp(prefix=".write_test.", dir=folder)
        os.close(fd)
        os.unlink(probe)
    except OSError as err:
        raise OutputPathError(
            f"{what} {folder} is not writable ({type(err).__name__}: {err.strerror or err}); "
            f"choose another one, e.g. hydra.run.dir=<writable folder>"
        ) from err
    return folder


# --------------------------------------------------------------------------------------------------
# RNG states (as tensors / plain lists, so that weights_only=True can load them)
# --------------------------------------------------------------------------------------------------


def capture_rng_state() -> dict[str, Any]:
    """States of torch (CPU and every CUDA device), numpy's global RNG and Python's ``random``."""
    np_state = np.random.get_state()
    py_state = random.getstate()
    return {
        "torch": torch.get_rng_state(),
        "cuda": torch.cuda.get_rng_state_all() if torch.cuda.is_available() else [],
        "numpy": {
            "name": str(np_state[0]),
            "keys": torch.from_numpy(np.asarray(np_state[1], dtype=np.int64)),
            "pos": int(np_state[2]),
            "has_gauss": int(np_state[3]),
            "cached_gauss": float(np_state[4]),
        },
        "python": {"version": int(py_state[0]), "state": list(py_state[1]), "gauss_next": py_state[2]},
    }


def restore_rng_state(state: Mapping[str, Any]) -> None:
    """Inverse of :func:`capture_rng_state` (CUDA states are restored when the device count matches)."""
    torch.set_rng_state(state["torch"].cpu())
    cuda_states = list(state.get("cuda") or [])
    if cuda_states and torch.cuda.is_available() and len(cuda_states) == torch.cuda.device_count():
        torch.cuda.set_rng_state_all([s.cpu() for s in cuda_states])
    np_state = state["numpy"]
    np.random.set_state(
        (
            np_state["name"],
            np_state["keys"].numpy().astype(np.uint32),
            int(np_state["pos"]),
            int(np_state["has_gauss"]),
            float(np_state["cached_gauss"]),
        )
    )
    py_state = state["python"]
    random.setstate((int(py_state["version"]), tuple(int(x) for x in py_state["state"]), py_state["gauss_next"]))
