"""A full disk: how to recognise it, how to say it, and how much room a job needs. No torch here.

An SD card fills up. A write that hits ENOSPC (or EDQUOT) must not end a job as "failed" with a
traceback: every writer in the project writes atomically (durable.py, checkpoint.py), so the
previous checkpoint and every committed registry row survive, and the job stops as "paused_disk"
(contract.OUTCOME_EXIT_CODES) with a message naming the path and the free space. The daemon
refuses to dispatch a job while the free space under $HOPE_HOME is below a floor
(`dispatch_floor_mb`), so a paused job does not start again only to fill the card once more.
"""
from __future__ import annotations

import errno
import os
import shutil
from pathlib import Path

FULL_ERRNOS = frozenset({errno.ENOSPC, errno.EDQUOT})
# SQLite says SQLITE_FULL this way ("database or disk is full"); sqlalchemy wraps it.
_SQLITE_FULL = "database or disk is full"
# What the floor adds to the checkpoints' room: metrics, logs, the registry's WAL, a dataset cache.
FLOOR_MARGIN_MB = 200.0
MB = 1024 * 1024


def is_disk_full(exc: BaseException | None) -> bool:
    """True for ENOSPC/EDQUOT anywhere in an exception's chain, and SQLite's SQLITE_FULL."""
    seen = set()
    while exc is not None and id(exc) not in seen:
        seen.add(id(exc))
        if isinstance(exc, OSError) and exc.errno in FULL_ERRNOS:
            return True
        if _SQLITE_FULL in str(exc):
            return True
        exc = getattr(exc, "orig", None) or exc.__cause__ or exc.__context__
    return False


def free_mb(path: str | os.PathLike) -> float | None:
    """Free space (MB) for an unprivileged writer on the filesystem holding `path` (its nearest
    existing parent if it does not exist yet); None when even that cannot be read."""
    p = Path(path).absolute()
    while not p.exists() and p != p.parent:
        p = p.parent
    try:
        return shutil.disk_usage(p).free / MB
    except OSError:
        return None


def full_message(exc: BaseException, fallback: str | os.PathLike, what: str = "write") -> str:
    """'no space left ...: <path> (N MB free ...)': the path the write named, else `fallback`."""
    path = getattr(exc, "filename", None) or fallback
    free = free_mb(path)
    room = f"{free:.1f} MB free" if free is not None else "free space unknown"
    return (f"no space left on the device: {what} to {path} failed ({room} there): "
            f"{getattr(exc, 'strerror', None) or exc}; free some space (or prune old runs) and resume")


def dispatch_floor_mb(checkpoint_mb: float, keep_last: int, setting_mb: float = 0.0) -> float:
    """Free space a job needs before it starts: the setting when one is given (> 0), else the
    job's checkpoint size x (keep_last + 2) (the kept ones, the one being written, and the
    pointer/temp slack) + FLOOR_MARGIN_MB."""
    if setting_mb > 0:
        return float(setting_mb)
    return checkpoint_mb * (max(int(keep_last), 1) + 2) + FLOOR_MARGIN_MB


__all__ = ["FLOOR_MARGIN_MB", "FULL_ERRNOS", "dispatch_floor_mb", "free_mb", "full_message", "is_disk_full"]
