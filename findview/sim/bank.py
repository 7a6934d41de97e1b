"""A bounded bank of decoded panoramas on the simulation device, with LRU eviction and prefetch.

All panoramas live in one preallocated ``(capacity, He, We, 3)`` uint8 tensor (the *slots*), so a
batched renderer can address any mix of panoramas with a single gather, and resetting an episode never
copies a panorama. Slots in use by running episodes are pinned (reference counted); the least recently
used unpinned slot is recycled. Decoding (OpenCV, which releases the GIL) runs in background threads
so that :meth:`PanoramaBank.prefetch` hides it behind simulation steps.

Sizing (``sim.bank_mb``): when the bound holds every panorama the environments may use (the whole
train split), each is decoded once, on first use, and stays on the device as uint8; nothing is
evicted, and an episode start costs no host-device copy. Otherwise the bank is a bounded cache that
streams from disk: least recently used unpinned panoramas are evicted, the environment asks the bank to
prefetch (decode in the background) the panoramas of its upcoming episodes, and on CUDA the decoded
image reaches its slot through a page-locked buffer with a non-blocking copy.
"""

from __future__ import annotations

import logging
import os
import threading
from collections import OrderedDict
from concurrent.futures import Future, ThreadPoolExecutor

import cv2
import numpy as np
import torch

from findview.imageio import load_panorama

log = logging.getLogger(__name__)

__all__ = ["PanoramaBank"]


class PanoramaBank:
    """Decoded panoramas in device memory, bounded by ``budget_mb``.

    Args:
        device: where the slots live.
        budget_mb: memory bound of the slot tensor, MiB.
        equi_height: panorama height ``He`` in pixels (``We = 2 He``); ``None`` takes the first
            panorama's. Panoramas of another size are resized to it (INTER_AREA), with a warning.
        prefetch_workers: decoding threads; 0 decodes inline.
        max_panoramas: upper bound on distinct panoramas ever needed (e.g. the dataset size), so that
            small datasets do not reserve the whole budget.
        min_slots: the bank must hold at least this many panoramas at once (e.g. the number of envs).
    """

    def __init__(
        self,
        device: torch.device | str = "cpu",
        budget_mb: float = 2048,
        equi_height: int | None = None,
        prefetch_workers: int = 2,
        max_panoramas: int | None = None,
        min_slots: int = 1,
    ) -> None:
        if budget_mb <= 0:
            raise ValueError(f"sim.bank_mb must be positive, got {budget_mb}")
        self.device = torch.device(device)
        self.budget_mb = float(budget_mb)
        self.equi_height = equi_height
        self.max_panoramas = max_panoramas
        self.min_slots = max(1, int(min_slots))
        self.slots: torch.Tensor | None = None  # (capacity, He, We, 3) uint8
        self._slot_of: OrderedDict[str, int] = OrderedDict()  # path -> slot, LRU order (oldest first)
        self._path_of: dict[int, str] = {}
        self._refs: dict[int, int] = {}
        self._free: list[int] = []
        self._pending: dict[str, Future] = {}
        self._lock = threading.Lock()
        self._pool = ThreadPoolExecutor(prefetch_workers, thread_name_prefix="pano") if prefetch_workers > 0 else None
        self._warned_resize = False
        self.stats = {"hits": 0, "misses": 0, "prefetched": 0, "evictions": 0}

    # ------------------------------------------------------------------ public
    @property
    def capacity(self) -> int:
        return 0 if self.slots is None else self.slots.shape[0]

    def acquire(self, path: str) -> int:
        """Slot index holding ``path`` (decoding it if needed); pins the slot until :meth:`release`."""
        path = os.fspath(path)
        if path in self._slot_of:
            slot = self._slot_of[path]
            self._slot_of.move_to_end(path)
            self.stats["hits"] += 1
        else:
            img = self._take_decoded(path)
            slot = self._store(path, img)
        self._refs[slot] = self._refs.get(slot, 0) + 1
        return slot

    def release(self, slot: int) -> None:
        """Unpin a slot returned by :meth:`acquire`."""
        n = self._refs.get(slot, 0)
        if n <= 0:
            raise RuntimeError(f"panorama slot {slot} released more often than acquired")
        self._refs[slot] = n - 1

    def prefetch(self, paths) -> None:
        """Start decoding ``paths`` in the background (no-op for resident or pending ones)."""
        if self._pool is None:
            return
        for p in paths:
            p = os.fspath(p)
            with self._lock:
                if p in self._slot_of or p in self._pending:
                    continue
                self._pending[p] = self._pool.submit(self._decode, p)

    def panorama(self, slot: int) -> torch.Tensor:
        """The ``(He, We, 3)`` uint8 view of a slot."""
        assert self.slots is not None
        return self.slots[slot]

    def close(self) -> None:
        if self._pool is not None:
            self._pool.shutdown(wait=False, cancel_futures=True)
            self._pool = None

    def __del__(self):  # pragma: no cover - best effort
        try:
            self.close()
        except Exception:
            pass

    # ----------------------------------------------------------------- private
    def _decode(self, path: str) -> np.ndarray:
        img = load_panorama(path)
        if self.equi_height is not None and img.shape[0] != self.equi_height:
            if not self._warned_resize:
                log.warning(
                    "panorama %s is %dx%d; resizing panoramas to %dx%d (set sim.equi_height to change)",
                    path, img.shape[1], img.shape[0], 2 * self.equi_height, self.equi_height,
                )
                self._warned_resize = True
            img = cv2.resize(img, (2 * self.equi_height, self.equi_height), interpolation=cv2.INTER_AREA)
        return img

    def _take_decoded(self, path: str) -> np.ndarray:
        with self._lock:
            fut = self._pending.pop(path, None)
        if fut is not None:
            self.stats["prefetched"] += 1
            img = fut.result()
        else:
            self.stats["misses"] += 1
            img = self._decode(path)
        if self.equi_height is None:
            self.equi_height = img.shape[0]
        if img.shape[0] != self.equi_height:  # decoded before equi_height was known
            img = cv2.resize(img, (2 * self.equi_height, self.equi_height), interpolation=cv2.INTER_AREA)
        return img

    def _allocate(self, He: int) -> None:
        per = He * 2 * He * 3
        cap = int(self.budget_mb * 2**20 // per)
        if self.max_panoramas is not None:
            cap = min(cap, max(self.max_panoramas, self.min_slots))
        if cap < self.min_slots:
            need = self.min_slots * per / 2**20
            raise ValueError(
                f"sim.bank_mb={self.budget_mb:g} MiB holds {cap} panoramas of {2 * He}x{He} but "
                f"{self.min_slots} are needed at once (one per env): set sim.bank_mb >= {need:.0f}"
            )
        self.slots = torch.empty((cap, He, 2 * He, 3), dtype=torch.uint8, device=self.device)
        self._free = list(range(cap - 1, -1, -1))
        log.info("panorama bank: %d slots of %dx%d on %s (%.0f MiB)", cap, 2 * He, He, self.device, cap * per / 2**20)

    def _store(self, path: str, img: np.ndarray) -> int:
        if self.slots is None:
            self._allocate(img.shape[0])
        if self._free:
            slot = self._free.pop()
        else:
            slot = self._evict()
        src = torch.from_numpy(img)
        if self.device.type == "cuda":  # page-locked staging: the copy is queued, the host does not wait
            self.slots[slot].copy_(src.pin_memory(), non_blocking=True)
        else:
            self.slots[slot].copy_(src)
        self._slot_of[path] = slot
        self._path_of[slot] = path
        self._refs[slot] = 0
        return slot

    def _evict(self) -> int:
        for path, slot in self._slot_of.items():  # oldest first
            if self._refs.get(slot, 0) == 0:
                del self._slot_of[path]
                del self._path_of[slot]
                self.stats["evictions"] += 1
                return slot
        raise RuntimeError(
            f"panorama bank full: all {self.capacity} slots are in use by running episodes; raise sim.bank_mb"
        )
