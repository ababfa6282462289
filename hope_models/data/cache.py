"""A dataset compiled once into memory-mapped arrays, keyed by a content fingerprint: load_or_build.

Training reads windows from these arrays instead of JSON, so its memory does not grow with the
dataset. The cache dir is named by sha256(dataset file paths + contents, the spec request, the
cache format), so it is reused while the data is unchanged and rebuilt when any file changes.
Building is cache_build.py, reading (and the layout on disk) dataset_cache.py.
"""
from __future__ import annotations

import hashlib
import os
import shutil
import time
from dataclasses import dataclass, field
from pathlib import Path

from hope_models.data.cache_build import build_cache
from hope_models.data.dataset_cache import (
    CACHE_FORMAT,
    DEFAULT_RESIDENT_BUDGET_MB,
    CacheError,
    DatasetCache,
    open_cache,
)
from hope_models.data.spec_request import SpecRequest


def data_fingerprint(dataset_dir: Path, skip: Path | None = None) -> str:
    """sha256 over every file's relative path, size and contents (sorted; hidden entries skipped)."""
    h = hashlib.sha256()
    root = Path(dataset_dir)
    files = []
    for dirpath, dirnames, filenames in os.walk(root):
        d = Path(dirpath)
        dirnames[:] = sorted(n for n in dirnames if not n.startswith(".") and (skip is None or d / n != skip))
        files.extend(d / n for n in filenames if not n.startswith("."))
    for path in sorted(files, key=lambda p: p.relative_to(root).as_posix()):
        rel = path.relative_to(root).as_posix().encode("utf-8")
        size = path.stat().st_size
        h.update(len(rel).to_bytes(4, "little") + rel + size.to_bytes(8, "little"))
        with open(path, "rb") as f:
            while chunk := f.read(1 << 20):
                h.update(chunk)
    return h.hexdigest()


def cache_key(data_fp: str, request: SpecRequest) -> str:
    h = hashlib.sha256()
    for part in (CACHE_FORMAT, data_fp, request.identity()):
        h.update(part.encode("utf-8") + b"\0")
    return h.hexdigest()[:32]


@dataclass
class CacheInfo:
    path: Path
    fingerprint: str  # the cache key: data + spec request + format
    data_fingerprint: str
    reused: bool
    build_seconds: float  # of this call's build (0 when reused); the original is in the manifest
    fingerprint_seconds: float
    notes: list[str] = field(default_factory=list)


def _spec_request(spec_path: str | Path | None) -> SpecRequest:
    return SpecRequest() if spec_path is None else SpecRequest.load(spec_path)


def load_or_build(dataset_dir: str | Path, cache_root: str | Path, spec_path: str | Path | None = None,
                  request: SpecRequest | None = None,
                  resident_budget_mb: float = DEFAULT_RESIDENT_BUDGET_MB) -> tuple[DatasetCache, CacheInfo]:
    """Open the cache of this dataset + spec, building it first if the data changed or it never existed."""
    dataset = Path(dataset_dir).resolve()
    root = Path(cache_root).resolve()
    if not dataset.is_dir():
        raise CacheError(f"{dataset}: dataset dir not found")
    if request is None:
        request = _spec_request(spec_path)
    started = time.perf_counter()
    skip = root if root.is_relative_to(dataset) else None
    data_fp = data_fingerprint(dataset, skip)
    key = cache_key(data_fp, request)
    fp_seconds = time.perf_counter() - started
    final = root / key
    notes: list[str] = []
    if final.is_dir():
        try:
            return open_cache(final, resident_budget_mb), CacheInfo(final, key, data_fp, True, 0.0, fp_seconds)
        except CacheError as exc:  # damaged (disk trouble, manual edits): rebuild it, say so
            notes.append(f"rebuilt a damaged cache: {exc}")
            shutil.rmtree(final, ignore_errors=True)
    t0 = time.perf_counter()
    build_cache(dataset, root, key, data_fp, request, skip)
    build_s = time.perf_counter() - t0
    return open_cache(final, resident_budget_mb), CacheInfo(final, key, data_fp, False, build_s, fp_seconds, notes)
