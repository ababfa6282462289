"""Pixel rules shared by every format: float images to uint8, depth units, the area resize.

The area (box) filter is Pillow's BOX resample: each output pixel is the mean of the source
pixels its footprint covers, weighted by the covered fraction, for any ratio. Colour is resized
as uint8 RGB; depth as float32 metres with zeros ("no reading") left out of the mean: the
depth and a 0/1 validity mask are box-resized alike and divided, so an output pixel is the
mean of the valid readings under it, and 0 only when none is valid.
"""
from __future__ import annotations

from typing import Any

import numpy as np
from PIL import Image

from hope_models.media.errors import MediaError

_BOX = Image.Resampling.BOX


def floats_to_uint8(raw: np.ndarray) -> np.ndarray:
    """float32 image values in [0, 1] -> uint8 by rint(x * 255): the one rule for inline image_rgb
    floats and float frames alike. Out-of-range or non-finite values raise MediaError."""
    if not np.isfinite(raw).all():
        raise MediaError("image values are NaN or infinite")
    lo, hi = float(raw.min()), float(raw.max())
    if lo < 0.0 or hi > 1.0:
        raise MediaError(f"image values span [{lo:g}, {hi:g}], expected [0, 1]")
    return np.rint(raw * 255.0).astype(np.uint8)


def millimetres_to_metres(raw: np.ndarray) -> np.ndarray:
    """uint16 depth in millimetres (0 = no reading) -> float32 metres [H, W, 1]."""
    return (raw.astype(np.float32) / np.float32(1000.0)).reshape(raw.shape[0], raw.shape[1], 1)


def checked_metres(raw: np.ndarray) -> np.ndarray:
    """float depth taken as metres -> float32 [H, W, 1]; NaN is a missing reading (stored as 0,
    the house's "no reading"), while a negative or infinite distance is a MediaError."""
    depth = raw.astype(np.float32).reshape(raw.shape[0], raw.shape[1], 1)
    depth = np.where(np.isnan(depth), np.float32(0.0), depth)
    if not np.isfinite(depth).all():
        raise MediaError("depth values are infinite")
    if depth.size and float(depth.min()) < 0.0:
        raise MediaError(f"depth values go down to {float(depth.min()):g} m; a distance is never negative")
    return depth


def check_out_hw(out_hw: Any) -> tuple[int, int]:
    """out_hw as (height, width) of positive ints, or ValueError naming the parameter."""
    try:
        height, width = out_hw
    except (TypeError, ValueError):
        raise ValueError(f"out_hw {out_hw!r} is not a (height, width) pair") from None
    for n in (height, width):
        if isinstance(n, bool) or not isinstance(n, (int, np.integer)) or n <= 0:
            raise ValueError(f"out_hw {out_hw!r}: height and width must be positive ints")
    return int(height), int(width)


def area_resize(img: np.ndarray, out_hw: tuple[int, int]) -> np.ndarray:
    """Area (box) resize of uint8 RGB [h, w, 3] or float32 depth [h, w, 1] to out_hw; same dtype out."""
    height, width = check_out_hw(out_hw)
    if img.ndim == 3 and img.shape[2] == 3 and img.dtype == np.uint8:
        if img.shape[:2] == (height, width):
            return np.array(img, order="C", copy=True)
        return area_resize_image(Image.fromarray(np.ascontiguousarray(img)), (height, width))
    if img.ndim == 3 and img.shape[2] == 1 and img.dtype == np.float32:
        return _depth_resize(img[:, :, 0], height, width)
    raise ValueError(f"area_resize takes uint8 [h, w, 3] or float32 [h, w, 1], not {img.dtype} {list(img.shape)}")


def area_resize_image(img: Image.Image, out_hw: tuple[int, int]) -> np.ndarray:
    """area_resize of a Pillow RGB image: what a decoder holding one skips the array round trip with."""
    height, width = out_hw
    if img.size != (width, height):
        img = img.resize((width, height), _BOX)
    return np.array(img)


def _depth_resize(depth: np.ndarray, height: int, width: int) -> np.ndarray:
    if depth.shape == (height, width):
        return np.array(depth, dtype=np.float32, copy=True).reshape(height, width, 1)
    readings = depth > 0  # NaN and negatives are no reading either: they must not reach the mean
    valid = readings.astype(np.float32)
    total = np.asarray(Image.fromarray(np.where(readings, depth, np.float32(0.0))).resize((width, height), _BOX))
    share = np.asarray(Image.fromarray(valid).resize((width, height), _BOX))
    out = np.zeros((height, width), dtype=np.float32)
    # share is the valid fraction under each output pixel; below 1e-6 is rounding, not a reading
    np.divide(total, share, out=out, where=share > 1e-6)
    return out.reshape(height, width, 1)
