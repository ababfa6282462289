"""Find the episodes under a path and read each with the reader for its layout.

One SourceReport per episode source: an episode dir, a single-JSON file, a steps-only JSONL, a
TFRecord (any name with `.tfrecord`; gzip is detected by the reader from the bytes), an MCAP or
ContinuonCloud's `.npz` (read with its `.npz.json` sidecar, which is never an episode itself).
Directories are walked recursively in name order. Manifests and metadata files are never
episodes; hidden entries (`.git`, the ingest writer's `.tmp-*` dirs) and half-written
`*.partial`/`*.tmp` files are passed over; other files (`.npy`, `.wav`, `.md`, ...) are ignored.
A file given explicitly with an unknown extension is identified from its content.
"""
from __future__ import annotations

import json
import os
from pathlib import Path
from typing import Callable, Iterable, Iterator

from .episode import ERROR, WARNING, Problem, SourceReport
from .inflate import Budget, BudgetError, InflateError
from .json_text import (
    DEFAULT_MAX_FILE_BYTES,
    DEFAULT_MAX_LINE_BYTES,
    ReadLimits,
    TextReadError,
    decode_text,
    read_bytes,
)
from .read_episode_dir import LEGACY_STEPS_FILE, METADATA_FILE, read_episode_dir, step_files
from .read_mcap import read_mcap
from .read_npz import NPZ_SUFFIX, SIDECAR_SUFFIX, read_npz
from .read_single_json import read_single_json
from .read_steps_jsonl import read_steps_jsonl
from .read_tfrecord import GZIP_MAGIC, read_tfrecord, valid_record_at

Reader = Callable[[Path, ReadLimits], SourceReport]

# Files that describe episodes or datasets but are not episodes themselves.
NOT_EPISODES = {METADATA_FILE, "upload_manifest.json", "manifest.json", "dataset.json", "dataset_manifest.json",
                "feature_spec.json", "features.json", "ingest_report.json", "validation.json"}
NOT_EPISODE_SUFFIXES = (".validation.json", "_manifest.json", ".manifest.json", SIDECAR_SUFFIX)
UNFINISHED_SUFFIXES = (".partial", ".tmp")
EPISODE_DIR_PARTS = {METADATA_FILE, "steps", LEGACY_STEPS_FILE, "blobs"}  # consumed by the dir reader
MCAP_MAGIC = b"\x89MCAP0\r\n"

READERS: dict[str, Reader] = {
    "json": read_single_json,
    "jsonl": read_steps_jsonl,
    "tfrecord": read_tfrecord,
    "mcap": read_mcap,
    "npz": read_npz,
}


def is_manifest(name: str) -> bool:
    lower = name.lower()
    return lower in NOT_EPISODES or lower.endswith(NOT_EPISODE_SUFFIXES)


def kind_from_name(name: str) -> str | None:
    lower = name.lower()
    if lower.endswith(UNFINISHED_SUFFIXES):
        return None
    if lower.endswith(".mcap"):
        return "mcap"
    if lower.endswith(NPZ_SUFFIX):
        return "npz"
    if ".tfrecord" in lower:  # x.tfrecord, x.tfrecord.gz, x.tfrecords, x.tfrecord-00000-of-00004
        return "tfrecord"
    if lower.endswith(".jsonl"):
        return "jsonl"
    if lower.endswith(".json"):
        return "json"
    return None


def is_episode_dir(path: Path) -> bool:
    return (path / METADATA_FILE).is_file() or (path / LEGACY_STEPS_FILE).is_file() or bool(step_files(path))


def kind_from_content(file: Path, limits: ReadLimits) -> str | None:
    """For a file named explicitly with an unknown extension: what its bytes say it is."""
    try:
        data = read_bytes(file, limits)
    except TextReadError:
        return None
    if data.startswith(MCAP_MAGIC):
        return "mcap"
    if data.startswith(GZIP_MAGIC) or valid_record_at(data, 0) is not None:
        return "tfrecord"
    try:
        text = decode_text(data).lstrip()
    except TextReadError:
        return None
    if text.startswith("["):
        return "json"
    if text.startswith("{"):
        # one object per line is JSONL; one object over many lines is a single JSON document
        first, _, rest = text.partition("\n")
        try:
            json.loads(first)
        except ValueError:  # not JSON, or an integer too long for int(): the reader says which
            return "json"
        return "jsonl" if rest.strip() else "json"
    return None


def _safely(reader: Reader, path: Path, limits: ReadLimits) -> SourceReport:
    # Readers record bad data as problems; this only stops an unforeseen reader bug from
    # aborting a whole batch, and it reports the failure as an error for that path.
    if limits.budget is not None:
        limits.budget.check(str(path))
    try:
        return reader(path, limits)
    except BudgetError:
        raise  # the whole upload is refused, not this one file
    except InflateError as exc:
        if limits.budget is not None:
            raise BudgetError(exc.message, exc.status) from None
        return SourceReport(source=str(path), problems=[Problem(ERROR, str(path), exc.message)])
    except Exception as exc:  # noqa: BLE001
        return SourceReport(source=str(path), problems=[Problem(
            ERROR, str(path), f"reader failed: {type(exc).__name__}: {exc}")])


def _walk(directory: Path, limits: ReadLimits) -> Iterator[SourceReport]:
    if limits.budget is not None:
        limits.budget.check(str(directory))
    consumed: set[str] = set()
    if is_episode_dir(directory):
        yield _safely(read_episode_dir, directory, limits)
        consumed = EPISODE_DIR_PARTS
    try:
        entries = sorted(os.scandir(directory), key=lambda e: e.name)
    except OSError as exc:
        yield SourceReport(source=str(directory), problems=[Problem(
            ERROR, str(directory), f"cannot list directory: {exc.strerror or exc}")])
        return
    for entry in entries:
        name = entry.name
        if name.startswith(".") or name in consumed:
            continue
        path = Path(entry.path)
        if entry.is_dir(follow_symlinks=False):
            yield from _walk(path, limits)
        elif entry.is_file() and not is_manifest(name):
            kind = kind_from_name(name)
            if kind is not None:
                yield _safely(READERS[kind], path, limits)


def _iter_one(p: Path, limits: ReadLimits) -> Iterator[SourceReport]:
    if p.is_dir():
        yield from _walk(p, limits)
        return
    if not p.exists():
        yield SourceReport(source=str(p), problems=[Problem(ERROR, str(p), "no such file or directory")])
        return
    if p.name == METADATA_FILE:
        # Naming an episode's metadata file means the episode.
        yield _safely(read_episode_dir, p.parent, limits)
        return
    if p.name.endswith(SIDECAR_SUFFIX) and p.with_name(p.name[:-len(".json")]).is_file():
        # Naming an npz's sidecar means the npz.
        yield _safely(read_npz, p.with_name(p.name[:-len(".json")]), limits)
        return
    if is_manifest(p.name):
        yield SourceReport(source=str(p), skipped=True, skip_reason="a manifest, not an episode",
                           problems=[Problem(WARNING, str(p), "manifest/metadata file is not an episode; skipped")])
        return
    kind = kind_from_name(p.name) or kind_from_content(p, limits)
    if kind is None:
        yield SourceReport(source=str(p), problems=[Problem(
            ERROR, str(p), "not a recognised episode file (expected an episode dir, .json, .jsonl, "
                           "TFRecord, .mcap or .npz)")])
        return
    yield _safely(READERS[kind], p, limits)


def iter_reports(paths: Iterable[str | os.PathLike], *, max_file_bytes: int = DEFAULT_MAX_FILE_BYTES,
                 max_line_bytes: int = DEFAULT_MAX_LINE_BYTES, budget: Budget | None = None) -> Iterator[SourceReport]:
    """One SourceReport at a time, so a caller that drops each one keeps memory flat in dataset size.
    With an upload's `budget`, a decompression bomb or its deadline raises BudgetError."""
    limits = ReadLimits(max_file_bytes=max_file_bytes, max_line_bytes=max_line_bytes, budget=budget)
    seen: set[str] = set()
    for path in paths:
        key = os.path.realpath(path)
        if key in seen:
            continue
        seen.add(key)
        yield from _iter_one(Path(path), limits)


def read_path(path: str | os.PathLike, *, max_file_bytes: int = DEFAULT_MAX_FILE_BYTES,
              max_line_bytes: int = DEFAULT_MAX_LINE_BYTES) -> list[SourceReport]:
    return list(iter_reports([path], max_file_bytes=max_file_bytes, max_line_bytes=max_line_bytes))


def read_paths(paths: Iterable[str | os.PathLike], *, max_file_bytes: int = DEFAULT_MAX_FILE_BYTES,
               max_line_bytes: int = DEFAULT_MAX_LINE_BYTES) -> list[SourceReport]:
    return list(iter_reports(paths, max_file_bytes=max_file_bytes, max_line_bytes=max_line_bytes))
