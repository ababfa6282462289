"""A camera frame in a BrainService request, checked and turned into the uint8 [H, W, 3] the served
frame VQ-VAE reads. Torch-free.

A request's `frame` is one of:

    "<base64 of a JPEG or PNG>"            (a `data:image/...;base64,` prefix is allowed)
    {"encoding": "jpeg" | "png", "data": "<base64>"}
    {"encoding": "raw", "shape": [H, W, 3], "data": "<base64 of H*W*3 uint8 bytes, row-major RGB>"}
    [[[r, g, b], ...], ...]                (nested lists of integers 0-255, H x W x 3)

A JPEG or PNG may be any size up to MAX_IMAGE_PIXELS: it is decoded and area-resized to the model's
frame exactly as the training cache resized the frames it learnt from (hope_models.media). A raw
array carries no size of its own to trust, so it must be the model's frame size already. Anything
else is a BrainError(400) that says what is wrong: not an image, a truncated one, a declared size
above the limit (refused before decoding), the wrong shape, values outside 0-255.
"""
from __future__ import annotations

import base64
import binascii
import math
from typing import Any

import numpy as np

from hope_models.media import MediaError, decode_image_bytes
from hope_models.runtime.brain_input import BrainError

MAX_IMAGE_PIXELS = 16_000_000  # a 4K camera frame is 8.3 MP; a larger declared size is refused unread
MAX_FRAME_CHARS = 8 << 20  # base64 characters of one frame (6 MiB of image)
ENCODINGS = ("jpeg", "png", "raw")


def _b64(data: Any, where: str) -> bytes:
    if not isinstance(data, str):
        raise BrainError(f"{where}: expected a base64 string, got {type(data).__name__}")
    if len(data) > MAX_FRAME_CHARS:
        raise BrainError(f"{where}: {len(data)} characters; a frame may have at most {MAX_FRAME_CHARS}")
    if data.startswith("data:"):
        head, _, data = data.partition(",")
        if not head.endswith(";base64"):
            raise BrainError(f"{where}: a data: URL must be base64 (data:image/jpeg;base64,...)")
    try:
        return base64.b64decode(data, validate=True)
    except (binascii.Error, ValueError):
        raise BrainError(f"{where}: not valid base64") from None


def _image(data: bytes, shape: tuple[int, int, int], where: str) -> np.ndarray:
    try:
        return decode_image_bytes(data, shape[:2], where, max_pixels=MAX_IMAGE_PIXELS)
    except MediaError as exc:
        raise BrainError(str(exc)) from None


def _raw(obj: dict, shape: tuple[int, int, int], where: str) -> np.ndarray:
    got = obj.get("shape")
    if (not isinstance(got, list) or len(got) != 3
            or not all(isinstance(n, int) and not isinstance(n, bool) for n in got)):
        raise BrainError(f"{where}.shape: expected [height, width, 3], got {got!r}")
    if tuple(got) != shape:
        raise BrainError(f"{where}.shape: {got}, the served tokenizer reads {list(shape)} frames "
                         "(send a JPEG or PNG to have it resized)")
    data = _b64(obj.get("data"), f"{where}.data")
    if len(data) != math.prod(shape):
        raise BrainError(f"{where}.data: {len(data)} bytes, a {list(shape)} uint8 frame has {math.prod(shape)}")
    return np.frombuffer(data, dtype=np.uint8).reshape(shape).copy()


def _lists(value: list, shape: tuple[int, int, int], where: str) -> np.ndarray:
    h, w, c = shape
    if len(value) != h:  # checked before numpy sees it: a huge list is refused without a copy
        raise BrainError(f"{where}: {len(value)} rows, the served tokenizer reads {list(shape)} frames")
    try:
        arr = np.asarray(value)
    except (ValueError, TypeError):
        raise BrainError(f"{where}: not a regular [height][width][3] array of integers") from None
    if arr.shape != shape:
        raise BrainError(f"{where}: shape {list(arr.shape)}, the served tokenizer reads {list(shape)} frames")
    if arr.dtype.kind not in "iu":
        raise BrainError(f"{where}: values must be integers 0-255, got {arr.dtype}")
    if arr.min() < 0 or arr.max() > 255:
        raise BrainError(f"{where}: values must be within 0-255, got {int(arr.min())}..{int(arr.max())}")
    return arr.astype(np.uint8)


def frame_from_request(value: Any, shape: tuple[int, int, int], where: str = "frame") -> np.ndarray:
    """The request's camera frame as uint8 [H, W, 3] of `shape` (the served tokenizer's), or
    BrainError(400) naming what is wrong."""
    shape = (int(shape[0]), int(shape[1]), int(shape[2]))
    if isinstance(value, str):
        return _image(_b64(value, where), shape, where)
    if isinstance(value, dict):
        encoding = value.get("encoding")
        if encoding not in ENCODINGS:
            raise BrainError(f"{where}.encoding: expected one of {', '.join(ENCODINGS)}, got {encoding!r}")
        unknown = set(value) - {"encoding", "data", "shape"}
        if unknown:
            raise BrainError(f"{where}: unknown keys {sorted(unknown)}")
        if encoding == "raw":
            return _raw(value, shape, where)
        return _image(_b64(value.get("data"), f"{where}.data"), shape, where)
    if isinstance(value, list):
        return _lists(value, shape, where)
    raise BrainError(f"{where}: expected a base64 JPEG/PNG string, an object with encoding and data, or "
                     f"[height][width][3] integer lists; got {type(value).__name__}")
