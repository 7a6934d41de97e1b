"""Digital corruptions: brightness, contrast, saturate (HSV) and JPEG compression."""

from __future__ import annotations

import cv2
import numpy as np
import torch

# added to the HSV value channel (V in [0, 1])
BRIGHTNESS = (0.1, 0.2, 0.3, 0.4, 0.5)
# factor applied to the deviation from the per-image, per-channel mean
CONTRAST = (0.4, 0.3, 0.2, 0.1, 0.05)
# (scale, offset) of the HSV saturation: S' = clip(S * scale + offset, 0, 1)
SATURATE = ((0.3, 0.0), (0.1, 0.0), (2.0, 0.0), (5.0, 0.1), (20.0, 0.2))
# JPEG quality (libjpeg scale 1-100), 4:2:0 chroma subsampling
JPEG_QUALITY = (25, 18, 15, 10, 7)


def rgb_to_hsv(x: torch.Tensor) -> torch.Tensor:
    """``(B, 3, H, W)`` RGB in [0, 1] -> HSV, all channels in [0, 1] (hue in turns).

    Conventions of ``skimage.color.rgb2hsv``: grey pixels (max == min) get hue 0 and saturation 0;
    on ties for the maximum channel, blue wins over green over red.
    """
    r, g, b = x[:, 0], x[:, 1], x[:, 2]
    v = x.amax(dim=1)
    delta = v - x.amin(dim=1)
    grey = delta == 0
    safe = torch.where(grey, torch.ones_like(delta), delta)
    s = torch.where(grey, torch.zeros_like(v), delta / torch.where(v == 0, torch.ones_like(v), v))
    h = (g - b) / safe
    h = torch.where(g == v, 2.0 + (b - r) / safe, h)
    h = torch.where(b == v, 4.0 + (r - g) / safe, h)
    h = torch.remainder(h / 6.0, 1.0)
    h = torch.where(grey, torch.zeros_like(h), h)
    return torch.stack([h, s, v], dim=1)


def hsv_to_rgb(hsv: torch.Tensor) -> torch.Tensor:
    """Inverse of :func:`rgb_to_hsv` (the six-sector formula of ``skimage.color.hsv2rgb``)."""
    h, s, v = hsv[:, 0], hsv[:, 1], hsv[:, 2]
    hi = torch.floor(h * 6.0)
    f = h * 6.0 - hi
    p = v * (1.0 - s)
    q = v * (1.0 - f * s)
    t = v * (1.0 - (1.0 - f) * s)
    sector = torch.remainder(hi, 6.0).long()  # (B, H, W)
    # (r, g, b) of each sector as indices into the candidates (v, t, p, q)
    table = torch.tensor([[0, 1, 2], [3, 0, 2], [2, 0, 1], [2, 3, 0], [1, 2, 0], [0, 2, 3]], device=hsv.device)
    idx = table[sector].permute(0, 3, 1, 2)  # (B, 3, H, W)
    return torch.stack([v, t, p, q], dim=1).gather(1, idx)


def brightness(x: torch.Tensor, severity: int, g: torch.Generator) -> torch.Tensor:
    """HSV: ``V' = clip(V + c, 0, 1)`` with hue and saturation kept.

    Computed in float64 like the reference, so that values that are integers in exact arithmetic
    round (and then truncate) the same way; :func:`findview.corruptions.corrupt` passes float64
    input to this function and to :func:`saturate`.
    """
    c = BRIGHTNESS[severity - 1]
    hsv = rgb_to_hsv(x.double())
    hsv = torch.stack([hsv[:, 0], hsv[:, 1], (hsv[:, 2] + c).clamp(0.0, 1.0)], dim=1)
    return hsv_to_rgb(hsv)


def contrast(x: torch.Tensor, severity: int, g: torch.Generator) -> torch.Tensor:
    """``(x - m) * c + m`` with ``m`` the mean of each channel over the image."""
    c = CONTRAST[severity - 1]
    m = x.mean(dim=(2, 3), keepdim=True)
    return (x - m) * c + m


def saturate(x: torch.Tensor, severity: int, g: torch.Generator) -> torch.Tensor:
    """HSV: ``S' = clip(S * scale + offset, 0, 1)`` with hue and value kept (float64, as the reference).

    Grey pixels have hue 0 (red), so a positive offset tints them red.
    """
    scale, offset = SATURATE[severity - 1]
    hsv = rgb_to_hsv(x.double())
    hsv = torch.stack([hsv[:, 0], (hsv[:, 1] * scale + offset).clamp(0.0, 1.0), hsv[:, 2]], dim=1)
    return hsv_to_rgb(hsv)


def jpeg_uint8(images: torch.Tensor, severity: int) -> torch.Tensor:
    """Encode and decode each uint8 image ``(B, 3, H, W)`` with the standard JPEG codec.

    OpenCV's libjpeg at quality 25, 18, 15, 10, 7 with 4:2:0 chroma subsampling (OpenCV's default,
    set explicitly where the option exists). Per-image work on the CPU; returns uint8 on
    ``images.device``.
    """
    quality = JPEG_QUALITY[severity - 1]
    params = [int(cv2.IMWRITE_JPEG_QUALITY), quality]
    if hasattr(cv2, "IMWRITE_JPEG_SAMPLING_FACTOR"):
        params += [int(cv2.IMWRITE_JPEG_SAMPLING_FACTOR), int(cv2.IMWRITE_JPEG_SAMPLING_FACTOR_420)]
    planes = images.detach().contiguous().cpu().numpy()  # (B, 3, H, W)
    out = np.empty_like(planes)
    for i in range(planes.shape[0]):
        bgr = cv2.merge([planes[i, 2], planes[i, 1], planes[i, 0]])  # OpenCV wants (H, W, 3) BGR
        ok, buf = cv2.imencode(".jpg", bgr, params)
        if not ok:
            raise RuntimeError("OpenCV could not encode an image as JPEG")
        b, g, r = cv2.split(cv2.imdecode(buf, cv2.IMREAD_COLOR))
        out[i, 0], out[i, 1], out[i, 2] = r, g, b
    return torch.from_numpy(out).to(images.device)


def jpeg_compression(x: torch.Tensor, severity: int, g: torch.Generator) -> torch.Tensor:
    """JPEG round trip of float images in [0, 1] (rounded to uint8 first); see :func:`jpeg_uint8`."""
    u8 = torch.round(x * 255.0).clamp_(0, 255).to(torch.uint8)
    return jpeg_uint8(u8, severity).to(x.dtype) / 255.0
