"""The ``phase`` policy variant's band-limited phase correlation (:class:`PhaseCorrelation`)."""

from __future__ import annotations

import math

import pytest
import torch

from findview.corruptions import corrupt
from findview.sim.equi2pers import equi2pers
from findview_baselines.rl.encoders import (
    PHASE_BANDWIDTHS, PHASE_SCALARS, DirectEncoder, PhaseCorrelation, phase_setup,
)
from findview_baselines.rl.policy import Policy, check_signature

pytestmark = pytest.mark.usefixtures("one_torch_thread")

K = len(PHASE_BANDWIDTHS)


def texture(size: int, seed: int = 0) -> torch.Tensor:
    """(1, 1, size, size) smooth random texture in [0, 1] (3x3 box-filtered noise: structure at every scale
    phase correlation looks at)."""
    noise = torch.rand(1, 1, size, size, generator=torch.Generator().manual_seed(seed))
    return torch.nn.functional.avg_pool2d(noise, 3, 1, 1)


def peak_shift(scalars: torch.Tensor, pc: PhaseCorrelation, band: int = 0) -> tuple[float, float]:
    """The (dy, dx) of a surface's peak in pixels of the averaged images."""
    return float(scalars[0, 2 * K + band]) * pc.height, float(scalars[0, 3 * K + band]) * pc.width


@pytest.mark.parametrize("dy, dx", [(-6, 8), (10, -6), (0, 0), (16, 16)])
def test_peak_lies_at_the_translation_in_averaged_pixels(dy: int, dx: int) -> None:
    # view[y + dy, x + dx] = target[y, x]: crops of one texture, the view's window moved by (-dy, -dx)
    big = texture(160)
    target = big[..., 48:112, 48:112]
    view = big[..., 48 - dy:112 - dy, 48 - dx:112 - dx]
    pc = PhaseCorrelation(64, 64, cells=8, shifts=6)
    assert (pc.pool, pc.height, pc.width) == (2, 32, 32)
    surfaces, scalars = pc(view, target)
    assert surfaces.shape == (1, K, 13, 13) and scalars.shape == (1, PHASE_SCALARS)
    for band in range(K):
        assert peak_shift(scalars, pc, band) == (dy / 2, dx / 2)
    # the surfaces line up with the coarse cost volume: 8-pixel cells, bin 6 is zero shift (no shift here lies on a
    # bin border, +-4, +-12, ... pixels)
    row, col = divmod(int(surfaces[0, 0].flatten().argmax()), 13)
    assert (row - 6, col - 6) == (round(dy / 8), round(dx / 8))
    # a clear peak: far above any entry of an unrelated pair
    _, unrelated = pc(texture(64, seed=5), target)
    assert float(scalars[0, 0]) > 2.0 * float(unrelated[0, 0])


def test_identical_images_give_the_band_weights_alone() -> None:
    # V conj(V) / |V conj(V)| = 1 at every frequency, so the surface is the inverse transform of the Gaussian band
    # weights, the same for any image: phase correlation, not plain correlation (which would depend on the image)
    pc = PhaseCorrelation(64, 64, cells=8, shifts=6)
    h, w = pc.height, pc.width
    expected = []
    for sigma in PHASE_BANDWIDTHS:
        fy = torch.fft.fftfreq(2 * h)[:, None]
        fx = torch.fft.rfftfreq(2 * w)[None, :]
        surface = torch.fft.irfft2(torch.exp(-(fy ** 2 + fx ** 2) / (2 * sigma ** 2)), s=(2 * h, 2 * w))
        expected.append(float((surface[0, 0] - surface.mean()) / surface.std() / 10.0))
    for seed in (3, 4):
        image = texture(64, seed=seed)
        _, scalars = pc(image, image.clone())
        zero = scalars[0, K:2 * K]
        torch.testing.assert_close(zero, torch.tensor(expected), atol=1e-3, rtol=1e-3)
        torch.testing.assert_close(scalars[0, :K], zero)  # the peak is at zero shift
        assert int(scalars[0, 4 * K:].argmax()) == 4  # centre of the 3 x 3 neighbourhood
    assert expected[0] > expected[1] > 0  # the wide band is the sharper peak


def test_non_square_views_and_the_centre_neighbourhood() -> None:
    big = texture(160, seed=6)
    pc = PhaseCorrelation(48, 64, cells=8, shifts=6)
    assert (pc.pool, pc.height, pc.width) == (1, 48, 64)  # the short side is under 64: no averaging
    # one cell up (6 rows of a 48-row view) and two cells right (16 columns): view[y - 6, x + 16] = target[y, x]
    target = big[..., 50:98, 40:104]
    view = big[..., 56:104, 24:88]
    surfaces, scalars = pc(view, target)
    assert peak_shift(scalars, pc) == (-6, 16)
    row, col = divmod(int(surfaces[0, 0].flatten().argmax()), 13)
    # the same bin as the coarse cost volume's minimum (8 x 8 thumbnails: cells of 6 x 8 pixels)
    enc = DirectEncoder(48, 64, 16, fine_shifts=0)
    thumb = lambda x: torch.nn.functional.adaptive_avg_pool2d(x, 8)  # noqa: E731
    best = int(enc.global_costs(thumb(view), thumb(target)).argmin())
    assert (row, col) == divmod(best, 13) == (5, 8)
    # a shift of one row: the 3 x 3 neighbourhood of zero shift is highest at (+1, 0), entry 7
    _, near = pc(big[..., 49:97, 40:104], target)  # view[y + 1, x] = target[y, x]
    assert int(near[0, 4 * K:].argmax()) == 7


def test_an_affine_change_of_the_intensities_changes_nothing() -> None:
    big = texture(160, seed=1)
    target, view = big[..., 40:104, 40:104], big[..., 44:108, 30:94]
    pc = PhaseCorrelation(64, 64, cells=8, shifts=6)
    surfaces, scalars = pc(view, target)
    dim_surfaces, dim_scalars = pc(view, 0.3 * target + 0.5)  # contrast down to 30%, brighter
    torch.testing.assert_close(dim_scalars, scalars, atol=1e-4, rtol=1e-4)
    torch.testing.assert_close(dim_surfaces, surfaces, atol=1e-4, rtol=1e-4)


@pytest.mark.parametrize("corruption", [None, "fog", "contrast", "gaussian_noise"])
def test_a_rendered_rotation_reads_its_hand_computed_shift_under_corruption(corruption: str | None) -> None:
    # a 14.04-degree turn to the right: the target's centre lies f tan(14.04) = 32 * 0.25 = 8 pixels right of the
    # view's centre (64-pixel views, FoV 90, f = 32), 4 pixels after averaging 2x2; pitch 0: no vertical shift
    equi = (torch.nn.functional.interpolate(texture(128, seed=2).repeat(1, 3, 1, 2), size=(512, 1024),
                                            mode="bicubic", align_corners=False).clamp(0, 1) * 255).to(torch.uint8)
    yaw = math.degrees(math.atan(0.25))
    view = equi2pers(equi, torch.tensor([0.0]), torch.tensor([0.0]), 90.0, 64, 64)
    target = equi2pers(equi, torch.tensor([0.0]), torch.tensor([yaw]), 90.0, 64, 64)
    if corruption:
        target = corrupt(target, corruption, 3, generator=torch.Generator().manual_seed(0))
    pc = PhaseCorrelation(64, 64, cells=8, shifts=6)
    grey = lambda x: x.float().mean(dim=1, keepdim=True) / 255  # noqa: E731
    _, scalars = pc(grey(view), grey(target))
    dy, dx = peak_shift(scalars, pc)
    assert dy == 0 and abs(dx - 4) <= 1, (dy, dx)
    # and the other way round: the target to the left
    _, back = pc(grey(target), grey(view))
    assert abs(peak_shift(back, pc)[1] + 4) <= 1


def test_phase_variant_builds_runs_and_is_its_own_signature() -> None:
    policy = Policy(64, 64, "phase", 32, fine_shifts=2, fine_scales=4)
    robust = Policy(64, 64, "robust", 32, fine_shifts=2, fine_scales=4)
    assert policy.encoder.phase is not None and robust.encoder.phase is None
    assert policy.encoder.head[0].in_channels == robust.encoder.head[0].in_channels + K
    assert policy.encoder.fuse[0].in_features == robust.encoder.fuse[0].in_features + PHASE_SCALARS
    obs = {"view": torch.randint(0, 256, (3, 3, 64, 64), dtype=torch.uint8)}
    obs["target"] = obs["view"].flip(-1)
    dist, values, hidden = policy(obs, policy.initial_hidden(3), torch.ones(3))
    assert dist.logits.shape == (3, 5) and torch.isfinite(dist.logits).all() and torch.isfinite(values).all()
    # nothing before the head is learned: the phase module has no parameters
    assert not list(policy.encoder.phase.parameters())
    with pytest.raises(ValueError, match="variant is 'robust' in the checkpoint but 'phase'"):
        check_signature(robust.model_signature(), policy.model_signature())
    with pytest.raises(ValueError, match="variant is 'robust' in the checkpoint but 'phase'"):
        check_signature(robust.model_signature(), policy.model_signature(), transfer=True)
    with pytest.raises(ValueError, match="phase=True .* needs normalized=True"):
        DirectEncoder(64, 64, 32, phase=True)


@pytest.mark.parametrize("height, width, pool, h, w", [(64, 64, 2, 32, 32), (256, 256, 8, 32, 32), (33, 99, 1, 33, 99),
                                                      (70, 96, 2, 35, 48)])
def test_phase_setup_sizes_window_and_band_weights(height: int, width: int, pool: int, h: int, w: int) -> None:
    """Block size min(H, W) // 32 (at least 1) and the averaged size by hand; the window is 0 at the borders and 1
    at the centre of an odd side; the band weight is 1 at zero frequency and exp(-f^2 / (2 sigma^2)) at
    (0, f near 1/4 cycle per pixel), on the rfft grid of the 2h x 2w zero-padded image."""
    got_pool, got_h, got_w, window, weights = phase_setup(height, width, (0.3, 0.1))
    assert (got_pool, got_h, got_w) == (pool, h, w)
    assert window.shape == (h, w) and weights.shape == (2, 2 * h, w + 1)
    assert float(window[0].abs().max()) == 0.0 and float(window[:, -1].abs().max()) == 0.0
    if h % 2 and w % 2:
        assert float(window[h // 2, w // 2]) == pytest.approx(1.0)
    assert weights[:, 0, 0].tolist() == [1.0, 1.0]
    col = round(0.25 * 2 * w)  # the rfft column nearest 1/4 cycle per pixel (2w samples): col / (2w) cycles
    f = col / (2 * w)
    for k, sigma in enumerate((0.3, 0.1)):
        assert float(weights[k, 0, col]) == pytest.approx(math.exp(-(f ** 2) / (2 * sigma ** 2)), rel=1e-5)
