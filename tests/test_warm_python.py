"""tools/warm_python.py: commands forked from a warm server behave as if each were its own ``python <script>``."""

from __future__ import annotations

import importlib.util
import os
import sys
import time
from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parents[1]
pytestmark = pytest.mark.skipif(not hasattr(os, "fork"), reason="needs fork (POSIX)")


def _warm_python():
    spec = importlib.util.spec_from_file_location("warm_python", REPO / "tools" / "warm_python.py")
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


warm_python = _warm_python()


@pytest.fixture(scope="module")
def runner():
    with warm_python.WarmPython(preload=("json",)) as r:  # a light server: these tests are about the forking
        yield r


def _script(folder: Path, name: str, body: str) -> str:
    path = folder / name
    path.write_text(body)
    return str(path)


def test_a_command_gets_its_arguments_folder_environment_status_and_output(runner, tmp_path):
    work = tmp_path / "work"
    work.mkdir()
    script = _script(tmp_path, "show.py", (
        "import os, sys\n"
        "print('argv', sys.argv[1:])\n"
        "print('cwd', os.getcwd())\n"
        "print('env', os.environ.get('WARM_TEST_VALUE'), 'HOME' in os.environ)\n"
        "print('main', sys.modules['__main__'].__file__)\n"
        "print('to stderr', file=sys.stderr)\n"
        "sys.exit(3)\n"))
    code, out = runner.run([script, "a=1", "--b"], cwd=work, env={"WARM_TEST_VALUE": "x y"}, timeout=60)
    assert code == 3
    lines = out.splitlines()
    assert "argv ['a=1', '--b']" in lines
    assert f"cwd {work}" in lines
    assert "env x y False" in lines  # exactly the environment given, nothing of the server's
    assert f"main {script}" in lines  # multiprocessing's spawn re-imports __main__ by this name
    assert "to stderr" in lines


def test_exit_statuses_are_those_of_python(runner, tmp_path):
    cases = {
        "pass\n": 0,
        "import sys\nsys.exit()\n": 0,
        "import sys\nsys.exit(2)\n": 2,
        "import sys\nsys.exit('bad input: x')\n": 1,
        "raise ValueError('boom')\n": 1,
    }
    for i, (body, want) in enumerate(cases.items()):
        code, out = runner.run([_script(tmp_path, f"s{i}.py", body)], cwd=tmp_path, env={}, timeout=60)
        assert code == want, (body, out)
    assert "ValueError: boom" in out  # the traceback, as Python prints it
    code, out = runner.run([_script(tmp_path, "msg.py", "import sys\nsys.exit('bad input: x')\n")],
                           cwd=tmp_path, env={}, timeout=60)
    assert out.strip() == "bad input: x"


def test_a_command_ends_as_python_ends(runner, tmp_path):
    """Threads joined and ``atexit`` handlers run (multiprocessing and joblib clean up in them)."""
    script = _script(tmp_path, "ending.py", (
        "import atexit, threading, time\n"
        "atexit.register(print, 'atexit ran')\n"
        "threading.Thread(target=lambda: (time.sleep(0.5), print('thread done'))).start()\n"
        "print('main done')\n"))
    assert runner.run([script], cwd=tmp_path, env={}, timeout=60) == (0, "main done\nthread done\natexit ran\n")


def test_nothing_one_command_does_reaches_the_next(runner, tmp_path):
    set_it = _script(tmp_path, "set.py", "import json, os\njson.MARK = 1\nos.environ['LEFT'] = '1'\nprint('set')\n")
    read_it = _script(tmp_path, "read.py", "import json, os\nprint(hasattr(json, 'MARK'), 'LEFT' in os.environ)\n")
    assert runner.run([set_it], cwd=tmp_path, env={}, timeout=60) == (0, "set\n")
    assert runner.run([read_it], cwd=tmp_path, env={}, timeout=60) == (0, "False False\n")


def test_a_command_past_its_timeout_is_killed_with_what_it_started(runner, tmp_path):
    marker = tmp_path / "child_alive"
    late = _script(tmp_path, "late.py", f"import time\ntime.sleep(3)\nopen({str(marker)!r}, 'w').close()\n")
    script = _script(tmp_path, "hang.py", (
        "import subprocess, sys, time\n"
        f"subprocess.Popen([sys.executable, {late!r}])\n"
        "print('started', flush=True)\n"
        "time.sleep(60)\n"))
    t0 = time.monotonic()
    code, out = runner.run([script], cwd=tmp_path, env={}, timeout=1.0)
    assert code is None and "started" in out
    assert time.monotonic() - t0 < 20
    time.sleep(4)
    assert not marker.exists(), "the command's own child outlived the timeout"
    assert runner.run([_script(tmp_path, "after.py", "print('ok')\n")], cwd=tmp_path, env={}, timeout=60) == (0, "ok\n")


@pytest.mark.parametrize("command, want", [
    ("python tools/eval.py agent=sift", True),
    ("FINDVIEW_X=1 python benchmarks/robustness.py --agents sift", True),
    ("OMP_NUM_THREADS=1 python tools/train.py", False),  # read when the OpenMP library loads: a new Python
    ("PYTHONHASHSEED=0 python tools/train.py", False),
    ("torchrun --nproc_per_node=2 tools/train.py", False),
    ("python -m pytest tests", False),
    ("pip install -e .", False),
])
def test_forkable(command, want):
    assert warm_python.forkable(command.split()) is want


def test_the_server_refuses_to_start_without_its_imports():
    with pytest.raises(RuntimeError, match="server"):
        warm_python.WarmPython(preload=("no_such_module_for_warm_python",))
