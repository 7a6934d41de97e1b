"""findview.dataset: discovery, validation, splits, difficulty rules, sampling, episode files, ensure_dataset."""

from __future__ import annotations

import json
import math
import os
from pathlib import Path

import cv2
import numpy as np
import pytest

from findview.dataset import (
    DIFFICULTIES,
    DatasetError,
    EpisodeSampler,
    ImageEntry,
    SamplingError,
    check_fov,
    check_pitch_bound,
    difficulty_mask,
    discover,
    discover_folder,
    discover_indoor360,
    discover_sun360,
    episode_file,
    load_episodes,
    load_split,
    make_static_episodes,
    pitch_distribution,
    sample_pitch,
    sample_rotations,
    satisfies,
    split_entries,
    validate_images,
    write_episode_file,
    write_splits,
)


def prepare_dataset(cfg, *args, **kwargs):
    """:func:`findview.dataset.prepare_dataset` of a mapping (converted once, like any caller outside the tools)."""
    from findview.config import DatasetConfig, as_section
    from findview.dataset import prepare_dataset as prepare

    return prepare(as_section(cfg, DatasetConfig), *args, **kwargs)


def ensure_dataset(cfg, *args, **kwargs):
    """:func:`findview.dataset.ensure_dataset` of a mapping (converted once with as_section)."""
    from findview.config import DatasetConfig, as_section
    from findview.dataset import ensure_dataset as ensure

    return ensure(as_section(cfg, DatasetConfig), *args, **kwargs)
from findview.dataset.splits import normalize_ratios, split_counts
from findview.geometry import yaw_diff
from findview.imageio import PanoramaError, load_panorama

REPO = Path(__file__).resolve().parents[1]


# ---------------------------------------------------------------------------------------------------
# helpers
# ---------------------------------------------------------------------------------------------------
def _write(path: Path, h: int = 64, w: int = 128, channels: int = 3, seed: int = 0) -> Path:
    path.parent.mkdir(parents=True, exist_ok=True)
    rng = np.random.default_rng(seed)
    shape = (h, w) if channels == 1 else (h, w, channels)
    assert cv2.imwrite(str(path), rng.integers(0, 256, shape, dtype=np.uint8))
    return path


def _rule(dp: np.ndarray, dy: np.ndarray, difficulty: str, f: float, T: int = 5000, hard_rule: str = "or") -> np.ndarray:
    """The docs/TASK.md (Difficulties) rules written out independently of the implementation."""
    l1 = dp + dy
    base = (l1 > 10) & (l1 < T)
    if difficulty == "easy":
        return base & (np.sqrt(dp**2 + dy**2) <= math.sqrt(2) * f / 2 + 1e-9)
    if difficulty == "medium":
        return base & (l1 > f / 2) & (l1 <= f)
    if hard_rule == "or":
        return base & ((dp > f) | (dy > f))
    return base & (dp > f) & (dy > f)


# ---------------------------------------------------------------------------------------------------
# discovery
# ---------------------------------------------------------------------------------------------------
def test_discover_sun360_mini(sun360_mini: Path, sun360_mini_files: list[Path]) -> None:
    indoor = discover_sun360(sun360_mini, "indoor")
    assert len(indoor) == 16
    counts: dict[str, int] = {}
    for e in indoor:
        assert os.path.isabs(e.path) and Path(e.path).is_file()
        assert Path(e.path).parent.name == e.label
        counts[e.label] = counts.get(e.label, 0) + 1
    assert counts == {"bedroom": 4, "greenhouse": 4, "museum": 4, "office": 4}
    outdoor = discover_sun360(sun360_mini, "outdoor")
    assert {e.label for e in outdoor} == {"beach", "forest", "mountain", "park"} and len(outdoor) == 16
    others = discover_sun360(sun360_mini, "others")
    assert len(others) == 4 and {e.label for e in others} == {"others"}
    everything = discover("sun360", sun360_mini, "all")
    assert len(everything) == 36
    assert sorted(Path(e.path) for e in everything) == sorted(p.resolve() for p in sun360_mini_files)
    assert everything == sorted(everything)  # deterministic order


def test_discover_sun360_errors(tmp_path: Path) -> None:
    with pytest.raises(DatasetError, match="subset"):
        discover_sun360(tmp_path, "kitchen")
    for bad in ("indoor+kitchen", "indoor+indoor", "all+indoor", "indoor+"):
        with pytest.raises(DatasetError, match=r"unknown SUN360 subset.*joined by '\+'"):
            discover_sun360(tmp_path, bad)
    with pytest.raises(DatasetError, match=r"SUN360 root folder not found.*indoor\|outdoor\|others"):
        discover_sun360(tmp_path / "nope", "indoor")
    (tmp_path / "indoor" / "bedroom").mkdir(parents=True)
    with pytest.raises(DatasetError, match=r"outdoor.*<root>/<indoor\|outdoor\|others>/<sub-category>"):
        discover_sun360(tmp_path, "outdoor")
    with pytest.raises(DatasetError, match=r"no panorama found in .*indoor.*layout"):
        discover_sun360(tmp_path, "indoor")


def test_discover_folder_labels_and_indoor360(tmp_path: Path) -> None:
    root = tmp_path / "mypanos"
    _write(root / "top.png")
    _write(root / "kitchen" / "k1.jpg")
    _write(root / "a" / "b" / "deep.JPG")
    _write(root / ".hidden" / "h.png")
    _write(root / "kitchen" / ".dot.png")
    (root / "notes.txt").write_text("not an image")
    entries = discover_folder(root)
    labels = {Path(e.path).name: e.label for e in entries}
    assert labels == {"top.png": "mypanos", "k1.jpg": "kitchen", "deep.JPG": "a/b"}
    flat = discover_indoor360(root)
    assert len(flat) == 3 and {e.label for e in flat} == {"indoor360"}


def test_discover_missing_or_empty_folder(tmp_path: Path) -> None:
    with pytest.raises(DatasetError, match=str(tmp_path / "missing")):
        discover_folder(tmp_path / "missing")
    (tmp_path / "empty").mkdir()
    (tmp_path / "empty" / "readme.txt").write_text("x")
    with pytest.raises(DatasetError, match=r"no image found in folder .*empty"):
        discover_folder(tmp_path / "empty")
    with pytest.raises(DatasetError, match="360-Indoor folder"):
        discover_indoor360(tmp_path / "empty")
    with pytest.raises(DatasetError, match="unknown dataset kind"):
        discover("flickr", tmp_path)


# ---------------------------------------------------------------------------------------------------
# validation
# ---------------------------------------------------------------------------------------------------
def test_validate_rejects_truncated_and_wrong_aspect(tmp_path: Path) -> None:
    good = _write(tmp_path / "good.jpg", 128, 256)
    trunc = _write(tmp_path / "trunc.jpg", 128, 256, seed=1)
    data = trunc.read_bytes()
    trunc.write_bytes(data[: len(data) // 2])
    wrong = _write(tmp_path / "wrong.png", 200, 300)
    validate_images([ImageEntry(str(good), "x")], progress=False)
    with pytest.raises(PanoramaError, match=r"trunc.jpg: .*(truncated|cannot decode)"):
        validate_images([ImageEntry(str(good), "x"), ImageEntry(str(trunc), "x")], progress=False)
    with pytest.raises(PanoramaError, match=r"wrong.png.*300x200"):
        validate_images([ImageEntry(str(wrong), "x")], progress=False)
    with pytest.raises(PanoramaError, match=r"2 invalid panoramas: .*(trunc|wrong).*(trunc|wrong)"):
        validate_images([ImageEntry(str(p), "x") for p in (good, trunc, wrong, good)], workers=2, progress=False)


def test_validate_accepts_gray_and_rgba(tmp_path: Path) -> None:
    gray = _write(tmp_path / "gray.png", 64, 128, channels=1)
    rgba = _write(tmp_path / "rgba.png", 64, 128, channels=4)
    validate_images([ImageEntry(str(gray), "x"), ImageEntry(str(rgba), "x")], progress=False)
    for p in (gray, rgba):
        img = load_panorama(p)
        assert img.shape == (64, 128, 3) and img.dtype == np.uint8


# ---------------------------------------------------------------------------------------------------
# splits
# ---------------------------------------------------------------------------------------------------
def _fake_entries(root: Path, sizes: dict[str, int]) -> list[ImageEntry]:
    return [ImageEntry(str(root / lab / f"pano_{i:04d}.jpg"), lab) for lab, n in sizes.items() for i in range(n)]


def test_split_counts_rule() -> None:
    r = normalize_ratios([0.8, 0.1, 0.1])
    assert split_counts(10, r) == [8, 1, 1]
    assert split_counts(50, r) == [40, 5, 5]
    assert split_counts(4, r) == [3, 1, 0]  # leftover: tie between val and test -> split order
    assert split_counts(4, r, assigned=[3, 1, 0], seen=4) == [3, 0, 1]  # test is now further below its share
    assert split_counts(7, normalize_ratios([0, 0, 1])) == [0, 0, 7]
    assert normalize_ratios([8, 1, 1]) == r
    for bad in ([0.5, 0.5], [-1, 1, 1], [0, 0, 0], ["a", 1, 1]):
        with pytest.raises(DatasetError):
            normalize_ratios(bad)


def test_split_per_label_and_deterministic(tmp_path: Path) -> None:
    sizes = {"bedroom": 50, "office": 23, "museum": 7, "beach": 4, "solo": 1}
    entries = _fake_entries(tmp_path, sizes)
    a = split_entries(entries, tmp_path, (0.8, 0.1, 0.1), seed=0)
    b = split_entries(list(reversed(entries)), tmp_path, (0.8, 0.1, 0.1), seed=0)
    assert a == b  # independent of input order
    flat = [e for s in ("train", "val", "test") for e in a[s]]
    assert sorted(flat) == sorted(entries) and len(set(flat)) == len(entries)  # exactly one split each
    for lab, n in sizes.items():
        got = [sum(e.label == lab for e in a[s]) for s in ("train", "val", "test")]
        for c, r in zip(got, (0.8, 0.1, 0.1)):
            assert math.floor(n * r) <= c <= math.ceil(n * r), (lab, got)
    assert [sum(e.label == "bedroom" for e in a[s]) for s in ("train", "val", "test")] == [40, 5, 5]
    total = len(entries)
    for s, r in zip(("train", "val", "test"), (0.8, 0.1, 0.1)):
        assert abs(len(a[s]) - r * total) <= 1
    c = split_entries(entries, tmp_path, (0.8, 0.1, 0.1), seed=1)
    assert c != a
    # the split depends on paths relative to the root, not on where the data set lives
    moved = [ImageEntry(e.path.replace(str(tmp_path), "/somewhere/else"), e.label) for e in entries]
    d = split_entries(moved, "/somewhere/else", (0.8, 0.1, 0.1), seed=0)
    assert [Path(e.path).name for e in d["val"]] == [Path(e.path).name for e in a["val"]]
    everything_test = split_entries(entries, tmp_path, (0, 0, 1), seed=0)
    assert not everything_test["train"] and not everything_test["val"] and len(everything_test["test"]) == total


def test_split_duplicates_rejected(tmp_path: Path) -> None:
    e = ImageEntry(str(tmp_path / "a.jpg"), "x")
    with pytest.raises(DatasetError, match="duplicate"):
        split_entries([e, e], tmp_path)


def test_splits_file_roundtrip_and_missing(tmp_path: Path) -> None:
    root = tmp_path / "data"
    entries = _fake_entries(root, {"a": 10, "b": 10})
    splits = split_entries(entries, root)
    out = tmp_path / "out"
    write_splits(out, splits, dataset="toy", root=root, seed=0, ratios=[0.8, 0.1, 0.1])
    doc = json.loads((out / "splits.json").read_text())
    assert doc["dataset"] == "toy" and doc["root"] == str(root) and doc["seed"] == 0
    assert doc["ratios"] == [0.8, 0.1, 0.1]
    assert doc["splits"]["val"][0]["image"].startswith(("a/", "b/"))
    for s in ("train", "val", "test"):
        assert load_split(out, s) == splits[s]
    other = load_split(out, "test", root=tmp_path / "elsewhere")
    assert all(e.path.startswith(str(tmp_path / "elsewhere")) for e in other)
    with pytest.raises(DatasetError, match="unknown split"):
        load_split(out, "dev")
    with pytest.raises(FileNotFoundError, match=r"splits file not found: .*nowhere.*make_dataset"):
        load_split(tmp_path / "nowhere", "test")


# ---------------------------------------------------------------------------------------------------
# difficulty rules
# ---------------------------------------------------------------------------------------------------
def test_difficulty_hand_cases_fov90() -> None:
    # easy bound at fov 90: sqrt(2) * 45 = 63.64
    assert satisfies(0, 0, 45, 45, "easy", 90)  # L2 = 63.64, exactly on the bound
    assert not satisfies(0, 0, 45, 46, "easy", 90)  # L2 = 64.35
    assert satisfies(0, 0, 0, 63, "easy", 90) and not satisfies(0, 0, 0, 64, "easy", 90)
    assert not satisfies(0, 0, 5, 5, "easy", 90)  # L1 = 10 is not > 10
    assert satisfies(0, 0, 5, 6, "easy", 90)
    # yaw wraps: -90 -> 91 is 181 apart, i.e. 179 the short way
    assert yaw_diff(-90, 91) == 179
    assert satisfies(0, -90, 0, 91, "hard", 90)
    assert not satisfies(0, -90, 0, 91, "medium", 90)
    assert satisfies(0, 170, 0, -171, "easy", 90)  # 341 apart -> 19
    # medium: f/2 < L1 <= f
    assert not satisfies(0, 0, 0, 45, "medium", 90)
    assert satisfies(0, 0, 0, 46, "medium", 90)
    assert satisfies(20, 0, -20, 50, "medium", 90)  # L1 = 90
    assert not satisfies(20, 0, -20, 51, "medium", 90)  # L1 = 91
    # hard OR vs AND
    assert satisfies(60, 0, -35, 10, "hard", 90, hard_rule="or")  # dpitch 95 > 90
    assert not satisfies(60, 0, -35, 10, "hard", 90, hard_rule="and")
    assert satisfies(60, 0, -35, 100, "hard", 90, hard_rule="and")  # 95 and 100
    assert not satisfies(45, 0, -45, 180, "hard", 90, hard_rule="and")  # dpitch 90 is not > 90
    assert satisfies(45, 0, -45, 180, "hard", 90, hard_rule="or")
    # L1 < T
    assert not satisfies(0, 0, 0, 60, "medium", 90, max_steps=50)


def test_difficulty_fov60_and_mask_matches_rule() -> None:
    assert satisfies(0, 0, 30, 30, "easy", 60) and not satisfies(0, 0, 30, 31, "easy", 60)  # bound 42.43
    rng = np.random.default_rng(0)
    dp = rng.integers(0, 121, 20000)
    dy = rng.integers(0, 181, 20000)
    for f in (90, 60, 67.5):
        for d in DIFFICULTIES:
            for rule in ("or", "and"):
                np.testing.assert_array_equal(difficulty_mask(dp, dy, d, f, 5000, rule), _rule(dp, dy, d, f, 5000, rule))


def test_bad_settings() -> None:
    with pytest.raises(ValueError, match=r"unknown difficulty 'extreme'; valid: easy, medium, hard"):
        satisfies(0, 0, 0, 20, "extreme", 90)
    for f in (0, 180, -5, 200):
        with pytest.raises(ValueError, match=r"fov must be in \(0, 180\)"):
            check_fov(f)
    with pytest.raises(ValueError, match=r"pitch_bound must be in \[0, 90\]"):
        check_pitch_bound(91)
    with pytest.raises(ValueError, match="hard_rule"):
        difficulty_mask(np.array([0]), np.array([100]), "hard", 90, hard_rule="xor")
    with pytest.raises(ValueError, match="fov"):
        EpisodeSampler([ImageEntry("/x.jpg", "a")], fov=180)
    with pytest.raises(ValueError, match="pitch_bound"):
        EpisodeSampler([ImageEntry("/x.jpg", "a")], fov=90, pitch_bound=95)
    with pytest.raises(ValueError, match="at least one image"):
        EpisodeSampler([], fov=90)


# ---------------------------------------------------------------------------------------------------
# sampling
# ---------------------------------------------------------------------------------------------------
def test_pitch_prior() -> None:
    values, probs = pitch_distribution(60)
    assert values[0] == -60 and values[-1] == 60 and len(values) == 121
    assert probs.sum() == pytest.approx(1.0) and np.allclose(probs, probs[::-1])
    assert probs.argmax() == 60
    assert probs[60 + 18] / probs[60] == pytest.approx(math.exp(-0.5))  # 18 deg = one std (0.3 * 60)
    rng = np.random.default_rng(0)
    n = 200_000
    x = sample_pitch(rng, n, 60)
    assert x.min() >= -60 and x.max() <= 60
    # chi-square on 10-degree bins (11 degrees of freedom -> 99.9% quantile ~ 31)
    edges = np.arange(-60, 71, 10)
    obs = np.histogram(x, bins=edges)[0]
    exp = np.array([probs[(values >= lo) & (values < hi)].sum() for lo, hi in zip(edges[:-1], edges[1:])]) * n
    chi2 = ((obs - exp) ** 2 / exp).sum()
    assert chi2 < 31.3, chi2
    assert np.mean(np.abs(x) <= 18) > 0.6 and np.mean(np.abs(x) > 40) < 0.05


@pytest.mark.parametrize("fov", [90, 60])
def test_sampled_rotations_satisfy_rules(fov: float) -> None:
    rng = np.random.default_rng(1)
    for d in DIFFICULTIES:
        for rule in ("or", "and"):
            n = 300 if (d, rule) == ("hard", "and") else 3000  # AND accepts ~1e-4 of candidates at fov 90
            r = sample_rotations(d, n, rng, fov, 60, 5000, rule)
            assert r.shape == (n, 4) and r.dtype == np.int64
            assert np.all(np.abs(r[:, [0, 2]]) <= 60)
            assert np.all((r[:, [1, 3]] > -180) & (r[:, [1, 3]] <= 180))
            dp, dy = np.abs(r[:, 0] - r[:, 2]), yaw_diff(r[:, 1], r[:, 3])
            l1 = dp + dy
            assert np.all((l1 > 10) & (l1 < 5000))
            assert np.all(_rule(dp, dy, d, fov, 5000, rule)), (d, rule)
    # pitch keeps more mass near 0 among sampled episodes too
    r = sample_rotations("hard", 20000, rng, 90)
    p = np.concatenate([r[:, 0], r[:, 2]])
    assert np.mean(np.abs(p) <= 10) > 2.5 * np.mean((np.abs(p) > 40) & (np.abs(p) <= 50))


def test_sampling_impossible_is_an_error() -> None:
    rng = np.random.default_rng(0)
    with pytest.raises(SamplingError, match=r"'hard'.*fov=90.*pitch_bound=5"):
        sample_rotations("hard", 1, rng, 90, pitch_bound=5, hard_rule="and", max_tries=20000)
    with pytest.raises(SamplingError, match=r"'medium'.*max_steps=30"):
        sample_rotations("medium", 1, rng, 90, max_steps=30, max_tries=20000)
    s = EpisodeSampler([ImageEntry("/x.jpg", "a")], fov=90, pitch_bound=5, hard_rule="and", max_tries=20000)
    with pytest.raises(SamplingError, match="hard"):
        s.sample("hard")
    assert s.sample("easy").difficulty == "easy"  # other difficulties still work
    # OR with a small pitch bound is possible through the yaw
    assert sample_rotations("hard", 10, rng, 90, pitch_bound=5).shape == (10, 4)


def test_episode_sampler() -> None:
    images = [ImageEntry(f"/data/img{i}.jpg", f"lab{i % 3}") for i in range(7)]
    a = EpisodeSampler(images, fov=90, seed=3)
    b = EpisodeSampler(images, fov=90, seed=3)
    ea = [a.sample(d) for d in DIFFICULTIES * 50]
    eb = [b.sample(d) for d in DIFFICULTIES * 50]
    assert ea == eb and [e.seed for e in ea] == [e.seed for e in eb]
    assert len({e.episode_id for e in ea}) == len(ea)
    assert len({e.seed for e in ea}) == len(ea)
    assert {e.image for e in ea} == {im.path for im in images}
    for e in ea:
        assert e.label == f"lab{int(e.image[-5]) % 3}"
        assert satisfies(e.init_pitch, e.init_yaw, e.target_pitch, e.target_yaw, e.difficulty, 90)
    c = EpisodeSampler(images, fov=90, seed=4)
    assert [c.sample("easy") for _ in range(20)] != [EpisodeSampler(images, 90, 3).sample("easy") for _ in range(20)]
    assert {a.sample_level(1).difficulty for _ in range(50)} == {"easy"}
    two = [a.sample_level(2).difficulty for _ in range(400)]
    assert set(two) == {"easy", "medium"} and 120 < two.count("easy") < 280
    three = [a.sample_level(3).difficulty for _ in range(900)]
    assert all(200 < three.count(d) < 400 for d in DIFFICULTIES)
    for bad in (0, 4, 1.5):
        with pytest.raises(ValueError, match="level"):
            a.sample_level(bad)
    with pytest.raises(ValueError, match="valid: easy, medium, hard"):
        a.sample("nightmare")
    plain = EpisodeSampler(["/a.jpg"], fov=60, seed=0, hard_rule="and").sample("hard")
    assert plain.image == "/a.jpg" and abs(plain.init_pitch - plain.target_pitch) > 60


def test_sampler_is_fast() -> None:
    import time

    s = EpisodeSampler([ImageEntry("/x.jpg", "a")], fov=90, seed=0)
    t0 = time.perf_counter()
    for _ in range(3000):
        s.sample_level(3)
    assert time.perf_counter() - t0 < 3.0  # ~0.1 s on one core


def test_sampler_level_modes() -> None:
    images = [ImageEntry(f"/data/img{i}.jpg", "a") for i in range(4)]
    s = EpisodeSampler(images, fov=90, seed=7)
    for k, d in enumerate(DIFFICULTIES, start=1):
        assert {s.sample_level(k, mode="bounded").difficulty for _ in range(60)} == {d}
    two = [s.sample_level(2, mode="unbounded").difficulty for _ in range(400)]
    assert set(two) == {"easy", "medium"} and 120 < two.count("easy") < 280  # 200 expected, ~7 sigma
    # bounded level k is exactly the stream of sample(k-th difficulty): no extra random draw
    a, b = EpisodeSampler(images, 90, seed=8), EpisodeSampler(images, 90, seed=8)
    assert [a.sample_level(2, "bounded") for _ in range(30)] == [b.sample("medium") for _ in range(30)]
    with pytest.raises(ValueError, match="curriculum mode 'sideways'"):
        s.sample_level(1, mode="sideways")


def _roundtrip(state: dict) -> dict:
    """``state`` through torch.save / torch.load(weights_only=True), as in a checkpoint."""
    import io

    import torch

    buf = io.BytesIO()
    torch.save(state, buf)
    buf.seek(0)
    return torch.load(buf, weights_only=True)


@pytest.mark.parametrize("mode", ["unbounded", "bounded"])
def test_sampler_state_resumes_exactly(mode: str) -> None:
    images = [ImageEntry(f"/data/img{i}.jpg", f"l{i % 2}") for i in range(5)]
    # buffer=8: the N and M draws cross several refills of the rotation pools
    a = EpisodeSampler(images, fov=60, seed=11, buffer=8)
    for i in range(37):  # N episodes
        a.sample_level(1 + i % 3, mode)
    state = _roundtrip(a.state_dict())
    json.dumps(state)  # plain values only
    after = [a.sample_level(1 + i % 3, mode) for i in range(50)]  # M episodes
    b = EpisodeSampler(images, fov=60, seed=11, buffer=8)
    b.load_state_dict(state)
    assert [b.sample_level(1 + i % 3, mode) for i in range(50)] == after
    fresh = EpisodeSampler(images, fov=60, seed=11, buffer=8)
    assert [fresh.sample_level(1 + i % 3, mode) for i in range(50)] != after  # the state did matter
    for other in (EpisodeSampler(images, fov=90, seed=11, buffer=8), EpisodeSampler(images, fov=60, seed=12)):
        with pytest.raises(ValueError, match=r"(fov|seed)=.*cannot continue"):
            other.load_state_dict(state)
    with pytest.raises(ValueError, match="not an EpisodeSampler state"):
        b.load_state_dict({"level": 1})


@pytest.mark.parametrize("mode", ["unbounded", "bounded"])
def test_sampled_source_level_mode_and_resume(mode: str) -> None:
    from findview.task.sources import SampledEpisodeSource

    images = [ImageEntry(f"/data/img{i}.jpg", "a") for i in range(3)]
    src = SampledEpisodeSource(EpisodeSampler(images, 90, seed=2, buffer=8), level=2, lookahead=4, mode=mode)
    assert len(src.peek(4)) == 4
    got = {src.next().difficulty for _ in range(200)}
    assert got == ({"medium"} if mode == "bounded" else {"easy", "medium"})
    src.peek(4)  # queued level-2 episodes are dropped when the level changes
    src.level = 3
    got = [src.next().difficulty for _ in range(300)]
    if mode == "bounded":
        assert set(got) == {"hard"}
    else:
        assert set(got) == set(DIFFICULTIES) and all(60 < got.count(d) < 140 for d in DIFFICULTIES)
    src.peek(3)
    state = _roundtrip(src.state_dict())
    after = [src.next() for _ in range(40)]
    again = SampledEpisodeSource(EpisodeSampler(images, 90, seed=2, buffer=8), level=1, lookahead=4, mode=mode)
    again.load_state_dict(state)
    assert again.level == 3 and [again.next() for _ in range(40)] == after
    other = "bounded" if mode == "unbounded" else "unbounded"
    with pytest.raises(ValueError, match="curriculum mode"):
        SampledEpisodeSource(EpisodeSampler(images, 90, seed=2), mode=other).load_state_dict(state)
    with pytest.raises(ValueError, match="level must be an integer in"):
        src.level = 4
    with pytest.raises(ValueError, match="unknown curriculum mode"):
        SampledEpisodeSource(EpisodeSampler(images, 90), mode="easy-first")


# ---------------------------------------------------------------------------------------------------
# static episode files
# ---------------------------------------------------------------------------------------------------
def test_static_episodes_file(tmp_path: Path) -> None:
    root = tmp_path / "root"
    images = [ImageEntry(str(root / "a" / f"p{i}.jpg"), "a") for i in range(3)]
    eps = make_static_episodes(images, "test", 90, episodes_per_image=2, seed=5)
    assert len(eps) == 3 * 3 * 2
    assert len({e.episode_id for e in eps}) == len(eps)
    for d in DIFFICULTIES:
        sub = [e for e in eps if e.difficulty == d]
        assert len(sub) == 6 and all(sum(e.image == im.path for e in sub) == 2 for im in images)
        assert all(satisfies(e.init_pitch, e.init_yaw, e.target_pitch, e.target_yaw, d, 90) for e in sub)
    assert eps == make_static_episodes(images, "test", 90, 2, seed=5)
    assert eps != make_static_episodes(images, "test", 90, 2, seed=6)
    assert [e.init_yaw for e in eps] != [e.init_yaw for e in make_static_episodes(images, "val", 90, 2, seed=5)]
    path = episode_file(tmp_path / "out", "test", 90)
    assert path == tmp_path / "out" / "episodes" / "test_fov90.json"
    assert episode_file(tmp_path, "val", 67.5).name == "val_fov67.5.json"
    kw = dict(dataset="toy", root=root, split="test", fov=90, hard_rule="or", seed=5)
    write_episode_file(path, eps, **kw)
    first = path.read_bytes()
    write_episode_file(path, make_static_episodes(images, "test", 90, 2, seed=5), **kw)
    assert path.read_bytes() == first  # byte-identical
    doc = json.loads(first)
    assert doc["dataset"] == "toy" and doc["split"] == "test" and doc["fov"] == 90 and doc["hard_rule"] == "or"
    assert doc["root"] == str(root) and doc["episodes"][0]["image"] == "a/p0.jpg"
    loaded = load_episodes(path)
    assert loaded == eps and all(os.path.isabs(e.image) for e in loaded)
    moved = load_episodes(path, root=tmp_path / "moved")
    assert moved[0].image == str(tmp_path / "moved" / "a" / "p0.jpg")
    with pytest.raises(FileNotFoundError, match=r"episode file not found: .*test_fov60.json.*make_dataset"):
        load_episodes(episode_file(tmp_path / "out", "test", 60))
    with pytest.raises(DatasetError, match="episodes_per_image"):
        make_static_episodes(images, "test", 90, episodes_per_image=-1)


# ---------------------------------------------------------------------------------------------------
# ensure_dataset / prepare_dataset and the configs
# ---------------------------------------------------------------------------------------------------
def _toy_folder(root: Path) -> None:
    for lab in ("x", "y"):
        for i in range(5):
            _write(root / lab / f"{lab}{i}.png", 32, 64, seed=i)


def test_ensure_dataset_builds_then_reuses(tmp_path: Path) -> None:
    root, out = tmp_path / "imgs", tmp_path / "out"
    _toy_folder(root)
    cfg = {"name": "toy", "kind": "folder", "root": str(root), "out_dir": str(out), "episode_fovs": [90, 60]}
    assert ensure_dataset(cfg, [90], progress=False) == out
    splits, ep90 = out / "splits.json", episode_file(out, "test", 90)
    assert splits.is_file() and ep90.is_file() and episode_file(out, "val", 90).is_file()
    assert not episode_file(out, "test", 60).exists()  # only the FoVs asked for
    stamp = (splits.stat().st_mtime_ns, ep90.stat().st_mtime_ns, ep90.read_bytes())
    ensure_dataset(cfg, [90], progress=False)
    assert (splits.stat().st_mtime_ns, ep90.stat().st_mtime_ns, ep90.read_bytes()) == stamp  # reused
    s = prepare_dataset({**cfg, "episodes_per_image": 2}, [90], progress=False)
    assert s.splits_reused and not s.episodes_reused[("test", 90.0)]
    assert s.episode_counts[("test", 90.0)] == {d: 2 * s.images["test"] for d in DIFFICULTIES}
    s = prepare_dataset({**cfg, "split": [0.5, 0.25, 0.25]}, [90], progress=False)
    assert not s.splits_reused and s.images == {"train": 5, "val": 3, "test": 2}  # exact 5 / 2.5 / 2.5
    assert "test" in s.format() and str(ep90) in s.format()


def _file_state(*paths: Path) -> list[tuple[int, bytes]]:
    return [(p.stat().st_mtime_ns, p.read_bytes()) for p in paths]


def test_static_episodes_depend_on_the_dataset_only(tmp_path: Path) -> None:
    root, out = tmp_path / "imgs", tmp_path / "out"
    _toy_folder(root)
    cfg = {"name": "toy", "kind": "folder", "root": str(root), "out_dir": str(out), "split": [0.2, 0.4, 0.4]}
    ensure_dataset(cfg, [90], pitch_bound=60, max_steps=5000, progress=False)
    files = [out / "splits.json", episode_file(out, "val", 90), episode_file(out, "test", 90)]
    before = _file_state(*files)
    # other task.max_steps (the old code resampled with L1 < 40 here): nothing is rewritten
    for max_steps in (40, 200, 100000):
        assert ensure_dataset(cfg, [90], pitch_bound=60, max_steps=max_steps, progress=False) == out
    assert _file_state(*files) == before
    # T of the static episodes is a dataset setting, with the benchmark's default 5000
    eps = load_episodes(files[2])
    assert max(abs(e.init_pitch - e.target_pitch) + yaw_diff(e.init_yaw, e.target_yaw) for e in eps) >= 40
    # another pitch clamp than the episodes were made for: one line naming the file, both bounds, the fix
    with pytest.raises(DatasetError) as err:
        ensure_dataset(cfg, [90], pitch_bound=45, progress=False)
    msg = str(err.value)
    assert "\n" not in msg and str(episode_file(out, "val", 90)) in msg
    assert "dataset.episode_pitch_bound=60" in msg and "task.pitch_bound=45" in msg
    assert "python tools/make_dataset.py" in msg and "dataset.episode_pitch_bound=45" in msg
    assert _file_state(*files) == before
    # no episode files needed (splits_to_make=[]): any clamp is fine
    ensure_dataset({**cfg, "splits_to_make": []}, [90], pitch_bound=0, progress=False)
    # changed dataset episode settings: ensure_dataset refuses to overwrite, naming the key
    with pytest.raises(DatasetError, match=r"val_fov90.json was made for other settings \(dataset.episode_seed 0 "
                                           r"in the file, 3 now\).*make_dataset.py"):
        ensure_dataset({**cfg, "episode_seed": 3}, [90], progress=False)
    with pytest.raises(DatasetError, match=r"splits.json was made for other dataset settings \(split_seed 0 "
                                           r"in the file, 1 now\)"):
        ensure_dataset({**cfg, "split_seed": 1}, [90], progress=False)
    assert _file_state(*files) == before
    # a new FoV is only added
    ensure_dataset(cfg, [60], progress=False)
    assert episode_file(out, "test", 60).is_file() and _file_state(*files) == before
    # make_dataset (prepare_dataset) rebuilds from the dataset keys
    s = prepare_dataset({**cfg, "episode_pitch_bound": 20, "episode_max_steps": 100}, [90], progress=False)
    assert not s.episodes_reused[("test", 90.0)]
    eps = load_episodes(files[2])
    assert all(abs(p) <= 20 for e in eps for p in (e.init_pitch, e.target_pitch))
    assert all(10 < abs(e.init_pitch - e.target_pitch) + yaw_diff(e.init_yaw, e.target_yaw) < 100 for e in eps)
    assert json.loads(files[2].read_text())["pitch_bound"] == 20
    ensure_dataset({**cfg, "episode_pitch_bound": 20, "episode_max_steps": 100}, [90], pitch_bound=20,
                   progress=False)
    for key, value in (("episode_pitch_bound", 91), ("episode_max_steps", 11)):
        with pytest.raises(DatasetError, match=f"dataset.{key}"):
            ensure_dataset({**cfg, key: value}, [90], progress=False)
    from omegaconf.errors import ValidationError

    with pytest.raises(ValidationError, match="episode_max_steps"):  # a type the schema refuses
        ensure_dataset({**cfg, "episode_max_steps": "many"}, [90], progress=False)


def test_config_files(tmp_path: Path) -> None:
    from findview_baselines.cli import compose_config, validate_config

    names = {p.stem for p in (REPO / "configs" / "dataset").glob("*.yaml")}
    assert {"synthetic", "sun360_indoor", "sun360_outdoor", "indoor360", "folder"} <= names
    for name in names:
        cfg = validate_config(compose_config("make_dataset", [f"dataset={name}"])).dataset
        assert cfg.out_dir == f"data/{cfg.name}" and cfg.hard_rule == "or" and cfg.episodes_per_image == 1
        assert cfg.episode_pitch_bound == 60 and cfg.episode_max_steps == 5000  # the benchmark's T and bound
    # the folder config, used as a node: root / out_dir overrides and ensure_dataset
    root, out = tmp_path / "imgs", tmp_path / "out"
    _toy_folder(root)
    cfg = compose_config("make_dataset", ["dataset=folder", f"dataset.root={root}", f"dataset.out_dir={out}",
                                          "dataset.split=[0,0,1]"]).dataset
    assert ensure_dataset(cfg, [90], progress=False) == out
    assert len(load_split(out, "test")) == 10 and load_split(out, "train") == []
    assert len(load_episodes(episode_file(out, "test", 90))) == 30
    cfg = validate_config(compose_config("make_dataset", ["dataset=sun360_indoor", "dataset.root=null"])).dataset
    with pytest.raises(DatasetError, match=r"dataset.root is not set.*dataset.root="):
        ensure_dataset(cfg, [90], progress=False)


def test_prepare_sun360_mini(sun360_mini: Path, tmp_path: Path) -> None:
    cfg = {"name": "mini", "kind": "sun360", "root": str(sun360_mini), "subset": "indoor", "out_dir": str(tmp_path)}
    s = prepare_dataset(cfg, [90], progress=False)
    assert sum(s.images.values()) == 16
    assert set().union(*(set(v) for v in s.labels.values())) == {"bedroom", "greenhouse", "museum", "office"}
    eps = load_episodes(episode_file(tmp_path, "val", 90))
    assert len(eps) == 3 * s.images["val"] and all(Path(e.image).is_file() for e in eps)


def test_prepare_sun360_indoor_plus_outdoor_keeps_each_folder_split(sun360_mini: Path, tmp_path: Path) -> None:
    """dataset.subset=indoor+outdoor: the union of the indoor and the outdoor data sets' own splits (split folder
    by folder), so no val / test image of either trains; a joint split of the same 32 images would differ."""
    def splits(subset: str) -> dict[str, set[str]]:
        out = tmp_path / subset
        cfg = {"name": subset, "kind": "sun360", "root": str(sun360_mini), "subset": subset, "out_dir": str(out),
               "validate": False}
        prepare_dataset(cfg, [90], progress=False)
        return {split: {Path(e.path).name for e in load_split(out, split)} for split in ("train", "val", "test")}

    indoor, outdoor, both = splits("indoor"), splits("outdoor"), splits("indoor+outdoor")
    for split in ("train", "val", "test"):
        assert both[split] == indoor[split] | outdoor[split]
    assert sum(len(v) for v in both.values()) == 32
    assert not (both["train"] & (indoor["test"] | outdoor["test"] | indoor["val"] | outdoor["val"]))
