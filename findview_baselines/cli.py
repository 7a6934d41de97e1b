"""What every tool in ``tools/`` shares: typed configs checked before any work, one-line user errors with
exit status 2, signals turned into clean exits, and the CPU thread policy.

A tool is::

    from findview_baselines.cli import run_tool

    def main(cfg: EvalConfig, ctx: ToolContext) -> None: ...   # the validated object tree

    if __name__ == "__main__":
        run_tool("eval", main)

:func:`run_tool`

1. registers the schemas (:func:`findview_baselines.config.register_configs`) and the resolvers;
2. composes the config of every job of the command line (each combination of a ``-m`` sweep) and turns
   it into objects, so a wrong type, an unknown key (presets included) or an out-of-range value stops the
   command before anything runs: one line ``<tool>: error: <key>=<value>: expected ...`` on stderr, exit 2;
3. hands over to Hydra (run folder, logging, multirun), calling ``main(typed, ctx)`` per job with the
   job's validated object tree (:class:`~findview_baselines.config.TrainConfig`,
   :class:`~findview_baselines.config.EvalConfig`, ...: the schemas' dataclasses, every value resolved);
4. maps what ``main`` raises: :data:`USER_ERRORS` -> one line and exit 2 (a run folder left with only
   Hydra's files is removed); ``KeyboardInterrupt`` -> exit 130; :class:`Interrupted` (a SIGTERM / SIGINT
   turned into a clean stop by the trainer) -> exit 128 + signal number. Anything else is a bug and
   keeps its traceback.
"""

from __future__ import annotations

import logging
import os
import shutil
import sys
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, NoReturn

from omegaconf import DictConfig

from findview.config import ConfigError
from findview_baselines.config import (  # re-exported: composition and the one-line errors
    CONFIG_DIR,
    compose_config,
    config_error_line,
    register_resolvers,
)
from findview_baselines.errors import Interrupted, UserError  # re-exported: defined below every layer

__all__ = [
    "Interrupted",
    "UserError",
    "USER_ERRORS",
    "ToolContext",
    "compose_config",
    "validate_config",
    "config_error_line",
    "run_tool",
    "CONFIG_DIR",
]

log = logging.getLogger("findview")


def _user_errors() -> tuple[type[BaseException], ...]:
    from findview.dataset.discovery import DatasetError
    from findview.dataset.sampler import SamplingError
    from findview.dataset.splits import MissingDataFile
    from findview.imageio import PanoramaError
    from findview_baselines.rl.checkpoint import CheckpointError, CheckpointNotFound, OutputPathError

    return (UserError, ConfigError, DatasetError, MissingDataFile, PanoramaError, SamplingError, CheckpointError,
            CheckpointNotFound, OutputPathError)


#: exceptions printed as one line with exit status 2: the project's own error types for problems a user
#: caused (config, data, checkpoint, output path). A bare ``ValueError`` / ``OSError`` from inside the
#: library is a bug and keeps its traceback (exit 1). Set ``FINDVIEW_DEBUG=1`` to get the traceback of a
#: user error too.
USER_ERRORS: tuple[type[BaseException], ...] = _user_errors()


@dataclass
class ToolContext:
    """What a tool's ``main`` gets besides the config."""

    run_dir: Path
    """The job's output folder (Hydra's ``runtime.output_dir``)."""
    choices: dict[str, str] = field(default_factory=dict)
    """Config-group choices, e.g. ``{"agent": "sift", "dataset": "synthetic"}``."""
    overrides: list[str] = field(default_factory=list)
    """The job's command-line overrides (what the user set, e.g. for keys a checkpoint must not replace)."""


# ------------------------------------------------------------------------------------------------
# Resolvers
# ------------------------------------------------------------------------------------------------


# ------------------------------------------------------------------------------------------------
# Composition and validation
# ------------------------------------------------------------------------------------------------


def _job_overrides(argv: Sequence[str], multirun: bool) -> list[list[str]]:
    """The overrides of every job the command line asks for (one list for a single run)."""
    overrides = [a for a in argv if not a.startswith("-")]
    if not multirun:
        return [overrides]
    from hydra._internal.core_plugins.basic_sweeper import BasicSweeper
    from hydra.core.override_parser.overrides_parser import OverridesParser

    parsed = OverridesParser.create().parse_overrides(overrides)
    batches = BasicSweeper.split_arguments(parsed, None)
    return [job for batch in batches for job in batch] or [overrides]


def validate_config(cfg: DictConfig) -> Any:
    """Instantiate the schemas of ``cfg`` (without its ``hydra`` node), which runs every range check.

    Returns the object tree (``TrainConfig``, ``EvalConfig``, ...). Raises :class:`ConfigError` (one-line
    message naming the key).
    """
    from findview_baselines.config import typed_config

    return typed_config(cfg)


def _torch_threads(typed: Any) -> int | None:
    """The CPU thread count a tool's config asks for (``torch_threads`` or ``trainer.torch_threads``; null:
    findview's policy)."""
    from findview_baselines.config import EvalConfig, TrainConfig

    if isinstance(typed, TrainConfig):
        return typed.trainer.torch_threads
    if isinstance(typed, EvalConfig):
        return typed.torch_threads
    return None


def _fail(tool: str, message: str, status: int = 2) -> NoReturn:
    print(f"{tool}: error: {' '.join(message.split())}", file=sys.stderr, flush=True)
    sys.exit(status)


def precheck(tool: str, config_name: str, argv: Sequence[str], check_run_dir: bool = False) -> None:
    """Compose and validate every job of the command line; exit 2 with one line on the first problem
    (``check_run_dir``: also a run / sweep folder that cannot be written, see :func:`check_output_folder`)."""
    flags = [a for a in argv if a.startswith("-")]
    if any(f not in ("-m", "--multirun") for f in flags):
        return  # --help, --cfg job, --info ...: Hydra's own business
    jobs = _job_overrides(argv, multirun=bool(flags))
    for job in jobs:
        try:
            cfg = compose_config(config_name, job, return_hydra_config=True)
        except Exception as err:
            _fail(tool, config_error_line(err))
        try:
            validate_config(cfg)
        except ConfigError as err:
            _fail(tool, str(err))
    if check_run_dir:
        _precheck_run_dir(tool, cfg, multirun=bool(flags))


def check_output_folder(folder: str | os.PathLike, what: str) -> None:
    """Prove that ``folder`` can be created and written, leaving nothing behind that was not there.

    Raises:
        OutputPathError: (from :func:`findview_baselines.rl.checkpoint.check_writable`) naming the folder.
    """
    from findview_baselines.rl.checkpoint import check_writable

    folder = Path(folder).expanduser().absolute()
    first_new = None  # the outermost folder the check creates
    for p in (folder, *folder.parents):
        if os.path.lexists(p):
            break
        first_new = p
    try:
        check_writable(folder, what)
    finally:
        if first_new is not None:
            shutil.rmtree(first_new, ignore_errors=True)  # Hydra makes it; a check must leave nothing behind


def _precheck_run_dir(tool: str, cfg: DictConfig, multirun: bool = False) -> None:
    """A run into a folder that cannot be written (or, single runs, that a live training holds) fails
    before Hydra creates anything; a sweep checks its sweep folder. Shared by every tool."""
    from findview_baselines.rl.checkpoint import OutputPathError
    from findview_baselines.rl.safety import lock_holder

    key = "hydra.sweep.dir" if multirun else "hydra.run.dir"
    try:
        run_dir = Path(str(cfg.hydra.sweep.dir if multirun else cfg.hydra.run.dir))
    except Exception:
        return  # a name Hydra only knows at run time: left to the run
    holder = lock_holder(run_dir) if not multirun and run_dir.is_dir() else None
    if holder is not None:
        _fail(tool, f"run folder {run_dir} is in use by a live training run (pid {holder}); wait for it to "
                    f"finish, stop it, or train into another folder (hydra.run.dir=<folder>)")
    try:
        check_output_folder(run_dir, f"{'sweep' if multirun else 'run'} folder ({key})")
    except OutputPathError as err:
        _fail(tool, str(err))


def _is_disposable(entry: Path) -> bool:
    """Hydra's files, a log, a released run lock, or a folder holding nothing else."""
    if entry.name in (".hydra", ".run.lock") or (entry.is_file() and entry.suffix == ".log"):
        return True
    return entry.is_dir() and all(_is_disposable(e) for e in entry.iterdir())


def _remove_if_empty_run(run_dir: Path) -> None:
    """Remove a run folder that holds no results (a run that failed before producing any)."""
    try:
        entries = list(run_dir.iterdir())
    except OSError:
        return
    if all(_is_disposable(e) for e in entries):
        shutil.rmtree(run_dir, ignore_errors=True)
        parent = run_dir.parent  # outputs/eval/<name>/ may be empty now
        try:
            if parent.is_dir() and not any(parent.iterdir()):
                parent.rmdir()
        except OSError:
            pass


def run_tool(
    config_name: str,
    main: Callable[[Any, ToolContext], Any],
    tool: str | None = None,
    check_run_dir: bool = True,
    implied: Callable[[list[str]], list[str]] | None = None,
) -> None:
    """Run ``main`` as the Hydra app of ``configs/<config_name>.yaml`` (see module docstring).

    Args:
        config_name: the primary config.
        main: ``main(typed, ctx)``, called per job with the validated object tree of the job's config.
        tool: the name in messages (default ``config_name``).
        check_run_dir: refuse a run / sweep folder that cannot be written before anything runs (one line,
            exit 2); ``False`` where another process owns the folder (torchrun ranks > 0).
        implied: rewrites the command-line arguments before composition, for overrides that imply
            others (``tools/eval.py``: ``checkpoint=`` implies ``agent=ppo``); validation, Hydra and
            ``ctx.overrides`` see the result.
    """
    import hydra
    from hydra.core.hydra_config import HydraConfig

    from findview.runtime import configure_threads
    from findview_baselines.config import register_configs

    tool = tool or config_name
    register_configs()
    register_resolvers()
    if implied is not None:
        sys.argv[1:] = implied(list(sys.argv[1:]))
    precheck(tool, config_name, sys.argv[1:], check_run_dir)

    @hydra.main(version_base="1.3", config_path=str(CONFIG_DIR), config_name=config_name)
    def _app(cfg: DictConfig) -> None:
        hc = HydraConfig.get()
        ctx = ToolContext(Path(hc.runtime.output_dir), dict(hc.runtime.choices), list(hc.overrides.task))
        try:
            typed = validate_config(cfg)  # checked before Hydra started: the objects main works on
            configure_threads(_torch_threads(typed))
            main(typed, ctx)
        except Interrupted as err:
            print(f"{tool}: {err}", file=sys.stderr, flush=True)
            sys.exit(128 + err.signum)
        except KeyboardInterrupt:
            print(f"{tool}: interrupted; nothing more was written", file=sys.stderr, flush=True)
            _remove_if_empty_run(ctx.run_dir)
            sys.exit(130)
        except USER_ERRORS as err:
            if os.environ.get("FINDVIEW_DEBUG"):
                raise
            logging.shutdown()
            _remove_if_empty_run(ctx.run_dir)
            _fail(tool, str(err))

    _app()
