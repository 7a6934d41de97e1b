"""The learned agent's anytime stop (``agent.stop_by``, findview_baselines/agents/give_up.py), against hand-worked
walks on a toy 1-degree world."""

from __future__ import annotations

import pytest
import torch

from _stand_in import StandInPolicy
from findview.episode import Episode
from findview_baselines.agents.base import DOWN, LEFT, RIGHT, STOP, UP
from findview_baselines.agents.give_up import GiveUp


def test_walk_goes_pitch_first_then_yaw_the_short_way_round_and_stops():
    g = GiveUp(1, stop_by=100, yaw_cells=360)
    idx = torch.tensor([0])
    g.observe(idx, torch.tensor([0.5]), torch.tensor([3]), torch.tensor([358]))  # best pose: pitch +3, yaw -2
    pitch, yaw, moves = 0, 5, []
    for _ in range(20):
        a = int(g.walk(idx, torch.tensor([pitch]), torch.tensor([yaw]))[0])
        moves.append(a)
        if a == STOP:
            break
        pitch += {UP: 1, DOWN: -1}.get(a, 0)
        yaw = (yaw + {RIGHT: 1, LEFT: -1}.get(a, 0)) % 360
    # from (0, 5) to (3, 358): 3 x UP, then 7 x LEFT through yaw 0 (not 353 x RIGHT), then STOP
    assert moves == [UP] * 3 + [LEFT] * 7 + [STOP]
    assert not bool(g.returning[0])


def test_observe_gives_up_when_the_steps_left_just_cover_the_walk():
    """Best pose 10 moves away, margin 5: the walk's STOP lands on step stop_by exactly when the slot gives up at
    step stop_by - 10 - 5 + ... : at act s, s + 10 + 5 >= 100 first holds at s = 85."""
    g = GiveUp(1, stop_by=100, yaw_cells=360, margin=5)
    idx = torch.tensor([0])
    g.observe(idx, torch.tensor([0.9]), torch.tensor([0]), torch.tensor([0]))  # act 1: best pose at the start
    due_at = None
    for s in range(2, 100):
        # the agent stands 10 yaw steps to the right of its best pose, with a lower STOP probability
        if bool(g.observe(idx, torch.tensor([0.01]), torch.tensor([0]), torch.tensor([10]))[0]):
            due_at = s
            break
    assert due_at == 85
    assert int(g.distance(idx, torch.tensor([0]), torch.tensor([10]))[0]) == 10


def test_a_stop_head_never_sure_enough_does_not_walk_back():
    g = GiveUp(2, stop_by=10, yaw_cells=360, min_prob=0.1)
    idx = torch.tensor([0, 1])
    due = None
    for _ in range(12):
        due = g.observe(idx, torch.tensor([0.09, 0.11]), torch.tensor([0, 0]), torch.tensor([0, 0]))
    assert due.tolist() == [False, True]
    with pytest.raises(ValueError, match="min_prob"):
        GiveUp(1, stop_by=10, yaw_cells=360, min_prob=1.5)
    with pytest.raises(ValueError, match="stop_by"):
        GiveUp(1, stop_by=0, yaw_cells=360)


class RingPolicy(StandInPolicy):
    """A stand-in network for the learned agent: it always prefers RIGHT (with the search memory it circles its row,
    then moves on) and never stops by itself; where the view's pixels encode pitch 0 and yaw ``sure_yaw`` its STOP
    probability is ``sure`` (0.001 elsewhere)."""

    def __init__(self, sure_yaw: int, sure: float) -> None:
        super().__init__()
        self.sure_yaw, self.sure = sure_yaw, sure

    def forward(self, obs, hidden, masks, memory=None):  # noqa: ANN001, ANN201
        yaw = obs["view"][:, 0, 0, 0].long() + 256 * obs["view"][:, 1, 0, 0].long()
        pitch = obs["view"][:, 2, 0, 0].long() - 128
        stop = torch.where((yaw == self.sure_yaw) & (pitch == 0), torch.tensor(self.sure), torch.tensor(0.001))
        right = 1.0 - stop - 0.003
        probs = torch.stack([torch.full_like(stop, 0.001)] * 3 + [right, stop], dim=1)
        return torch.distributions.Categorical(probs=probs), torch.zeros(len(yaw)), hidden


def run_ring(stop_by: int, sure: float, T: int = 1000) -> tuple[list[int], tuple[int, int], int]:
    """The agent on a toy world of 1-degree poses (the view encodes pitch and yaw) from (0, 0) for up to T steps:
    its actions, final (pitch, yaw) (degrees, yaw 0..359) and the step of its STOP (0 if none)."""
    from findview_baselines.agents.ppo_agent import PPOAgent

    agent = PPOAgent(RingPolicy(sure_yaw=40, sure=sure), 1, revisit_penalty=16.0, stop_by=stop_by)
    agent.reset([0], [Episode("e", "x.jpg", 0, 0, 0, 10, difficulty="easy", seed=1)])
    pitch, yaw, actions = 0, 0, []
    for step in range(1, T + 1):
        view = torch.zeros(1, 3, 8, 8, dtype=torch.uint8)
        view[0, 0], view[0, 1], view[0, 2] = yaw % 256, yaw // 256, pitch + 128
        a = int(agent.act({"view": view, "target": torch.zeros_like(view)})[0])
        actions.append(a)
        if a == STOP:
            return actions, (pitch, yaw), step
        pitch += {UP: 1, DOWN: -1}.get(a, 0)
        yaw = (yaw + {RIGHT: 1, LEFT: -1}.get(a, 0)) % 360
    return actions, (pitch, yaw), 0


def test_the_agent_walks_back_to_its_most_stop_like_view_by_step_T():
    # turning right it passes (0, 40) (STOP probability 0.3, never its argmax) in its first turn, then searches
    # on; when the walk home needs the steps left it goes back there and stops, by step T
    actions, pose, stopped_at = run_ring(stop_by=1000, sure=0.3)
    assert pose == (0, 40)
    # the walk starts at the first act s with s + d + 1 >= T (d: its moves; margin 1 without the refinement), and
    # s + d grows by 0 or 2 per act, so its STOP (act s + d) is act T - 1 or T: the whole budget was searched
    assert stopped_at in (999, 1000)
    assert actions[:359] == [RIGHT] * 359  # the policy's own first turn (then the memory sends it up a row)
    # off: it circles until T; a stop head below min_prob (0.1) is not trusted either
    assert run_ring(stop_by=0, sure=0.3)[2] == 0
    assert run_ring(stop_by=1000, sure=0.05)[2] == 0


def test_stop_by_needs_the_search_memory():
    from findview_baselines.agents.ppo_agent import PPOAgent

    with pytest.raises(ValueError, match="search memory"):
        PPOAgent(RingPolicy(0, 0.3), 1, stop_by=1000)
    with pytest.raises(ValueError, match="stop_by_phase"):
        PPOAgent(RingPolicy(0, 0.3), 1, revisit_penalty=16.0, fov=90.0, stop_by_phase=True)  # no stop_by
    with pytest.raises(ValueError, match="stop_by_phase"):
        PPOAgent(RingPolicy(0, 0.3), 1, revisit_penalty=16.0, stop_by=1000, stop_by_phase=True)  # no fov


def test_phase_goal_is_the_pose_plus_the_shift_measured_at_the_clearest_peak():
    """Two measurements: the clearer one (peak 0.4 at (2, 10), target measured 3.4 degrees up and 5.6 to the left)
    sets the goal to (2 + 3, 10 - 6) = (5, 4); a stop head that reached min_prob walks to its own best pose instead."""
    g = GiveUp(2, stop_by=50, yaw_cells=360, min_prob=0.1, phase=True)
    idx = torch.tensor([0, 1])
    g.observe_phase(idx, torch.tensor([0.4, 0.4]), torch.tensor([2, 2]), torch.tensor([10, 10]),
                    torch.tensor([3.4, 3.4]), torch.tensor([-5.6, -5.6]))
    g.observe_phase(idx, torch.tensor([0.2, 0.2]), torch.tensor([0, 0]), torch.tensor([0, 0]),
                    torch.tensor([-30.0, -30.0]), torch.tensor([90.0, 90.0]))  # a weaker peak does not replace it
    due = None
    for _ in range(50):  # slot 0's stop head stays at 0.01, slot 1's reached 0.5 at (0, 0) on the first step
        due = g.observe(idx, torch.tensor([0.01, 0.5 if due is None else 0.01]), torch.tensor([0, 0]), torch.tensor([0, 0]))
        if bool(due.all()):
            break
    assert due.tolist() == [True, True]
    assert g.by_phase(idx).tolist() == [True, False]
    assert g.distance(idx, torch.tensor([0, 0]), torch.tensor([0, 0])).tolist() == [5 + 4, 0]
    # without phase the never-sure slot does not walk
    g_off = GiveUp(1, stop_by=50, yaw_cells=360, min_prob=0.1)
    g_off.observe_phase(torch.tensor([0]), torch.tensor([0.4]), torch.tensor([2]), torch.tensor([10]),
                        torch.tensor([3.4]), torch.tensor([-5.6]))
    assert not any(bool(g_off.observe(torch.tensor([0]), torch.tensor([0.01]), torch.tensor([0]), torch.tensor([0]))[0])
                   for _ in range(60))


def test_a_walk_blocked_in_pitch_keeps_its_pitch_and_turns():
    """A phase goal 4 rows above a pitch limit the slot reaches after 2 UP moves: the blocked UP ends the pitch part
    of the walk, the yaw part follows, then STOP."""
    g = GiveUp(1, stop_by=100, yaw_cells=360, phase=True)
    idx = torch.tensor([0])
    g.observe_phase(idx, torch.tensor([0.3]), torch.tensor([0]), torch.tensor([0]), torch.tensor([4.0]), torch.tensor([3.0]))
    pitch, yaw, moves, blocked = 0, 0, [], False
    for _ in range(20):
        a = int(g.walk(idx, torch.tensor([pitch]), torch.tensor([yaw]), torch.tensor([blocked]))[0])
        moves.append(a)
        if a == STOP:
            break
        blocked = a == UP and pitch == 2  # the limit
        pitch += 1 if a == UP and not blocked else 0
        yaw += 1 if a == RIGHT else 0
    assert moves == [UP, UP, UP, RIGHT, RIGHT, RIGHT, STOP]
    assert (pitch, yaw) == (2, 3)
    # without phase a blocked move changes nothing: the walk back to a visited pose keeps asking for its pitch
    g_off = GiveUp(1, stop_by=100, yaw_cells=360)
    g_off.observe(idx, torch.tensor([0.5]), torch.tensor([4]), torch.tensor([3]))  # best pose (4, 3)
    first = int(g_off.walk(idx, torch.tensor([0]), torch.tensor([0]), torch.tensor([False]))[0])
    again = [int(g_off.walk(idx, torch.tensor([1]), torch.tensor([0]), torch.tensor([True]))[0]) for _ in range(3)]
    assert [first] + again == [UP] * 4


def test_each_episode_measures_against_its_own_target():
    """The target spectrum is taken once per episode: a slot that starts a new episode measures against the new
    target, not the one of its previous episode."""
    from findview_baselines.agents.ppo_agent import PPOAgent
    from findview_baselines.agents.stop_refine import phase_spectrum

    agent = PPOAgent(BlindPolicy(), 1, revisit_penalty=16.0, fov=90.0, stop_by=1000, stop_by_phase=True)
    gen = torch.Generator().manual_seed(0)
    frames = [torch.randint(0, 256, (1, 3, 64, 64), dtype=torch.uint8, generator=gen) for _ in range(3)]
    for k, target in enumerate(frames[1:]):
        agent.reset([0], [Episode(f"e{k}", "x.jpg", 0, 0, 0, 10, difficulty="easy", seed=k)])
        assert not bool(agent.give_up.spectrum_fresh[0])
        agent.act({"view": frames[0], "target": target})
        assert torch.equal(agent.give_up.target_spectra[0], phase_spectrum(target, 1)[0])


class BlindPolicy(StandInPolicy):
    """A stop head that never recognises the target (STOP probability 0.001 everywhere) and a preference for RIGHT:
    with the search memory the agent circles its row."""

    height = width = 64

    def forward(self, obs, hidden, masks, memory=None):  # noqa: ANN001, ANN201
        n = obs["view"].shape[0]
        probs = torch.tensor([[0.001, 0.001, 0.001, 0.996, 0.001]]).expand(n, 5)
        return torch.distributions.Categorical(probs=probs), torch.zeros(n), hidden


@pytest.mark.parametrize("kind, seed", [("village", 4), ("room", 3)])
def test_stop_by_phase_finds_a_target_the_stop_head_never_recognises(tmp_path, kind: str, seed: int):
    """A synthetic panorama, the target 6 degrees above the start row and 100 degrees to the right, an agent whose
    stop head never passes 0.001: with ``stop_by_phase`` (and the stop refinement) it walks back after its turn to
    where phase correlation pointed and stops exactly on the target by step T; with ``stop_by`` alone it runs out of
    steps wherever its search took it."""
    import cv2

    from findview.dataset import generate_panorama
    from findview.sim import PanoramaBank, Simulator
    from findview.task import FindViewEnv, StaticEpisodeSource
    from findview_baselines.agents.ppo_agent import PPOAgent
    from findview_baselines.agents.stop_refine import StopRefiner

    path = tmp_path / f"{kind}.png"
    cv2.imwrite(str(path), cv2.cvtColor(generate_panorama(seed, kind, 1024), cv2.COLOR_RGB2BGR))
    T = 500
    results = {}
    for phase in (False, True):
        episode = Episode("e", str(path), 0, 0, 6, 100, difficulty="medium", seed=1)
        bank = PanoramaBank("cpu", 256, min_slots=1, prefetch_workers=0)
        env = FindViewEnv(Simulator(bank, fov=90.0, height=64, width=64), StaticEpisodeSource([episode]), 1,
                          max_steps=T, auto_reset=False)
        agent = PPOAgent(BlindPolicy(), 1, revisit_penalty=16.0, refiner=StopRefiner(1, 90.0), fov=90.0,
                         stop_by=T, stop_by_phase=phase)
        obs = env.reset()
        agent.reset([0], [episode])
        info = None
        for _ in range(T):
            obs, _, done, infos = env.step(agent.act(obs))
            if bool(done[0]):
                info = infos[0]
                break
        results[phase] = info
    assert results[True]["called_stop"] and results[True]["eps"] == 0
    assert results[True]["steps"] <= T
    assert not results[False]["called_stop"] and results[False]["eps"] > 20
