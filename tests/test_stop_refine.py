"""The stop refinement (findview_baselines/agents/stop_refine.py): phase correlation measures one- and
two-degree rotations between rendered views with the right sign, trusts no unrelated pair, and a slot that
stops near the target ends exactly on it."""

from __future__ import annotations

import cv2
import pytest
import torch

from findview.dataset import generate_panorama
from findview.episode import Episode
from findview.sim import PanoramaBank, Simulator
from findview.task import Action, FindViewEnv, StaticEpisodeSource
from findview_baselines.agents.stop_refine import StopRefiner, residual_rotation

SIZE, FOV = 64, 90.0


@pytest.fixture(scope="module")
def panos(tmp_path_factory) -> list[str]:
    folder = tmp_path_factory.mktemp("refine_panos")
    paths = []
    for seed, kind in ((3, "room"), (4, "village")):
        path = folder / f"{kind}.png"
        cv2.imwrite(str(path), cv2.cvtColor(generate_panorama(seed, kind, 1024), cv2.COLOR_RGB2BGR))
        paths.append(str(path))
    return paths


def render(pano: str, poses: list[tuple[int, int]]) -> torch.Tensor:
    bank = PanoramaBank("cpu", 512, min_slots=1, prefetch_workers=0)
    sim = Simulator(bank, fov=FOV, height=SIZE, width=SIZE)
    slot = bank.acquire(pano)
    n = len(poses)
    pitch = torch.tensor([p for p, _ in poses], dtype=torch.float32)
    yaw = torch.tensor([y for _, y in poses], dtype=torch.float32)
    return sim.render(torch.full((n,), slot, dtype=torch.long), pitch, yaw)


@pytest.mark.parametrize("pano_index", [0, 1])
def test_measures_small_rotations_with_their_sign(panos, pano_index: int) -> None:
    """Target at (pitch 5, yaw 40); views 1 or 2 degrees off on one axis: the measured rotation from the view
    to the target has the sign of the move that reaches it, the offset's size within 0.6 degree (sub-pixel
    peaks read high: one degree is 0.56 pixel here), and about 0 (within 0.25) on the other axis."""
    offsets = [(0, -1), (0, 1), (0, -2), (0, 2), (-1, 0), (1, 0), (-2, 0), (2, 0), (0, 0)]
    target_pose = (5, 40)
    views = render(panos[pano_index], [(target_pose[0] - dp, target_pose[1] - dy) for dp, dy in offsets])
    target = render(panos[pano_index], [target_pose] * len(offsets))
    dyaw, dpitch, peak = residual_rotation(views, target, FOV)
    for k, (dp, dy) in enumerate(offsets):
        measured = (dpitch[k].item(), dyaw[k].item())
        for true, got in zip((dp, dy), measured):
            assert got == pytest.approx(true, abs=0.6 if true else 0.25), (dp, dy, measured)
    assert peak.min().item() > 0.2


def test_unrelated_views_are_not_trusted(panos) -> None:
    views = render(panos[0], [(0, 0), (10, 120), (-20, -90)])
    targets = render(panos[1], [(0, 0), (10, 120), (-20, -90)])
    far = render(panos[0], [(0, 60), (10, -60), (-20, 90)])
    assert residual_rotation(views, targets, FOV)[2].max().item() < 0.15  # min_peak: shifts of 1-2 degrees read 0.27-0.79
    assert residual_rotation(views, far, FOV)[2].max().item() < 0.15  # min_peak: shifts of 1-2 degrees read 0.27-0.79
    refiner = StopRefiner(3, FOV)
    actions = refiner.decide(torch.arange(3), views, targets)
    assert actions.tolist() == [int(Action.STOP)] * 3 and refiner.moves.tolist() == [0, 0, 0]


def test_stops_near_the_target_end_on_it(panos) -> None:
    """Episodes whose agent wants to stop 1-2 degrees off (both axes too): the refinement walks to the exact
    target within its move budget and then stops."""
    offsets = [(0, 1), (0, -2), (1, 0), (-2, 0), (1, 1), (-1, 2), (2, -1), (0, 0)]
    episodes = [Episode(f"e{k}", panos[k % 2], dp, 30 + dy, 0, 30, difficulty="easy") for k, (dp, dy) in enumerate(offsets)]
    bank = PanoramaBank("cpu", 512, min_slots=len(episodes), prefetch_workers=0)
    env = FindViewEnv(Simulator(bank, fov=FOV, height=SIZE, width=SIZE), StaticEpisodeSource(episodes), len(episodes))
    obs = env.reset()
    refiner = StopRefiner(len(episodes), FOV, max_moves=4)
    done = torch.zeros(len(episodes), dtype=torch.bool)
    final: list[tuple[int, int] | None] = [None] * len(episodes)
    for _ in range(6):
        ids = torch.nonzero(~done).flatten()
        actions = torch.full((len(episodes),), int(Action.STOP))
        actions[ids] = refiner.decide(ids, obs["view"][ids], obs["target"][ids])
        for k in ids.tolist():
            if actions[k] == int(Action.STOP):
                final[k] = (int(env.pitch[k]), int(env.yaw[k]))
        done |= actions == int(Action.STOP)
        if bool(done.all()):
            break
        obs = env.step(actions)[0]  # a stopped slot's source is exhausted: it idles
    assert bool(done.all())
    assert final == [(0, 30)] * len(episodes)
    assert refiner.moves.tolist() == [abs(dp) + abs(dy) for dp, dy in offsets]


def test_block_spectra_measure_as_the_block_averaged_images(panos) -> None:
    """``phase_spectrum(images, 2)`` (grey and 2x2 block mean in one pass, as ``stop_by_phase`` measures 256-pixel
    views at 128) gives the rotation that :func:`residual_rotation` measures on the 2x2 block means of the images
    themselves (float, not rounded), and refuses a size that is not a multiple of the block."""
    from findview_baselines.agents.stop_refine import phase_spectrum, rotation_between

    bank = PanoramaBank("cpu", 512, min_slots=1, prefetch_workers=0)
    sim = Simulator(bank, fov=FOV, height=128, width=128)
    slot = bank.acquire(panos[1])
    poses = [(0, 37), (3, 40), (-4, 45), (8, 30)]
    n = len(poses)
    views = sim.render(torch.full((n,), slot), torch.tensor([p for p, _ in poses]), torch.tensor([y for _, y in poses]))
    target = sim.render(torch.full((n,), slot), torch.full((n,), 2), torch.full((n,), 40))
    got = rotation_between(phase_spectrum(views, 2), phase_spectrum(target, 2), FOV, 64)
    pool = lambda x: torch.nn.functional.avg_pool2d(x.float(), 2)  # noqa: E731
    want = residual_rotation(pool(views), pool(target), FOV)
    for g, w in zip(got, want):
        assert torch.allclose(g, w, atol=1e-3), (g, w)
    assert got[2].min().item() > 0.2  # all within a few degrees: clear peaks
    with pytest.raises(ValueError, match="blocks of 3"):
        phase_spectrum(views, 3)
