"""Run ``python <script> args`` commands without paying Python's imports each time (POSIX: fork).

A server process imports the heavy packages once (torch, OpenCV, kornia, Hydra, findview); for each command
it forks, and the child changes to the command's folder and environment, sends its output to a file and
runs the script as ``__main__``. Each command still runs in a process of its own, made from the same
untouched server (nothing one command does reaches the next), but starts in about 0.1 s instead of about
2.5 s of imports on one core. ``tools/check_docs.py`` runs its ~50 documented commands this way.

What a forked command cannot change: settings read when a library loads (``OMP_NUM_THREADS``,
``OMP_WAIT_POLICY``, ``OPENBLAS_NUM_THREADS``, ``PYTHON*``); callers run commands that set such variables as
ordinary processes (:func:`forkable`).

    runner = WarmPython()
    code, output = runner.run(["/abs/tools/eval.py", "agent=sift"], cwd=folder, env=dict(os.environ), timeout=600)
    runner.close()
"""

from __future__ import annotations

import atexit
import gc
import json
import os
import re
import selectors
import signal
import subprocess
import sys
import tempfile
import threading
from pathlib import Path
from typing import Optional

# imported once by the server, in this order (findview first: it sets OMP_WAIT_POLICY before torch loads)
PRELOAD = ("findview", "numpy", "cv2", "torch", "kornia", "hydra", "omegaconf", "tqdm", "torch.utils.tensorboard",
           "findview_baselines.cli", "findview_baselines.config", "findview_baselines.training",
           "findview_baselines.evaluation.evaluate")
# environment variables read when a library loads: a command that sets one runs as an ordinary process
LOAD_TIME_ENV = re.compile(r"^(OMP_|OPENBLAS_|MKL_|KMP_|PYTHON|LD_|CUDA_|TORCH_)")


def fork_args(words: list[str]) -> Optional[tuple[dict[str, str], list[str]]]:
    """For the command ``words`` (shell words, ``VAR=value`` assignments first) of the form ``python <file>.py ...``
    with no assignment to a load-time variable (:data:`LOAD_TIME_ENV`): its assignments and the arguments after
    ``python`` (what :meth:`WarmPython.run` takes); ``None`` for any other command."""
    i = 0
    while i < len(words) and re.fullmatch(r"[A-Za-z_]\w*=.*", words[i]):
        if LOAD_TIME_ENV.match(words[i]):
            return None
        i += 1
    rest = words[i:]
    if not (len(rest) >= 2 and rest[0] == "python" and rest[1].endswith(".py") and not rest[1].startswith("-")):
        return None
    return dict(w.split("=", 1) for w in words[:i]), rest[1:]


def forkable(words: list[str]) -> bool:
    """Whether :class:`WarmPython` can run the command ``words`` (:func:`fork_args`)."""
    return fork_args(words) is not None


class WarmPython:
    """A server that forks a fresh process per command from one that imported :data:`PRELOAD` once."""

    def __init__(self, preload: tuple[str, ...] = PRELOAD) -> None:
        self._proc = subprocess.Popen(
            [sys.executable, __file__, "--serve", *preload],
            stdin=subprocess.PIPE, stdout=subprocess.PIPE, text=True, bufsize=1,
        )
        reply = self._read(timeout=300)
        if reply.get("ready") is not True:
            raise RuntimeError(f"warm_python: the server did not start: {reply}")

    def _read(self, timeout: Optional[float]) -> dict:
        """The server's next reply line (``{}`` when ``timeout`` seconds pass first)."""
        assert self._proc.stdout is not None
        sel = selectors.DefaultSelector()
        sel.register(self._proc.stdout, selectors.EVENT_READ)
        try:
            if not sel.select(timeout):
                return {}
        finally:
            sel.close()
        line = self._proc.stdout.readline()
        if not line:
            raise RuntimeError(f"warm_python: the server exited (status {self._proc.poll()})")
        return json.loads(line)

    def run(self, argv: list[str], cwd: Path, env: dict[str, str], timeout: float) -> tuple[Optional[int], str]:
        """Run ``python argv[0] argv[1:]`` in ``cwd`` with environment ``env``.

        Returns:
            (exit status, or ``None`` when it ran past ``timeout`` seconds and was killed; its stdout and
            stderr, interleaved as written).
        """
        assert self._proc.stdin is not None
        fd, out = tempfile.mkstemp(prefix="warm_python_", suffix=".log")
        os.close(fd)
        try:
            self._proc.stdin.write(json.dumps({"argv": argv, "cwd": str(cwd), "env": env, "output": out}) + "\n")
            self._proc.stdin.flush()
            pid = self._read(timeout=60)["pid"]
            reply = self._read(timeout=timeout)
            if not reply:  # past the timeout: kill its process group, then collect the server's reply
                try:
                    os.killpg(pid, signal.SIGKILL)
                except ProcessLookupError:
                    pass
                self._read(timeout=60)
                return None, Path(out).read_text(errors="replace")
            return int(reply["returncode"]), Path(out).read_text(errors="replace")
        finally:
            os.unlink(out)

    def close(self) -> None:
        """Stop the server."""
        if self._proc.poll() is None:
            assert self._proc.stdin is not None
            self._proc.stdin.close()
            try:
                self._proc.wait(timeout=30)
            except subprocess.TimeoutExpired:
                self._proc.kill()
                self._proc.wait()

    def __enter__(self) -> "WarmPython":
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()


# ---- the server side ----------------------------------------------------------------------------------------
def _child(request: dict) -> int:
    """In the forked process: become the command and run it; returns its exit status (for :func:`_exit`)."""
    try:
        os.setsid()  # its own process group: a timeout kills it and whatever it started
        out = os.open(request["output"], os.O_WRONLY | os.O_CREAT | os.O_TRUNC, 0o644)
        devnull = os.open(os.devnull, os.O_RDONLY)
        os.dup2(devnull, 0)
        os.dup2(out, 1)
        os.dup2(out, 2)
        os.close(out)
        os.close(devnull)
        sys.stdin = open(os.devnull)
        sys.stdout.reconfigure(line_buffering=True)
        sys.stderr.reconfigure(line_buffering=True)
        os.chdir(request["cwd"])
        os.environ.clear()
        os.environ.update(request["env"])
        script = os.path.abspath(request["argv"][0])
        sys.argv = [script, *request["argv"][1:]]
        sys.path[0] = os.path.dirname(script)
        import runpy

        runpy.run_path(script, run_name="__main__")
        return 0
    except SystemExit as e:
        if e.code is None:
            return 0
        if isinstance(e.code, int):
            return e.code
        print(e.code, file=sys.stderr)
        return 1
    except BaseException:  # noqa: BLE001 - report anything, as Python would, then exit 1
        import traceback

        traceback.print_exc()
        return 1


def _exit(code: int) -> None:
    """End the forked process as Python ends one, in what a command can see: non-daemon threads joined, ``atexit``
    handlers run (multiprocessing and joblib clean up there), output flushed; then leave without tearing the
    interpreter down (it would write to every object the server imported, each page a copy-on-write fault after
    the fork: about 1 s per command). Never returns."""
    try:
        shutdown = getattr(threading, "_shutdown", None)  # what the interpreter calls first at exit
        if shutdown is not None:
            shutdown()
        atexit._run_exitfuncs()
    finally:
        for stream in (sys.stdout, sys.stderr):
            try:
                stream.flush()
            except Exception:  # noqa: BLE001 - a closed stream: nothing left to write
                pass
        os._exit(code & 0xFF)


def serve(preload: list[str]) -> None:
    """Import ``preload``, then for each request line on stdin fork a child, reply ``{"pid"}`` and, when the
    child ends, ``{"returncode"}``. Ends at end of input."""
    import importlib

    for name in preload:
        importlib.import_module(name)
    gc.freeze()  # the imported objects leave the collector's lists: a child's collections do not copy their pages
    reply = sys.stdout
    reply.write(json.dumps({"ready": True}) + "\n")
    reply.flush()
    for line in sys.stdin:
        request = json.loads(line)
        sys.stdout.flush()
        sys.stderr.flush()
        pid = os.fork()
        if pid == 0:
            _exit(_child(request))
        reply.write(json.dumps({"pid": pid}) + "\n")
        reply.flush()
        _, status = os.waitpid(pid, 0)
        reply.write(json.dumps({"returncode": os.waitstatus_to_exitcode(status)}) + "\n")
        reply.flush()


if __name__ == "__main__":
    if len(sys.argv) < 2 or sys.argv[1] != "--serve":
        sys.exit("usage: used by tools/check_docs.py (python tools/warm_python.py --serve <module>...)")
    serve(sys.argv[2:])
