"""One frame in a .npy file: the header checked first, then the array read once, never unpickled.

Accepted: uint8 colour [H, W, 3] (or [H, W, 4]: the alpha is dropped; [H, W] or [H, W, 1]: grey,
repeated to three channels), float32 colour in [0, 1], uint16 depth in millimetres and float32
depth in metres ([H, W] or [H, W, 1]). The channel order is taken as RGB: the file does not say,
and guessing BGR from the pixels would be wrong as often as right.
"""
from __future__ import annotations

import numpy as np

from hope_models.media.errors import MediaError, check_pixels
from hope_models.media.info import FrameInfo
from hope_models.media.pixels import checked_metres, floats_to_uint8, millimetres_to_metres

_NPY_MAGIC = b"\x93NUMPY"
ACCEPTED_DTYPES = ("uint8", "uint16", "float32")
_ACCEPTED_TEXT = "uint8 (colour), uint16 (depth, mm) or float32 (colour in [0, 1] or depth in m)"


class NpyHeader:
    """What a .npy header declares: shape, dtype, byte order, where the data starts."""

    def __init__(self, shape: tuple[int, ...], dtype: np.dtype, fortran: bool, offset: int):
        self.shape, self.dtype, self.fortran, self.offset = shape, dtype, fortran, offset


def read_header(f, name: str) -> NpyHeader:
    """The header of an open .npy file, or MediaError: not a .npy, unreadable, or Python objects."""
    if f.read(len(_NPY_MAGIC)) != _NPY_MAGIC:
        raise MediaError(f"{name}: not a .npy file (no NUMPY magic)")
    f.seek(0)
    try:
        version = np.lib.format.read_magic(f)
        if version == (1, 0):
            shape, fortran, dtype = np.lib.format.read_array_header_1_0(f)
        elif version in ((2, 0), (3, 0)):
            shape, fortran, dtype = np.lib.format.read_array_header_2_0(f)
        else:
            raise MediaError(f"{name}: unsupported .npy version {version}")
    except MediaError:
        raise
    except Exception as exc:  # untrusted bytes: numpy's header parser raises tokenize errors too
        raise MediaError(f"{name}: unreadable .npy header: {type(exc).__name__}: {exc}") from None
    if dtype.hasobject:
        raise MediaError(f"{name}: holds Python objects (dtype {dtype}); loading it would need pickle, which is refused")
    return NpyHeader(tuple(int(n) for n in shape), dtype, bool(fortran), f.tell())


def _frame_shape(header: NpyHeader, name: str, max_pixels: int) -> tuple[int, int, int]:
    if header.dtype.name not in ACCEPTED_DTYPES:  # the name ignores byte order: >u2 is uint16
        raise MediaError(f"{name}: dtype {header.dtype} is not a frame; accepted: {_ACCEPTED_TEXT}")
    shape = header.shape
    if len(shape) == 2:
        shape = (*shape, 1)
    if len(shape) != 3 or shape[2] not in (1, 3, 4):
        raise MediaError(f"{name}: shape {list(header.shape)} is not one frame; expected [H, W], [H, W, 1], "
                         "[H, W, 3] or [H, W, 4]")
    check_pixels(shape[0], shape[1], max_pixels, f".npy shape {list(header.shape)}", name)
    return shape[0], shape[1], shape[2]


def probe_npy(f, name: str, max_pixels: int) -> FrameInfo:
    header = read_header(f, name)
    height, width, channels = _frame_shape(header, name, max_pixels)
    return FrameInfo("NPY", height, width, channels, header.dtype.name)


def load_npy(f, size: int, name: str, kind: str, max_pixels: int) -> np.ndarray:
    """The frame of an open .npy file: uint8 [H, W, 3] for kind "rgb", float32 metres [H, W, 1] for "depth"."""
    header = read_header(f, name)
    height, width, channels = _frame_shape(header, name, max_pixels)
    expected = header.offset + height * width * channels * header.dtype.itemsize
    if size != expected:
        raise MediaError(f"{name}: {size} bytes, the header declares {expected} "
                         f"({list(header.shape)} {header.dtype}): {'truncated' if size < expected else 'trailing bytes'}")
    # read once, right after the header already parsed (np.load would parse it again)
    data = f.read(expected - header.offset)
    if len(data) != expected - header.offset:
        raise MediaError(f"{name}: truncated while reading ({len(data)} of {expected - header.offset} data bytes)")
    arr = np.frombuffer(data, dtype=header.dtype).reshape((height, width, channels),
                                                          order="F" if header.fortran else "C")
    arr = arr.astype(header.dtype.newbyteorder("="), copy=False)
    try:
        if kind == "depth":
            if channels != 1 or arr.dtype == np.uint8:
                raise MediaError(f"{arr.dtype} {list(header.shape)} is not a depth image; expected uint16 "
                                 "millimetres or float32 metres, [H, W] or [H, W, 1]")
            return millimetres_to_metres(arr[:, :, 0]) if arr.dtype == np.uint16 else checked_metres(arr[:, :, 0])
        if arr.dtype == np.uint16:
            raise MediaError("uint16 is depth (millimetres), not colour; decode it with kind='depth'")
        if arr.dtype == np.float32:
            arr = floats_to_uint8(arr)
    except MediaError as exc:
        raise MediaError(f"{name}: {exc}") from None
    if channels == 1:
        return np.repeat(arr, 3, axis=2)
    return np.ascontiguousarray(arr[:, :, :3])  # [H, W, 4]: the alpha is dropped
