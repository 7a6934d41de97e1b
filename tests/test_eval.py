"""tools/eval.py, tools/collect_results.py and the evaluation harness, end to end on a tiny folder
data set (3 real panoramas, test split only, 1 episode per image per difficulty) with 64x64 views."""

from __future__ import annotations

import json
import math
import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import cv2
import pytest
import torch

REPO = Path(__file__).resolve().parents[1]
PY = sys.executable
SMALL = ["sim.height=64", "sim.width=64", "progress=false"]
METRICS = {"eps", "omega_stop", "omega_perf", "spl", "episodes"}
EPISODE_KEYS = {
    "episode_id", "image", "difficulty", "init_pitch", "init_yaw", "target_pitch", "target_yaw",
    "final_pitch", "final_yaw", "steps", "called_stop", "eps",
}


def run_tool(tool: str, *args: str, cwd: Path | None = None, timeout: float = 120) -> subprocess.CompletedProcess:
    env = {**os.environ, "HYDRA_FULL_ERROR": "0", "OMP_NUM_THREADS": "1"}
    return subprocess.run(
        [PY, str(REPO / "tools" / tool), *args], capture_output=True, text=True, cwd=cwd or REPO, timeout=timeout, env=env
    )


def check(proc: subprocess.CompletedProcess) -> subprocess.CompletedProcess:
    assert proc.returncode == 0, f"exit {proc.returncode}\nstdout:\n{proc.stdout[-3000:]}\nstderr:\n{proc.stderr[-3000:]}"
    return proc


@pytest.fixture(scope="module", autouse=True)
def one_torch_thread():
    """Small tensors: one intra-op thread is faster (and much faster on a busy machine)."""
    before = torch.get_num_threads()
    torch.set_num_threads(1)
    yield
    torch.set_num_threads(before)


@pytest.fixture(scope="module")
def folder_ds(tmp_path_factory, sun360_mini_files) -> dict[str, Path]:
    """3 panoramas (512x256) in <root>/<label>/, split [0, 0, 1], 1 episode per image per difficulty."""
    base = tmp_path_factory.mktemp("folder_ds")
    root, out = base / "images", base / "data"
    picks = [f for f in sun360_mini_files if "/indoor/" in f.as_posix()][:2] + [
        f for f in sun360_mini_files if "/outdoor/" in f.as_posix()
    ][:1]
    for k, f in enumerate(picks):
        img = cv2.imread(str(f), cv2.IMREAD_COLOR)
        dst = root / f.parent.name / f"pano_{k}.jpg"
        dst.parent.mkdir(parents=True, exist_ok=True)
        cv2.imwrite(str(dst), cv2.resize(img, (512, 256), interpolation=cv2.INTER_AREA))
    check(
        run_tool(
            "make_dataset.py", "dataset=folder", f"dataset.root={root}", f"dataset.out_dir={out}",
            "dataset.split=[0,0,1]", "dataset.episodes_per_image=1", "dataset.episode_fovs=[90]",
            "dataset.splits_to_make=[test]", "progress=false",
        )
    )
    assert (out / "episodes" / "test_fov90.json").is_file()
    return {"root": root, "out": out, "base": base}


def ds_args(ds: dict[str, Path]) -> list[str]:
    # the settings the folder was made with: tools refuse data made for other settings (test_integrity.py)
    return ["dataset=folder", f"dataset.root={ds['root']}", f"dataset.out_dir={ds['out']}", "dataset.split=[0,0,1]",
            "split=test"]


def read_summary(run_dir: Path) -> dict:
    return json.loads((run_dir / "summary.json").read_text())


def check_schema(summary: dict, difficulties: set[str]) -> None:
    assert set(summary) == difficulties | {"runtime"}
    for d in difficulties:
        m = summary[d]
        assert set(m) == METRICS
        assert isinstance(m["episodes"], int) and m["episodes"] > 0
        for k in ("eps", "omega_stop", "omega_perf", "spl"):
            assert isinstance(m[k], float)
        for k in ("omega_stop", "omega_perf", "spl"):
            assert 0.0 <= m[k] <= 1.0
    rt = summary["runtime"]
    assert set(rt) == {"agent_fps", "env_fps"}
    assert all(isinstance(v, float) and v > 0 for v in rt.values())


def without_runtime(summary: dict) -> dict:
    return {k: v for k, v in summary.items() if k != "runtime"}


# ------------------------------------------------------------------------------------------------
# tools/eval.py
# ------------------------------------------------------------------------------------------------
def test_oracle_end_to_end(folder_ds, tmp_path):
    out = tmp_path / "oracle"
    check(run_tool("eval.py", "agent=oracle", *ds_args(folder_ds), *SMALL, f"hydra.run.dir={out}"))
    summary = read_summary(out)
    check_schema(summary, {"easy", "medium", "hard"})
    for d in ("easy", "medium", "hard"):
        assert summary[d] == {"eps": 0.0, "omega_stop": 1.0, "omega_perf": 1.0, "spl": 1.0, "episodes": 3}
    lines = (out / "episodes.jsonl").read_text().splitlines()
    assert len(lines) == 9
    recs = [json.loads(x) for x in lines]
    for r in recs:
        assert EPISODE_KEYS <= set(r)
        assert (r["final_pitch"], r["final_yaw"]) == (r["target_pitch"], r["target_yaw"])
        assert r["called_stop"] is True and r["eps"] == 0 and r["steps"] == r["shortest_path"]
    # records in the episode file's order
    doc = json.loads((folder_ds["out"] / "episodes" / "test_fov90.json").read_text())
    assert [r["episode_id"] for r in recs] == [e["episode_id"] for e in doc["episodes"]]
    md = (out / "summary.md").read_text()
    assert "easy eps" in md and "hard SPL" in md and "agent FPS" in md and "| oracle |" in md
    assert (out / ".hydra" / "config.yaml").is_file() and (out / "config_resolved.yaml").is_file()
    assert json.loads((out / "run.json").read_text())["runtime"]["agent_decisions"] == sum(r["steps"] for r in recs)
    assert not list(out.glob(".*.tmp"))


def test_random_deterministic(folder_ds, tmp_path):
    args = ["agent=random", *ds_args(folder_ds), *SMALL, "task.max_steps=100", "num_envs=4", "seed=3"]
    a, b = tmp_path / "a", tmp_path / "b"
    check(run_tool("eval.py", *args, f"hydra.run.dir={a}"))
    check(run_tool("eval.py", *args, f"hydra.run.dir={b}"))
    sa, sb = read_summary(a), read_summary(b)
    check_schema(sa, {"easy", "medium", "hard"})
    assert without_runtime(sa) == without_runtime(sb)
    assert (a / "episodes.jsonl").read_text() == (b / "episodes.jsonl").read_text()
    recs = [json.loads(x) for x in (a / "episodes.jsonl").read_text().splitlines()]
    assert all(r["steps"] <= 100 for r in recs)
    assert all(r["called_stop"] or r["steps"] == 100 for r in recs)


def test_easy_only_with_video(folder_ds, tmp_path):
    out = tmp_path / "easy"
    check(run_tool("eval.py", "agent=oracle", *ds_args(folder_ds), *SMALL, "difficulty=easy", "video=1", f"hydra.run.dir={out}"))
    summary = read_summary(out)
    check_schema(summary, {"easy"})
    assert summary["easy"]["episodes"] == 3
    recs = [json.loads(x) for x in (out / "episodes.jsonl").read_text().splitlines()]
    assert {r["difficulty"] for r in recs} == {"easy"}
    videos = sorted((out / "videos").glob("*.mp4"))
    assert [v.stem for v in videos] == [recs[0]["episode_id"]]
    cap = cv2.VideoCapture(str(videos[0]))
    assert cap.isOpened()
    frames = 0
    while True:
        ok, frame = cap.read()
        if not ok:
            break
        frames += 1
        assert frame.shape == (256, 2 * 256 + 2 * 256, 3)  # view | target (64 x 64 shown 4x) | panorama (256 x 512)
    assert frames == recs[0]["steps"] + 1


def test_missing_episode_file_says_how_to_make_it(folder_ds, tmp_path):
    empty = tmp_path / "nothing_here"
    proc = run_tool(
        "eval.py", "agent=oracle", "dataset=folder", f"dataset.root={folder_ds['root']}", f"dataset.out_dir={empty}",
        "split=val", *SMALL, f"hydra.run.dir={tmp_path / 'run'}",
    )
    assert proc.returncode == 2
    assert "python tools/make_dataset.py dataset=folder" in proc.stderr
    assert f"dataset.out_dir={empty}" in proc.stderr and f"dataset.root={folder_ds['root']}" in proc.stderr
    assert "val_fov90.json" in proc.stderr
    assert "Traceback" not in proc.stderr
    assert not (tmp_path / "run" / "summary.json").exists()


def test_unknown_agent_lists_valid_names(tmp_path):
    proc = run_tool("eval.py", "agent=no_such_agent", f"hydra.run.dir={tmp_path}")
    assert proc.returncode != 0
    err = proc.stderr + proc.stdout
    for name in ("oracle", "random", "orb", "sift"):
        assert name in err


def _eval_cfg(*overrides: str):
    """The validated eval config of ``overrides`` (like the tool composes it)."""
    from findview_baselines.cli import compose_config, validate_config

    return validate_config(compose_config("eval", list(overrides)))


def test_stop_by_beyond_the_step_limit_is_clamped_with_a_warning(caplog):
    """agent.stop_by is T, the step the learned agent stops by: evaluated with a smaller task.max_steps the agent
    stops by that step instead, and the log says so (a value up to T is kept)."""
    from findview_baselines.evaluation.evaluate import apply_checkpoint_config, build_agent

    ck = str(REPO / "pretrained" / "findview_sun360mini_indoor_robust.pth")
    for stop_by, expected in ((5000, 30), (20, 20)):
        overrides = [f"checkpoint={ck}", "agent=ppo", "task.max_steps=30", f"agent.stop_by={stop_by}"]
        cfg = apply_checkpoint_config(_eval_cfg(*overrides), overrides)
        with caplog.at_level("WARNING", logger="findview.eval"):
            agent, _ = build_agent(cfg, 1, "cpu")
        assert agent.give_up is not None and agent.give_up.stop_by == expected
    assert "agent.stop_by=5000 is beyond task.max_steps=30" in caplog.text
    assert "agent.stop_by=20" not in caplog.text


def test_difficulty_filter():
    from findview.episode import Episode
    from findview_baselines.evaluation.evaluate import EvalError, filter_episodes

    eps = [Episode(f"e{i}", "x.jpg", 0, 0, 0, 20, difficulty=d) for i, d in enumerate(["easy", "hard", "easy", "medium"])]
    assert [e.episode_id for e in filter_episodes(eps, "easy")] == ["e0", "e2"]
    assert [e.episode_id for e in filter_episodes(eps, None, 3)] == ["e0", "e1", "e2"]
    assert [e.episode_id for e in filter_episodes(eps, ["hard", "medium"])] == ["e1", "e3"]
    with pytest.raises(EvalError, match="valid: easy, medium, hard"):
        filter_episodes(eps, "extreme")


def test_unknown_agent_name_in_config_lists_registered_agents(folder_ds, tmp_path):
    from dataclasses import replace

    from findview_baselines.config import RandomAgentConfig
    from findview_baselines.evaluation.evaluate import EvalError, build_agent

    cfg = replace(_eval_cfg(), agent=RandomAgentConfig(name="no_such_agent"))
    with pytest.raises(EvalError, match=r"valid agents: .*oracle.*random"):
        build_agent(cfg, 2, torch.device("cpu"))
    with pytest.raises(EvalError, match="checkpoint="):
        build_agent(_eval_cfg("agent=ppo"), 2, torch.device("cpu"))


def test_ctrl_c_writes_nothing(folder_ds, tmp_path):
    from findview.dataset import episode_file, read_episode_file

    # a long episode file (the test episodes repeated), so the run is still going when SIGINT arrives
    doc = read_episode_file(episode_file(folder_ds["out"], "test", 90))
    many = [dict(e, episode_id=f"{e['episode_id']}-{k}") for k in range(2000) for e in doc["episodes"]]
    big = tmp_path / "many_episodes.json"
    big.write_text(json.dumps(dict(doc, episodes=many)))
    out = tmp_path / "interrupted"
    cmd = [PY, str(REPO / "tools" / "eval.py"), "agent=random", *ds_args(folder_ds), *SMALL, "num_envs=2",
           f"episodes={big}", f"hydra.run.dir={out}"]
    # a Ctrl-C reaches the tool as SIGINT with its default action, also when this test runs in a background job
    # (a non-interactive shell starts those with SIGINT ignored, and Python then keeps ignoring it)
    restore_sigint = lambda: signal.signal(signal.SIGINT, signal.SIG_DFL)  # noqa: E731
    proc = subprocess.Popen(cmd, cwd=REPO, stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True,
                            preexec_fn=restore_sigint)
    try:
        deadline = time.time() + 60
        for line in proc.stdout:  # wait until the episodes run
            if "evaluating" in line or time.time() > deadline:
                break
        time.sleep(0.5)
        proc.send_signal(signal.SIGINT)
        rest, _ = proc.communicate(timeout=120)  # seconds on a loaded 2-core machine; 1-2 s when it is quiet
    finally:
        if proc.poll() is None:
            proc.kill()
    assert proc.returncode == 130, rest
    assert "interrupted" in rest
    for name in ("summary.json", "summary.md", "episodes.jsonl"):
        assert not (out / name).exists()


# ------------------------------------------------------------------------------------------------
# threshold search: hydra multirun + tools/collect_results.py
# ------------------------------------------------------------------------------------------------
def test_multirun_and_collect_results(folder_ds, tmp_path):
    sweep = tmp_path / "sweep"
    check(
        run_tool(
            "eval.py", "-m", "agent=orb", "agent.d_thresh=20,inf", *ds_args(folder_ds), *SMALL, "difficulty=easy",
            "task.max_steps=60", "max_episodes=2", "agent.threads=1", f"hydra.sweep.dir={sweep}",
        )
    )
    runs = sorted(p.parent.parent for p in sweep.rglob(".hydra/config.yaml"))
    assert len(runs) == 2 and all((r / "summary.json").is_file() for r in runs)
    # d_thresh=inf reaches the agent as the float inf
    from omegaconf import OmegaConf

    values = sorted(float(OmegaConf.load(r / ".hydra" / "config.yaml").agent.d_thresh) for r in runs)
    assert values[0] == 20.0 and math.isinf(values[1])

    # orb at 64 x 64 never stops within T = 60: the runs are marked, no d_thresh is picked from them
    tuned, table = tmp_path / "orb_tuned_folder.yaml", tmp_path / "table.md"
    proc = check(run_tool("collect_results.py", str(sweep), f"out={tuned}", f"table={table}", "allow_test_tuning=true"))
    text = table.read_text()
    assert "| difficulty | agent | 20 | inf |" in text and "T = 60" in text
    stops = {float(OmegaConf.load(r / ".hydra" / "config.yaml").agent.d_thresh): read_summary(r)["easy"]["omega_stop"] for r in runs}
    assert all(v == 0 for v in stops.values()), stops  # the premise of this check
    assert "| easy | orb |" in text and "(no stop)" in text and "**" not in text
    assert not tuned.exists() and "no run stopped" in proc.stderr and "no tuned config written" in proc.stdout

    # a tuned config composes as an agent config (inherits orb.yaml, overrides d_thresh.easy)
    from findview_baselines.cli import compose_config, validate_config
    from findview_baselines.evaluation.results import tuned_config_text

    extra = tmp_path / "extra_configs" / "agent"
    extra.mkdir(parents=True)
    (extra / "orb_tuned_folder.yaml").write_text(tuned_config_text("orb", "folder", {"easy": 20.0}))
    c = compose_config("eval", [f"hydra.searchpath=[file://{extra.parent}]", "agent=orb_tuned_folder"])
    validate_config(c)  # the tuned file is checked against the agent schema like any other
    assert c.agent.name == "orb" and c.agent.n_features == 500
    assert float(c.agent.d_thresh.easy) == 20.0 and math.isinf(float(c.agent.d_thresh.hard))


def test_collect_results_table_layout(tmp_path):
    """Fake multirun: two agents x two thresholds x one difficulty, ties bold."""
    from findview_baselines.evaluation.results import best_thresholds, find_runs, threshold_table

    def fake(i: int, agent: str, thresh, eps: float, spl: float) -> None:
        d = tmp_path / str(i)
        (d / ".hydra").mkdir(parents=True)
        t = ".inf" if thresh == "inf" else thresh
        (d / ".hydra" / "config.yaml").write_text(
            f"agent:\n  name: {agent}\n  d_thresh: {t}\ndataset:\n  name: toy\nsplit: val\ndifficulty: hard\n"
        )
        m = {"eps": eps, "omega_stop": 1.0, "omega_perf": 0.5, "spl": spl, "episodes": 4}
        (d / "summary.json").write_text(json.dumps({"hard": m, "runtime": {"agent_fps": 1.0, "env_fps": 1.0}}))

    fake(0, "sift", 10, 5.0, 0.1)
    fake(1, "sift", "inf", 2.5, 0.3)
    fake(2, "orb", 10, 1.25, 0.2)
    fake(3, "orb", "inf", 1.25, 0.4)
    (tmp_path / "4" / ".hydra").mkdir(parents=True)  # an interrupted run: no summary
    (tmp_path / "4" / ".hydra" / "config.yaml").write_text("agent:\n  name: orb\n  d_thresh: 30\n")
    warnings: list[str] = []
    runs = find_runs(tmp_path, warn=warnings.append)
    assert len(runs) == 4 and len(warnings) == 1
    table = threshold_table(runs)
    assert "| hard | orb | **1.25** | **1.25** |" in table
    assert "| hard | sift | 5.00 | **2.50** |" in table
    best = best_thresholds(runs)
    assert best[("sift", "toy")] == {"hard": math.inf}
    assert best[("orb", "toy")] == {"hard": math.inf}  # tie on eps -> higher SPL


# ------------------------------------------------------------------------------------------------
# harness and PPO agent, in process
# ------------------------------------------------------------------------------------------------
def _episodes(ds):
    from findview.dataset import episode_file, load_episodes

    return load_episodes(episode_file(ds["out"], "test", 90))


_SIM = []


def _env(episodes, num_envs, max_steps=5000):
    """An env over ``episodes`` (findview.build, like the tools); one simulator (and its per-pitch grids)
    is shared by every test env."""
    from findview.build import build_simulator, build_static_env

    from findview.config import SimConfig, TaskConfig

    sim_cfg = SimConfig(fov=90, height=64, width=64, device="cpu", bank_mb=64, prefetch_workers=0)
    if not _SIM:
        _SIM.append(build_simulator(sim_cfg, 60, [e.image for e in episodes], 8))
    return build_static_env(sim_cfg, TaskConfig(max_steps=max_steps), episodes, num_envs, simulator=_SIM[0])


def test_harness_counts_and_batch_invariance(folder_ds):
    from findview_baselines.agents import make_agent
    from findview_baselines.evaluation import run_episodes

    episodes = _episodes(folder_ds)
    out = {}
    for n in (1, 4):
        env = _env(episodes, n)
        records, rt = run_episodes(env, make_agent("oracle", None, n), progress=False)
        out[n] = records
        assert [r["episode_id"] for r in records] == [e.episode_id for e in episodes]
        assert rt.agent_decisions == rt.env_steps == sum(r["steps"] for r in records)
        assert rt.episodes == len(episodes) and rt.agent_fps > 0 and rt.env_fps > 0
    assert out[1] == out[4]
    env = _env(episodes, 4)
    records, rt = run_episodes(env, make_agent("oracle", None, 4), progress=False, max_episodes=5)
    assert [r["episode_id"] for r in records] == [e.episode_id for e in episodes[:5]]


def test_progress_bar_moves_before_the_first_episode_ends(folder_ds):
    """A run whose episodes all go to T shows growing step counts while the episode count is still 0."""
    import io

    from findview_baselines.agents import make_agent
    from findview_baselines.evaluation import run_episodes

    episodes = _episodes(folder_ds)[:2]
    env = _env(episodes, 2, max_steps=400)
    stream = io.StringIO()
    clock = iter(range(0, 10**6, 1))

    class SlowRandom:  # never stops; each decision "takes" 0.3 s of a fake clock
        name = "walker"

        def reset(self, env_ids, eps):
            pass

        def act(self, obs):
            return torch.full((2,), 2, dtype=torch.long)  # LEFT forever: episodes end only at T

    import findview_baselines.evaluation.harness as harness

    real = harness.time.perf_counter
    harness.time.perf_counter = lambda: next(clock) * 0.3  # type: ignore[assignment]
    try:
        records, rt = run_episodes(env, SlowRandom(), progress=True, progress_stream=stream)
    finally:
        harness.time.perf_counter = real  # type: ignore[assignment]
    assert len(records) == 2 and all(not r["called_stop"] and r["steps"] == 400 for r in records)
    lines = [s for s in stream.getvalue().replace("\r", "\n").splitlines() if " 0/2 " in s and "steps=" in s]
    counts = [int(s.split("steps=")[1].split()[0]) for s in lines]
    assert len(counts) >= 3 and counts == sorted(counts) and counts[-1] > counts[0] > 0


def _tiny_checkpoint(path: Path, height: int = 64, width: int = 64) -> Path:
    from findview_baselines.rl.policy import Policy

    torch.manual_seed(0)
    policy = Policy(height, width, "early_fusion", hidden_size=32)
    torch.save({"signature": policy.model_signature(), "policy": policy.state_dict(), "update": 0}, path)
    return path


@pytest.fixture(scope="module")
def tiny_ckpt(tmp_path_factory) -> Path:
    return _tiny_checkpoint(tmp_path_factory.mktemp("ckpt") / "tiny.pth")


def test_ppo_agent_checkpoint(folder_ds, tiny_ckpt):
    from findview_baselines.agents.ppo_agent import PPOAgent
    from findview_baselines.evaluation import run_episodes

    ckpt = tiny_ckpt
    with pytest.raises(ValueError, match=r"64x64.*sim.height=128"):
        PPOAgent.from_checkpoint(ckpt, 2, "cpu", height=128, width=64)
    episodes = _episodes(folder_ds)[:4]
    results = []
    for sample in (False, True):
        for n in (2, 4):
            agent = PPOAgent.from_checkpoint(ckpt, n, "cpu", seed=1, sample=sample, height=64, width=64)
            records, _ = run_episodes(_env(episodes, n, max_steps=40), agent, progress=False)
            assert len(records) == 4 and all(r["steps"] <= 40 for r in records)
            results.append([(r["steps"], r["final_pitch"], r["final_yaw"]) for r in records])
    assert results[0] == results[1]  # greedy: batch composition does not matter
    assert results[2] == results[3]  # sampling: one random stream per episode


def test_eval_tool_with_checkpoint(folder_ds, tiny_ckpt, tmp_path):
    ckpt = tiny_ckpt
    out = tmp_path / "ppo"
    check(
        run_tool("eval.py", "agent=ppo", f"checkpoint={ckpt}", *ds_args(folder_ds), *SMALL, "task.max_steps=30",
                 "max_episodes=4", f"hydra.run.dir={out}")
    )
    summary = read_summary(out)
    assert sum(summary[d]["episodes"] for d in summary if d != "runtime") == 4
    assert json.loads((out / "run.json").read_text())["agent"] == "ppo"

    # a checkpoint trained on another view size (not a multiple of its own): the message says which sizes
    from findview_baselines.evaluation.evaluate import EvalError, build_agent

    cfg = _eval_cfg("agent=ppo", f"checkpoint={ckpt}", "sim.height=100", "sim.width=100")
    with pytest.raises(EvalError, match=r"64x64.*sim.height=100"):
        build_agent(cfg, 2, torch.device("cpu"))
    # a multiple of it is averaged down by the agent
    cfg = _eval_cfg("agent=ppo", f"checkpoint={ckpt}", "sim.height=128", "sim.width=128")
    assert build_agent(cfg, 2, torch.device("cpu"))[0].policy.height == 64


def test_checkpoint_eval_takes_the_revisit_penalty_from_the_run_or_the_command_line(tiny_ckpt, tmp_path):
    from findview_baselines.evaluation.evaluate import apply_checkpoint_config, build_agent

    state = torch.load(tiny_ckpt, weights_only=True)
    state["config"] = {"agent": {"revisit_penalty": 1.5, "revisit_row_stride": 30}, "sim": {"fov": 90.0}}
    ckpt = tmp_path / "with_run_config.pth"
    torch.save(state, ckpt)

    def agent_for(path: Path, overrides: list[str], penalty: float | None):
        given = [] if penalty is None else [f"agent.revisit_penalty={penalty}"]
        cfg = _eval_cfg("agent=ppo", f"checkpoint={path}", *given)
        cfg = apply_checkpoint_config(cfg, overrides)
        return build_agent(cfg, 2, torch.device("cpu"))[0]

    assert agent_for(ckpt, [], None).revisits.penalty == 1.5  # the training run's setting
    assert agent_for(ckpt, [], None).revisits.rows.stride == 30
    cfg = _eval_cfg("agent=ppo", f"checkpoint={ckpt}", "agent.revisit_row_stride=45")
    cfg = apply_checkpoint_config(cfg, ["agent.revisit_row_stride=45"])
    assert build_agent(cfg, 2, torch.device("cpu"))[0].revisits.rows.stride == 45  # the command line wins
    assert agent_for(ckpt, [], None).revisits.near_rows == 0  # a run without the key: no near visits
    near = ["agent.revisit_near_rows=16", "agent.revisit_near_penalty=2.5", "agent.revisit_near_age=7",
            "agent.revisit_near_since=50"]
    revisits = build_agent(apply_checkpoint_config(_eval_cfg("agent=ppo", f"checkpoint={ckpt}", *near), near), 2,
                           torch.device("cpu"))[0].revisits
    assert (revisits.near.rows, revisits.near.penalty, revisits.near.age, revisits.near.since) == (16, 2.5, 7, 50)
    rows = ["agent.revisit_row_after=1000", "agent.revisit_row_budget=720"]  # with the run's stride 30
    revisits = build_agent(apply_checkpoint_config(_eval_cfg("agent=ppo", f"checkpoint={ckpt}", *rows), rows), 2,
                           torch.device("cpu"))[0].revisits
    assert (revisits.rows.stride, revisits.rows.after, revisits.rows.budget) == (30, 1000, 720)
    mirror = ["agent.mirror_steps=5000"]  # the mirror play reaches the agent; off unless given
    played = build_agent(apply_checkpoint_config(_eval_cfg("agent=ppo", f"checkpoint={ckpt}", *mirror), mirror), 2,
                         torch.device("cpu"))[0]
    assert played.mirror_steps == 5000 and played.hidden_mirror.shape == played.hidden.shape
    assert agent_for(ckpt, [], None).hidden_mirror is None
    assert agent_for(ckpt, ["agent.revisit_penalty=4"], 4.0).revisits.penalty == 4.0  # the command line wins
    assert agent_for(ckpt, ["agent.revisit_penalty=0"], 0.0).revisits is None  # 0 switches it off
    assert agent_for(tiny_ckpt, [], None).revisits is None  # a run without the key: the plain policy


def test_checkpoint_eval_agent_fov_follows_the_runs_fov(tiny_ckpt, tmp_path):
    """agent.fov (the stop refinement's and the search memory's degrees) is the FoV the views get: the checkpoint's
    run's, else the command line's sim.fov, unless agent.fov itself is given."""
    from findview_baselines.evaluation.evaluate import apply_checkpoint_config

    state = torch.load(tiny_ckpt, weights_only=True)
    state["config"] = {"sim": {"fov": 60.0}}
    ckpt = tmp_path / "fov60.pth"
    torch.save(state, ckpt)
    for given, sim_fov, agent_fov in (([], 60.0, 60.0), (["sim.fov=90"], 90.0, 90.0), (["agent.fov=75"], 60.0, 75.0)):
        cfg = apply_checkpoint_config(_eval_cfg("agent=ppo", f"checkpoint={ckpt}", *given), given)
        assert (cfg.sim.fov, cfg.agent.fov) == (sim_fov, agent_fov), given


def test_checkpoint_eval_renders_at_the_size_its_run_rendered(tiny_ckpt, tmp_path):
    """A run with agent.downsample=k rendered k times its network's size: evaluation renders that size too
    unless the command line gives one; a checkpoint without a run config renders its network's size."""
    from findview_baselines.evaluation.evaluate import apply_checkpoint_config

    state = torch.load(tiny_ckpt, weights_only=True)
    h, w = int(state["signature"]["height"]), int(state["signature"]["width"])
    state["config"] = {"sim": {"fov": 90.0, "height": 4 * h, "width": 4 * w}}
    ckpt = tmp_path / "downsampled_run.pth"
    torch.save(state, ckpt)
    cfg = apply_checkpoint_config(_eval_cfg("agent=ppo", f"checkpoint={ckpt}"), [])
    assert (cfg.sim.height, cfg.sim.width) == (4 * h, 4 * w)
    given = ["sim.height=" + str(2 * h), "sim.width=" + str(2 * w)]
    cfg = apply_checkpoint_config(_eval_cfg("agent=ppo", f"checkpoint={ckpt}", *given), given)
    assert (cfg.sim.height, cfg.sim.width) == (2 * h, 2 * w)
    del state["config"]
    torch.save(state, ckpt)
    cfg = apply_checkpoint_config(_eval_cfg("agent=ppo", f"checkpoint={ckpt}", "sim.height=32"), ["sim.height=32"])
    assert (cfg.sim.height, cfg.sim.width) == (32, w)


def test_a_missing_checkpoint_next_to_a_model_card_points_to_the_card(tmp_path):
    from findview_baselines.rl.checkpoint import load_checkpoint

    with pytest.raises(FileNotFoundError, match="checkpoint not found") as plain:
        load_checkpoint(tmp_path / "agent.pth")
    assert "README" not in str(plain.value)
    (tmp_path / "README.md").write_text("# model card\n")
    with pytest.raises(FileNotFoundError, match=r"agent\.pth.*README\.md says how to make it"):
        load_checkpoint(tmp_path / "agent.pth")


# ------------------------------------------------------------------------------------------------
# trace=true: traces.jsonl, the TraceRecorder, the agents' STOP probability
# ------------------------------------------------------------------------------------------------
def _moved(pose: tuple[int, int], action: int, step: int = 1, bound: int = 60) -> tuple[int, int]:
    """The pose after ``action`` (UP=0, DOWN=1, LEFT=2, RIGHT=3, STOP=4): pitch clamped at ``bound``, yaw
    wrapped into (-180, 180]; written out here, not taken from the environment."""
    pitch, yaw = pose
    if action == 0:
        pitch = min(pitch + step, bound)
    elif action == 1:
        pitch = max(pitch - step, -bound)
    elif action in (2, 3):
        yaw += step if action == 3 else -step
        yaw = yaw - 360 if yaw > 180 else yaw + 360 if yaw <= -180 else yaw
    return pitch, yaw


def _check_trace(trace: dict, rec: dict) -> None:
    """One episode's trace against its episodes.jsonl record: one entry per step, starting at the initial pose,
    each pose the previous one moved by the previous action, the last action leading to the final pose, and
    the last action STOP exactly when the episode stopped."""
    acts = trace["action"]
    assert trace["episode_id"] == rec["episode_id"]
    assert len(acts) == len(trace["pitch"]) == len(trace["yaw"]) == rec["steps"] > 0
    poses = list(zip(trace["pitch"], trace["yaw"])) + [(rec["final_pitch"], rec["final_yaw"])]
    assert poses[0] == _moved((rec["init_pitch"], rec["init_yaw"]), 4)
    for k, a in enumerate(acts):
        assert poses[k + 1] == _moved(poses[k], a), (rec["episode_id"], k, poses[k], a, poses[k + 1])
    assert (acts[-1] == 4) == rec["called_stop"]
    assert 4 not in acts[:-1]


def _read_jsonl(path: Path) -> list[dict]:
    return [json.loads(x) for x in path.read_text().splitlines()]


def test_trace_of_a_rule_based_agent(folder_ds, tmp_path):
    """evaluate() with trace=true: traces.jsonl lines in episodes.jsonl's order, poses that follow the actions,
    stop_prob null (the random agent has none); without trace no traces.jsonl."""
    from findview_baselines.evaluation.evaluate import evaluate

    overrides = ["agent=random", *ds_args(folder_ds), *SMALL, "task.max_steps=5", "num_envs=4", "seed=3"]
    for trace in (True, False):
        out = tmp_path / str(trace)
        given = [*overrides, f"trace={str(trace).lower()}"]
        evaluate(_eval_cfg(*given), out, choices={"dataset": "folder", "agent": "random"}, overrides=given)
        assert (out / "traces.jsonl").is_file() == trace
    out = tmp_path / "True"
    recs, traces = _read_jsonl(out / "episodes.jsonl"), _read_jsonl(out / "traces.jsonl")
    assert [t["episode_id"] for t in traces] == [r["episode_id"] for r in recs] and len(recs) == 9
    for t, r in zip(traces, recs):
        assert list(t) == ["episode_id", "pitch", "yaw", "action", "stop_prob"]
        assert t["stop_prob"] is None
        _check_trace(t, r)
    # the premises: every action occurs, episodes end both ways
    assert {a for t in traces for a in t["action"]} == {0, 1, 2, 3, 4}
    assert {r["called_stop"] for r in recs} == {True, False}
    assert not list(out.glob(".*.tmp"))


def test_trace_recorder_clamps_wraps_and_restarts_slots(folder_ds):
    """A scripted agent at the pitch bound and across yaw +-180, on 2 slots for 3 episodes (the third starts in a
    slot another episode left): exact poses, actions and the agent's per-step values (NaN -> None)."""
    from dataclasses import replace

    from findview_baselines.agents.base import Agent
    from findview_baselines.evaluation import TraceRecorder, run_episodes

    base = _episodes(folder_ds)[0]
    episodes = [replace(base, episode_id="up", init_pitch=58, init_yaw=178),
                replace(base, episode_id="down", init_pitch=-58, init_yaw=-179),
                replace(base, episode_id="left", init_pitch=0, init_yaw=-179)]
    scripts = {"up": [0, 0, 0, 0, 3, 3, 3, 1, 2, 2, 4], "down": [1] * 12, "left": [2, 2, 4]}

    class Scripted(Agent):
        name = "scripted"

        def __init__(self, num_envs):
            super().__init__(num_envs)
            self.script, self.k, self.last_k = [[]] * num_envs, [0] * num_envs, [0] * num_envs

        def reset(self, env_ids, eps):
            super().reset(env_ids, eps)
            for i, ep in zip(env_ids, eps):
                self.script[i], self.k[i] = (scripts[ep.episode_id] if ep is not None else []), 0

        def act(self, obs):
            self.last_k = list(self.k)
            acts = [self.script[i][self.k[i]] if self.k[i] < len(self.script[i]) else 4 for i in range(self.num_envs)]
            self.k = [k + 1 for k in self.k]
            return torch.tensor(acts)

        def step_stop_prob(self):  # the step index / 100, no value at step 2
            return torch.tensor([float("nan") if k == 2 else k / 100 for k in self.last_k])

    agent = Scripted(2)
    tracer = TraceRecorder(agent.step_stop_prob)
    records, _ = run_episodes(_env(episodes, 2, max_steps=12), agent, progress=False, callbacks=[tracer])
    assert [r["episode_id"] for r in records] == ["up", "down", "left"]
    up, down, left = (tracer.traces[e] for e in ("up", "down", "left"))
    assert list(zip(up["pitch"], up["yaw"])) == [(58, 178), (59, 178), (60, 178), (60, 178), (60, 178), (60, 179),
                                                  (60, 180), (60, -179), (59, -179), (59, 180), (59, 179)]
    assert up["action"] == scripts["up"] and down["action"] == scripts["down"]
    assert down["pitch"] == [-58, -59, -60, -60, -60, -60, -60, -60, -60, -60, -60, -60] and set(down["yaw"]) == {-179}
    assert (left["pitch"], left["yaw"], left["action"]) == ([0, 0, 0], [-179, 180, 179], [2, 2, 4])
    assert up["stop_prob"] == [0.0, 0.01, None, 0.03, 0.04, 0.05, 0.06, 0.07, 0.08, 0.09, 0.1]
    assert left["stop_prob"] == [0.0, 0.01, None]
    for r in records:
        _check_trace(tracer.traces[r["episode_id"]], r)
    assert [r["called_stop"] for r in records] == [True, False, True]
    no_probs = TraceRecorder()  # no stop_prob function: null as a whole
    run_episodes(_env(episodes, 2, max_steps=12), Scripted(2), progress=False, callbacks=[no_probs])
    assert no_probs.traces["up"]["action"] == scripts["up"] and no_probs.traces["up"]["stop_prob"] is None


def test_ppo_step_stop_prob_is_the_networks_own(tiny_ckpt):
    """step_stop_prob: the network's STOP probability of the last act, before the search memory (whose own
    distribution is 0 or 1 on STOP), NaN for a slot the network did not decide for; rule-based agents: None."""
    from findview_baselines.agents import make_agent
    from findview_baselines.agents.base import STOP
    from findview_baselines.agents.ppo_agent import PPOAgent

    assert make_agent("random", None, 2).step_stop_prob() is None
    assert make_agent("oracle", None, 2).step_stop_prob() is None
    g = torch.Generator().manual_seed(0)
    obs = {k: torch.randint(0, 256, (3, 3, 64, 64), dtype=torch.uint8, generator=g) for k in ("view", "target")}
    for penalty in (0.0, 2.0):
        agent = PPOAgent.from_checkpoint(tiny_ckpt, 3, "cpu", height=64, width=64, revisit_penalty=penalty)
        with torch.no_grad():
            dist, _, _ = agent.policy(obs, agent.policy.initial_hidden(3, "cpu"), torch.ones(3))
        expected = dist.probs[:, STOP]
        assert ((expected > 0.01) & (expected < 0.99)).all()  # the premise: not the memory's 0 / 1
        agent.reset([0, 1, 2], [None, None, None])
        agent.done[:] = False  # three running slots (reset with no episodes idles them)
        agent.act(obs)
        assert torch.allclose(agent.step_stop_prob(), expected, atol=1e-6), penalty
        agent.done[:] = [False, True, False]  # slot 1 has stopped: the network does not decide for it
        agent.act(obs)
        p = agent.step_stop_prob()
        assert torch.isnan(p[1]) and not torch.isnan(p[[0, 2]]).any() and ((p[[0, 2]] >= 0) & (p[[0, 2]] <= 1)).all()


def test_trace_of_the_learned_agent(folder_ds, tiny_ckpt, tmp_path):
    """tools/eval.py trace=true with a checkpoint: a STOP probability per step, in [0, 1], consistent with the
    greedy actions (STOP only where it is the argmax, so >= 1/5; a move only where STOP is not, so <= 1/2)."""
    out = tmp_path / "ppo_trace"
    check(run_tool("eval.py", "agent=ppo", f"checkpoint={tiny_ckpt}", *ds_args(folder_ds), *SMALL, "task.max_steps=30",
                   "max_episodes=4", "num_envs=2", "trace=true", f"hydra.run.dir={out}"))
    recs, traces = _read_jsonl(out / "episodes.jsonl"), _read_jsonl(out / "traces.jsonl")
    assert [t["episode_id"] for t in traces] == [r["episode_id"] for r in recs] and len(recs) == 4
    for t, r in zip(traces, recs):
        _check_trace(t, r)
        probs = t["stop_prob"]
        assert len(probs) == r["steps"] and all(isinstance(p, float) and 0.0 <= p <= 1.0 for p in probs)
        for a, p in zip(t["action"], probs):
            assert p >= 0.2 if a == 4 else p <= 0.5
    assert len({p for t in traces for p in t["stop_prob"]}) > 1
