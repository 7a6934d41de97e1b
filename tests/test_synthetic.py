"""findview.dataset.synthetic: procedural panoramas (determinism, texture richness, distinctness, cache)."""

from __future__ import annotations

from pathlib import Path

import cv2
import numpy as np
import pytest
import torch

from findview.dataset import DatasetError, SCENE_KINDS, ensure_synthetic_images, generate_panorama, sample_pitch
from findview.imageio import load_panorama


def _equi2pers():
    from findview.sim import equi2pers

    return equi2pers


@pytest.fixture(scope="module")
def panos() -> dict[str, np.ndarray]:
    """One full-size (1024x512) panorama per scene kind."""
    return {kind: generate_panorama(10 + i, kind, 1024) for i, kind in enumerate(SCENE_KINDS)}


def _views(img: np.ndarray, pitch, yaw, fov: float = 90, size: int = 256) -> np.ndarray:
    """Gray ``(B, size, size)`` uint8 views of an RGB panorama."""
    equi2pers = _equi2pers()
    pitch = torch.as_tensor(np.asarray(pitch, dtype=np.float64))
    yaw = torch.as_tensor(np.asarray(yaw, dtype=np.float64))
    equi = torch.from_numpy(img).permute(2, 0, 1)[None].contiguous()
    out = []
    for i in range(len(pitch)):  # one view per call: no (B, 3, He, We) copy of the panorama
        v = equi2pers(equi, pitch[i : i + 1], yaw[i : i + 1], fov, size, size)[0].permute(1, 2, 0).numpy()
        out.append(cv2.cvtColor(np.ascontiguousarray(v), cv2.COLOR_RGB2GRAY))
    return np.stack(out)


def test_shape_determinism_and_variety() -> None:
    a = generate_panorama(7, "room", 256)
    assert a.shape == (128, 256, 3) and a.dtype == np.uint8
    assert np.array_equal(a, generate_panorama(7, "room", 256))
    b = generate_panorama(8, "room", 256)
    assert np.abs(a.astype(int) - b).mean() > 20  # another seed, another scene
    c = generate_panorama(7, "landscape", 256)
    assert np.array_equal(c, generate_panorama(7, "landscape", 256))
    assert np.abs(c.astype(int) - generate_panorama(8, "landscape", 256)).mean() > 5
    with pytest.raises(ValueError, match="scene kind"):
        generate_panorama(0, "castle")
    with pytest.raises(ValueError, match="even number"):
        generate_panorama(0, "room", 255)


def test_orb_keypoints_in_random_views(panos: dict[str, np.ndarray]) -> None:
    orb = cv2.ORB_create(500)
    rng = np.random.default_rng(0)
    fractions = {}
    for kind, img in panos.items():
        n = 10  # 40 views in all
        pitch = sample_pitch(rng, n, 60)
        yaw = rng.integers(-179, 181, n)
        counts = [len(orb.detect(v, None)) for v in _views(img, pitch, yaw)]
        fractions[kind] = np.mean(np.array(counts) >= 200)
        assert fractions[kind] >= 0.7, (kind, counts)
    assert np.mean(list(fractions.values())) >= 0.9, fractions


def test_views_in_different_directions_are_distinct(panos: dict[str, np.ndarray]) -> None:
    """Non-overlapping views share no ORB matches (ratio test 0.7), while nearby views share many."""
    orb = cv2.ORB_create(500)
    bf = cv2.BFMatcher(cv2.NORM_HAMMING)

    def good(a: np.ndarray, b: np.ndarray) -> int:
        _, da = orb.detectAndCompute(a, None)
        _, db = orb.detectAndCompute(b, None)
        pairs = bf.knnMatch(da, db, k=2)
        return sum(1 for m in pairs if len(m) == 2 and m[0].distance < 0.7 * m[1].distance)

    for kind, img in panos.items():
        v = _views(img, [0, 0, 0, 0, 2], [-135, -45, 45, 135, 47])
        near = good(v[2], v[4])
        assert near >= 100, (kind, near)
        for i, j in ((0, 1), (1, 2), (2, 3), (3, 0), (0, 2)):
            assert good(v[i], v[j]) < 0.1 * near, (kind, i, j)
            assert np.abs(v[i].astype(int) - v[j]).mean() > 15, (kind, i, j)


def test_ray_cast_geometry(panos: dict[str, np.ndarray]) -> None:
    """The panorama is a function of direction: continuous across the +-180 seam, and each pole row
    (all pixels look almost the same way) is smooth: at most an edge or two crossing the pole."""
    for kind, img in panos.items():
        g = cv2.cvtColor(img, cv2.COLOR_RGB2GRAY).astype(float)
        seam = np.abs(g[:, 0] - g[:, -1]).mean()
        adjacent = np.abs(g[:, 1:] - g[:, :-1]).mean()
        assert seam < 2.0 * adjacent + 1, (kind, seam, adjacent)
        for row in (g[0], g[-1]):
            assert np.count_nonzero(np.abs(np.diff(row)) > 20) <= 4, kind


def test_ensure_synthetic_images(tmp_path: Path) -> None:
    root = tmp_path / "synthetic" / "images"
    entries = ensure_synthetic_images(root, num_images=3, seed=1, width=128, labels=["room", "landscape"], progress=False)
    assert [(Path(e.path).relative_to(root).as_posix(), e.label) for e in entries] == [
        ("room/synth_0000.jpg", "room"),
        ("landscape/synth_0001.jpg", "landscape"),
        ("room/synth_0002.jpg", "room"),
    ]
    for e in entries:
        assert load_panorama(e.path).shape == (64, 128, 3)
    assert (root / "synthetic.json").is_file()
    first = Path(entries[0].path)
    stamp = (first.stat().st_mtime_ns, first.read_bytes())
    again = ensure_synthetic_images(root, 3, 1, 128, ["room", "landscape"], progress=False)
    assert again == entries and (first.stat().st_mtime_ns, first.read_bytes()) == stamp  # cached
    ensure_synthetic_images(root, 2, 2, 128, ["room", "landscape"], progress=False)
    assert first.read_bytes() != stamp[1]  # another seed: regenerated
    assert not (root / "room" / "synth_0002.jpg").exists()  # stale image removed
    with pytest.raises(DatasetError, match="scene kinds"):
        ensure_synthetic_images(root, 2, 0, 128, ["castle"], progress=False)
