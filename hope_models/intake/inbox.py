"""The inbox: the dataset dir episodes from outside land in (the app's handoff, uploads, `ingest`).

It is an ordinary canonical dataset (rlds/ingest.py: validated with the train profile, written
once, the manifest the record of every episode), with three differences:

* everything entering it is untrusted: blob URIs are followed only inside the episode's own dir
  (rlds/write_episode_dir.confine_blobs), so an absolute or `file://` URI is kept as text and no
  file of the trainer's is ever read for it;
* every change happens under an exclusive flock on the inbox dir (rlds/ingest.dataset_lock, the
  one every ingest takes, the `ingest` command's too): a handoff, an upload, a tag and `ingest`
  may run at once in different processes, and each one reads the manifest, changes it and writes
  it back whole;
* each episode's manifest record also says what it can train (`trainable`, `not_trainable`:
  intake/trainable.py), what each camera gives (`cameras`) and what the tokenizer reads (`reads`), its `tags`, its `origin` (who brought it: "app:episode_handoff",
  "upload", "cli:ingest", ...) and its `warnings` (the first WARNINGS_KEPT validation warnings).
  Tags live only in the manifest, never in the episode's content, so tagging changes neither its
  content hash nor what dedupes against it.

Tags are capped: MAX_TAG_CHARS each, MAX_TAGS_PER_REQUEST given at once, MAX_TAGS_PER_EPISODE
on one episode (an upload's tags past it are left out with a warning; `tag_episode` past it: 413).

InboxError carries the HTTP status a view answers with: 400 bad input, 404 unknown episode, 409
a dataset dir that is not ours, 413 an episode's tags full, 507 a full disk (what was written is kept).
"""
from __future__ import annotations

import os
import shutil
import uuid
from contextlib import contextmanager
from pathlib import Path
from typing import Any, Iterable, Iterator

from hope_models.intake.trainable import COMPONENTS, VERDICT_EXTRAS, trainable_json
from hope_models.rlds.app_record import AppRecordError, episode_from_record
from hope_models.rlds.ingest import (
    IngestDiskFull,
    IngestError,
    Manifest,
    dataset_lock,
    ingest_paths,
    ingest_reports,
    load_manifest,
    write_manifest,
)
from hope_models.rlds.read_episode_dir import read_episode_dir

STAGE_PREFIX = ".stage-"
MAX_TAG_CHARS = 64
# an episode's tags live in the inbox manifest, which every change rewrites whole: 30 uploads of
# ~900 tags each once grew it from 22 kB to 1.9 MB
MAX_TAGS_PER_EPISODE = 64
MAX_TAGS_PER_REQUEST = 16
WARNINGS_KEPT = 20
APP_IDS = "app-"
HANDOFF_ORIGIN = "app:episode_handoff"


class InboxError(Exception):
    def __init__(self, message: str, status: int = 400):
        super().__init__(message)
        self.message = message
        self.status = status


@contextmanager
def inbox_lock(inbox_dir: str | os.PathLike) -> Iterator[Path]:
    """The inbox dir (created), held exclusively (rlds/ingest.dataset_lock: the same lock the
    `ingest` command takes) until the block ends."""
    try:
        with dataset_lock(inbox_dir) as inbox:
            yield inbox
    except IngestError as exc:
        raise InboxError(str(exc), 409) from None


def check_tag(tag: Any, field: str = "tag") -> str:
    if not isinstance(tag, str) or not tag.strip():
        raise InboxError(f"{field}: expected a non-empty string")
    if len(tag) > MAX_TAG_CHARS:
        raise InboxError(f"{field}: {len(tag)} characters; at most {MAX_TAG_CHARS}")
    # a lone UTF-16 surrogate (half an emoji from Dart) is kept, escaped in the manifest like
    # everywhere else; a control character is refused
    if any(ord(c) < 32 or ord(c) == 127 for c in tag):
        raise InboxError(f"{field}: holds a control character")
    return tag


def _merge_tags(old: Any, new: Iterable[str]) -> tuple[list[str], list[str]]:
    """(the tags, at most MAX_TAGS_PER_EPISODE of them, and the new ones left out for want of room)."""
    tags = [t for t in old if isinstance(t, str)] if isinstance(old, list) else []
    fresh = [t for t in dict.fromkeys(new) if t not in tags]
    room = max(MAX_TAGS_PER_EPISODE - len(tags), 0)
    return tags + fresh[:room], fresh[room:]


def _annotate(inbox: Path, manifest: Manifest, entry: dict[str, Any], tags: list[str],
              origin: str) -> dict[str, Any]:
    """The manifest record of one ingest result gains what the inbox keeps; returns the entry
    with those keys."""
    if entry["action"] == "skipped":
        return entry
    if entry["action"] == "rejected":
        record = manifest.rejected.get(entry["source"])
        can: list[str] = []
        cannot = {c: "the episode was rejected" for c in COMPONENTS}
        seen: dict[str, Any] = {}
    else:
        record = manifest.episodes.get(entry["episode_id"])
        if record is None:  # pragma: no cover - ingest records every episode it places
            return entry
        verdict = _with_verdict(inbox, record)  # a known episode's verdict does not change
        can, cannot = verdict["trainable"], verdict["not_trainable"]
        seen = {k: verdict[k] for k in VERDICT_EXTRAS if k in verdict}
    if record is not None:
        record["trainable"], record["not_trainable"] = can, cannot
        record.update(seen)
        record["tags"], left_out = _merge_tags(record.get("tags"), tags)
        record.setdefault("origin", origin)
        if entry["action"] != "rejected":
            record.setdefault("warnings", list(entry.get("warnings", []))[:WARNINGS_KEPT])
        if left_out:
            entry = dict(entry, warnings=list(entry.get("warnings", [])) + [
                f"tags: {', '.join(map(repr, left_out))} not added: the episode holds {MAX_TAGS_PER_EPISODE} "
                f"tags, the most it may"])
    return dict(entry, trainable=can, not_trainable=cannot, **seen,
                tags=record.get("tags", tags) if record else tags,
                origin=record.get("origin", origin) if record else origin)


def _finish(inbox: Path, result: dict[str, Any], tags: list[str], origin: str) -> dict[str, Any]:
    manifest = load_manifest(inbox)
    result["episodes"] = [_annotate(inbox, manifest, e, tags, origin) for e in result["episodes"]]
    result["summary"]["manifest_written"] = write_manifest(inbox, manifest) or result["summary"]["manifest_written"]
    return result


def _ingest_errors(fn, *args, **kwargs) -> dict[str, Any]:
    try:
        return fn(*args, **kwargs)
    except FileNotFoundError as exc:
        raise InboxError(str(exc), 400) from None
    except IngestDiskFull as exc:
        raise InboxError(str(exc), 507) from None
    except IngestError as exc:
        raise InboxError(str(exc), 409) from None


def ingest_into_inbox(paths: Iterable[str | os.PathLike], inbox_dir: str | os.PathLike, *,
                      tags: Iterable[str] = (), origin: str, **reader_options: Any) -> dict[str, Any]:
    """ingest_paths into the inbox, blobs confined, under the lock; each episode's entry (and
    manifest record) gains trainable, not_trainable, tags and origin."""
    tags = [check_tag(t, f"tags[{i}]") for i, t in enumerate(tags)]
    if len(tags) > MAX_TAGS_PER_REQUEST:
        raise InboxError(f"tags: {len(tags)} of them; at most {MAX_TAGS_PER_REQUEST} at once")
    with inbox_lock(inbox_dir) as inbox:
        result = _ingest_errors(ingest_paths, list(paths), inbox, confined=True, locked=True, **reader_options)
        return _finish(inbox, result, tags, origin)


def _clear_stages(inbox: Path) -> None:
    # Called under the lock: a stage dir seen then belongs to a handoff that died mid-way.
    for entry in inbox.iterdir():
        if entry.name.startswith(STAGE_PREFIX) and entry.is_dir():
            shutil.rmtree(entry, ignore_errors=True)


def ingest_record(record: dict[str, Any], assets: list[dict[str, Any]], files: dict[str, Path],
                  inbox_dir: str | os.PathLike, *, origin: str = HANDOFF_ORIGIN) -> dict[str, Any]:
    """The app's EpisodeRecord (+ its assets and the files that came, by file name) into the inbox.

    Returns the episode's entry (as ingest_into_inbox's) plus `remote_uris`: local_uri -> the
    absolute path its file is stored at. Raises InboxError 400 for a record that is no episode
    (nothing written); a record validation rejects is listed in the manifest and answered with
    status "rejected"."""
    with inbox_lock(inbox_dir) as inbox:
        _clear_stages(inbox)
        stage = inbox / f"{STAGE_PREFIX}{uuid.uuid4().hex}"
        stage.mkdir()
        try:
            try:
                report = episode_from_record(record, assets, files, stage, origin=origin)
            except AppRecordError as exc:
                raise InboxError(str(exc), 400) from None
            result = _ingest_errors(ingest_reports, [report], inbox, confined=True, content_ids=APP_IDS,
                                    locked=True)
            result = _finish(inbox, result, [], origin)
        finally:
            shutil.rmtree(stage, ignore_errors=True)
    entry = dict(result["episodes"][0])
    remote: dict[str, str] = {}
    if entry["action"] != "rejected":
        for asset in report.episodes[0].metadata.get("assets", []):
            stored = inbox / entry["episode_id"] / asset["uri"] if "uri" in asset else None
            if stored is not None and stored.is_file():
                remote[asset["local_uri"]] = str(stored)
    entry["remote_uris"] = remote
    return entry


def _status(record: dict[str, Any]) -> str:
    return "warnings" if record.get("warnings") else "ok"


def list_inbox(inbox_dir: str | os.PathLike) -> list[dict[str, Any]]:
    """One entry per episode, accepted and rejected, in id order (rejected ones after)."""
    inbox = Path(os.path.abspath(inbox_dir))
    if not inbox.is_dir():
        return []
    try:
        manifest = load_manifest(inbox)
    except IngestError as exc:
        raise InboxError(str(exc), 409) from None
    out = [_entry(_with_verdict(inbox, r)) for _, r in sorted(manifest.episodes.items())]
    for _, r in sorted(manifest.rejected.items()):
        out.append({"episode_id": r.get("episode_id"), "steps": 0, "status": "rejected",
                    "errors": list(r.get("reasons", [])), "warnings": [], "trainable": [],
                    "not_trainable": {c: "the episode was rejected" for c in COMPONENTS},
                    "tags": list(r.get("tags", [])), "source": r.get("source"), "origin": r.get("origin")})
    return out


def _with_verdict(inbox: Path, record: dict[str, Any]) -> dict[str, Any]:
    """A record written by a plain ingest (the command line into the inbox dir) has no verdict yet:
    it is worked out here, for this answer (stored when an inbox ingest brings that episode again)."""
    if "trainable" in record:  # stored by an inbox ingest (one written before cameras has none)
        return record
    eps = read_episode_dir(inbox / record["episode_id"]).episodes
    if not eps:
        return dict(record, trainable=[], not_trainable={c: "unreadable" for c in COMPONENTS})
    return dict(record, **trainable_json(eps[0]))


def _entry(record: dict[str, Any]) -> dict[str, Any]:
    warnings = record.get("warnings", [])
    return {"episode_id": record["episode_id"], "steps": record.get("steps", 0), "status": _status(record),
            "errors": [], "warnings": warnings if isinstance(warnings, list) else [],
            "trainable": list(record.get("trainable", [])), "not_trainable": dict(record.get("not_trainable", {})),
            **{k: record[k] for k in VERDICT_EXTRAS if k in record},
            "tags": list(record.get("tags", [])), "source": record.get("source"), "origin": record.get("origin")}


def tag_episode(inbox_dir: str | os.PathLike, episode_id: Any, tag: Any) -> dict[str, Any]:
    """Adds `tag` (once) to an episode's manifest record; returns its list_inbox entry."""
    tag = check_tag(tag)
    if not isinstance(episode_id, str) or not episode_id:
        raise InboxError("episode_id: expected a non-empty string")
    with inbox_lock(inbox_dir) as inbox:
        try:
            manifest = load_manifest(inbox)
        except IngestError as exc:
            raise InboxError(str(exc), 409) from None
        record = manifest.episodes.get(episode_id)
        if record is None:
            raise InboxError(f"episode {episode_id!r} is not in the inbox", 404)
        record["tags"], left_out = _merge_tags(record.get("tags"), [tag])
        if left_out:
            raise InboxError(f"episode {episode_id!r} already holds {MAX_TAGS_PER_EPISODE} tags, the most it "
                             f"may; tag {tag!r} not added", 413)
        write_manifest(inbox, manifest)
        return _entry(record)
