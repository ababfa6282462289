"""POST /api/training/episode_handoff: the Continuon app hands an episode and its media to the trainer.

What the app sends (BrainClient.handoffEpisodeAssets): multipart/form-data with a `manifest` field
(its EpisodeRecord as JSON, no episode id), an `assets` field (a JSON list of
{local_uri, sensor, frame_id, captured_at_ms, ...}) and one `asset` file part per asset file it
still has, named by the last path segment of the asset's local_uri. The body may be up to
settings.upload_max_mb (webapp/uploads.py), read after the token check.

The episode goes into the inbox (hope_models/data/inbox.py: validated, blobs confined to the
episode's own dir, named by its content, so a repeated handoff is the same episode). The answer:
200 {"remote_uris": {local_uri: path under $HOPE_HOME}, "episode_id", "action" (written |
unchanged | duplicate), "status" (ok | warnings), "trainable", "not_trainable", "cameras" (one line
per camera: "egocentric_video: 12/12 frames, JPEG 480x640 -> 64x64" or why not), "reads" (what the
tokenizer will read), "warnings"}; the
app reads remote_uris. Bad JSON, a field of the wrong shape (named, e.g.
`manifest.steps[3].action: ...`) or a file part no asset names is a 400 with nothing written; an
episode validation rejects is a 422 with its reasons (listed as rejected in the inbox).
"""
from __future__ import annotations

import logging
import os
from pathlib import Path
from typing import Any

from flask import Blueprint, current_app, jsonify

from hope_models.intake.inbox import HANDOFF_ORIGIN, InboxError, ingest_record
from hope_models.intake.trainable import verdict_fields
from hope_models.rlds.json_text import TextReadError, parse_json_document
from webapp.errors import ApiError, error_response
from webapp.uploads import large_body, received

log = logging.getLogger(__name__)
bp = Blueprint("handoff", __name__)
ASSET_PART = "asset"


def _json_field(fields: dict[str, str], name: str, default: Any = None) -> Any:
    if name not in fields:
        if default is not None:
            return default
        raise ApiError(f"{name}: required form field (the EpisodeRecord as JSON)", 400)
    try:
        return parse_json_document(fields[name])
    except TextReadError as exc:
        raise ApiError(f"{name}: {exc}", 400) from None


def _asset_files(files: list[tuple[str, str, Path, int]]) -> dict[str, Path]:
    out: dict[str, Path] = {}
    for field, filename, path, _size in files:
        if field != ASSET_PART:
            raise ApiError(f"file part {field!r}: unexpected; asset files are sent as {ASSET_PART!r} parts", 400)
        if filename in out:
            raise ApiError(f"asset {filename!r}: sent twice", 400)
        out[filename] = path
    return out


def _under_home(path: str, home: Path) -> str:
    rel = os.path.relpath(path, home)
    return path if rel.startswith("..") else rel


@bp.post("/api/training/episode_handoff")
@large_body
def episode_handoff():
    hope = current_app.extensions["hope"]
    settings = hope.settings
    with received(settings) as got:
        if got.body is not None:
            raise ApiError("expected a multipart/form-data body with the fields manifest and assets", 400)
        manifest = _json_field(got.fields, "manifest")
        assets = _json_field(got.fields, "assets", default=[])
        files = _asset_files(got.files)
        try:
            entry = ingest_record(manifest, assets, files, settings.inbox_dir, origin=HANDOFF_ORIGIN)
        except InboxError as exc:
            raise ApiError(exc.message, exc.status) from None
    if entry["action"] == "rejected":
        log.info("handoff: rejected (%s)", "; ".join(entry["errors"][:3]))
        return error_response("the episode was rejected: " + "; ".join(entry["errors"][:5]), 422,
                              errors=entry["errors"], warnings=entry["warnings"])
    home = Path(settings.home)
    remote = {k: _under_home(v, home) for k, v in entry["remote_uris"].items()}
    log.info("handoff: %s %s, %d steps, %d of %d asset files stored, trainable: %s", entry["action"],
             entry["episode_id"], entry["steps"], len(remote), len(assets) if isinstance(assets, list) else 0,
             ", ".join(entry["trainable"]) or "nothing")
    if entry["action"] == "written":
        hope.wake_daemon()
    return jsonify({"remote_uris": remote, "episode_id": entry["episode_id"], "action": entry["action"],
                    "status": "warnings" if entry["warnings"] else "ok", **verdict_fields(entry),
                    "warnings": entry["warnings"]})
