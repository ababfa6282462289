"""The entry points for one file: probe (header only) and decode_still (one frame, resized).

A file's format is told by its first bytes only (sniff), never by its name: a .jpg holding a PNG
decodes as the PNG it is, a .npy holding anything else is refused.
"""
from __future__ import annotations

import io
import os
from pathlib import Path

import numpy as np
from PIL import Image

from hope_models.media.errors import DEFAULT_MAX_PIXELS, MediaError, label
from hope_models.media.image import probe_image, read_image
from hope_models.media.info import FrameInfo
from hope_models.media.npy import load_npy, probe_npy
from hope_models.media.pixels import area_resize, area_resize_image, check_out_hw
from hope_models.media.sniff import SNIFF_BYTES, sniff_bytes
from hope_models.media.video import VIDEO_KINDS, open_video

FRAME_KINDS = ("rgb", "depth")


def _stat(path: Path, name: str) -> int:
    try:
        size = path.stat().st_size
    except FileNotFoundError:
        raise MediaError(f"{name}: file not found") from None
    except OSError as exc:
        raise MediaError(f"{name}: unreadable: {exc.strerror or exc}") from None
    if not path.is_file():
        raise MediaError(f"{name}: not a regular file")
    if size == 0:
        raise MediaError(f"{name}: empty file (0 bytes)")
    return size


def _kind(f, name: str) -> str:
    kind = sniff_bytes(f.read(SNIFF_BYTES))
    f.seek(0)
    if kind is None:
        raise MediaError(f"{name}: not a known media file (its first bytes match none of npy, jpeg, png, mp4, webm)")
    if kind == "empty":  # emptied between stat and open
        raise MediaError(f"{name}: empty file (0 bytes)")
    return kind


def probe(path: str | os.PathLike, where: str | None = None, max_pixels: int = DEFAULT_MAX_PIXELS) -> FrameInfo:
    """What the file's header says (format, native size, channels, dtype); no pixel is decoded.
    MediaError when the file is unusable: empty, unknown, unreadable header, too many pixels."""
    path, name = Path(path), label(path, where)
    _stat(path, name)
    try:
        with open(path, "rb") as f:
            kind = _kind(f, name)
            if kind == "npy":
                return probe_npy(f, name, max_pixels)
            if kind in VIDEO_KINDS:
                f.close()
                container, _stream, info, _duration = open_video(path, name, max_pixels)
                container.close()
                return info
            return probe_image(f, kind, name, max_pixels)
    except OSError as exc:
        raise MediaError(f"{name}: unreadable: {exc.strerror or exc}") from None


def decode_still(path: str | os.PathLike, out_hw: tuple[int, int], kind: str = "rgb", where: str | None = None,
                 max_pixels: int = DEFAULT_MAX_PIXELS) -> np.ndarray:
    """The one frame of an npy / jpeg / png file, area-resized to out_hw (height, width).

    kind "rgb": uint8 [H, W, 3]; kind "depth": float32 [H, W, 1] in metres (uint16 .npy or 16-bit
    grey PNG in millimetres, float32 .npy in metres). MediaError naming the file (and `where`)
    for anything unusable; ValueError for a bad out_hw or kind."""
    if kind not in FRAME_KINDS:
        raise ValueError(f"kind {kind!r}: expected one of {', '.join(FRAME_KINDS)}")
    hw = check_out_hw(out_hw)
    path, name = Path(path), label(path, where)
    size = _stat(path, name)
    try:
        with open(path, "rb") as f:
            fmt = _kind(f, name)
            if fmt in VIDEO_KINDS:
                raise MediaError(f"{name}: a {fmt} video, not a still frame; read it with VideoFrames")
            frame: Image.Image | np.ndarray = (load_npy(f, size, name, kind, max_pixels) if fmt == "npy"
                                               else read_image(f, fmt, name, hw, kind, max_pixels))
    except OSError as exc:
        raise MediaError(f"{name}: unreadable: {exc.strerror or exc}") from None
    if isinstance(frame, Image.Image):  # a decoded RGB image goes straight into the same BOX resize
        return area_resize_image(frame, hw)
    return area_resize(frame, hw)


def decode_image_bytes(data: bytes, out_hw: tuple[int, int], name: str,
                       max_pixels: int = DEFAULT_MAX_PIXELS) -> np.ndarray:
    """A JPEG or PNG held in memory (a request body's image) as uint8 RGB [H, W, 3], area-resized to
    out_hw exactly as decode_still does a file; MediaError naming `name` for anything else."""
    hw = check_out_hw(out_hw)
    if not data:
        raise MediaError(f"{name}: empty image (0 bytes)")
    fmt = sniff_bytes(data[:SNIFF_BYTES])
    if fmt not in ("jpeg", "png"):
        raise MediaError(f"{name}: not a JPEG or PNG image (its first bytes match {fmt or 'no known format'})")
    frame = read_image(io.BytesIO(data), fmt, name, hw, "rgb", max_pixels)
    return area_resize_image(frame, hw) if isinstance(frame, Image.Image) else area_resize(frame, hw)
