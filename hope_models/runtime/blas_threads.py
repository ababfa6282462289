"""NumPy's BLAS limited to one thread in the serving process, at run time, without an environment variable.

BrainService's products are tiny ([256, 8] x [8, 256] and smaller): OpenBLAS splitting them over
threads only makes them wait for each other, and on a loaded 2-core machine the frame answer took
36 ms p50 with OpenBLAS's default (a thread per core) against 2.3 ms with one (docs/benchmarks.md,
section 6). OPENBLAS_NUM_THREADS=1 would do it only if set before NumPy loads, and every child
(the worker, a job's trainer) would inherit it, while they train with torch and choose their own
threads (torch on aarch64 may itself use an OpenBLAS). So the library NumPy has already loaded is
found in /proc/self/maps, opened with ctypes (RTLD_NOLOAD: never a second copy) and told directly;
the count is read back through its getter, and what was done is returned and logged, never assumed.

No OpenBLAS found (another BLAS, a platform without /proc) is logged once at INFO and left alone:
this is a speed setting, not a correctness one.
"""
from __future__ import annotations

import ctypes
import logging
import os
import sys
from dataclasses import dataclass
from pathlib import Path
from typing import Callable

import numpy as np

log = logging.getLogger(__name__)

# A constant, not a Settings field: one thread is right for every model BrainService serves (their
# products are far below the size where threads pay), and the serving commands would have to
# thread a setting through four constructors for a value nobody should change.
SERVING_BLAS_THREADS = 1

# (set, get) pairs by the prefixes and suffixes OpenBLAS builds export: numpy's scipy-openblas64
# wheels, scipy-openblas32, an ILP64 build with the 64_ suffix, a plain distribution build.
SYMBOLS = (("scipy_openblas_set_num_threads64_", "scipy_openblas_get_num_threads64_"),
           ("scipy_openblas_set_num_threads", "scipy_openblas_get_num_threads"),
           ("openblas_set_num_threads64_", "openblas_get_num_threads64_"),
           ("openblas_set_num_threads", "openblas_get_num_threads"))

_logged: set[str] = set()


@dataclass(frozen=True)
class BlasThreads:
    """What limit_numpy_blas_threads did: the library and its symbol, the count before and after
    (read back through its getter), or None where nothing was found; `note` says it in words."""
    library: str | None
    symbol: str | None
    before: int | None
    after: int | None
    note: str


@dataclass(frozen=True)
class OpenBlas:
    """An OpenBLAS already loaded in this process, with its thread-count functions."""
    path: str
    set_symbol: str
    set_threads: Callable[[int], None]
    get_threads: Callable[[], int]

    def threads(self) -> int:
        return int(self.get_threads())


def mapped_openblas(maps: Path = Path("/proc/self/maps")) -> list[str] | None:
    """The files whose name holds "openblas" mapped into this process, in order; None without /proc."""
    try:
        text = maps.read_text()
    except OSError:
        return None
    found: list[str] = []
    for line in text.splitlines():
        parts = line.split(None, 5)
        if len(parts) < 6 or parts[5].endswith("(deleted)"):
            continue
        path = parts[5].strip()
        if "openblas" in os.path.basename(path).lower() and path not in found:
            found.append(path)
    return found


def numpys(paths: list[str]) -> list[str]:
    """Those of paths that are NumPy's: its wheel's own (numpy.libs/, numpy/), else a system OpenBLAS
    (a distribution's NumPy links one), never torch's (a process serving NumPy should not carry torch,
    but if one does, its threads are torch's business)."""
    root = Path(np.__file__).resolve().parent
    own = tuple(f"{root}{suffix}{os.sep}" for suffix in ("", ".libs"))
    wheel = [p for p in paths if p.startswith(own)]
    if wheel:
        return wheel
    return [p for p in paths if not any(f"{os.sep}{d}{os.sep}" in p for d in ("torch", "torch.libs"))]


def open_openblas(path: str) -> OpenBlas | None:
    """The loaded library at path with a set/get pair it exports, or None."""
    try:
        lib = ctypes.CDLL(path, mode=getattr(os, "RTLD_NOLOAD", 0))
    except OSError:
        return None
    for set_name, get_name in SYMBOLS:
        set_threads, get_threads = getattr(lib, set_name, None), getattr(lib, get_name, None)
        if set_threads is not None and get_threads is not None:
            set_threads.argtypes, set_threads.restype = [ctypes.c_int], None
            get_threads.argtypes, get_threads.restype = [], ctypes.c_int
            return OpenBlas(path, set_name, set_threads, get_threads)
    return None


def numpy_openblas() -> OpenBlas | str:
    """NumPy's loaded OpenBLAS, or a sentence saying why there is none to use."""
    paths = mapped_openblas()
    if paths is None:
        return f"no /proc/self/maps on {sys.platform}; NumPy's BLAS is {_blas_name()}"
    candidates = numpys(paths)
    if not candidates:
        return f"no OpenBLAS of NumPy's mapped (NumPy's BLAS is {_blas_name()}; mapped: {paths or 'none'})"
    if len(candidates) > 1:
        return f"more than one OpenBLAS mapped, none known to be NumPy's: {candidates}"
    return open_openblas(candidates[0]) or f"{candidates[0]} exports none of the thread-count functions"


def limit_numpy_blas_threads(threads: int = SERVING_BLAS_THREADS) -> BlasThreads:
    """Tell NumPy's loaded OpenBLAS to use `threads`, for this process only (no environment
    variable: children keep their own defaults). Returns what was done; logs it once at INFO."""
    if threads < 1:
        raise ValueError(f"threads={threads} must be >= 1")
    found = numpy_openblas()
    if not isinstance(found, OpenBlas):
        result = BlasThreads(None, None, None, None, f"BLAS threads left as they are: {found}")
    else:
        before = found.threads()
        if before != threads:
            found.set_threads(threads)
        after = found.threads()
        if after == threads:
            note = (f"NumPy's OpenBLAS ({found.path}) at {threads} thread(s)"
                    + ("" if before == threads else f", was {before}"))
        else:
            note = f"NumPy's OpenBLAS ({found.path}) still at {after} thread(s) after asking for {threads}"
        result = BlasThreads(found.path, found.set_symbol, before, after, note)
    key = result.note.split(", was ")[0]  # a second BrainService in the process says nothing new
    if key not in _logged:
        _logged.add(key)
        log.info("%s", result.note)
    return result


def _blas_name() -> str:
    try:
        blas = np.show_config(mode="dicts")["Build Dependencies"]["blas"]
        return f"{blas.get('name', 'unknown')} {blas.get('version', '')}".strip()
    except Exception:  # an older NumPy without mode="dicts": the name is for the log only
        return "unknown"
