"""Fewer malloc arenas for the long-lived service processes (serve, webapp, daemon, the inference door).

glibc gives threads their own malloc arenas, up to eight per core. A threaded server starts a thread
per connection, so under a flood of requests its heap spreads over many arenas whose freed memory is
rarely handed back: in the soak, serve's RSS climbed ~70 MB in three minutes with no Python object
kept (tracemalloc showed none); with two arenas it stayed within ~15 MB (docs/benchmarks.md). Set in
the process itself rather than through MALLOC_ARENA_MAX, so a training child (torch, intra-op
threads) keeps glibc's default. Call it first thing, before threads start.
"""
from __future__ import annotations

import ctypes
import logging

log = logging.getLogger(__name__)

M_ARENA_MAX = -8  # glibc's mallopt parameter
SERVICE_ARENAS = 2


def limit_malloc_arenas(arenas: int = SERVICE_ARENAS) -> bool:
    """mallopt(M_ARENA_MAX, arenas); False where there is no glibc (musl, macOS): nothing changes."""
    try:
        mallopt = ctypes.CDLL(None).mallopt
    except (OSError, AttributeError):
        return False
    mallopt.argtypes = (ctypes.c_int, ctypes.c_int)
    mallopt.restype = ctypes.c_int
    return mallopt(M_ARENA_MAX, int(arenas)) == 1


__all__ = ["SERVICE_ARENAS", "limit_malloc_arenas"]
