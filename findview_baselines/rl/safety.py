"""What keeps a training run safe: one live run per folder (:class:`RunLock`) and signals turned into a
clean stop (:class:`StopOnSignal`)."""

from __future__ import annotations

import errno
import fcntl
import logging
import os
import signal
import threading
from pathlib import Path
from typing import Any

__all__ = ["RunLock", "RunFolderBusy", "StopOnSignal", "lock_holder"]

log = logging.getLogger(__name__)

LOCK_NAME = ".run.lock"


class RunFolderBusy(RuntimeError):
    """Another live process trains into the same run folder."""


def lock_holder(run_dir: str | os.PathLike) -> int | None:
    """The pid of the live process holding ``run_dir``'s lock, or ``None`` (free, or a stale lock)."""
    path = Path(run_dir) / LOCK_NAME
    if not path.is_file():
        return None
    try:
        fd = os.open(path, os.O_RDWR)
    except OSError:
        return None
    try:
        fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
    except OSError as err:
        if err.errno in (errno.EAGAIN, errno.EACCES, errno.EWOULDBLOCK):
            try:
                return int(os.pread(fd, 32, 0).decode().strip() or -1)
            except (OSError, ValueError):
                return -1
        return None
    finally:
        os.close(fd)  # closing also releases a lock we may just have taken
    return None


class RunLock:
    """Exclusive lock on a run folder for the lifetime of a training run.

    The lock is an ``flock`` on ``<run_dir>/.run.lock`` (which also holds the holder's pid): the kernel
    drops it when the holder exits, however it exits, so the lock of a killed run is simply taken over.

    Raises:
        RunFolderBusy: (on enter) a live process holds the folder; the message names it and the pid.
    """

    def __init__(self, run_dir: str | os.PathLike) -> None:
        self.path = Path(run_dir) / LOCK_NAME
        self._fd: int | None = None

    def __enter__(self) -> "RunLock":
        self.path.parent.mkdir(parents=True, exist_ok=True)
        fd = os.open(self.path, os.O_RDWR | os.O_CREAT, 0o644)
        try:
            fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
        except OSError:
            try:
                holder = os.pread(fd, 32, 0).decode().strip() or "?"
            except OSError:
                holder = "?"
            os.close(fd)
            raise RunFolderBusy(
                f"run folder {self.path.parent} is in use by a live training run (pid {holder}); wait for it "
                f"to finish, stop it, or train into another folder (hydra.run.dir=<folder>)"
            ) from None
        os.ftruncate(fd, 0)
        os.pwrite(fd, f"{os.getpid()}\n".encode(), 0)
        self._fd = fd
        return self

    def __exit__(self, *exc: Any) -> None:
        if self._fd is not None:
            try:
                os.ftruncate(self._fd, 0)
            finally:
                os.close(self._fd)  # releases the flock
                self._fd = None


class StopOnSignal:
    """SIGTERM / SIGINT / SIGUSR1 ask the run to stop at the next safe point instead of killing it.

    The first signal sets :attr:`signum` (the run loop then abandons or finishes the current update,
    writes ``latest.pth`` and exits with 128 + signum: 143 / 130 / 138); a second SIGINT (Ctrl-C twice)
    raises ``KeyboardInterrupt`` at once. SIGUSR1 is what a SLURM job gets before its time limit
    (``--signal=USR1@120``, docs/CLUSTER.md). Only installed in the main thread; the previous handlers
    come back on exit. Under torchrun, :class:`findview_baselines.rl.distributed.AgreedStop` makes every
    rank stop when any one of them got a signal.
    """

    SIGNALS = (signal.SIGTERM, signal.SIGINT, signal.SIGUSR1)

    def __init__(self) -> None:
        self.signum: int | None = None
        self._previous: dict[int, Any] = {}
        self._ignore_on_exit = False

    def ignore_after_exit(self) -> None:
        """On exit, ignore these signals instead of restoring the previous handlers.

        For a rank of a torchrun job that stopped on a signal and is only exiting: the first rank to exit
        with 128 + signum makes torchrun send SIGTERM to the others, which must still exit with their own
        status instead of dying of it half-way through their exit."""
        self._ignore_on_exit = True

    @property
    def requested(self) -> bool:
        """A stop was asked for."""
        return self.signum is not None

    def __call__(self) -> bool:
        """Same as :attr:`requested` (a ``should_stop`` callable for the algorithms)."""
        return self.signum is not None

    def agree(self) -> bool:
        """Same as :attr:`requested` (the run loop's check between updates; collective under torchrun)."""
        return self.signum is not None

    def close(self) -> None:
        """Nothing to finish in a single process (see ``AgreedStop.close``)."""

    def _handle(self, signum: int, frame: Any) -> None:
        if self.signum is not None and signum == signal.SIGINT:
            raise KeyboardInterrupt
        if self.signum is None:
            self.signum = signum
            log.warning("%s: stopping at the next safe point and writing latest.pth (Ctrl-C again aborts at once)",
                        signal.Signals(signum).name)

    def __enter__(self) -> "StopOnSignal":
        if threading.current_thread() is threading.main_thread():
            for s in self.SIGNALS:
                self._previous[s] = signal.getsignal(s)
                signal.signal(s, self._handle)
        return self

    def __exit__(self, *exc: Any) -> None:
        for s, handler in self._previous.items():
            signal.signal(s, signal.SIG_IGN if self._ignore_on_exit else handler)
        self._previous.clear()

