"""The pitch-warped phase correlation (``agent.pitch_warps``, rl/pitch_warps.py): its warp against the renderer,
its cue on rendered pitch offsets, and the policy / checkpoint / agent plumbing."""

from __future__ import annotations

import math

import pytest
import torch

from _growable import check_grows_from_a_checkpoint_without_it
from findview.corruptions import corrupt
from findview.sim.equi2pers import equi2pers
from findview_baselines.agents.ppo_agent import PPOAgent
from findview_baselines.rl.checkpoint import checkpoint_payload, save_checkpoint
from findview_baselines.rl.pitch_warps import WARP_FEATURES, WARP_FRACTIONS, PitchWarpedPhase, warp_grids
from findview_baselines.rl.policy import Policy

pytestmark = pytest.mark.usefixtures("one_torch_thread")

K = len(WARP_FRACTIONS)


def panorama(seed: int = 2, smooth: int = 3) -> torch.Tensor:
    """(1, 3, 512, 1024) uint8: box-filtered noise upsampled bicubically (structure at every scale)."""
    noise = torch.rand(1, 3, 128, 256, generator=torch.Generator().manual_seed(seed))
    noise = torch.nn.functional.avg_pool2d(noise, smooth, 1, smooth // 2)
    up = torch.nn.functional.interpolate(noise, size=(512, 1024), mode="bicubic", align_corners=False)
    return (up.clamp(0, 1) * 255).to(torch.uint8)


def render(equi: torch.Tensor, pitch: float, yaw: float, size: int = 64, fov: float = 90.0) -> torch.Tensor:
    return equi2pers(equi, torch.tensor([pitch]), torch.tensor([yaw]), fov, size, size).float() / 255


def test_grid_by_hand_at_zero_and_at_the_view_centre() -> None:
    # dp = 0: every view pixel reads the same target pixel (grid_sample's align_corners=False pixel centres)
    grid, valid = warp_grids(4, 4, 90.0, torch.tensor([0.0]))
    centres = (torch.arange(4) + 0.5) / 2 - 1
    assert torch.allclose(grid[0, :, :, 0], centres[None, :].expand(4, 4))
    assert torch.allclose(grid[0, :, :, 1], centres[:, None].expand(4, 4))
    assert bool(valid.all())
    # dp = +30 at FoV 90 (f = W / 2): the view's ray through the image centre is 30 degrees below the target's
    # axis, so it falls f tan 30 below the target's centre; a 2x2 image's centre is the corner of its 4 pixels,
    # so take the 4 pixels' mean of the vertical coordinate, which is exact for the middle column of rays
    grid, valid = warp_grids(2, 2, 90.0, torch.tensor([30.0]))
    # pixel (row 0, col 0): ray (-0.5, 0.5, 1) / f with f = 1 -> after pitch -30: y_t = 0.5 cos30 - sin30
    y_t = 0.5 * math.cos(math.radians(30)) - math.sin(math.radians(30))
    z_t = 0.5 * math.sin(math.radians(30)) + math.cos(math.radians(30))
    assert grid[0, 0, 0, 1].item() == pytest.approx(-y_t / z_t, abs=1e-6)  # (v / f) / (H / 2 / f): same units
    assert grid[0, 0, 0, 0].item() == pytest.approx(-0.5 / z_t, abs=1e-6)


@pytest.mark.parametrize("pitch, offset", [(0.0, 30.0), (10.0, -30.0), (-20.0, 15.0)])
def test_the_warped_target_is_the_view_where_both_see(pitch: float, offset: float) -> None:
    """A target rendered ``offset`` degrees above the view (same yaw), warped by that offset, is the view
    itself over the pixels both cameras see; warped by the opposite offset it is not."""
    equi = panorama(smooth=9)  # smooth: bilinear resampling of the target costs little
    view, target = render(equi, pitch, 40.0, 128), render(equi, pitch + offset, 40.0, 128)
    errors = {}
    for hyp in (offset, -offset):
        grid, valid = warp_grids(128, 128, 90.0, torch.tensor([hyp]))
        warped = torch.nn.functional.grid_sample(target, grid, align_corners=False)
        inside = valid[0, 0] > 0
        errors[hyp] = (warped - view).abs()[0].mean(0)[inside].mean().item()
        assert inside.float().mean() > 0.2
    assert errors[offset] < 0.01 < errors[-offset] / 3, errors


# fog at 45 degrees is left out: with a third of the view shared, fog's haze leaves too little (on other textures the
# +45 hypothesis does not always win; the network learns how far to trust the cue)
@pytest.mark.parametrize("offset, corruption", [
    (30.0, None), (-30.0, None), (45.0, None), (-15.0, None), (30.0, "fog"), (-30.0, "fog"), (-15.0, "fog"),
    (30.0, "gaussian_noise"), (45.0, "gaussian_noise"), (-15.0, "gaussian_noise"),
])
def test_the_right_hypothesis_peaks_at_zero_shift(offset: float, corruption: str | None) -> None:
    equi = panorama()
    view = render(equi, 0.0, 10.0)
    target256 = equi2pers(equi, torch.tensor([offset]), torch.tensor([10.0]), 90.0, 256, 256)
    if corruption:
        target256 = corrupt(target256, corruption, 3, generator=torch.Generator().manual_seed(0))
    target = torch.nn.functional.avg_pool2d(target256.float() / 255, 4)
    out = PitchWarpedPhase(64, 64, 90.0)(view, target)[0]
    assert out.shape == (WARP_FEATURES,)
    peaks, dy, dx = out[:K], out[K:2 * K] * 32, out[2 * K:] * 32
    right = min(range(K), key=lambda i: abs(WARP_FRACTIONS[i] * 90 - offset))
    assert int(peaks.argmax()) == right, peaks
    assert abs(dy[right]) <= 1 and abs(dx[right]) <= 1, (dy, dx)
    # an unrelated target (the opposite side of the sphere) stays well below
    unrelated = PitchWarpedPhase(64, 64, 90.0)(view, render(equi, offset, 190.0))[0, :K]
    assert unrelated.max() < peaks.max() - 0.5, (unrelated, peaks)


def test_an_affine_change_of_the_target_changes_nothing() -> None:
    equi = panorama()
    view, target = render(equi, 5.0, 0.0), render(equi, 35.0, 0.0)
    warps = PitchWarpedPhase(64, 64, 90.0)
    torch.testing.assert_close(warps(view, target * 0.5 + 0.2), warps(view, target), atol=1e-3, rtol=1e-3)


def test_the_fov_sets_the_hypotheses() -> None:
    """At FoV 60 the hypotheses are 10, 20, 30 degrees: a target 20 degrees up peaks on +20 (fraction 1/3)."""
    equi = panorama()
    view, target = render(equi, 0.0, 0.0, fov=60.0), render(equi, 20.0, 0.0, fov=60.0)
    peaks = PitchWarpedPhase(64, 64, 60.0)(view, target)[0, :K]
    assert WARP_FRACTIONS[int(peaks.argmax())] == pytest.approx(1 / 3)
    with pytest.raises(ValueError, match="field of view"):
        PitchWarpedPhase(64, 64, 0.0)


def small_policy(pitch_warps: int = WARP_FEATURES) -> Policy:
    torch.manual_seed(0)
    return Policy(64, 64, variant="phase", hidden_size=16, fine_shifts=1, fine_scales=2, pitch_warps=pitch_warps,
                  warp_fov=90.0)


def test_the_policy_grows_the_warps_from_a_checkpoint_without_them(tmp_path) -> None:
    grown = small_policy()
    check_grows_from_a_checkpoint_without_it(tmp_path, small_policy(0), grown, "pitch_warps", WARP_FEATURES, grown.warp_proj)
    with pytest.raises(ValueError, match="pitch_warps must be 0"):
        small_policy(3)
    with pytest.raises(ValueError, match="pitch_warps needs one of the variants"):
        Policy(64, 64, variant="early_fusion", hidden_size=16, pitch_warps=WARP_FEATURES)


def test_the_agent_needs_the_views_fov(tmp_path) -> None:
    policy = small_policy()
    path = save_checkpoint(tmp_path / "warps.pth", checkpoint_payload(policy, 0, 0, {}, None, None, None))
    with pytest.raises(ValueError, match="needs the views' field of view"):
        PPOAgent.from_checkpoint(path, 1)
    agent = PPOAgent.from_checkpoint(path, 1, fov=60.0)
    assert agent.policy.warp.fov == 60.0
