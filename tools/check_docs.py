"""Run every documented shell command, so that the docs cannot drift from the code.

    python tools/check_docs.py                       # README.md, docs/*.md, pretrained/README.md, benchmarks/RESULTS.md
    python tools/check_docs.py README.md --list      # only list what would run
    python tools/check_docs.py --keep                # keep the temporary working folder (printed)

What counts as a command: a line of a fenced code block (```, ```bash, ```sh, ```console) or the text of
an inline code span (paragraphs and table cells) that starts with ``python tools/``, ``python benchmarks/``,
``pip install``, ``torchrun`` or ``tensorboard`` (after optional ``VAR=value`` assignments). Backslash
continuations are joined, ``#`` comments dropped, ``a && b`` chains split and a background ``a &`` run in
turn.

How it runs them:

- in one temporary working folder per run, doc by doc and in the order written, so a later command sees
  what an earlier one made (``data/``, ``outputs/``); the folder holds a copy of the repository's
  ``pretrained/`` (a card's "make it" commands end by writing the shipped file: they write the copy, never the
  repository's); the scripts are called by absolute path; each command has a timeout;
- a plain ``python <script> ...`` runs in a process forked from one that imported torch, OpenCV, Hydra and
  findview once (``tools/warm_python.py``: each command still gets a process of its own, ~2 s sooner); one
  with shell syntax or a load-time variable (``OMP_NUM_THREADS=1 python ...``) runs under bash; ``--cold``
  runs them all under bash;
- placeholders are filled in from ``PLACEHOLDERS`` (``<name>`` -> synthetic, ``<sun360_mini>`` -> the
  folder in ``$FINDVIEW_SUN360_MINI``, ``<a|b|c>`` -> a, ...); an optional part ``[key=...]`` is left out;
- long commands get small overrides appended (``OVERRIDES``: later arguments win in Hydra and argparse);
- ``pip install`` is checked, not run: every extra it names exists in setup.py, every requirement parses;
- ``tensorboard --logdir D`` is checked, not run (a server): ``tensorboard`` is installed and D holds
  event files;
- a console example (``$ cmd`` followed by ``tool: error: ...``) must exit 2 and print that line;
  everything else must exit 0.

Skipped, with a note: a command that needs the real panoramas while ``FINDVIEW_SUN360_MINI`` is unset,
or a ``pretrained/*.pth`` that is not there (both fail under ``CI=true``), and every command of a block
(or paragraph) preceded by ``<!-- check_docs: skip (reason) -->``: only for commands that take hours or
need a GPU / cluster.

Prints a table (doc, line, status, seconds, command); exit status 1 if any command failed.
"""

from __future__ import annotations

import argparse
import ast
import functools
import glob
import os
import re
import shlex
import shutil
import subprocess
import sys
import tempfile
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Callable, Optional, Union

sys.path.insert(0, str(Path(__file__).resolve().parent))  # its sibling module, also when loaded by file path
from warm_python import WarmPython, fork_args  # noqa: E402

REPO = Path(__file__).resolve().parents[1]
DEFAULT_DOCS = ("README.md", "docs/*.md", "pretrained/README.md", "benchmarks/RESULTS.md")
SUN360_ENV = "FINDVIEW_SUN360_MINI"

_ASSIGN = r"(?:[A-Za-z_][A-Za-z0-9_]*=\S*\s+)*"
COMMAND_RE = re.compile(_ASSIGN + r"(?:python (?:tools|benchmarks)/\S|pip install \S|torchrun \S|tensorboard \S)")
SKIP_RE = re.compile(r"<!--\s*check_docs:\s*skip\s*\((?P<reason>.*)\)\s*-->")
FENCE_RE = re.compile(r"^\s*```\s*(?P<lang>[\w-]*)\s*$")
SHELL_LANGS = {"", "bash", "sh", "shell", "console"}
# shell syntax that a forked ``python <script>`` could not reproduce: such a command runs under bash
SHELL_SYNTAX = re.compile(r"[|&;<>()$`*?!\\]")


# ---- placeholders ----------------------------------------------------------------------------------
@dataclass
class Context:
    """What a placeholder may need: the working folder and the environment."""

    cwd: Path
    sun360: Optional[str]
    needs: set = field(default_factory=set)  # "sun360" when a command used the real panoramas


def _sun360(ctx: Context) -> str:
    ctx.needs.add("sun360")
    return ctx.sun360 or "/missing-FINDVIEW_SUN360_MINI"


def _newest(pattern: str, default: str, parent: bool = False) -> Callable[[Context], str]:
    def find(ctx: Context) -> str:
        hits = sorted(glob.glob(str(ctx.cwd / pattern), recursive=True), key=os.path.getmtime)
        hit = os.path.relpath(hits[-1], ctx.cwd) if hits else default
        return os.path.dirname(hit) if parent else hit

    return find


PRETRAINED = "pretrained/findview_sun360mini_indoor.pth"
Value = Union[str, Callable[[Context], str]]
# (regex, value): applied in this order; a value may be a function of the working folder
PLACEHOLDERS: list[tuple[str, Value]] = [
    # the real panoramas (SUN360 layout); the docs' example paths of a full copy stand for them too
    (r"<SUN360 or sun360_mini>|<sun360_mini>|\$\{?FINDVIEW_SUN360_MINI\}?|/data/SUN360|/path/to/SUN360", _sun360),
    # a data set config name
    (r"<name>", "synthetic"),
    # checkpoints: the newest one an earlier command of the doc wrote
    (r"<ckpt>|<best\.pth>|<path>", _newest("outputs/**/checkpoints/best.pth", "outputs/NO-CHECKPOINT-YET/best.pth")),
    # RESULTS.md's fine-tuning "before" agent is the pretrained imitation agent (same model signature)
    (r"<before\.pth>|<after\.pth>", PRETRAINED),
    # the folder of the last Hydra multirun
    (r"<multirun dir>", _newest("**/multirun.yaml", "NO-MULTIRUN-YET/multirun.yaml", parent=True)),
    # agents
    (r"<agent>|<a>", "orb"),
    # RESULTS.md, learned-agent table: "CK a checkpoint, P the penalty, S val or test, D indoor or outdoor"
    (r"\$CK\b", PRETRAINED),
    (r"\$P\b", "16"),
    (r"\$D\b", "indoor"),
    (r"\$S\b", "test"),
    # process count of a torchrun template
    (r"--nproc_per_node=K\b", "--nproc_per_node=2"),
]
ALTERNATIVES_RE = re.compile(r"<([\w.]+(?:\|[\w.]+)+)>")  # <a|b|c> -> a
OPTIONAL_RE = re.compile(r"(?:(?<=\s)|^)\[[^\]\s]*\](?=\s|$)")  # a whole [key=value] token: optional
ELLIPSIS_RE = re.compile(r"(?:(?<=\s)|^)\.\.\.(?=\s|$)")  # a standalone "...": "and so on"


def substitute(cmd: str, ctx: Context) -> str:
    cmd = cmd.replace("\\|", "|")
    cmd = OPTIONAL_RE.sub("", cmd)
    cmd = ELLIPSIS_RE.sub("", cmd)
    cmd = ALTERNATIVES_RE.sub(lambda m: m.group(1).split("|")[0], cmd)
    for pattern, value in PLACEHOLDERS:
        if re.search(pattern, cmd):
            cmd = re.sub(pattern, (value(ctx) if callable(value) else value).replace("\\", "\\\\"), cmd)
    return " ".join(cmd.split())


# ---- small overrides ----------------------------------------------------------------------------------
# appended to a command; Hydra and argparse take the last value of a key. Keys: configs/, findview/config.py,
# findview_baselines/config.py, and each benchmark's argparse.
TRAIN = ("trainer.num_updates=2 trainer.val_interval=1 trainer.val_episodes=2 trainer.val_num_envs=2 "
         "trainer.val_max_steps=30 trainer.num_envs=2 trainer.log_interval=1 trainer.checkpoint_interval=1 "
         "trainer.progress=false task.max_steps=300 sim.height=64 sim.width=64")
# per algorithm (a key of the algorithm that does not run is refused)
TRAIN_ALGORITHM = {
    "dagger": "trainer.dagger.rollout_steps=8 trainer.dagger.seq_len=8 trainer.dagger.epochs=1",
    "ppo": "trainer.ppo.rollout_steps=8 trainer.ppo.ppo_epochs=1",
}
EVAL = "max_episodes=2 task.max_steps=30 progress=false"
# every tools/ command: smaller synthetic panoramas (generated in seconds, not 20 s; a synthetic-only key)
TOOLS = "dataset.width=256"
HYDRA_TOOLS = {f"tools/{t}.py" for t in ("train", "eval", "make_dataset", "render_episode", "render_corruptions")}
EVAL_VIEWS = "sim.height=64 sim.width=64"  # rule-based agents: 64x64 views are 16x cheaper
OVERRIDES: dict[str, str] = {
    "tools/train.py": TRAIN,
    "tools/eval.py": EVAL,
    "benchmarks/bench_sim.py": "--iters 1 --env-steps 5 --batch 2",
    "benchmarks/bench_train.py": "--updates 1 --rollout-steps 2 --num-envs 2",
    "benchmarks/bench_dagger.py": "--updates 1 --rounds 1",
    "benchmarks/bench_scale.py": "--quick",
    "benchmarks/bench_lr_scaling.py": "--quick",
    "benchmarks/bench_load.py": "--rounds 1 --env-steps 2 --decisions 2 --ppo-size 64 --ppo-envs 2 --ppo-steps 2",
    "benchmarks/bench_distributed.py": "--updates 2 --envs 2 --rollout-steps 4 --hidden 32",
    "benchmarks/bench_corruptions.py": "--repeats 1 --batch 2 --size 64 --names fog",
    "tools/train_stop_offsets.py": "--pairs 40 --blur-pairs 10 --val-pairs 20 --epochs 1",
    "benchmarks/robustness.py": "--T 30 --max-episodes 2 --corruptions fog --severities 3 --fovs 90 --no-clear --calibration-episodes 0 --jobs 2 --override dataset.width=256",
}
TIMEOUT_S = 300


# ---- extraction --------------------------------------------------------------------------------------------
@dataclass
class DocCommand:
    doc: str
    line: int
    text: str  # as written (continuations joined, comment dropped)
    expect_error: Optional[str] = None  # console example: the error line it must print (exit 2)
    skip: Optional[str] = None  # reason from a skip marker
    block: int = 0  # first line of its code block or paragraph: later commands of a block may need earlier ones


def _strip_comment(line: str) -> str:
    """Drop a shell comment (# outside quotes, at the start or after whitespace)."""
    quote = None
    for i, ch in enumerate(line):
        if quote:
            if ch == quote:
                quote = None
        elif ch in "'\"":
            quote = ch
        elif ch == "#" and (i == 0 or line[i - 1].isspace()):
            return line[:i].rstrip()
    return line.rstrip()


def split_commands(line: str) -> list[str]:
    """``a && b`` -> [a, b] (``&&`` outside quotes); ``a & b`` and ``a &`` (a job in the background, beside the
    next) -> [a, b] and [a]: the checker runs the parts one after the other. A redirection (``2>&1``, ``&>``) is
    no separator."""
    parts, quote, start, i = [], None, 0, 0
    while i < len(line):
        ch = line[i]
        if quote:
            quote = None if ch == quote else quote
        elif ch in "'\"":
            quote = ch
        elif ch == "&" and not (line[i - 1:i] in ("<", ">") or line[i + 1:i + 2] == ">"):  # not 2>&1, &>
            step = 2 if line.startswith("&&", i) else 1
            parts.append(line[start:i].strip())
            start = i + step
            i += step - 1
        i += 1
    parts.append(line[start:].strip())
    return [p for p in parts if p]


def is_command(text: str) -> bool:
    return COMMAND_RE.match(text.strip() + " ") is not None


def _fenced(doc: str, block: list[tuple[int, str]], skip: Optional[str]) -> list[DocCommand]:
    out: list[DocCommand] = []
    # join continuations, keep the first line number
    logical: list[tuple[int, str]] = []
    buf, start = "", 0
    for no, raw in block:
        text = raw.rstrip()
        if not buf:
            start = no
        if text.endswith("\\"):
            buf += _strip_comment(text[:-1]) + " "
            continue
        logical.append((start, buf + text))
        buf = ""
    if buf:
        logical.append((start, buf))
    for k, (no, text) in enumerate(logical):
        console = text.lstrip().startswith("$ ")
        if console:
            text = text.lstrip()[2:]
        elif any(t.lstrip().startswith("$ ") for _, t in logical):
            continue  # output line of a console example
        expect = None
        if console:
            following = []
            for _, t in logical[k + 1:]:
                if t.lstrip().startswith("$ "):
                    break
                following.append(t.strip())
            expect = next((t for t in following if re.match(r"[\w.-]+: error: ", t)), None)
        for part in split_commands(_strip_comment(text)):
            if is_command(part):
                out.append(DocCommand(doc, no, " ".join(part.split()), expect, skip, block[0][0] if block else 0))
    return out


def _inline(doc: str, para: list[tuple[int, str]], skip: Optional[str]) -> list[DocCommand]:
    out: list[DocCommand] = []
    text = "\n".join(t for _, t in para)
    offsets, pos = [], 0
    for no, t in para:
        offsets.append((pos, no))
        pos += len(t) + 1
    for m in re.finditer(r"(?<!`)`([^`]+)`(?!`)", text):
        line = max(no for off, no in offsets if off <= m.start())
        for part in split_commands(m.group(1).replace("\n", " ")):
            if is_command(part):
                out.append(DocCommand(doc, line, " ".join(part.split()), None, skip, para[0][0] if para else 0))
    return out


def extract(markdown: str, doc: str = "<string>") -> list[DocCommand]:
    """Every command of a Markdown text, in order (see the module docstring)."""
    commands: list[DocCommand] = []
    pending: Optional[str] = None  # reason of a skip marker waiting for its block / paragraph
    para: list[tuple[int, str]] = []
    para_skip: Optional[str] = None
    fence: Optional[list[tuple[int, str]]] = None
    fence_lang = ""

    def flush_para() -> None:
        nonlocal para, para_skip
        if para:
            commands.extend(_inline(doc, para, para_skip))
        para, para_skip = [], None

    for no, line in enumerate(markdown.splitlines(), start=1):
        m = FENCE_RE.match(line)
        if fence is not None:
            if m and not m.group("lang"):
                if fence_lang in SHELL_LANGS:
                    commands.extend(_fenced(doc, fence, pending))
                pending, fence = None, None
            else:
                fence.append((no, line))
            continue
        if m:
            flush_para()
            fence, fence_lang = [], m.group("lang").lower()
            continue
        marker = SKIP_RE.search(line)
        if marker and not SKIP_RE.sub("", line).strip():  # a marker on a line of its own
            flush_para()
            pending = marker.group("reason").strip() or "no reason given"
            continue
        if not line.strip():
            flush_para()
            continue
        if not para:
            para_skip, pending = pending, None
        if marker:
            para_skip = marker.group("reason").strip() or "no reason given"
        para.append((no, line))
    flush_para()
    return commands


# ---- running -------------------------------------------------------------------------------------------------
@dataclass
class Result:
    cmd: DocCommand
    status: str  # ok | FAIL | skip
    seconds: float = 0.0
    note: str = ""
    ran: str = ""


def _script(cmd: str) -> Optional[str]:
    m = re.search(r"(?:^|\s)((?:tools|benchmarks)/[\w/]+\.py)\b", cmd)
    return m.group(1) if m else None


def _extras() -> set[str]:
    tree = ast.parse((REPO / "setup.py").read_text())
    for node in ast.walk(tree):
        if isinstance(node, ast.keyword) and node.arg == "extras_require" and isinstance(node.value, ast.Dict):
            return {ast.literal_eval(k) for k in node.value.keys}
    return set()


def check_pip(cmd: str) -> Optional[str]:
    """None when the ``pip install`` line is well formed and names only existing extras, else why not."""
    try:
        args = shlex.split(cmd)
    except ValueError as e:
        return f"cannot parse: {e}"
    args = args[args.index("pip") + 2:]
    extras = _extras()
    for arg in args:
        if arg.startswith("-"):
            continue
        m = re.fullmatch(r"(?:\.|findview)\[([\w,\s-]+)\]", arg)
        if m:
            missing = [e.strip() for e in m.group(1).split(",") if e.strip() not in extras]
            if missing:
                return f"no extra {missing} in setup.py (has {sorted(extras)})"
            continue
        if arg in (".", "findview"):
            continue
        try:
            from packaging.requirements import Requirement

            Requirement(arg)
        except ImportError:
            pass
        except Exception as e:  # InvalidRequirement
            return f"not a requirement: {arg!r} ({e})"
    return None


def check_tensorboard(cmd: str, cwd: Path) -> Optional[str]:
    args = shlex.split(cmd)
    if shutil.which("tensorboard") is None:
        try:
            import tensorboard  # noqa: F401
        except ImportError:
            return "tensorboard is not installed"
    logdir = next((a.split("=", 1)[1] for a in args if a.startswith("--logdir=")), None)
    if logdir is None and "--logdir" in args:
        logdir = args[args.index("--logdir") + 1]
    if logdir is None:
        return "no --logdir"
    if not list((cwd / logdir).rglob("events.out.tfevents.*")):
        return f"no TensorBoard event files under {logdir}"
    return None


def _train_algorithm(cmd: str, script: str) -> str:
    """``trainer.algorithm`` of a documented ``tools/train.py`` command (``ppo`` when it does not compose:
    its run then shows the problem). Only the overrides that can choose it are composed (``trainer=``,
    ``trainer.algorithm=``, ``[+]experiment=``), once per distinct set: the docs hold many train commands."""
    args = [a for a in shlex.split(cmd.split(script, 1)[1]) if not a.startswith("-") and "=" in a]
    chooses = tuple(a for a in args if a.split("=", 1)[0].lstrip("+~") in ("trainer", "trainer.algorithm", "experiment"))
    return _compose_algorithm(chooses)


@functools.lru_cache(maxsize=None)
def _compose_algorithm(args: tuple[str, ...]) -> str:
    from findview_baselines.cli import compose_config

    try:
        return str(compose_config("train", list(args)).trainer.algorithm)
    except Exception:
        return "ppo"


def prepare(cmd: str, overrides: bool = True) -> str:
    """Scripts by absolute path, the small overrides appended (not to an error example: they could hide it)."""
    script = _script(cmd)
    if script is None:
        return cmd
    if script == "tools/check_docs.py":  # itself: only list what it would run (running it would recurse)
        return f"{cmd.replace(script, str(REPO / script), 1)} --list"
    extra = OVERRIDES.get(script, "") if overrides else ""
    if overrides and script in HYDRA_TOOLS:
        extra = f"{extra} {TOOLS}"
    if overrides and script == "tools/train.py":
        extra = f"{extra} {TRAIN_ALGORITHM[_train_algorithm(cmd, script)]}"
    if overrides and script == "tools/eval.py" and "checkpoint=" not in cmd:
        extra = f"{extra} {EVAL_VIEWS}"  # with a checkpoint the view size is the checkpoint's
    cmd = re.sub(r"(^|\s)" + re.escape(script), lambda m: m.group(1) + str(REPO / script), cmd, count=1)
    return f"{cmd} {extra}".strip()


def run_all(commands: list[DocCommand], cwd: Path, ci: bool, timeout: float, verbose: bool = False,
            warm: Optional[WarmPython] = None) -> list[Result]:
    """:func:`run_one` for each command in order; a command whose block had an earlier command skipped for want of
    its data (not a skip marker) is skipped too, since it may need what that one would have made."""
    results: list[Result] = []
    wanting: set[tuple[str, int]] = set()  # (doc, block) with a command skipped for missing data
    for c in commands:
        if not c.skip and (c.doc, c.block) in wanting:
            r = Result(c, "skip", note="an earlier command of its block was skipped (missing data)")
        else:
            r = run_one(c, cwd, ci, timeout, warm)
            if r.status == "skip" and not c.skip:
                wanting.add((c.doc, c.block))
        results.append(r)
        if verbose:
            print(f"[{r.status} {r.seconds:5.1f}s] {c.doc}:{c.line}: {r.ran or c.text}", flush=True)
    return results


def run_one(c: DocCommand, cwd: Path, ci: bool, timeout: float, warm: Optional[WarmPython] = None) -> Result:
    """Check or run one command in ``cwd``; ``python <script>`` commands in a process forked by ``warm`` (when given)."""
    if c.skip:
        return Result(c, "skip", note=f"marked: {c.skip}")
    ctx = Context(cwd, os.environ.get(SUN360_ENV) or None)
    cmd = substitute(c.text, ctx)
    left = re.findall(r"<[^<>\s]*>", cmd)
    if left:
        return Result(c, "FAIL", note=f"unknown placeholder {left[0]} (add it to PLACEHOLDERS)", ran=cmd)
    missing = []
    if "sun360" in ctx.needs and not ctx.sun360:
        missing.append(f"{SUN360_ENV} is not set")
    for m in re.finditer(r"(pretrained/[\w.-]+\.pth)", cmd):
        if not (REPO / m.group(1)).is_file():
            missing.append(f"{m.group(1)} is missing")
    if missing:
        note = "; ".join(missing)
        return Result(c, "FAIL" if ci else "skip", note=note + (" (CI=true)" if ci else ""), ran=cmd)
    words = cmd.split()
    while words and re.fullmatch(r"[A-Za-z_]\w*=\S*", words[0]):
        words = words[1:]
    if words[:2] == ["pip", "install"]:
        why = check_pip(cmd)
        return Result(c, "FAIL" if why else "ok", note=why or "checked, not run", ran=cmd)
    if words[:1] == ["tensorboard"]:
        why = check_tensorboard(cmd, cwd)
        return Result(c, "FAIL" if why else "ok", note=why or "logdir checked, not run", ran=cmd)
    ran = prepare(cmd, overrides=c.expect_error is None)
    env = dict(os.environ)
    env["PATH"] = os.path.dirname(sys.executable) + os.pathsep + env.get("PATH", "")
    env["PYTHONUNBUFFERED"] = "1"
    t0 = time.monotonic()
    try:
        fork = fork_args(shlex.split(ran)) if warm is not None and not SHELL_SYNTAX.search(ran) else None
    except ValueError:  # unbalanced quotes: bash reports them
        fork = None
    if fork is not None:
        assigned, argv = fork  # VAR=value assignments, none of them read at load time
        returncode, output = warm.run(argv, cwd=cwd, env={**env, **assigned}, timeout=timeout)
        if returncode is None:
            return Result(c, "FAIL", time.monotonic() - t0, f"timeout after {timeout:.0f} s", ran)
    else:
        try:
            p = subprocess.run(["bash", "-c", ran], cwd=cwd, env=env, capture_output=True, text=True,
                               timeout=timeout, stdin=subprocess.DEVNULL, start_new_session=True)
        except subprocess.TimeoutExpired:
            return Result(c, "FAIL", time.monotonic() - t0, f"timeout after {timeout:.0f} s", ran)
        returncode, output = p.returncode, p.stdout + p.stderr
    dt = time.monotonic() - t0
    if c.expect_error is not None:
        want = c.expect_error.split("(...)")[0].strip()
        if returncode != 2:
            return Result(c, "FAIL", dt, f"exit {returncode}, the doc shows an error (exit 2)", ran)
        if want not in output:
            got = next((ln for ln in output.splitlines() if ": error: " in ln), output.strip()[-200:])
            return Result(c, "FAIL", dt, f"printed {got!r}, the doc shows {c.expect_error!r}", ran)
        return Result(c, "ok", dt, "exit 2 with the doc's error line", ran)
    if returncode != 0:
        tail = " | ".join(output.strip().splitlines()[-3:])[-400:]
        return Result(c, "FAIL", dt, f"exit {returncode}: {tail}", ran)
    return Result(c, "ok", dt, "", ran)


def doc_paths(patterns: list[str]) -> list[Path]:
    out: list[Path] = []
    for pat in patterns:
        hits = sorted(REPO.glob(pat)) if any(ch in pat for ch in "*?[") else [REPO / pat]
        out += [h for h in hits if h not in out]
    return out


def main(argv: Optional[list[str]] = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0],
                                 formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("docs", nargs="*", default=list(DEFAULT_DOCS),
                    help="Markdown files or globs, relative to the repository root (default: all the docs)")
    ap.add_argument("--list", action="store_true", help="print the commands (placeholders filled in), run nothing")
    ap.add_argument("--timeout", type=float, default=TIMEOUT_S, help="seconds per command")
    ap.add_argument("--workdir", type=Path, default=None, help="working folder (default: a new temporary one)")
    ap.add_argument("--keep", action="store_true", help="keep the temporary working folder")
    ap.add_argument("-v", "--verbose", action="store_true", help="also print each command as run")
    ap.add_argument("--cold", action="store_true",
                    help="run every command in a new Python, as a shell would (default: `python <script>` commands "
                         "in processes forked from one that imported torch and findview once: ~2 s less each)")
    args = ap.parse_args(argv)
    ci = os.environ.get("CI", "").lower() == "true"

    commands: list[DocCommand] = []
    for path in doc_paths(args.docs):
        if not path.is_file():
            print(f"check_docs: error: no such doc: {path}", file=sys.stderr)
            return 2
        commands += extract(path.read_text(encoding="utf-8"), str(path.relative_to(REPO)))
    if args.list:
        ctx = Context(REPO, os.environ.get(SUN360_ENV) or "$" + SUN360_ENV)
        for c in commands:
            mark = f"  [skip: {c.skip}]" if c.skip else (f"  [expects: {c.expect_error}]" if c.expect_error else "")
            print(f"{c.doc}:{c.line}: {prepare(substitute(c.text, ctx), c.expect_error is None)}{mark}")
        return 0

    work = args.workdir or Path(tempfile.mkdtemp(prefix="findview_check_docs_"))
    work.mkdir(parents=True, exist_ok=True)
    if not (work / "pretrained").exists():  # a copy: a documented command may write a file there (a card's last step)
        shutil.copytree(REPO / "pretrained", work / "pretrained")
    warm = None if args.cold or not hasattr(os, "fork") else WarmPython()
    try:
        results = run_all(commands, work, ci, args.timeout, args.verbose, warm)
    finally:
        if warm is not None:
            warm.close()
        if args.keep or args.workdir:
            print(f"working folder: {work}")
        else:
            shutil.rmtree(work, ignore_errors=True)

    width = max([len(f"{r.cmd.doc}:{r.cmd.line}") for r in results] + [8])
    print(f"{'doc:line':<{width}}  {'status':<6}  {'s':>6}  command")
    for r in results:
        text = r.cmd.text if len(r.cmd.text) <= 110 else r.cmd.text[:107] + "..."
        print(f"{r.cmd.doc + ':' + str(r.cmd.line):<{width}}  {r.status:<6}  {r.seconds:6.1f}  {text}")
        if r.note:
            print(f"{'':<{width}}  {'':<6}  {'':>6}  -> {r.note}")
    failed = [r for r in results if r.status == "FAIL"]
    n = {s: sum(r.status == s for r in results) for s in ("ok", "skip", "FAIL")}
    total = sum(r.seconds for r in results)
    print(f"check_docs: {len(results)} commands: {n['ok']} ok, {n['skip']} skipped, {n['FAIL']} failed ({total:.0f} s)")
    return 1 if failed else 0


if __name__ == "__main__":
    sys.exit(main())
