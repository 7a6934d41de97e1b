"""Typed configs: every tool config composes against its schema; wrong types, unknown keys (presets
included) and out-of-range values fail at compose time with one line naming the key; every schema field
is documented; the code reads only keys the schemas define."""

from __future__ import annotations

import ast
import dataclasses
import inspect
import os
import subprocess
import sys
from pathlib import Path

import pytest

import findview.config as core_config
import findview_baselines.config as baseline_config
from findview_baselines.cli import compose_config, config_error_line, precheck, validate_config

REPO = Path(__file__).resolve().parents[1]


def error_of(config_name: str, overrides: list[str]) -> str:
    """The one-line error of composing + validating, or '' when the config is fine."""
    try:
        validate_config(compose_config(config_name, overrides))
    except Exception as err:  # noqa: BLE001 - the point is the message
        return config_error_line(err)
    return ""


@pytest.mark.parametrize(
    "config_name, overrides",
    [
        ("train", []),
        ("train", ["trainer=dagger"]),
        ("train", ["+experiment=quickstart"]),
        ("train", ["+experiment=cpu_small"]),
        ("train", ["+experiment=imitate"]),
        ("train", ["+experiment=reinforce"]),
        ("train", ["+experiment=robust"]),
        ("train", ["+experiment=robust_focus"]),
        ("train", ["+experiment=robust_finetune"]),
        ("train", ["+experiment=robust_memory"]),
        ("train", ["+experiment=robust_polish"]),
        ("train", ["sim=fov60", "corruption.name=weather", "corruption.severity=[1,3]"]),
        ("eval", []),
        *[("eval", [f"agent={a}"]) for a in ("random", "oracle", "orb", "sift", "rotation", "ppo")],
        *[("eval", [f"dataset={d}"]) for d in ("synthetic", "sun360_indoor", "sun360_outdoor", "indoor360", "folder")],
        ("make_dataset", []),
        ("render_episode", []),
    ],
)
def test_every_shipped_config_composes_and_validates(config_name: str, overrides: list[str]) -> None:
    assert error_of(config_name, overrides) == ""


@pytest.mark.parametrize("overrides", [[], ["dataset=sun360_indoor", "sim.fov=60"]])
def test_robust_memory_starts_from_where_the_robust_preset_writes_its_best_checkpoint(overrides: list[str]) -> None:
    """The two stages of the shipped robust agents chain with the same overrides: stage 2's default init_from is
    stage 1's run folder (the robust preset's hydra.run.dir) + checkpoints/best.pth."""
    stage1 = compose_config("train", ["+experiment=robust", *overrides], return_hydra_config=True)
    stage2 = compose_config("train", ["+experiment=robust_memory", *overrides])
    run_dir = stage1.hydra.run.dir
    assert stage2.init_from == f"{run_dir}/checkpoints/best.pth"
    assert (stage2.agent.variant, stage2.agent.hidden_size) == (stage1.agent.variant, stage1.agent.hidden_size)
    assert stage2.agent.memory_inputs and not stage1.agent.memory_inputs
    assert stage2.scheduler.start_level == 3  # hard episodes from the first update, no curriculum restart


def test_robust_polish_continues_stage_2_as_the_card_runs_it() -> None:
    """Stage 3 starts from stage 2's last update (latest.pth: the weights of its val_u01000.pth, the stage-2 file),
    keeps its network (memory inputs, pitch warps) and labels (no yaw band: turn towards any overlapping target, since
    session 37), lets the learner act (beta 0.2 -> 0),
    and its two search weights write to two run folders (the card averages them)."""
    stage2 = compose_config("train", ["+experiment=robust_memory"], return_hydra_config=True)
    runs = [compose_config("train", ["+experiment=robust_polish", f"trainer.dagger.search_weight={w}"], return_hydra_config=True)
            for w in (0.6, 0.3)]
    stage3 = runs[0]
    assert stage3.init_from == f"{stage2.hydra.run.dir}/checkpoints/latest.pth"
    assert stage3.agent.memory_inputs and stage3.agent.pitch_warps
    assert stage3.trainer.dagger.search_yaw_band == stage2.trainer.dagger.search_yaw_band == 1.0
    assert (stage3.trainer.dagger.beta_start, stage3.trainer.dagger.beta_end) == (0.2, 0.0)
    assert stage3.trainer.dagger.lr < stage2.trainer.dagger.lr
    assert stage3.scheduler.start_level == 3
    assert runs[0].hydra.run.dir != runs[1].hydra.run.dir


@pytest.mark.parametrize(
    "config_name, overrides, expected",
    [
        ("train", ["trainer.num_envs=abc"], "trainer.num_envs='abc': expected an integer"),
        ("train", ["trainer.ppo.lr=fast"], "trainer.ppo.lr='fast': expected a number"),
        ("train", ["trainer.ppo.lr=-1"], "trainer.ppo.lr=-1.0: expected a positive number"),
        # PPO's hyper-parameters moved from agent.* to trainer.ppo.*: the old spelling names the new key
        ("train", ["agent.lr=1e-3"], "agent.lr is now trainer.ppo.lr"),
        ("train", ["agent.rollout_steps=64"], "agent.rollout_steps is now trainer.ppo.rollout_steps"),
        # a key of the trainer that does not run would silently do nothing: refused, naming the way out
        ("train", ["trainer=dagger", "trainer.ppo.lr=1e-3"],
         "trainer.ppo.lr=0.001 is set but trainer.algorithm=dagger does not use trainer.ppo.*: drop it, set "
         "trainer.dagger.lr, or train with trainer=ppo"),
        ("train", ["trainer.dagger.epochs=2"], "trainer.dagger.epochs=2.0 is set but trainer.algorithm=ppo"),
        ("train", ["trainer=dagger", "trainer.dagger.lr=0"], "trainer.dagger.lr must be positive, got 0.0"),
        ("train", ["sim.fov=wide"], "sim.fov='wide': expected a number"),
        ("train", ["sim.fov=200"], "sim.fov=200.0: expected a field of view in (0, 180) degrees"),
        ("train", ["trainer.num_update=10"], "unknown key 'trainer.num_update'"),
        ("train", ["trainer.ppo.eps=1e-5"], "unknown key 'trainer.ppo.eps'"),  # Adam's epsilon is trainer.ppo.adam_eps
        ("train", ["agent.deterministic_eval=false"], "unknown key 'agent.deterministic_eval'"),  # one switch: sample
        ("train", ["trainer.algorithm=sarsa"], "trainer.algorithm='sarsa': expected ppo | dagger"),
        ("train", ["task.reward.name=dense"], "task.reward.name='dense': expected paper | bell | basic"),
        ("eval", ["agent=sift", "agent.d_thresh=-3"], "agent.d_thresh=-3: expected a descriptor distance"),
        ("eval", ["difficulty=extreme"], "difficulty='extreme': expected null | easy | medium | hard"),
        ("eval", ["agent=bogus"], "unknown agent 'bogus'; valid: oracle, orb, ppo, random, rotation, sift"),
        ("eval", ["corruption.severity=7"], "corruption.severity=7: expected an integer 1-5"),
        ("eval", ["dataset.hard_rule=xor"], "dataset.hard_rule='xor': expected or | and"),
        ("eval", ["agent=ppo", "agent.stop_min_prob=0"], "agent.stop_min_prob=0.0: expected null or a probability in (0, 1]"),
        ("eval", ["agent=ppo", "agent.stop_prob=0.3", "agent.stop_min_prob=0.5"],
         "agent.stop_min_prob=0.5: expected at most agent.stop_prob=0.3"),
        ("eval", ["agent=ppo", "agent.revisit_near_rows=-2"], "agent.revisit_near_rows=-2: expected 0 (off) or a number of rows"),
        ("eval", ["agent=ppo", "agent.revisit_near_age=0"], "agent.revisit_near_age=0: expected a number of steps >= 1"),
        ("eval", ["agent=ppo", "agent.revisit_near_since=-1"], "agent.revisit_near_since=-1: expected 0 or a number of steps"),
        ("eval", ["agent=ppo", "agent.mirror_steps=-1"], "agent.mirror_steps=-1: expected 0 (off) or a number of policy steps"),
        ("eval", ["agent=ppo", "agent.revisit_row_after=-5"], "agent.revisit_row_after=-5: expected 0 or a number of steps"),
        ("eval", ["agent=ppo", "agent.revisit_row_stride=30", "agent.revisit_row_budget=-1"],
         "agent.revisit_row_budget=-1: expected 0 or a number of steps"),
        ("eval", ["agent=ppo", "agent.stop_by_phase=true"],
         "agent.stop_by=0: expected a step number (T) with agent.stop_by_phase=true"),
    ],
)
def test_bad_values_fail_at_compose_time_naming_the_key(config_name: str, overrides: list[str], expected: str) -> None:
    message = error_of(config_name, overrides)
    assert expected in message and "\n" not in message


def test_a_misspelt_key_inside_a_preset_fails(tmp_path: Path) -> None:
    preset = tmp_path / "experiment" / "typo.yaml"
    preset.parent.mkdir()
    preset.write_text("# @package _global_\ntrainer:\n  num_update: 10\n")
    message = error_of("train", [f"hydra.searchpath=[file://{tmp_path}]", "+experiment=typo"])
    assert "unknown key 'trainer.num_update'" in message


def test_the_tools_print_one_line_and_exit_2() -> None:
    env = {**os.environ, "PYTHONPATH": str(REPO)}
    done = subprocess.run(
        [sys.executable, str(REPO / "tools" / "train.py"), "trainer.num_envs=abc"],
        capture_output=True, text=True, env=env, timeout=120,
    )
    assert done.returncode == 2
    assert done.stderr.strip() == "train: error: trainer.num_envs='abc': expected an integer"


def test_a_multirun_sweep_is_checked_before_any_job(capsys: pytest.CaptureFixture[str]) -> None:
    """The bad value is the third of the sweep: nothing runs, one line, exit 2."""
    with pytest.raises(SystemExit) as info:
        precheck("eval", "eval", ["-m", "agent=sift", "agent.d_thresh=10,20,oops"])
    assert info.value.code == 2
    assert capsys.readouterr().err.strip() == (
        "eval: error: agent.d_thresh='oops': expected a descriptor distance >= 0 (or inf), or {easy, medium, hard} of them"
    )


def _schemas() -> list[type]:
    out = []
    for module in (core_config, baseline_config):
        for _, obj in inspect.getmembers(module, dataclasses.is_dataclass):
            if obj.__module__ == module.__name__:
                out.append(obj)
    return [*out, baseline_config.DAggerConfig, baseline_config.PPOConfig]


def test_every_schema_field_has_a_docstring() -> None:
    """Field docstrings are the documentation: each field is followed by a string literal."""
    tool_fields = {"dataset", "sim", "task", "corruption", "agent", "trainer", "scheduler"}  # documented in their group
    missing = []
    for schema in _schemas():
        tree = ast.parse(inspect.getsource(schema))
        body = tree.body[0].body
        for k, node in enumerate(body):
            if isinstance(node, ast.AnnAssign) and isinstance(node.target, ast.Name):
                name = node.target.id
                documented = k + 1 < len(body) and isinstance(body[k + 1], ast.Expr) and isinstance(
                    getattr(body[k + 1], "value", None), ast.Constant
                )
                if not documented and name not in tool_fields:
                    missing.append(f"{schema.__name__}.{name}")
    assert not missing, f"fields without a docstring: {missing}"


def test_the_builders_take_the_typed_sections(tmp_path: Path) -> None:
    """findview.build (used by train, eval, render, benchmarks and tests) reads the attributes of the typed
    sections (a key the schema does not define would be an AttributeError); mappings are converted once at the
    caller with as_section."""
    import numpy as np

    from findview.build import build_env, build_simulator
    from findview.task import StaticEpisodeSource

    sim_cfg = core_config.SimConfig(fov=90.0, height=16, width=16, device="cpu", prefetch_workers=0)
    task_cfg = core_config.as_section({"max_steps": 50}, core_config.TaskConfig)
    sim = build_simulator(sim_cfg, 60, [], 1)
    env = build_env(sim, StaticEpisodeSource([]), 1, task_cfg)
    assert (sim.height, sim.width, env.max_steps, env.pitch_bound) == (16, 16, 50, 60)
    assert np.isfinite(sim.fov)
    assert core_config.as_section(sim_cfg, core_config.SimConfig) is sim_cfg
    with pytest.raises(Exception, match="no_such_key"):
        core_config.as_section({"no_such_key": 1}, core_config.SimConfig)
