"""Baseline agents: registry, random, oracle, the paper's orb/sift rules and the rotation agent."""

from __future__ import annotations

import dataclasses
import functools
import math
from pathlib import Path

import cv2
import numpy as np
import pytest
import torch

from findview import sim as sim_mod
from findview import task
from findview.episode import Episode
from findview.geometry import l1_distance, wrap_yaw
from findview.imageio import load_panorama
from findview_baselines.agents import agent_names, default_agent_config, make_agent
from findview_baselines.agents.base import DOWN, LEFT, RIGHT, STOP, UP, gray_of, host_images, rgb_to_gray
from findview_baselines.agents.feature_base import ViewCache
from findview_baselines.agents.feature_matching import (
    FeatureMatchingAgent,
    detect,
    displacement_votes,
    is_oscillating,
    knn2,
    parse_d_thresh,
    vote_action,
)
from findview_baselines.agents.rotation import (
    decompose_relative_rotation,
    estimate_from_images,
    kabsch,
    mean_chromaticity,
    photometric_score,
    photometric_template,
)

FOV, H, W = 90.0, 256, 256
PANOS = ("pano_aaacisrhqnnvoq.jpg", "pano_abrirqbocvnkye.jpg")  # indoor bedroom, indoor greenhouse


# ------------------------------------------------------------------------------------------------
# helpers
# ------------------------------------------------------------------------------------------------
def _equi2pers():
    from findview.sim import equi2pers

    return equi2pers


def render(
    equi: torch.Tensor, rotations: list[tuple[int, int]], fov: float = FOV, h: int = H, w: int = W
) -> torch.Tensor:
    """Views ``(B, 3, h, w)`` uint8 of ``equi (1, 3, He, We)`` at ``(pitch, yaw)`` degrees."""
    p = torch.tensor([float(r[0]) for r in rotations], dtype=torch.float64)
    y = torch.tensor([float(r[1]) for r in rotations], dtype=torch.float64)
    return _equi2pers()(equi.expand(len(rotations), -1, -1, -1), p, y, fov, h, w, mode="bilinear")


@pytest.fixture(scope="module")
def panos(sun360_mini_files: list[Path]) -> dict[str, torch.Tensor]:
    by_name = {f.name: f for f in sun360_mini_files}
    return {n: torch.from_numpy(load_panorama(by_name[n])).permute(2, 0, 1)[None].contiguous() for n in PANOS}


def obs_of(view: torch.Tensor, target: torch.Tensor) -> dict[str, torch.Tensor]:
    return {"view": view, "target": target}


def ep(init=(0, 0), target=(0, 20), difficulty="easy", eid="t0") -> Episode:
    return Episode(eid, "x.jpg", init[0], init[1], target[0], target[1], difficulty=difficulty, seed=7)


class TinyEnv:
    """The task's move rules (docs/TASK.md) on one panorama, rendering with equi2pers.

    ``corrupt`` (optional) maps the ``(1, 3, h, w)`` uint8 target to the one the agent sees.
    """

    def __init__(
        self, equi: torch.Tensor, episode: Episode, pitch_bound: int = 60, size: tuple[int, int] = (H, W), corrupt=None
    ) -> None:
        self.equi, self.ep, self.bound, self.size = equi, episode, pitch_bound, size
        self.pitch, self.yaw, self.steps = episode.init_pitch, episode.init_yaw, 0
        self.target = render(equi, [(episode.target_pitch, episode.target_yaw)], FOV, *size)
        if corrupt is not None:
            self.target = corrupt(self.target)

    def obs(self) -> dict[str, torch.Tensor]:
        return obs_of(render(self.equi, [(self.pitch, self.yaw)], FOV, *self.size), self.target)

    def step(self, a: int) -> bool:
        self.steps += 1
        if a == STOP:
            return True
        self.pitch = int(np.clip(self.pitch + (a == UP) - (a == DOWN), -self.bound, self.bound))
        self.yaw = int(wrap_yaw(self.yaw + (a == RIGHT) - (a == LEFT)))
        return False

    def eps(self) -> int:
        return int(l1_distance(self.pitch, self.yaw, self.ep.target_pitch, self.ep.target_yaw))


def pose_views(equi: torch.Tensor, h: int = 128, w: int = 128):
    """``at(p, y)``: the ``(1, 3, h, w)`` view of ``equi`` at pitch ``p``, yaw ``y`` (degrees), each pose
    rendered once (the scripted walks of the view-cache tests revisit poses)."""
    return functools.lru_cache(maxsize=None)(lambda p, y: render(equi, [(p, y)], h=h, w=w))


def agent_cfg(name: str, **values):
    """The typed config of agent ``name``: the schema's defaults with ``values``."""
    return dataclasses.replace(default_agent_config(name), **values)


def simulate_oracle_episode(e: Episode, order: str = "pitch_first", pitch_bound: int = 60) -> tuple[int, int, int, int]:
    """Run the oracle with the task rules (no rendering); returns (final pitch, yaw, steps, last action)."""
    agent = make_agent("oracle", agent_cfg("oracle", order=order, pitch_bound=pitch_bound), 1, "cpu", 0)
    agent.reset([0], [e])
    dummy = torch.zeros(1, 3, 4, 4, dtype=torch.uint8)
    pitch, yaw, steps = e.init_pitch, e.init_yaw, 0
    for _ in range(1000):
        a = int(agent.act(obs_of(dummy, dummy))[0])
        steps += 1
        if a == STOP:
            return pitch, yaw, steps, a
        pitch = int(np.clip(pitch + (a == UP) - (a == DOWN), -pitch_bound, pitch_bound))
        yaw = int(wrap_yaw(yaw + (a == RIGHT) - (a == LEFT)))
    raise AssertionError("oracle never stopped")


# ------------------------------------------------------------------------------------------------
# registry and config handling
# ------------------------------------------------------------------------------------------------
def test_registry_names_and_errors():
    assert {"random", "oracle", "orb", "sift", "rotation"} <= set(agent_names())
    with pytest.raises(ValueError, match="valid agents: .*oracle.*orb.*random.*rotation.*sift"):
        make_agent("nope", None, 1, "cpu", 0)
    with pytest.raises(TypeError, match="d_tresh"):  # the schema knows its keys
        agent_cfg("orb", d_tresh=50)
    with pytest.raises(ValueError, match="the config given is for agent 'sift'"):
        make_agent("orb", agent_cfg("sift"), 1, "cpu", 0)
    a = make_agent("sift", agent_cfg("sift", d_thresh=50), 2, "cpu", 0)
    assert isinstance(a, FeatureMatchingAgent) and a.detector == "sift"
    assert a.d_thresh["hard"] == 50.0


def test_agent_yaml_configs(repo_root: Path):
    from findview_baselines.cli import compose_config, validate_config

    for name in ("random", "oracle", "orb", "sift", "rotation"):
        cfg = validate_config(compose_config("eval", [f"agent={name}", "sim=fov60", "task.pitch_bound=45"])).agent
        assert cfg.name == name
        agent = make_agent(name, cfg, 2, "cpu", 0)
        if name in ("orb", "sift"):
            assert agent.d_thresh == {"easy": math.inf, "medium": math.inf, "hard": math.inf, "default": math.inf}
        if name == "oracle":
            assert agent.pitch_bound == 45  # the task's clamp
        if name == "rotation":
            assert agent.fov == 60.0  # the rendered views' FoV


def test_parse_d_thresh():
    assert parse_d_thresh(50)["medium"] == 50.0
    assert parse_d_thresh("inf")["easy"] == math.inf
    assert parse_d_thresh(None)["hard"] == math.inf
    d = parse_d_thresh({"easy": 60, "medium": "inf", "hard": 20})
    assert (d["easy"], d["medium"], d["hard"]) == (60.0, math.inf, 20.0)
    assert parse_d_thresh({"hard": 10})["easy"] == math.inf
    with pytest.raises(ValueError, match="unknown difficulties"):
        parse_d_thresh({"eazy": 10})
    with pytest.raises(ValueError):
        parse_d_thresh(-1)


# ------------------------------------------------------------------------------------------------
# random
# ------------------------------------------------------------------------------------------------
def test_random_reproducible():
    dummy = torch.zeros(3, 3, 4, 4, dtype=torch.uint8)

    def run(seed: int) -> torch.Tensor:
        a = make_agent("random", None, 3, "cpu", seed)
        a.reset([0, 1, 2], [ep(), ep(), ep()])
        return torch.stack([a.act(obs_of(dummy, dummy)) for _ in range(50)])

    r1, r2, r3 = run(1), run(1), run(2)
    assert torch.equal(r1, r2) and not torch.equal(r1, r3)
    assert r1.dtype == torch.int64 and r1.shape == (50, 3)
    assert set(r1.unique().tolist()) == {0, 1, 2, 3, 4}


# ------------------------------------------------------------------------------------------------
# oracle
# ------------------------------------------------------------------------------------------------
@pytest.mark.parametrize("order", ["pitch_first", "yaw_first"])
@pytest.mark.parametrize(
    "init,target",
    [
        ((0, 0), (5, 20)),
        ((0, 175), (-3, -170)),  # yaw wrap: 15 degrees to the right across 180
        ((2, -170), (0, 172)),  # yaw wrap to the left
        ((60, 10), (48, -5)),  # at the pitch bound
        ((-60, 0), (60, 0)),  # bound to bound
        ((0, 0), (0, 180)),  # half turn
        ((0, 90), (0, -90)),
    ],
)
def test_oracle_shortest_path(order, init, target):
    e = ep(init, target)
    pitch, yaw, steps, last = simulate_oracle_episode(e, order)
    assert last == STOP
    assert (pitch, yaw) == (target[0], wrap_yaw(target[1]))
    assert steps == l1_distance(*init, *target) + 1  # L*: SPL 1


def test_oracle_batched_and_idle_after_stop():
    a = make_agent("oracle", None, 2, "cpu", 0)
    a.reset([0, 1], [ep((0, 0), (0, 2)), ep((0, 0), (-1, 0))])
    dummy = torch.zeros(2, 3, 4, 4, dtype=torch.uint8)
    seq = [a.act(obs_of(dummy, dummy)).tolist() for _ in range(4)]
    assert seq == [[RIGHT, DOWN], [RIGHT, STOP], [STOP, STOP], [STOP, STOP]]
    with pytest.raises(RuntimeError, match="never reset"):
        make_agent("oracle", None, 1, "cpu", 0).act(obs_of(dummy[:1], dummy[:1]))


# ------------------------------------------------------------------------------------------------
# the paper's voting rules (pure functions)
# ------------------------------------------------------------------------------------------------
def test_displacement_votes_signs():
    disp = np.array(
        [
            [-6.0, 1.0],  # content further left in the target: turn right
            [6.0, -1.0],  # further right: turn left
            [1.0, 5.0],  # lower in the target: look up
            [-1.0, -5.0],  # higher in the target: look down
            [0.5, -0.5],  # ~0: stop
        ]
    )
    assert displacement_votes(disp, 1.0).tolist() == [RIGHT, LEFT, UP, DOWN, STOP]
    assert vote_action(np.array([[-3.0, 0], [-4.0, 1], [0, 5.0]])) == RIGHT
    assert vote_action(np.zeros((0, 2))) is None


def test_is_oscillating():
    assert is_oscillating([LEFT, RIGHT, LEFT], RIGHT, 4)
    assert is_oscillating([UP, DOWN, UP], DOWN, 4)
    assert not is_oscillating([RIGHT, LEFT], RIGHT, 4)  # window not full yet
    assert not is_oscillating([RIGHT, RIGHT, RIGHT], RIGHT, 4)
    assert not is_oscillating([LEFT, RIGHT, UP], DOWN, 4)
    assert not is_oscillating([RIGHT, RIGHT, LEFT], RIGHT, 4)  # not alternating
    assert is_oscillating([RIGHT, RIGHT, LEFT], RIGHT, 4, rule="mixed")
    assert not is_oscillating([LEFT, RIGHT, LEFT], RIGHT, 1)  # disabled


def test_gray_matches_opencv():
    rng = np.random.default_rng(0)
    img = torch.from_numpy(rng.integers(0, 256, size=(2, 3, 17, 23), dtype=np.uint8))
    ours = rgb_to_gray(img)
    for k in range(2):
        ref = cv2.cvtColor(np.ascontiguousarray(img[k].permute(1, 2, 0).numpy()), cv2.COLOR_RGB2GRAY)
        assert np.array_equal(ours[k], ref)


def test_host_images_one_copy_any_layout():
    rng = np.random.default_rng(1)
    nhwc = torch.from_numpy(rng.integers(0, 256, size=(4, 9, 11, 3), dtype=np.uint8))
    obs = nhwc.permute(0, 3, 1, 2)  # the environment's layout: a channels-last buffer seen as NCHW
    got = host_images(obs, [3, 1])
    assert got.shape == (2, 3, 9, 11) and np.array_equal(got, obs[[3, 1]].numpy())
    assert np.array_equal(host_images(obs), obs.numpy()) and host_images(obs).base is not None  # no copy
    assert np.array_equal(rgb_to_gray(obs), rgb_to_gray(obs.contiguous()))


@pytest.mark.parametrize("kind", ["orb", "sift"])
def test_knn2_matches_bfmatcher(panos, kind):
    v = render(panos[PANOS[0]], [(0, 0), (0, 4)])
    g = rgb_to_gray(v)
    a, b = detect(kind, g[0]), detect(kind, g[1])
    dist, idx = knn2(a.des, b.des, kind)
    bf = cv2.BFMatcher(cv2.NORM_HAMMING if kind == "orb" else cv2.NORM_L2)
    ref = bf.knnMatch(a.des, b.des, k=2)
    assert len(ref) == len(dist)
    for q, (m, n) in enumerate(ref):
        assert np.isclose(dist[q, 0], m.distance, rtol=1e-4, atol=0.05)
        assert np.isclose(dist[q, 1], n.distance, rtol=1e-4, atol=0.05)
        assert idx[q, 0] == m.trainIdx or np.isclose(dist[q, 0], dist[q, 1])


# ------------------------------------------------------------------------------------------------
# orb / sift on real renders
# ------------------------------------------------------------------------------------------------
@pytest.mark.parametrize("kind", ["orb", "sift"])
@pytest.mark.parametrize("pano", PANOS)
def test_feature_agent_directions(panos, kind, pano):
    base = (5, 30)
    cases = [((5, 35), RIGHT), ((5, 25), LEFT), ((10, 30), UP), ((0, 30), DOWN), ((5, 30), STOP)]
    views = render(panos[pano], [base] + [c[0] for c in cases])
    n = len(cases)
    agent = make_agent(kind, None, n, "cpu", 0)
    agent.reset(list(range(n)), [ep(base, c[0]) for c in cases])
    actions = agent.act(obs_of(views[:1].expand(n, -1, -1, -1).contiguous(), views[1:].contiguous()))
    assert actions.tolist() == [c[1] for c in cases]
    assert actions.dtype == torch.int64 and actions.device == views.device
    # a slot that said STOP stays idle (STOP) until it is reset; a None episode idles a slot too
    agent.reset([0], [None])
    again = agent.act(obs_of(views[:1].expand(n, -1, -1, -1).contiguous(), views[1:].contiguous()))
    assert again.tolist() == [STOP] + [c[1] for c in cases[1:-1]] + [STOP]


def test_feature_agent_oscillation_stops(panos):
    views = render(panos[PANOS[0]], [(5, 30), (5, 33)])  # the votes say RIGHT
    agent = make_agent("orb", None, 1, "cpu", 0)
    agent.reset([0], [ep()])
    agent.states[0].history.extend([LEFT, RIGHT, LEFT])  # the last three actions alternated
    assert int(agent.act(obs_of(views[:1], views[1:]))[0]) == STOP
    agent.reset([0], [ep()])
    agent.states[0].history.extend([RIGHT, RIGHT, RIGHT])
    assert int(agent.act(obs_of(views[:1], views[1:]))[0]) == RIGHT


@pytest.mark.parametrize("kind", ["orb", "sift"])
def test_feature_agent_flat_image_repeats_previous(panos, kind):
    grey = torch.full((1, 3, H, W), 128, dtype=torch.uint8)
    real = render(panos[PANOS[0]], [(5, 30)])
    agent = make_agent(kind, None, 1, "cpu", 3)
    agent.reset([0], [ep()])
    first = [int(agent.act(obs_of(grey, real))[0]) for _ in range(3)]
    assert first[0] in (LEFT, RIGHT) and first == [first[0]] * 3  # seeded left/right, then repeated
    agent.reset([0], [ep()])
    agent.states[0].prev = UP
    assert int(agent.act(obs_of(real, grey))[0]) == UP  # flat target: repeat the previous action
    # the seeded initial direction is a function of (seed, episode)
    agent2 = make_agent(kind, None, 1, "cpu", 3)
    agent2.reset([0], [ep()])
    assert int(agent2.act(obs_of(grey, real))[0]) == first[0]


def test_d_thresh_per_difficulty_drops_votes(panos):
    views = render(panos[PANOS[0]], [(5, 30), (5, 35)])
    # d_thresh 0 on hard keeps no match (distances > 0) -> repeat the previous action
    agent = make_agent("orb", agent_cfg("orb", d_thresh={"easy": math.inf, "hard": 0}), 1, "cpu", 0)
    agent.reset([0], [ep(difficulty="hard")])
    agent.states[0].prev = DOWN
    assert int(agent.act(obs_of(views[:1], views[1:]))[0]) == DOWN
    agent.reset([0], [ep(difficulty="easy")])
    assert int(agent.act(obs_of(views[:1], views[1:]))[0]) == RIGHT


# ------------------------------------------------------------------------------------------------
# rotation agent
# ------------------------------------------------------------------------------------------------
def _rx(a: float) -> np.ndarray:
    c, s = math.cos(math.radians(a)), math.sin(math.radians(a))
    return np.array([[1, 0, 0], [0, c, s], [0, -s, c]])


def _ry(a: float) -> np.ndarray:
    c, s = math.cos(math.radians(a)), math.sin(math.radians(a))
    return np.array([[c, 0, s], [0, 1, 0], [-s, 0, c]])


@pytest.mark.parametrize("pc,dyaw,pt", [(7, 10, 7), (-20, -35, 15), (40, 120, -30), (0, 0, 12), (10, -170, 55)])
def test_decompose_relative_rotation(pc, dyaw, pt):
    r = _rx(-pc) @ _ry(dyaw) @ _rx(pt)
    dp, dy, ec, et = decompose_relative_rotation(r)
    assert dp == pytest.approx(pt - pc, abs=1e-9) and dy == pytest.approx(dyaw, abs=1e-9)
    if dyaw != 0:
        assert ec == pytest.approx(pc, abs=1e-6) and et == pytest.approx(pt, abs=1e-6)


def test_kabsch_recovers_rotation():
    rng = np.random.default_rng(0)
    r = _rx(-12) @ _ry(33) @ _rx(5)
    src = rng.normal(size=(20, 3))
    src /= np.linalg.norm(src, axis=1, keepdims=True)
    assert np.allclose(kabsch(src, src @ r.T), r, atol=1e-9)


@pytest.mark.parametrize("dp,dy", [(0, 10), (8, -15), (-20, 30)])
def test_rotation_estimate_accuracy(panos, dp, dy):
    base = (5, 30)
    views = render(panos[PANOS[1]], [base, (base[0] + dp, base[1] + dy)])
    g = rgb_to_gray(views)
    est = estimate_from_images(g[0], g[1], FOV)
    assert est.valid
    assert abs(est.dpitch - dp) <= 1.0 and abs(est.dyaw - dy) <= 1.0
    assert est.rounded() == (dp, dy)
    if dy != 0:
        assert abs(est.pitch_current - base[0]) <= 1.5  # the absolute pitch is observable too


def test_rotation_agent_walks_straight_and_stops(panos):
    e = ep((5, 30), (-3, 41))
    env = TinyEnv(panos[PANOS[1]], e)
    agent = make_agent("rotation", None, 1, "cpu", 0)
    agent.reset([0], [e])
    for _ in range(200):
        if env.step(int(agent.act(env.obs())[0])):
            break
    assert env.eps() == 0
    assert env.steps == l1_distance(5, 30, -3, 41) + 1  # shortest path: SPL 1


def test_rotation_agent_finds_a_motion_blurred_target_at_half_size(panos):
    """Motion blur (severity 3) leaves a target few full-size keypoints that match; the agent then looks
    again at half size, where they do, and heads for the target (15 degrees up) at once instead of
    starting its search (a yaw sweep). Four blur directions; on this panorama the full-size estimate
    alone finds nothing in any of them."""
    from findview.corruptions import corrupt

    equi = panos[PANOS[1]]
    e = ep((0, 30), (15, 40))
    view = render(equi, [(0, 30)])
    from findview_baselines.config import RotationAgentConfig

    firsts, full_size_only = [], []
    for seed in range(4):
        target = corrupt(render(equi, [(15, 40)]), "motion_blur", 3, generator=torch.Generator().manual_seed(seed))
        for cfg, out in ((None, firsts), (RotationAgentConfig(search_scale=1.0), full_size_only)):
            agent = make_agent("rotation", cfg, 1, "cpu", 0)
            agent.reset([0], [e])
            out.append(int(agent.act(obs_of(view, target))[0]))
    assert firsts.count(UP) >= 3, firsts
    # the control: without the half-size look (search_scale 1) the first look finds nothing to head for
    assert full_size_only.count(UP) <= 1, full_size_only


def test_view_cache_computes_each_view_once():
    """The cache gives back what was computed for a view with the same shape, dtype and bytes (another array
    object included), computes each view once, drops the least recently used view beyond its capacity, and
    with capacity 0 computes every time."""
    gen = np.random.default_rng(0)
    views = [gen.integers(0, 256, (3, 8, 8), dtype=np.uint8) for _ in range(3)]
    calls: list[int] = []

    def compute(i: int):
        calls.append(i)
        return ("value", i)

    cache = ViewCache(2)
    assert cache.get(views[0], lambda: compute(0)) == ("value", 0)
    assert cache.get(views[0].copy(), lambda: compute(99)) == ("value", 0)  # the bytes are the key, not the object
    assert calls == [0] and cache.hits == 1
    cache.get(views[1], lambda: compute(1))
    cache.get(views[0], lambda: compute(0))  # a hit: view 0 is now the most recently used
    cache.get(views[2], lambda: compute(2))  # evicts view 1
    cache.get(views[1], lambda: compute(1))
    assert calls == [0, 1, 2, 1] and len(cache) == 2 and cache.hits == 2
    # the same bytes in another shape or dtype are another view
    cache = ViewCache(4)
    cache.get(views[0], lambda: compute(10))
    cache.get(views[0].reshape(3, -1), lambda: compute(11))
    cache.get(views[0].view(np.int8), lambda: compute(12))
    assert calls[-3:] == [10, 11, 12] and cache.hits == 0
    off = ViewCache(0)
    off.get(views[0], lambda: compute(20))
    off.get(views[0], lambda: compute(21))
    assert calls[-2:] == [20, 21] and len(off) == 0


def test_sift_circling_with_the_view_cache_acts_as_without_it(panos):
    """A sift slot whose target is from another panorama finds no match and repeats its move: it circles and
    sees the same views again after a turn. With the cache those views are not detected and matched again
    (hits), and the actions are the ones of the agent without the cache."""
    target = render(panos[PANOS[0]], [(10, 50)], h=128, w=128)
    view_at = pose_views(panos[PANOS[1]])

    runs = []
    for cache_views in (400, 0):
        agent = make_agent("sift", agent_cfg("sift", cache_views=cache_views), 1, "cpu", 0)
        agent.reset([0], [ep((0, 0), (10, 50))])
        p, y, actions = 0, 0, []
        for _ in range(380):
            a = int(agent.act(obs_of(view_at(p, y), target))[0])
            actions.append(a)
            if a == STOP:
                break
            p = int(np.clip(p + (a == UP) - (a == DOWN), -60, 60))
            y = int(wrap_yaw(y + (a == RIGHT) - (a == LEFT)))
        runs.append((actions, agent.slots[0].views.hits))
    (cached, hits), (plain, no_hits) = runs
    assert cached == plain and len(cached) == 380
    assert hits >= 10 and no_hits == 0


def test_orb_view_cache_replays_real_votes_across_episodes(panos):
    """Scripted back-and-forth sweeps past targets in view (the poses do not follow the actions, so views
    repeat while the rule votes moves and STOP): two slots, two episodes with other targets and difficulties
    (a per-difficulty ``d_thresh``). With the cache the actions are those without it, the cache has hits, and
    it starts empty for each new episode (a cached vote is only valid for its own target)."""
    at = [pose_views(panos[PANOS[0]]), pose_views(panos[PANOS[1]])]
    sweep = [(0, y) for y in [*range(0, 10), *range(10, -1, -1)]] * 2
    episodes = [((0, 6), "easy", (0, 3), "hard"), ((0, 2), "medium", (0, 8), "easy")]
    runs = []
    for cache_views in (400, 0):
        agent = make_agent("orb", agent_cfg("orb", cache_views=cache_views,
                                            d_thresh={"easy": 40.0, "medium": 30.0, "hard": float("inf")}), 2, "cpu", 0)
        actions, hits = [], []
        for n, (t0, d0, t1, d1) in enumerate(episodes):
            agent.reset([0, 1], [ep((0, 0), t0, d0, f"a{n}"), ep((0, 0), t1, d1, f"b{n}")])
            assert all(len(s.views) == 0 for s in agent.slots)
            target = torch.cat([at[0](*t0), at[1](*t1)])
            for p, y in sweep:
                actions.append(agent.act(obs_of(torch.cat([at[0](p, y), at[1](p, y)]), target)).tolist())
                for s in agent.slots:  # keep both slots acting after a STOP: the sweep is scripted
                    s.done = False
            hits.append(sum(s.views.hits for s in agent.slots))
        runs.append((actions, hits))
    (cached, hits), (plain, no_hits) = runs
    assert cached == plain
    assert all(h >= 10 for h in hits) and no_hits == [0, 0]
    taken = {a for step in cached for a in step}
    assert STOP in taken and len(taken - {STOP}) >= 2  # real votes: STOP and moves


def test_rotation_agent_identical_and_flat(panos):
    view = render(panos[PANOS[0]], [(5, 30)])
    grey = torch.full((1, 3, H, W), 128, dtype=torch.uint8)
    agent = make_agent("rotation", None, 2, "cpu", 0)
    agent.reset([0, 1], [ep(eid="a"), ep(eid="b")])
    obs = obs_of(torch.cat([view, grey]), torch.cat([view, view]))
    first = agent.act(obs).tolist()
    assert first[0] == STOP
    assert first[1] in (LEFT, RIGHT)  # nothing to match: sweep the yaw in one direction
    sweep = [int(agent.act(obs)[1]) for _ in range(20)]
    assert sweep == [first[1]] * 20


def _play(env: TinyEnv, agent, max_steps: int, each=None) -> bool:
    """Run one episode of ``agent`` (slot 0) in ``env``; returns whether it called STOP."""
    for _ in range(max_steps):
        a = int(agent.act(env.obs())[0])
        if each is not None:
            each(a)
        if env.step(a):
            return True
    return False


def _blur_noise_brighten(img: torch.Tensor) -> torch.Tensor:
    """Gaussian blur (sigma 1.5 px), Gaussian noise (std 12 levels) and +35 brightness, plain torch ops."""
    x = img.float()
    k = torch.exp(-0.5 * (torch.arange(-4, 5, dtype=torch.float32) / 1.5) ** 2)
    k = k / k.sum()
    x = torch.nn.functional.pad(x, (4, 4, 4, 4), mode="replicate")
    x = torch.nn.functional.conv2d(x, k.view(1, 1, 1, 9).expand(3, 1, 1, 9), groups=3)
    x = torch.nn.functional.conv2d(x, k.view(1, 1, 9, 1).expand(3, 1, 9, 1), groups=3)
    g = torch.Generator().manual_seed(0)
    x = x + 12.0 * torch.randn(x.shape, generator=g) + 35.0
    return x.round().clamp(0, 255).to(torch.uint8)


def test_photometric_check(panos):
    views = render(panos[PANOS[0]], [(5, 30), (5, 150)])
    t = [photometric_template(v.numpy()) for v in views]
    assert photometric_score(t[0], t[0]) == pytest.approx(1.0, abs=1e-5)  # the definition
    bad = _blur_noise_brighten(views[:1])[0].numpy()
    assert photometric_score(t[0], photometric_template(bad)) > 0.85
    assert photometric_score(t[0], t[1]) < 0.5  # another part of the room
    assert not photometric_template(np.full((3, 32, 32), 77, np.uint8)).any()  # flat: no structure
    assert np.allclose(mean_chromaticity(np.full((3, 4, 4), 77, np.uint8)), 1 / 3)
    # the agent's check: the corrupted view passes, the same wall in another colour does not
    walls = render(two_walls_panorama(), [(0, 90), (0, -90)])
    agent = make_agent("rotation", None, 1, "cpu", 0)
    agent.reset([0], [ep()])
    s = agent.slots[0]
    s.target = agent.prepare_target(s, views[0].numpy())
    assert agent.verify(s, bad)[0] and not agent.verify(s, views[1].numpy())[0]
    s.target = agent.prepare_target(s, walls[0].numpy())
    assert agent.verify(s, walls[0].numpy()) == (True, pytest.approx(1.0, abs=1e-5))
    assert not agent.verify(s, walls[1].numpy())[0]


def two_walls_panorama() -> torch.Tensor:
    """A 1024x512 panorama: a smooth grey surround and two walls with the same dark letters and shapes,
    one red (centred at yaw +90, on the horizon), one blue (yaw -90)."""
    h, w = 512, 1024
    yy, xx = np.mgrid[0:h, 0:w]
    pano = np.stack([100 + 40 * yy / h, 110 + 0 * xx, 120 - 30 * yy / h], axis=-1).astype(np.uint8)
    rng = np.random.default_rng(3)
    patch = np.zeros((180, 220), np.uint8)  # 1 where the pattern is dark
    letters = "FINDVIEWQRST2468"
    for k in range(14):
        org = (int(rng.integers(5, 180)), int(rng.integers(25, 175)))
        cv2.putText(patch, letters[k % len(letters)], org, cv2.FONT_HERSHEY_SIMPLEX, 1.2, 1, 3)
    for _ in range(6):
        cv2.circle(patch, (int(rng.integers(10, 210)), int(rng.integers(10, 170))), int(rng.integers(4, 12)), 1, -1)
    for centre_u, colour in ((768, (220, 40, 40)), (256, (40, 40, 220))):
        top, left = h // 2 - 90, centre_u - 110
        wall = np.empty((180, 220, 3), np.uint8)
        wall[:] = colour
        wall[patch > 0] = (10, 10, 10)
        pano[top : top + 180, left : left + 220] = wall
    return torch.from_numpy(pano).permute(2, 0, 1)[None].contiguous()


def test_rotation_agent_rejects_the_wrong_wall():
    equi = two_walls_panorama()
    e = ep((0, -75), (0, 90), difficulty="hard")  # the blue wall in view, the red one is the target
    env = TinyEnv(equi, e)
    agent = make_agent("rotation", None, 1, "cpu", 0)
    agent.reset([0], [e])
    assert _play(env, agent, 1500)
    assert env.eps() == 0
    rejected = agent.slots[0].rejected
    # the blue wall was a candidate and was rejected once (then never revisited)
    assert len(rejected) == 1
    p, y, score = rejected[0]
    assert (p + e.init_pitch, wrap_yaw(y + e.init_yaw)) == (0, -90) and score < agent.verify_thresh


def test_rotation_agent_corrupted_target(panos):
    e = ep((5, 30), (-8, 72), difficulty="medium")
    env = TinyEnv(panos[PANOS[1]], e, corrupt=_blur_noise_brighten)
    agent = make_agent("rotation", None, 1, "cpu", 0)
    agent.reset([0], [e])
    assert _play(env, agent, 400)
    assert env.eps() == 0
    # no view equals a corrupted target: the stop came from the colour check
    assert not torch.equal(env.obs()["view"], env.target)


def test_rotation_refine_climbs_to_the_best_pose():
    """The one-degree refinement on a toy world where a pose (p, y) sees a crop shifted by 2 px per
    degree, and the target (pose (0, 0)) is noisy: from (1, -1) it must climb to (0, 0) and stop."""
    rng = np.random.default_rng(0)
    world = cv2.GaussianBlur(rng.integers(0, 256, (160, 160, 3)).astype(np.uint8), (0, 0), 2.0)

    def view_at(p: int, y: int) -> np.ndarray:
        r, c = 48 - 2 * p, 48 + 2 * y
        return np.ascontiguousarray(world[r : r + 64, c : c + 64].transpose(2, 0, 1))

    noisy = view_at(0, 0).astype(np.int16) + rng.integers(-20, 21, (3, 64, 64))
    agent = make_agent("rotation", None, 1, "cpu", 0)
    agent.reset([0], [ep()])
    s = agent.slots[0]
    s.target = agent.prepare_target(s, noisy.clip(0, 255).astype(np.uint8))
    s.pose_p, s.pose_y, s.mode = 1, -1, "refine"
    for _ in range(30):
        a = agent.step(0, s, view_at(s.pose_p, s.pose_y))
        if a == STOP:
            break
    assert a == STOP and (s.pose_p, s.pose_y) == (0, 0)
    assert len(s.scores) <= 9  # each pose scored once, only around the path


def test_rotation_agent_far_target_and_the_pitch_bound(sun360_mini_files):
    """The target is far from the start (no overlap, first search row too high); the start is near the
    top bound and the search runs into the clamp: the agent's dead reckoning must keep its pitch, and
    the search must find the target within its rows (a bounded number of steps)."""
    image = str({f.name: f for f in sun360_mini_files}[PANOS[1]])
    e = Episode("far", image, 55, 10, -45, -150, difficulty="hard", seed=3)
    bank = sim_mod.PanoramaBank("cpu", 256, prefetch_workers=0)
    size = 128  # small views keep the test fast; keypoints at full size
    sim = sim_mod.Simulator(bank, FOV, size, size, pitch_bound=60)
    env = task.FindViewEnv(sim, task.StaticEpisodeSource([e]), 1, max_steps=5000, pitch_bound=60, prefetch=0)
    agent = make_agent("rotation", agent_cfg("rotation", search_scale=1.0), 1, "cpu", 0)
    spacing = agent.row_spacing(size, size)
    bound = 4 * 360 + 2 * 120 + spacing  # four rows and the moves between them
    obs = env.reset()
    agent.reset([0], [e])
    wrong, record = [], None
    try:
        for _ in range(bound):
            a = agent.act(obs)
            # the agent's pitch before the move it just booked (the clamp of its previous move
            # accounted) is the env's pitch relative to the start
            before = agent.slots[0].pose_p - int(a[0] == UP) + int(a[0] == DOWN)
            if before != int(env.pitch[0]) - e.init_pitch:
                wrong.append((int(env.steps[0]), before, int(env.pitch[0])))
            obs, _, _, infos = env.step(a)
            if infos[0] is not None:
                record = infos[0]
                break
    finally:
        env.close()
    assert record is not None and record["called_stop"] and record["eps"] == 0
    assert not wrong
    s = agent.slots[0]
    assert s.hi is not None and s.hi + e.init_pitch == 60  # it ran into the top bound and knows it


# ------------------------------------------------------------------------------------------------
# through the real environment
# ------------------------------------------------------------------------------------------------
ENV_PITCH_BOUND = 30


def _env_run(agent_name: str, episodes: list[Episode], num_envs: int, max_steps: int, cfg=None) -> list[dict]:
    bank = sim_mod.PanoramaBank("cpu", 256, prefetch_workers=0)
    # a small pitch bound keeps the simulator's per-pitch grids cheap; the episodes stay well inside it
    sim = sim_mod.Simulator(bank, FOV, H, W, pitch_bound=ENV_PITCH_BOUND)
    env = task.FindViewEnv(
        sim, task.StaticEpisodeSource(episodes), num_envs, max_steps=max_steps, pitch_bound=ENV_PITCH_BOUND, prefetch=0
    )
    cfg = dict(cfg or {})
    if agent_name in ("oracle", "rotation"):
        cfg["pitch_bound"] = ENV_PITCH_BOUND
    agent = make_agent(agent_name, agent_cfg(agent_name, **cfg), num_envs, "cpu", 0)
    obs = env.reset()
    started = [i for i in range(num_envs) if env.episodes[i] is not None]
    agent.reset(started, [env.episodes[i] for i in started])
    records: list[dict] = []
    try:
        for _ in range(len(episodes) * max_steps + 1):
            if not bool(env.active.any()):
                break
            obs, _, _, infos = env.step(agent.act(obs))
            records += [r for r in infos if r is not None]
            new = [i for i in range(num_envs) if bool(env.new_episode[i])]
            if new:
                agent.reset(new, [env.episodes[i] for i in new])
    finally:
        env.close()
    assert len(records) == len(episodes)
    return records


@pytest.fixture(scope="module")
def env_episodes(sun360_mini_files: list[Path]) -> list[Episode]:
    files = {f.name: str(f) for f in sun360_mini_files}
    return [
        Episode("e0", files[PANOS[0]], 5, 30, 12, 45, difficulty="easy", seed=1),
        Episode("e1", files[PANOS[1]], -10, 170, 0, -165, difficulty="easy", seed=2),
        Episode("e2", files[PANOS[1]], 0, 0, 20, -40, difficulty="medium", seed=3),
    ]


def test_env_oracle(env_episodes):
    from findview.metrics import summarize

    recs = _env_run("oracle", env_episodes, 2, 5000)
    assert all(r["eps"] == 0 and r["called_stop"] and r["steps"] == r["shortest_path"] for r in recs)
    s = summarize(recs)
    assert s["easy"]["spl"] == 1.0 and s["medium"]["spl"] == 1.0


def test_env_orb_and_rotation(env_episodes):
    recs = _env_run("orb", env_episodes[:2], 2, 150)
    for r in recs:
        assert r["called_stop"] or r["steps"] == 150
        assert r["eps"] < l1_distance(r["init_pitch"], r["init_yaw"], r["target_pitch"], r["target_yaw"])
    recs = _env_run("rotation", env_episodes, 2, 300)
    assert all(r["called_stop"] and r["eps"] == 0 for r in recs)
