"""Averaging the weights of checkpoints of one network (``average_checkpoints``, ``tools/average_checkpoints.py``)."""

from __future__ import annotations

import subprocess
import sys
from pathlib import Path

import pytest
import torch

from findview_baselines.rl.checkpoint import (
    CheckpointError,
    average_checkpoints,
    checkpoint_payload,
    load_policy,
    save_checkpoint,
)
from findview_baselines.rl.policy import Policy

TOOL = Path(__file__).resolve().parents[1] / "tools" / "average_checkpoints.py"


def small_policy(seed: int, hidden_size: int = 16) -> Policy:
    torch.manual_seed(seed)
    return Policy(64, 64, variant="phase", hidden_size=hidden_size, fine_shifts=1, fine_scales=2)


def write(tmp_path: Path, name: str, policy: Policy, update: int = 7) -> Path:
    return save_checkpoint(tmp_path / name, checkpoint_payload(policy, update, 100, {"seed": update}, {"all": {"eps": 1.0}},
                                                               1.0, {"optimizer": {}}))


def test_the_average_is_the_mean_of_the_weights_and_loads_into_the_network(tmp_path: Path) -> None:
    a, b, c = small_policy(0), small_policy(1), small_policy(2)
    paths = [write(tmp_path, f"{n}.pth", p, update=u) for n, p, u in (("a", a, 500), ("b", b, 400), ("c", c, 300))]
    state = average_checkpoints(paths)
    fresh = small_policy(3)
    soup = save_checkpoint(tmp_path / "soup.pth", state)
    loaded = load_policy(soup, fresh)
    sa, sb, sc, sf = a.state_dict(), b.state_dict(), c.state_dict(), fresh.state_dict()
    for key, value in sf.items():
        if value.is_floating_point():
            expected = (sa[key].double() + sb[key].double() + sc[key].double()) / 3
            torch.testing.assert_close(value.double(), expected, rtol=0, atol=1e-6)
        else:
            assert torch.equal(value, sa[key])
    # a weight that differs between the inputs is neither input's
    key = next(k for k, v in sa.items() if v.is_floating_point() and not torch.equal(v, sb[k]))
    assert not torch.equal(sf[key], sa[key]) and not torch.equal(sf[key], sb[key])
    # the rest is the first input's, without what no validation measured
    assert loaded["signature"] == a.model_signature() and loaded["config"] == {"seed": 500} and loaded["update"] == 500
    assert loaded["val"] is None and loaded["best_val_eps"] is None and loaded["trainer"] is None
    assert loaded["averaged_from"] == [{"path": str(p), "update": u} for p, u in zip(paths, (500, 400, 300))]
    # a file of exactly representable weights: 1 and 3 average to 2
    with torch.no_grad():
        for p in a.parameters():
            p.fill_(1.0)
        for p in b.parameters():
            p.fill_(3.0)
    state = average_checkpoints([write(tmp_path, "ones.pth", a), write(tmp_path, "threes.pth", b)])
    assert all(bool((v == 2.0).all()) for k, v in state["policy"].items() if k in dict(a.named_parameters()))


def test_other_networks_are_refused_by_name(tmp_path: Path) -> None:
    a = write(tmp_path, "a.pth", small_policy(0))
    wide = write(tmp_path, "wide.pth", small_policy(1, hidden_size=32))
    with pytest.raises(CheckpointError, match=r"wide.pth against .*a.pth: other model signatures \(differ in hidden_size\)"):
        average_checkpoints([a, wide])
    with pytest.raises(ValueError, match="at least one checkpoint, got none"):
        average_checkpoints([])
    text = tmp_path / "notes.pth"
    text.write_text("not weights")
    with pytest.raises(CheckpointError, match="notes.pth: not a findview checkpoint"):
        average_checkpoints([a, text])


def test_the_tool_writes_once_and_refuses_bad_input(tmp_path: Path) -> None:
    a, b = write(tmp_path, "a.pth", small_policy(0)), write(tmp_path, "b.pth", small_policy(1))
    out = tmp_path / "soup" / "avg.pth"

    def run(*args: str) -> subprocess.CompletedProcess:
        return subprocess.run([sys.executable, str(TOOL), *args], capture_output=True, text=True, timeout=120)

    done = run(str(a), str(b), "--out", str(out))
    assert done.returncode == 0, done.stderr
    state = torch.load(out, weights_only=True)
    assert torch.equal(state["policy"]["actor.weight"], average_checkpoints([a, b])["policy"]["actor.weight"])
    again = run(str(a), str(b), "--out", str(out))
    assert again.returncode == 2 and f"{out} exists; pass --overwrite" in again.stderr
    assert run(str(a), str(b), "--out", str(out), "--overwrite").returncode == 0
    assert [p.name for p in out.parent.iterdir()] == ["avg.pth"]  # nothing half-written left beside it
    same = run(str(a), str(b), "--out", str(a))
    assert same.returncode == 2 and "is one of the inputs" in same.stderr
    wide = write(tmp_path, "wide.pth", small_policy(2, hidden_size=32))
    refused = run(str(a), str(wide), "--out", str(tmp_path / "x.pth"))
    assert refused.returncode == 2 and "other model signatures" in refused.stderr
    assert not (tmp_path / "x.pth").exists()
    # one input: its weights bit for bit, its signature and config, no resume state (a file to ship)
    alone = run(str(a), "--out", str(tmp_path / "z.pth"))
    assert alone.returncode == 0 and "copied the weights" in alone.stdout, alone.stderr
    copy, original = torch.load(tmp_path / "z.pth", weights_only=True), torch.load(a, weights_only=True)
    assert copy["policy"].keys() == original["policy"].keys()
    assert all(torch.equal(copy["policy"][k], v) for k, v in original["policy"].items())
    assert copy["signature"] == original["signature"] and copy["trainer"] is None
    missing = run(str(a), str(tmp_path / "nope.pth"), "--out", str(tmp_path / "y.pth"))
    assert missing.returncode == 2 and "checkpoint not found" in missing.stderr
