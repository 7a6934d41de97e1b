"""findview.metrics on hand-computed episodes (docs/TASK.md, Metrics)."""

from __future__ import annotations

import json
import math

import pytest

from findview.episode import Episode
from findview.metrics import (
    RECORD_KEYS,
    aggregate,
    blind_search_path,
    blind_search_spl,
    episode_spl,
    format_table,
    make_record,
    summarize,
)


def _ep(init=(0, 0), target=(0, 20), difficulty="easy", eid="e") -> Episode:
    return Episode(eid, "img.jpg", init[0], init[1], target[0], target[1], difficulty=difficulty, label="lab")


def test_record_keys_and_json():
    r = make_record(_ep(), 0, 20, 21, True)
    assert tuple(r) == RECORD_KEYS
    assert r["eps"] == 0 and r["shortest_path"] == 21 and r["called_stop"] is True
    assert json.loads(json.dumps(r)) == r


def test_yaw_wrap_error_and_shortest_path():
    # target yaw -179, final yaw 179: wrapped difference 2 degrees
    ep = _ep(init=(10, 170), target=(-5, -179))
    r = make_record(ep, 0, 179, 30, True)
    assert r["eps"] == 5 + 2
    # shortest path: |10 - -5| + wrapped(170, -179) = 15 + 11, + 1 for stop
    assert r["shortest_path"] == 15 + 11 + 1
    assert make_record(_ep(target=(0, 180)), 0, -179, 3, True)["eps"] == 1


def test_forced_stop_not_counted():
    ep = _ep(target=(0, 20))
    forced = make_record(ep, 0, 20, 5000, False)  # at the target but never called stop
    assert forced["eps"] == 0
    assert episode_spl(forced) == 0.0
    m = aggregate([forced])
    assert m["omega_stop"] == 0.0
    assert m["omega_perf"] == 0.0  # documented: no stopped episode -> 0.0
    assert m["spl"] == 0.0 and m["eps"] == 0.0 and m["episodes"] == 1


def test_spl_exact_and_detour():
    ep = _ep(init=(0, 0), target=(3, -4))  # L* = 7 + 1 = 8
    exact = make_record(ep, 3, -4, 8, True)
    assert episode_spl(exact) == 1.0
    detour = make_record(ep, 3, -4, 12, True)
    assert episode_spl(detour) == pytest.approx(8 / 12)
    wrong = make_record(ep, 3, -3, 8, True)  # stopped one degree off: S = 0
    assert episode_spl(wrong) == 0.0


def test_summary_per_difficulty():
    recs = [
        # easy: stop perfect (SPL 1), stop perfect with detour (SPL 21/28), stop off by 3, forced off by 10
        make_record(_ep(target=(0, 20), eid="a"), 0, 20, 21, True),
        make_record(_ep(target=(0, 20), eid="b"), 0, 20, 28, True),
        make_record(_ep(target=(0, 20), eid="c"), 2, 21, 40, True),
        make_record(_ep(target=(0, 20), eid="d"), 0, 10, 5000, False),
        # hard: one forced stop only
        make_record(_ep(target=(0, 150), difficulty="hard", eid="e"), 0, -170, 5000, False),
    ]
    s = summarize(recs)
    assert list(s) == ["easy", "hard"]
    e = s["easy"]
    assert e["episodes"] == 4
    assert e["eps"] == pytest.approx((0 + 0 + 3 + 10) / 4)
    assert e["omega_stop"] == pytest.approx(3 / 4)
    assert e["omega_perf"] == pytest.approx(2 / 3)  # among the stoppers only
    assert e["spl"] == pytest.approx((1 + 21 / 28 + 0 + 0) / 4)
    h = s["hard"]
    assert h["eps"] == 40 and h["omega_stop"] == 0 and h["omega_perf"] == 0 and h["spl"] == 0
    for g in s.values():
        for k in ("omega_stop", "omega_perf", "spl"):
            assert 0.0 <= g[k] <= 1.0
    s_all = summarize(recs, include_all=True)
    assert s_all["all"]["episodes"] == 5
    assert s_all["all"]["eps"] == pytest.approx((13 + 40) / 5)


def test_summary_order_and_missing_eps_recomputed():
    r = make_record(_ep(difficulty="medium"), 1, 19, 30, True)
    r2 = make_record(_ep(difficulty="easy"), 0, 20, 30, True)
    del r["eps"], r["shortest_path"]
    s = summarize([r, r2])
    assert list(s) == ["easy", "medium"]
    assert s["medium"]["eps"] == 2


def test_empty_group():
    m = aggregate([])
    assert m["episodes"] == 0 and math.isnan(m["eps"])
    assert summarize([]) == {}


def test_format_table_layouts():
    recs = [
        make_record(_ep(target=(0, 20)), 0, 20, 21, True),
        make_record(_ep(target=(0, 30), difficulty="medium"), 0, 29, 40, True),
    ]
    s = summarize(recs)
    single = format_table(s)
    lines = single.splitlines()
    assert lines[0].startswith("| difficulty | eps | omega_stop | omega_perf | SPL")
    assert "| easy | 0.00 | 100.0% | 100.0% | 100.0% | 1 |" in lines
    assert "| medium | 1.00 | 100.0% | 0.0% | 0.0% | 1 |" in lines
    multi = format_table({"orb": s, "oracle": s}, difficulties=["easy", "medium", "hard"])
    ml = multi.splitlines()
    assert ml[0].count("|") == 2 + 12
    assert ml[2].startswith("| orb | 0.00 | 100.0% | 100.0% | 100.0% | 1.00 |")
    assert ml[2].rstrip().endswith("- | - | - | - |")
    assert len(ml) == 4


def test_blind_search_path_by_hand():
    # target 120 degrees to the right at the same pitch, FoV 90: no overlap at the start
    assert blind_search_path(0, 0, 0, 120, 90, "right") == 121  # pans the short way: L* = 121
    assert blind_search_path(0, 0, 0, 120, 90, "left") == 241  # the long way round: 360 - 120 + stop
    # across the seam: from yaw 170 to -70 is 120 to the right
    assert blind_search_path(0, 170, 0, -70, 90, "right") == 121
    assert blind_search_path(0, 170, 0, -70, 90, "left") == 241
    # pitch adds on both sides: 30 up, 100 to the left
    assert blind_search_path(-10, 0, 20, -100, 90, "left") == 30 + 100 + 1
    assert blind_search_path(-10, 0, 20, -100, 90, "right") == 30 + 260 + 1
    # an overlapping start (|dpitch| <= fov, |dyaw| <= fov) takes the shortest path whichever side
    assert blind_search_path(10, 0, -20, -60, 90, "right") == blind_search_path(10, 0, -20, -60, 90, "left") == 91
    # exactly 180 apart: both sides are as long
    assert blind_search_path(0, 0, 0, 180, 90, "right") == blind_search_path(0, 0, 0, 180, 90, "left") == 181
    with pytest.raises(ValueError, match="direction"):
        blind_search_path(0, 0, 0, 120, 90, "up")


def test_blind_search_spl_means_and_coin():
    episodes = [
        {"init_pitch": 0, "init_yaw": 0, "target_pitch": 0, "target_yaw": 120},  # right 1, left 121/241
        Episode("e", "img.jpg", 0, 0, 0, -150, "hard"),  # right 151/211, left 1
    ]
    b = blind_search_spl(episodes, 90)
    assert b["episodes"] == 2
    assert b["right"] == pytest.approx((1 + 151 / 211) / 2)
    assert b["left"] == pytest.approx((121 / 241 + 1) / 2)
    assert b["coin"] == pytest.approx((b["right"] + b["left"]) / 2)
    # every start overlapping: the bound is 1 (nothing to search)
    assert blind_search_spl([{"init_pitch": 0, "init_yaw": 0, "target_pitch": 5, "target_yaw": 40}], 90)["coin"] == 1.0
    assert math.isnan(blind_search_spl([], 90)["coin"])


def test_search_bound_script_tables(tmp_path, capsys):
    import importlib.util
    import pathlib

    spec = importlib.util.spec_from_file_location(
        "search_bound", pathlib.Path(__file__).resolve().parents[1] / "benchmarks" / "search_bound.py"
    )
    mod = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(mod)
    hard = [
        {"episode_id": "a", "difficulty": "hard", "init_pitch": 0, "init_yaw": 0, "target_pitch": 0, "target_yaw": 120},
        {"episode_id": "b", "difficulty": "hard", "init_pitch": 0, "init_yaw": 0, "target_pitch": 0, "target_yaw": -150},
    ]
    episode_file = tmp_path / "val_fov90.json"
    episode_file.write_text(json.dumps({"fov": 90, "episodes": hard}))
    # an eval run folder: the agent panned right on both (exact stops, 121 and 211 steps: first passes)
    run = tmp_path / "run"
    run.mkdir()
    (run / "run.json").write_text(json.dumps({"fov": 90.0}))
    records = [dict(hard[0], steps=121, called_stop=True, eps=0), dict(hard[1], steps=211, called_stop=True, eps=0)]
    (run / "episodes.jsonl").write_text("".join(json.dumps(r) + "\n" for r in records))
    mod.main([str(episode_file), str(run)])
    out = capsys.readouterr().out
    right = 100 * (1 + 151 / 211) / 2
    assert f"| hard | 2 | {right:.1f}% |" in out
    # the agent that panned right on both reaches the pan-right bound exactly, every stop exact and on its first pass
    assert out.count(f"{right:.1f}%") == 3 and "| 100.0% | 100.0% |" in out
    # the same stops after a full extra turn are exact but not first passes
    records = [dict(r, steps=r["steps"] + 360) for r in records]
    (run / "episodes.jsonl").write_text("".join(json.dumps(r) + "\n" for r in records))
    mod.main([str(run)])
    assert "| 100.0% | 0.0% |" in capsys.readouterr().out
    (tmp_path / "bad.json").write_text(json.dumps([1, 2]))
    with pytest.raises(SystemExit, match="not a findview episode file"):
        mod.main([str(tmp_path / "bad.json")])


def test_direction_probe_puts_each_target_exactly_its_offset_to_the_left() -> None:
    import importlib.util
    import pathlib

    spec = importlib.util.spec_from_file_location(
        "direction_probe", pathlib.Path(__file__).resolve().parents[1] / "benchmarks" / "direction_probe.py"
    )
    mod = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(mod)
    probes = mod.probe_episodes(["a.jpg", "b.jpg"], per_cell=6, fov=90.0, seed=3)
    assert len(probes) == 6 * len(mod.YAW_OFFSETS) * len(mod.PITCH_OFFSETS)
    for ep, dy, dp, sign in probes:
        assert -180 < ep.target_yaw <= 180 and abs(ep.target_pitch) <= 60
        assert (ep.init_yaw - ep.target_yaw) % 360 == dy  # dy degrees to the left (yaw decreases to the left)
        assert ep.target_pitch - ep.init_pitch == sign * dp
