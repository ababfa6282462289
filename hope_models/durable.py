"""Small helpers for files that must survive a crash or be checked byte for byte.

A rename is only durable once the directory holding it is fsynced; every atomic writer in the
project (ingest, the cache, checkpoints) ends with `fsync_path(parent)` for that reason.
"""
from __future__ import annotations

import hashlib
import os


def fsync_path(path: str | os.PathLike) -> None:
    """fsync a file or a directory (a directory fsync makes the renames inside it durable)."""
    fd = os.open(path, os.O_RDONLY)
    try:
        os.fsync(fd)
    finally:
        os.close(fd)


def file_sha256(path: str | os.PathLike) -> str:
    digest = hashlib.sha256()
    with open(path, "rb") as f:
        for chunk in iter(lambda: f.read(1 << 20), b""):
            digest.update(chunk)
    return digest.hexdigest()
