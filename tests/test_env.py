"""The batched FindView environment: rules and rewards of docs/TASK.md (sections Episodes, Rewards), resets, state."""

from __future__ import annotations

import cv2
import numpy as np
import pytest
import torch

from findview.episode import Episode
from findview.sim import PanoramaBank, Simulator, equi2pers
from findview.task import Action, FindViewEnv, RewardConfig, StaticEpisodeSource

U, D, L, R, S = (int(a) for a in (Action.UP, Action.DOWN, Action.LEFT, Action.RIGHT, Action.STOP))


@pytest.fixture(scope="module")
def panos(tmp_path_factory) -> list[str]:
    """Three random-texture 2:1 panoramas (256x128 PNG)."""
    d = tmp_path_factory.mktemp("panos")
    rng = np.random.default_rng(0)
    paths = []
    for k in range(3):
        small = rng.integers(0, 255, (16, 32, 3), dtype=np.uint8)
        img = cv2.resize(small, (256, 128), interpolation=cv2.INTER_CUBIC)
        p = d / f"p{k}.png"
        cv2.imwrite(str(p), img)
        paths.append(str(p))
    return paths


def make_env(episodes, n=2, device="cpu", **kw) -> FindViewEnv:
    bank = PanoramaBank(device, 64, min_slots=n, prefetch_workers=0)
    sim = Simulator(bank, fov=90, height=24, width=32, pitch_bound=60)
    return FindViewEnv(sim, StaticEpisodeSource(episodes), n, **kw)


def ep(path, i, p0, y0, p1, y1, diff="easy") -> Episode:
    return Episode(f"e{i}", path, p0, y0, p1, y1, difficulty=diff)


def test_moves_clamp_and_wrap(panos):
    env = make_env([ep(panos[0], 0, 59, 179, 0, 0), ep(panos[1], 1, -60, -179, 0, 0)])
    env.reset()
    env.step(torch.tensor([U, D]))
    assert env.pitch.tolist() == [60, -60]  # second move into the bound: no change
    env.step(torch.tensor([U, L]))
    assert env.pitch.tolist() == [60, -60] and env.yaw.tolist() == [179, 180]  # -179 - 1 wraps to 180
    env.step(torch.tensor([R, R]))
    assert env.yaw.tolist() == [180, -179]
    env.step(torch.tensor([R, D]))
    assert env.yaw.tolist() == [-179, -179] and env.steps.tolist() == [4, 4]  # clamped moves cost a step


def test_rewards_and_stop_record(panos):
    cfg = RewardConfig()
    env = make_env([ep(panos[0], 0, 0, 0, 2, 3), ep(panos[1], 1, 0, 0, 0, -1)], auto_reset=False, reward=cfg)
    env.reset()
    _, r, done, infos = env.step(torch.tensor([U, L]))  # both move closer by 1
    assert torch.allclose(r, torch.tensor([0.1 - 0.01, 0.1 - 0.01]))
    assert not done.any()
    _, r, done, infos = env.step(torch.tensor([R, S]))  # env 1 stops at eps 0
    assert done.tolist() == [False, True]
    assert r[1].item() == pytest.approx(100 / (0 + 10) + 0 - 0.01)
    rec = infos[1]
    assert rec["called_stop"] and rec["eps"] == 0 and rec["steps"] == 2 and rec["shortest_path"] == 2
    assert (rec["final_pitch"], rec["final_yaw"]) == (0, -1)


def test_stepping_a_finished_episode_is_an_error(panos):
    env = make_env([ep(panos[0], 0, 0, 0, 0, 5), ep(panos[1], 1, 0, 0, 0, 5)], auto_reset=False)
    env.reset()
    env.step(torch.tensor([S, R]))
    with pytest.raises(RuntimeError, match=r"reset_envs\(\[0\]\)"):
        env.step(torch.tensor([R, R]))


def test_forced_stop_and_stop_reward(panos):
    env = make_env([ep(panos[0], 0, 0, 0, 0, 20)], n=1, max_steps=3, auto_reset=False)
    env.reset()
    env.step(torch.tensor([R]))
    env.step(torch.tensor([R]))
    _, r, done, infos = env.step(torch.tensor([L]))  # third step hits T without stop
    assert done.item() and not infos[0]["called_stop"] and infos[0]["steps"] == 3 and infos[0]["eps"] == 19
    assert r.item() == pytest.approx(-100 + 0.1 * (18 - 19) - 0.01)


def test_stop_on_last_allowed_step_counts_as_called(panos):
    env = make_env([ep(panos[0], 0, 0, 0, 0, 2)], n=1, max_steps=3, auto_reset=False)
    env.reset()
    env.step(torch.tensor([R]))
    env.step(torch.tensor([R]))
    _, r, done, infos = env.step(torch.tensor([S]))
    assert infos[0]["called_stop"] and infos[0]["eps"] == 0 and infos[0]["steps"] == 3
    assert r.item() == pytest.approx(10 - 0.01)


def test_views_match_direct_render_and_target_is_fixed(panos):
    env = make_env([ep(panos[2], 0, 10, 170, -5, -175)], n=1)
    obs = env.reset()
    target0 = obs["target"].clone()
    equi = torch.from_numpy(cv2.cvtColor(cv2.imread(panos[2]), cv2.COLOR_BGR2RGB)).permute(2, 0, 1)[None]
    for a, (p, y) in [(U, (11, 170)), (R, (11, 171)), (R, (11, 172)), (D, (10, 172))]:
        obs, *_ = env.step(torch.tensor([a]))
        ref = equi2pers(equi, float(p), float(y), 90, 24, 32, backend="torch")
        assert (obs["view"].int() - ref.int()).abs().max() <= 2
        assert torch.equal(obs["target"], target0)
    ref_t = equi2pers(equi, -5.0, -175.0, 90, 24, 32, backend="torch")
    assert (target0.int() - ref_t.int()).abs().max() <= 2


def test_auto_reset_and_exhaustion(panos):
    eps_ = [ep(panos[k % 3], k, 0, 0, 0, 12) for k in range(3)]
    env = make_env(eps_, n=2)
    env.reset()
    assert env.new_episode.tolist() == [True, True]
    _, _, done, infos = env.step(torch.tensor([S, R]))
    assert done.tolist() == [True, False] and env.new_episode.tolist() == [True, False]
    assert env.episodes[0].episode_id == "e2" and env.steps.tolist() == [0, 1]
    _, _, done, _ = env.step(torch.tensor([S, S]))
    assert done.tolist() == [True, True] and env.active.tolist() == [False, False]  # source exhausted
    _, r, done, infos = env.step(torch.tensor([R, R]))  # inactive slots ignore actions
    assert not done.any() and r.abs().sum() == 0 and infos == [None, None]


def test_bad_actions(panos):
    env = make_env([ep(panos[0], 0, 0, 0, 0, 12)], n=1)
    env.reset()
    with pytest.raises(ValueError, match="actions"):
        env.step(torch.tensor([5]))
    with pytest.raises(ValueError, match="expected 1 actions"):
        env.step(torch.tensor([0, 1]))


def test_state_dict_roundtrip(panos):
    eps_ = [ep(panos[k % 3], k, k, -k, 0, 30) for k in range(6)]
    a = make_env(eps_, n=2)
    a.reset()
    for act in [R, U, R]:
        a.step(torch.tensor([act, act]))
    state = a.state_dict()
    b = make_env(eps_, n=2)
    obs_b = b.load_state_dict(state)
    assert torch.equal(obs_b["view"], a.view) and torch.equal(obs_b["target"], a.target)
    for act in [S, L, R, S]:
        oa, ra, da, ia = a.step(torch.tensor([act, R]))
        ob, rb, db, ib = b.step(torch.tensor([act, R]))
        assert torch.equal(ra, rb) and torch.equal(da, db) and ia == ib and torch.equal(oa["view"], ob["view"])


@pytest.mark.skipif(not torch.cuda.is_available(), reason="no CUDA device")
def test_cuda_matches_cpu(panos):  # pragma: no cover - runs only with a GPU
    eps_ = [ep(panos[k % 3], k, 0, 170, 5, -170) for k in range(2)]
    a, b = make_env(eps_, n=2), make_env(eps_, n=2, device="cuda")
    a.reset(), b.reset()
    for act in [R, R, U, S]:
        oa, ra, *_ = a.step(torch.tensor([act, act]))
        ob, rb, *_ = b.step(torch.tensor([act, act], device="cuda"))
        assert torch.allclose(ra, rb.cpu()) and (oa["view"].int() - ob["view"].cpu().int()).abs().max() <= 2


def test_gym_wrapper(panos):
    pytest.importorskip("gymnasium")
    from findview.task.gym_env import FindViewGymEnv

    bank = PanoramaBank("cpu", 16, prefetch_workers=0)
    sim = Simulator(bank, fov=90, height=24, width=32)
    env = FindViewGymEnv(sim, episodes=[ep(panos[0], 0, 0, 0, 1, 0)], max_steps=10)
    obs, info = env.reset(seed=0)
    assert env.observation_space.contains(obs) and env.action_space.n == 5
    obs, r, term, trunc, info = env.step(U)
    assert (term, trunc) == (False, False) and r == pytest.approx(0.1 - 0.01)
    obs, r, term, trunc, info = env.step(S)
    assert term and not trunc and info["eps"] == 0 and r == pytest.approx(10 - 0.01)
    with pytest.raises(RuntimeError, match="reset"):
        env.step(U)
