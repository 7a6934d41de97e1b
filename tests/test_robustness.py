"""benchmarks/robustness.py end to end on the built-in synthetic data: a tiny benchmark (random agent, fog and
contrast at severities 1 and 3, FoV 90, T = 30) runs, writes the tables and the plot, resumes, and
``--dry-run`` runs nothing."""

from __future__ import annotations

import json
import signal
import sys
import threading
import time
from pathlib import Path

import cv2
import pytest

REPO = Path(__file__).resolve().parents[1]
ARGS = ["--agents", "random", "--corruptions", "fog", "contrast", "--severities", "1", "3", "--fovs", "90",
        "--T", "30", "--calibration-episodes", "1", "--jobs", "2"]
CELLS = ["random_fov90_clear", "random_fov90_contrast_s1", "random_fov90_contrast_s3", "random_fov90_fog_s1",
         "random_fov90_fog_s3"]


sys.path.insert(0, str(REPO / "benchmarks"))
import robustness  # noqa: E402  (benchmarks/robustness.py)

ROBUST_CKPT = str(REPO / "pretrained" / "findview_sun360mini_indoor_robust.pth")


def plan(*argv: str) -> list:
    """The cells ``benchmarks/robustness.py`` would run for ``argv`` (nothing is run)."""
    args = robustness.build_parser().parse_args(list(argv))
    args.fovs = [float(f) for f in args.fovs]
    agents = robustness.parse_agents(args.agents, AssertionError)
    return robustness.make_plan(args, agents, robustness.parse_corruptions(args.corruptions, AssertionError))


def bench(capsys, out: Path, *extra: str) -> str:
    """The command in this process (it starts tools/eval.py subprocesses itself); returns its stdout."""
    rc = robustness.main([*ARGS, "--out", str(out), *extra])
    captured = capsys.readouterr()
    assert rc == 0, captured.out + captured.err
    return captured.out


def test_robustness_benchmark_end_to_end(tmp_path, capsys, monkeypatch):
    monkeypatch.chdir(REPO)  # the synthetic data set's images: data/synthetic/images of the repository
    out = tmp_path / "bench"

    # --dry-run: the plan, nothing run or written
    stdout = bench(capsys, out, "--dry-run")
    assert "5 cells" in stdout and "dry run" in stdout
    assert sum(line.strip().startswith("run ") for line in stdout.splitlines()) == 5
    assert not out.exists()

    # the benchmark: every cell ran, with an estimate before and the wall time after
    stdout = bench(capsys, out)
    assert "expected run time" in stdout and "wall time" in stdout
    assert stdout.index("expected run time") < stdout.index("[1/5]")
    runs = out / "runs"
    assert sorted(p.name for p in runs.iterdir()) == CELLS
    for cell in CELLS:
        summary = json.loads((runs / cell / "summary.json").read_text())
        assert sum(summary[d]["episodes"] for d in ("easy", "medium", "hard")) == 12
        meta = json.loads((runs / cell / "run.json").read_text())
        assert meta["corruption"] == ("none" if cell.endswith("clear") else cell.split("_")[2])
    mtimes = {c: (runs / c / "summary.json").stat().st_mtime_ns for c in CELLS}

    # tables: per severity, eps and omega_stop, rows = agents, columns = clear + the corruptions by category
    tables = (out / "tables.md").read_text()
    for metric in ("eps", "omega_stop"):
        for sev in (1, 3):
            assert f"{metric} averaged over the difficulties, severity {sev}" in tables
    assert tables.count("| agent | clear | contrast | fog |") == 4
    assert tables.count("| *category* |  | *digital* | *weather* |") == 4
    rows = [line for line in tables.splitlines() if line.startswith("| random |")]
    assert len(rows) == 5 and all(len(r.strip("|").split("|")) in (4, 10) for r in rows)
    assert "| agent | clear | blur s1 | blur s3 | noise s1 | noise s3 | digital s1 | digital s3 | weather s1 | weather s3 |" in tables

    # the plot: one PNG for FoV 90, of the documented size
    png = cv2.imread(str(out / "plots" / "eps_vs_severity_fov90.png"))
    assert png is not None and png.shape[:2] == robustness.PLOT_SIZE

    # resume: a second invocation skips every finished cell and runs nothing
    stdout = bench(capsys, out)
    assert "5 finished, 0 to run" in stdout and "[1/" not in stdout
    assert {c: (runs / c / "summary.json").stat().st_mtime_ns for c in CELLS} == mtimes

    # a cell whose settings changed is not finished (the next invocation would re-run it)
    args = robustness.build_parser().parse_args([*ARGS, "--out", str(out)])
    args.fovs = [float(f) for f in args.fovs]
    agents = robustness.parse_agents(args.agents, AssertionError)
    plan = robustness.make_plan(args, agents, robustness.parse_corruptions(args.corruptions, AssertionError))
    assert [c.name for c in plan if robustness.is_done(c, {})] == [c.name for c in plan]
    args.T = 31
    plan = robustness.make_plan(args, agents, robustness.parse_corruptions(args.corruptions, AssertionError))
    assert not any(robustness.is_done(c, {}) for c in plan)


def test_dataset_overrides_reach_the_data_set_step(tmp_path, capsys, monkeypatch):
    """An ``--override dataset.KEY=V`` changes the episodes, so tools/make_dataset.py gets it as well as every
    cell; other overrides (agent.*) go to the cells only."""
    monkeypatch.chdir(REPO)
    stdout = bench(capsys, tmp_path / "bench", "--dry-run", "--override", "dataset.hard_rule=and",
                   "--override", "agent.threads=1")
    lines = stdout.splitlines()
    step = lines[lines.index("dry run: nothing is run. The data set step:") + 1]
    assert "make_dataset.py" in step and "dataset.hard_rule=and" in step and "agent.threads" not in step
    cells = [line for line in lines if line.strip().startswith("run ")]
    assert cells and all("dataset.hard_rule=and" in c and "agent.threads=1" in c for c in cells)


def test_expected_time_from_the_finished_cells(tmp_path):
    """The finished cells' run.json loop times, episodes and steps give each agent a rate (with the calibration's
    start-up seconds) that estimates the rest; a cell without (a readable) run.json gives nothing."""
    cells = plan(*ARGS, "--agents", "random", "orb", "--out", str(tmp_path))
    random_cells = [c for c in cells if c.agent.key == "random"]
    runtimes = [{"wall_seconds": 100.0, "episodes": 10, "env_steps": 1000},
                {"wall_seconds": 300.0, "episodes": 30, "env_steps": 1000}]
    for c, rt in zip(random_cells, [*runtimes, None, "broken"]):
        c.run_dir.mkdir(parents=True)
        if rt is not None:
            (c.run_dir / "run.json").write_text(json.dumps({"runtime": rt}) if rt != "broken" else "{")
    calibrated = {"random": robustness.Rate(1.0, 0.01, 2.5, "calibration")}
    rates, n = robustness.rates_from_finished(cells, calibrated)
    assert n == 2 and set(rates) == {"random"}
    r = rates["random"]  # 400 s over 40 episodes and 2000 steps
    assert (r.s_per_episode, r.s_per_step, r.startup_s) == (10.0, 0.2, 2.5)
    todo = random_cells[2:4]  # the two unfinished cells, 12 episodes each: 2 x (2.5 + 120) s on 2 jobs -> 122.5 s
    exp, most, lines = robustness.estimate(todo, rates, {90.0: 12}, 100, jobs=2)
    assert exp == 122.5 and most == 2.5 + 12 * 100 * 0.2 and "2 finished cells, 40 episodes" in lines[0]
    assert robustness.rates_from_finished(cells, {})[0]["random"].startup_s == 4.0  # no calibration yet


def test_user_agent_threads_are_not_overridden():
    """``--override agent.threads=1`` reaches every cell's command; the tool's own thread count (appended
    after the user's overrides, where it would win) is only added when the user set none."""
    base = ["--agents", "rotation", "--corruptions", "fog", "--severities", "3", "--fovs", "90"]
    for cell in plan(*base, "--override", "agent.threads=1"):
        threads = [o for o in cell.overrides + cell.runtime if o.startswith("agent.threads=")]
        assert threads == ["agent.threads=1"], cell.name
    for cell in plan(*base):
        assert len([o for o in cell.runtime if o.startswith("agent.threads=")]) == 1, cell.name
        assert not any(o.startswith("agent.threads=") for o in cell.overrides), cell.name


def test_checkpoint_size_renders_only_the_checkpoints_larger():
    """``--checkpoint-size 256`` gives the checkpoint's cells 256x256 views (at every FoV), while the rule-based
    agents keep their FoV preset (60: ``sim=fov60``, 256x192, with no size override that would square it)."""
    base = ["--agents", "rotation", f"checkpoint={ROBUST_CKPT}", "--corruptions", "fog", "--severities", "3",
            "--fovs", "90", "60"]

    def sizes(cell) -> list[str]:
        return [o for o in cell.overrides if o.startswith(("sim=", "sim.height=", "sim.width=", "sim.fov="))]

    cells = plan(*base, "--checkpoint-size", "256")
    assert len(cells) == 8  # 2 agents x 2 FoVs x (fog 3 + clear)
    for cell in cells:
        fov = "90" if cell.fov == 90.0 else "60"
        if cell.agent.checkpoint:
            assert sizes(cell) == [f"sim.fov={fov}", "sim.height=256", "sim.width=256"], cell.name
        else:
            assert sizes(cell) == [f"sim=fov{fov}"], cell.name
    for cell in plan(*base):  # default: the checkpoint's own size (no size override)
        if cell.agent.checkpoint:
            assert not any(o.startswith(("sim.height=", "sim.width=")) for o in cell.overrides), cell.name


def test_stopping_ends_a_job_that_ignores_sigint():
    """Ctrl-C / SIGTERM of the benchmark stops its running tools/eval.py jobs, even when they ignore SIGINT
    (as every job started in the background of a non-interactive shell does)."""
    runner = robustness.Runner()
    result: list = []
    t = threading.Thread(target=lambda: result.append(runner.run([sys.executable, "-c", "import time; time.sleep(60)"])))
    previous = signal.signal(signal.SIGINT, signal.SIG_IGN)  # the child inherits SIGINT ignored, from its start
    try:
        t.start()
        deadline = time.monotonic() + 30
        while not runner.live and time.monotonic() < deadline:
            time.sleep(0.05)
    finally:
        signal.signal(signal.SIGINT, previous)
    assert runner.live
    t0 = time.monotonic()
    runner.stop()
    t.join(timeout=30)
    assert not t.is_alive() and time.monotonic() - t0 < 20
    rc, _, _ = result[0]
    assert rc != 0
    assert runner.run([sys.executable, "-c", "pass"])[0] == 130  # nothing new starts once stopping


def test_checkpoint_size_that_is_not_a_multiple_is_refused_before_running(tmp_path, capsys):
    """A size the checkpoint's network (64x64) cannot average down to stops the command at once, naming the
    checkpoint and the sizes; nothing is run."""
    with pytest.raises(SystemExit):
        robustness.main(["--agents", f"checkpoint={ROBUST_CKPT}", "--checkpoint-size", "100", "--out", str(tmp_path / "o")])
    err = capsys.readouterr().err
    assert "--checkpoint-size 100" in err and ROBUST_CKPT in err and "64x64" in err and "256" in err
    assert not (tmp_path / "o").exists()
