"""The batched renderer used by the FindView task.

Rotations are integer degrees, so the simulator keeps one sampling grid per pitch in
``[-pitch_bound, pitch_bound]`` and renders any yaw as a horizontal shift of that grid by
``yaw / 360 * We`` panorama columns (exact: yaw only adds to the longitude). All envs' views are
rendered in one call from the panorama bank's slots.

Grids are built lazily, the first time a pitch is rendered (about 1 ms each at 256x256 on one
CPU thread, always computed on the CPU in float32 so that every device samples the same points):
the first reset of 16 envs builds at most 32 of the 121 grids instead of all of them.

Two backends implement the same mapping (docs/TASK.md):

- ``opencv`` (CPU default for bilinear / nearest): ``cv2.remap`` per view with ``BORDER_WRAP``,
  SIMD fixed-point sampling (sample points quantised to 1/32 pixel).
- ``torch`` (CUDA default, any device, every mode): one batched gather over the slot tensor,
  float32 weights.
"""

from __future__ import annotations

import logging

import cv2
import numpy as np
import torch

from findview.runtime import light_work
from findview.sim.bank import PanoramaBank
from findview.sim.equi2pers import MODES, _wrapped, sample_equirect, to_output_dtype, yaw0_points

log = logging.getLogger(__name__)

__all__ = ["Simulator", "resolve_device"]

BACKENDS = ("auto", "opencv", "torch")


def resolve_device(device: str | torch.device = "auto") -> torch.device:
    """``auto`` -> ``cuda`` when available, else ``cpu``; otherwise ``torch.device(device)``."""
    if isinstance(device, torch.device):
        return device
    if device in (None, "auto"):
        return torch.device("cuda" if torch.cuda.is_available() else "cpu")
    dev = torch.device(device)
    if dev.type == "cuda" and not torch.cuda.is_available():
        raise ValueError(f"sim.device={device!r} but CUDA is not available; use sim.device=cpu or auto")
    return dev


def check_view_config(fov: float, height: int, width: int, mode: str) -> None:
    """Raise ``ValueError`` naming the bad value."""
    if not 0 < float(fov) < 180:
        raise ValueError(f"sim.fov must be in (0, 180) degrees, got {fov!r}")
    if int(height) <= 0 or int(width) <= 0:
        raise ValueError(f"sim.height and sim.width must be positive pixels, got {height}x{width}")
    if mode not in MODES:
        raise ValueError(f"sim.mode must be one of {MODES}, got {mode!r}")


class Simulator:
    """Render ``(N, 3, H, W)`` uint8 views of panoramas held in a :class:`PanoramaBank`.

    Args:
        bank: decoded panoramas (its ``equi_height`` is fixed at the first load).
        fov: horizontal field of view, degrees.
        height, width: view size, pixels.
        pitch_bound: largest ``|pitch|`` ever rendered, degrees (one grid per integer pitch up to it,
            each built on first use).
        mode: ``bilinear`` | ``nearest`` | ``bicubic``.
        backend: ``auto`` | ``opencv`` | ``torch`` (see module docstring).
    """

    @light_work()
    def __init__(
        self,
        bank: PanoramaBank,
        fov: float = 90.0,
        height: int = 256,
        width: int = 256,
        pitch_bound: int = 60,
        mode: str = "bilinear",
        backend: str = "auto",
    ) -> None:
        check_view_config(fov, height, width, mode)
        if not 0 <= int(pitch_bound) <= 90:
            raise ValueError(f"task.pitch_bound must be in [0, 90] degrees, got {pitch_bound!r}")
        if backend not in BACKENDS:
            raise ValueError(f"sim.backend must be one of {BACKENDS}, got {backend!r}")
        self.bank = bank
        self.device = bank.device
        self.fov, self.height, self.width = float(fov), int(height), int(width)
        self.pitch_bound = int(pitch_bound)
        self.mode = mode
        if backend == "auto":
            backend = "opencv" if self.device.type == "cpu" and mode != "bicubic" else "torch"
        if backend == "opencv" and (self.device.type != "cpu" or mode == "bicubic"):
            raise ValueError("sim.backend=opencv needs sim.device=cpu and mode bilinear or nearest")
        self.backend = backend
        self._grids_for: int | None = None  # equi height the grids were built for
        self._built: list[bool] = []  # per pitch index (pitch + pitch_bound): grid built
        self._n_built = 0

    # ------------------------------------------------------------------ grids
    @property
    def grids_built(self) -> int:
        """How many per-pitch grids exist (they are built on first use of each pitch)."""
        return self._n_built

    def _reset_grids(self, He: int) -> None:
        """Forget the grids (a new panorama height): storage for all pitches, none built."""
        P = 2 * self.pitch_bound + 1
        if self.backend == "opencv":
            self._u_np: list[np.ndarray | None] = [None] * P
            self._v_np: list[np.ndarray | None] = [None] * P
        else:
            HW = self.height * self.width
            self._u = torch.zeros((P, HW), dtype=torch.float32, device=self.device)
            self._v = torch.zeros((P, HW), dtype=torch.float32, device=self.device)
        self._built = [False] * P
        self._n_built = 0
        self._grids_for = He

    def _ensure_grids(self, pidx: list[int], He: int) -> None:
        """Build the grids of the pitch indices ``pidx`` (``pitch + pitch_bound``) not built yet."""
        if self._grids_for != He:
            self._reset_grids(He)
        if self._n_built == len(self._built):
            return
        missing = sorted({p for p in pidx if not self._built[p]})
        if not missing:
            return
        grids = [yaw0_points(float(p - self.pitch_bound), self.fov, self.height, self.width, He) for p in missing]
        if self.backend == "opencv":
            for p, (u, v) in zip(missing, grids):
                self._u_np[p], self._v_np[p] = u.numpy(), v.numpy()
        else:
            idx = torch.tensor(missing, dtype=torch.long, device=self.device)
            self._u.index_copy_(0, idx, torch.stack([g[0].reshape(-1) for g in grids]).to(self.device))
            self._v.index_copy_(0, idx, torch.stack([g[1].reshape(-1) for g in grids]).to(self.device))
        for p in missing:
            self._built[p] = True
        self._n_built += len(missing)

    @light_work()
    def build_all_grids(self, equi_height: int) -> None:
        """Build every pitch's grid now (e.g. before timing steps) for panoramas ``equi_height`` high."""
        self._ensure_grids(list(range(2 * self.pitch_bound + 1)), int(equi_height))

    # ----------------------------------------------------------------- render
    def new_buffer(self, n: int) -> torch.Tensor:
        """An ``(n, H, W, 3)`` uint8 buffer on the device for :meth:`render_into`."""
        return torch.zeros((n, self.height, self.width, 3), dtype=torch.uint8, device=self.device)

    @light_work()
    def render(self, slots: torch.Tensor, pitch: torch.Tensor, yaw: torch.Tensor) -> torch.Tensor:
        """Views ``(N, 3, H, W)`` uint8 for bank slots ``(N,)`` at integer ``pitch, yaw (N,)`` degrees.

        The result is stored channels-last (``memory_format=torch.channels_last``).
        """
        out = self.new_buffer(int(slots.shape[0]))
        self.render_into(out, torch.arange(out.shape[0], device=self.device), slots, pitch, yaw)
        return out.permute(0, 3, 1, 2)

    @light_work()
    def render_into(
        self, out: torch.Tensor, rows: torch.Tensor, slots: torch.Tensor, pitch: torch.Tensor, yaw: torch.Tensor,
        validate: bool = True,
    ) -> None:
        """Write the views of ``slots, pitch, yaw (n,)`` into ``out[rows]`` (``out``: ``(N, H, W, 3)`` uint8).

        ``validate``: check that every pitch is within ``[-pitch_bound, pitch_bound]`` (``ValueError``
        otherwise); callers that clamp pitch themselves pass ``False``, which on CUDA saves a host-device
        sync per call (the torch backend then never waits for the device once every pitch's grid exists).
        """
        assert self.bank.slots is not None, "acquire a panorama from the bank before rendering"
        He = self.bank.slots.shape[1]
        if int(slots.shape[0]) == 0:
            return
        if self.backend == "opencv":
            self._render_opencv(out, rows, slots, pitch, yaw, He)
        else:
            self._render_torch(out, rows, slots, pitch, yaw, He, validate)

    def _pitch_index(self, pitch: torch.Tensor, validate: bool = True) -> torch.Tensor:
        p = pitch.long()
        if validate and bool(((p < -self.pitch_bound) | (p > self.pitch_bound)).any()):
            raise ValueError(f"pitch outside [-{self.pitch_bound}, {self.pitch_bound}]: {p.tolist()}")
        return p + self.pitch_bound

    def _render_opencv(self, out, rows, slots, pitch, yaw, He: int) -> None:
        We = 2 * He
        pidx = self._pitch_index(pitch).tolist()
        self._ensure_grids(pidx, He)
        shift = (yaw.to(torch.float32) * (We / 360.0)).tolist()
        slot_l = slots.tolist()
        bank = self.bank.slots.numpy()
        out_np = out.numpy()
        interp = cv2.INTER_LINEAR if self.mode == "bilinear" else cv2.INTER_NEAREST
        for r, s, p, sh in zip(rows.tolist(), slot_l, pidx, shift):
            mapx = _wrapped(self._u_np[p], sh, We)
            cv2.remap(bank[s], mapx, self._v_np[p], interp, dst=out_np[r], borderMode=cv2.BORDER_WRAP)

    def _render_torch(self, out, rows, slots, pitch, yaw, He: int, validate: bool = True) -> None:
        We = 2 * He
        pidx = self._pitch_index(pitch.to(self.device), validate)
        if self._grids_for != He or self._n_built < len(self._built):
            if self.device.type != "cpu":  # all grids at once (about 0.1 s): no per-step sync afterwards
                self._ensure_grids(list(range(2 * self.pitch_bound + 1)), He)
            else:
                self._ensure_grids(torch.unique(pidx).tolist(), He)
        u = self._u[pidx] + (yaw.to(self.device, torch.float32) * (We / 360.0))[:, None]
        v = self._v[pidx]
        flat = self.bank.slots.view(-1, 3)
        base = (slots.to(self.device).long() * (He * We))[:, None]
        res = to_output_dtype(sample_equirect(flat, base, u, v, He, self.mode), torch.uint8)
        out.index_copy_(0, rows.to(self.device), res.view(-1, self.height, self.width, 3))
