"""Walk a dataset dir one episode source at a time, so no pass ever holds the whole dataset.

`discover.read_path(dataset_dir)` would return every episode of the dataset at once; the spec
inference and the cache build instead hand it one episode dir (or loose episode file) at a time
and drop the episodes before reading the next, which keeps their memory flat in dataset size.
The walk follows discover's own rules (same episode-dir test, same manifest and file-kind
filters), so it finds exactly the sources `read_path(dataset_dir)` would.
"""
from __future__ import annotations

import os
from collections.abc import Iterator
from pathlib import Path

from hope_models.rlds.discover import is_episode_dir, is_manifest, kind_from_name, read_path
from hope_models.rlds.episode import SourceReport


def iter_sources(dataset_dir: Path, skip: Path | None = None) -> Iterator[Path]:
    """Episode dirs and loose episode files under dataset_dir, in name order.

    `skip` is a directory to leave out (a cache kept inside the dataset dir).
    """
    if is_episode_dir(dataset_dir):
        yield dataset_dir
        return
    for entry in sorted(os.scandir(dataset_dir), key=lambda e: e.name):
        path = Path(entry.path)
        if entry.name.startswith(".") or (skip is not None and path == skip):
            continue
        if entry.is_dir(follow_symlinks=False):
            yield from iter_sources(path, skip)
        elif entry.is_file() and not is_manifest(entry.name) and kind_from_name(entry.name) is not None:
            yield path


def read_source(path: Path, max_file_bytes: int | None = None, max_line_bytes: int | None = None) -> list[SourceReport]:
    """All episodes of one source (usually one), read by discover.read_path."""
    limits = {k: v for k, v in (("max_file_bytes", max_file_bytes), ("max_line_bytes", max_line_bytes)) if v}
    return read_path(path, **limits)
