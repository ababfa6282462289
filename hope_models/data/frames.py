"""Image frames stored as blob files: finding the references, resolving them, loading them safely.

A step's observation may reference its camera frame instead of holding it inline, e.g.

    "media": {"rgb": {"uri": "blobs/step_000012_rgb.npy", "width": 64, "height": 64,
                      "format": "npy_uint8_hwc"}}

or `"rgb_front": {"uri": "..."}`: any observation object with a `uri` naming a `.npy` file. The
file holds one frame, uint8 [H, W, 3], or float32 in [0, 1] (turned into uint8 exactly as the
inline `image_rgb` floats are). Files are read with np.load(allow_pickle=False) only, after their
header has been checked (shape, dtype, no Python objects) and their size guarded.

URIs are resolved against the episode's blob root (`Episode.blob_root`, the episode dir for
episode dirs); a URI with a scheme, an absolute path, `..` that leaves the root or a symlink that
points out of it is refused. This module raises `BlobFrameError` with a message that names the
URI and the file; the cache turns it into an excluded episode with the step and field.
"""
from __future__ import annotations

import math
import os
import posixpath
import re
from pathlib import Path
from typing import Any

import numpy as np

from hope_models.media import MediaError
from hope_models.media import floats_to_uint8 as media_floats_to_uint8

FRAME_BLOB_SUFFIX = ".npy"
_NPY_MAGIC = b"\x93NUMPY"
_NPY_HEADER_ALLOWANCE = 1 << 20  # a .npy header is at most 4 GiB in theory, a few hundred bytes in practice
_SCHEME = re.compile(r"^[A-Za-z][A-Za-z0-9+.\-]+:")  # two letters at least: not a drive letter
# Blob references whose name says they are not a colour image (a depth map, a waveform, ...).
_NOT_RGB = ("depth", "audio", "segment", "mask", "normal", "flow", "lidar", "point", "thermal", "ir")


class BlobFrameError(ValueError):
    """A frame blob cannot be used; the message names the URI and, once resolved, the file."""


# -- references in an observation ---------------------------------------------------------------

def frame_blob_uri(value: Any) -> str | None:
    """The URI of a frame reference (an object with a `uri`, or the URI string itself), else None."""
    if isinstance(value, dict):
        value = value.get("uri")
    return value if isinstance(value, str) and value else None


def frame_blob_refs(observation: Any, prefix: str = "observation",
                    shape: tuple[int, int, int] = (64, 64, 3)) -> dict[str, str]:
    """Dotted path -> URI of every object in the observation that references a `.npy` colour frame.

    Skipped: URIs not ending in .npy, names that say depth/audio/mask/..., and blocks whose
    declared width/height/channels disagree with `shape` (the file itself is checked on load).
    """
    out: dict[str, str] = {}
    if not isinstance(observation, dict):
        return out
    for key, value in observation.items():
        if not isinstance(key, str) or not isinstance(value, dict):
            continue
        path = f"{prefix}.{key}"
        if "uri" not in value:
            out.update(frame_blob_refs(value, path, shape))
            continue
        uri = frame_blob_uri(value)
        if uri is None or not uri.lower().endswith(FRAME_BLOB_SUFFIX):
            continue
        if any(word in key.lower() for word in _NOT_RGB):
            continue
        declared = {"height": shape[0], "width": shape[1], "channels": shape[2]}
        if any(isinstance(value.get(k), int) and value[k] != n for k, n in declared.items()):
            continue
        out[path] = uri
    return out


# -- resolving ------------------------------------------------------------------------------------

def resolve_blob_uri(uri: str, blob_root: str | os.PathLike | None) -> Path:
    """The local file a relative URI names inside the blob root, or BlobFrameError saying why not."""
    if not isinstance(uri, str) or not uri:
        raise BlobFrameError(f"blob uri {uri!r} is not a non-empty string")
    if _SCHEME.match(uri):
        raise BlobFrameError(f"blob uri {uri!r} has a scheme; only paths relative to the episode dir are read")
    norm = uri.replace("\\", "/")
    if norm.startswith("/") or os.path.isabs(uri):
        raise BlobFrameError(f"blob uri {uri!r} is an absolute path; only paths inside the episode dir are read")
    rel = posixpath.normpath(norm)
    if rel == ".." or rel.startswith("../"):
        raise BlobFrameError(f"blob uri {uri!r} escapes the episode dir (..)")
    if blob_root is None:
        raise BlobFrameError(f"blob uri {uri!r} is relative but the episode has no dir to resolve it against")
    root = Path(blob_root)
    local = root / rel
    # A symlink inside the episode dir can still point anywhere; only the real path counts.
    if not os.path.realpath(local).startswith(os.path.realpath(root) + os.sep):
        raise BlobFrameError(f"blob uri {uri!r} escapes the episode dir ({local} resolves outside {root})")
    return local


# -- loading --------------------------------------------------------------------------------------

def _check_header(f, shape: tuple[int, ...], where: str) -> np.dtype:
    if f.read(len(_NPY_MAGIC)) != _NPY_MAGIC:
        raise BlobFrameError(f"{where}: not a .npy file (no NUMPY magic)")
    f.seek(0)
    try:
        version = np.lib.format.read_magic(f)
        if version == (1, 0):
            file_shape, _fortran, dtype = np.lib.format.read_array_header_1_0(f)
        elif version in ((2, 0), (3, 0)):
            file_shape, _fortran, dtype = np.lib.format.read_array_header_2_0(f)
        else:
            raise BlobFrameError(f"{where}: unsupported .npy version {version}")
    except BlobFrameError:
        raise
    except Exception as exc:  # untrusted bytes: numpy's header parser raises tokenize errors too
        raise BlobFrameError(f"{where}: unreadable .npy header: {type(exc).__name__}: {exc}") from None
    if dtype.hasobject:
        raise BlobFrameError(f"{where}: holds Python objects (dtype {dtype}); loading it would need pickle, "
                             "which is refused")
    if not (dtype == np.uint8 or (dtype.kind == "f" and dtype.itemsize == 4)):
        raise BlobFrameError(f"{where}: dtype {dtype}, expected uint8 or float32 in [0, 1]")
    if tuple(file_shape) != tuple(shape):
        raise BlobFrameError(f"{where}: shape {list(file_shape)}, expected {list(shape)}")
    return dtype


def load_frame_blob(path: str | os.PathLike, shape: tuple[int, int, int], uri: str | None = None) -> np.ndarray:
    """One frame file as uint8 [H, W, 3], or BlobFrameError naming the file and what is wrong."""
    path = Path(path)
    where = f"blob {uri!r} ({path})" if uri is not None else str(path)
    try:
        size = path.stat().st_size
    except FileNotFoundError:
        raise BlobFrameError(f"{where}: file not found") from None
    except OSError as exc:
        raise BlobFrameError(f"{where}: unreadable: {exc.strerror or exc}") from None
    if not path.is_file():
        raise BlobFrameError(f"{where}: not a regular file")
    limit = math.prod(shape) * 4 + _NPY_HEADER_ALLOWANCE
    if size > limit:
        raise BlobFrameError(f"{where}: {size} bytes, too large for one {list(shape)} frame")
    try:
        with open(path, "rb") as f:
            dtype = _check_header(f, shape, where)
            f.seek(0)
            arr = np.load(f, allow_pickle=False)
    except BlobFrameError:
        raise
    except Exception as exc:  # untrusted bytes: whatever numpy raises means "not a usable frame"
        raise BlobFrameError(f"{where}: unreadable: {type(exc).__name__}: {exc}") from None
    if not isinstance(arr, np.ndarray) or arr.shape != tuple(shape) or arr.dtype != dtype:
        raise BlobFrameError(f"{where}: did not load as a {list(shape)} array")
    if arr.dtype == np.uint8:
        return np.ascontiguousarray(arr)
    try:
        return floats_to_uint8(arr.astype(np.float32, copy=False))
    except BlobFrameError as exc:
        raise BlobFrameError(f"{where}: {exc}") from None


def floats_to_uint8(raw: np.ndarray) -> np.ndarray:
    """hope_models.media's float rule (rint(x * 255) of values in [0, 1]), raising BlobFrameError
    as the callers of this module expect."""
    try:
        return media_floats_to_uint8(raw)
    except MediaError as exc:
        raise BlobFrameError(str(exc)) from None
