"""The 16 natural image corruptions of the robustness benchmark, as batched torch operations.

Definitions and severity tables are those of ImageNet-C (Hendrycks & Dietterich 2019) as packaged
by Michaelis et al. 2019 (``imagecorruptions`` 1.1.2); see docs/TASK.md. The reference package is
not needed: the frost textures ship with findview (``findview/corruptions/frost``, Apache-2.0).

Entry point: :func:`corrupt`. Helpers for configuration code: :data:`NAMES`, :data:`CATEGORIES`,
:func:`resolve_names`, :func:`check_severity`, :func:`frost_textures_available` and
:func:`check_frost_textures`.

Randomness and devices: every random draw uses the ``torch.Generator`` passed to :func:`corrupt`
(never the global RNG). A generator on another device than the images (e.g. a CPU generator with
CUDA images) draws one seed from which a generator on the images' device is made, so the result is
reproducible for a given generator state on each device, but CPU and CUDA outputs differ. The JPEG
codec and the water-drop shading of ``spatter`` (severities 1-3) run per image on the CPU with
OpenCV; all other steps stay on the images' device.
"""

from __future__ import annotations

from collections.abc import Callable, Iterable

import torch

from findview.runtime import light_work

from . import blur, digital, noise, weather
from ._common import device_generator
from .weather import FROST_DIR, check_frost_textures, frost_textures_available, missing_frost_textures

__all__ = [
    "NAMES",
    "CATEGORIES",
    "SEVERITIES",
    "FROST_DIR",
    "corrupt",
    "resolve_names",
    "check_severity",
    "check_name",
    "frost_textures_available",
    "check_frost_textures",
    "missing_frost_textures",
]

#: The 16 corruptions in the paper's order (blur, noise, digital, weather).
NAMES: tuple[str, ...] = (
    "motion_blur",
    "defocus_blur",
    "glass_blur",
    "gaussian_blur",
    "gaussian_noise",
    "impulse_noise",
    "shot_noise",
    "speckle_noise",
    "brightness",
    "contrast",
    "saturate",
    "jpeg_compression",
    "snow",
    "spatter",
    "fog",
    "frost",
)

#: Category -> names, in the paper's order.
CATEGORIES: dict[str, tuple[str, ...]] = {
    "blur": NAMES[0:4],
    "noise": NAMES[4:8],
    "digital": NAMES[8:12],
    "weather": NAMES[12:16],
}

#: Valid severities (1 = mildest, 5 = strongest).
SEVERITIES: tuple[int, ...] = (1, 2, 3, 4, 5)

_Op = Callable[[torch.Tensor, int, torch.Generator], torch.Tensor]
_OPS: dict[str, _Op] = {
    "motion_blur": blur.motion_blur,
    "defocus_blur": blur.defocus_blur,
    "glass_blur": blur.glass_blur,
    "gaussian_blur": blur.gaussian_blur,
    "gaussian_noise": noise.gaussian_noise,
    "impulse_noise": noise.impulse_noise,
    "shot_noise": noise.shot_noise,
    "speckle_noise": noise.speckle_noise,
    "brightness": digital.brightness,
    "contrast": digital.contrast,
    "saturate": digital.saturate,
    "jpeg_compression": digital.jpeg_compression,
    "snow": weather.snow,
    "spatter": weather.spatter,
    "fog": weather.fog,
    "frost": weather.frost,
}
assert tuple(_OPS) == NAMES

#: Smallest image side accepted (pixels), as the reference.
MIN_SIDE = 32


def check_name(name: object) -> str:
    """Return ``name`` if it is one of :data:`NAMES`, else raise a one-line ``ValueError`` listing them."""
    if not isinstance(name, str) or name not in _OPS:
        raise ValueError(f"unknown corruption {name!r}: expected one of {', '.join(NAMES)}")
    return name


def check_severity(severity: object) -> int:
    """Return ``severity`` as an int if it is an integer in 1-5, else raise a one-line ``ValueError``."""
    if isinstance(severity, bool) or not isinstance(severity, int) or severity not in SEVERITIES:
        # accept integral floats/strings only when they are exact integers in range
        try:
            value = int(str(severity)) if not isinstance(severity, (bool, float)) else None
        except ValueError:
            value = None
        if isinstance(severity, float) and severity.is_integer():
            value = int(severity)
        if value is None or value not in SEVERITIES:
            raise ValueError(f"invalid corruption severity {severity!r}: expected an integer from 1 to 5")
        return value
    return severity


def resolve_names(spec: str | Iterable[str] | None) -> tuple[str, ...]:
    """Expand a corruption selection to names, in the order of :data:`NAMES` for groups.

    ``spec`` is one name, a category (``blur``, ``noise``, ``digital``, ``weather``), ``"all"``,
    ``"none"`` (or ``None``, giving ``()``), or a list of any of those (order kept, duplicates
    dropped). Raises a one-line ``ValueError`` listing the valid values for anything else.
    """
    if spec is None:
        return ()
    items = [spec] if isinstance(spec, str) else list(spec)
    out: list[str] = []
    for item in items:
        if not isinstance(item, str):
            raise ValueError(f"invalid corruption {item!r}: expected a name, a category, 'all' or 'none'")
        key = item.strip()
        if key == "none":
            names: tuple[str, ...] = ()
        elif key == "all":
            names = NAMES
        elif key in CATEGORIES:
            names = CATEGORIES[key]
        elif key in _OPS:
            names = (key,)
        else:
            raise ValueError(
                f"unknown corruption {item!r}: expected 'all', 'none', a category ({', '.join(CATEGORIES)}) "
                f"or one of {', '.join(NAMES)}"
            )
        out.extend(n for n in names if n not in out)
    return tuple(out)


@light_work()
def corrupt(
    images: torch.Tensor, name: str, severity: int, generator: torch.Generator | None = None
) -> torch.Tensor:
    """Apply corruption ``name`` at ``severity`` to a batch of images.

    Args:
        images: ``(B, 3, H, W)`` RGB, uint8 in [0, 255] or floating point in [0, 1], on any device;
            ``H, W >= 32`` pixels.
        name: one of :data:`NAMES`.
        severity: 1 (mildest) to 5.
        generator: source of all randomness (the global RNG is never used). ``None`` means a fresh
            generator seeded with 0, so repeated calls give the same result. A generator on another
            device than ``images`` seeds one on the images' device (see the module docstring).

    Returns:
        The corrupted batch with the shape, dtype and device of ``images``. For uint8 input the values
        are truncated to integers like the reference (``np.uint8``); float output is in [0, 1], not
        quantised (the reference's intermediate quantisations, e.g. in glass blur, snow and JPEG, are
        kept).
    """
    check_name(name)
    severity = check_severity(severity)
    if not isinstance(images, torch.Tensor):
        raise TypeError(f"images must be a torch.Tensor, got {type(images).__name__}")
    if images.dim() != 4 or images.shape[1] != 3:
        raise ValueError(f"images must have shape (B, 3, H, W), got {tuple(images.shape)}")
    if min(images.shape[2], images.shape[3]) < MIN_SIDE:
        size = f"{images.shape[2]}x{images.shape[3]}"
        raise ValueError(f"images must be at least {MIN_SIDE}x{MIN_SIDE} pixels, got {size}")
    is_uint8 = images.dtype == torch.uint8
    if not is_uint8 and not images.is_floating_point():
        raise ValueError(f"images must be uint8 or floating point, got {images.dtype}")
    if name == "frost":
        check_frost_textures()
    if images.shape[0] == 0:
        return images.clone()
    g = device_generator(generator, images.device)
    # the HSV corruptions follow the reference's float64 arithmetic (see digital.brightness)
    dtype = torch.float64 if name in ("brightness", "saturate") else torch.float32
    if is_uint8:
        if name == "jpeg_compression":  # the codec works on uint8 directly
            return digital.jpeg_uint8(images, severity)
        x = images.to(dtype).div_(255.0)
    else:
        x = images.to(dtype, copy=True)
    y = _OPS[name](x, severity, g)
    if is_uint8:
        # The reference truncates. Float64 results follow the reference's arithmetic and are truncated
        # as they are; float32 ones get a small allowance so exact integers stay exact. ``x`` is our
        # own copy, so ``y`` (which may be ``x`` or a view of it) can be scaled in place.
        eps = 0.0 if y.dtype == torch.float64 else 1e-3
        return y.mul_(255.0).add_(eps).clamp_(0.0, 255.0).to(torch.uint8)
    return y.clamp(0.0, 1.0).to(images.dtype)
