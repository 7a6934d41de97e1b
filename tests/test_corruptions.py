"""findview.corruptions: contract (shapes, dtypes, RNG), hand-computed cases and fidelity to the
reference PSNR table (docs/TASK.md, 36 central crops of sun360_mini)."""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch

import findview.corruptions as fc
from findview.corruptions import CATEGORIES, NAMES, corrupt, resolve_names
from findview.corruptions import weather
from findview.corruptions._common import gaussian_kernel1d, motion_blur
from findview.corruptions.blur import MOTION_BLUR, glass_shuffle_sources

RANDOM = {
    "motion_blur", "glass_blur", "gaussian_noise", "impulse_noise", "shot_noise", "speckle_noise",
    "snow", "spatter", "fog", "frost",
}  # fmt: skip
DETERMINISTIC = set(NAMES) - RANDOM


def _images(b: int = 2, h: int = 40, w: int = 48, seed: int = 0) -> torch.Tensor:
    """Smooth random uint8 images ``(b, 3, h, w)`` (upsampled noise, so blurs change them a little)."""
    g = torch.Generator().manual_seed(seed)
    low = torch.rand((b, 3, h // 4, w // 4), generator=g)
    up = torch.nn.functional.interpolate(low, size=(h, w), mode="bilinear", align_corners=False)
    return (up * 255).round().clamp(0, 255).to(torch.uint8)


def _gen(seed: int) -> torch.Generator:
    return torch.Generator().manual_seed(seed)


@pytest.fixture(autouse=True, scope="module")
def _one_thread():
    """Run this module on one intra-op thread, restoring the setting afterwards.

    Several corruptions issue many small tensor ops (one per motion-blur tap and image); on a machine
    whose cores are shared with other jobs, OpenMP thread barriers make them 10-100x slower.
    """
    saved = torch.get_num_threads()
    torch.set_num_threads(1)
    yield
    torch.set_num_threads(saved)


# ------------------------------------------------------------------------------------ names/config
def test_names_and_categories() -> None:
    assert len(NAMES) == 16 and len(set(NAMES)) == 16
    assert NAMES[:4] == ("motion_blur", "defocus_blur", "glass_blur", "gaussian_blur")
    assert NAMES[-4:] == ("snow", "spatter", "fog", "frost")
    assert tuple(CATEGORIES) == ("blur", "noise", "digital", "weather")
    assert sum(CATEGORIES.values(), ()) == NAMES
    assert CATEGORIES["digital"] == ("brightness", "contrast", "saturate", "jpeg_compression")


def test_resolve_names() -> None:
    assert resolve_names("fog") == ("fog",)
    assert resolve_names("none") == () and resolve_names(None) == () and resolve_names([]) == ()
    assert resolve_names("all") == NAMES
    assert resolve_names("noise") == ("gaussian_noise", "impulse_noise", "shot_noise", "speckle_noise")
    assert resolve_names(["frost", "blur", "frost"]) == ("frost",) + CATEGORIES["blur"]
    with pytest.raises(ValueError, match="unknown corruption 'fogg'.*motion_blur.*frost"):
        resolve_names("fogg")
    with pytest.raises(ValueError, match="unknown corruption 'zoom_blur'"):
        resolve_names(["fog", "zoom_blur"])


@pytest.mark.parametrize("bad", [0, 6, -1, 2.5, "x", True, None])
def test_bad_severity(bad: object) -> None:
    with pytest.raises(ValueError, match=f"invalid corruption severity {bad!r}") as info:
        fc.check_severity(bad)
    assert "\n" not in str(info.value)
    with pytest.raises(ValueError, match="severity"):
        corrupt(_images(1), "fog", bad)  # type: ignore[arg-type]


def test_good_severity() -> None:
    assert [fc.check_severity(s) for s in (1, 2, 3, 4, 5)] == [1, 2, 3, 4, 5]
    assert fc.check_severity(3.0) == 3 and fc.check_severity("4") == 4


def test_bad_name_and_input() -> None:
    with pytest.raises(ValueError, match="unknown corruption 'blurr': expected one of motion_blur"):
        corrupt(_images(1), "blurr", 1)
    with pytest.raises(ValueError, match=r"\(B, 3, H, W\)"):
        corrupt(torch.zeros(3, 40, 40, dtype=torch.uint8), "fog", 1)
    with pytest.raises(ValueError, match="at least 32x32"):
        corrupt(torch.zeros(1, 3, 20, 40, dtype=torch.uint8), "fog", 1)
    with pytest.raises(ValueError, match="uint8 or floating point"):
        corrupt(torch.zeros(1, 3, 40, 40, dtype=torch.int32), "fog", 1)


def test_frost_textures(tmp_path, monkeypatch) -> None:
    assert fc.frost_textures_available()
    assert [p.name for p in weather.frost_texture_paths()] == [f"frost{i}.{e}" for i, e in
                                                               zip(range(1, 6), ["png"] * 3 + ["jpg"] * 2)]
    monkeypatch.setattr(weather, "FROST_DIR", tmp_path)
    assert not fc.frost_textures_available()
    with pytest.raises(FileNotFoundError, match=r"frost texture .*frost1\.png not found.*pip install") as info:
        corrupt(_images(1), "frost", 1)
    assert "\n" not in str(info.value)
    corrupt(_images(1), "fog", 1)  # the other corruptions do not need the textures


# ---------------------------------------------------------------------------------------- contract
@pytest.mark.parametrize("name", NAMES)
def test_contract(name: str) -> None:
    """Shape, dtype, device and range kept; deterministic per seed; global RNG untouched; float input
    ``u8 / 255`` gives the uint8 result within one grey level."""
    x = _images(2, 40, 48)
    state = torch.get_rng_state()
    y = corrupt(x, name, 3, _gen(1))
    assert torch.equal(torch.get_rng_state(), state), "global RNG state changed"
    assert y.shape == x.shape and y.dtype == torch.uint8 and y.device == x.device
    assert torch.equal(y, corrupt(x, name, 3, _gen(1)))
    assert torch.equal(y, corrupt(x.contiguous(memory_format=torch.channels_last), name, 3, _gen(1)))
    assert torch.equal(corrupt(x, name, 3), corrupt(x, name, 3))  # generator=None: fixed seed
    if name in RANDOM:
        assert not torch.equal(y, corrupt(x, name, 3, _gen(2)))
    else:
        assert torch.equal(y, corrupt(x, name, 3, _gen(2)))
    for dtype in (torch.float32, torch.float64):
        yf = corrupt(x.to(dtype) / 255.0, name, 3, _gen(1))
        assert yf.shape == x.shape and yf.dtype == dtype
        assert float(yf.min()) >= 0.0 and float(yf.max()) <= 1.0
        diff = (yf.double() * 255.0 - y.double()).abs()
        assert float(diff.mean()) < 0.6 and float((diff > 1.01).double().mean()) < 0.002, name
    assert torch.equal(torch.get_rng_state(), state)


def test_batch_of_one_and_empty() -> None:
    x = _images(3)
    assert corrupt(x[:0], "snow", 2).shape == (0, 3, 40, 48)
    # images are corrupted independently: draws differ between the images of a batch
    y = corrupt(torch.cat([x[:1], x[:1]]), "gaussian_noise", 2, _gen(0))
    assert not torch.equal(y[0], y[1])


@pytest.mark.skipif(not torch.cuda.is_available(), reason="no CUDA device")
@pytest.mark.parametrize("name", NAMES)
def test_cuda_with_cpu_generator(name: str) -> None:
    x = _images(2).cuda()
    y = corrupt(x, name, 3, _gen(0))
    assert y.device == x.device and y.dtype == x.dtype and y.shape == x.shape
    assert torch.equal(y, corrupt(x, name, 3, _gen(0)))


# ---------------------------------------------------------------------------- hand-computed cases
def test_glass_shuffle_matches_sequential_copy() -> None:
    """The pointer-jumping formulation equals the reference's sequential in-place loop."""
    g = _gen(0)
    for h, w, delta in ((12, 15, 1), (13, 11, 2), (16, 16, 3)):
        offsets = torch.randint(-delta, delta, (3, 2, h, w), generator=g)
        img = torch.arange(3 * h * w).view(3, h, w)
        src = glass_shuffle_sources(offsets, h, w, delta)
        fast = img.view(3, -1).gather(1, src).view(3, h, w)
        for b in range(3):
            a = img[b].clone()
            for r in range(h - delta, delta, -1):
                for c in range(w - delta, delta, -1):
                    a[r, c] = a[r + offsets[b, 0, r, c], c + offsets[b, 1, r, c]]
            assert torch.equal(fast[b], a)


def test_motion_blur_kernel_by_hand() -> None:
    """Angle 0: output(x) = sum_i k_i img(min(x + i, W - 1)), k_i ~ exp(-i^2 / (2 sigma^2))."""
    w = 40
    row = torch.zeros(w, dtype=torch.float64)
    row[20] = 1.0
    img = row.view(1, 1, 1, w).expand(1, 3, 34, w).clone()
    out = motion_blur(img, 3, 2.0, torch.zeros(1))
    k = np.exp(-np.arange(7) ** 2 / 8.0)
    k /= k.sum()
    expect = np.zeros(w)
    for x in range(w):
        for i in range(7):
            expect[x] += k[i] * row[min(x + i, w - 1)].item()
    assert np.allclose(out[0, 0, 10].numpy(), expect, atol=1e-6)
    # angle 90 degrees: the shift is along rows (dy = -ceil(i - 0.5) = -i)
    out = motion_blur(img.transpose(2, 3).contiguous(), 3, 2.0, torch.full((1,), 90.0))
    assert np.allclose(out[0, 0, :, 10].numpy(), expect, atol=1e-6)


def test_gaussian_blur_by_hand() -> None:
    x = torch.zeros(1, 3, 41, 41, dtype=torch.uint8)
    x[0, :, 20, 20] = 255
    y = corrupt(x, "gaussian_blur", 1)  # sigma 1, radius 4
    k = gaussian_kernel1d(1.0, 4)
    assert int(y[0, 0, 20, 20]) == math.floor(255 * k[4] * k[4])
    assert int(y[0, 0, 20, 22]) == math.floor(255 * k[4] * k[6])
    assert int(y[0, 0, 20, 25]) == 0  # beyond the 4-sigma radius
    flat = torch.full((1, 3, 64, 64), 77, dtype=torch.uint8)
    for name in ("gaussian_blur", "defocus_blur", "glass_blur", "motion_blur"):
        assert torch.equal(corrupt(flat, name, 5, _gen(0)), flat), name


def _truncated(values: list[int], exact: list[float]) -> bool:
    """``values`` are the truncations of ``exact`` (grey levels); a value that is an integer in exact
    arithmetic may land one level lower through float rounding, as in the reference."""
    return all(v in (math.floor(e - 1e-6), math.floor(e + 1e-6)) for v, e in zip(values, exact))


def test_digital_by_hand() -> None:
    x = torch.zeros(1, 3, 32, 32, dtype=torch.uint8)
    x[0, :, :16] = torch.tensor([200, 100, 50], dtype=torch.uint8).view(3, 1, 1)
    x[0, :, 16:] = 10
    top, bottom = (200, 100, 50), (10, 10, 10)
    # contrast sev 1: (v - m) * 0.4 + m with the per-channel mean m over the image
    means = (105.0, 55.0, 30.0)
    y = corrupt(x, "contrast", 1)
    assert _truncated(y[0, :, 0, 0].tolist(), [(v - m) * 0.4 + m for v, m in zip(top, means)])
    assert _truncated(y[0, :, 31, 0].tolist(), [(v - m) * 0.4 + m for v, m in zip(bottom, means)])
    # brightness sev 2: V 200 -> 200 + 0.2 * 255; hue and saturation kept => channels scale by V'/V
    y = corrupt(x, "brightness", 2)
    assert _truncated(y[0, :, 0, 0].tolist(), [c * (200 + 51) / 200 for c in top])
    assert _truncated(y[0, :, 31, 0].tolist(), [10 + 51.0] * 3)
    # saturate sev 4: grey pixels get hue 0 (red): (V, V (1 - S'), V (1 - S')) with S' = 0.1
    y = corrupt(x, "saturate", 4)
    assert _truncated(y[0, :, 31, 0].tolist(), [10.0, 9.0, 9.0])
    # saturate sev 2: S' = 0.1 S, so each channel becomes V - (V - c) * 0.1
    y = corrupt(x, "saturate", 2)
    assert _truncated(y[0, :, 0, 0].tolist(), [200 - (200 - c) * 0.1 for c in top])


def test_impulse_noise_flips_channels_independently() -> None:
    x = torch.full((4, 3, 64, 64), 128, dtype=torch.uint8)
    c = 0.27  # severity 5
    y = corrupt(x, "impulse_noise", 5, _gen(0))
    flipped = y != 128
    assert abs(float(flipped.double().mean()) - c) < 0.01
    assert set(y[flipped].unique().tolist()) == {0, 255}
    assert abs(float((y == 255).double().mean()) - c / 2) < 0.01
    per_pixel = flipped.sum(dim=1)
    # independent per channel: exactly one of three flipped with prob 3 c (1 - c)^2
    assert abs(float((per_pixel == 1).double().mean()) - 3 * c * (1 - c) ** 2) < 0.015


def test_noise_statistics() -> None:
    x = torch.full((2, 3, 128, 128), 0.5, dtype=torch.float64)
    assert abs(float((corrupt(x, "gaussian_noise", 1, _gen(0)) - 0.5).std()) - 0.08) < 0.002
    y = corrupt(x, "shot_noise", 1, _gen(0)) * 60  # Poisson(30)
    assert abs(float(y.mean()) - 30) < 0.1 and abs(float(y.var()) - 30) < 1.0
    assert torch.allclose(y, y.round(), atol=1e-4)
    z = corrupt(x, "speckle_noise", 1, _gen(0))  # 0.5 + 0.5 N(0, 0.15^2)
    assert abs(float((z - 0.5).std()) - 0.075) < 0.002


def test_frost_uses_first_five_textures_only() -> None:
    x = torch.zeros(40, 3, 32, 32, dtype=torch.uint8)
    seen = set()
    orig = weather._frost_tensor

    def spy(index, h, w, device):
        seen.add(index)
        return orig(index, h, w, device)

    weather._frost_tensor, saved = spy, weather._frost_tensor
    try:
        corrupt(x, "frost", 1, _gen(0))
    finally:
        weather._frost_tensor = saved
    assert seen == {0, 1, 2, 3, 4}


# --------------------------------------------------------------------------------- fidelity (PSNR)
# The acceptance table of docs/TASK.md: mean PSNR (dB) of the uint8 corrupted crop against the clean
# crop over the 36 crops, and tolerance, per corruption and severity 1-5 (imagecorruptions 1.1.2).
ACCEPTANCE = {
    "motion_blur": ((23.80, 21.90, 20.44, 19.44, 18.91), (0.17, 0.15, 0.15, 0.15, 0.15)),
    "defocus_blur": ((24.22, 23.25, 21.92, 21.12, 20.48), (0.05,) * 5),
    "glass_blur": ((23.26, 23.45, 20.73, 21.17, 20.73), (0.10,) * 5),
    "gaussian_blur": ((27.33, 23.95, 22.55, 21.68, 20.57), (0.05,) * 5),
    "gaussian_noise": ((22.28, 18.94, 15.73, 13.03, 10.59), (0.10,) * 5),
    "impulse_noise": ((20.14, 17.11, 15.35, 12.59, 10.58), (0.10,) * 5),
    "shot_noise": ((21.55, 17.98, 15.11, 11.86, 10.07), (0.10,) * 5),
    "speckle_noise": ((22.68, 20.32, 15.85, 13.98, 12.13), (0.10,) * 5),
    "brightness": ((21.94, 16.12, 13.10, 11.20, 9.97), (0.05,) * 5),
    "contrast": ((18.21, 16.87, 15.71, 14.69, 14.21), (0.05,) * 5),
    "saturate": ((23.26, 21.05, 22.20, 14.49, 11.74), (0.05,) * 5),
    "jpeg_compression": ((27.86, 26.97, 26.41, 25.16, 23.98), (0.05,) * 5),
    "snow": ((15.28, 11.40, 11.36, 9.82, 8.74), (0.10,) * 5),
    "spatter": ((34.24, 24.65, 22.65, 18.36, 16.23), (0.71, 0.16, 0.15, 0.15, 0.15)),
    "fog": ((14.30, 13.45, 12.68, 12.72, 12.22), (0.29, 0.28, 0.27, 0.23, 0.21)),
    "frost": ((12.77, 11.71, 10.94, 11.01, 11.13), (0.41, 0.54, 0.57, 0.60, 0.55)),
}
# Draws per crop where one draw's spread is too close to the tolerance. spatter 2 is the tightest
# case: the reference itself (imagecorruptions 1.1.2 with OpenCV 4.8, scikit-image 0.20) averages
# 24.80 dB there over 6 draws, and ours 24.78 over 30, both within but near the edge of the table's
# 24.65 +- 0.16; means of 5 draws vary by +-0.06 dB.
DRAWS = {"spatter": (4, 5, 1, 1, 1), "fog": (5, 5, 4, 3, 2)}


@pytest.fixture(scope="module")
def crops(sun360_mini_files) -> torch.Tensor:
    """The 36 crops: rows 128-383, cols 384-639 of each panorama (sorted by path), ``(36, 3, 256, 256)``."""
    from findview.imageio import load_panorama

    arr = np.stack([load_panorama(f)[128:384, 384:640] for f in sun360_mini_files])
    return torch.from_numpy(arr).permute(0, 3, 1, 2).contiguous()


def _psnr(y: torch.Tensor, x: torch.Tensor) -> float:
    mse = (y.float() - x.float()).square_().mean(dim=(1, 2, 3)).double()  # float32 cascade sums suffice
    return float((10 * torch.log10(255.0**2 / mse)).mean())


def _quantise(y: torch.Tensor) -> torch.Tensor:
    return torch.floor(y.clamp(0, 1) * 255.0 + 1e-3).to(torch.uint8)


@pytest.mark.parametrize("name", NAMES)
def test_fidelity_psnr(name: str, crops: torch.Tensor) -> None:
    """Mean PSNR per severity within the acceptance tolerance.

    motion_blur: its only randomness is the angle, so the expectation is taken with stratified
    angles (two per crop, spread evenly over [-45, 45)) through the same blur ``corrupt`` uses;
    frost: each crop under two of the five textures (every texture equally often) at random positions.
    """
    means, tols = ACCEPTANCE[name]
    n = crops.shape[0]
    got = []
    for s in range(1, 6):
        if name == "motion_blur":
            radius, sigma = MOTION_BLUR[s - 1]
            angles = torch.cat([-45 + 90 * (torch.randperm(n, generator=_gen(k)) + 0.5) / n for k in range(2)])
            xs = crops.repeat(2, 1, 1, 1)
            y = _quantise(motion_blur(xs.float() / 255.0, radius, sigma, angles))
            psnr = _psnr(y, xs)
        elif name == "frost":
            xs = crops.repeat(2, 1, 1, 1)
            textures = torch.cat([(torch.arange(n) + 2 * k) % 5 for k in range(2)])  # each texture 14-15 times
            positions = torch.rand((2 * n, 2), generator=_gen(s), dtype=torch.float64)
            psnr = _psnr(_quantise(weather.frost_blend(xs.float() / 255.0, s, textures, positions)), xs)
        else:
            draws = DRAWS.get(name, (1,) * 5)[s - 1]
            g = _gen(s - 1)
            psnr = float(np.mean([_psnr(corrupt(crops, name, s, g), crops) for _ in range(draws)]))
        got.append(psnr)
    bad = [(s + 1, round(got[s], 3), means[s], tols[s]) for s in range(5) if abs(got[s] - means[s]) > tols[s]]
    assert not bad, f"{name}: (severity, PSNR, reference, tol) out of tolerance: {bad}"


def test_motion_blur_wiring_uses_uniform_angle() -> None:
    """``corrupt`` draws one angle per image uniform in [-45, 45) and applies the tested blur."""
    x = _images(3, 40, 40)
    g = _gen(5)
    y = corrupt(x, "motion_blur", 2, g)
    g2 = _gen(5)
    angles = torch.rand((3,), generator=g2) * 90.0 - 45.0
    radius, sigma = MOTION_BLUR[1]
    assert torch.equal(y, _quantise(motion_blur(x.float() / 255.0, radius, sigma, angles)))


# ----------------------------------------------------------------------------- render tool (grid)
def test_render_corruptions_grid() -> None:
    import importlib.util
    from pathlib import Path

    path = Path(__file__).resolve().parents[1] / "tools" / "render_corruptions.py"
    spec = importlib.util.spec_from_file_location("render_corruptions_tool", path)
    mod = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(mod)
    view = _images(1, 48, 64)[0].permute(1, 2, 0).numpy()
    grid = mod.corruption_grid(view, 2, seed=0, labels=False)
    assert grid.shape == (4 * 48, 5 * 64, 3) and grid.dtype == np.uint8
    assert np.array_equal(grid[:48, :64], view)  # the clean view first
    assert all(np.array_equal(grid[r * 48 : (r + 1) * 48, :64], view) for r in range(4))  # in every row: no black tile
    tiles = [grid[r * 48 : (r + 1) * 48, c * 64 : (c + 1) * 64] for r in range(4) for c in range(1, 5)]
    # brightness (row 2, column 1) equals corrupt() on the view
    want = corrupt(torch.from_numpy(view).permute(2, 0, 1)[None], "brightness", 2)[0].permute(1, 2, 0).numpy()
    assert np.array_equal(tiles[8], want)
    assert all(not np.array_equal(t, view) for t in tiles)
    labelled = mod.corruption_grid(view, 2, seed=0, labels=True)
    assert not np.array_equal(labelled, grid)
    with pytest.raises(ValueError, match="severity 7"):
        mod.corruption_grid(view, 7)


def test_render_corruptions_tool(tmp_path) -> None:
    import subprocess
    import sys
    from pathlib import Path

    import cv2

    repo = Path(__file__).resolve().parents[1]
    pano = tmp_path / "pano.png"
    rng = np.random.default_rng(0)
    img = cv2.resize(rng.integers(0, 256, (16, 32, 3), dtype=np.uint8), (256, 128), interpolation=cv2.INTER_LINEAR)
    cv2.imwrite(str(pano), img)
    out = tmp_path / "grid.png"
    cmd = [sys.executable, str(repo / "tools" / "render_corruptions.py"), f"image={pano}", "target=[0,90]",
           "severity=4", "sim.height=48", "sim.width=64", f"out={out}", f"hydra.run.dir={tmp_path / 'run'}"]
    res = subprocess.run(cmd, cwd=repo, capture_output=True, text=True, timeout=120)
    assert res.returncode == 0, res.stderr[-2000:]
    grid = cv2.imread(str(out))
    assert grid is not None and grid.shape == (4 * 48, 5 * 64, 3)
