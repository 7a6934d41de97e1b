"""The learned agent's mirror play (``agent.mirror_steps``, findview_baselines/agents/ppo_agent.py): the fused
distribution against hand-computed values, and the agent on toy worlds whose views tell a stand-in network where
to turn."""

from __future__ import annotations

import math

import pytest
import torch

from _stand_in import StandInPolicy
from findview_baselines.agents.base import LEFT, RIGHT, STOP, UP
from findview_baselines.agents.ppo_agent import PPOAgent, mirror_mean


def log_probs(*rows: list[float]) -> torch.Tensor:
    return torch.tensor(rows, dtype=torch.float64).log()


def test_a_network_that_acts_the_same_in_a_mirror_is_unchanged():
    # a mirror-symmetric network gives the mirrored episode its distribution with LEFT and RIGHT swapped
    own = [0.1, 0.05, 0.25, 0.5, 0.1]  # UP, DOWN, LEFT, RIGHT, STOP
    mirrored = [0.1, 0.05, 0.5, 0.25, 0.1]
    fused = mirror_mean(log_probs(own, mirrored), 1).probs[0]
    assert torch.allclose(fused, torch.tensor(own, dtype=torch.float64))


def test_the_fused_distribution_is_the_normalised_geometric_mean():
    own = [0.1, 0.1, 0.2, 0.5, 0.1]
    mirrored = [0.3, 0.1, 0.4, 0.1, 0.1]  # in the mirror's own frame: its LEFT is the episode's RIGHT
    # by hand: sqrt(own * mirrored in the episode's frame) = sqrt([.03, .01, .02, .2, .01]), then normalised
    geo = [math.sqrt(x) for x in (0.1 * 0.3, 0.1 * 0.1, 0.2 * 0.1, 0.5 * 0.4, 0.1 * 0.1)]
    expected = torch.tensor([g / sum(geo) for g in geo], dtype=torch.float64)
    assert torch.allclose(mirror_mean(log_probs(own, mirrored), 1).probs[0], expected)
    # several episodes: rows 0..K-1 are the episodes, K..2K-1 their mirrors
    two = mirror_mean(log_probs(own, [0.2] * 5, mirrored, [0.2] * 5), 2).probs
    assert torch.allclose(two[0], expected)
    assert torch.allclose(two[1], torch.full((5,), 0.2, dtype=torch.float64))
    with pytest.raises(ValueError, match="2 x 2 rows"):
        mirror_mean(log_probs(own, mirrored, own), 2)


def test_when_the_plays_disagree_about_turning_back_the_one_going_on_leads():
    # the episode prefers RIGHT (0.6 against LEFT 0.2); its mirror, in the episode's frame, prefers LEFT (0.7 / 0.1)
    own = [0.1, 0.05, 0.2, 0.6, 0.05]
    mirrored = [0.1, 0.05, 0.1, 0.7, 0.05]  # own frame: RIGHT 0.7 = the episode's LEFT
    mirrored_here = [0.1, 0.05, 0.7, 0.1, 0.05]  # the same in the episode's frame
    pair = log_probs(own, mirrored)
    free = mirror_mean(pair, 1).probs[0]
    # by hand: LEFT sqrt(.2 * .7) = 0.374 beats RIGHT sqrt(.6 * .1) = 0.245
    assert int(free.argmax()) == LEFT
    # heading RIGHT: the mirror would turn back, the episode's own play goes on: its distribution alone
    assert mirror_mean(pair, 1, torch.tensor([RIGHT])).probs[0].tolist() == pytest.approx(own)
    # heading LEFT: now the mirror goes on and leads
    assert mirror_mean(pair, 1, torch.tensor([LEFT])).probs[0].tolist() == pytest.approx(mirrored_here)
    # no yaw move yet (-1, or UP as the last move): the geometric mean
    assert torch.allclose(mirror_mean(pair, 1, torch.tensor([-1])).probs[0], free)
    assert torch.allclose(mirror_mean(pair, 1, torch.tensor([UP])).probs[0], free)
    # both plays want to turn back (or both to go on): the geometric mean, which turns back
    both_left = log_probs([0.1, 0.05, 0.6, 0.2, 0.05], mirrored)
    assert torch.allclose(mirror_mean(both_left, 1, torch.tensor([RIGHT])).probs[0],
                          mirror_mean(both_left, 1).probs[0])
    assert int(mirror_mean(both_left, 1, torch.tensor([RIGHT])).probs[0].argmax()) == LEFT
    # the leader's moves, but STOP needs both plays: its log-probability stays the mean of the two
    stopper = [0.1, 0.05, 0.05, 0.3, 0.5]  # own frame: LEFT 0.05 is the episode's RIGHT; STOP 0.5
    led = mirror_mean(log_probs(own, stopper), 1, torch.tensor([LEFT])).probs[0]
    # by hand: the mirror goes on (episode's LEFT 0.3 > RIGHT 0.05) and leads: [.1, .05, .3, .05] and STOP sqrt(.05 * .5)
    unnormalised = [0.1, 0.05, 0.3, 0.05, math.sqrt(0.05 * 0.5)]
    assert led.tolist() == pytest.approx([x / sum(unnormalised) for x in unnormalised])
    assert int(led.argmax()) == LEFT  # alone, the mirror would have stopped
    # one row per episode: two episodes heading RIGHT and LEFT in one call
    rows = mirror_mean(log_probs(own, own, mirrored, mirrored), 2, torch.tensor([RIGHT, LEFT])).probs
    assert rows[0].tolist() == pytest.approx(own) and rows[1].tolist() == pytest.approx(mirrored_here)


class HalvesPolicy(StandInPolicy):
    """A stand-in network that reads the two halves of its view (8x8 pixels; ``s``, ``r``: the means of the left and
    right halves, 0..1). ``detector``: RIGHT 0.97 where the right half is the brighter (a target it sees on its
    right), else RIGHT 0.6 and LEFT 0.3 (it misses a target on its left); otherwise RIGHT 0.45 + 0.4 ``s`` and LEFT
    0.45 - 0.4 ``s`` (a search that turns right). Its GRU state adds ``s`` every step, so each play's state says
    which pictures it saw."""

    def __init__(self, detector: bool) -> None:
        super().__init__()
        self.detector = detector

    def forward(self, obs, hidden, masks, memory=None):  # noqa: ANN001, ANN201
        view = obs["view"].double() / 255.0
        s, r = view[..., :4].mean(dim=(1, 2, 3)), view[..., 4:].mean(dim=(1, 2, 3))
        if self.detector:
            # sees a target on its right (right half brighter): RIGHT 0.97; otherwise it turns right anyway, unsure
            right = torch.where(r > s + 0.1, 0.97, 0.6)
            left = torch.where(r > s + 0.1, 0.01, 0.3)
        else:
            # always prefers RIGHT, the more so the brighter the left half
            right, left = 0.45 + 0.4 * s, 0.45 - 0.4 * s
        rest = (1.0 - right - left) / 3
        probs = torch.stack([rest, rest, left, right, rest], dim=1)
        return torch.distributions.Categorical(probs=probs), torch.zeros(len(s)), hidden + s[:, None].float()


def halves(left: int, right: int) -> torch.Tensor:
    view = torch.zeros(1, 3, 8, 8, dtype=torch.uint8)
    view[..., :4], view[..., 4:] = left, right
    return view


def test_the_mirror_finds_a_target_on_the_side_the_network_misses():
    target = torch.zeros(1, 3, 8, 8, dtype=torch.uint8)
    for mirror_steps, side in ((0, RIGHT), (5, LEFT)):
        agent = PPOAgent(HalvesPolicy(detector=True), 1, mirror_steps=mirror_steps)
        # target on the left: the network alone turns right (0.6); its mirror sees it on its right (0.97)
        assert int(agent.act({"view": halves(200, 0), "target": target})[0]) == side
    # target on the right: both turn right
    agent = PPOAgent(HalvesPolicy(detector=True), 1, mirror_steps=5)
    assert int(agent.act({"view": halves(0, 200), "target": target})[0]) == RIGHT


def test_each_play_keeps_its_own_state_for_mirror_steps_then_the_network_acts_alone():
    target = torch.zeros(1, 3, 8, 8, dtype=torch.uint8)
    agent = PPOAgent(HalvesPolicy(detector=True), 1, mirror_steps=2)
    for _ in range(3):
        agent.act({"view": halves(51, 153), "target": target})  # left half 0.2, right half 0.6
    # the network's state saw the left half 3 times; the mirror's saw the flipped view's left half (0.6) twice
    assert agent.hidden[0, 0].item() == pytest.approx(0.6)
    assert agent.hidden_mirror[0, 0].item() == pytest.approx(1.2)
    # step 3 was the network's alone: its target on the left is missed (RIGHT), where steps 1-2 turned LEFT
    agent.reset([0], [None])
    agent.done[:] = False
    actions = [int(agent.act({"view": halves(200, 0), "target": target})[0]) for _ in range(3)]
    assert actions == [LEFT, LEFT, RIGHT]
    assert agent.hidden_mirror[0, 0].item() == pytest.approx(0.0)  # reset, then two flipped right halves of 0
    with pytest.raises(ValueError, match="mirror_steps"):
        PPOAgent(HalvesPolicy(detector=True), 1, mirror_steps=-1)


def test_a_network_that_searches_turning_right_does_not_turn_back_and_forth_with_its_mirror():
    # a ring of 1-degree poses whose views alternate: even yaw bright on the left, odd yaw bright on the right. The
    # network always prefers RIGHT; its mirror (which prefers its own RIGHT, the episode's LEFT) is the surer of the
    # two at odd yaw, so the plain geometric mean would turn back there every time; the play going on leads instead
    target = torch.zeros(1, 3, 8, 8, dtype=torch.uint8)

    def view(yaw: int) -> torch.Tensor:
        return halves(230, 20) if yaw % 2 == 0 else halves(20, 230)

    policy = HalvesPolicy(detector=False)
    at_odd = torch.cat([policy({"view": v, "target": target}, torch.zeros(1, 1), None)[0].logits
                        for v in (view(1), view(1).flip(-1))])
    assert int(mirror_mean(at_odd, 1).probs[0].argmax()) == LEFT  # the pull this test is about
    agent = PPOAgent(policy, 1, mirror_steps=1000)
    yaw, moves = 0, []
    for _ in range(100):
        a = int(agent.act({"view": view(yaw), "target": target})[0])
        moves.append(a)
        yaw += {RIGHT: 1, LEFT: -1}[a]
    assert moves == [RIGHT] * 100  # the first move: RIGHT at even yaw; after it the episode's own play leads


def test_a_real_network_reading_its_memory_plays_its_mirror_for_the_first_steps():
    """The learned network (the ``phase`` variant with search-memory inputs, as the robust files) acts with the mirror
    on: every action is a valid move, the mirror's state moves for the first ``mirror_steps`` steps only, and a slot
    whose episode restarts starts its mirror again."""
    from findview_baselines.rl.policy import Policy
    from findview_baselines.rl.search_memory import MEMORY_FEATURES

    torch.manual_seed(0)
    policy = Policy(64, 64, variant="phase", hidden_size=16, memory_inputs=MEMORY_FEATURES)
    agent = PPOAgent(policy, 3, revisit_penalty=16.0, fov=90.0, mirror_steps=2)
    gen = torch.Generator().manual_seed(1)
    target = torch.randint(0, 256, (3, 3, 64, 64), dtype=torch.uint8, generator=gen)
    states = []
    for _ in range(4):
        view = torch.randint(0, 256, (3, 3, 64, 64), dtype=torch.uint8, generator=gen)
        actions = agent.act({"view": view, "target": target})
        assert actions.shape == (3,) and bool(((actions >= 0) & (actions <= STOP)).all())
        states.append(agent.hidden_mirror.clone())
        agent.done[:] = False  # keep every slot acting
    assert not torch.equal(states[0], states[1])  # steps 1 and 2 play the mirror
    assert torch.equal(states[1], states[2]) and torch.equal(states[2], states[3])  # steps 3 and 4 do not
    assert agent.policy_steps.tolist() == [4, 4, 4]
    agent.reset([1], [None])
    assert agent.policy_steps.tolist() == [4, 0, 4] and float(agent.hidden_mirror[1].abs().sum()) == 0.0
