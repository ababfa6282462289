"""JPEG and PNG frames through Pillow, with no global Pillow setting touched.

A JPEG is decoded in draft mode: libjpeg's DCT scaling decodes straight at 1/2, 1/4 or 1/8 of
the size (the smallest still at least the output size), so a 640x480 frame bound for 64x64 costs
a 160x120 decode; the area resize does the rest. A truncated JPEG is an error (Pillow's
LOAD_TRUNCATED_IMAGES stays off). Pillow's decompression-bomb warning is turned into an error
for the duration of the call only, and the declared size is checked against max_pixels before
any pixel is decoded.
"""
from __future__ import annotations

import warnings
from collections.abc import Iterator
from contextlib import contextmanager
from typing import BinaryIO

import numpy as np
from PIL import Image

from hope_models.media.errors import MediaError, check_pixels
from hope_models.media.info import FrameInfo
from hope_models.media.pixels import millimetres_to_metres

PIL_FORMATS = {"jpeg": "JPEG", "png": "PNG"}
_DEPTH_MODES = ("I;16", "I;16L", "I;16B", "I")  # 16-bit grey; older Pillows open it as 32-bit "I"
# Pillow mode -> channels as stored (a palette image holds RGB colours)
_CHANNELS = {"1": 1, "L": 1, "LA": 2, "P": 3, "PA": 4, "RGB": 3, "RGBA": 4, "RGBX": 4, "CMYK": 4, "YCbCr": 3}


@contextmanager
def pillow_errors(name: str, fmt: str) -> Iterator[None]:
    """Whatever Pillow raises or warns about untrusted bytes becomes MediaError naming the file.

    catch_warnings swaps the process's warning filters while it runs (Python < 3.14 has no
    per-thread filters), so another thread's warnings are ignored meanwhile too: filters, not
    Pillow's MAX_IMAGE_PIXELS, because the filters are restored on the way out.
    """
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")  # e.g. corrupt EXIF: the pixels still decode; nothing to act on
        warnings.simplefilter("error", Image.DecompressionBombWarning)
        try:
            yield
        except MediaError:
            raise
        except (Image.DecompressionBombError, Image.DecompressionBombWarning) as exc:
            raise MediaError(f"{name}: {fmt} declares too many pixels: {exc}") from None
        except Exception as exc:  # untrusted bytes: any Pillow failure means "not a usable frame"
            raise MediaError(f"{name}: undecodable {fmt}: {type(exc).__name__}: {exc}") from None


def _open(f: BinaryIO, kind: str, name: str, max_pixels: int) -> Image.Image:
    fmt = PIL_FORMATS[kind]
    img = Image.open(f, formats=[fmt])  # header only: nothing is decoded yet
    width, height = img.size
    check_pixels(height, width, max_pixels, f"{fmt} header", name)
    return img


def probe_image(f: BinaryIO, kind: str, name: str, max_pixels: int) -> FrameInfo:
    fmt = PIL_FORMATS[kind]
    with pillow_errors(name, fmt):
        img = _open(f, kind, name, max_pixels)
        width, height = img.size
        if img.mode in _DEPTH_MODES:
            return FrameInfo(fmt, height, width, 1, "uint16")
        if img.mode not in _CHANNELS:
            raise MediaError(f"{name}: {fmt} of mode {img.mode} is not a camera frame")
        return FrameInfo(fmt, height, width, _CHANNELS[img.mode], "uint8")


def read_image(f: BinaryIO, kind: str, name: str, out_hw: tuple[int, int], frame_kind: str,
               max_pixels: int) -> Image.Image | np.ndarray:
    """The frame of an open JPEG/PNG before the area resize: a loaded Pillow RGB image, or float32
    metres [h, w, 1] for frame_kind "depth" (16-bit grey PNG, millimetres). A JPEG comes at its
    draft size."""
    fmt = PIL_FORMATS[kind]
    with pillow_errors(name, fmt):
        img = _open(f, kind, name, max_pixels)
        if frame_kind == "depth":
            return _depth(img, fmt, name)
        if img.mode in _DEPTH_MODES:
            raise MediaError(f"{name}: 16-bit grey {fmt} is a depth image (millimetres); decode it with kind='depth'")
        if img.mode not in _CHANNELS:
            raise MediaError(f"{name}: {fmt} of mode {img.mode} is not a camera frame")
        if kind == "jpeg":
            img.draft("RGB", (out_hw[1], out_hw[0]))
        # RGBA/LA/PA lose their alpha here: a camera frame's transparency carries nothing to learn
        rgb = img.convert("RGB") if img.mode != "RGB" else img
        rgb.load()
        return rgb


def _depth(img: Image.Image, fmt: str, name: str) -> np.ndarray:
    if fmt != "PNG" or img.mode not in _DEPTH_MODES:
        raise MediaError(f"{name}: {fmt} of mode {img.mode} is not a depth image; expected a 16-bit grey PNG "
                         "(millimetres)")
    raw = np.asarray(img)
    if raw.dtype != np.uint16:  # the 32-bit "I" an older Pillow gives: must still be 16-bit values
        if raw.size and (int(raw.min()) < 0 or int(raw.max()) > 65535):
            raise MediaError(f"{name}: depth PNG values outside 0..65535")
        raw = raw.astype(np.uint16)
    return millimetres_to_metres(raw)
