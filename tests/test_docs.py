"""Every documented command runs (tools/check_docs.py), and the extractor finds what it should."""

from __future__ import annotations

import hashlib
import importlib.util
import os
import subprocess
import sys
import time
from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parents[1]


def _check_docs():
    spec = importlib.util.spec_from_file_location("check_docs", REPO / "tools" / "check_docs.py")
    module = importlib.util.module_from_spec(spec)
    sys.modules["check_docs"] = module
    spec.loader.exec_module(module)
    return module


check_docs = _check_docs()

SAMPLE = """# Title

Run `python tools/eval.py agent=<orb|sift> dataset=<name> [episode_index=3]` or read `findview/sim.py`.

| command | what |
|---|---|
| `python tools/make_dataset.py dataset=<name>` | make it |

```bash
# a comment
pip install -e . && python tools/train.py +experiment=quickstart \\
    trainer.num_updates=5   # trailing comment
python -m pytest -q tests
OMP_NUM_THREADS=1 python benchmarks/bench_sim.py --iters 2
python tools/train.py seed=1 &
python tools/train.py seed=2 & python tools/eval.py 'a&b' > log 2>&1
wait
```

```
$ python tools/train.py trainer.num_envs=abc
train: error: trainer.num_envs='abc': expected an integer
```

<!-- check_docs: skip (needs a GPU) -->
```bash
python benchmarks/bench_train.py --device cuda
```

<!-- check_docs: skip (hours) -->
Inline: `torchrun --nproc_per_node=K tools/train.py ...
trainer.distributed=true`.

```python
python tools/not_shell.py
```

Afterwards `python tools/render_episode.py dataset.root=<sun360_mini>` runs again.
"""


def test_extractor_finds_commands_joins_splits_and_marks():
    cmds = check_docs.extract(SAMPLE, "sample.md")
    texts = [c.text for c in cmds]
    assert texts == [
        "python tools/eval.py agent=<orb|sift> dataset=<name> [episode_index=3]",
        "python tools/make_dataset.py dataset=<name>",
        "pip install -e .",
        "python tools/train.py +experiment=quickstart trainer.num_updates=5",
        "OMP_NUM_THREADS=1 python benchmarks/bench_sim.py --iters 2",
        "python tools/train.py seed=1",  # a background job: run in turn
        "python tools/train.py seed=2",
        "python tools/eval.py 'a&b' > log 2>&1",  # a redirection is no separator
        "python tools/train.py trainer.num_envs=abc",
        "python benchmarks/bench_train.py --device cuda",
        "torchrun --nproc_per_node=K tools/train.py ... trainer.distributed=true",
        "python tools/render_episode.py dataset.root=<sun360_mini>",
    ]
    lines = [c.line for c in cmds]
    assert lines == [3, 7, 11, 11, 14, 15, 16, 16, 21, 27, 31, 38]
    by_text = {c.text: c for c in cmds}
    assert by_text["python tools/train.py trainer.num_envs=abc"].expect_error == (
        "train: error: trainer.num_envs='abc': expected an integer")
    assert by_text["python benchmarks/bench_train.py --device cuda"].skip == "needs a GPU"
    assert by_text["torchrun --nproc_per_node=K tools/train.py ... trainer.distributed=true"].skip == "hours"
    assert [c.skip for c in cmds].count(None) == 10  # the markers stop at their own block / paragraph


def test_placeholders_and_overrides(tmp_path):
    ctx = check_docs.Context(tmp_path, "/panos")
    cmd = check_docs.substitute(
        "python tools/eval.py agent=<orb\\|sift> dataset=<name> [episode_index=3] dataset.root=<sun360_mini> "
        "'corruption.severity=[1,3]' ...", ctx)
    assert cmd == "python tools/eval.py agent=orb dataset=synthetic dataset.root=/panos 'corruption.severity=[1,3]'"
    assert ctx.needs == {"sun360"}
    assert "$FINDVIEW_SUN360_MINI" not in check_docs.substitute("x --root $FINDVIEW_SUN360_MINI", ctx)
    assert check_docs.substitute("torchrun --nproc_per_node=K tools/train.py", ctx).endswith("=2 tools/train.py")
    ran = check_docs.prepare("python tools/eval.py split=test")
    assert str(REPO / "tools" / "eval.py") in ran and ran.index("split=test") < ran.index("max_episodes=2")
    # the checker's own command only lists (running it would run every doc again, recursively)
    assert check_docs.prepare("python tools/check_docs.py README.md").endswith("check_docs.py README.md --list")
    # an error example gets no overrides (they could hide the error)
    assert check_docs.prepare("python tools/train.py trainer.num_envs=abc", overrides=False).endswith("num_envs=abc")


def test_pip_install_is_checked_not_run():
    assert check_docs.check_pip("pip install -e '.[dev]'") is None
    assert check_docs.check_pip("pip install 'findview[gym]'") is None
    assert "no extra" in check_docs.check_pip("pip install 'findview[nosuchextra]'")


def test_a_block_after_a_command_skipped_for_missing_data_is_skipped(tmp_path, monkeypatch):
    """Without the sun360_mini panoramas the first command of a block is skipped, and so is the next one, which
    reads what the first would have written (it would fail); a block of its own still runs."""
    monkeypatch.delenv(check_docs.SUN360_ENV, raising=False)
    markdown = "\n".join([
        "```",
        "python tools/train_stop_offsets.py --splits s/splits.json --root <sun360_mini> --out made.pth",
        "python tools/average_checkpoints.py made.pth made.pth --out avg.pth",
        "```",
        "",
        "```",
        "python tools/average_checkpoints.py missing.pth --out avg.pth",
        "```",
    ])
    commands = check_docs.extract(markdown, "x.md")
    assert [c.block for c in commands] == [2, 2, 7]  # the first line inside each fence
    results = check_docs.run_all(commands, tmp_path, ci=False, timeout=120)
    assert [r.status for r in results] == ["skip", "skip", "FAIL"]
    assert "earlier command of its block" in results[1].note


def test_every_documented_command_runs(tmp_path):
    """Every command of README.md, docs/*.md and pretrained/README.md, with small overrides (tools/check_docs.py's
    OVERRIDES). benchmarks/RESULTS.md's commands are checked by ``python tools/check_docs.py benchmarks/RESULTS.md``
    (several minutes: many benchmark scripts), not by the suite.

    README.md runs in one checker process and the other docs in a second one at the same time, each in a working
    folder of its own (so no doc relies on what another made), which halves the wall time of the suite's longest
    test on two cores. Each checker forks its ``python <script>`` commands from a server that imported torch and
    findview once (tools/warm_python.py): measured 132 s -> 82 s for this test on a 2-core AMD EPYC."""
    env = dict(os.environ)
    t0 = time.monotonic()
    # the model cards end their "make it" commands by writing the shipped files: the checker must leave them be
    shipped_before = _digests(REPO / "pretrained")
    groups = {"readme": ["README.md"], "others": ["docs/*.md", "pretrained/README.md"]}
    procs = {}
    for name, docs in groups.items():
        workdir = tmp_path / name
        workdir.mkdir()
        procs[name] = subprocess.Popen(
            [sys.executable, str(REPO / "tools" / "check_docs.py"), "--workdir", str(workdir), *docs],
            cwd=REPO, env=env, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    failures = []
    for name, proc in procs.items():
        try:
            out, err = proc.communicate(timeout=900)
        except subprocess.TimeoutExpired:
            for other in procs.values():
                other.kill()
            raise
        print(out[-6000:], err[-2000:])
        if proc.returncode != 0:
            failures.append(f"{groups[name]}: exit {proc.returncode}\n{out[-6000:]}{err[-2000:]}")
    assert not failures, "\n".join(failures)
    assert _digests(REPO / "pretrained") == shipped_before, "running the documented commands changed pretrained/"
    print(f"check_docs took {time.monotonic() - t0:.0f} s")


def _digests(folder: Path) -> dict[str, str]:
    """SHA-256 of every file in ``folder``, by name."""
    return {p.name: hashlib.sha256(p.read_bytes()).hexdigest() for p in sorted(folder.iterdir()) if p.is_file()}


def test_a_command_the_fork_cannot_parse_runs_under_bash(tmp_path):
    """Unbalanced quotes: the checker does not crash while deciding whether to fork; bash reports the command."""
    if not hasattr(os, "fork"):
        pytest.skip("needs fork (POSIX)")
    command = check_docs.extract("```\npython tools/eval.py agent='sift\n```\n", "x.md")[0]
    with check_docs.WarmPython(preload=("json",)) as warm:
        result = check_docs.run_one(command, tmp_path, False, 60, warm)
    assert result.status == "FAIL" and "bash" in result.note
