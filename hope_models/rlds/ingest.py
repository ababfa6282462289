"""Ingest: bring episodes from any layout into one canonical dataset dir, once.

Each episode is validated with the train profile; rejected ones are not written, only listed in
the dataset manifest with their reasons. The manifest (<dataset>/manifest.json) records every
episode's content hash, which is what makes ingest idempotent: the same input finds its hash and
writes nothing, and a different episode whose id is taken gets the deterministic suffix
`-<first 8 hex of its content hash>`. The manifest holds no timestamps, so a re-run with the same
input leaves it byte-identical (and untouched on disk). Keys other callers add to an episode's
record (the inbox's `trainable`, `tags`, ...) are kept when the manifest is rewritten.

Content hashes are key-order independent (write_episode_dir.py); a record written before that
holds the legacy hash, so an episode not found by its hash is looked for by its legacy one and
its record moves to the new hash (`hash_version` 2), with nothing written twice.

Every ingest holds an exclusive flock on the dataset dir itself while it reads, writes and
rewrites the manifest (`dataset_lock`), so two ingests into one dataset from different processes
(the command line, the app's handoff, an upload) never lose each other's records. The dir, not a
lock file in it: a dataset holds its episodes and its manifest and nothing else.

`ingest_reports(..., confined=True)` is for episodes that came over the network: their blob URIs
are followed only inside their own dir (write_episode_dir.confine_blobs); `content_ids` names
each episode `<prefix><first 16 hex of its content hash>` (episodes that carry no id of their own).
"""
from __future__ import annotations

import fcntl
import json
import os
import re
from contextlib import contextmanager
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Iterable, Iterator

from ..disk import full_message, is_disk_full
from ..durable import atomic_write
from .episode import Episode, SourceReport
from .inflate import BudgetError
from .json_text import json_dumps
from .validation_report import exception_entry, read_reports, report_entries, unique_paths
from .write_episode_dir import (
    PreparedEpisode,
    confine_blobs,
    prepare_episode,
    remove_stale_tmp_dirs,
    safe_episode_id,
    write_prepared,
)

MANIFEST = "manifest.json"
MANIFEST_FORMAT = "hope-rlds-dataset"
HASH_VERSION = 2  # content_sha256 over sorted keys; records without it hold the legacy hash


class IngestError(Exception):
    """The dataset dir cannot be ingested into (e.g. its manifest is not ours or is corrupt)."""


class IngestDiskFull(IngestError):
    """A write hit ENOSPC/EDQUOT: no episode is rejected for it; what was written is in the
    manifest (when that still fits) and a re-run after freeing space goes on from there."""


@dataclass
class Manifest:
    episodes: dict[str, dict[str, Any]] = field(default_factory=dict)  # by episode id
    rejected: dict[str, dict[str, Any]] = field(default_factory=dict)  # by source
    skipped: dict[str, dict[str, Any]] = field(default_factory=dict)  # by source

    def __post_init__(self) -> None:
        self._by_hash = {e["content_sha256"]: eid for eid, e in self.episodes.items()}
        self._legacy = {e["content_sha256"]: eid for eid, e in self.episodes.items()
                        if e.get("hash_version") != HASH_VERSION}

    def id_of(self, content_sha256: str) -> str | None:
        return self._by_hash.get(content_sha256)

    def id_of_prepared(self, prepared: PreparedEpisode) -> str | None:
        """The id this content is recorded under, by its hash or (a record from before sorted
        keys) by its legacy hash; a legacy record found is moved to the new hash."""
        known = self.id_of(prepared.content_sha256)
        if known is not None or not self._legacy:
            return known
        legacy = prepared.legacy_content_sha256()
        episode_id = self._legacy.pop(legacy, None) if legacy else None
        if episode_id is None:
            return None
        record = self.episodes[episode_id]
        self._by_hash.pop(record["content_sha256"], None)
        record.update(content_sha256=prepared.content_sha256, hash_version=HASH_VERSION)
        self._by_hash.setdefault(prepared.content_sha256, episode_id)
        return episode_id

    def add(self, record: dict[str, Any]) -> None:
        self.episodes[record["episode_id"]] = record
        self._by_hash.setdefault(record["content_sha256"], record["episode_id"])

    def to_json(self) -> dict[str, Any]:
        episodes = [self.episodes[k] for k in sorted(self.episodes)]
        return {
            "format": MANIFEST_FORMAT,
            "counts": {
                "episodes": len(episodes),
                "steps": sum(e["steps"] for e in episodes),
                "imagined": sum(1 for e in episodes if e["imagined"]),
                "rejected": len(self.rejected),
                "skipped": len(self.skipped),
            },
            "episodes": episodes,
            "rejected": [self.rejected[k] for k in sorted(self.rejected)],
            "skipped": [self.skipped[k] for k in sorted(self.skipped)],
        }

    def text(self) -> str:
        return json_dumps(self.to_json(), indent=2, sort_keys=True) + "\n"


def load_manifest(dataset_dir: Path) -> Manifest:
    path = dataset_dir / MANIFEST
    if not path.exists():
        return Manifest()
    try:
        raw = json.loads(path.read_text(encoding="utf-8"))
        if raw.get("format") != MANIFEST_FORMAT:
            raise ValueError(f"format is {raw.get('format')!r}, expected {MANIFEST_FORMAT!r}")
        # An episode dir deleted by hand is no longer in the dataset.
        return Manifest(
            episodes={e["episode_id"]: e for e in raw["episodes"]
                      if (dataset_dir / e["episode_id"]).is_dir()},
            rejected={e["source"]: e for e in raw["rejected"]},
            skipped={e["source"]: e for e in raw["skipped"]},
        )
    except (ValueError, KeyError, TypeError, AttributeError) as exc:
        raise IngestError(f"{path}: not a dataset manifest this tool can update: {exc}") from None


def write_manifest(dataset_dir: Path, manifest: Manifest) -> bool:
    """Writes only when the text changed, so a re-run leaves even the mtime alone."""
    path = dataset_dir / MANIFEST
    text = manifest.text()
    if path.exists() and path.read_text(encoding="utf-8") == text:
        return False
    atomic_write(path, text)
    return True


def _holds(existing_dir: Path, prepared: PreparedEpisode) -> bool:
    """Whether a dir that is not in the manifest (a run that crashed before writing the manifest)
    already holds this content."""
    for report in read_reports(existing_dir):
        for ep in report.episodes:
            if prepare_episode(ep).content_sha256 == prepared.content_sha256:
                return True
    return False


def _place(ep: Episode, prepared: PreparedEpisode, dataset_dir: Path,
           manifest: Manifest) -> tuple[str, bool]:
    """The id this episode gets and whether it still has to be written."""
    known = manifest.id_of_prepared(prepared)
    if known is not None:
        return known, False
    base = safe_episode_id(ep.episode_id)
    digest = prepared.content_sha256
    for candidate in (base, f"{base}-{digest[:8]}", f"{base}-{digest[:16]}", f"{base}-{digest}"):
        if candidate in manifest.episodes:
            continue  # taken by a different content (same content was found by hash above)
        target = dataset_dir / candidate
        if not target.exists():
            return candidate, True
        if target.is_dir() and _holds(target, prepared):
            return candidate, False
    raise IngestError(f"{ep.source}: no free episode id for {ep.episode_id!r} in {dataset_dir}")


def _ingest_episode(ep: Episode, entry: dict[str, Any], dataset_dir: Path,
                    manifest: Manifest, content_ids: str | None = None) -> dict[str, Any]:
    prepared = prepare_episode(ep)
    if content_ids is not None:
        ep.episode_id = prepared.episode_id = f"{content_ids}{prepared.content_sha256[:16]}"
        ep.metadata["episode_id"] = prepared.metadata["episode_id"] = ep.episode_id
    episode_id, needs_write = _place(ep, prepared, dataset_dir, manifest)
    if needs_write:
        write_prepared(prepared, dataset_dir, episode_id)
        action = "written"
    else:
        known = manifest.episodes.get(episode_id)
        original_id = known.get("source_episode_id", episode_id) if known else ep.episode_id
        # "duplicate": this content is already in the dataset, ingested under another id
        action = "unchanged" if original_id == ep.episode_id else "duplicate"
    if episode_id not in manifest.episodes:
        record = {"episode_id": episode_id, "source": ep.source, "steps": len(ep.steps),
                  "content_sha256": prepared.content_sha256, "hash_version": HASH_VERSION,
                  "imagined": ep.is_imagined}
        if episode_id != ep.episode_id:
            record["source_episode_id"] = ep.episode_id
        manifest.add(record)
    manifest.rejected.pop(ep.source, None)
    manifest.skipped.pop(ep.source, None)
    return dict(entry, episode_id=episode_id, action=action)


def ingest_paths(paths: Iterable[str | os.PathLike], dataset_dir: str | os.PathLike, *,
                 confined: bool = False, locked: bool = False, sources_as: tuple[str, str] | None = None,
                 **reader_options: Any) -> dict[str, Any]:
    """Ingests every episode under `paths` into `dataset_dir`; returns what happened to each.

    `sources_as` = (a dir, its name): sources under a dir that is gone after this call (an upload
    extracted to a temp dir) are recorded, and reported, under that name instead.
    Raises FileNotFoundError for a missing input path and IngestError for an unusable dataset dir."""
    sources = [Path(os.path.abspath(p)) for p in unique_paths(paths)]
    for source in sources:
        if not source.exists():
            raise FileNotFoundError(f"{source}: no such file or directory")
    reports = (report for source in sources for report in read_reports(source, **reader_options))
    return ingest_reports(reports, dataset_dir, confined=confined, locked=locked, sources_as=sources_as)


@contextmanager
def dataset_lock(dataset_dir: str | os.PathLike) -> Iterator[Path]:
    """The dataset dir (created), held exclusively until the block ends; the kernel drops the lock
    when its holder dies. Not re-entrant: a holder calls ingest_reports(..., locked=True)."""
    dataset = Path(os.path.abspath(dataset_dir))
    if dataset.exists() and not dataset.is_dir():
        raise IngestError(f"{dataset}: exists and is not a directory")
    dataset.mkdir(parents=True, exist_ok=True)
    fd = os.open(dataset, os.O_RDONLY | os.O_DIRECTORY)  # flock(2) locks a directory as well as a file
    try:
        fcntl.flock(fd, fcntl.LOCK_EX)
        yield dataset
    finally:
        os.close(fd)


def ingest_reports(reports: Iterable[SourceReport], dataset_dir: str | os.PathLike, *,
                   confined: bool = False, content_ids: str | None = None,
                   locked: bool = False, sources_as: tuple[str, str] | None = None) -> dict[str, Any]:
    """`ingest_paths` for reports already read (or built in memory, like the app's handoff).
    `locked`: the caller holds dataset_lock already."""
    if not locked:
        with dataset_lock(dataset_dir) as dataset:
            return ingest_reports(reports, dataset, confined=confined, content_ids=content_ids, locked=True,
                                  sources_as=sources_as)
    dataset = Path(os.path.abspath(dataset_dir))
    remove_stale_tmp_dirs(dataset)
    manifest = load_manifest(dataset)
    results: list[dict[str, Any]] = []
    try:
        _ingest_each(reports, dataset, manifest, results, confined, content_ids)
    except BudgetError:  # an upload refused mid-way: what it placed is recorded before it goes
        if sources_as is not None:
            _rename_sources(manifest, results, *sources_as)
        _save_what_fits(dataset, manifest)
        raise
    if sources_as is not None:
        results = _rename_sources(manifest, results, *sources_as)
    manifest_written = write_manifest(dataset, manifest)
    summary = {action: sum(1 for r in results if r["action"] == action)
               for action in ("written", "unchanged", "duplicate", "rejected", "skipped")}
    summary["ok"] = summary["rejected"] == 0
    summary["manifest_written"] = manifest_written
    return {"dataset": str(dataset), "episodes": results, "summary": summary}


def _ingest_each(reports: Iterable[SourceReport], dataset: Path, manifest: Manifest, results: list[dict[str, Any]],
                 confined: bool, content_ids: str | None) -> None:
    """Each report's episodes validated and placed (or recorded as unwritten), results appended."""
    for report in reports:
        if confined:
            for ep in report.episodes:
                confine_blobs(ep)  # before validation: it must not look at outside files either
        entries = report_entries(report, "train")
        if not report.episodes:
            results.extend(_record_unwritten(entry, manifest) for entry in entries)
            continue
        for ep, entry in zip(report.episodes, entries, strict=True):
            if entry["status"] == "rejected":
                results.append(_record_unwritten(entry, manifest))
                continue
            try:
                results.append(_ingest_episode(ep, entry, dataset, manifest, content_ids))
            except OSError as exc:
                if is_disk_full(exc):  # the card, not the episode: stop, keep what is done
                    _save_what_fits(dataset, manifest)
                    raise IngestDiskFull(full_message(exc, dataset, f"ingest of {ep.source}")) from None
                results.append(_record_unwritten(exception_entry(ep.source, exc, ep.episode_id), manifest))
            except (ValueError, TypeError) as exc:  # unwritable content
                results.append(_record_unwritten(exception_entry(ep.source, exc, ep.episode_id), manifest))


def _rename_sources(manifest: Manifest, results: list[dict[str, Any]], root: str,
                    name: str) -> list[dict[str, Any]]:
    """Every mention of `root` (sources, reasons, warnings) in the results and the manifest as `name`."""
    root = os.path.abspath(root).rstrip(os.sep)
    pattern = re.compile(re.escape(root) + r"(?=/|\b|$)")

    def text(value: Any) -> Any:
        if isinstance(value, str):
            return pattern.sub(lambda _m: name, value)
        if isinstance(value, list):
            return [text(v) for v in value]
        if isinstance(value, dict):
            return {k: text(v) for k, v in value.items()}
        return value

    for record in manifest.episodes.values():
        record["source"] = text(record.get("source"))
    manifest.rejected = {text(k): text(v) for k, v in manifest.rejected.items()}
    manifest.skipped = {text(k): text(v) for k, v in manifest.skipped.items()}
    return [text(r) for r in results]


def _save_what_fits(dataset: Path, manifest: Manifest) -> None:
    try:
        write_manifest(dataset, manifest)
    except OSError as exc:  # atomic: the previous manifest stays; a re-run ingests those episodes again
        if not is_disk_full(exc):
            raise


def _record_unwritten(entry: dict[str, Any], manifest: Manifest) -> dict[str, Any]:
    if entry["status"] == "skipped":
        reason = (entry["warnings"] or [entry["source"] + ": skipped"])[0]
        manifest.skipped[entry["source"]] = {"source": entry["source"], "reason": reason}
        return dict(entry, action="skipped")
    manifest.rejected[entry["source"]] = {"source": entry["source"], "episode_id": entry["episode_id"],
                                          "reasons": entry["errors"]}
    return dict(entry, action="rejected")
