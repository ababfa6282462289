"""Episodes: package uploads, the inbox and its tags (the Robot Editor's Episodes page and the app's calls).

    POST /api/episodes/upload     a package as the raw body (how the producers send it) or as
                                  multipart file part(s) named `file` (a browser's drag-and-drop),
                                  up to settings.upload_max_mb (webapp/uploads.py)
    GET  /api/episodes            the Editor's table: {"episodes": [...], "inbox", "upload_max_mb"}
    GET  /api/v1/data/episodes    the Continuon app's list: {"episodes": [...]}
    POST /api/v1/data/tag         JSON {"episode_id", "tag"} -> {"success": true, "episode": {...}}

The two package kinds (hope_models/rlds/upload_package.py tells them apart by their bytes): the
Pi runtime's `<episode_id>.tar.gz` (checksums of its upload_manifest.json verified) and the XR
app's zip of an episode dir, which it POSTs with `Content-Type: application/zip` and the headers
X-Continuon-Tag-xr_mode / -control_role / -environment_id (also in its metadata.json, so not
repeated as tags) and X-Continuon-Tag-list (comma-separated: each one becomes an inbox tag, as
does each of a multipart `tags` field). Every package of a request is extracted to
$HOPE_HOME/tmp/package-<sha of its bytes> (one upload at a time extracts and ingests; removed
after) before any is ingested, so one refused package (400 naming the member, 413 too large,
507 no room in $HOPE_HOME/tmp) means nothing is written at all. Extracting and reading share one
budget (rlds/inflate.Budget: 200 times the bytes sent may be inflated by the compressed data
inside the packages' files as they are read, in upload_extract_s plus SECONDS_PER_MB per MB sent
and per MB a package unpacks to); a package unpacks to at most upload_unpack_max_mb (never past
the room in $HOPE_HOME/tmp) and holds at most upload_max_members members (413 naming the file and
the cap, found by a streaming pass that writes nothing, so a bomb never fills the disk); a bomb found while
reading is a 413 naming the file, and episodes of the request ingested before it stay (sent
again, they are answered "unchanged"). Accepted ones go into the
inbox (hope_models/data/inbox.py: validated with the train profile, blobs confined to the episode's
own dir, idempotent); the answer lists each episode's verdict: 200 {"packages": [{"name", "kind",
"episodes": [{"episode_id", "action", "status", "errors", "warnings", "steps", "trainable",
"not_trainable", "cameras", "reads"?, "tags", "origin", "source"}]}], "summary"}. A package with no episode in it is a
400. An episode validation rejects is listed (status "rejected", its errors) like the others.

A list entry is hope_models/data/inbox.list_inbox's: {"episode_id", "steps", "status" (ok |
warnings | rejected), "errors", "warnings", "trainable", "not_trainable" ({component: why}),
"tags", "source", "origin"}.
"""
from __future__ import annotations

import fcntl
import logging
import os
import re
import shutil
import uuid
from contextlib import contextmanager
from pathlib import Path
from typing import Any, Iterator

from flask import Blueprint, current_app, jsonify, request

from hope_models.durable import file_sha256
from hope_models.intake.inbox import (
    MAX_TAGS_PER_REQUEST,
    InboxError,
    check_tag,
    ingest_into_inbox,
    list_inbox,
    tag_episode,
)
from hope_models.intake.trainable import verdict_fields
from hope_models.rlds.inflate import Budget, InflateError, ratio_limit
from hope_models.rlds.upload_package import KINDS, PackageError, extract_upload
from webapp.api.validation import get_str, json_body, query_args
from webapp.errors import ApiError
from webapp.uploads import TMP_DIR, Received, TmpRoom, large_body, received

log = logging.getLogger(__name__)
bp = Blueprint("episodes", __name__)

FILE_PART = "file"
TAG_LIST_HEADER = "X-Continuon-Tag-list"
MAX_PACKAGES = 20  # one drop of a browser; more is a client gone wrong
# ingest's verdicts in the words of the inbox's list (and of the app's handoff answer)
STATUS = {"accepted": "ok", "accepted_with_warnings": "warnings"}
EXTRACTED = "package-"
# time to unpack, read and ingest a MB sent, on top of upload_extract_s: a big real package is
# written twice (tmp, then the inbox) to an SD card at ~10 MB/s; a small bomb gets the base only
SECONDS_PER_MB = 0.5


def _split_tags(text: str, where: str) -> list[str]:
    tags: list[str] = []
    for i, tag in enumerate(t.strip() for t in text.split(",")):
        if tag:
            try:
                tags.append(check_tag(tag, f"{where}[{i}]"))
            except InboxError as exc:
                raise ApiError(exc.message, exc.status) from None
            if len(tags) > MAX_TAGS_PER_REQUEST:
                raise ApiError(f"{where}: more than {MAX_TAGS_PER_REQUEST} tags in one request", 400)
    return tags


def _packages(got: Received) -> list[tuple[str, Path]]:
    """(label, path) of each package the request holds."""
    if got.body is not None:
        if got.size == 0:
            raise ApiError("empty body: send the package as the body or as multipart part(s) named 'file'", 400)
        return [("request body", got.body)]
    stray = [field for field, *_ in got.files if field != FILE_PART]
    if stray:
        raise ApiError(f"file part {stray[0]!r}: unexpected; packages are sent as {FILE_PART!r} parts", 400)
    if not got.files:
        raise ApiError(f"no file part named {FILE_PART!r} in the multipart body", 400)
    if len(got.files) > MAX_PACKAGES:
        raise ApiError(f"{len(got.files)} packages in one upload; at most {MAX_PACKAGES}", 400)
    return [(f"file {filename!r}" if filename else f"file part {i}", path)
            for i, (_, filename, path, _) in enumerate(got.files)]


def _extracted_at(settings: Any) -> re.Pattern:
    """Where uploads are extracted ($HOPE_HOME/tmp/package-<sha>/): a path that means nothing
    to a client (and is gone after the request), in the sources and messages ingest recorded."""
    return re.compile(re.escape(str(Path(settings.home) / TMP_DIR)) + "/" + EXTRACTED + r"[0-9a-f]+/?")


def _readable(value: Any, where: re.Pattern, label: str) -> Any:
    if isinstance(value, str):
        return where.sub(label, value)
    if isinstance(value, list):
        return [_readable(v, where, label) for v in value]
    return value


def _entry(entry: dict[str, Any], where: re.Pattern, label: str = "upload:") -> dict[str, Any]:
    out = {k: _readable(entry.get(k), where, label) for k in ("source", "errors", "warnings")}
    out["status"] = STATUS.get(entry["status"], entry["status"])
    return dict(entry, **out)


def _episode_answer(entry: dict[str, Any], where: re.Pattern, label: str) -> dict[str, Any]:
    entry = _entry(entry, where, label + ":")
    return {"episode_id": entry.get("episode_id"), "action": entry["action"], "status": entry["status"],
            "errors": entry.get("errors") or [], "warnings": entry.get("warnings") or [],
            "steps": entry.get("steps", 0), **verdict_fields(entry), "tags": entry.get("tags", []),
            "origin": entry.get("origin"), "source": entry.get("source")}


@contextmanager
def _extraction_area(settings: Any) -> Iterator[Path]:
    """$HOPE_HOME/tmp, held by one upload's extraction and ingest at a time (an flock on the dir:
    the kernel drops it when its holder dies). Packages are extracted to `package-<sha>` in it,
    a name of their bytes, so ingest records the same source for the same package (a rejected
    one uploaded again replaces its record instead of adding one); the lock makes that name free."""
    area = Path(settings.home) / TMP_DIR
    area.mkdir(mode=0o700, parents=True, exist_ok=True)
    fd = os.open(area, os.O_RDONLY | os.O_DIRECTORY)
    try:
        fcntl.flock(fd, fcntl.LOCK_EX)
        yield area
    finally:
        os.close(fd)


def _extract(area: Path, packages: list[tuple[str, Path]], settings: Any, budget: Budget, room: TmpRoom,
             into: list[tuple[str, str, Path, Path]]) -> None:
    """Every package extracted before any is ingested: (label, kind, what to ingest, its dir)
    appended to `into` as each dir is made, so the caller removes them whatever happens. What
    they unpack to is counted in $HOPE_HOME/tmp's room (TmpRoom) while they are there: one package
    unpacks to at most upload_unpack_max_mb, and never to more than that room."""
    # the room in $HOPE_HOME/tmp can never exceed upload_tmp_max_mb: past that a package is as
    # refused (413) as past its own cap; within it but past the room now, 507 (others hold it)
    limit = min(int(settings.upload_unpack_max_mb), int(settings.upload_tmp_max_mb)) << 20
    cap_words = (f"upload_unpack_max_mb={settings.upload_unpack_max_mb}"
                 if settings.upload_unpack_max_mb <= settings.upload_tmp_max_mb
                 else f"upload_tmp_max_mb={settings.upload_tmp_max_mb}")
    seen = set()
    for label, path in packages:
        sha = file_sha256(path)[:16]
        if sha in seen:  # the same bytes twice in one drop: one result
            continue
        seen.add(sha)
        dest = area / f"{EXTRACTED}{sha}"
        shutil.rmtree(dest, ignore_errors=True)  # left by an upload that died (we hold the lock)
        dest.mkdir()
        into.append((label, "", dest, dest))
        room_left = room.available()
        try:
            kind, where = extract_upload(path, dest, label=label, max_total_bytes=limit, budget=budget,
                                         max_members=int(settings.upload_max_members), cap_words=cap_words,
                                         room=room_left, room_words=f"$HOPE_HOME/tmp has room for {room_left} "
                                         "bytes now (upload_tmp_max_mb, disk_floor_mb)")
        except PackageError as exc:
            raise ApiError(exc.message, exc.status) from None
        into[-1] = (label, kind, where, dest)
        room.take(sum(f.stat().st_size for f in dest.rglob("*") if f.is_file()), label)


def _to_trash(dest: Path) -> Path:
    """`dest` renamed to a name no other upload uses, so it can be removed after the lock is let go
    (removing 10,000 files takes seconds on an SD card)."""
    trash = dest.with_name(f".trash-{uuid.uuid4().hex}")
    try:
        os.rename(dest, trash)
    except OSError:
        shutil.rmtree(dest, ignore_errors=True)
    return trash


def _ingest(settings: Any, packages: list[tuple[str, Path]], tags: list[str], room: TmpRoom) -> list[dict]:
    trash: list[Path] = []
    try:
        return _ingest_locked(settings, packages, tags, room, trash)
    finally:
        for path in trash:
            shutil.rmtree(path, ignore_errors=True)


def _ingest_locked(settings: Any, packages: list[tuple[str, Path]], tags: list[str], room: TmpRoom,
                   trash: list[Path]) -> list[dict]:
    with _extraction_area(settings) as area:
        extracted: list[tuple[str, str, Path, Path]] = []
        # started once the lock is ours: what the request sent, times the ratio, may be inflated
        sent = sum(p.stat().st_size for _, p in packages)
        budget = Budget(ratio_limit(sent), settings.upload_extract_s + SECONDS_PER_MB * sent / (1 << 20),
                        per_unpacked_mb_s=SECONDS_PER_MB)
        label = packages[0][0] if packages else "upload"
        try:
            _extract(area, packages, settings, budget, room, extracted)
            out = []
            for label, kind, where, _ in extracted:
                try:
                    # the extraction dir is gone after this request: sources are named by the package
                    result = ingest_into_inbox([where], settings.inbox_dir, tags=tags, origin=f"upload:{kind}",
                                               sources_as=(str(where), f"upload:{where.name}"), budget=budget)
                except InboxError as exc:
                    raise ApiError(exc.message, exc.status) from None
                episodes = [_episode_answer(e, _extracted_at(settings), label) for e in result["episodes"]]
                if not episodes:
                    raise ApiError(f"{label}: no episode in this {KINDS[kind]}", 400)
                out.append({"name": label, "kind": kind, "episodes": episodes})
            return out
        except InflateError as exc:  # a bomb inside a member, or the budget's deadline
            raise ApiError(_readable(exc.message, _extracted_at(settings), label + ":"), exc.status) from None
        finally:
            trash.extend(_to_trash(dest) for *_, dest in extracted)


@bp.post("/api/episodes/upload")
@large_body
def upload():
    hope = current_app.extensions["hope"]
    settings = hope.settings
    tags = _split_tags(request.headers.get(TAG_LIST_HEADER, ""), TAG_LIST_HEADER)  # before the body
    with received(settings, max_parts=MAX_PACKAGES + 1) as got:
        tags += [t for t in _split_tags(got.fields.get("tags", ""), "tags") if t not in tags]
        if len(tags) > MAX_TAGS_PER_REQUEST:
            raise ApiError(f"{TAG_LIST_HEADER} and tags: more than {MAX_TAGS_PER_REQUEST} tags in one request", 400)
        packages = _ingest(settings, _packages(got), tags, got.room)
    episodes = [e for p in packages for e in p["episodes"]]
    summary = {action: sum(1 for e in episodes if e["action"] == action)
               for action in ("written", "unchanged", "duplicate", "rejected", "skipped")}
    log.info("upload: %s", ", ".join(f"{p['name']} ({p['kind']}): " + ", ".join(
        f"{e['episode_id']} {e['action']}" for e in p["episodes"]) for p in packages))
    if summary["written"]:
        hope.wake_daemon()
    return jsonify({"packages": packages, "summary": summary})


def _inbox() -> list[dict[str, Any]]:
    settings = current_app.extensions["hope"].settings
    try:
        entries = list_inbox(settings.inbox_dir)
    except InboxError as exc:
        raise ApiError(exc.message, exc.status) from None
    return [_entry(e, _extracted_at(settings)) for e in entries]


@bp.get("/api/episodes")
def editor_list():
    query_args()
    settings = current_app.extensions["hope"].settings
    return jsonify({"episodes": _inbox(), "inbox": str(settings.inbox_dir),
                    "upload_max_mb": int(settings.upload_max_mb)})


@bp.get("/api/v1/data/episodes")
def app_list():
    query_args()
    return jsonify({"episodes": _inbox()})


@bp.post("/api/v1/data/tag")
def app_tag():
    body = json_body(allowed=("episode_id", "tag"), required=("episode_id", "tag"))
    episode_id = get_str(body, "episode_id")
    tag = get_str(body, "tag")
    settings = current_app.extensions["hope"].settings
    try:
        entry = tag_episode(settings.inbox_dir, episode_id, tag)
    except InboxError as exc:
        raise ApiError(exc.message, exc.status) from None
    return jsonify({"success": True, "episode": _entry(entry, _extracted_at(settings))})
