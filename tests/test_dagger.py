"""Privileged oracle labels (findview.task.oracle) and the DAgger trainer (findview_baselines.rl.dagger)."""

from __future__ import annotations

import io
from types import SimpleNamespace

import cv2
import numpy as np
import pytest
import torch

from _training import write_panoramas
from findview.config import ConfigError
from findview.dataset import EpisodeSampler, ImageEntry
from findview.geometry import l1_distance, wrap_yaw
from findview.sim import PanoramaBank, Simulator
from findview.task import Action, FindViewEnv, StaticEpisodeSource
from findview.task.oracle import (
    optimal_action_mask,
    optimal_action_mask_for,
    oracle_actions,
    oracle_actions_for,
    overlap_mask,
    pan_action_mask,
    pan_actions,
    rotation_labels,
    rotation_targets,
    sweep_action_mask,
    sweep_actions,
)
from findview.task.sources import SampledEpisodeSource
from findview_baselines.rl.dagger import DAggerConfig, DAggerTrainer, SequenceBuffer, beta_at, set_nll
from findview_baselines.rl.policy import Policy
from findview_baselines.rl.ppo_trainer import UpdateAbandoned
from findview_baselines.rl.scheduler import DifficultyScheduler
from findview_baselines.rl.search_memory import MEMORY_FEATURES

UP, DOWN, LEFT, RIGHT, STOP = (int(a) for a in (Action.UP, Action.DOWN, Action.LEFT, Action.RIGHT, Action.STOP))


pytestmark = pytest.mark.usefixtures("one_torch_thread")


def t(*values: int) -> torch.Tensor:
    return torch.tensor(values, dtype=torch.long)


# --------------------------------------------------------------------------------------------------
# Oracle labels, hand-computed
# --------------------------------------------------------------------------------------------------


def test_oracle_single_axis_moves_and_stop() -> None:
    # from (0, 0) to: above, below, right, left, here
    actions = oracle_actions(t(0, 0, 0, 0, 0), t(0, 0, 0, 0, 0), t(5, -3, 0, 0, 0), t(0, 0, 10, -10, 0))
    assert actions.tolist() == [UP, DOWN, RIGHT, LEFT, STOP]
    assert actions.dtype == torch.long


def test_oracle_takes_the_short_way_round_and_pans_right_at_180() -> None:
    # 170 -> -170 is 20 degrees to the right; -170 -> 170 is 20 to the left; 0 -> 180 and 90 -> -90 are
    # exactly 180 apart (documented: RIGHT)
    actions = oracle_actions(t(0, 0, 0, 0), t(170, -170, 0, 90), t(0, 0, 0, 0), t(-170, 170, 180, -90))
    assert actions.tolist() == [RIGHT, LEFT, RIGHT, RIGHT]


def test_oracle_orders() -> None:
    args = (t(0, 0, 0), t(0, 0, 0), t(5, 5, 12), t(10, -5, 3))  # (5, +10), (5, -5) tie, (12, +3)
    assert oracle_actions(*args, order="pitch_first").tolist() == [UP, UP, UP]
    assert oracle_actions(*args, order="yaw_first").tolist() == [RIGHT, LEFT, RIGHT]
    assert oracle_actions(*args, order="larger_first").tolist() == [RIGHT, UP, UP]
    with pytest.raises(ValueError, match="order"):
        oracle_actions(*args, order="diagonal")


def test_oracle_with_coarse_steps_stops_below_one_step() -> None:
    # step_deg 2: a remaining 1 degree cannot be reduced, 2 can
    actions = oracle_actions(t(0, 0, 0), t(0, 0, 0), t(1, 2, 0), t(1, 0, -2), step_deg=2)
    assert actions.tolist() == [STOP, UP, LEFT]


def walk(actions_fn, pitch: torch.Tensor, yaw: torch.Tensor, tp: torch.Tensor, ty: torch.Tensor, steps: int):
    """Apply ``actions_fn`` with the environment's rules (1-degree steps, pitch clamp 60, yaw wrap) until
    every env stopped; returns the number of moves each made before its STOP (-1 if it never stopped)."""
    n = pitch.shape[0]
    moves = torch.full((n,), -1, dtype=torch.long)
    for k in range(steps):
        a = actions_fn(pitch, yaw, tp, ty)
        newly = (a == STOP) & (moves < 0)
        moves[newly] = k
        run = moves < 0
        pitch = (pitch + ((a == UP).long() - (a == DOWN).long()) * run).clamp(-60, 60)
        yaw = wrap_yaw(yaw + ((a == RIGHT).long() - (a == LEFT).long()) * run)
        if bool((moves >= 0).all()):
            break
    return moves, pitch, yaw


def test_following_the_oracle_walks_a_shortest_path() -> None:
    g = torch.Generator().manual_seed(0)
    n = 200
    p0, tp = torch.randint(-60, 61, (n,), generator=g), torch.randint(-60, 61, (n,), generator=g)
    y0, ty = torch.randint(-179, 181, (n,), generator=g), torch.randint(-179, 181, (n,), generator=g)
    for order in ("pitch_first", "yaw_first", "larger_first"):
        moves, pitch, yaw = walk(lambda *s: oracle_actions(*s, order=order), p0, y0, tp, ty, 400)
        assert torch.equal(moves, l1_distance(p0, y0, tp, ty))  # exactly |dpitch| + dyaw moves, then STOP
        assert torch.equal(pitch, tp) and torch.equal(yaw, ty)


def test_optimal_action_sets() -> None:
    # (+5 up, +10 right): UP or RIGHT; here: STOP; exactly 180 apart: LEFT or RIGHT; (-3 down, 20 left)
    mask = optimal_action_mask(t(0, 0, 0, 3), t(0, 0, 90, 0), t(5, 0, 0, 0), t(10, 0, -90, -20))
    assert mask.int().tolist() == [[1, 0, 0, 1, 0], [0, 0, 0, 0, 1], [0, 0, 1, 1, 0], [0, 1, 1, 0, 0]]
    # sweep: no overlap (150 left, 5 up) -> UP or RIGHT; overlapping 30 left -> LEFT
    mask = sweep_action_mask(t(0, 0), t(0, 0), t(5, 0), t(-150, -30), fov=90)
    assert mask.int().tolist() == [[1, 0, 0, 1, 0], [0, 0, 1, 0, 0]]
    env = SimpleNamespace(pitch=t(0), yaw=t(0), target_pitch=t(0), target_yaw=t(-150), step_deg=1,
                          sim=SimpleNamespace(fov=90.0))
    assert optimal_action_mask_for(env).int().tolist() == [[0, 0, 1, 0, 0]]
    assert optimal_action_mask_for(env, search="sweep").int().tolist() == [[0, 0, 0, 1, 0]]


def test_any_action_of_the_set_walks_a_shortest_path() -> None:
    g = torch.Generator().manual_seed(2)
    n = 200
    p0, tp = torch.randint(-60, 61, (n,), generator=g), torch.randint(-60, 61, (n,), generator=g)
    y0, ty = torch.randint(-179, 181, (n,), generator=g), torch.randint(-179, 181, (n,), generator=g)

    def random_member(*state: torch.Tensor) -> torch.Tensor:
        mask = optimal_action_mask(*state)
        return torch.multinomial(mask.float(), 1, generator=g).squeeze(1)

    moves, pitch, yaw = walk(random_member, p0, y0, tp, ty, 400)
    assert torch.equal(moves, l1_distance(p0, y0, tp, ty))
    assert torch.equal(pitch, tp) and torch.equal(yaw, ty)


def test_set_nll_by_hand() -> None:
    logits = torch.log(torch.tensor([[0.1, 0.2, 0.3, 0.3, 0.1], [0.1, 0.2, 0.3, 0.3, 0.1]]))
    accepted = torch.tensor([[1, 0, 0, 1, 0], [0, 0, 0, 0, 1]], dtype=torch.bool)
    # -log(0.1 + 0.3) and -log(0.1)
    expected = torch.tensor([-np.log(0.4), -np.log(0.1)])
    assert set_nll(logits, accepted).item() == pytest.approx(expected.mean().item(), rel=1e-5)
    weights = torch.tensor([1.0, 1.0, 1.0, 1.0, 3.0])  # stop weighs 3
    assert set_nll(logits, accepted, weights).item() == pytest.approx(
        (expected[0] + 3 * expected[1]).item() / 4, rel=1e-5
    )
    # row weights (search_weight on no-overlap rows) multiply the class weights
    rows = torch.tensor([0.5, 1.0])
    assert set_nll(logits, accepted, weights, rows).item() == pytest.approx(
        (0.5 * expected[0] + 3 * expected[1]).item() / 3.5, rel=1e-5
    )
    assert set_nll(logits, accepted, None, rows).item() == pytest.approx(
        (0.5 * expected[0] + expected[1]).item() / 1.5, rel=1e-5
    )
    # a one-action set is the cross-entropy
    one_hot = torch.nn.functional.one_hot(torch.tensor([2, 4]), 5).bool()
    expected_ce = torch.nn.functional.cross_entropy(logits, torch.tensor([2, 4]))
    torch.testing.assert_close(set_nll(logits, one_hot), expected_ce)


def test_overlap_and_rotation_targets() -> None:
    # fov 90: (+30 up, 45 left) overlaps; 120 right does not; 100 up does not; exactly 90 right does
    args = (t(0, 0, -50, 0), t(0, 0, 0, 10), t(30, 0, 50, 0), t(-45, 120, 0, 100))
    assert overlap_mask(*args, fov=90).tolist() == [True, False, False, True]
    labels = rotation_targets(*args, fov=90)
    assert labels.dtype == torch.float32 and labels.shape == (4, 3)
    expected = torch.tensor([[30 / 90, -45 / 90, 1.0], [0.0, 120 / 90, 0.0], [100 / 90, 0.0, 0.0], [0.0, 1.0, 1.0]])
    torch.testing.assert_close(labels, expected)


def test_sweep_prior_matches_pitch_then_pans_right() -> None:
    # no overlap: 10 below and 150 left -> DOWN; level and 150 left -> RIGHT (not the oracle's LEFT);
    # overlapping 30 left -> LEFT like the oracle; on target -> STOP
    args = (t(10, 0, 0, 5), t(0, 0, 0, 5), t(0, 0, 0, 5), t(-150, -150, -30, 5))
    assert sweep_actions(*args, fov=90).tolist() == [DOWN, RIGHT, LEFT, STOP]
    assert oracle_actions(*args).tolist() == [DOWN, LEFT, LEFT, STOP]


def test_sweep_prior_always_reaches_the_target_without_looping() -> None:
    g = torch.Generator().manual_seed(1)
    n = 300
    p0, tp = torch.randint(-60, 61, (n,), generator=g), torch.randint(-60, 61, (n,), generator=g)
    y0, ty = torch.randint(-179, 181, (n,), generator=g), torch.randint(-179, 181, (n,), generator=g)
    moves, pitch, yaw = walk(lambda *s: sweep_actions(*s, fov=90), p0, y0, tp, ty, 800)
    assert (moves >= 0).all() and torch.equal(pitch, tp) and torch.equal(yaw, ty)
    # at most the pitch distance plus one right turn short of an overlap, plus the final approach
    assert (moves <= (tp - p0).abs() + 360).all()
    assert (moves >= l1_distance(p0, y0, tp, ty)).all()


def test_pan_prior_pans_right_at_the_current_pitch_until_the_views_overlap() -> None:
    # no overlap: 10 below and 150 left -> RIGHT (not the sweep's DOWN); 100 above, level -> UP (no pan
    # reaches an overlap); overlapping 30 left -> LEFT like the oracle; on target -> STOP
    args = (t(10, -50, 0, 5), t(0, 0, 0, 5), t(0, 50, 0, 5), t(-150, 0, -30, 5))
    assert pan_actions(*args, fov=90).tolist() == [RIGHT, UP, LEFT, STOP]
    mask = pan_action_mask(*args, fov=90).int().tolist()
    assert mask == [[0, 0, 0, 1, 0], [1, 0, 0, 0, 0], [0, 0, 1, 0, 0], [0, 0, 0, 0, 1]]
    # the border with the oracle is no trap: 90 left (overlap) -> LEFT, 91 left -> RIGHT (away)
    assert pan_actions(t(0, 0), t(0, 0), t(0, 0), t(-90, -91), fov=90).tolist() == [LEFT, RIGHT]


def test_pan_prior_always_reaches_the_target_without_looping() -> None:
    g = torch.Generator().manual_seed(3)
    n = 300
    p0, tp = torch.randint(-60, 61, (n,), generator=g), torch.randint(-60, 61, (n,), generator=g)
    y0, ty = torch.randint(-179, 181, (n,), generator=g), torch.randint(-179, 181, (n,), generator=g)
    moves, pitch, yaw = walk(lambda *s: pan_actions(*s, fov=90), p0, y0, tp, ty, 800)
    assert (moves >= 0).all() and torch.equal(pitch, tp) and torch.equal(yaw, ty)
    # a no-overlap start pans right at most 360 - 2 * 90 + 1 degrees before the views overlap, then the
    # shortest path from there (at most |dpitch| + 90)
    assert (moves <= (tp - p0).abs() + 181 + 90).all()
    assert (moves >= l1_distance(p0, y0, tp, ty)).all()
    overlapping = overlap_mask(p0, y0, tp, ty, fov=90)
    assert torch.equal(moves[overlapping], l1_distance(p0, y0, tp, ty)[overlapping])


def test_pan_prior_pitch_band_moves_the_pitch_first_when_the_target_is_far_above_or_below() -> None:
    # FoV 60, target 150 to the left: 40 above -> UP with band 0.5 (40 > 30), RIGHT with band 1 (40 <= 60);
    # 25 below -> RIGHT either way (25 <= 30); 40 above but overlapping (20 left) -> the oracle's move
    args = (t(0, 0, 0), t(0, 0, 0), t(40, -25, 40), t(-150, -150, -20))
    assert pan_actions(*args, fov=60).tolist() == [RIGHT, RIGHT, UP]
    assert pan_actions(*args, fov=60, pitch_band=0.5).tolist() == [UP, RIGHT, UP]
    assert pan_action_mask(*args, fov=60, pitch_band=0.5).int().tolist() == [
        [1, 0, 0, 0, 0], [0, 0, 0, 1, 0], [1, 0, 1, 0, 0]]
    # band 0: match the pitch exactly before panning (the sweep's move order, with a one-move set)
    assert pan_actions(t(0), t(0), t(-1), t(-150), fov=60, pitch_band=0.0).tolist() == [DOWN]
    with pytest.raises(ValueError, match="pitch_band"):
        pan_actions(*args, fov=60, pitch_band=1.5)
    with pytest.raises(ValueError, match=r"row_done_band must be in \[0, 1\]"):  # the message names the argument
        pan_actions(*args, fov=60, row_done=torch.ones(3, dtype=torch.bool), row_done_band=-0.5)
    # it always arrives: a walk from random starts ends on the target, the pan starting within 30 degrees
    g = torch.Generator().manual_seed(5)
    n = 300
    p0, tp = torch.randint(-60, 61, (n,), generator=g), torch.randint(-60, 61, (n,), generator=g)
    y0, ty = torch.randint(-179, 181, (n,), generator=g), torch.randint(-179, 181, (n,), generator=g)
    moves, pitch, yaw = walk(lambda *s: pan_actions(*s, fov=60, pitch_band=0.5), p0, y0, tp, ty, 900)
    assert (moves >= 0).all() and torch.equal(pitch, tp) and torch.equal(yaw, ty)
    # pitch moves lie on a shortest path: at most one right turn short of an overlap more than the L1 distance
    assert (moves <= l1_distance(p0, y0, tp, ty) + 360 - 2 * 60 + 1 + 60).all()


def test_pan_prior_yaw_band_pans_until_the_target_is_well_into_the_view() -> None:
    # FoV 90, band 0.5 (45 degrees): a target 60 to the left shows a 30-degree strip -> RIGHT (band 1: LEFT, into
    # the overlap); 45 to the left (on the band) -> LEFT, 46 -> RIGHT; 60 to the right -> RIGHT either way;
    # 10 above and 40 to the left -> the oracle's set {UP, LEFT}
    args = (t(0, 0, 0, 0, 0), t(0, 0, 0, 0, 0), t(0, 0, 0, 0, 10), t(-60, -45, -46, 60, -40))
    assert pan_actions(*args, fov=90).tolist() == [LEFT, LEFT, LEFT, RIGHT, UP]
    assert pan_actions(*args, fov=90, yaw_band=0.5).tolist() == [RIGHT, LEFT, RIGHT, RIGHT, UP]
    assert pan_action_mask(*args, fov=90, yaw_band=0.5).int().tolist() == [
        [0, 0, 0, 1, 0], [0, 0, 1, 0, 0], [0, 0, 0, 1, 0], [0, 0, 0, 1, 0], [1, 0, 1, 0, 0]]
    assert overlap_mask(*args, fov=90, yaw_band=0.5).tolist() == [False, True, False, False, True]
    # one band per environment: band 1 for the first two, 0.5 for the rest
    per_env = torch.tensor([1.0, 1.0, 0.5, 0.5, 0.5])
    assert pan_actions(*args, fov=90, yaw_band=per_env).tolist() == [LEFT, LEFT, RIGHT, RIGHT, UP]
    with pytest.raises(ValueError, match="yaw_band"):
        overlap_mask(*args, fov=90, yaw_band=torch.tensor([1.0, 0.0, 0.5, 0.5, 0.5]))
    for bad in (0.0, 1.5):
        with pytest.raises(ValueError, match="yaw_band"):
            pan_actions(*args, fov=90, yaw_band=bad)
    env = SimpleNamespace(pitch=args[0], yaw=args[1], target_pitch=args[2], target_yaw=args[3], step_deg=1,
                          sim=SimpleNamespace(fov=90.0))
    assert oracle_actions_for(env, search="pan", yaw_band=0.5).tolist() == [RIGHT, LEFT, RIGHT, RIGHT, UP]
    with pytest.raises(ValueError, match="'pan' search prior only"):
        oracle_actions_for(env, search="sweep", yaw_band=0.5)
    # no start is trapped: every walk ends on the target, one right turn at most longer than the L1 distance
    g = torch.Generator().manual_seed(7)
    n = 300
    p0, tp = torch.randint(-60, 61, (n,), generator=g), torch.randint(-60, 61, (n,), generator=g)
    y0, ty = torch.randint(-179, 181, (n,), generator=g), torch.randint(-179, 181, (n,), generator=g)
    moves, pitch, yaw = walk(lambda *s: pan_actions(*s, fov=90, yaw_band=0.5), p0, y0, tp, ty, 900)
    assert (moves >= 0).all() and torch.equal(pitch, tp) and torch.equal(yaw, ty)
    assert (moves <= l1_distance(p0, y0, tp, ty) + 360).all()
    in_band = overlap_mask(p0, y0, tp, ty, fov=90, yaw_band=0.5)
    assert torch.equal(moves[in_band], l1_distance(p0, y0, tp, ty)[in_band])


def test_labels_from_an_env_object() -> None:
    env = SimpleNamespace(
        pitch=t(0, 0), yaw=t(0, 0), target_pitch=t(0, 0), target_yaw=t(-150, -20), step_deg=1,
        sim=SimpleNamespace(fov=90.0),
    )
    assert oracle_actions_for(env).tolist() == [LEFT, LEFT]
    assert oracle_actions_for(env, search="sweep").tolist() == [RIGHT, LEFT]
    assert oracle_actions_for(env, search="pan").tolist() == [RIGHT, LEFT]
    assert optimal_action_mask_for(env, search="pan").int().tolist() == [[0, 0, 0, 1, 0], [0, 0, 1, 0, 0]]
    torch.testing.assert_close(rotation_labels(env), torch.tensor([[0.0, -150 / 90, 0.0], [0.0, -20 / 90, 1.0]]))
    with pytest.raises(ValueError, match="search prior"):
        oracle_actions_for(env, search="spiral")


# --------------------------------------------------------------------------------------------------
# Config, beta, buffer
# --------------------------------------------------------------------------------------------------


def test_config_validation_and_beta_schedule() -> None:
    with pytest.raises(ValueError, match="multiple of trainer.dagger.seq_len"):
        DAggerConfig(rollout_steps=30, seq_len=16)
    with pytest.raises(ValueError, match="beta_end"):
        DAggerConfig(beta_end=1.5)
    with pytest.raises(ValueError, match="dagger.search_prior"):
        DAggerConfig(search_prior="spiral")
    with pytest.raises(ValueError, match="dagger.search_pitch_band"):
        DAggerConfig(search_pitch_band=-0.1)
    with pytest.raises(ValueError, match="dagger.search_yaw_band"):
        DAggerConfig(search_yaw_band=0.0)
    with pytest.raises(ValueError, match="'pan' search prior only"):
        DAggerConfig(search_yaw_band=0.5, search_prior="oracle")
    with pytest.raises(ValueError, match="dagger.labels"):
        DAggerConfig(labels="soft")
    cfg = DAggerConfig(beta_start=1.0, beta_end=0.2, beta_decay_updates=4)
    assert [beta_at(cfg, u) for u in (0, 1, 2, 4, 9)] == pytest.approx([1.0, 0.8, 0.6, 0.2, 0.2])
    assert beta_at(DAggerConfig(beta_decay_updates=0, beta_end=0.3), 0) == 0.3


def test_sequence_buffer_is_fifo_and_batches_time_major() -> None:
    L, H = 3, 2
    buf = SequenceBuffer(capacity=4, seq_len=L, height=2, width=2, hidden_size=H)

    def chunks(first: int, n: int):
        ids = torch.arange(first, first + n)  # chunk id, written into every field
        steps = torch.arange(L)[:, None]
        view = (ids[None, :] * 10 + steps).to(torch.uint8)[..., None, None, None].expand(L, n, 3, 2, 2)
        labels = torch.nn.functional.one_hot((ids[None] + steps) % 5, 5).bool()
        return view, view + 1, ids[:, None].float().expand(n, H), torch.ones(L, n), labels

    buf.add(*chunks(0, 3))
    buf.add(*chunks(3, 3))  # overwrites the two oldest (ids 0, 1)
    assert len(buf) == 4 and buf.pos == 2
    stored = sorted(int(h) for h in buf.hidden0[:, 0])
    assert stored == [2, 3, 4, 5]
    slot = int((buf.hidden0[:, 0] == 4).nonzero())
    other = int((buf.hidden0[:, 0] == 2).nonzero())
    b = buf.batch(torch.tensor([slot, other]))
    # time-major rows: t * 2 + k
    assert b["view"][:, 0, 0, 0].tolist() == [40, 20, 41, 21, 42, 22]
    assert b["labels"].int().argmax(dim=1).tolist() == [4, 2, 0, 3, 1, 4]
    assert b["hidden0"][:, 0].tolist() == [4.0, 2.0]
    lean = buf.batch(torch.tensor([slot, other]), images=False)  # a trainer reading cached fixed inputs
    assert "view" not in lean and "target" not in lean
    assert all(torch.equal(lean[k], b[k]) for k in lean)
    idx = buf.sample(10, torch.Generator().manual_seed(0))
    assert sorted(idx.tolist()) == [0, 1, 2, 3]


# --------------------------------------------------------------------------------------------------
# The trainer on real FindView environments
# --------------------------------------------------------------------------------------------------


def colour_panorama(seed: int, width: int = 128) -> np.ndarray:
    """``width/2 x width`` BGR: hue turns once around the longitude, brightness falls with latitude, discs."""
    rng = np.random.default_rng(seed)
    height = width // 2
    u = np.arange(width, dtype=np.float64)[None, :].repeat(height, 0)
    v = np.arange(height, dtype=np.float64)[:, None].repeat(width, 1)
    hue = (rng.integers(0, 180) + 180.0 * u / width) % 180
    value = 60 + 180 * (1 - v / height)
    image = cv2.cvtColor(np.stack([hue, np.full_like(hue, 200), value], -1).astype(np.uint8), cv2.COLOR_HSV2BGR)
    for _ in range(25):
        x, y = (int(c) for c in rng.integers(0, (width, height)))
        cv2.circle(image, (x, y), int(rng.integers(2, height // 8)), tuple(int(c) for c in rng.integers(0, 256, 3)), -1)
    return image


@pytest.fixture(scope="module")
def panoramas(tmp_path_factory) -> list[ImageEntry]:
    return write_panoramas(tmp_path_factory.mktemp("dagger_panoramas"), colour_panorama, range(300, 306), "wheel")


def make_env(images, num_envs: int, size: int, pitch_bound: int, max_steps: int, source) -> FindViewEnv:
    bank = PanoramaBank("cpu", prefetch_workers=0, max_panoramas=len(images), min_slots=num_envs)
    sim = Simulator(bank, fov=90, height=size, width=size, pitch_bound=max(pitch_bound, 1))
    return FindViewEnv(sim, source, num_envs, max_steps=max_steps, pitch_bound=pitch_bound)


def sampled_env(images, num_envs: int, size: int, pitch_bound: int, max_steps: int, seed: int) -> FindViewEnv:
    sampler = EpisodeSampler(images, 90, seed=seed, pitch_bound=pitch_bound, max_steps=max_steps)
    return make_env(images, num_envs, size, pitch_bound, max_steps, SampledEpisodeSource(sampler, level=1))


def test_rollout_labels_and_oracle_only_rollout_finishes_episodes_perfectly(panoramas) -> None:
    """beta = 1: every executed action is the label, so every finished episode is a perfect stop."""
    torch.manual_seed(0)
    env = sampled_env(panoramas, 4, 32, 20, 200, seed=5)
    policy = Policy(32, 32, variant="correlation", hidden_size=16)
    cfg = DAggerConfig(rollout_steps=24, seq_len=8, buffer_size=1000, batch_sequences=4, beta_end=1.0)
    trainer = DAggerTrainer(env, policy, cfg, total_updates=10)
    trainer.start()
    records = []
    for _ in range(3):
        stats = trainer.train_update()
        records += stats["episodes"]
    assert stats["oracle_share"] == 1.0 and stats["beta"] == 1.0
    assert stats["update"] == 3 and stats["env_steps"] == 3 * 24 * 4
    assert records and all(r["called_stop"] and r["eps"] == 0 and r["steps"] == r["shortest_path"] for r in records)
    assert len(trainer.buffer) == 3 * 3 * 4  # 3 updates x 3 chunks x 4 envs
    # label sets: never empty, STOP only alone
    labels = trainer.buffer.labels[: len(trainer.buffer)].flatten(0, 1)
    assert labels.any(dim=1).all()
    assert (labels[labels[:, STOP]].sum(dim=1) == 1).all()
    for key in ("policy_loss", "accuracy", "entropy", "grad_norm", "lr", "rollout_agreement", "buffer_steps"):
        assert np.isfinite(stats[key]), key


def test_search_weight_marks_exactly_the_no_overlap_steps(panoramas) -> None:
    """With the pan prior, a step weighs search_weight iff its label is the search's lone RIGHT (no overlap;
    pitches within +-20 keep |dpitch| below the FoV), and every other step weighs 1."""
    torch.manual_seed(0)
    env = sampled_env(panoramas, 4, 32, 20, 200, seed=6)
    env.source.level = 3  # easy, medium and hard starts
    policy = Policy(32, 32, variant="direct", hidden_size=16, fine_shifts=1, fine_scales=2)
    cfg = DAggerConfig(rollout_steps=32, seq_len=8, buffer_size=2000, batch_sequences=4, beta_end=1.0,
                       search_prior="pan", labels="set", search_weight=0.25)
    trainer = DAggerTrainer(env, policy, cfg, total_updates=10)
    trainer.start()
    for _ in range(3):
        trainer.train_update()
    n = len(trainer.buffer)
    weights = trainer.buffer.weights[:n].flatten()
    labels = trainer.buffer.labels[:n].flatten(0, 1)
    searching = weights == 0.25
    assert bool(searching.any()) and bool((weights[~searching] == 1.0).all())
    only_right = (labels.int() == torch.tensor([0, 0, 0, 1, 0])).all(dim=1)
    assert torch.equal(searching, only_right & searching)  # every down-weighted step is a pure "pan right"
    assert trainer.buffer.state_dict()["weights"].shape == (n, 8)


def test_first_steps_weigh_first_steps_weight_times_their_weight(panoramas) -> None:
    """first_steps=2, first_steps_weight=3 with search_weight=0.25: a step weighs 3 or 0.75 iff it is its episode's
    first or second step (read from the buffer's masks, 0 where an episode begins), else 1 or 0.25."""
    torch.manual_seed(0)
    env = sampled_env(panoramas, 4, 32, 20, 200, seed=6)
    env.source.level = 3
    policy = Policy(32, 32, variant="direct", hidden_size=16, fine_shifts=1, fine_scales=2)
    cfg = DAggerConfig(rollout_steps=32, seq_len=8, buffer_size=2000, batch_sequences=4, beta_end=1.0,
                       search_prior="pan", labels="set", search_weight=0.25, first_steps=2, first_steps_weight=3.0)
    trainer = DAggerTrainer(env, policy, cfg, total_updates=10)
    trainer.start()
    for _ in range(3):
        trainer.train_update()
    n = len(trainer.buffer)
    weights, masks = trainer.buffer.weights[:n], trainer.buffer.masks[:n]  # (chunks, 8)
    starts = masks == 0
    assert int(starts.sum()) >= 4  # episodes began inside the rollouts (the first of each slot, then more)
    second = torch.zeros_like(starts)
    second[:, 1:] = starts[:, :-1]
    first = weights.isclose(torch.tensor(3.0)) | weights.isclose(torch.tensor(0.75))
    assert torch.equal(first & (starts | second), starts | second)
    # every other step inside a chunk keeps its weight; a chunk's step 0 may be the second of an episode begun before
    inner = ~(starts | second)
    inner[:, 0] = False
    assert not bool(first[inner].any())
    assert bool(weights[inner].isclose(torch.tensor(1.0)).any()) and bool(weights[inner].isclose(torch.tensor(0.25)).any())


def test_first_steps_config_is_validated() -> None:
    with pytest.raises(ConfigError, match="first_steps must be >= 0"):
        DAggerConfig(first_steps=-1)
    with pytest.raises(ConfigError, match="first_steps_weight must be positive"):
        DAggerConfig(first_steps=2, first_steps_weight=0.0)


@pytest.mark.parametrize("yaw_band", [1.0, 0.5])
def test_trainer_labels_follow_the_search_yaw_band(panoramas, yaw_band) -> None:
    """The trainer's labels and search weights at poses set by hand: targets 60 and 40 degrees to the left, 10 above
    and 40 to the left, 60 to the right (FoV 90); with band 0.5 the first and the last are searches (RIGHT, weight
    search_weight)."""
    env = sampled_env(panoramas, 4, 32, 20, 200, seed=6)
    policy = Policy(32, 32, variant="correlation", hidden_size=16)
    cfg = DAggerConfig(rollout_steps=8, seq_len=8, buffer_size=100, batch_sequences=4, search_prior="pan",
                       labels="set", search_yaw_band=yaw_band)
    trainer = DAggerTrainer(env, policy, cfg, total_updates=10)
    trainer.start()
    for name, values in (("pitch", (0, 0, 0, 0)), ("yaw", (0, 0, 0, 0)), ("target_pitch", (0, 0, 10, 0)),
                         ("target_yaw", (-60, -40, -40, 60))):
        getattr(env, name).copy_(t(*values))
    oracle, label, searching, leave = trainer._labels(None)
    first = [RIGHT, [0, 0, 0, 1, 0]] if yaw_band < 1 else [LEFT, [0, 0, 1, 0, 0]]
    assert oracle.tolist() == [first[0], LEFT, UP, RIGHT]
    assert label.int().tolist() == [first[1], [0, 0, 1, 0, 0], [1, 0, 1, 0, 0], [0, 0, 0, 1, 0]]
    # 60 to the right is outside the band too: its RIGHT is then the search's, weighing search_weight
    assert searching.tolist() == [yaw_band < 1, False, False, yaw_band < 1] and not leave.any()


def test_search_yaw_band_after_applies_the_band_once_the_row_search_is_under_way(panoramas) -> None:
    """search_yaw_band=0.5, search_yaw_band_after=0.5 (FoV 90: 45 degrees of the row seen): targets 60 degrees to the
    left and 60 to the right, each once at the start of a row (1 degree seen: band 1, so LEFT towards the first, at
    full weight) and once under way (45 and 200 degrees seen: band 0.5, RIGHT, weight search_weight)."""
    with pytest.raises(ValueError, match="search_yaw_band_after"):
        DAggerConfig(search_yaw_band_after=0.5)  # band 1: nothing to delay
    with pytest.raises(ValueError, match="search_yaw_band_after"):
        DAggerConfig(search_yaw_band=0.5, search_yaw_band_after=-1.0)
    cfg = DAggerConfig(rollout_steps=8, seq_len=8, buffer_size=100, batch_sequences=4, search_prior="pan",
                       labels="set", search_weight=0.25, search_yaw_band=0.5, search_yaw_band_after=0.5)
    with pytest.raises(ValueError, match="memory_inputs"):
        DAggerTrainer(sampled_env(panoramas, 4, 32, 20, 200, seed=6), Policy(32, 32, variant="direct", hidden_size=16),
                      cfg, total_updates=10, revisit_penalty=2.0)
    env = sampled_env(panoramas, 4, 32, 20, 200, seed=6)
    policy = Policy(32, 32, variant="direct", hidden_size=16, fine_shifts=1, fine_scales=2, memory_inputs=MEMORY_FEATURES)
    trainer = DAggerTrainer(env, policy, cfg, total_updates=10, revisit_penalty=2.0)
    trainer.start()
    for name, values in (("pitch", (0, 0, 0, 0)), ("yaw", (0, 0, 0, 0)), ("target_pitch", (0, 0, 0, 0)),
                         ("target_yaw", (-60, 60, -60, 60))):
        getattr(env, name).copy_(t(*values))
    memory = torch.zeros(4, MEMORY_FEATURES)
    memory[:, 1] = torch.tensor([1.0, 1.0, 45.0, 200.0]) / 360  # degrees of the row seen, as a share of a turn
    oracle, label, searching, leave = trainer._labels(memory)
    assert oracle.tolist() == [LEFT, RIGHT, RIGHT, RIGHT]
    assert label.int().tolist() == [[0, 0, 1, 0, 0], [0, 0, 0, 1, 0], [0, 0, 0, 1, 0], [0, 0, 0, 1, 0]]
    assert searching.tolist() == [False, False, True, True] and not leave.any()
    trainer.train_update()  # a whole update labels with one band per environment
    assert len(trainer.buffer) == 4 * cfg.rollout_steps // cfg.seq_len


def dagger_run(images, updates: int, state: dict | None = None, aux: bool = True, revisit_penalty: float = 0.0,
               near_rows: int = 0):
    """A small DAgger run (correlation policy, aux loss on, set labels, tiny FIFO buffer that wraps, curriculum);
    resumes from ``state`` when given. ``near_rows > 0``: the search memory's near visits (1 logit per visit)."""
    from findview_baselines.rl.search_memory import NearVisits

    torch.manual_seed(0)
    env = sampled_env(images, 3, 32, 30, 120, seed=11)
    policy = Policy(32, 32, variant="correlation", hidden_size=16)
    cfg = DAggerConfig(
        rollout_steps=8, seq_len=4, buffer_size=24, batch_sequences=3, epochs=2.0, beta_decay_updates=3,
        aux_coef=0.5 if aux else 0.0, sample_actions=True, stop_weight=2.0, linear_decay=True, labels="set",
        search_prior="pan", search_weight=0.5,
    )
    levels: list[int] = []
    trainer = DAggerTrainer(env, policy, cfg, total_updates=6, scheduler=DifficultyScheduler(6), set_level=lambda k: (
        levels.append(k), setattr(env.source, "level", k)), revisit_penalty=revisit_penalty,
        revisit_near=NearVisits(near_rows, 1.0, 1) if near_rows else NearVisits())
    if state is None:
        trainer.start()
    else:
        trainer.load_state_dict(state)
    for _ in range(updates):
        trainer.train_update()
    return trainer, levels


@pytest.mark.parametrize("revisit_penalty, near_rows", [(0.0, 0), (2.0, 0), (2.0, 4)])
def test_exact_resume_half_plus_half_equals_one_run(panoramas, revisit_penalty, near_rows) -> None:
    """6 updates in one go == 3 updates, an abandoned 4th (stop request), save, load, 3 more; also when the
    learner acts with its search memory (whose visit counts, and with near visits their steps, are part of the
    resume state)."""
    straight, levels = dagger_run(panoramas, 6, revisit_penalty=revisit_penalty, near_rows=near_rows)
    assert levels == [1, 2, 3]
    first, _ = dagger_run(panoramas, 3, revisit_penalty=revisit_penalty, near_rows=near_rows)
    calls = iter(range(100))
    with pytest.raises(UpdateAbandoned):  # a stop request in the middle of the 4th rollout
        first.train_update(should_stop=lambda: next(calls) >= 5)
    blob = io.BytesIO()
    torch.save(first.state_dict(), blob)
    blob.seek(0)
    state = torch.load(blob, weights_only=True)
    resumed, _ = dagger_run(panoramas, 3, state=state, revisit_penalty=revisit_penalty, near_rows=near_rows)
    if revisit_penalty:
        assert int(straight.revisits.visits.sum()) > 0
        assert torch.equal(straight.revisits.visits, resumed.revisits.visits)
    if near_rows:
        assert int(straight.revisits.clock.sum()) > 0
        assert torch.equal(straight.revisits.last_visit, resumed.revisits.last_visit)
    assert resumed.update == straight.update == 6 and resumed.env_steps == straight.env_steps
    for (name, a), b in zip(straight.policy.state_dict().items(), resumed.policy.state_dict().values()):
        assert torch.equal(a, b), name
    assert all(torch.equal(a, b) for a, b in zip(straight.aux_head.parameters(), resumed.aux_head.parameters()))
    assert torch.equal(straight.buffer.labels, resumed.buffer.labels)
    assert torch.equal(straight.env.yaw, resumed.env.yaw)


def test_resume_rejects_a_different_model_or_trainer(panoramas) -> None:
    trainer, _ = dagger_run(panoramas, 1, aux=False)
    state = trainer.state_dict()
    env = sampled_env(panoramas, 3, 32, 30, 120, seed=11)
    with pytest.raises(ValueError, match="hidden_size is 16 in the checkpoint but 8"):
        DAggerTrainer(env, Policy(32, 32, variant="correlation", hidden_size=8), trainer.cfg, 6).load_state_dict(state)
    with pytest.raises(ValueError, match="not saved by the DAgger trainer"):
        trainer.load_state_dict({"signature": state["signature"], "policy": state["policy"]})


def teacher_forced_agreement(env: FindViewEnv, policy: Policy) -> tuple[float, float]:
    """Walk the oracle's actions over a static source and ask the policy (greedy, its GRU fed by that walk) at
    every step: ``(share of steps where its action lies in the optimal set, share of steps where it says STOP
    although STOP is not optimal)``. Both are properties of the policy on fixed states, not of a trajectory it
    chose, so they do not amplify a small numerical difference the way a greedy rollout can."""
    obs = env.reset()
    hidden = policy.initial_hidden(env.num_envs)
    good = total = false_stops = 0
    with torch.no_grad():
        while bool(env.active.any()):
            active = env.active.clone()
            actions, _, _, hidden = policy.act(obs, hidden, (~env.new_episode).float(), deterministic=True)
            optimal = optimal_action_mask_for(env)
            good += int((optimal.gather(1, actions[:, None]).squeeze(1) & active).sum())
            false_stops += int(((actions == STOP) & ~optimal[:, STOP] & active).sum())
            total += int(active.sum())
            obs, _, _, _ = env.step(oracle_actions_for(env))
    return good / total, false_stops / total


@pytest.mark.parametrize("seed", [0, 1])
def test_dagger_learns_a_trivial_world(panoramas, seed) -> None:
    """Yaw-only colour wheels, easy starts, 32x32 views: 30 DAgger updates (3,840 labelled steps) teach the
    policy the oracle's moves on episodes of a held-out seed.

    Numerically sensitive (docs/NUMERICS.md): the weights after training differ in the last bits between CPUs
    and thread counts. The assertion is on the teacher-forced agreement with the optimal action set, measured
    on seeds 0-8 with 1 thread and seeds 1, 5, 9 with 2 threads while tuning: 0.885-0.993 after training (untrained
    0.15-0.55; always moving towards one side agrees on about half the steps), so the bar of 0.8 leaves a margin on every seed; false
    stops stayed below 0.2% of steps. Greedy rollouts were
    not used: a policy without the search memory can circle between two poses, which turns a tiny difference
    in the weights into a 30-degree difference in the result."""
    torch.manual_seed(seed)
    size, max_steps = 32, 80
    env = sampled_env(panoramas, 8, size, 0, max_steps, seed=3 + seed)
    policy = Policy(size, size, variant="direct", hidden_size=64, fine_shifts=1, fine_scales=2)
    sampler = EpisodeSampler(panoramas, 90, seed=777, pitch_bound=0, max_steps=max_steps)
    episodes = [sampler.sample("easy") for _ in range(24)]
    static = lambda: make_env(panoramas, 8, size, 0, max_steps, StaticEpisodeSource(episodes))  # noqa: E731
    before, _ = teacher_forced_agreement(static(), policy)
    cfg = DAggerConfig(
        lr=2e-3, rollout_steps=16, seq_len=8, buffer_size=4096, batch_sequences=16, epochs=4.0, beta_decay_updates=10
    )
    trainer = DAggerTrainer(env, policy, cfg, total_updates=30)
    trainer.start()
    for _ in range(30):
        trainer.train_update()
    after, false_stops = teacher_forced_agreement(static(), policy)
    print(f"\nDAgger seed {seed}: teacher-forced agreement {before:.3f} -> {after:.3f}, false stops {false_stops:.4f}")
    assert after >= 0.8
    assert false_stops <= 0.02


def fixed_cache_run(images, cache: bool, updates: int = 3) -> DAggerTrainer:
    """A small DAgger run of the ``phase`` policy (fixed encoder part: cost volumes and phase correlation)."""
    torch.manual_seed(0)
    env = sampled_env(images, 3, 32, 30, 120, seed=12)
    policy = Policy(32, 32, variant="phase", hidden_size=16, fine_shifts=1, fine_scales=2)
    cfg = DAggerConfig(
        rollout_steps=8, seq_len=4, buffer_size=96, batch_sequences=3, epochs=2.0, beta_decay_updates=3,
        labels="set", search_prior="pan", cache_fixed_features=cache,
    )
    trainer = DAggerTrainer(env, policy, cfg, total_updates=6)
    trainer.start()
    for _ in range(updates):
        trainer.train_update()
    return trainer


def test_cached_fixed_features_train_the_same_weights(panoramas) -> None:
    """Computing the parameter-free encoder part once per buffered step (cache_fixed_features) is the same
    training as recomputing it at every gradient step: the same weights after 3 updates (to float rounding),
    and the cached rows are what the policy computes from the stored images."""
    cached = fixed_cache_run(panoramas, cache=True)
    plain = fixed_cache_run(panoramas, cache=False)
    assert plain.buffer.fixed is None and cached.buffer.fixed is not None
    n = len(cached.buffer)
    assert n == 3 * 2 * 3  # 3 updates x 2 chunks x 3 envs
    for (name, a), b in zip(cached.policy.state_dict().items(), plain.policy.state_dict().values()):
        assert torch.allclose(a, b, atol=1e-5, rtol=1e-4), name
    fresh = cached.policy.fixed_features(
        {"view": cached.buffer.view[:n].flatten(0, 1), "target": cached.buffer.target[:n].flatten(0, 1)}
    )
    assert torch.allclose(cached.buffer.fixed[:n].flatten(0, 1), fresh, atol=1e-6)
    # a resumed run (save_buffer) rebuilds the cache from the saved images
    state = cached.state_dict()
    assert "fixed" not in state["buffer"]
    env = sampled_env(panoramas, 3, 32, 30, 120, seed=12)
    policy = Policy(32, 32, variant="phase", hidden_size=16, fine_shifts=1, fine_scales=2)
    resumed = DAggerTrainer(env, policy, cached.cfg, total_updates=6)
    resumed.load_state_dict(state)
    assert torch.allclose(resumed.buffer.fixed[:n], cached.buffer.fixed[:n], atol=1e-6)


def memory_run(images, updates: int, state: dict | None = None, cover_cells: int = 6, warm: float = 0.0,
               row_done_labels: str = "target", penalised: str = "none") -> DAggerTrainer:
    """A DAgger run of a policy that reads its search memory, on hard starts only, with the oracle executing every
    step and a memory that calls a row done after ``cover_cells`` yaw cells (a full turn would take 360 steps)."""
    torch.manual_seed(0)
    env = sampled_env(images, 3, 32, 30, 120, seed=13)
    env.source.level = 3
    policy = Policy(32, 32, variant="direct", hidden_size=16, fine_shifts=1, fine_scales=2, memory_inputs=MEMORY_FEATURES)
    cfg = DAggerConfig(rollout_steps=16, seq_len=4, buffer_size=400, batch_sequences=3, epochs=2.0, beta_end=1.0,
                       labels="set", search_prior="pan", search_weight=0.25, row_done_band=0.0, memory_warm_start=warm,
                       row_done_labels=row_done_labels, penalised_loss=penalised)
    trainer = DAggerTrainer(env, policy, cfg, total_updates=6, revisit_penalty=2.0)
    trainer.revisits.cover_cells = cover_cells
    if state is None:
        trainer.start()
    else:
        trainer.load_state_dict(state)
    for _ in range(updates):
        trainer.train_update()
    return trainer


def test_memory_inputs_reach_the_buffer_the_labels_and_the_resume_state(panoramas) -> None:
    """With memory inputs, the buffer keeps the memory's features of every step; where the memory calls the row
    done and the views do not overlap (an oracle walk pans right for a while on hard starts), the label leaves the
    row by a lone pitch move at full weight; a row that is not done keeps the down-weighted lone RIGHT; and 4 updates
    equal 2 + save + load + 2."""
    with pytest.raises(ValueError, match="needs revisit_penalty > 0"):
        DAggerTrainer(sampled_env(panoramas, 3, 32, 30, 120, seed=13),
                      Policy(32, 32, variant="direct", hidden_size=16, memory_inputs=MEMORY_FEATURES), DAggerConfig(), 6)
    trainer = memory_run(panoramas, 4)
    n = len(trainer.buffer)
    memory = trainer.buffer.memory[:n].flatten(0, 1)
    labels = trainer.buffer.labels[:n].flatten(0, 1)
    weights = trainer.buffer.weights[:n].flatten()
    assert memory.shape == (n * 4, MEMORY_FEATURES)
    done = memory[:, 0] == 1.0
    lone = labels.sum(dim=1) == 1
    pitch_move = lone & (labels[:, Action.UP] | labels[:, Action.DOWN])
    right = lone & labels[:, Action.RIGHT]
    assert bool((done & pitch_move).any())  # rows left after the memory called them done
    assert not bool((weights[done] == 0.25).any())  # leaving a row weighs 1
    assert bool((~done & right & (weights == 0.25)).any()) and not bool((done & right & (weights == 0.25)).any())
    # the memory's features are in [0, 1] except the signed pitch offset
    assert bool(((memory[:, :6] >= 0) & (memory[:, :6] <= 1)).all())
    # exact resume, the memory's features saved with the buffer
    first = memory_run(panoramas, 2)
    state = first.state_dict()
    assert state["buffer"]["memory"].shape[-1] == MEMORY_FEATURES
    blob = io.BytesIO()
    torch.save(state, blob)
    blob.seek(0)
    resumed = memory_run(panoramas, 2, state=torch.load(blob, weights_only=True))
    for (name, a), b in zip(trainer.policy.state_dict().items(), resumed.policy.state_dict().values()):
        assert torch.equal(a, b), name
    assert torch.equal(trainer.buffer.memory[:n], resumed.buffer.memory[:n])


def test_penalised_loss_keeps_the_move_penalties_and_trains_on_them(panoramas) -> None:
    """``penalised_loss=moves``: the buffer keeps, per step, the memory's penalty of each move (2 logit units per
    earlier visit of its destination);
    the rollouts are the oracle's either way (beta 1), so the labels are the same and only the loss differs; the
    penalties resume exactly."""
    with pytest.raises(ValueError, match="penalised_loss"):
        DAggerTrainer(sampled_env(panoramas, 3, 32, 30, 120, seed=13), Policy(32, 32, variant="direct", hidden_size=16),
                      DAggerConfig(penalised_loss="moves"), 6)
    plain, pen = memory_run(panoramas, 3), memory_run(panoramas, 3, penalised="moves")
    n = len(pen.buffer)
    penalty = pen.buffer.penalty[:n].flatten(0, 1)
    assert penalty.shape == (n * 4, 4)
    assert bool((penalty >= 0).all()) and bool((penalty % 2.0 == 0).all())
    masks = pen.buffer.masks[:n].flatten()
    # an episode's first step (mask 0) has a fresh memory: no penalty; every later step came from a neighbour it
    # visited (or was blocked towards one, which counts as visited): some move costs 2 or more
    assert bool((penalty[masks == 0] == 0).all()) and bool((masks == 0).any())
    assert bool((penalty[masks == 1].amax(dim=1) >= 2.0).all())
    assert torch.equal(plain.buffer.labels[:n], pen.buffer.labels[:n])
    assert any(not torch.equal(a, b) for a, b in zip(plain.policy.state_dict().values(), pen.policy.state_dict().values()))
    first = memory_run(panoramas, 2, penalised="moves")
    blob = io.BytesIO()
    torch.save(first.state_dict(), blob)
    blob.seek(0)
    resumed = memory_run(panoramas, 1, state=torch.load(blob, weights_only=True), penalised="moves")
    for (name, a), b in zip(pen.policy.state_dict().items(), resumed.policy.state_dict().values()):
        assert torch.equal(a, b), name


def test_penalised_loss_rows_keeps_the_penalty_of_the_row_leaving_steps_only(panoramas) -> None:
    """``penalised_loss=rows``: a step keeps its move penalties only where its label leaves a looked-around row (a lone
    UP or DOWN at full weight, where the memory calls the row done and the views do not overlap); every other step's
    penalties are 0."""
    with pytest.raises(Exception, match="penalised_loss"):
        DAggerConfig(penalised_loss="all")
    with pytest.raises(ValueError, match="memory_inputs"):  # without the memory's inputs no step leaves a done row
        DAggerTrainer(sampled_env(panoramas, 3, 32, 30, 120, seed=13), Policy(32, 32, variant="direct", hidden_size=16),
                      DAggerConfig(penalised_loss="rows"), 6, revisit_penalty=2.0)
    trainer = memory_run(panoramas, 4, row_done_labels="rows", penalised="rows")
    n = len(trainer.buffer)
    penalty = trainer.buffer.penalty[:n].flatten(0, 1)
    memory = trainer.buffer.memory[:n].flatten(0, 1)
    labels = trainer.buffer.labels[:n].flatten(0, 1)
    weights = trainer.buffer.weights[:n].flatten()
    kept = penalty.amax(dim=1) > 0
    leaving = (memory[:, 0] == 1.0) & (labels.sum(dim=1) == 1) & (labels[:, Action.UP] | labels[:, Action.DOWN])
    assert bool(kept.any())
    assert bool((leaving[kept]).all()) and bool((weights[kept] == 1.0).all())


@pytest.mark.parametrize("warm", [0.0, 1.0])
def test_memory_warm_start_begins_episodes_with_their_row_looked_around(panoramas, warm) -> None:
    """memory_warm_start=1: every episode's first step already has its row done (a full turn of cells seen);
    0: no first step has (one cell seen)."""
    trainer = memory_run(panoramas, 3, cover_cells=360, warm=warm)
    n = len(trainer.buffer)
    first = trainer.buffer.masks[:n].flatten() == 0
    memory = trainer.buffer.memory[:n].flatten(0, 1)
    assert bool(first.any())
    assert torch.equal(memory[first, 0], torch.full((int(first.sum()),), warm))
    assert torch.allclose(memory[first, 1], torch.full((int(first.sum()),), 1.0 if warm else 1 / 360))


def test_row_done_labels_rows_leave_for_the_search_rows(panoramas) -> None:
    """row_done_labels=rows: where the memory calls the row done, the views do not overlap and a search row is left,
    the label is the lone pitch move towards it (here FoV 90: rows +-45, +-90 from the start), at full weight."""
    trainer = memory_run(panoramas, 6, row_done_labels="rows", warm=1.0)
    n = len(trainer.buffer)
    memory = trainer.buffer.memory[:n].flatten(0, 1)
    labels = trainer.buffer.labels[:n].flatten(0, 1)
    weights = trainer.buffer.weights[:n].flatten()
    done = memory[:, 0] == 1.0
    lone_pitch = (labels.sum(dim=1) == 1) & (labels[:, Action.UP] | labels[:, Action.DOWN])
    assert bool((done & lone_pitch & (weights == 1.0)).any())
    # a step at the start row with no search row done goes to the first row of ring 1: only UP or DOWN is labelled
    first = (trainer.buffer.masks[:n].flatten() == 0) & done & (weights == 1.0) & lone_pitch
    assert bool(first.any())


# --------------------------------------------------------------------------------------------------
# Overlapped updates (overlap_rollout): the rollout in a second thread beside the gradient steps
# --------------------------------------------------------------------------------------------------


def overlap_run(images, overlap: bool, updates: int, thread=None) -> DAggerTrainer:
    """A small DAgger run of the ``phase`` policy with its search memory, the learner acting alone from update 2
    (beta 0); ``thread`` replaces ``threading.Thread`` in the trainer's module (a stand-in that runs the rollout
    at another time)."""
    import findview_baselines.rl.dagger as dagger_module

    torch.manual_seed(0)
    env = sampled_env(images, 3, 32, 30, 120, seed=14)
    policy = Policy(32, 32, variant="phase", hidden_size=16, fine_shifts=1, fine_scales=2)
    cfg = DAggerConfig(rollout_steps=8, seq_len=4, buffer_size=96, batch_sequences=3, epochs=2.0,
                       beta_decay_updates=2, labels="set", search_prior="pan", overlap_rollout=overlap)
    trainer = DAggerTrainer(env, policy, cfg, total_updates=6, revisit_penalty=2.0)
    trainer.start()
    real = dagger_module.threading.Thread
    if thread is not None:
        dagger_module.threading.Thread = thread
    try:
        for _ in range(updates):
            trainer.train_update()
    finally:
        dagger_module.threading.Thread = real
    return trainer


class RunAtStart:
    """A ``threading.Thread`` stand-in that runs its target at ``start()``: the rollout before the gradient steps."""

    def __init__(self, target, name=None, daemon=None) -> None:
        self.target = target

    def start(self) -> None:
        self.target()

    def join(self) -> None:
        pass


class RunAtJoin(RunAtStart):
    """Runs its target at ``join()``: the rollout after the gradient steps have changed the weights."""

    def start(self) -> None:
        pass

    def join(self) -> None:
        self.target()


def test_overlapped_rollouts_are_deterministic_and_independent_of_the_thread_timing(panoramas) -> None:
    """With overlap_rollout the rollout and the gradient steps share no state: the threaded run gives the same
    weights, buffer and environment as the rollout run entirely before the gradient steps, and as the rollout run
    entirely after them (it acts with the weights copied before them, not the ones they change). The first update
    (empty buffer) is the sequential one; later ones differ from it (the gradient steps do not see the rollout
    collected beside them), and every rollout still reaches the buffer."""
    threaded = overlap_run(panoramas, True, 4)
    for stand_in in (RunAtStart, RunAtJoin):
        other = overlap_run(panoramas, True, 4, thread=stand_in)
        for (name, a), b in zip(threaded.policy.state_dict().items(), other.policy.state_dict().values()):
            assert torch.equal(a, b), (stand_in.__name__, name)
        assert torch.equal(threaded.buffer.labels, other.buffer.labels)
        assert torch.equal(threaded.buffer.fixed, other.buffer.fixed)
        assert torch.equal(threaded.env.yaw, other.env.yaw) and torch.equal(threaded.hidden, other.hidden)
    first_overlap, first_plain = overlap_run(panoramas, True, 1), overlap_run(panoramas, False, 1)
    assert all(torch.equal(a, b) for a, b in zip(first_overlap.params, first_plain.params))
    plain = overlap_run(panoramas, False, 4)
    assert len(threaded.buffer) == len(plain.buffer) == 4 * 2 * 3  # 4 rollouts x 2 chunks x 3 envs
    assert threaded.env_steps == plain.env_steps == 4 * 8 * 3
    assert not all(torch.equal(a, b) for a, b in zip(threaded.params, plain.params))
    # the acting copy holds the weights of the last update's start, not the trained ones
    assert not all(torch.equal(a, b) for a, b in zip(threaded._acting.parameters(), threaded.policy.parameters()))


def test_overlapped_update_raises_the_rollouts_error_and_honours_a_stop_before_it(panoramas) -> None:
    from torch.distributions import Distribution

    before = Distribution._validate_args
    trainer = overlap_run(panoramas, True, 2)
    assert Distribution._validate_args == before  # the two threads leave the global argument checks as they were
    weights = [p.detach().clone() for p in trainer.params]
    size, update = len(trainer.buffer), trainer.update
    with pytest.raises(UpdateAbandoned):
        trainer.train_update(should_stop=lambda: True)
    assert trainer.update == update and len(trainer.buffer) == size
    assert all(torch.equal(a, b) for a, b in zip(weights, trainer.params))

    def broken(*args, **kwargs):
        raise RuntimeError("simulator failed in the rollout thread")

    trainer._collect = broken
    with pytest.raises(RuntimeError, match="rollout thread"):
        trainer.train_update()


def test_train_only_moves_the_named_modules_alone(panoramas) -> None:
    """``train_only=[wide_proj]``: after an update the wide match's projection has moved and every other weight
    is bit for bit what it was; a name that is no module of the policy is refused with the modules it has."""
    from findview_baselines.rl.wide_match import WIDE_FEATURES

    with pytest.raises(ValueError, match="train_only"):
        DAggerConfig(train_only=[])
    torch.manual_seed(0)
    policy = Policy(32, 32, variant="phase", hidden_size=16, fine_shifts=1, fine_scales=2, wide_match=WIDE_FEATURES)
    with pytest.raises(ValueError, match="no module 'wide'.*wide_proj"):
        DAggerTrainer(sampled_env(panoramas, 4, 32, 20, 200, seed=7), policy, DAggerConfig(train_only=["wide"]),
                      total_updates=10)
    before = {k: v.clone() for k, v in policy.state_dict().items()}
    cfg = DAggerConfig(rollout_steps=16, seq_len=8, buffer_size=200, batch_sequences=4, beta_end=0.5,
                       train_only=["wide_proj"])
    trainer = DAggerTrainer(sampled_env(panoramas, 4, 32, 20, 200, seed=7), policy, cfg, total_updates=10)
    trainer.start()
    trainer.train_update()
    trainer.train_update()
    moved = {k for k, v in policy.state_dict().items() if not torch.equal(v, before[k])}
    assert moved and all(k.startswith("wide_proj.") for k in moved), moved


def test_first_steps_turn_labels_the_turn_alone(panoramas) -> None:
    """first_steps_turn with first_steps=3: at env step 0 a target 40 degrees left and 10 above is labelled LEFT alone
    (the set would also allow UP), one 60 right RIGHT alone, one straight above keeps its set (no turn to make), and
    a hard one (150 degrees to the side) keeps the search's RIGHT; at step 3 the labels are the sets again."""
    env = sampled_env(panoramas, 4, 32, 20, 200, seed=6)
    policy = Policy(32, 32, variant="correlation", hidden_size=16)
    cfg = DAggerConfig(rollout_steps=8, seq_len=8, buffer_size=100, batch_sequences=4, search_prior="pan",
                       labels="set", first_steps=3, first_steps_turn=True)
    trainer = DAggerTrainer(env, policy, cfg, total_updates=10)
    trainer.start()
    for name, values in (("pitch", (0, 0, 0, 0)), ("yaw", (0, 0, 0, 0)), ("target_pitch", (10, 0, 20, 0)),
                         ("target_yaw", (-40, 60, 0, 150))):
        getattr(env, name).copy_(t(*values))
    env.steps.zero_()
    oracle, label, searching, _ = trainer._labels(None)
    assert oracle.tolist() == [LEFT, RIGHT, UP, RIGHT]
    assert label.int().tolist() == [[0, 0, 1, 0, 0], [0, 0, 0, 1, 0], [1, 0, 0, 0, 0], [0, 0, 0, 1, 0]]
    assert searching.tolist() == [False, False, False, True]
    env.steps.fill_(3)
    _, label, _, _ = trainer._labels(None)
    assert label.int().tolist()[:2] == [[1, 0, 1, 0, 0], [0, 0, 0, 1, 0]]
    with pytest.raises(ConfigError, match="first_steps_turn=true labels"):
        DAggerConfig(first_steps_turn=True)
