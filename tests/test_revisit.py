"""The learned agents' search memory (findview_baselines/rl/search_memory.py), against hand-worked walks."""

from __future__ import annotations

import pytest
import torch

from findview_baselines.agents.base import DOWN, LEFT, RIGHT, STOP, UP
from findview_baselines.rl.search_memory import NearVisits, RevisitPenalty, RowSearch


def pose_view(pitch: int, yaw: int) -> torch.Tensor:
    """A (3, 2, 2) uint8 image unique to a pose (the simulator's view changes with every move)."""
    img = torch.zeros(3, 2, 2, dtype=torch.uint8)
    img[0, 0, 0] = pitch % 256
    img[1, 0, 0] = yaw % 360 % 256
    img[2, 0, 0] = yaw % 360 // 256
    return img


class LoopWorld:
    """One agent on a 1-degree grid whose policy prefers RIGHT at even yaw and LEFT at odd yaw (margin 1 logit
    over UP; DOWN and STOP far below): the plain argmax loops between yaw 0 and 1 forever."""

    def __init__(self, pitch_limit: int = 90) -> None:
        self.pitch, self.yaw, self.limit = 0, 0, pitch_limit

    def logits(self) -> torch.Tensor:
        row = torch.tensor([0.0, -5.0, -5.0, -5.0, -5.0])
        row[RIGHT if self.yaw % 2 == 0 else LEFT] = 1.0
        return row[None]

    def step(self, action: int) -> None:
        if action == UP:
            self.pitch = min(self.pitch + 1, self.limit)
        elif action == DOWN:
            self.pitch = max(self.pitch - 1, -self.limit)
        elif action == LEFT:
            self.yaw -= 1
        elif action == RIGHT:
            self.yaw += 1


def walk(penalty: float, steps: int, pitch_limit: int = 90) -> list[int]:
    world, guard = LoopWorld(pitch_limit), RevisitPenalty(1, penalty) if penalty > 0 else None
    idx, actions = torch.tensor([0]), []
    for _ in range(steps):
        logits = world.logits()
        if guard is not None:
            logits = guard.adjust(idx, pose_view(world.pitch, world.yaw)[None], logits)
        a = int(logits.argmax(dim=-1))
        if guard is not None:
            guard.moved(idx, torch.tensor([a]))
        actions.append(a)
        world.step(a)
    return actions


def test_plain_policy_loops_and_the_penalty_breaks_the_loop():
    assert walk(0.0, 8) == [RIGHT, LEFT] * 4
    # penalty 2: at yaw 1 (first visit), LEFT leads back to yaw 0 (1 visit): 1 - 2 = -1 < UP's 0 -> UP
    assert walk(2.0, 2) == [RIGHT, UP]
    # penalty 0.3: LEFT / RIGHT cost 0.3 per visit of the pose they lead to. Its visits at steps 1..8:
    # 0, 1, 1, 2, 2, 3, 3, 4 -> the preferred move is worth 1, 0.7, 0.7, 0.4, 0.4, 0.1, 0.1, -0.2 against UP's 0
    assert walk(0.3, 8) == [RIGHT, LEFT] * 3 + [RIGHT, UP]


def test_dead_reckoning_and_visit_counts():
    guard = RevisitPenalty(2, 1.0)
    idx = torch.tensor([1])
    pose = [0, 0]
    for a in (RIGHT, RIGHT, LEFT, UP, LEFT, LEFT, LEFT):
        guard.adjust(idx, pose_view(*pose)[None], torch.zeros(1, 5))
        guard.moved(idx, torch.tensor([a]))
        pose[0] += {UP: 1, DOWN: -1}.get(a, 0)
        pose[1] += {RIGHT: 1, LEFT: -1}.get(a, 0)
    guard.adjust(idx, pose_view(*pose)[None], torch.zeros(1, 5))
    assert (int(guard.pitch[1]), int(guard.yaw[1])) == (1, 358)  # yaw -2 wraps to 358
    m = guard.max_pitch
    v = guard.visits[1]
    assert int(v[m, 0]) == 1 and int(v[m, 1]) == 2 and int(v[m, 2]) == 1  # yaw 1 visited twice
    assert [int(v[m + 1, y]) for y in (1, 0, 359, 358)] == [1, 1, 1, 1]
    assert int(v.sum()) == 8
    assert int(guard.visits[0].sum()) == 0  # the other slot never acted


def test_a_blocked_move_counts_as_a_revisit():
    # pitch limit 0: UP leaves the view unchanged, so the pose stays and its visit count grows
    guard = RevisitPenalty(1, 1.0)
    idx = torch.tensor([0])
    view = pose_view(0, 0)[None]
    for _ in range(3):
        out = guard.adjust(idx, view, torch.tensor([[1.0, -5.0, 0.0, 0.0, -5.0]]))
        guard.moved(idx, torch.tensor([UP]))  # the test presses UP whatever the penalty says
    assert (int(guard.pitch[0]), int(guard.yaw[0])) == (0, 0)
    assert int(guard.visits[0, guard.max_pitch, 0]) == 3
    # UP's destination (pitch +1) was never reached, but each of the 2 blocked tries counts as a visit of it:
    # at the 3rd choice UP is worth 1 - 2 x 1.0; LEFT / RIGHT lead to empty cells
    assert int(guard.visits[0, guard.max_pitch + 1, 0]) == 2
    assert out[0, :4].tolist() == [-1.0, -5.0, 0.0, 0.0]


def test_stop_stays_the_policys_decision():
    guard = RevisitPenalty(2, 10.0)
    idx = torch.tensor([0, 1])
    views = torch.stack([pose_view(0, 0), pose_view(5, 5)])
    # slot 0 wants to stop: it stops; slot 1 prefers a move slightly, STOP is second: after its moves are
    # penalised below STOP's logit, it must still move, never stop
    logits = torch.tensor([[0.0, 0.0, 0.0, 0.0, 3.0], [1.0, 0.0, 0.0, 0.0, 0.9]])
    for _ in range(6):
        out = guard.adjust(idx, views, logits)
        acts = out.argmax(dim=-1)
        assert int(acts[0]) == STOP and int(acts[1]) != STOP
        guard.moved(idx, torch.tensor([STOP, int(acts[1])]))
        views[1] = views[1] + 1  # slot 1's view changes with every move
    assert torch.isinf(out[0, :4]).all() and torch.isinf(out[1, 4])


def test_reset_forgets_and_bad_values_are_refused():
    guard = RevisitPenalty(1, 1.0)
    idx = torch.tensor([0])
    guard.adjust(idx, pose_view(0, 0)[None], torch.zeros(1, 5))
    guard.moved(idx, torch.tensor([RIGHT]))
    guard.adjust(idx, pose_view(0, 1)[None], torch.zeros(1, 5))
    guard.reset(idx)
    assert int(guard.visits.sum()) == 0 and int(guard.yaw[0]) == 0 and int(guard.last_move[0]) == -1
    with pytest.raises(ValueError, match="revisit penalty"):
        RevisitPenalty(1, 0.0)
    with pytest.raises(ValueError, match="step_deg"):
        RevisitPenalty(1, 1.0, step_deg=7)


def test_ppo_agent_refuses_a_negative_penalty():
    from findview_baselines.agents.ppo_agent import PPOAgent
    from findview_baselines.rl.policy import Policy

    with pytest.raises(ValueError, match="revisit_penalty"):
        PPOAgent(Policy(64, 64, "early_fusion", hidden_size=8), 1, revisit_penalty=-1.0)


def row_walk(steps: int, pitch_limit: int, row_after: int = 0, stride: int = 5) -> tuple[list[int], RevisitPenalty]:
    """An agent that always prefers RIGHT, on a 30-degree grid (12 yaw cells), memory penalty 1, row search with
    stride ``stride`` steps (5: rows +5, -5, then +10, beyond the 6-step pitch range: the search ends)."""
    guard = RevisitPenalty(1, 1.0, step_deg=30, rows=RowSearch(stride=stride, after=row_after))
    assert guard.yaw_cells == 12 and guard.cover_cells == 11 and guard.max_pitch == 6
    idx, pitch, yaw, actions = torch.tensor([0]), 0, 0, []
    for _ in range(steps):
        out = guard.adjust(idx, pose_view(pitch, yaw)[None], torch.tensor([[0.0, 0.0, -5.0, 5.0, -9.0]]))
        a = int(out.argmax(dim=-1))
        guard.moved(idx, torch.tensor([a]))
        actions.append(a)
        if a == UP:
            pitch = min(pitch + 1, pitch_limit)
        elif a == DOWN:
            pitch = max(pitch - 1, -pitch_limit)
        else:
            yaw += 1 if a == RIGHT else -1 if a == LEFT else 0
    return actions, guard


def test_row_search_moves_to_the_next_rows_after_a_turn():
    # 11 of 12 yaw cells seen (the 11th arrival, step 10): 5 forced UPs to row +5; there the band of rows 3..7 holds
    # the transit column only, so 10 more RIGHTs fill it to 11 cells; then 10 DOWNs to row -5 and 10 RIGHTs again;
    # the next rows (+10, then -10) are out of range, both skipped at once, so the search ends and the policy (with
    # its memory) acts freely
    actions, guard = row_walk(46, pitch_limit=90)
    assert actions[:45] == [RIGHT] * 10 + [UP] * 5 + [RIGHT] * 10 + [DOWN] * 10 + [RIGHT] * 10
    assert int(guard.row_k[0]) == 4 and not bool(guard.row_seek[0]) and int(guard.pitch[0]) == -5


def test_row_search_skips_a_row_beyond_the_pitch_limit():
    # the simulator stops the pitch at +-3: the 4th forced UP leaves the view unchanged, so the agent turns to
    # row -5; the 7th DOWN is blocked at -3 too; the row after (+10) is beyond the limit met above (and out of
    # range), skipped with the one after it (-10, beyond the limit met below): the search ends
    actions, guard = row_walk(30, pitch_limit=3)
    assert actions[:10] == [RIGHT] * 10
    assert actions[10:14] == [UP] * 4
    assert actions[14:21] == [DOWN] * 7 and actions[21:] == [RIGHT] * 9
    assert int(guard.row_k[0]) == 4 and not bool(guard.row_seek[0]) and int(guard.pitch[0]) == -3
    assert (int(guard.row_reach_hi[0]), int(guard.row_reach_lo[0])) == (3, -3)


def test_row_search_does_not_walk_again_to_rows_beyond_a_limit_it_met():
    # stride 2 on the 6-step grid, pitch limit 3: rows +2 and -2 lie in reach (each done on arrival, the band of
    # +-2 rows holds the start row's turn); +4 is walked to and blocked at 3 (5 UPs and the blocked try), -4 at -3
    # (6 DOWNs and the blocked try). Then +6 and -6 lie beyond both limits met: no move is forced for them (before,
    # each was walked to across the whole range again, 7 UPs then 7 DOWNs) and the policy turns on
    actions, guard = row_walk(60, pitch_limit=3, stride=2)
    assert actions[:12] == [RIGHT] * 10 + [UP] * 2
    assert actions[12:16] == [DOWN] * 4
    assert actions[16:22] == [UP] * 6 and actions[22:29] == [DOWN] * 7
    assert actions[29:] == [RIGHT] * 31
    assert (int(guard.row_reach_hi[0]), int(guard.row_reach_lo[0])) == (3, -3) and not bool(guard.row_seek[0])
    # the limits met are part of the resume state, and a new episode forgets them
    resumed = RevisitPenalty(1, 1.0, step_deg=30, rows=RowSearch(stride=2))
    resumed.load_state_dict(guard.state_dict())
    assert (int(resumed.row_reach_hi[0]), int(resumed.row_reach_lo[0])) == (3, -3)
    old = guard.state_dict()
    old["row"] = old["row"][:5]  # a state saved before the limits were kept: none met
    resumed.load_state_dict(old)
    assert (int(resumed.row_reach_hi[0]), int(resumed.row_reach_lo[0])) == (6, -6)
    guard.reset(torch.tensor([0]))
    assert (int(guard.row_reach_hi[0]), int(guard.row_reach_lo[0])) == (6, -6)


def test_row_search_after_a_step_leaves_the_policy_alone_until_then():
    # the row is looked around at the 11th arrival, but nothing is forced before step 16 (row_after 15): the policy
    # turns on (RIGHT 5 against 1 per earlier visit), then 5 forced UPs to row +5 and the walk of the test above
    actions, guard = row_walk(21, pitch_limit=90, row_after=15)
    assert actions[:15] == [RIGHT] * 15
    assert actions[15:20] == [UP] * 5 and actions[20] == RIGHT
    assert int(guard.row_k[0]) == 1 and int(guard.row_started[0]) == 16


def zigzag_walk(steps: int, row_budget: int) -> tuple[list[int], RevisitPenalty]:
    """On the 1-degree grid (360 yaw cells), a policy that zigzags: UP to pitch 3 in even columns, DOWN to 0 in odd
    ones, one RIGHT at each end (each preferred by 5 logits; every cell it visits is new, so the memory never
    charges it). Row search with stride 10 and a budget of ``row_budget`` steps per row (0: none)."""
    guard = RevisitPenalty(1, 1.0, rows=RowSearch(stride=10, budget=row_budget))
    idx, pitch, yaw, actions = torch.tensor([0]), 0, 0, []
    for _ in range(steps):
        logits = torch.tensor([[0.0, 0.0, 0.0, 0.0, -9.0]])
        if yaw % 2 == 0:
            logits[0, UP if pitch < 3 else RIGHT] = 5.0
        else:
            logits[0, DOWN if pitch > 0 else RIGHT] = 5.0
        a = int(guard.adjust(idx, pose_view(pitch, yaw)[None], logits).argmax(dim=-1))
        guard.moved(idx, torch.tensor([a]))
        actions.append(a)
        pitch += {UP: 1, DOWN: -1}.get(a, 0)
        yaw += {RIGHT: 1, LEFT: -1}.get(a, 0)
    return actions, guard


def test_row_budget_moves_a_zigzag_that_never_finishes_a_row_on():
    # the zigzag sees 1 new column per 4 steps: the band of rows -2..2 never holds 90% of 360 columns in 200
    # steps, so without a budget the row search never acts and the pitch stays in 0..3
    plain, guard = zigzag_walk(200, row_budget=0)
    assert set(plain) == {UP, DOWN, RIGHT} and int(guard.row_k[0]) == 0
    # budget 50: at the 51st arrival the row is given up, and UPs are forced from pitch p (0..3) to row +10; the
    # forced run starts at step 51 whatever the policy prefers there
    actions, guard = zigzag_walk(200, row_budget=50)
    assert actions[:50] == plain[:50]
    run = actions[50:].index(DOWN) if DOWN in actions[50:] else len(actions) - 50
    assert run >= 7 and actions[50:50 + 7] == [UP] * 7
    assert int(guard.row_k[0]) >= 1 and int(guard.row_started[0]) >= 51
    # the budget runs from the row's choice: the next row (-10) is chosen 50 steps after the first, or once row +10
    # is looked around, whichever comes first; the resume state keeps the step the row was chosen at
    resumed = RevisitPenalty(1, 1.0, rows=RowSearch(stride=10, budget=50))
    resumed.load_state_dict(guard.state_dict())
    assert int(resumed.row_started[0]) == int(guard.row_started[0]) and int(resumed.row_k[0]) == int(guard.row_k[0])
    assert int(resumed.clock[0]) == int(guard.clock[0]) == 200  # the budget counts on from where it was
    with pytest.raises(ValueError, match="need stride, after and budget >= 0"):
        RowSearch(stride=10, budget=-1)
    with pytest.raises(ValueError, match="need a row search"):  # no stride: nothing to start late or give up
        RowSearch(after=1000)


def pacing_walk(steps: int, hold: bool) -> list[tuple[int, int]]:
    """On the 1-degree grid, a policy that paces a column: UP (5 logits) until pitch +30, then DOWN (5) until -30,
    and so on, one RIGHT at each end, with STOP always its second choice (3 logits). Row search with stride 10 from
    the first step, no budget. Returns the (pitch, yaw) after each step."""
    guard = RevisitPenalty(1, 1.0, rows=RowSearch(stride=10, hold=hold))
    idx, pitch, yaw, going_up, poses = torch.tensor([0]), 0, 0, True, []
    for _ in range(steps):
        logits = torch.tensor([[0.0, 0.0, 0.0, 0.0, 3.0]])
        if going_up and pitch >= 30 or not going_up and pitch <= -30:
            going_up = not going_up
            logits[0, RIGHT] = 5.0
        else:
            logits[0, UP if going_up else DOWN] = 5.0
        a = int(guard.adjust(idx, pose_view(pitch, yaw)[None], logits).argmax(dim=-1))
        guard.moved(idx, torch.tensor([a]))
        assert a != STOP  # STOP is never the argmax, with or without the hold
        pitch += {UP: 1, DOWN: -1}.get(a, 0)
        yaw += {RIGHT: 1, LEFT: -1}.get(a, 0)
        poses.append((pitch, yaw))
    return poses


def test_row_hold_keeps_a_column_pacer_within_half_a_stride_of_its_row():
    """A policy that paces pitch -30..+30 leaves the start row (row 0 of a stride-10 search) at once; with the hold
    it stays within 5 steps of it (half the stride) and, barred from its pitch move at the band's edge, takes
    another move (never STOP, its second choice) instead, so it moves along the row."""
    free = pacing_walk(200, hold=False)
    assert max(p for p, _ in free) == 30 and min(p for p, _ in free) == -30
    held = pacing_walk(200, hold=True)
    assert max(p for p, _ in held) == 5 and min(p for p, _ in held) >= -5
    assert len({y for _, y in held}) > len({y for _, y in free})  # barred pitch moves became yaw moves
    with pytest.raises(ValueError, match="need a row search"):
        RowSearch(hold=True)


def test_stop_prob_stops_on_the_policys_own_stop_probability():
    """A policy whose output is fixed at P = (0.1, 0.1, 0.1, 0.4, 0.3) for (UP, DOWN, LEFT, RIGHT, STOP): the
    argmax turns RIGHT; with ``stop_prob`` 0.29 the agent stops (also with the search memory on, which would
    otherwise forbid STOP as a non-argmax action); with 0.31 it still turns (thresholds clear of the float32
    rounding of 0.3)."""
    from findview_baselines.agents.ppo_agent import PPOAgent
    from findview_baselines.rl.policy import Policy

    policy = Policy(32, 32, "direct", hidden_size=8)
    with torch.no_grad():
        policy.actor.weight.zero_()
        policy.actor.bias.copy_(torch.log(torch.tensor([0.1, 0.1, 0.1, 0.4, 0.3])))
    obs = {"view": torch.zeros(1, 3, 32, 32, dtype=torch.uint8), "target": torch.zeros(1, 3, 32, 32, dtype=torch.uint8)}

    def first_action(**kw) -> int:
        from findview.episode import Episode

        agent = PPOAgent(policy, 1, **kw)
        agent.reset([0], [Episode("e", "x.jpg", 0, 0, 0, 10, difficulty="easy", seed=1)])
        return int(agent.act(obs)[0])

    assert first_action() == RIGHT
    assert first_action(stop_prob=0.29) == STOP
    assert first_action(stop_prob=0.29, revisit_penalty=16.0) == STOP
    assert first_action(stop_prob=0.31) == RIGHT
    with pytest.raises(ValueError, match="stop_prob"):
        PPOAgent(policy, 1, stop_prob=0.0)


def test_stop_min_prob_refuses_an_unsure_stop_for_the_most_likely_move():
    """A policy fixed at P = (0.1, 0.05, 0.15, 0.2, 0.5) for (UP, DOWN, LEFT, RIGHT, STOP): the argmax stops. With
    ``stop_min_prob`` 0.51 the stop is refused and the agent takes the most likely move, RIGHT, with the search
    memory on as well; a sampling agent never draws STOP. 0.49 lets the stop stand; a threshold above ``stop_prob`` is refused."""
    from findview.episode import Episode
    from findview_baselines.agents.ppo_agent import PPOAgent
    from findview_baselines.rl.policy import Policy

    policy = Policy(32, 32, "direct", hidden_size=8)
    with torch.no_grad():
        policy.actor.weight.zero_()
        policy.actor.bias.copy_(torch.log(torch.tensor([0.1, 0.05, 0.15, 0.2, 0.5])))
    obs = {"view": torch.zeros(1, 3, 32, 32, dtype=torch.uint8), "target": torch.zeros(1, 3, 32, 32, dtype=torch.uint8)}

    def actions(steps: int = 1, **kw) -> list[int]:
        agent = PPOAgent(policy, 1, **kw)
        agent.reset([0], [Episode("e", "x.jpg", 0, 0, 0, 10, difficulty="easy", seed=1)])
        return [int(agent.act(obs)[0]) for _ in range(steps)]

    assert actions() == [STOP]
    assert actions(stop_min_prob=0.49) == [STOP]
    assert actions(stop_min_prob=0.51) == [RIGHT]
    # with the memory the refused stop leaves the moves to the memory, as a policy that has no STOP at all would
    no_stop = Policy(32, 32, "direct", hidden_size=8)
    with torch.no_grad():
        no_stop.actor.weight.zero_()
        no_stop.actor.bias.copy_(torch.log(torch.tensor([0.1, 0.05, 0.15, 0.2, 1e-30])))
    reference = PPOAgent(no_stop, 1, revisit_penalty=16.0)
    reference.reset([0], [Episode("e", "x.jpg", 0, 0, 0, 10, difficulty="easy", seed=1)])
    expected = [int(reference.act(obs)[0]) for _ in range(6)]
    assert expected[0] == RIGHT and len(set(expected)) > 1  # the memory does steer it
    assert actions(6, stop_min_prob=0.51, revisit_penalty=16.0) == expected
    # sampling: STOP (half the mass) is never drawn, the moves keep their odds among themselves
    sampled = actions(200, stop_min_prob=0.51, sample=True)
    assert STOP not in sampled and sampled.count(RIGHT) > sampled.count(DOWN)
    assert actions(stop_min_prob=0.5, stop_prob=0.5) == [STOP]  # stop_prob forces what stop_min_prob allows
    with pytest.raises(ValueError, match="stop_min_prob"):
        PPOAgent(policy, 1, stop_min_prob=0.0)
    with pytest.raises(ValueError, match="stop_min_prob"):
        PPOAgent(policy, 1, stop_prob=0.3, stop_min_prob=0.4)



def walk_guard(guard: RevisitPenalty, slot: int, moves: list[int]) -> None:
    """Walk slot ``slot`` of ``guard`` from (0, 0) through ``moves`` (a new view per pose), then arrive."""
    idx, pose = torch.tensor([slot]), [0, 0]
    for a in moves:
        guard.arrive(idx, pose_view(*pose)[None])
        guard.moved(idx, torch.tensor([a]))
        pose[0] += {UP: 1, DOWN: -1}.get(a, 0)
        pose[1] += {RIGHT: 1, LEFT: -1}.get(a, 0)
    guard.arrive(idx, pose_view(*pose)[None])


def test_near_visits_are_counted_beside_a_moves_destination():
    # visited: row 0, yaw 0..3; then (1, 3), (2, 3); now at (2, 2). Worked by hand, in UP, DOWN, LEFT, RIGHT order:
    # exact cells (penalty 2 per visit): UP (3, 2) 0, DOWN (1, 2) 0, LEFT (2, 1) 0, RIGHT (2, 3) 1 -> [0, 0, 0, 2].
    # near rows 2 (0.5 per visit of the most visited near cell): UP reads yaw 2, rows 4, 5 (none); DOWN yaw 2, rows
    # 0, -1 (row 0 visited); LEFT yaw 1, rows 0, 1, 3, 4 (row 0); RIGHT yaw 3, rows 0, 1, 3, 4 (rows 0 and 1).
    moves = [RIGHT, RIGHT, RIGHT, UP, UP, LEFT]
    exact = RevisitPenalty(1, 2.0)
    near = RevisitPenalty(2, 2.0, near=NearVisits(2, 0.5, 1))
    walk_guard(exact, 0, moves)
    walk_guard(near, 1, moves)  # slot 1 of two: the gathers are batched over slots
    assert exact.move_penalties(torch.tensor([0])).tolist() == [[0.0, 0.0, 0.0, 2.0]]
    assert near.move_penalties(torch.tensor([1])).tolist() == [[0.0, 0.5, 0.5, 2.5]]
    assert near.move_penalties(torch.tensor([0])).tolist() == [[0.0, 0.0, 0.0, 0.0]]  # slot 0 never moved
    # near rows 1: DOWN reads yaw 2, row 0 (visited); LEFT yaw 1, rows 1, 3 (none); RIGHT yaw 3, rows 1, 3 (row 1)
    narrow = RevisitPenalty(1, 2.0, near=NearVisits(1, 0.5, 1))
    walk_guard(narrow, 0, moves)
    assert narrow.move_penalties(torch.tensor([0])).tolist() == [[0.0, 0.5, 0.0, 2.5]]
    # near_age 5: one step per arrival, so the clock at (2, 2) reads 7; yaw 2 of row 0 was last visited at step 3
    # (4 steps ago: too recent, DOWN is free), yaw 1 at step 2 (5 steps ago: LEFT pays), yaw 3 of row 0 at step 4
    # and of row 1 at step 5 (too recent: RIGHT pays its exact visit only)
    aged = RevisitPenalty(1, 2.0, near=NearVisits(2, 0.5, 5))
    walk_guard(aged, 0, moves)
    assert aged.move_penalties(torch.tensor([0])).tolist() == [[0.0, 0.0, 0.5, 2.0]]
    resumed = RevisitPenalty(1, 2.0, near=NearVisits(2, 0.5, 5))
    resumed.load_state_dict(aged.state_dict())  # the resume state keeps the ages
    assert resumed.move_penalties(torch.tensor([0])).tolist() == [[0.0, 0.0, 0.5, 2.0]]
    # near since 5: only visits made at step 5 or later are near ones: (1, 3) at 5, (2, 3) at 6, (2, 2) at 7. DOWN's
    # yaw 2 of row 0 (step 3) and LEFT's yaw 1 of row 0 (step 2) no longer count; RIGHT's (1, 3) does (since 6: not)
    for since, right in ((5, 2.5), (6, 2.0)):
        recent = RevisitPenalty(1, 2.0, near=NearVisits(2, 0.5, 1, since=since))
        walk_guard(recent, 0, moves)
        assert recent.move_penalties(torch.tensor([0])).tolist() == [[0.0, 0.0, 0.0, right]]
    # until 0.5: the flag the agent sets once its net finds the view near. Measured 0.5 on slot 1 of two (at the bar)
    # and 0.49 on slot 0: slot 1 pays its exact visits only (RIGHT's 2.0), slot 0 its near ones too; a reset clears
    # the flag, a resume keeps it
    found = RevisitPenalty(2, 2.0, near=NearVisits(2, 0.5, 1, until=0.5))
    walk_guard(found, 0, moves)
    walk_guard(found, 1, moves)
    found.found_near(torch.tensor([0, 1]), torch.tensor([0.49, 0.5]))
    assert found.move_penalties(torch.tensor([0, 1])).tolist() == [[0.0, 0.5, 0.5, 2.5], [0.0, 0.0, 0.0, 2.0]]
    kept = RevisitPenalty(2, 2.0, near=NearVisits(2, 0.5, 1, until=0.5))
    kept.load_state_dict(found.state_dict())
    assert kept.move_penalties(torch.tensor([1])).tolist() == [[0.0, 0.0, 0.0, 2.0]]
    found.reset(torch.tensor([1]))
    walk_guard(found, 1, moves)
    assert found.move_penalties(torch.tensor([1])).tolist() == [[0.0, 0.5, 0.5, 2.5]]
    unset = RevisitPenalty(1, 2.0, near=NearVisits(2, 0.5, 1))  # without until the flag is never set
    walk_guard(unset, 0, moves)
    unset.found_near(torch.tensor([0]), torch.tensor([0.9]))
    assert unset.move_penalties(torch.tensor([0])).tolist() == [[0.0, 0.5, 0.5, 2.5]]
    for bad in ({"rows": -1, "penalty": 1.0}, {"rows": 2}, {"rows": 2, "penalty": 1.0, "age": 0},
                {"rows": 2, "penalty": 1.0, "since": -1}, {"rows": 2, "penalty": 1.0, "until": 1.0},
                {"rows": 2, "penalty": 1.0, "until": -0.1}):
        with pytest.raises(ValueError, match="near visits"):
            RevisitPenalty(1, 1.0, near=NearVisits(**bad))
    # a resume state saved without near visits has no ages to restore: refused, not silently aged
    with pytest.raises(ValueError, match="saved without near visits"):
        RevisitPenalty(1, 2.0, near=NearVisits(2, 0.5, 5)).load_state_dict(exact.state_dict())


def test_near_visits_stop_a_resweep_of_the_same_yaw_one_row_up():
    # a policy that pans RIGHT over yaw 0..5 on even rows and LEFT back on odd ones, climbing one row (UP, logit 0)
    # at each end (a search that keeps going back over what it has seen, as a learned agent drawn to a look-alike
    # region does). Exact cells never repeat, so the plain memory lets it pan every row. With near rows 2 (penalty 3,
    # any age) a pan over yaw seen within 2 rows costs 3 per step (1 - 3 < UP's 0): it climbs until the pan is 3 rows
    # from the last.
    def panned_rows(near_rows: int, near_age: int = 1) -> list[int]:
        guard = RevisitPenalty(1, 3.0, near=NearVisits(near_rows, 3.0, near_age))
        idx, pose, rows = torch.tensor([0]), [0, 0], []
        for _ in range(24):
            logits = torch.tensor([[0.0, -9.0, -9.0, -9.0, -9.0]])
            if pose[0] % 2 == 0 and pose[1] < 5:
                logits[0, RIGHT] = 1.0
            elif pose[0] % 2 == 1 and pose[1] > 0:
                logits[0, LEFT] = 1.0
            a = int(guard.adjust(idx, pose_view(*pose)[None], logits).argmax(dim=-1))
            guard.moved(idx, torch.tensor([a]))
            pose[0] += {UP: 1, DOWN: -1}.get(a, 0)
            pose[1] += {RIGHT: 1, LEFT: -1}.get(a, 0)
            if a in (LEFT, RIGHT):
                rows.append(pose[0])
        return sorted(set(rows))

    # 24 steps: 5 pan moves and 1 climb per row (plain); 5 pan moves and 3 climbs per panned row (near rows 2)
    assert panned_rows(0) == [0, 1, 2, 3]
    assert panned_rows(2) == [0, 3, 6]
    # visits younger than near_age do not count: with an age of 100 steps the 24-step walk is the plain one
    assert panned_rows(2, near_age=100) == [0, 1, 2, 3]
