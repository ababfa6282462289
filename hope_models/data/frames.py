"""Frame files a step references: resolving their URIs inside the episode, and the float rule.

A step's observation may reference its camera frame instead of holding it inline, e.g.

    "media": {"rgb": {"uri": "blobs/step_000012_rgb.npy", "width": 64, "height": 64,
                      "format": "npy_uint8_hwc"}}

Which references are cameras, and reading them, is cameras.py (decoding is hope_models.media).
URIs are resolved against the episode's blob root (`Episode.blob_root`, the episode dir for
episode dirs); a URI with a scheme, an absolute path, `..` that leaves the root or a symlink that
points out of it is refused with `BlobFrameError`, whose message names the URI and the file; the
cache turns it into an excluded episode with the step and field.
"""
from __future__ import annotations

import os
import posixpath
import re
from pathlib import Path

import numpy as np

from hope_models.media import MediaError
from hope_models.media import floats_to_uint8 as media_floats_to_uint8

_SCHEME = re.compile(r"^[A-Za-z][A-Za-z0-9+.\-]+:")  # two letters at least: not a drive letter


class BlobFrameError(ValueError):
    """A frame blob cannot be used; the message names the URI and, once resolved, the file."""


def resolve_blob_uri(uri: str, blob_root: str | os.PathLike | None) -> Path:
    """The local file a URI names inside the blob root (relative to it, or an absolute path inside
    it), or BlobFrameError saying why not."""
    if not isinstance(uri, str) or not uri:
        raise BlobFrameError(f"blob uri {uri!r} is not a non-empty string")
    if _SCHEME.match(uri):
        raise BlobFrameError(f"blob uri {uri!r} has a scheme; only paths relative to the episode dir are read")
    norm = uri.replace("\\", "/")
    if norm.startswith("/") or os.path.isabs(uri):
        # A recorder that writes absolute paths (the Pi's camera_episode_recorder names its JPEGs
        # out_dir/<id>_blobs/<frame>.jpg) is read when the path lies inside the episode's own dir.
        if blob_root is not None and os.path.isabs(uri):
            real, root_real = os.path.realpath(uri), os.path.realpath(blob_root)
            if real.startswith(root_real + os.sep):
                return Path(real)
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


def floats_to_uint8(raw: np.ndarray) -> np.ndarray:
    """hope_models.media's float rule (rint(x * 255) of values in [0, 1]), raising BlobFrameError
    as the callers of this module expect."""
    try:
        return media_floats_to_uint8(raw)
    except MediaError as exc:
        raise BlobFrameError(str(exc)) from None
