"""Pictures of episodes: view outlines on the panorama, the paper's Figure 2 layout, MP4 replays.

Where a view lies on the panorama is found by projecting its outline with the camera mapping of docs/TASK.md (section World and camera)
(the one :func:`findview.sim.equi2pers` renders with): an image point ``(x, y)`` (continuous pixel
coordinates, pixel ``(i, j)`` covers ``[i, i+1) x [j, j+1)``, so its centre is ``(i + 0.5, j + 0.5)``)
has the camera ray ``((x - W/2) / f', -(y - H/2) / f', 1)``, rotated by pitch about x then yaw about y,
then ``lon = atan2(d_x, d_z)``, ``lat = asin(d_y / |d|)``, ``u = (lon / 2pi + 0.5) We - 0.5``,
``v = (0.5 - lat / pi) He - 0.5``. The outline is the border of the image rectangle
``[0, W] x [0, H]``. Outlines that cross the panorama's seam (or circle a pole) are drawn segment by
segment, each segment unwrapped to its short way round and drawn at ``u``, ``u - We`` and ``u + We``
so the pieces on both sides of the seam appear.

Images are RGB ``uint8`` ``(H, W, 3)`` numpy arrays here; OpenCV writers get BGR.
"""

from __future__ import annotations

import math
import os
import tempfile
from collections.abc import Iterable, Sequence
from pathlib import Path

import cv2
import numpy as np
import torch

from findview.geometry import focal_length, wrap_yaw

__all__ = [
    "INIT_COLOR",
    "TARGET_COLOR",
    "VIEW_COLOR",
    "project_view_points",
    "view_outline",
    "draw_outline",
    "render_views",
    "downscale_panorama",
    "episode_figure",
    "replay_rotations",
    "episode_frame",
    "write_video",
]

INIT_COLOR = (255, 64, 64)  # RGB: initial view (red)
VIEW_COLOR = (64, 224, 64)  # RGB: current view in videos (green)
TARGET_COLOR = (255, 210, 0)  # RGB: target view (yellow)


# --------------------------------------------------------------------------------------------------
# geometry
# --------------------------------------------------------------------------------------------------
def project_view_points(
    xs: np.ndarray, ys: np.ndarray, pitch: float, yaw: float, fov: float, height: int, width: int, equi_height: int
) -> np.ndarray:
    """Panorama sample points ``(K, 2)`` (``u, v``, pixel centres at integers) of view image points.

    Args:
        xs, ys: ``(K,)`` continuous view coordinates (pixel ``(i, j)`` has its centre at
            ``(i + 0.5, j + 0.5)``).
        pitch, yaw: view rotation, degrees.
        fov: horizontal field of view, degrees.
        height, width: view size, pixels.
        equi_height: panorama height ``He`` (``We = 2 He``).

    Returns:
        ``u`` in ``[-0.5, We - 0.5)`` (not wrapped further) and ``v`` in ``[-0.5, He - 0.5]``.
    """
    f = float(focal_length(fov, width))
    x = (np.asarray(xs, np.float64) - width / 2) / f
    y = -(np.asarray(ys, np.float64) - height / 2) / f
    z = np.ones_like(x)
    p, w = math.radians(pitch), math.radians(yaw)
    y1 = y * math.cos(p) + z * math.sin(p)
    z1 = -y * math.sin(p) + z * math.cos(p)
    x2 = x * math.cos(w) + z1 * math.sin(w)
    z2 = -x * math.sin(w) + z1 * math.cos(w)
    norm = np.sqrt(x2 * x2 + y1 * y1 + z2 * z2)
    lon = np.arctan2(x2, z2)
    lat = np.arcsin(np.clip(y1 / norm, -1.0, 1.0))
    We, He = 2 * equi_height, equi_height
    u = (lon / (2 * math.pi) + 0.5) * We - 0.5
    v = (0.5 - lat / math.pi) * He - 0.5
    return np.stack([u, v], axis=1)


def view_outline(
    pitch: float, yaw: float, fov: float, height: int, width: int, equi_height: int, samples_per_side: int = 48
) -> np.ndarray:
    """The view's border projected on the panorama: ``(4 * samples_per_side, 2)`` points ``(u, v)``.

    The loop runs clockwise from the top-left corner along the image rectangle ``[0, W] x [0, H]``.
    """
    n = max(2, int(samples_per_side))
    t = np.linspace(0.0, 1.0, n, endpoint=False)
    xs = np.concatenate([t * width, np.full(n, float(width)), (1 - t) * width, np.zeros(n)])
    ys = np.concatenate([np.zeros(n), t * height, np.full(n, float(height)), (1 - t) * height])
    return project_view_points(xs, ys, pitch, yaw, fov, height, width, equi_height)


def draw_outline(
    image: np.ndarray,
    uv: np.ndarray,
    equi_height: int,
    color: Sequence[int],
    thickness: int = 2,
    closed: bool = True,
) -> np.ndarray:
    """Draw a projected outline (from :func:`view_outline`) on a (possibly resized) panorama, in place.

    Args:
        image: ``(h, 2h, C)`` uint8 panorama picture (any size; ``uv`` is scaled from ``equi_height``).
        uv: ``(K, 2)`` panorama points of the full-size panorama.
        equi_height: ``He`` the points refer to.
        color: line colour in ``image``'s channel order.
        thickness: line width, pixels.
        closed: join the last point to the first.

    Returns:
        ``image``.
    """
    h, w = image.shape[:2]
    We = 2 * equi_height
    s = w / We
    pts = np.asarray(uv, np.float64)
    if len(pts) < 2:
        return image
    nxt = np.roll(pts, -1, axis=0) if closed else pts[1:]
    cur = pts if closed else pts[:-1]
    nu = nxt[:, 0].copy()
    du = nu - cur[:, 0]
    nu[du > We / 2] -= We  # unwrap each segment the short way round the seam
    nu[du < -We / 2] += We
    shift = 4  # sub-pixel precision of cv2.line
    k = float(1 << shift)
    col = tuple(int(c) for c in color)
    for off in (-We, 0.0, We):
        x0 = ((cur[:, 0] + off + 0.5) * s - 0.5) * k
        x1 = ((nu + off + 0.5) * s - 0.5) * k
        y0 = ((cur[:, 1] + 0.5) * s - 0.5) * k
        y1 = ((nxt[:, 1] + 0.5) * s - 0.5) * k
        lo, hi = np.minimum(x0, x1), np.maximum(x0, x1)
        visible = (hi >= -thickness * k) & (lo <= (w + thickness) * k)
        for a, b, c, d in zip(x0[visible], y0[visible], x1[visible], y1[visible]):
            cv2.line(image, (int(round(a)), int(round(b))), (int(round(c)), int(round(d))), col, thickness, cv2.LINE_AA, shift)
    return image


# --------------------------------------------------------------------------------------------------
# rendering
# --------------------------------------------------------------------------------------------------
def render_views(
    panorama: np.ndarray, rotations: Sequence[tuple[int, int]], fov: float, height: int, width: int, mode: str = "bilinear"
) -> np.ndarray:
    """Perspective views ``(K, height, width, 3)`` uint8 of one panorama at ``(pitch, yaw)`` rotations."""
    from findview.sim import equi2pers

    equi = torch.from_numpy(np.ascontiguousarray(panorama)).permute(2, 0, 1)[None]
    out = np.empty((len(rotations), height, width, 3), np.uint8)
    for k, (p, y) in enumerate(rotations):
        v = equi2pers(equi, torch.tensor([float(p)]), torch.tensor([float(y)]), fov, height, width, mode)
        out[k] = v[0].permute(1, 2, 0).numpy()
    return out


def downscale_panorama(panorama: np.ndarray, height: int) -> np.ndarray:
    """The panorama resized to ``(height, 2 * height)`` (area interpolation when shrinking)."""
    h = int(height)
    if panorama.shape[0] == h and panorama.shape[1] == 2 * h:
        return panorama.copy()
    interp = cv2.INTER_AREA if h < panorama.shape[0] else cv2.INTER_LINEAR
    return cv2.resize(panorama, (2 * h, h), interpolation=interp)


def _frame_border(image: np.ndarray, color: Sequence[int], thickness: int = 2) -> np.ndarray:
    """A coloured frame drawn inside the image border (in place)."""
    h, w = image.shape[:2]
    cv2.rectangle(image, (0, 0), (w - 1, h - 1), tuple(int(c) for c in color), thickness)
    return image


def _label(image: np.ndarray, text: str, color: Sequence[int]) -> None:
    """A small caption with a dark outline at the top-left corner (in place)."""
    scale = max(0.35, image.shape[0] / 320.0)
    org = (6, 6 + int(14 * scale))
    cv2.putText(image, text, org, cv2.FONT_HERSHEY_SIMPLEX, scale, (0, 0, 0), 3, cv2.LINE_AA)
    cv2.putText(image, text, org, cv2.FONT_HERSHEY_SIMPLEX, scale, tuple(int(c) for c in color), 1, cv2.LINE_AA)


def episode_figure(
    panorama: np.ndarray,
    init: tuple[int, int],
    target: tuple[int, int],
    fov: float,
    height: int,
    width: int,
    mode: str = "bilinear",
    pano_height: int | None = None,
    labels: bool = True,
) -> np.ndarray:
    """The paper's Figure 2: the panorama with both view outlines, beside the two perspective views.

    Layout: the panorama resized to ``pano_height x 2 pano_height`` (default ``2 * height``) on the
    left, the initial view (red frame) above the target view (yellow frame) on the right. The canvas is
    ``max(pano_height, 2 height) x (2 pano_height + width)`` (RGB uint8, black padding).
    """
    He = panorama.shape[0]
    ph = int(pano_height) if pano_height else 2 * int(height)
    pano = downscale_panorama(panorama, ph)
    draw_outline(pano, view_outline(*init, fov, height, width, He), He, INIT_COLOR, max(2, ph // 128))
    draw_outline(pano, view_outline(*target, fov, height, width, He), He, TARGET_COLOR, max(2, ph // 128))
    views = render_views(panorama, [init, target], fov, height, width, mode)
    for v, c, name in zip(views, (INIT_COLOR, TARGET_COLOR), ("initial", "target")):
        _frame_border(v, c)
        if labels:
            _label(v, name, c)
    canvas = np.zeros((max(ph, 2 * height), 2 * ph + width, 3), np.uint8)
    canvas[:ph, : 2 * ph] = pano
    canvas[:height, 2 * ph :] = views[0]
    canvas[height : 2 * height, 2 * ph :] = views[1]
    return canvas


def replay_rotations(
    init: tuple[int, int], actions: Iterable[int], pitch_bound: int = 60, step_deg: int = 1
) -> list[tuple[int, int]]:
    """Rotations along an action sequence with the environment's rules (docs/TASK.md, section Episodes).

    Returns ``len(actions) + 1`` rotations: the start, then the rotation after each action.
    """
    p, y = int(init[0]), int(wrap_yaw(int(init[1])))
    out = [(p, y)]
    for a in actions:
        a = int(a)
        if a == 0:
            p = min(p + step_deg, pitch_bound)
        elif a == 1:
            p = max(p - step_deg, -pitch_bound)
        elif a == 2:
            y = int(wrap_yaw(y - step_deg))
        elif a == 3:
            y = int(wrap_yaw(y + step_deg))
        out.append((p, y))
    return out


def episode_frame(
    view: np.ndarray,
    target: np.ndarray,
    pano_small: np.ndarray,
    view_uv: np.ndarray,
    target_uv: np.ndarray,
    equi_height: int,
) -> np.ndarray:
    """One video frame: current view | target view | panorama with both outlines (RGB).

    The frame is ``max(H, ph) x (2 W + 2 ph)`` for views ``H x W`` and a ``ph x 2 ph`` panorama strip
    (black padding below the shorter part). No input is modified.
    """
    h, w = view.shape[:2]
    ph = pano_small.shape[0]
    pano = pano_small.copy()
    t = max(1, ph // 128)
    draw_outline(pano, target_uv, equi_height, TARGET_COLOR, t)
    draw_outline(pano, view_uv, equi_height, VIEW_COLOR, t)
    frame = np.zeros((max(h, ph), 2 * w + 2 * ph, 3), np.uint8)
    frame[:h, :w] = _frame_border(view.copy(), VIEW_COLOR)
    frame[:h, w : 2 * w] = _frame_border(target.copy(), TARGET_COLOR)
    frame[:ph, 2 * w :] = pano
    return frame


def _upscale(image: np.ndarray, factor: int) -> np.ndarray:
    """``image`` enlarged ``factor`` times with nearest-neighbour sampling (the agent's pixels, unblurred)."""
    if factor <= 1:
        return image
    return cv2.resize(image, (image.shape[1] * factor, image.shape[0] * factor), interpolation=cv2.INTER_NEAREST)


def write_video(
    path: str | os.PathLike,
    panorama: np.ndarray,
    rotations: Sequence[tuple[int, int]],
    target: tuple[int, int],
    fov: float,
    height: int,
    width: int,
    mode: str = "bilinear",
    fps: float = 30.0,
    pano_height: int | None = None,
    min_view_height: int = 256,
) -> Path:
    """Write an MP4 (``mp4v``) with one :func:`episode_frame` per rotation, atomically.

    The views are rendered at the agent's ``height x width`` and enlarged by a whole factor (nearest
    neighbour) until they are at least ``min_view_height`` pixels high (a 64 x 64 view shows as 256 x 256);
    the panorama strip beside them is ``pano_height`` (default: the shown view height) high; when it
    differs from the view height the shorter part is padded. Frames are written to a temp file beside
    ``path``, then renamed.

    Returns:
        ``path``.

    Raises:
        RuntimeError: OpenCV cannot open an MP4 writer.
    """
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    He = panorama.shape[0]
    factor = max(1, -(-int(min_view_height) // int(height)))  # ceil
    shown_h, shown_w = int(height) * factor, int(width) * factor
    ph = int(pano_height) if pano_height else shown_h
    rows = max(ph, shown_h)
    pano_small = downscale_panorama(panorama, ph)
    tgt = _upscale(render_views(panorama, [target], fov, height, width, mode)[0], factor)
    tgt_uv = view_outline(*target, fov, height, width, He)
    frame_w = 2 * shown_w + 2 * ph
    fd, tmp = tempfile.mkstemp(prefix=f".{path.stem}.", suffix=".mp4", dir=path.parent)
    os.close(fd)
    writer = cv2.VideoWriter(tmp, cv2.VideoWriter_fourcc(*"mp4v"), float(fps), (frame_w, rows))
    try:
        if not writer.isOpened():
            raise RuntimeError(f"OpenCV cannot write MP4 (mp4v) video to {tmp}")
        chunk = 64
        for start in range(0, len(rotations), chunk):
            rots = list(rotations[start : start + chunk])
            views = render_views(panorama, rots, fov, height, width, mode)
            for rot, view in zip(rots, views):
                frame = episode_frame(_upscale(view, factor), tgt, pano_small,
                                      view_outline(*rot, fov, height, width, He), tgt_uv, He)
                writer.write(cv2.cvtColor(frame, cv2.COLOR_RGB2BGR))
        writer.release()
        umask = os.umask(0)
        os.umask(umask)
        os.chmod(tmp, 0o666 & ~umask)  # mkstemp makes 0600 files; give the video the usual mode
        os.replace(tmp, path)
    except BaseException:
        writer.release()
        if os.path.exists(tmp):
            os.unlink(tmp)
        raise
    return path


def parse_rotation(value: object, what: str) -> tuple[int, int]:
    """``[pitch, yaw]`` (a list or config list of integer degrees) -> ``(pitch, yaw)``.

    Raises:
        ConfigError: (a user error) one line naming ``what`` and the value.
    """
    from omegaconf import OmegaConf

    from findview.config import ConfigError

    try:
        seq = list(OmegaConf.to_container(value) if OmegaConf.is_config(value) else value)  # type: ignore[arg-type]
        if len(seq) != 2 or any(float(v) != int(float(v)) for v in seq):
            raise ValueError
        return int(float(seq[0])), int(float(seq[1]))
    except (TypeError, ValueError):
        raise ConfigError(f"{what} must be [pitch, yaw] in integer degrees, got {value!r}") from None


def write_png(path: str | os.PathLike, rgb: np.ndarray) -> Path:
    """Write an ``(H, W, 3)`` uint8 RGB picture as PNG, atomically (temp file + rename)."""
    from findview.utils import atomic_write

    def _write(tmp: str) -> None:
        ok, buf = cv2.imencode(".png", cv2.cvtColor(rgb, cv2.COLOR_RGB2BGR))
        if not ok:
            raise RuntimeError("PNG encoding failed")
        with open(tmp, "wb") as f:
            f.write(buf.tobytes())

    return atomic_write(path, _write)
