"""Small helpers for files that must survive a crash or be checked byte for byte.

A rename is only durable once the directory holding it is fsynced; every atomic writer in the
project (ingest, the cache, checkpoints) ends with `fsync_path(parent)` for that reason.

`atomic_write` / `atomic_open` are the one way to replace a single file: write a hidden temp file
in the same dir, flush + fsync it, `os.replace` it onto the target, fsync the dir. A reader sees the
old file or the new one, never half of one, even across a power cut; on an error (or an exception
raised inside `atomic_open`) the temp file is removed and the old file is left as it was.
"""
from __future__ import annotations

import ctypes
import functools
import hashlib
import os
from contextlib import contextmanager
from pathlib import Path
from typing import IO, Iterator


def fsync_path(path: str | os.PathLike) -> None:
    """fsync a file or a directory (a directory fsync makes the renames inside it durable)."""
    fd = os.open(path, os.O_RDONLY)
    try:
        os.fsync(fd)
    finally:
        os.close(fd)


def fsync_files(paths: list[Path], anchor: str | os.PathLike) -> None:
    """Make many new files' data durable: one syncfs(2) of the file system `anchor` is on where
    Linux offers it (8,000 small files cost one flush, not 8,000 fsyncs: on an SD card each
    fsync waits for the card), else one fsync each."""
    if len(paths) > 1 and _syncfs(anchor):
        return
    for path in paths:
        fsync_path(path)


def _syncfs(anchor: str | os.PathLike) -> bool:
    libc = _libc()
    if libc is None or not hasattr(libc, "syncfs"):
        return False
    fd = os.open(anchor, os.O_RDONLY)
    try:
        return libc.syncfs(fd) == 0
    finally:
        os.close(fd)


@functools.lru_cache(maxsize=1)
def _libc() -> ctypes.CDLL | None:
    try:
        return ctypes.CDLL(None, use_errno=True)
    except OSError:
        return None


def file_sha256(path: str | os.PathLike) -> str:
    digest = hashlib.sha256()
    with open(path, "rb") as f:
        for chunk in iter(lambda: f.read(1 << 20), b""):
            digest.update(chunk)
    return digest.hexdigest()


def _temp_name(path: Path) -> Path:
    # hidden (discover and the cache pass over dot-files) and named after the target, so
    # `.last.tmp-*` still matches checkpoint.clean_temp
    return path.with_name(f".{path.name}.tmp-{os.getpid()}-{os.urandom(4).hex()}")


@contextmanager
def atomic_open(path: str | os.PathLike, mode: str = "wb", *, perms: int = 0o666) -> Iterator[IO]:
    """`with atomic_open(path, "wb") as f:` for a writer that streams; the file appears at `path`
    only when the block ends without an exception. mode is "wb" or "w" (UTF-8, "\n" newlines).
    perms go through the umask exactly as open() does, so a file's mode is what open() gave it."""
    if mode not in ("wb", "w"):
        raise ValueError(f"atomic_open: mode must be 'wb' or 'w', not {mode!r}")
    path = Path(path)
    tmp = _temp_name(path)
    fd = os.open(tmp, os.O_WRONLY | os.O_CREAT | os.O_EXCL | os.O_NOFOLLOW | os.O_CLOEXEC, perms)
    try:
        text = mode == "w"
        with os.fdopen(fd, mode, encoding="utf-8" if text else None, newline="\n" if text else None) as f:
            fd = -1  # the file object owns it now
            yield f
            f.flush()
            os.fsync(f.fileno())
        os.replace(tmp, path)
    except BaseException:
        if fd >= 0:
            os.close(fd)
        tmp.unlink(missing_ok=True)
        raise
    fsync_path(path.parent)


def atomic_write(path: str | os.PathLike, data: bytes | str, *, perms: int = 0o666) -> None:
    """Replace `path` with `data` (a str is written as UTF-8) atomically and durably."""
    if isinstance(data, str):
        data = data.encode("utf-8")
    with atomic_open(path, "wb", perms=perms) as f:
        f.write(data)
