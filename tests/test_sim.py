"""Rendering against independent expectations: a per-pixel float64 reference written from the mapping in docs/TASK.md."""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch

from findview.imageio import load_panorama
from findview.sim import PanoramaBank, Simulator, equi2pers


def reference_pixel(equi: np.ndarray, pitch: float, yaw: float, fov: float, H: int, W: int, i: int, j: int) -> np.ndarray:
    """The mapping of docs/TASK.md, one pixel at a time, float64, bilinear with u wrapping and v clamped."""
    f = W / (2 * math.tan(math.radians(fov) / 2))
    x, y, z = (i + 0.5 - W / 2) / f, -(j + 0.5 - H / 2) / f, 1.0
    p, w = math.radians(pitch), math.radians(yaw)
    y, z = y * math.cos(p) + z * math.sin(p), -y * math.sin(p) + z * math.cos(p)
    x, z = x * math.cos(w) + z * math.sin(w), -x * math.sin(w) + z * math.cos(w)
    lon = math.atan2(x, z)
    lat = math.asin(y / math.sqrt(x * x + y * y + z * z))
    He, We = equi.shape[:2]
    u = (lon / (2 * math.pi) + 0.5) * We - 0.5
    v = (0.5 - lat / math.pi) * He - 0.5
    v = min(max(v, 0.0), He - 1.0)
    u0, v0 = math.floor(u), math.floor(v)
    fu, fv = u - u0, v - v0
    c = lambda uu, vv: equi[min(vv, He - 1), uu % We].astype(np.float64)  # noqa: E731
    top = c(u0, v0) * (1 - fu) + c(u0 + 1, v0) * fu
    bot = c(u0, v0 + 1) * (1 - fu) + c(u0 + 1, v0 + 1) * fu
    return top * (1 - fv) + bot * fv


ROTATIONS = [(0, 0), (60, 179), (-60, -179), (37, 180), (-12, -95), (5, 1), (59, -1), (-33, 172)]


@pytest.fixture(scope="module")
def pano(sun360_mini_files) -> np.ndarray:
    return load_panorama(sun360_mini_files[0])


@pytest.mark.parametrize("backend", ["torch", "opencv"])
def test_equi2pers_matches_float64_reference(pano, backend):
    rng = np.random.default_rng(0)
    H, W, fov = 96, 128, 75.0
    equi = torch.from_numpy(pano).permute(2, 0, 1)[None].repeat(len(ROTATIONS), 1, 1, 1)
    pitch = torch.tensor([r[0] for r in ROTATIONS], dtype=torch.float64)
    yaw = torch.tensor([r[1] for r in ROTATIONS], dtype=torch.float64)
    out = equi2pers(equi, pitch, yaw, fov, H, W, backend=backend).numpy()
    assert out.shape == (len(ROTATIONS), 3, H, W) and out.dtype == np.uint8
    diffs = []
    for b, (p, y) in enumerate(ROTATIONS):
        for _ in range(150):
            i, j = int(rng.integers(W)), int(rng.integers(H))
            ref = reference_pixel(pano, p, y, fov, H, W, i, j)
            diffs.append(np.abs(out[b, :, j, i].astype(np.float64) - ref).max())
    diffs = np.array(diffs)
    # torch: float32 weights + rounding -> within 1 level; OpenCV quantises sample points to 1/32 px
    assert diffs.max() <= (1.0 if backend == "torch" else 3.0)
    assert diffs.mean() < 0.6


def test_equi2pers_float64_input_is_exact(pano):
    equi = torch.from_numpy(pano).permute(2, 0, 1)[None].double()
    out = equi2pers(equi, torch.tensor([23.0]), torch.tensor([-170.0]), 90, 32, 32)[0].numpy()
    assert out.dtype == np.float64
    for i, j in [(0, 0), (31, 31), (16, 5), (3, 29)]:
        np.testing.assert_allclose(out[:, j, i], reference_pixel(pano, 23, -170, 90, 32, 32, i, j), atol=1e-6)


def _marker_pano(He=256, lon_deg=30.0, lat_deg=0.0) -> np.ndarray:
    """Black panorama with a white disc (radius 4 px) centred at (lon, lat)."""
    We = 2 * He
    img = np.zeros((He, We, 3), np.uint8)
    u = (math.radians(lon_deg) / (2 * math.pi) + 0.5) * We - 0.5
    v = (0.5 - math.radians(lat_deg) / math.pi) * He - 0.5
    yy, xx = np.mgrid[0:He, 0:We]
    img[(xx - u) ** 2 + (yy - v) ** 2 <= 16] = 255
    return img


def _centroid(view: torch.Tensor) -> tuple[float, float]:
    m = view[0].double()
    ys, xs = torch.nonzero(m > 128, as_tuple=True)
    assert len(xs) > 0, "marker not visible"
    return float(xs.double().mean()), float(ys.double().mean())


def test_direction_conventions():
    W = H = 64
    right = torch.from_numpy(_marker_pano(lon_deg=30)).permute(2, 0, 1)[None]
    x, y = _centroid(equi2pers(right, 0.0, 0.0, 90, H, W)[0])
    assert x > W / 2 + 10 and abs(y - (H / 2 - 0.5)) < 1.5  # +lon appears on the right at yaw 0
    x, y = _centroid(equi2pers(right, 0.0, 30.0, 90, H, W)[0])
    assert abs(x - (W / 2 - 0.5)) < 1.5  # +yaw pans right onto it
    up = torch.from_numpy(_marker_pano(lon_deg=0, lat_deg=25)).permute(2, 0, 1)[None]
    x, y = _centroid(equi2pers(up, 0.0, 0.0, 90, H, W)[0])
    assert y < H / 2 - 10  # +lat appears in the upper half (row 0 at the top)
    x, y = _centroid(equi2pers(up, 25.0, 0.0, 90, H, W)[0])
    assert abs(y - (H / 2 - 0.5)) < 1.5 and abs(x - (W / 2 - 0.5)) < 1.5
    # expected horizontal offset of lon 30 at yaw 0: f' tan(30) pixels right of the centre
    x, _ = _centroid(equi2pers(right, 0.0, 0.0, 90, H, W)[0])
    assert abs(x + 0.5 - W / 2 - (W / 2) * math.tan(math.radians(30))) < 1.0


def test_seam_is_continuous():
    """A view straddling the +-180 seam equals the same view of the panorama rolled by half a turn."""
    rng = np.random.default_rng(1)
    He = 64
    img = np.kron(rng.integers(0, 255, (He // 4, He // 2, 3)), np.ones((4, 4, 1))).astype(np.uint8)
    a = torch.from_numpy(img).permute(2, 0, 1)[None]
    b = torch.from_numpy(np.roll(img, He, axis=1)).permute(2, 0, 1)[None]  # lon shifted by 180 deg
    va = equi2pers(a, 10.0, 180.0, 90, 48, 48, backend="torch")
    vb = equi2pers(b, 10.0, 0.0, 90, 48, 48, backend="torch")
    assert (va.int() - vb.int()).abs().max() <= 1


def test_centre_pixel_at_origin():
    """At (0, 0) the four central pixels surround the panorama centre (u = We/2 - 0.5, v = He/2 - 0.5)."""
    He = 128
    yy, xx = np.mgrid[0:He, 0 : 2 * He].astype(np.float64)
    smooth = np.stack([xx / (2 * He) * 255, yy / He * 255, np.full_like(xx, 7)], -1)
    equi = torch.from_numpy(smooth).permute(2, 0, 1)[None]
    v = equi2pers(equi, 0.0, 0.0, 90, 64, 64)[0]
    centre = v[:, 31:33, 31:33].mean(dim=(1, 2))
    expected = torch.tensor([(He - 0.5) / (2 * He) * 255, (He / 2 - 0.5) / He * 255, 7.0], dtype=torch.float64)
    assert torch.allclose(centre, expected, atol=0.05)


def test_fov60_shape_and_extent():
    He = 256
    yy, xx = np.mgrid[0:He, 0 : 2 * He].astype(np.float64)
    lon_img = np.stack([xx, yy, xx * 0], -1)  # channel 0 = u, channel 1 = v
    equi = torch.from_numpy(lon_img).permute(2, 0, 1)[None]
    v = equi2pers(equi, 0.0, 0.0, 60, 192, 256)
    assert v.shape == (1, 3, 192, 256)
    f = 256 / (2 * math.tan(math.radians(30)))
    lon_left = math.atan2((0.5 - 128) / f, 1.0)  # leftmost column on the horizon row pair
    u_expected = (lon_left / (2 * math.pi) + 0.5) * 2 * He - 0.5
    assert abs(float(v[0, 0, 96, 0]) - u_expected) < 0.3
    # vertical extent: the top row sits at atan((96 - 0.5) / f) above the horizon (centre column pair)
    lat_top = math.atan((96 - 0.5) / f)
    v_expected = (0.5 - lat_top / math.pi) * He - 0.5
    assert abs(float(v[0, 1, 0, 128]) - v_expected) < 0.5


def test_modes_and_dtypes(pano):
    equi = torch.from_numpy(pano).permute(2, 0, 1)[None]
    for mode in ("bilinear", "nearest", "bicubic"):
        a = equi2pers(equi, 10.0, 20.0, 90, 64, 64, mode=mode)
        b = equi2pers(equi.float(), 10.0, 20.0, 90, 64, 64, mode=mode)
        assert a.dtype == torch.uint8 and b.dtype == torch.float32
        d = (a.float() - b.clamp(0, 255)).abs()
        if mode == "nearest":  # OpenCV (uint8) and torch (float) paths may round exact ties differently
            assert (d > 0).float().mean() < 1e-3
        else:
            assert d.max() <= 1.0 + 1e-3
    near = equi2pers(equi, 10.0, 20.0, 90, 64, 64, mode="nearest", backend="torch")
    colours = set(map(tuple, pano.reshape(-1, 3).tolist()))
    sample = near[0].permute(1, 2, 0).reshape(-1, 3)[::97].tolist()
    assert all(tuple(c) in colours for c in sample)  # nearest copies pixels
    with pytest.raises(ValueError, match="mode"):
        equi2pers(equi, 0.0, 0.0, 90, 8, 8, mode="cubic")
    with pytest.raises(ValueError, match="fov"):
        equi2pers(equi, 0.0, 0.0, 180, 8, 8)
    with pytest.raises(ValueError, match="2:1"):
        equi2pers(equi[:, :, :, :100], 0.0, 0.0, 90, 8, 8)


@pytest.mark.parametrize("mode", ["bilinear", "nearest", "bicubic"])
def test_simulator_matches_equi2pers(sun360_mini_files, mode):
    """Per-pitch grids + yaw shift give the same views as the direct renderer, for both backends."""
    bank = PanoramaBank("cpu", 64, min_slots=2, prefetch_workers=0)
    slots = torch.tensor([bank.acquire(str(sun360_mini_files[3])), bank.acquire(str(sun360_mini_files[20]))])
    pitch = torch.tensor([60, -47])
    yaw = torch.tensor([180, -179])
    backends = ["torch"] + (["opencv"] if mode != "bicubic" else [])
    for backend in backends:
        sim = Simulator(bank, fov=90, height=64, width=64, pitch_bound=60, mode=mode, backend=backend)
        views = sim.render(slots, pitch, yaw)
        equi = torch.stack([bank.panorama(int(s)).permute(2, 0, 1) for s in slots])
        ref = equi2pers(equi, pitch.double(), yaw.double(), 90, 64, 64, mode=mode, backend="torch")
        d = (views.int() - ref.int()).abs()
        if mode == "nearest":  # float32 vs float64 sample points may pick the neighbour on exact ties
            assert (d > 0).float().mean() < 1e-3, backend
        else:
            assert d.float().mean() < 0.05 and d.max() <= (2 if backend == "opencv" else 1), (backend, d.max())


def test_simulator_rejects_bad_config(sun360_mini_files):
    bank = PanoramaBank("cpu", 16, prefetch_workers=0)
    with pytest.raises(ValueError, match="fov"):
        Simulator(bank, fov=0)
    with pytest.raises(ValueError, match="pitch_bound"):
        Simulator(bank, pitch_bound=91)
    with pytest.raises(ValueError, match="bank_mb"):
        PanoramaBank("cpu", 1, min_slots=4).acquire(str(sun360_mini_files[0]))


def test_bank_lru_and_prefetch(sun360_mini_files):
    bank = PanoramaBank("cpu", 3 * 1.5 + 0.1, prefetch_workers=1)  # three 1024x512 panoramas
    paths = [str(p) for p in sun360_mini_files[:5]]
    s0 = bank.acquire(paths[0])  # pinned
    for p in paths[1:3]:
        bank.release(bank.acquire(p))
    bank.prefetch([paths[3]])
    s3 = bank.acquire(paths[3])  # evicts the least recently used unpinned one (paths[1])
    assert bank.capacity == 3 and bank.stats["evictions"] == 1 and bank.stats["prefetched"] == 1
    assert paths[1] not in bank._slot_of and paths[0] in bank._slot_of
    assert torch.equal(bank.panorama(s3), torch.from_numpy(load_panorama(paths[3])))
    assert torch.equal(bank.panorama(s0), torch.from_numpy(load_panorama(paths[0])))
    bank.acquire(paths[2])
    with pytest.raises(RuntimeError, match="bank full"):
        bank.acquire(paths[4])


def reference_uv(pitch: float, fov: float, H: int, W: int, He: int, i: int, j: int) -> tuple[float, float]:
    """The sample point of view pixel (i, j) at (pitch, yaw 0), float64, u wrapped into [0, We), v clamped."""
    f = W / (2 * math.tan(math.radians(fov) / 2))
    x, y, z = (i + 0.5 - W / 2) / f, -(j + 0.5 - H / 2) / f, 1.0
    p = math.radians(pitch)
    y, z = y * math.cos(p) + z * math.sin(p), -y * math.sin(p) + z * math.cos(p)
    lon, lat = math.atan2(x, z), math.asin(y / math.sqrt(x * x + y * y + z * z))
    u = ((lon / (2 * math.pi) + 0.5) * 2 * He - 0.5) % (2 * He)
    v = min(max((0.5 - lat / math.pi) * He - 0.5, 0.0), He - 1.0)
    return u, v


@pytest.mark.parametrize("dtype", [torch.float64, torch.float32])
def test_yaw0_points_match_reference(dtype):
    from findview.sim.equi2pers import yaw0_points

    H, W, He, fov = 24, 40, 128, 75.0
    tol = 1e-9 if dtype == torch.float64 else 2e-3  # pixels
    for pitch in (-60.0, -7.0, 0.0, 33.5, 60.0, 89.0):
        u, v = yaw0_points(pitch, fov, H, W, He, dtype=dtype)
        assert u.shape == v.shape == (H, W) and u.dtype == dtype
        for i, j in [(0, 0), (W - 1, H - 1), (W // 2, H // 2), (3, 17), (W - 1, 0)]:
            ru, rv = reference_uv(pitch, fov, H, W, He, i, j)
            du = abs(float(u[j, i]) - ru)
            assert min(du, 2 * He - du) <= tol and abs(float(v[j, i]) - rv) <= tol, (pitch, i, j)


@pytest.mark.parametrize("backend", ["opencv", "torch"])
def test_simulator_builds_grids_lazily(sun360_mini_files, backend):
    """The first render builds only the pitches it needs; views do not depend on which grids exist."""
    bank = PanoramaBank("cpu", 64, min_slots=2, prefetch_workers=0)
    slots = torch.tensor([bank.acquire(str(sun360_mini_files[1])), bank.acquire(str(sun360_mini_files[2]))])
    pitch, yaw = torch.tensor([-41, 17]), torch.tensor([90, -3])
    lazy = Simulator(bank, fov=90, height=48, width=64, pitch_bound=60, backend=backend)
    assert lazy.grids_built == 0
    first = lazy.render(slots, pitch, yaw).clone()
    assert lazy.grids_built == 2
    lazy.render(slots, torch.tensor([17, 0]), yaw)
    assert lazy.grids_built == 3  # 17 is reused, 0 is new
    eager = Simulator(bank, fov=90, height=48, width=64, pitch_bound=60, backend=backend)
    eager.build_all_grids(bank.slots.shape[1])
    assert eager.grids_built == 121
    assert torch.equal(eager.render(slots, pitch, yaw), first)
    ref = equi2pers(torch.stack([bank.panorama(int(s)).permute(2, 0, 1) for s in slots]), pitch.double(), yaw.double(), 90, 48, 64, backend="torch")
    assert (first.int() - ref.int()).abs().max() <= (2 if backend == "opencv" else 1)
