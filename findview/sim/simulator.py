"""The batched renderer used by the FindView task.

Rotations are integer degrees, so the simulator precomputes one sampling grid per pitch in
``[-pitch_bound, pitch_bound]`` and renders any yaw as a horizontal shift of that grid by
``yaw / 360 * We`` panorama columns (exact: yaw only adds to the longitude). All envs' views are
rendered in one call from the panorama bank's slots.

Two backends implement the same SPEC section 1 mapping:

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

from findview.sim.bank import PanoramaBank
from findview.sim.equi2pers import MODES, _wrapped, sample_equirect, sample_points, to_output_dtype

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
        pitch_bound: largest ``|pitch|`` ever rendered, degrees (grids are precomputed up to it).
        mode: ``bilinear`` | ``nearest`` | ``bicubic``.
        backend: ``auto`` | ``opencv`` | ``torch`` (see module docstring).
    """

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

    # ------------------------------------------------------------------ grids
    def _build_grids(self, He: int) -> None:
        pitches = torch.arange(-self.pitch_bound, self.pitch_bound + 1, dtype=torch.float32)
        u, v = sample_points(pitches, self.fov, self.height, self.width, He)  # (P, H, W) float32, u in [0, We)
        if self.backend == "opencv":
            self._u_np = u.numpy()
            self._v_np = v.numpy()
        else:
            P = pitches.numel()
            self._u = u.reshape(P, -1).to(self.device, torch.float32)
            self._v = v.reshape(P, -1).to(self.device, torch.float32)
        self._grids_for = He

    # ----------------------------------------------------------------- render
    def new_buffer(self, n: int) -> torch.Tensor:
        """An ``(n, H, W, 3)`` uint8 buffer on the device for :meth:`render_into`."""
        return torch.zeros((n, self.height, self.width, 3), dtype=torch.uint8, device=self.device)

    def render(self, slots: torch.Tensor, pitch: torch.Tensor, yaw: torch.Tensor) -> torch.Tensor:
        """Views ``(N, 3, H, W)`` uint8 for bank slots ``(N,)`` at integer ``pitch, yaw (N,)`` degrees.

        The result is stored channels-last (``memory_format=torch.channels_last``).
        """
        out = self.new_buffer(int(slots.shape[0]))
        self.render_into(out, torch.arange(out.shape[0], device=self.device), slots, pitch, yaw)
        return out.permute(0, 3, 1, 2)

    def render_into(
        self, out: torch.Tensor, rows: torch.Tensor, slots: torch.Tensor, pitch: torch.Tensor, yaw: torch.Tensor
    ) -> None:
        """Write the views of ``slots, pitch, yaw (n,)`` into ``out[rows]`` (``out``: ``(N, H, W, 3)`` uint8)."""
        assert self.bank.slots is not None, "acquire a panorama from the bank before rendering"
        He = self.bank.slots.shape[1]
        if self._grids_for != He:
            self._build_grids(He)
        if int(slots.shape[0]) == 0:
            return
        if self.backend == "opencv":
            self._render_opencv(out, rows, slots, pitch, yaw, He)
        else:
            self._render_torch(out, rows, slots, pitch, yaw, He)

    def _pitch_index(self, pitch: torch.Tensor) -> torch.Tensor:
        p = pitch.long()
        if bool(((p < -self.pitch_bound) | (p > self.pitch_bound)).any()):
            raise ValueError(f"pitch outside [-{self.pitch_bound}, {self.pitch_bound}]: {p.tolist()}")
        return p + self.pitch_bound

    def _render_opencv(self, out, rows, slots, pitch, yaw, He: int) -> None:
        We = 2 * He
        pidx = self._pitch_index(pitch).tolist()
        shift = (yaw.to(torch.float32) * (We / 360.0)).tolist()
        slot_l = slots.tolist()
        bank = self.bank.slots.numpy()
        out_np = out.numpy()
        interp = cv2.INTER_LINEAR if self.mode == "bilinear" else cv2.INTER_NEAREST
        for r, s, p, sh in zip(rows.tolist(), slot_l, pidx, shift):
            mapx = _wrapped(self._u_np[p], sh, We)
            cv2.remap(bank[s], mapx, self._v_np[p], interp, dst=out_np[r], borderMode=cv2.BORDER_WRAP)

    def _render_torch(self, out, rows, slots, pitch, yaw, He: int) -> None:
        We = 2 * He
        pidx = self._pitch_index(pitch.to(self.device))
        u = self._u[pidx] + (yaw.to(self.device, torch.float32) * (We / 360.0))[:, None]
        v = self._v[pidx]
        flat = self.bank.slots.view(-1, 3)
        base = (slots.to(self.device).long() * (He * We))[:, None]
        res = to_output_dtype(sample_equirect(flat, base, u, v, He, self.mode), torch.uint8)
        out.index_copy_(0, rows.to(self.device), res.view(-1, self.height, self.width, 3))
