"""The CPU thread policy of findview: fast on an idle machine, immune to a busy one, whatever the import order.

This module is the one place where findview's thread settings and their knobs are decided.

Why: torch runs its CPU kernels in an OpenMP thread team, numpy its matrix products in OpenBLAS threads,
OpenCV its own pool. By default the OpenMP team (GNU OpenMP, the runtime of the torch wheels on Linux)
and OpenBLAS's threads *spin-wait* between parallel regions. When other processes compete for the cores,
a spinning thread holds a core that the next region's threads need, and a handful of small ops on one
256x256 view cost milliseconds to a hundred milliseconds per call instead of a fraction of a millisecond.

The policy: **the thread count is chosen where the work is done**, for two kinds of work.

1. *Light work*, many small ops: the simulator (rendering, first reset, the environment's bookkeeping),
   the corruptions, the rule-based agents. It runs inside :func:`light_work`: one torch thread and one
   OpenBLAS thread, so no thread team exists to spin and nothing waits for a descheduled team member
   (one thread is as fast as two on these ops on an idle machine). OpenCV's pool (rendering, the feature
   agents) keeps its count on an idle machine (two threads render twice as fast) and shrinks to the
   cores that other runnable tasks leave when there are any (:func:`runnable_elsewhere`).
   ``FindViewEnv`` (construction, ``reset``, ``step``), ``Simulator`` (construction, ``render``),
   ``corrupt`` and the rule-based agents' ``reset`` / ``act`` enter it themselves, so a user script gets
   it without doing anything.
2. *Heavy work*, large convolutions and matrix products: the PPO and DAgger updates and rollouts, and the
   learned agents' forward passes, of a network of large convolutions (the paper's, on 128x128 views or
   more: ``Policy.heavy``). It runs inside :func:`heavy_work` on :func:`heavy_threads` torch threads (the
   cores this process may use that no other task is using, unless told otherwise). The same calls with a
   small network (the 64x64 CPU recipe) are light work: :func:`scoped` picks the scope per object.

Each scope sets the counts on entry (only those that differ) and restores the previous ones on exit, so
code outside them keeps the user's settings. Both are context managers and decorators; they nest.

Knobs, in order of precedence, for the heavy work's thread count:

- ``torch_threads`` in the train / eval configs (``trainer.torch_threads``), or
  :func:`configure_threads` ``(torch_threads=n)`` in a script;
- the environment variable ``FINDVIEW_COMPUTE_THREADS``;
- otherwise the cores in the process's CPU affinity mask (``os.sched_getaffinity``) that other runnable
  tasks leave free at the moment (:func:`heavy_threads`; then the count, and with it the last bits of the
  results, follows the machine's load: set a count for bit-identical reruns).

Also, as a second line of defence when findview is imported before torch and numpy:
``import findview`` puts ``OMP_WAIT_POLICY=PASSIVE`` (OpenMP threads sleep instead of spinning when
idle) and ``OPENBLAS_NUM_THREADS=1`` into the environment, unless the user set them. Both are read
once, when torch / numpy load their runtimes, and reach child processes; after that they do nothing
(:func:`wait_policy_effective` tells). The scopes above do not depend on them.

Measured on the 2-core development machine next to two busy processes (``benchmarks/RESULTS.md``, "Against
the authors' code, whatever the import order"): with torch imported first, before these scopes, the first
reset of 16 environments took 0.30 s against 0.05 s with findview first, and the sift agent ran at 20
decisions/s against 51; with them both orders run at the same speed.
"""

from __future__ import annotations

import ctypes
import functools
import logging
import os
import sys
from collections.abc import Callable, Iterator
from contextlib import AbstractContextManager, contextmanager
from typing import Any

log = logging.getLogger(__name__)

__all__ = [
    "DEFAULT_TORCH_THREADS",
    "COMPUTE_THREADS_ENV",
    "WAIT_POLICY",
    "set_wait_policy",
    "wait_policy_effective",
    "configure_threads",
    "compute_threads",
    "light_work",
    "heavy_work",
    "heavy_threads",
    "scoped",
    "runnable_elsewhere",
    "blas_threads",
]

#: torch's global intra-op thread count set by the tools (work outside the scopes: glue code)
DEFAULT_TORCH_THREADS = 1
#: environment variable giving the heavy work's torch thread count (see the module docstring)
COMPUTE_THREADS_ENV = "FINDVIEW_COMPUTE_THREADS"
#: the OpenMP wait policy findview asks for
WAIT_POLICY = "PASSIVE"

# the OMP_WAIT_POLICY in the environment when findview first saw torch loaded (None: not loaded yet)
_policy_at_torch_load: str | None = None
_warned = False
# heavy work's torch thread count set by configure_threads (None: COMPUTE_THREADS_ENV or the cores)
_compute_threads: int | None = None
# (get, set) thread-count functions of every OpenBLAS loaded in this process, found once numpy is loaded
_blas_controls: list[tuple[Callable[[], int], Callable[[int], None]]] | None = None


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
    """Apply the thread policy of this module; returns torch's global intra-op thread count now in effect.

    Args:
        torch_threads: the heavy work's torch threads (:func:`heavy_work`) and torch's global count;
            ``None`` or ``0``: heavy work on :func:`compute_threads`'s default, global count
            :data:`DEFAULT_TORCH_THREADS`.
        opencv_threads: ``cv2.setNumThreads`` value (``None``: leave OpenCV as it is).

    Raises:
        ValueError: a negative thread count.
    """
    global _warned, _compute_threads
    if torch_threads is not None and int(torch_threads) < 0:
        raise ValueError(f"torch_threads must be >= 0 (0 = the default {DEFAULT_TORCH_THREADS}), got {torch_threads}")
    if opencv_threads is not None and int(opencv_threads) < 0:
        raise ValueError(f"opencv_threads must be >= 0, got {opencv_threads}")
    set_wait_policy()
    import torch

    _compute_threads = int(torch_threads) if torch_threads else None
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


def _set_threads() -> int | None:
    """The heavy work's thread count set by :func:`configure_threads` or ``$FINDVIEW_COMPUTE_THREADS`` (None: unset).

    Raises:
        ValueError: ``$FINDVIEW_COMPUTE_THREADS`` is not a positive integer.
    """
    if _compute_threads:
        return _compute_threads
    value = os.environ.get(COMPUTE_THREADS_ENV, "").strip()
    if not value:
        return None
    if not value.isdigit() or int(value) < 1:
        raise ValueError(f"{COMPUTE_THREADS_ENV}={value!r}: expected a positive integer (torch threads)")
    return int(value)


def compute_threads() -> int:
    """The most torch threads heavy work uses: :func:`configure_threads`'s ``torch_threads``, else
    ``$FINDVIEW_COMPUTE_THREADS``, else the number of cores in this process's CPU affinity mask.

    Raises:
        ValueError: ``$FINDVIEW_COMPUTE_THREADS`` is not a positive integer.
    """
    return _set_threads() or _cores()


def _find_blas() -> list[tuple[Callable[[], int], Callable[[int], None]]]:
    """The thread-count functions of the OpenBLAS libraries loaded in this process (numpy's, torch's).

    Found from ``/proc/self/maps`` once numpy is loaded (Linux; elsewhere: none, and the scopes leave BLAS
    alone). The symbol names are OpenBLAS's own, with the prefix / suffix of numpy's ``scipy_openblas``
    build.
    """
    global _blas_controls
    if _blas_controls is not None:
        return _blas_controls
    if "numpy" not in sys.modules:
        return []
    found: list[tuple[Callable[[], int], Callable[[int], None]]] = []
    try:
        with open("/proc/self/maps") as maps:
            paths = sorted({line.split()[-1] for line in maps if "openblas" in line.rsplit("/", 1)[-1].lower()})
    except OSError:
        paths = []
    for path in paths:
        try:
            lib = ctypes.CDLL(path)
        except OSError:
            continue
        for prefix, suffix in (("scipy_openblas", "64_"), ("scipy_openblas", ""), ("openblas", "64_"), ("openblas", "")):
            get = getattr(lib, f"{prefix}_get_num_threads{suffix}", None)
            put = getattr(lib, f"{prefix}_set_num_threads{suffix}", None)
            if get is not None and put is not None:
                get.restype, put.argtypes = ctypes.c_int, [ctypes.c_int]
                found.append((get, put))
                break
    _blas_controls = found
    return found


def blas_threads() -> list[int]:
    """The thread count of each OpenBLAS loaded in this process (empty: none found)."""
    return [int(get()) for get, _ in _find_blas()]


@contextmanager
def _threads(kind: str) -> Iterator[None]:
    """The scope of ``kind`` ``"light"`` or ``"heavy"``; the counts are chosen on each entry (also when the
    scope decorates a function: the decorator re-enters it per call)."""
    import torch

    torch_threads, blas = (1, 1) if kind == "light" else (heavy_threads(), None)
    before = torch.get_num_threads()
    if before != torch_threads:
        torch.set_num_threads(torch_threads)
    blas_before = [(put, get()) for get, put in _find_blas()] if blas is not None else []
    for put, count in blas_before:
        if count != blas:
            put(blas)
    cv2 = sys.modules.get("cv2") if kind == "light" else None
    cv_before = cv2.getNumThreads() if cv2 is not None else 0
    cv_threads = max(1, min(cv_before, _cores() - _others())) if cv2 is not None else 0
    if cv_threads != cv_before:
        cv2.setNumThreads(cv_threads)
    try:
        yield
    finally:
        if before != torch_threads:
            torch.set_num_threads(before)
        for put, count in blas_before:
            if count != blas:
                put(count)
        if cv_threads != cv_before:
            cv2.setNumThreads(cv_before)


def light_work() -> AbstractContextManager[None]:
    """Scope (context manager or decorator) for many small ops: one torch thread, one OpenBLAS thread."""
    return _threads("light")


def runnable_elsewhere() -> int | None:
    """Tasks ready to run on this machine right now outside this process (Linux ``/proc``; ``None`` elsewhere).

    The kernel's count of runnable tasks (``/proc/loadavg``, 4th field) minus this process's threads in
    state ``R``: an instantaneous measure of the competing CPU load, unlike the load averages.
    """
    try:
        with open("/proc/loadavg") as f:
            running = int(f.read().split()[3].split("/")[0])
        ours = 0
        for tid in os.listdir("/proc/self/task"):
            try:
                with open(f"/proc/self/task/{tid}/stat") as f:
                    ours += f.read().rsplit(")", 1)[1].split()[0] == "R"
            except OSError:  # the thread ended meanwhile
                continue
    except (OSError, ValueError, IndexError):
        return None
    return max(0, running - ours)


# (time.monotonic() of the last look, what runnable_elsewhere() said then): looked at every LOAD_LOOK_S
_load_look: tuple[float, int] = (-1e9, 0)
#: seconds between two looks at the competing load (scopes entered more often reuse the last look)
LOAD_LOOK_S = 0.25


def _cores() -> int:
    """Cores in this process's CPU affinity mask."""
    try:
        return max(1, len(os.sched_getaffinity(0)))
    except AttributeError:  # not Linux
        return max(1, os.cpu_count() or 1)


def _others() -> int:
    """:func:`runnable_elsewhere`, looked at most every :data:`LOAD_LOOK_S` seconds (0 when unknown)."""
    global _load_look
    import time

    now = time.monotonic()
    if now - _load_look[0] >= LOAD_LOOK_S:
        _load_look = (now, runnable_elsewhere() or 0)
    return _load_look[1]


def heavy_threads() -> int:
    """The torch thread count :func:`heavy_work` uses now.

    Set explicitly (:func:`configure_threads`, ``$FINDVIEW_COMPUTE_THREADS``): exactly that. Otherwise the
    cores not taken by other runnable tasks (:func:`runnable_elsewhere`), between 1 and
    :func:`compute_threads`: two threads on a machine whose other core is busy would wait for each other at
    every parallel region (measured: the PPO update 2.9x slower next to two busy processes, against 1.6x
    on one thread). Results then depend on the load: the thread count changes how float reductions are
    split, so runs that must be bit-identical set the count.
    """
    chosen = _set_threads()
    if chosen:
        return chosen
    cap = compute_threads()
    return cap if cap == 1 else max(1, cap - _others())


def heavy_work() -> AbstractContextManager[None]:
    """Scope (context manager or decorator) for large convolutions: :func:`heavy_threads` torch threads."""
    return _threads("heavy")


def scoped(is_heavy: Callable[[Any], bool]) -> Callable[[Callable[..., Any]], Callable[..., Any]]:
    """Method decorator: run the method in :func:`heavy_work` when ``is_heavy(self)``, else in :func:`light_work`.

    For work whose size depends on the object: a network of large convolutions on 256x256 views is heavy
    work, a small network on 64x64 views is many small ops (on two threads it waits for the second thread
    at every op: measured, a DAgger update of the 64x64 CPU recipe ran at 130-235 env steps/s on two threads
    with ``OMP_WAIT_POLICY=PASSIVE`` against 240-360 on one).
    """

    def decorate(method: Callable[..., Any]) -> Callable[..., Any]:
        @functools.wraps(method)
        def wrapper(self: Any, *args: Any, **kwargs: Any) -> Any:
            with heavy_work() if is_heavy(self) else light_work():
                return method(self, *args, **kwargs)

        return wrapper

    return decorate
