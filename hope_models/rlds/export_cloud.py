"""Export to the Pi runtime's cloud upload package (FORMAT.md, "The Pi runtime's upload package").

<episode_id>.tar.gz holds <episode_id>/episode.json (single-JSON shape whose metadata carries
episode_id, robot_type, xr_mode, action_source and total_steps), the episode's relative blobs
under <episode_id>/blobs/, and <episode_id>/upload_manifest.json with the sha256 of every other
file. `metadata_checksum` is the sha256 of episode.json, as the Pi packager computes it.

Packages are byte-reproducible: tar entries carry the episode's start time, uid/gid 0 and fixed
modes, and the gzip header has no timestamp.
"""
from __future__ import annotations

import gzip
import hashlib
import io
import os
import tarfile
import time
from pathlib import Path
from typing import Any, Callable, Iterable

from ..durable import atomic_open
from .episode import Episode
from .json_text import json_bytes
from .validate import derive_action_source, robot_type
from .validation_report import exception_entry, read_reports, report_entries, unique_paths
from .write_episode_dir import prepare_episode, safe_episode_id

PACKAGE_VERSION = "1.0.0"
EPISODE_FILE = "episode.json"
UPLOAD_MANIFEST = "upload_manifest.json"


def created_timestamp_ns(metadata: dict[str, Any]) -> int:
    """The episode's start time when it has one (as the Pi packager uses), else now."""
    start_ns = metadata.get("start_timestamp_ns")
    if isinstance(start_ns, int) and not isinstance(start_ns, bool) and start_ns > 0:
        return start_ns
    start_ms = metadata.get("start_time_unix_ms")
    if isinstance(start_ms, (int, float)) and not isinstance(start_ms, bool) and start_ms > 0:
        return int(start_ms) * 1_000_000
    return time.time_ns()


def cloud_metadata(ep: Episode, canonical: dict[str, Any]) -> dict[str, Any]:
    """The canonical metadata plus the fields the upload path requires."""
    metadata = dict(canonical)
    metadata["robot_type"] = robot_type(ep.metadata)
    metadata["action_source"] = derive_action_source(ep)[0]
    metadata["total_steps"] = len(ep.steps)
    metadata.setdefault("xr_mode", None)
    return metadata


def _parent_dirs(names: Iterable[str]) -> list[str]:
    dirs = set()
    for name in names:
        for parent in Path(name).parents:
            if str(parent) != ".":
                dirs.add(parent.as_posix())
    return sorted(dirs)


def _tar_add(tar: tarfile.TarFile, name: str, data: bytes | None, mtime: int,
             source: Path | None = None) -> None:
    info = tarfile.TarInfo(name)
    info.mtime = mtime
    info.uid = info.gid = 0
    info.uname = info.gname = ""
    if data is None and source is None:
        info.type = tarfile.DIRTYPE
        info.mode = 0o755
        tar.addfile(info)
        return
    info.mode = 0o644
    if source is not None:
        info.size = source.stat().st_size
        with open(source, "rb") as f:
            tar.addfile(info, f)
    else:
        info.size = len(data or b"")
        tar.addfile(info, io.BytesIO(data or b""))


def export_episode(ep: Episode, out_dir: str | os.PathLike, created_ns: int | None = None,
                   episode_id: str | None = None) -> Path:
    """Writes <out_dir>/<episode_id>.tar.gz and returns its path. Does not validate: callers run
    the cloud profile first (`export_paths` does). Raises ValueError for content JSON cannot hold."""
    episode_id = safe_episode_id(episode_id or ep.episode_id)
    prepared = prepare_episode(ep, as_id=episode_id)
    metadata = cloud_metadata(ep, prepared.metadata)
    episode_json = json_bytes({"metadata": metadata, "steps": prepared.steps}, indent=2, allow_nan=False) + b"\n"
    checksums = {EPISODE_FILE: hashlib.sha256(episode_json).hexdigest()}
    checksums.update(prepared.blob_sha256)
    total_size = len(episode_json) + sum(p.stat().st_size for p in prepared.blobs.values())
    created = created_ns if created_ns is not None else created_timestamp_ns(ep.metadata)
    manifest = {
        "episode_id": episode_id,
        "total_steps": len(ep.steps),
        "robot_type": metadata["robot_type"],
        "xr_mode": metadata["xr_mode"],
        "action_source": metadata["action_source"],
        "created_timestamp_ns": created,
        "file_checksums": checksums,
        "metadata_checksum": checksums[EPISODE_FILE],
        "total_size_bytes": total_size,
        "version": PACKAGE_VERSION,
    }
    manifest_json = json_bytes(manifest, indent=2) + b"\n"

    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    final = out / f"{episode_id}.tar.gz"
    mtime = created // 1_000_000_000
    with atomic_open(final, "wb") as raw, gzip.GzipFile(fileobj=raw, mode="wb", mtime=0, filename="") as gz, \
            tarfile.open(fileobj=gz, mode="w", format=tarfile.PAX_FORMAT) as tar:
        _tar_add(tar, episode_id, None, mtime)
        _tar_add(tar, f"{episode_id}/{EPISODE_FILE}", episode_json, mtime)
        for directory in _parent_dirs(prepared.blobs):
            _tar_add(tar, f"{episode_id}/{directory}", None, mtime)
        for name, source in sorted(prepared.blobs.items()):
            _tar_add(tar, f"{episode_id}/{name}", None, mtime, source=source)
        _tar_add(tar, f"{episode_id}/{UPLOAD_MANIFEST}", manifest_json, mtime)
    return final


def export_each(paths: Iterable[str | os.PathLike], profile: str, allow_invalid: bool,
                export_one: Callable[[Episode, dict[str, Any], set[str]], dict[str, Any]],
                unwritten: dict[str, Any], **reader_options: Any) -> dict[str, Any]:
    """The walk every export makes: each episode under `paths` checked with `profile`, and those
    that pass (all with `allow_invalid`) handed to `export_one(ep, entry, used_ids)`, which returns
    its result; `unwritten` is what a refused or skipped result carries instead of file names."""
    paths = unique_paths(paths)
    for path in paths:
        if not path.exists():
            raise FileNotFoundError(f"{path}: no such file or directory")
    results: list[dict[str, Any]] = []
    used_ids: set[str] = set()
    for path in paths:
        for report in read_reports(path, **reader_options):
            entries = report_entries(report, profile)
            if not report.episodes:
                results.extend(dict(e, action="skipped" if e["status"] == "skipped" else "refused",
                                    **unwritten) for e in entries)
                continue
            for ep, entry in zip(report.episodes, entries, strict=True):
                if not entry["ok"] and not allow_invalid:
                    results.append(dict(entry, action="refused", **unwritten))
                    continue
                results.append(export_one(ep, entry, used_ids))
    summary = {action: sum(1 for r in results if r["action"] == action)
               for action in ("exported", "refused", "skipped")}
    summary["ok"] = summary["refused"] == 0
    return {"episodes": results, "summary": summary}


def export_paths(paths: Iterable[str | os.PathLike], out_dir: str | os.PathLike,
                 allow_invalid: bool = False, **reader_options: Any) -> dict[str, Any]:
    """Validates every episode under `paths` with the cloud profile and packages those that pass
    (all of them with `allow_invalid`, which still refuses content JSON cannot hold)."""

    def package_one(ep: Episode, entry: dict[str, Any], used_ids: set[str]) -> dict[str, Any]:
        try:
            episode_id = safe_episode_id(ep.episode_id)
            if episode_id in used_ids:
                # Two sources with one id would overwrite each other's package; the
                # second gets the same content-hash suffix ingest would give it.
                digest = prepare_episode(ep).content_sha256
                episode_id = f"{episode_id}-{digest[:8]}"
                entry = dict(entry, warnings=entry["warnings"] + [
                    f"{ep.source}: metadata.episode_id: {ep.episode_id!r} was already exported "
                    f"in this run; packaged as {episode_id!r}"])
            package = export_episode(ep, out_dir, episode_id=episode_id)
            used_ids.add(episode_id)
            return dict(entry, action="exported", package=str(package))
        except (OSError, ValueError, TypeError) as exc:
            failed = exception_entry(ep.source, exc, ep.episode_id)
            return dict(failed, action="refused", package=None, warnings=entry["warnings"])

    return export_each(paths, "cloud", allow_invalid, package_one, {"package": None}, **reader_options)
