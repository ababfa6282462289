"""POST /api/training/queue/episodes: the Continuon app's YouTube importer hands one episode to the robot.

What the app sends (continuonai/lib/services/training_queue_service.dart enqueueEpisode, called by
youtube_import_service.dart importAndPublish after the cloud built the episode from a video):

    POST /api/training/queue/episodes   Content-Type: application/json, authorization: Bearer <token>
    {"episode": <EpisodeRecord.toJson(): {"metadata": {"xr_mode", "control_role", "environment_id",
                 "tags", "source": "youtube", "provenance": {"video_url", ...}}, "steps": [{"observation",
                 "action", "is_terminal", "step_metadata"}], "task_classification"?, "source_context"?,
                 "assets"?}>,
     "request_public_listing": bool,
     "share"?: {"public", "slug", "title", "license", "tags"}}

The app reads only the status: any 2xx is success, anything else is an HttpException with the
status and the body, which the importer shows. The answer:

    200 {"success": true, "queued": true, "episode_id": "app-<content hash>", "action": "written" |
         "unchanged" | "duplicate", "status": "ok" | "warnings", "trainable": [...],
         "not_trainable": {component: why}, "cameras": [...], "reads"?, "warnings": [...],
         "public_listing": false}
    400 a body of the wrong shape, naming the field (`episode.steps[3].action: ...`, `share.tags: ...`)
    422 an episode validation rejects, with its reasons (listed as rejected in the inbox)

"Queued for training" here means what it means for every episode that reaches the trainer: it goes
into the inbox (the same hope_models.intake.inbox.ingest_record the app's handoff uses, origin
"app:training_queue"), named by its content so a repeat is the same episode, and continuous
learning trains on it with the rest when it can (its `trainable`). No run is queued for one episode.
Nothing is published from the trainer: `request_public_listing` and `share` are checked and kept
with the request's answer only (`public_listing` is always false, with a warning when a listing was
asked for); the listing is the app's business with its cloud. The body is at most the API's 1 MiB
(webapp/__init__.py MAX_BODY_BYTES): the importer's records hold steps of JSON, no media. The
bearer token is required, as for every call that changes state.
"""
from __future__ import annotations

import logging
from typing import Any

from flask import Blueprint, current_app, jsonify

from hope_models.intake.inbox import InboxError, ingest_record
from hope_models.intake.trainable import verdict_fields
from webapp.api.validation import json_body
from webapp.errors import ApiError, error_response

log = logging.getLogger(__name__)
bp = Blueprint("training_queue", __name__)

ORIGIN = "app:training_queue"
FIELDS = ("episode", "request_public_listing", "share")
# ShareMetadata.toJson (continuonai/lib/models/rlds_models.dart): field -> the JSON type it holds
SHARE_FIELDS: dict[str, tuple[type, str]] = {"public": (bool, "a boolean"), "slug": (str, "a string"),
                                             "title": (str, "a string"), "license": (str, "a string"),
                                             "tags": (list, "a list of strings")}
# ingest_record names the record `manifest` (the handoff's form field); here it is the body's `episode`
RECORD_NAME = "manifest"


def _check_share(share: Any) -> None:
    if share is None:
        return
    if not isinstance(share, dict):
        raise ApiError("share: expected an object {public, slug, title, license, tags} or no share", 400)
    for name, (kind, shown) in SHARE_FIELDS.items():
        if name in share and not isinstance(share[name], kind):
            raise ApiError(f"share.{name}: expected {shown}", 400)
    for i, tag in enumerate(share.get("tags") or []):
        if not isinstance(tag, str):
            raise ApiError(f"share.tags[{i}]: expected a string", 400)


def _field_named(message: str) -> str:
    """The record's errors as this body names its fields (`manifest.steps[2]` -> `episode.steps[2]`)."""
    return "episode" + message[len(RECORD_NAME):] if message.startswith(RECORD_NAME) else message


def _read() -> tuple[dict[str, Any], bool]:
    body = json_body(allowed=FIELDS, required=("episode",))
    episode = body["episode"]
    if not isinstance(episode, dict):
        raise ApiError("episode: expected an object (the EpisodeRecord: metadata, steps, ...)", 400)
    public = body.get("request_public_listing", False)
    if not isinstance(public, bool):
        raise ApiError("request_public_listing: expected true or false", 400)
    _check_share(body.get("share"))
    return episode, public


@bp.post("/api/training/queue/episodes")
def queue_episode():
    hope = current_app.extensions["hope"]
    episode, public = _read()
    try:
        entry = ingest_record(episode, [], {}, hope.settings.inbox_dir, origin=ORIGIN)
    except InboxError as exc:
        raise ApiError(_field_named(exc.message), exc.status) from None
    if entry["action"] == "rejected":
        log.info("training queue: rejected (%s)", "; ".join(entry["errors"][:3]))
        return error_response("the episode was rejected: " + "; ".join(entry["errors"][:5]), 422,
                              errors=entry["errors"], warnings=entry["warnings"])
    warnings = list(entry["warnings"])
    if public:
        warnings.append("request_public_listing: this trainer publishes nothing; the episode stays on this robot")
    log.info("training queue: %s %s, %d steps, trainable: %s", entry["action"], entry["episode_id"],
             entry["steps"], ", ".join(entry["trainable"]) or "nothing")
    if entry["action"] == "written":
        hope.wake_daemon()
    return jsonify({"success": True, "queued": True, "episode_id": entry["episode_id"], "action": entry["action"],
                    "status": "warnings" if warnings else "ok", **verdict_fields(entry), "warnings": warnings,
                    "public_listing": False})
