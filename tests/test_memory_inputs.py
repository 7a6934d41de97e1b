"""A policy that reads its search memory (``agent.memory_inputs``): the memory's features against hand-worked
walks, the labels that leave a finished row, the policy / checkpoint / agent / trainer plumbing."""

from __future__ import annotations

import pytest
import torch

from findview.task.actions import Action
from findview.task.oracle import pan_action_mask, pan_actions
from findview_baselines.agents.base import DOWN, RIGHT, UP
from findview_baselines.agents.ppo_agent import PPOAgent
from findview_baselines.rl.checkpoint import CheckpointError, load_policy, save_checkpoint
from findview_baselines.rl.policy import Policy
from findview_baselines.rl.search_memory import MEMORY_FEATURES, RevisitPenalty, memory_band


def step_all(memory: RevisitPenalty, views: torch.Tensor, action: list[int]) -> torch.Tensor:
    """Every slot takes ``action`` and arrives with a fresh view (nothing is blocked); returns the new views."""
    ids = torch.arange(len(action))
    memory.moved(ids, torch.tensor(action))
    views = views + 1
    memory.arrive(ids, views)
    return views


def test_memory_band_is_half_a_fov_minus_one_step() -> None:
    assert memory_band(60) == 29 and memory_band(90) == 44 and memory_band(62) == 30
    assert memory_band(2) == 1  # never below one step
    assert memory_band(60, step_deg=2) == 14


def test_memory_features_after_a_turn_and_a_climb() -> None:
    """Two slots pan a full turn (360 yaw cells) at their start row, then one climbs and one descends: the
    features follow the definition in RevisitPenalty.memory_features, worked by hand."""
    memory = RevisitPenalty(2, penalty=1.0)
    ids = torch.arange(2)
    views = torch.zeros(2, 3, 2, 2, dtype=torch.uint8)
    memory.arrive(ids, views)
    f = memory.memory_features(ids, 29)
    assert f.shape == (2, MEMORY_FEATURES)
    assert torch.allclose(f[0], torch.tensor([0.0, 1 / 360, 0.0, 0.0, 0.0, 0.0, 0.0]))
    for _ in range(322):  # 323 cells seen: not yet 0.9 of a turn (324, the default row_cover)
        views = step_all(memory, views, [RIGHT, RIGHT])
    assert memory.memory_features(ids, 29)[:, 0].tolist() == [0.0, 0.0]
    views = step_all(memory, views, [RIGHT, RIGHT])
    assert memory.memory_features(ids, 29)[:, 0].tolist() == [1.0, 1.0]
    for _ in range(36):
        views = step_all(memory, views, [RIGHT, RIGHT])
    assert torch.allclose(memory.memory_features(ids, 29), torch.tensor([[1.0, 1.0, 0.0, 0.0, 0.0, 0.0, 0.0]] * 2))
    for _ in range(29):  # 29 steps up / down: the band [p - 29, p + 29] still holds the start row
        views = step_all(memory, views, [UP, DOWN])
    f = memory.memory_features(ids, 29)
    assert f[:, 0].tolist() == [1.0, 1.0]
    views = step_all(memory, views, [UP, DOWN])  # 30 steps: the band has left the start row
    f = memory.memory_features(ids, 29)
    # here: only the column of the climb (1 of 360); no search row (+-30, +-60 from the start) looked around yet
    expected = torch.tensor([[0.0, 1 / 360, 0.0, 0.0, 0.0, 0.0, 30 / 90], [0.0, 1 / 360, 0.0, 0.0, 0.0, 0.0, -30 / 90]])
    assert torch.allclose(f, expected)
    for _ in range(359):  # a turn at +30 / -30: the search row +s (first slot) / -s (second) is done
        views = step_all(memory, views, [RIGHT, RIGHT])
    expected = torch.tensor([[1.0, 1.0, 1.0, 0.0, 0.0, 0.0, 30 / 90], [1.0, 1.0, 0.0, 1.0, 0.0, 0.0, -30 / 90]])
    assert torch.allclose(memory.memory_features(ids, 29), expected)
    for _ in range(60):  # through the start row (done) to -30 / +30: the band there is not done
        views = step_all(memory, views, [DOWN, UP])
    f = memory.memory_features(ids, 29)
    assert f[:, 0].tolist() == [0.0, 0.0] and f[:, 2:6].tolist() == [[1.0, 0.0, 0.0, 0.0], [0.0, 1.0, 0.0, 0.0]]
    memory.reset(torch.tensor([1]))
    memory.arrive(torch.tensor([1]), views[1:])
    assert torch.allclose(memory.memory_features(torch.tensor([1]), 29), torch.tensor([[0.0, 1 / 360] + [0.0] * 5]))
    with pytest.raises(ValueError, match="memory band must be >= 1"):
        memory.memory_features(ids, 0)


def test_running_column_counts_match_the_visit_grid() -> None:
    """The per-column counts that memory_features reads are kept in step with the visit grid through every way a
    visit is written: arrivals, blocked moves (here at a pitch limit of 3 steps), whole-row marks, resets and a
    resumed state. Expected: for every row r and column y, the number of rows below r with a visit there."""
    memory = RevisitPenalty(3, penalty=1.0, max_pitch_steps=3)
    gen = torch.Generator().manual_seed(0)
    ids = torch.arange(3)
    views = torch.zeros(3, 3, 2, 2, dtype=torch.uint8)

    def expected(m: RevisitPenalty) -> torch.Tensor:
        seen = (m.visits > 0).long()
        rows = seen.shape[1]
        return torch.stack([seen[:, :r].sum(dim=1) for r in range(rows + 1)], dim=1)

    reached = 0
    for t in range(400):
        moving = torch.rand(3, generator=gen) < 0.8  # the rest keep their view: a blocked move
        views = views + moving[:, None, None, None].to(torch.uint8)
        memory.arrive(ids, views)
        reached = max(reached, int(memory.pitch.abs().max()))
        memory.moved(ids, torch.randint(0, 4, (3,), generator=gen))
        if t % 97 == 50:
            memory.mark_row_seen(torch.tensor([t % 3]))
        if t % 131 == 130:
            memory.reset(torch.tensor([(t + 1) % 3]))
    assert int(memory.visits.sum()) > 400 and reached == 3  # the limit was pressed
    assert torch.equal(memory.seen_below.long(), expected(memory))
    resumed = RevisitPenalty(3, penalty=1.0, max_pitch_steps=3)
    resumed.load_state_dict(memory.state_dict())
    assert torch.equal(resumed.seen_below, memory.seen_below)


def test_arrive_then_penalise_is_adjust() -> None:
    """The split calls a memory-reading policy makes give the logits and counts of the one ``adjust`` call."""
    a, b = RevisitPenalty(3, penalty=2.0), RevisitPenalty(3, penalty=2.0)
    gen = torch.Generator().manual_seed(0)
    ids = torch.arange(3)
    views = torch.zeros(3, 3, 2, 2, dtype=torch.uint8)
    for t in range(40):
        logits = torch.randn(3, 5, generator=gen)
        views = views + (torch.arange(3)[:, None, None, None] != t % 3).to(torch.uint8)  # one slot blocked per step
        out_a = a.adjust(ids, views, logits)
        b.arrive(ids, views)
        out_b = b.penalise(ids, logits)
        assert torch.equal(out_a, out_b)
        act = out_a.argmax(dim=-1)
        a.moved(ids, act)
        b.moved(ids, act)
    assert torch.equal(a.visits, b.visits) and torch.equal(a.pitch, b.pitch) and torch.equal(a.yaw, b.yaw)


def test_pan_prior_leaves_a_finished_row_towards_the_target() -> None:
    """FoV 60. Overlapping starts keep the oracle's labels; where the views do not overlap, the pan prior pans
    RIGHT unless the searcher's row is done: then it moves the pitch towards the target (RIGHT again at dpitch 0)."""
    pitch = torch.tensor([0, 0, 0, 0, 10])
    yaw = torch.zeros(5, dtype=torch.long)
    target_pitch = torch.tensor([38, -38, 38, 0, 40])
    target_yaw = torch.tensor([170, 170, 170, 170, 20])  # the last one overlaps (|dpitch| 30, |dyaw| 20)
    row_done = torch.tensor([True, True, False, True, True])
    assert pan_actions(pitch, yaw, target_pitch, target_yaw, 60.0).tolist() == [RIGHT, RIGHT, RIGHT, RIGHT, UP]
    got = pan_actions(pitch, yaw, target_pitch, target_yaw, 60.0, row_done=row_done)
    assert got.tolist() == [UP, DOWN, RIGHT, RIGHT, UP]
    mask = pan_action_mask(pitch, yaw, target_pitch, target_yaw, 60.0, row_done=row_done)
    assert mask[:4].sum(dim=1).tolist() == [1, 1, 1, 1]  # the search's one move
    assert mask[0, UP] and mask[1, DOWN] and mask[2, RIGHT] and mask[3, RIGHT]
    assert mask[4].tolist() == [True, False, False, True, False]  # the overlap keeps the shortest-path set
    # row_done_band 0.25 (15 degrees at FoV 60): a done row is left only while the target is more than 15 degrees off
    near = pan_actions(torch.tensor([0, 0, 0]), torch.zeros(3, dtype=torch.long), torch.tensor([15, 16, -16]),
                       torch.tensor([170] * 3), 60.0, row_done=torch.tensor([True] * 3), row_done_band=0.25)
    assert near.tolist() == [RIGHT, UP, DOWN]


def test_following_the_row_done_labels_finds_a_target_the_pan_missed() -> None:
    """A searcher that misses a target 38 degrees above at FoV 60 on its first turn (it never treats the views as
    overlapping while |dpitch| > 20) follows the labels with its own memory: after the turn it climbs, pans
    again and reaches the target; without the memory's row_done it pans at its start row for ever."""

    def run(use_memory: bool, steps: int = 1500) -> bool:
        memory = RevisitPenalty(1, penalty=1.0)
        p, y, tp, ty = 0, 0, 38, 170
        view = torch.zeros(1, 3, 2, 2, dtype=torch.uint8)
        memory.arrive(torch.tensor([0]), view)
        for _ in range(steps):
            if (p, y) == (tp, ty):
                return True
            done = memory.memory_features(torch.tensor([0]), memory_band(60))[:, 0] > 0.5 if use_memory else None
            if abs(tp - p) > 20:  # the searcher does not see the overlap: the labels of a target out of view
                away = (y + 360) % 360 - 180  # 180 degrees round: never overlapping
                a = int(pan_actions(*[torch.tensor([v]) for v in (p, y, tp, away)], 60.0, row_done=done))
                assert a in (UP, DOWN, RIGHT)
            else:
                a = int(pan_actions(*[torch.tensor([v]) for v in (p, y, tp, ty)], 60.0))
            p += {UP: 1, DOWN: -1}.get(a, 0)
            y = (y + {RIGHT: 1, int(Action.LEFT): -1}.get(a, 0) + 180) % 360 - 180
            view = step_all(memory, view, [a])
        return False

    assert run(use_memory=True) and not run(use_memory=False)


def test_search_row_moves_go_to_the_next_row_not_looked_around() -> None:
    """Rows +30, -30, +60, -60 from the start (band 29): the first of a ring on the target's side, then the other,
    then the next ring; no move once all are done or on the row itself."""
    from findview_baselines.rl.dagger import search_row_moves

    memory = torch.zeros(7, MEMORY_FEATURES)
    memory[1, 2] = 1  # +30 done
    memory[2, 2:4] = 1  # ring 1 done
    memory[3, 2:6] = 1  # every row done
    memory[4, 3] = 1  # -30 done
    offset = torch.tensor([0, 30, 30, 0, -5, 0, 30])
    side = torch.tensor([1, 1, -1, 1, 1, -1, 1])
    got = search_row_moves(memory, offset, side, 29).tolist()
    # to +30, to -30, to -60 (the target's side of ring 2), none, to +30, to -30, on the row +30 itself: none
    assert got == [UP, DOWN, DOWN, -1, UP, DOWN, -1]


def small_memory_policy(memory_inputs: int = MEMORY_FEATURES) -> Policy:
    torch.manual_seed(0)
    return Policy(32, 32, variant="direct", hidden_size=16, fine_shifts=1, fine_scales=2, memory_inputs=memory_inputs)


def test_memory_policy_starts_as_the_policy_without_memory_and_grows_from_a_checkpoint(tmp_path) -> None:
    plain = small_memory_policy(0)
    path = save_checkpoint(tmp_path / "plain.pth", {"signature": plain.model_signature(), "policy": plain.state_dict()})
    grown = small_memory_policy()
    assert grown.model_signature()["memory_inputs"] == MEMORY_FEATURES
    with pytest.raises(CheckpointError, match=f"memory_inputs is 0 in the checkpoint but {MEMORY_FEATURES}"):
        load_policy(path, grown)  # evaluating / resuming needs the same model
    load_policy(path, grown, transfer=True)  # init_from: the new map starts at zero
    gen = torch.Generator().manual_seed(1)
    obs = {k: torch.randint(0, 256, (4, 3, 32, 32), dtype=torch.uint8, generator=gen) for k in ("view", "target")}
    hidden, masks = torch.zeros(4, 16), torch.ones(4)
    memory = torch.rand(4, MEMORY_FEATURES, generator=gen)
    with torch.no_grad():
        d0, v0, h0 = plain(obs, hidden, masks)
        d1, v1, h1 = grown(obs, hidden, masks, memory=memory)
    assert torch.allclose(d0.logits, d1.logits) and torch.allclose(v0, v1) and torch.allclose(h0, h1)
    with pytest.raises(ValueError, match="needs memory features of shape"):
        grown(obs, hidden, masks)
    with pytest.raises(ValueError, match="built without memory inputs"):
        plain(obs, hidden, masks, memory=memory)
    # a checkpoint that claims memory inputs but lacks their weights is refused, also as init_from
    broken = {k: v for k, v in grown.state_dict().items() if not k.startswith("memory_proj.")}
    bad = save_checkpoint(tmp_path / "broken.pth", {"signature": grown.model_signature(), "policy": broken})
    with pytest.raises(CheckpointError, match="Missing key.*memory_proj.weight"):
        load_policy(bad, small_memory_policy(), transfer=True)
    with pytest.raises(ValueError, match="memory_inputs must be 0"):
        Policy(32, 32, variant="direct", hidden_size=16, memory_inputs=3)
    # the memory reaches the output once its map has weights
    with torch.no_grad():
        grown.memory_proj.weight.fill_(0.5)
        d2, _, _ = grown(obs, hidden, masks, memory=memory)
    assert not torch.allclose(d1.logits, d2.logits)


def test_agent_reads_its_memory_once_per_step() -> None:
    policy = small_memory_policy()
    with pytest.raises(ValueError, match="reads its search memory"):
        PPOAgent(policy, 2, revisit_penalty=0.0, fov=60.0)
    with pytest.raises(ValueError, match="reads its search memory"):
        PPOAgent(policy, 2, revisit_penalty=4.0)  # no fov
    agent = PPOAgent(policy, 2, revisit_penalty=4.0, fov=60.0)
    assert agent.memory_band == 29
    agent.reset([0, 1], [None, None])
    agent.done[:] = False
    gen = torch.Generator().manual_seed(2)
    for _ in range(5):
        obs = {k: torch.randint(0, 256, (2, 3, 32, 32), dtype=torch.uint8, generator=gen) for k in ("view", "target")}
        agent.act(obs)
        agent.done[:] = False  # keep both slots acting even if the untrained network says STOP
    assert int(agent.revisits.visits.sum()) == 2 * 5  # one visit per slot and step, not two


def test_config_and_trainers_refuse_memory_without_the_memory() -> None:
    from findview_baselines.cli import compose_config, validate_config
    from findview_baselines.errors import UserError

    from findview.config import ConfigError

    with pytest.raises(ConfigError, match="agent.memory_inputs=true"):
        validate_config(compose_config("train", ["agent=ppo", "agent.memory_inputs=true"]))
    cfg = validate_config(compose_config("train", ["agent=ppo", "agent.memory_inputs=true", "agent.revisit_penalty=4"]))
    assert cfg.agent.memory_inputs
    from findview_baselines.training.build import make_trainer

    with pytest.raises(UserError, match="trainer=dagger only"):
        make_trainer(cfg, None, small_memory_policy(), None, 0)
