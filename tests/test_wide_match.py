"""The wide match (``agent.wide_match``, rl/wide_match.py): the overlap ZNCC against a hand computation, its peak on
known shifts (wide ones included) and rendered yaw offsets, its invariances, and the policy / checkpoint / agent
plumbing."""

from __future__ import annotations

import pytest
import torch

from _growable import check_grows_from_a_checkpoint_without_it
from _stand_in import StandInPolicy
from findview.sim.equi2pers import equi2pers
from findview_baselines.agents.ppo_agent import TURN_MIN_SHIFT, PPOAgent
from findview_baselines.rl.checkpoint import checkpoint_payload, save_checkpoint
from findview_baselines.rl.policy import WIDE_ON, Policy
from findview_baselines.rl.wide_match import (
    LOW, MIN_OVERLAP, WIDE_BINS, WIDE_FEATURES, WIDE_PEAK, WideMatch, overlap_zncc,
)

pytestmark = pytest.mark.usefixtures("one_torch_thread")


def zncc_by_hand(view: torch.Tensor, target: torch.Tensor, dy: int, dx: int) -> float:
    """ZNCC of view[y + dy, x + dx] with target[y, x] over the pixels where both exist, by explicit slicing."""
    h, w = view.shape
    ys, xs = slice(max(0, -dy), min(h, h - dy)), slice(max(0, -dx), min(w, w - dx))
    t = target[ys, xs].double()
    v = view[max(0, dy):min(h, h + dy), max(0, dx):min(w, w + dx)].double()
    v, t = v - v.mean(), t - t.mean()
    return float((v * t).sum() / (v.square().sum() * t.square().sum()).sqrt())


def test_every_shift_matches_the_hand_computation() -> None:
    gen = torch.Generator().manual_seed(0)
    view, target = torch.rand(2, 7, 9, generator=gen)
    z = overlap_zncc(view[None], target[None], min_overlap=0.0)[0]
    assert z.shape == (13, 17)
    for dy in range(-6, 7):
        for dx in range(-8, 9):
            if (7 - abs(dy)) * (9 - abs(dx)) < 2:  # a single pixel has no deviation: scores 0
                assert z[6 + dy, 8 + dx].item() == 0.0
                continue
            assert z[6 + dy, 8 + dx].item() == pytest.approx(zncc_by_hand(view, target, dy, dx), abs=1e-4), (dy, dx)


def test_small_overlaps_are_left_out() -> None:
    gen = torch.Generator().manual_seed(1)
    view, target = torch.rand(2, 1, 10, 10, generator=gen)
    z = overlap_zncc(view, target)[0]  # MIN_OVERLAP of 100 pixels: 20
    for dy, dx in [(0, 8), (9, 9), (-6, -6), (5, -7)]:  # overlaps 20, 1, 16 and 15 pixels
        enough = (10 - abs(dy)) * (10 - abs(dx)) >= MIN_OVERLAP * 100
        assert (z[9 + dy, 9 + dx].item() == LOW) != enough, (dy, dx)


@pytest.mark.parametrize("dy, dx", [(0, 0), (4, 20), (-3, -22), (0, 24), (10, -5)])
def test_a_shifted_crop_peaks_at_its_shift(dy: int, dx: int) -> None:
    """Two crops of one texture, the target's content ``(dy, dx)`` from the view's: the peak is 1 there, even
    where they share only a quarter of the image (dx = 24 of 32), where a Hann window leaves almost nothing."""
    big = torch.rand(1, 80, 120, generator=torch.Generator().manual_seed(2))
    y0, x0 = 20, 40
    view = big[:, y0:y0 + 32, x0:x0 + 32]
    target = big[:, y0 + dy:y0 + dy + 32, x0 + dx:x0 + dx + 32]
    z = overlap_zncc(view, target)[0]
    where = int(z.flatten().argmax())
    assert (where // 63 - 31, where % 63 - 31) == (dy, dx)
    assert z.max().item() == pytest.approx(1.0, abs=1e-4)


def test_the_features_of_an_identical_and_a_mirrored_pair() -> None:
    images = torch.rand(3, 3, 64, 64, generator=torch.Generator().manual_seed(3))
    wide = WideMatch(64, 64)
    out = wide(images, images)
    assert out.shape == (3, WIDE_FEATURES)
    centre = WIDE_BINS * WIDE_BINS // 2
    torch.testing.assert_close(out[:, centre], torch.ones(3), atol=1e-4, rtol=0)  # the zero-shift bin
    torch.testing.assert_close(out[:, -3:], torch.tensor([[1.0, 0.0, 0.0]] * 3), atol=1e-4, rtol=0)
    # a pair and its left-right mirror: the same peak, the column shift negated, the surface flipped left-right
    big = torch.rand(1, 3, 96, 160, generator=torch.Generator().manual_seed(4))
    view, target = big[..., 10:74, 20:84], big[..., 18:82, 60:124]  # target content 8 rows down, 40 columns right
    plain, mirrored = wide(view, target)[0], wide(view.flip(-1), target.flip(-1))[0]
    assert plain[-3].item() == pytest.approx(1.0, abs=1e-3)
    assert (plain[-2].item() * 32, plain[-1].item() * 32) == pytest.approx((4.0, 20.0))  # pixels of 32x32 blocks
    assert mirrored[-1].item() == pytest.approx(-plain[-1].item())
    grid = WIDE_BINS * WIDE_BINS
    torch.testing.assert_close(mirrored[:grid].view(WIDE_BINS, WIDE_BINS), plain[:grid].view(WIDE_BINS, WIDE_BINS).flip(-1))


def test_an_affine_change_of_the_target_changes_nothing() -> None:
    gen = torch.Generator().manual_seed(5)
    view, target = torch.rand(2, 2, 3, 64, 64, generator=gen)
    wide = WideMatch(64, 64)
    torch.testing.assert_close(wide(view, target * 0.5 + 0.2), wide(view, target), atol=1e-4, rtol=1e-4)


def panorama(seed: int) -> torch.Tensor:
    """(1, 3, 512, 1024) uint8: box-filtered (9x9) noise upsampled bicubically: smooth structure at several scales."""
    noise = torch.rand(1, 3, 128, 256, generator=torch.Generator().manual_seed(seed))
    noise = torch.nn.functional.avg_pool2d(noise, 9, 1, 4)
    up = torch.nn.functional.interpolate(noise, size=(512, 1024), mode="bicubic", align_corners=False)
    return (up.clamp(0, 1) * 255).to(torch.uint8)


def test_targets_at_the_edge_of_rendered_views_point_their_way() -> None:
    """Targets 40-60 degrees to the side of a FoV-90 view (a third to a half of it shared), on 4 panoramas: the
    peak's column shift has the offset's sign and a size between 0.75 and 1 times it (perspective stretches the
    shared band at the view's edge, so its shift in pixels reads as fewer degrees) for at least 28 of the 32 pairs
    (31 measured); its row shift stays within 4 degrees of 0."""
    wide = WideMatch(64, 64)
    right = 0
    offsets = (-60.0, -55.0, -50.0, -40.0, 40.0, 50.0, 55.0, 60.0)
    for seed in range(6, 10):
        equi = panorama(seed)
        view = equi2pers(equi, torch.tensor([0.0]), torch.tensor([0.0]), 90.0, 64, 64).float() / 255
        for yaw_offset in offsets:
            target = equi2pers(equi, torch.tensor([0.0]), torch.tensor([yaw_offset]), 90.0, 64, 64).float() / 255
            out = wide(view, target)[0]
            dx_deg = out[-1].item() * 90.0  # a fraction of the 32 columns, 90 degrees across
            if dx_deg * yaw_offset > 0 and 0.75 * abs(yaw_offset) <= abs(dx_deg) <= abs(yaw_offset) + 3.0:
                right += 1
                assert abs(out[-2].item()) * 90.0 <= 4.0
    assert right >= 28, right


def small_policy(wide_match: int = WIDE_FEATURES) -> Policy:
    torch.manual_seed(0)
    return Policy(64, 64, variant="phase", hidden_size=16, fine_shifts=1, fine_scales=2, wide_match=wide_match)


def test_the_policy_grows_the_wide_match_from_a_checkpoint_without_it(tmp_path) -> None:
    grown = small_policy()
    check_grows_from_a_checkpoint_without_it(tmp_path, small_policy(0), grown, "wide_match", WIDE_FEATURES, grown.wide_proj)
    with pytest.raises(ValueError, match="wide_match must be 0"):
        small_policy(3)
    with pytest.raises(ValueError, match="wide_match needs one of the variants"):
        Policy(64, 64, variant="early_fusion", hidden_size=16, wide_match=WIDE_FEATURES)


def test_the_wide_match_and_the_pitch_warps_together(tmp_path) -> None:
    """Both extra inputs at once read their own columns of the fixed features: zeroing one projection leaves the
    other's effect unchanged, and the agent loads the pair from its checkpoint."""
    from findview_baselines.rl.pitch_warps import WARP_FEATURES

    torch.manual_seed(0)
    policy = Policy(64, 64, variant="phase", hidden_size=16, fine_shifts=1, fine_scales=2, pitch_warps=WARP_FEATURES,
                    wide_match=WIDE_FEATURES)
    gen = torch.Generator().manual_seed(2)
    obs = {k: torch.randint(0, 256, (2, 3, 64, 64), dtype=torch.uint8, generator=gen) for k in ("view", "target")}
    fixed = policy.fixed_features(obs)
    split = policy.encoder.fixed_size
    assert fixed.shape[1] == split + WARP_FEATURES + WIDE_FEATURES
    view = policy._prepare(obs["view"])
    target = policy._prepare(obs["target"])
    torch.testing.assert_close(fixed[:, split + WARP_FEATURES:], policy.wide(view, target))
    with torch.no_grad():
        policy.wide_proj[-1].weight.fill_(0.3)
        base = policy.encoder.head_forward(fixed[:, :split]) + policy.warp_proj(fixed[:, split:split + WARP_FEATURES])
        torch.testing.assert_close(policy.features(None, fixed=fixed) - base,
                                   policy.wide_proj(fixed[:, split + WARP_FEATURES:]))
    path = save_checkpoint(tmp_path / "both.pth", checkpoint_payload(policy, 0, 0, {}, None, None, None))
    agent = PPOAgent.from_checkpoint(path, 1, fov=90.0)
    assert agent.policy.wide_match == WIDE_FEATURES and agent.policy.pitch_warps == WARP_FEATURES


def test_the_config_switch_builds_the_wide_match() -> None:
    from findview_baselines.config import PPOAgentConfig
    from findview_baselines.rl.policy import build_policy

    on = build_policy(PPOAgentConfig(variant="phase", hidden_size=16, fine_shifts=1, fine_scales=2, wide_match=True), 64, 64)
    off = build_policy(PPOAgentConfig(variant="phase", hidden_size=16, fine_shifts=1, fine_scales=2), 64, 64)
    assert on.wide_match == WIDE_FEATURES and isinstance(on.wide, WideMatch)
    assert off.wide_match == 0 and off.wide is None and "wide_match" not in off.model_signature()
    # the peak gate holds in training too: the trainer's network (build_policy) gets it from the config
    gated = build_policy(PPOAgentConfig(variant="phase", hidden_size=16, fine_shifts=1, fine_scales=2, wide_match=True,
                                        wide_match_min_peak=0.75), 64, 64)
    assert gated.wide_min_peak == 0.75 and on.wide_min_peak == 0.0
    with pytest.raises(ValueError, match=r"agent.wide_match_min_peak=0.5 needs a network that reads the wide match \(agent.wide_match=true"):
        build_policy(PPOAgentConfig(variant="phase", hidden_size=16, wide_match_min_peak=0.5), 64, 64)


def test_wide_on_rows_add_the_wide_match_and_the_others_nothing() -> None:
    """``obs[WIDE_ON]`` (agent.wide_match_steps): a row marked off gets the features of the network without the
    wide match's layer (its output zeroed by hand), a row marked on those of the ungated network."""
    policy = small_policy()
    with torch.no_grad():
        policy.wide_proj[-1].weight.normal_(0, 0.5)  # a trained layer: its output is not zero
        policy.wide_proj[-1].bias.fill_(0.2)
    gen = torch.Generator().manual_seed(3)
    obs = {k: torch.randint(0, 256, (3, 3, 64, 64), dtype=torch.uint8, generator=gen) for k in ("view", "target")}
    with torch.no_grad():
        on = policy.encode(obs)
        gated = policy.encode({**obs, WIDE_ON: torch.tensor([True, False, True])})
        fixed = policy.fixed_features(obs)
        without = policy.encoder.head_forward(fixed[:, :policy.encoder.fixed_size])
    assert not torch.allclose(on, without, atol=1e-3)
    torch.testing.assert_close(gated[[0, 2]], on[[0, 2]])
    torch.testing.assert_close(gated[1], without[1])
    # every row off: the wide match is not computed at all, and the features are the network's without the layer
    calls = []
    policy.wide.register_forward_hook(lambda *args: calls.append(1))
    with torch.no_grad():
        off = policy.encode({**obs, WIDE_ON: torch.zeros(3, dtype=torch.bool)})
    assert not calls
    torch.testing.assert_close(off, without)


def test_rows_below_the_min_peak_add_nothing_from_the_wide_match() -> None:
    """``wide_min_peak`` (agent.wide_match_min_peak): a pair whose target is the view itself peaks at 1 and keeps
    the wide match; a pair of unrelated noise images peaks lower and gets the network without the layer; the
    threshold combines with ``WIDE_ON``."""
    policy = small_policy()
    with torch.no_grad():
        policy.wide_proj[-1].weight.normal_(0, 0.5)
        policy.wide_proj[-1].bias.fill_(0.2)
    gen = torch.Generator().manual_seed(4)
    images = torch.randint(0, 256, (3, 3, 64, 64), dtype=torch.uint8, generator=gen)
    # rows: identical pair, unrelated pair, identical pair
    obs = {"view": images, "target": torch.stack([images[0], images[0].flip(-1).roll(17, -2), images[2]])}
    with torch.no_grad():
        fixed = policy.fixed_features(obs)
        peak = fixed[:, policy.encoder.fixed_size + WIDE_PEAK]
        assert peak[0].item() == pytest.approx(1.0, abs=1e-4) and peak[2].item() == pytest.approx(1.0, abs=1e-4)
        assert peak[1].item() < 0.5  # noise against unrelated noise: a weak best shift
        on = policy.encode(obs)
        without = policy.encoder.head_forward(fixed[:, :policy.encoder.fixed_size])
        policy.wide_min_peak = 0.9
        gated = policy.encode(obs)
        torch.testing.assert_close(gated[[0, 2]], on[[0, 2]])
        torch.testing.assert_close(gated[1], without[1])
        torch.testing.assert_close(policy.features(None, fixed=fixed), gated)  # the trainer's cached-input path too
        both = policy.encode({**obs, WIDE_ON: torch.tensor([False, True, True])})  # and WIDE_ON: only row 2 speaks
        torch.testing.assert_close(both[2], on[2])
        torch.testing.assert_close(both[:2], without[:2])


def test_the_agent_sets_the_min_peak_and_checks_it() -> None:
    from findview_baselines.config import PPOAgentConfig

    assert PPOAgent(small_policy(), 1, wide_match_min_peak=0.75).policy.wide_min_peak == 0.75
    assert PPOAgent(small_policy(), 1).policy.wide_min_peak == 0.0
    # no value keeps the network's own gate: the trainer's validation plays the network it trains (build_policy's gate)
    from findview_baselines.config import PPOAgentConfig as Config
    from findview_baselines.rl.policy import build_policy
    from findview_baselines.training.build import make_val_agent

    agent_cfg = Config(variant="phase", hidden_size=16, fine_shifts=1, fine_scales=2, wide_match=True,
                       wide_match_min_peak=0.75)
    trained = build_policy(agent_cfg, 64, 64)
    make_val_agent(agent_cfg, trained, 1, 0)
    assert trained.wide_min_peak == 0.75
    assert PPOAgent(trained, 1, wide_match_min_peak=0.0).policy.wide_min_peak == 0.0  # a value sets it
    with pytest.raises(ValueError, match="wide_match_min_peak=0.5 needs a network that reads the wide match"):
        PPOAgent(small_policy(0), 1, wide_match_min_peak=0.5)
    with pytest.raises(ValueError, match=r"wide_match_min_peak must be a ZNCC in \[0, 1\)"):
        PPOAgent(small_policy(), 1, wide_match_min_peak=1.0)
    with pytest.raises(ValueError, match=r"wide_match_min_peak must be a ZNCC in \[0, 1\)"):  # checked first
        PPOAgent(small_policy(0), 1, wide_match_min_peak=-0.1)
    assert PPOAgent(small_policy(0), 1, wide_match_min_peak=0.0).policy.wide_min_peak == 0.0  # no gate: nothing to set
    with pytest.raises(ValueError, match="agent.wide_match_min_peak"):
        PPOAgentConfig(wide_match_min_peak=-0.1)


def test_eval_takes_the_min_peak_the_checkpoint_trained_with(tmp_path) -> None:
    """tools/eval.py's config: a checkpoint whose run trained with ``agent.wide_match_min_peak`` is evaluated with
    it unless the command line says otherwise; a checkpoint without the key keeps the schema's 0."""
    from findview_baselines.cli import compose_config, validate_config
    from findview_baselines.evaluation.evaluate import apply_checkpoint_config, build_agent

    def min_peak(path, *given: str) -> float:
        composed = validate_config(compose_config("eval", ["agent=ppo", f"checkpoint={path}", *given]))
        cfg = apply_checkpoint_config(composed, list(given))
        return build_agent(cfg, 1, torch.device("cpu"))[0].policy.wide_min_peak

    config = {"agent": {"wide_match": True, "wide_match_min_peak": 0.75}, "sim": {"fov": 90.0, "height": 64, "width": 64}}
    gated = save_checkpoint(tmp_path / "gated.pth", checkpoint_payload(small_policy(), 0, 0, config, None, None, None))
    plain = save_checkpoint(tmp_path / "plain.pth", checkpoint_payload(small_policy(), 0, 0, {}, None, None, None))
    assert min_peak(gated) == 0.75
    assert min_peak(gated, "agent.wide_match_min_peak=0.6") == 0.6
    assert min_peak(gated, "agent.wide_match_min_peak=0") == 0.0
    assert min_peak(plain) == 0.0
    # the agent loaded straight from the file (no tools/eval.py) keeps the gate its network trained with too
    assert PPOAgent.from_checkpoint(gated, 1).policy.wide_min_peak == 0.75
    assert PPOAgent.from_checkpoint(gated, 1, wide_match_min_peak=0.5).policy.wide_min_peak == 0.5
    assert PPOAgent.from_checkpoint(plain, 1).policy.wide_min_peak == 0.0


class GateSpy(StandInPolicy):
    """A stand-in network that records the ``WIDE_ON`` rows it is given and always turns right."""

    wide_match = WIDE_FEATURES

    def __init__(self) -> None:
        super().__init__()
        self.seen: list[list[bool]] = []

    def forward(self, obs, hidden, masks, memory=None):
        from torch.distributions import Categorical

        self.seen.append(obs[WIDE_ON].tolist())
        logits = torch.tensor([[0.0, 0.0, 0.0, 5.0, 0.0]]).expand(len(obs["view"]), 5)
        return Categorical(logits=logits), None, hidden


@pytest.mark.parametrize("mirror_steps", [0, 2])
def test_the_agent_turns_the_wide_match_on_for_its_first_steps_only(mirror_steps: int) -> None:
    spy = GateSpy()
    agent = PPOAgent(spy, 2, wide_match_steps=3, mirror_steps=mirror_steps)
    obs = {k: torch.zeros(2, 3, 8, 8, dtype=torch.uint8) for k in ("view", "target")}
    for _ in range(4):
        agent.act(obs)
    agent.reset([1], [None])  # slot 1 begins a new episode: steps 1-3 again
    agent.done[:] = False
    for _ in range(2):
        agent.act(obs)
    own = [rows[:2] for rows in spy.seen]
    assert own == [[True, True]] * 3 + [[False, False], [False, True], [False, True]]
    # the mirror rows (steps 1..mirror_steps of a slot) follow their episode's step
    mirrors = [rows[2:] for rows in spy.seen]
    if mirror_steps:
        assert mirrors == [[True, True], [True, True], [], [], [True], [True]]
    else:
        assert mirrors == [[]] * 6


def test_wide_match_steps_needs_a_network_that_reads_the_wide_match() -> None:
    from findview_baselines.config import PPOAgentConfig

    with pytest.raises(ValueError, match="wide_match_steps=5 needs a network that reads the wide match"):
        PPOAgent(small_policy(0), 1, wide_match_steps=5)
    with pytest.raises(ValueError, match="wide_match_steps must be >= 0"):
        PPOAgent(small_policy(), 1, wide_match_steps=-1)
    with pytest.raises(ValueError, match="agent.wide_match_steps"):
        PPOAgentConfig(wide_match_steps=-2)


class Habit(StandInPolicy):
    """A stand-in network with the real wide match that plays a fixed habit: DOWN for its first ``down`` calls of an
    episode, then LEFT (logit 5) over RIGHT (3) over the rest (0)."""

    height = width = 64
    wide_match = WIDE_FEATURES

    def __init__(self, down: int = 0) -> None:
        super().__init__()
        self.wide = WideMatch(64, 64)
        self.down = down
        self.calls = 0

    def _prepare(self, images: torch.Tensor) -> torch.Tensor:
        return images.float() / 255 if images.dtype == torch.uint8 else images

    def forward(self, obs, hidden, masks, memory=None):
        from torch.distributions import Categorical

        self.calls += 1
        row = [0.0, 5.0, 0.0, 0.0, 0.0] if self.calls <= self.down else [0.0, 0.0, 5.0, 3.0, 0.0]
        return Categorical(logits=torch.tensor([row]).expand(len(obs["view"]), 5)), None, hidden


def edge_pair(yaw_offset: float) -> dict[str, torch.Tensor]:
    """A FoV-90 view at yaw 0 and a target ``yaw_offset`` degrees to its side (+: right), 64x64 uint8, one pair."""
    equi = panorama(7)
    view = equi2pers(equi, torch.tensor([0.0]), torch.tensor([0.0]), 90.0, 64, 64)
    target = equi2pers(equi, torch.tensor([0.0]), torch.tensor([yaw_offset]), 90.0, 64, 64)
    return {"view": view, "target": target}


def play(agent: PPOAgent, obs: dict[str, torch.Tensor], steps: int) -> list[int]:
    return [int(agent.act(obs)[0]) for _ in range(steps)]


def test_the_wide_match_sets_the_first_turn_and_nothing_after_it() -> None:
    """``wide_match_turn``: a network that habitually turns LEFT makes its first yaw move RIGHT when a sure wide match
    puts the target 50 degrees to the right, and is its own again after that move; with the target to the left, with
    the rule off, or with a target equal to the view (no column shift), its first move is its own LEFT."""
    from findview.task import Action

    L, R, D = int(Action.LEFT), int(Action.RIGHT), int(Action.DOWN)
    right, left = edge_pair(50.0), edge_pair(-50.0)
    assert WideMatch(64, 64)(right["view"].float() / 255, right["target"].float() / 255)[0, WIDE_PEAK] > 0.5
    assert play(PPOAgent(Habit(), 1, wide_match_steps=3, wide_match_turn=0.5), right, 3) == [R, L, L]
    assert play(PPOAgent(Habit(), 1, wide_match_steps=3, wide_match_turn=0.5), left, 2) == [L, L]
    assert play(PPOAgent(Habit(), 1, wide_match_steps=3), right, 2) == [L, L]
    same = {"view": right["view"], "target": right["view"].clone()}
    assert play(PPOAgent(Habit(), 1, wide_match_steps=3, wide_match_turn=0.5), same, 2) == [L, L]
    # a target 15 degrees to the right: its shift (about 5 of 32 columns) is below TURN_MIN_SHIFT, the habit decides
    near = edge_pair(15.0)
    shift = WideMatch(64, 64)(near["view"].float() / 255, near["target"].float() / 255)[0, WIDE_PEAK + 2]
    assert 0 < shift < TURN_MIN_SHIFT
    assert play(PPOAgent(Habit(), 1, wide_match_steps=3, wide_match_turn=0.5), near, 2) == [L, L]
    # a side set in the first steps holds until the first yaw move, however late: pitch moves first here
    agent = PPOAgent(Habit(down=5), 1, wide_match_steps=3, wide_match_turn=0.5)
    assert play(agent, right, 7) == [D] * 5 + [R, L]
    # a new episode forgets the side: an identical pair sets none, so the habit turns LEFT
    agent.reset([0], [None])
    agent.done[:] = False
    agent.policy.calls = 0
    agent.policy.down = 0
    assert play(agent, same, 1) == [L]


def test_wide_match_turn_is_checked() -> None:
    from findview_baselines.config import PPOAgentConfig
    from findview.config import ConfigError

    with pytest.raises(ValueError, match="wide_match_turn=0.5 reads the wide match in an episode's first steps"):
        PPOAgent(Habit(), 1, wide_match_turn=0.5)
    with pytest.raises(ValueError, match="wide_match_turn must be a ZNCC in"):
        PPOAgent(Habit(), 1, wide_match_steps=3, wide_match_turn=1.0)
    with pytest.raises(ConfigError, match="agent.wide_match_steps"):
        PPOAgentConfig(wide_match_turn=0.6)
    with pytest.raises(ConfigError, match="agent.wide_match_turn"):
        PPOAgentConfig(wide_match_turn=-0.1, wide_match_steps=10)
