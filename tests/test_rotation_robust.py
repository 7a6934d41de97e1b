"""The ``rotation`` agent against corrupted targets and look-alike views (issue 19, item 3).

- a flat-coloured cube-map scene (six uniform faces, one big letter each): the view of the mirror face
  (another colour, another letter, the same cube edges) must never pass the check before a stop, and an
  episode that starts facing it must end on the target;
- contrast and fog keep the structure and change intensities: the content score and the keypoint
  detection must not care;
- a verified stop that is not byte-identical to the target always runs the one-degree refinement.

The scene is painted here with numpy / OpenCV; the expectations (which face a pose looks at, what a
contrast change or a fog field does) follow from the geometry and the formulas, not from a run.
"""

from __future__ import annotations

import math

import cv2
import numpy as np
import pytest
import torch

from findview.episode import Episode
from findview.geometry import l1_distance, wrap_yaw
from findview.sim import equi2pers
from findview_baselines.agents import make_agent
from findview_baselines.agents.base import DOWN, LEFT, RIGHT, STOP, UP, gray_of
from findview_baselines.agents.feature_base import detect
from findview_baselines.agents.photometric import (
    detection_image,
    hue_residual,
    opponent_mean,
    opponent_template,
    photometric_score,
    structure_score,
    structure_template,
)

FOV, H, W = 90.0, 128, 128
# front (+z, yaw 0) yellow "A", back (yaw 180) green "H": 40-90 grey levels apart per channel, their
# chromaticities 0.28 apart at most; right red "R", left blue "M", top purple "W", bottom cyan "X"
FACES = {
    "front": ((220, 200, 40), "A"),
    "back": ((60, 170, 70), "H"),
    "right": ((200, 60, 60), "R"),
    "left": ((60, 90, 200), "M"),
    "top": ((160, 80, 170), "W"),
    "bottom": ((80, 170, 180), "X"),
}


def cube_panorama(height: int = 256, face_px: int = 256) -> torch.Tensor:
    """``(1, 3, height, 2 height)`` uint8 equirectangular panorama of the inside of a cube whose faces are
    uniform colours with one dark letter in the middle (docs/TASK.md's pixel -> direction mapping)."""
    tiles = {}
    for name, (colour, letter) in FACES.items():
        tile = np.empty((face_px, face_px, 3), np.uint8)
        tile[:] = colour
        s = face_px / 256.0
        cv2.putText(tile, letter, (int(45 * s), int(205 * s)), cv2.FONT_HERSHEY_SIMPLEX, 6.5 * s, (20, 20, 20),
                    int(22 * s), cv2.LINE_AA)
        tiles[name] = tile
    we = 2 * height
    v, u = np.mgrid[0:height, 0:we].astype(np.float64)
    lon = ((u + 0.5) / we - 0.5) * 2.0 * math.pi
    lat = (0.5 - (v + 0.5) / height) * math.pi
    x, y, z = np.cos(lat) * np.sin(lon), np.sin(lat), np.cos(lat) * np.cos(lon)
    out = np.zeros((height, we, 3), np.uint8)
    ax = np.argmax(np.abs(np.stack([x, y, z])), axis=0)
    # (face, mask, face coordinates (right, up) in [-1, 1] as seen from the centre of the cube)
    with np.errstate(divide="ignore", invalid="ignore"):
        parts = [
            ("front", (ax == 2) & (z > 0), x / z, y / z),
            ("back", (ax == 2) & (z < 0), x / z, -y / z),
            ("right", (ax == 0) & (x > 0), -z / x, y / x),
            ("left", (ax == 0) & (x < 0), -z / x, -y / x),
            ("top", (ax == 1) & (y > 0), x / y, -z / y),
            ("bottom", (ax == 1) & (y < 0), -x / y, -z / y),
        ]
        for name, m, a, b in parts:
            col = np.clip(((a[m] + 1.0) / 2.0 * face_px).astype(int), 0, face_px - 1)
            row = np.clip(((1.0 - b[m]) / 2.0 * face_px).astype(int), 0, face_px - 1)
            out[m] = tiles[name][row, col]
    return torch.from_numpy(out).permute(2, 0, 1)[None].contiguous()


@pytest.fixture(scope="module")
def cube() -> torch.Tensor:
    return cube_panorama()


def render(equi: torch.Tensor, pitch: int, yaw: int) -> torch.Tensor:
    """The ``(1, 3, H, W)`` uint8 view at ``(pitch, yaw)`` degrees."""
    p = torch.tensor([float(pitch)], dtype=torch.float64)
    y = torch.tensor([float(yaw)], dtype=torch.float64)
    return equi2pers(equi, p, y, FOV, H, W, mode="bilinear")


def contrast(img: torch.Tensor, c: float = 0.2) -> torch.Tensor:
    """``(x - m) c + m`` per channel (the contrast corruption's formula; severity 3 is ``c = 0.2``)."""
    x = img.double()
    m = x.mean(dim=(2, 3), keepdim=True)
    return ((x - m) * c + m).clamp(0, 255).to(torch.uint8)


def fog(img: torch.Tensor, strength: float = 2.5) -> torch.Tensor:
    """A smooth grey field (two slanted sine waves, one period across the image) added with ``strength``
    (levels / 255), then everything scaled back into range, like the fog corruption at severity 3."""
    _, _, h, w = img.shape
    yy, xx = torch.meshgrid(torch.arange(h, dtype=torch.float64), torch.arange(w, dtype=torch.float64), indexing="ij")
    field = 0.5 + 0.25 * torch.sin(2 * math.pi * (xx + 0.6 * yy) / w) + 0.25 * torch.cos(2 * math.pi * yy / h)
    x = img.double() / 255.0
    peak = x.amax()
    return ((x + strength * field) * peak / (peak + strength) * 255.0).clamp(0, 255).to(torch.uint8)


def episode(init: tuple[int, int], target: tuple[int, int]) -> Episode:
    return Episode("c0", "cube.jpg", init[0], init[1], target[0], target[1], difficulty="hard", seed=3)


def play(equi: torch.Tensor, e: Episode, target: torch.Tensor, agent, max_steps: int) -> tuple[bool, int, int]:
    """One episode with the task's move rules (docs/TASK.md); returns (called stop, eps, steps)."""
    agent.reset([0], [e])
    pitch, yaw = e.init_pitch, e.init_yaw
    for step in range(1, max_steps + 1):
        view = render(equi, pitch, yaw)
        a = int(agent.act({"view": view, "target": target})[0])
        if a == STOP:
            return True, int(l1_distance(pitch, yaw, e.target_pitch, e.target_yaw)), step
        pitch = int(np.clip(pitch + (a == UP) - (a == DOWN), -60, 60))
        yaw = int(wrap_yaw(yaw + (a == RIGHT) - (a == LEFT)))
    return False, int(l1_distance(pitch, yaw, e.target_pitch, e.target_yaw)), max_steps


# ------------------------------------------------------------------------------------------------
# the check before a stop
# ------------------------------------------------------------------------------------------------
def test_mirror_faces_are_rejected(cube):
    """Every target on a grid of poses against the views that share its cube geometry (yaw + 180, +-90;
    the pitch mirrored): the same edges, other colours and letters. None may pass, while the target's
    own view, clean, under contrast 0.2 and under fog, passes."""
    agent = make_agent("rotation", None, 1, "cpu", 0)
    accepted = []
    for tp in (-30, -10, 0, 20, 40):
        for ty in range(-180, 180, 30):
            clean = render(cube, tp, ty)
            for name, tgt in (("clean", clean), ("contrast", contrast(clean)), ("fog", fog(clean))):
                s = agent.new_slot(None, np.random.default_rng(0))
                s.target = agent.prepare_target(s, tgt[0].numpy())
                own = clean[0].numpy()
                assert agent.verify(s, own, agent.estimate(s, own))[0], (name, tp, ty)
                if name != "clean":
                    continue
                for mp, my in ((tp, ty + 180), (tp, ty + 90), (tp, ty - 90), (-tp, ty + 180)):
                    v = render(cube, mp, int(wrap_yaw(my)))[0].numpy()
                    if agent.verify(s, v, agent.estimate(s, v))[0]:
                        accepted.append(((tp, ty), (mp, my)))
    assert not accepted


def test_hue_residual_tells_yellow_from_green():
    yellow, green = FACES["front"][0], FACES["back"][0]
    flat = lambda c: np.broadcast_to(np.array(c, np.uint8)[:, None, None], (3, 8, 8)).copy()  # noqa: E731
    t = opponent_mean(flat(yellow))
    assert hue_residual(t, opponent_mean(flat(green))) > 100.0  # another hue, whatever the gain
    for gain in (0.3, 1.0, 2.5):  # the same hue at any brightness / saturation scale
        assert hue_residual(t * gain, t) < 1e-6


def test_agent_facing_the_mirror_face_ends_on_the_target(cube):
    """Start looking at the green "H" (yaw 180), target on the yellow "A": stop exactly on the target."""
    e = episode((0, 178), (4, -6))
    target = render(cube, e.target_pitch, e.target_yaw)
    agent = make_agent("rotation", None, 1, "cpu", 0)
    stopped, eps, _ = play(cube, e, target, agent, 1500)
    assert stopped and eps == 0


# ------------------------------------------------------------------------------------------------
# contrast and fog: structure stays, intensities change
# ------------------------------------------------------------------------------------------------
def test_structure_and_keypoints_survive_contrast_and_fog(cube):
    clean = render(cube, 10, 35)
    ref = structure_template(clean[0].numpy())
    n_clean = len(detect("sift", detection_image(gray_of(clean[0].numpy()))))
    assert n_clean >= 20
    # contrast is a gain about the mean: the locally normalised images are the same
    assert structure_score(structure_template(contrast(clean)[0].numpy()), ref) > 0.8
    # a fog field as strong as the picture on flat faces: less, but still above the stop threshold
    # (the mirror view, with the same cube edges, is told apart by its colours: test_mirror_faces_are_rejected)
    assert structure_score(structure_template(fog(clean)[0].numpy()), ref) > 0.35
    for bad in (contrast(clean), fog(clean)):
        # the locally normalised image keeps most keypoints (SIFT's contrast threshold drops them on raw gray)
        assert len(detect("sift", detection_image(gray_of(bad[0].numpy())))) >= 0.5 * n_clean


@pytest.mark.parametrize("corrupt", [contrast, fog], ids=["contrast", "fog"])
def test_corrupted_target_refined_to_the_exact_pose(cube, corrupt):
    """A corrupted target is never byte-identical to a view: the stop comes after the one-degree
    refinement (it scored the stop pose and its neighbours) and is exact."""
    e = episode((-5, 20), (8, 47))
    target = corrupt(render(cube, e.target_pitch, e.target_yaw))
    agent = make_agent("rotation", None, 1, "cpu", 0)
    stopped, eps, _ = play(cube, e, target, agent, 600)
    assert stopped and eps == 0
    assert len(agent.slots[0].scores) >= 5  # the pose and its four one-degree neighbours at least


# ------------------------------------------------------------------------------------------------
# opponent colour: fog and contrast only scale the colour differences
# ------------------------------------------------------------------------------------------------
def test_opponent_layout_survives_fog_and_contrast_not_the_mirror_face(cube):
    """The colour differences (R - G, G - B) of a fogged or low-contrast target are those of its view up to
    a gain (the fog field is grey): the score stays near 1, while the mirror face (the same edges in other
    colours) stays far below the stop threshold."""
    agent = make_agent("rotation", None, 1, "cpu", 0)
    for tp, ty in ((0, 0), (10, 35), (-20, 150)):
        clean = render(cube, tp, ty)
        ref = opponent_template(clean[0].numpy())
        for bad in (contrast(clean), fog(clean), fog(contrast(clean, 0.5), 4.0)):
            assert photometric_score(opponent_template(bad[0].numpy()), ref) > 0.95
        mirror = render(cube, tp, int(wrap_yaw(ty + 180)))
        assert photometric_score(opponent_template(mirror[0].numpy()), ref) < agent.verify_opponent - 0.25


def test_search_goes_full_size_after_a_blind_row(cube):
    """Coarse (half-size) keypoints of a corrupted target can miss everything: after as many coarse looks
    as a search row holds without one valid estimate, the search estimates from full-size views."""
    e = episode((0, 0), (0, 179))
    target = render(cube, e.target_pitch, e.target_yaw)
    agent = make_agent("rotation", None, 1, "cpu", 0)
    calls = []
    real = agent.estimate

    def estimate(s, view, coarse=False):  # every look is blind: the agent keeps searching
        calls.append(coarse)
        est = real(s, view, coarse)
        est.valid = False
        return est

    agent.estimate = estimate
    agent.reset([0], [e])
    view = render(cube, 0, 0)  # what the views show does not matter here, only which looks are made
    for _ in range(400):
        agent.act({"view": view, "target": target})
    assert agent.slots[0].mode == "search" and agent.slots[0].full_search
    row_checks = math.ceil((360 - round(FOV / 3)) / round(FOV / 8))  # 330 moves, a look every 11
    # the first look of an episode is at full size; finding nothing, it looks again at half size
    assert calls[:2] == [False, True]
    assert calls[2 : row_checks + 2] == [True] * row_checks
    # then every look is at full size, each followed by a half-size retry (a blurred target's keypoints)
    rest = calls[row_checks + 2 :]
    assert len(rest) >= 4 and rest == [False, True] * (len(rest) // 2) + [False] * (len(rest) % 2)
