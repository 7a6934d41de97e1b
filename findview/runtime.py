"""The CPU thread policy of findview: fast on an idle machine, and immune to a busy one.

Why: torch runs its CPU kernels in an OpenMP thread team. By default (GNU OpenMP, the runtime of
the torch wheels on Linux) the team's threads *spin-wait* between parallel regions. When other
processes compete for the cores, a spinning thread holds a core the next region's threads need, and
a handful of tiny torch ops on one 256x256 view (the agents' former RGB -> gray conversion) cost
milliseconds to a hundred milliseconds per call instead of a fraction of a millisecond.

The policy (documented defaults, each overridable):

1. ``OMP_WAIT_POLICY=PASSIVE``: OpenMP threads sleep instead of spinning when idle. The OpenMP
   runtime reads this variable once, when torch loads it, so it must be in the environment *before*
   ``import torch``: ``import findview`` sets it (``os.environ.setdefault``, so a value the user
   exported wins) when torch is not imported yet; the tools in ``tools/`` import ``findview``
   before torch. Setting it after torch was imported has no effect (measured: same spin-wait cost);
   :func:`configure_threads` then warns if it is asked for more than one torch thread.
   The variable is inherited by child processes (data workers, subprocess-based tools).
2. ``torch.set_num_threads(1)`` unless a tool is given another count (``torch_threads`` in the
   train / eval configs). findview's CPU work is many small ops (per-env bookkeeping, per-view
   conversions, small-batch inference) where one thread is as fast as two on an idle machine and
   never waits for a descheduled team member on a busy one. Rendering (OpenCV ``remap``) and the
   feature-based agents (OpenCV, their own thread pool) do not use torch's threads. Give CPU
   training of the full-size network more threads explicitly if the cores are free.
3. ``OPENBLAS_NUM_THREADS=1`` (set with the wait policy, before numpy loads, unless the user set a
   value): numpy's matrix products run inside the agents' own thread pool, where extra BLAS threads
   only oversubscribe the cores.
4. OpenCV's own thread count is left as it is (its thread pool does not show the spin-wait problem);
   pass ``opencv_threads`` to change it.

Who applies it: ``import findview`` does step 1 (nothing else: importing a library must not change
torch's global thread count); every tool in ``tools/`` calls :func:`configure_threads` with its
config's ``torch_threads`` (steps 2 and 3); code using findview as a library calls it once at start-up
(``configure_threads()`` for the defaults). GPU runs are unaffected: the policy only concerns
host-side torch ops.

Measured on a 2-core machine shared with other jobs (``benchmarks/RESULTS.md``, "CPU load immunity"):
the torch RGB -> gray conversion of one 256x256 view took 103 ms per call (median) with torch's
defaults (2 threads, spin-waiting), 0.7 ms with PASSIVE set by ``import findview``, 0.5 ms on 1 thread;
setting PASSIVE after ``import torch`` changed nothing (104 ms).
"""

from __future__ import annotations

import logging
import os
import sys

log = logging.getLogger(__name__)

__all__ = ["DEFAULT_TORCH_THREADS", "WAIT_POLICY", "set_wait_policy", "wait_policy_effective", "configure_threads"]

#: torch intra-op threads when none is given (see the module docstring)
DEFAULT_TORCH_THREADS = 1
#: the OpenMP wait policy findview asks for
WAIT_POLICY = "PASSIVE"

# the OMP_WAIT_POLICY in the environment when findview first saw torch loaded (None: not loaded yet)
_policy_at_torch_load: str | None = None
_warned = False


def set_wait_policy() -> bool:
    """Put ``OMP_WAIT_POLICY=PASSIVE`` into the environment unless the user set a value.

    Returns ``True`` when the OpenMP runtime will honour it, i.e. torch is not imported yet. Called by
    ``import findview``; call it yourself first thing in a script that imports torch before findview.
    """
    global _policy_at_torch_load
    # numpy's OpenBLAS: one thread. The feature agents run numpy matrix products inside their own thread
    # pool (one image per thread); OpenBLAS threads on top oversubscribe the cores and spin (measured:
    # sift agent 28 -> 46 FPS on 2 idle cores). Read when numpy loads, so only effective before that.
    os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")
    torch_loaded = "torch" in sys.modules
    if torch_loaded:
        if _policy_at_torch_load is None:
            _policy_at_torch_load = os.environ.get("OMP_WAIT_POLICY", "")
        os.environ.setdefault("OMP_WAIT_POLICY", WAIT_POLICY)  # still reaches child processes
        return False
    os.environ.setdefault("OMP_WAIT_POLICY", WAIT_POLICY)
    return True


def wait_policy_effective() -> bool:
    """Whether torch's OpenMP threads sleep when idle (``OMP_WAIT_POLICY=PASSIVE`` was set in time).

    Only meaningful once torch is imported; before that it reports the policy torch will get.
    """
    if "torch" not in sys.modules or _policy_at_torch_load is None:
        return os.environ.get("OMP_WAIT_POLICY", "").upper() == WAIT_POLICY
    return _policy_at_torch_load.upper() == WAIT_POLICY


def configure_threads(torch_threads: int | None = None, opencv_threads: int | None = None) -> int:
    """Apply the thread policy of this module; returns the torch intra-op thread count in effect.

    Args:
        torch_threads: torch intra-op threads (``None`` or ``0``: :data:`DEFAULT_TORCH_THREADS`).
        opencv_threads: ``cv2.setNumThreads`` value (``None``: leave OpenCV as it is).

    Raises:
        ValueError: a negative thread count.
    """
    global _warned
    if torch_threads is not None and int(torch_threads) < 0:
        raise ValueError(f"torch_threads must be >= 0 (0 = the default {DEFAULT_TORCH_THREADS}), got {torch_threads}")
    if opencv_threads is not None and int(opencv_threads) < 0:
        raise ValueError(f"opencv_threads must be >= 0, got {opencv_threads}")
    set_wait_policy()
    import torch

    n = int(torch_threads) if torch_threads else DEFAULT_TORCH_THREADS
    if torch.get_num_threads() != n:
        torch.set_num_threads(n)
    if n > 1 and not wait_policy_effective() and not _warned:
        _warned = True
        at_load = _policy_at_torch_load if _policy_at_torch_load is not None else os.environ.get("OMP_WAIT_POLICY", "")
        why = (
            f"OMP_WAIT_POLICY={at_load!r} when torch was loaded"
            if at_load
            else "torch was imported before findview without OMP_WAIT_POLICY=PASSIVE"
        )
        log.warning(
            "%s: %d torch threads may spin-wait and run many times slower on a busy CPU "
            "(export OMP_WAIT_POLICY=PASSIVE before starting Python, or use 1 thread)",
            why, n,
        )
    if opencv_threads is not None:
        import cv2

        cv2.setNumThreads(int(opencv_threads))
    return n
