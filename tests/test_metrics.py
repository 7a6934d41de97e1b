"""findview.metrics on hand-computed episodes (docs/TASK.md, Metrics)."""

from __future__ import annotations

import json
import math

import pytest

from findview.episode import Episode
from findview.metrics import RECORD_KEYS, aggregate, episode_spl, format_table, make_record, summarize


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
