"""Loading and validating equirectangular panoramas."""

from __future__ import annotations

import os
from pathlib import Path

import cv2
import numpy as np

IMAGE_EXTENSIONS = (".jpg", ".jpeg", ".png", ".bmp", ".webp", ".tif", ".tiff")


class PanoramaError(ValueError):
    """A panorama file that cannot be used (unreadable, truncated, wrong aspect ratio...)."""


def to_rgb(img: np.ndarray, path: str | os.PathLike = "<array>") -> np.ndarray:
    """Convert a decoded OpenCV image (gray, BGR, BGRA; uint8 or uint16) to contiguous RGB uint8."""
    if img.dtype == np.uint16:
        img = (img // 257).astype(np.uint8)
    elif img.dtype != np.uint8:
        raise PanoramaError(f"{path}: unsupported pixel type {img.dtype}, expected 8- or 16-bit")
    if img.ndim == 2:
        img = cv2.cvtColor(img, cv2.COLOR_GRAY2RGB)
    elif img.ndim == 3 and img.shape[2] == 1:
        img = cv2.cvtColor(img[:, :, 0], cv2.COLOR_GRAY2RGB)
    elif img.ndim == 3 and img.shape[2] == 3:
        img = cv2.cvtColor(img, cv2.COLOR_BGR2RGB)
    elif img.ndim == 3 and img.shape[2] == 4:
        img = cv2.cvtColor(img, cv2.COLOR_BGRA2RGB)
    else:
        raise PanoramaError(f"{path}: unsupported image shape {img.shape}, expected gray, RGB or RGBA")
    return np.ascontiguousarray(img)


def check_equirect_shape(height: int, width: int, path: str | os.PathLike = "<array>") -> None:
    """Raise :class:`PanoramaError` unless ``width == 2 * height`` (never silently stretched)."""
    if width != 2 * height:
        raise PanoramaError(
            f"{path}: not an equirectangular panorama: size {width}x{height} (WxH), expected width = 2 x height"
        )


def load_panorama(path: str | os.PathLike) -> np.ndarray:
    """Decode ``path`` to an ``(He, We, 3)`` RGB uint8 array, validating it.

    Grayscale and RGBA files are converted to RGB. Raises :class:`PanoramaError` naming the file when
    it is missing, unreadable, truncated or not 2:1.
    """
    path = Path(path)
    if not path.is_file():
        raise PanoramaError(f"{path}: panorama file not found")
    data = np.fromfile(str(path), dtype=np.uint8)
    if data.size == 0:
        raise PanoramaError(f"{path}: empty file")
    img = cv2.imdecode(data, cv2.IMREAD_UNCHANGED)
    if img is None:
        raise PanoramaError(f"{path}: cannot decode image (unreadable or not an image)")
    if _looks_truncated(data, path):
        raise PanoramaError(f"{path}: image file is truncated")
    img = to_rgb(img, path)
    check_equirect_shape(img.shape[0], img.shape[1], path)
    return img


def _looks_truncated(data: np.ndarray, path: Path) -> bool:
    """OpenCV decodes truncated JPEG/PNG silently (grey fill); detect it from the end markers."""
    suffix = path.suffix.lower()
    tail = data[-64:].tobytes()
    if suffix in (".jpg", ".jpeg") or data[:2].tobytes() == b"\xff\xd8":
        # a complete JPEG ends with EOI (FF D9), possibly followed by a little padding
        return b"\xff\xd9" not in data[-1024:].tobytes()
    if suffix == ".png" or data[:8].tobytes() == b"\x89PNG\r\n\x1a\n":
        return b"IEND" not in tail
    return False

