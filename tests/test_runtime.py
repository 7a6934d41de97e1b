"""The CPU thread policy (findview.runtime): OMP_WAIT_POLICY=PASSIVE reaches torch when findview is
imported first, a user's value wins, and configure_threads sets the documented default."""

from __future__ import annotations

import json
import os
import subprocess
import sys

import pytest

PROBE = """
import json, logging, os, sys
logging.basicConfig(level=logging.WARNING, stream=sys.stderr)
order = sys.argv[1]
if order == "torch_first":
    import torch
import findview
from findview.runtime import configure_threads, wait_policy_effective
import torch
default = configure_threads()  # the documented default
print("-- default done", file=sys.stderr, flush=True)
n = configure_threads(2)
print(json.dumps({"policy": os.environ.get("OMP_WAIT_POLICY"), "effective": wait_policy_effective(),
                  "default": default, "threads": torch.get_num_threads(), "returned": n}))
"""


def probe(*args: str, env_extra: dict | None = None) -> tuple[dict, str]:
    env = {k: v for k, v in os.environ.items() if k not in ("OMP_WAIT_POLICY", "OMP_NUM_THREADS")}
    env.update(env_extra or {})
    proc = subprocess.run([sys.executable, "-c", PROBE, *args], capture_output=True, text=True, env=env, timeout=120)
    assert proc.returncode == 0, proc.stderr
    return json.loads(proc.stdout.strip().splitlines()[-1]), proc.stderr


def test_findview_first_sets_passive_wait_policy():
    """Default 1 torch thread; 2 threads on request, without a warning (the policy is in effect)."""
    out, err = probe("findview_first")
    assert out == {"policy": "PASSIVE", "effective": True, "default": 1, "threads": 2, "returned": 2}
    assert "spin-wait" not in err


def test_torch_first_is_not_effective_and_warns_for_several_threads():
    out, err = probe("torch_first")
    assert out["effective"] is False and out["default"] == 1 and out["threads"] == 2
    before, after = err.split("-- default done")
    assert "spin-wait" not in before  # one thread: nothing to warn about
    assert "OMP_WAIT_POLICY" in after and "spin-wait" in after


def test_user_value_wins():
    out, _ = probe("findview_first", env_extra={"OMP_WAIT_POLICY": "ACTIVE"})
    assert out["policy"] == "ACTIVE" and out["effective"] is False


def test_bad_thread_count():
    from findview.runtime import configure_threads

    with pytest.raises(ValueError, match="torch_threads"):
        configure_threads(-1)
