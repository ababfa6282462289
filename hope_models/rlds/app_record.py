"""The Continuon app's EpisodeRecord (its episode handoff) as a canonical `Episode`.

The app posts `{"metadata": {...}, "steps": [...], "task_classification"?, "source_context"?,
"assets"?}` with no episode id, plus a list of assets `{"local_uri", "sensor", "frame_id",
"captured_at_ms", "mount"?, "remote_uri"?, "mime_type"?, "status"}` and the asset files it still
has. Keys go through normalize.py like every producer's (camelCase or snake_case, any order).

* The id is not chosen here: ingest names the episode `app-<content hash>` (ingest_reports'
  `content_ids`), so the same episode handed off twice, or spelled by two writers, is one episode.
* The clock: the record screen writes none at the step level; each sensor block carries its
  capture time (`observation.egocentric_video.timestamp_ms`, `observation.audio.device_mic.
  timestamp_ms`, or `step_metadata.timestamp_ms`, a string: Dart's step_metadata is
  Map<String, String>). One of them is lifted to the step's `timestamp_ms`, the same sensor on
  every step where it can be, and timestamps.py detects its unit like any other clock.
* Assets: a file that came is staged as `<stage>/blobs/assets/<name>` and listed in
  metadata.assets with that `uri`. A step names it however its writer spelled the path: the app's
  steps say `Uri.file(path).toString()` (`file:///data/.../egocentric-1.mp4`, spaces and non-ASCII
  percent-encoded) while the asset's `local_uri` is the bare path; the bare path and a
  percent-encoded one are the same file too. Every such URI field, anywhere in the step, is
  rewritten to the stored `uri` (`file_key`). A URI that names a listed asset whose file did not
  come is kept as text and named in one warning per field (how many steps, the first step and
  URI); an asset file that came empty (the app's stand-in when native capture fails) is named too.
  Phone paths stay opaque text otherwise (the episode is confined: nothing outside its own dir is
  ever opened, so no warning says whether a path exists here). `status` and `remote_uri` of an asset describe the phone's
  transfer, not the episode, and are left out so a retried handoff is the same content. A `uri`
  an asset arrives with is dropped: only a file that came gets one, naming where it is stored.
"""
from __future__ import annotations

import hashlib
import os
import re
import shutil
from dataclasses import dataclass
from pathlib import Path
from typing import Any
from urllib.parse import unquote

from .episode import Episode, SourceReport
from .json_text import json_dumps
from .normalize import normalize_metadata, snake_keys, step_from_obj
from .timestamps import CLOCKS, assign_timestamps
from .write_episode_dir import BLOBS_DIR, confine_blobs, rewrite_uris, step_uri_fields

LAYOUT = "app_handoff"
ASSETS_DIR = f"{BLOBS_DIR}/assets"
TRANSFER_KEYS = ("status", "remote_uri")  # the phone's upload state, not the episode
# Where an asset's file is stored is ours to say: a `uri` the client sends would be taken as a path
# on this host (and answered in remote_uris when a file is there: an oracle for host paths).
OURS = ("uri",)
MAX_NAME_BYTES = 200
_CLOCK_KEY = "timestamp_ms"
_FIRST_SENSORS = ("egocentric_video", "audio.device_mic", "audio.robot_mic")
_OTHER_SCHEME = re.compile(r"^[A-Za-z][A-Za-z0-9+.\-]+:")


class AppRecordError(ValueError):
    """The record or its assets cannot be an episode; the message names the field
    (`manifest.steps[3].action: ...`, `assets[1].local_uri: ...`)."""


def _kind(value: Any) -> str:
    return {dict: "object", list: "list", str: "string", bool: "boolean", type(None): "null"}.get(
        type(value), "number" if isinstance(value, (int, float)) else type(value).__name__)


def check_record(record: Any) -> dict[str, Any]:
    """The record's structure (what a step needs to be a step), with snake_case keys."""
    if not isinstance(record, dict):
        raise AppRecordError(f"manifest: expected a JSON object, got a {_kind(record)}")
    record = snake_keys(record)
    metadata = record.get("metadata")
    if not isinstance(metadata, dict):
        raise AppRecordError(f"manifest.metadata: expected an object, got {_kind(metadata)}")
    steps = record.get("steps")
    if not isinstance(steps, list):
        raise AppRecordError(f"manifest.steps: expected a list, got {_kind(steps)}")
    if not steps:
        raise AppRecordError("manifest.steps: the episode has no steps")
    for i, step in enumerate(steps):
        if not isinstance(step, dict):
            raise AppRecordError(f"manifest.steps[{i}]: expected an object, got {_kind(step)}")
        for key in ("observation", "action"):
            if not isinstance(step.get(key), dict):
                raise AppRecordError(f"manifest.steps[{i}].{key}: expected an object, got {_kind(step.get(key))}")
        meta = step.get("step_metadata")
        if meta is not None and not isinstance(meta, dict):
            raise AppRecordError(f"manifest.steps[{i}].step_metadata: expected an object, got {_kind(meta)}")
        terminal = step.get("is_terminal")
        if terminal is not None and not isinstance(terminal, bool):
            raise AppRecordError(f"manifest.steps[{i}].is_terminal: expected a boolean, got {_kind(terminal)}")
    return record


def asset_name(local_uri: str) -> str | None:
    """The file name the app sends a local_uri's file under (its last path segment), or None when
    that is no name a file may be stored under here."""
    name = local_uri[len("file://"):] if local_uri.startswith("file://") else local_uri
    name = name.rstrip("/").rsplit("/", 1)[-1]
    if (not name or name in (".", "..") or name.startswith(".") or "\\" in name
            or any(ord(c) < 32 or 0xD800 <= ord(c) <= 0xDFFF for c in name)
            or len(name.encode("utf-8")) > MAX_NAME_BYTES):
        return None
    return name


def check_assets(assets: Any, record_assets: Any = None) -> list[dict[str, Any]]:
    """The assets field (and the record's own `assets`, for local_uris the field does not list)."""
    out: list[dict[str, Any]] = []
    seen: set[str] = set()
    for where, items in (("assets", assets), ("manifest.assets", record_assets)):
        if items is None:
            continue
        if not isinstance(items, list):
            raise AppRecordError(f"{where}: expected a list, got {_kind(items)}")
        for i, raw in enumerate(items):
            if not isinstance(raw, dict):
                raise AppRecordError(f"{where}[{i}]: expected an object, got {_kind(raw)}")
            asset = snake_keys(raw)
            uri = asset.get("local_uri")
            if not isinstance(uri, str) or not uri:
                raise AppRecordError(f"{where}[{i}].local_uri: expected a non-empty string, got {_kind(uri)}")
            if uri not in seen:
                seen.add(uri)
                out.append(asset)
    return out


def _place_files(assets: list[dict[str, Any]], files: dict[str, Path], stage: Path) -> dict[str, str]:
    """Stages each file that came under the name its asset is stored as; local_uri -> that uri."""
    by_name: dict[str, list[str]] = {}
    for asset in assets:
        name = asset_name(asset["local_uri"])
        if name is not None:
            by_name.setdefault(name, []).append(asset["local_uri"])
    stored: dict[str, str] = {}
    for name, path in sorted(files.items()):
        owners = by_name.get(name)
        if not owners:
            raise AppRecordError(f"asset {name!r}: its file name is the last path segment of no asset's local_uri")
        # Two phone files with one name: the app sends only one part per name that matters here.
        rel = f"{ASSETS_DIR}/{name}"
        dest = stage / rel
        dest.parent.mkdir(parents=True, exist_ok=True)
        try:
            os.link(path, dest)  # the upload's own file on the same disk: no second copy
        except OSError:
            shutil.copyfile(path, dest)
        for owner in owners:
            stored[owner] = rel
    return stored


def file_keys(uri: str) -> list[str]:
    """The local paths a URI may spell: a `file:` URI's path (percent-decoded, as Dart's
    Uri.file encodes it; `file://localhost/` too), a bare path as written and percent-decoded.
    Another scheme names no local file: []."""
    for prefix in ("file://localhost/", "file:///", "file:/"):
        if uri.startswith(prefix):
            return [unquote("/" + uri[len(prefix):], errors="surrogateescape")]
    if _OTHER_SCHEME.match(uri):
        return []
    decoded = unquote(uri, errors="surrogateescape")
    return [uri] if decoded == uri else [uri, decoded]


def _asset_keys(assets: list[dict[str, Any]]) -> dict[str, str]:
    """Every spelling of each asset's path -> its local_uri (the first asset wins a clash)."""
    keys: dict[str, str] = {}
    for asset in assets:
        local = asset["local_uri"]
        for key in [local] + file_keys(local):
            keys.setdefault(key, local)
    return keys


@dataclass
class _Unsent:
    steps: int
    first_step: int
    first_uri: str


def _rewrite_step(step: dict[str, Any], i: int, keys: dict[str, str], stored: dict[str, str],
                  unsent: dict[str, _Unsent]) -> dict[str, Any]:
    """The step with every URI that names a stored asset (however spelled) set to its stored uri;
    URIs naming an asset whose file did not come are counted in `unsent` by field."""
    mapping: dict[str, str] = {}
    for field_path, uri in step_uri_fields(step):
        local = next((keys[k] for k in [uri] + file_keys(uri) if k in keys), None)
        if local is None:
            continue
        if local in stored:
            mapping[uri] = stored[local]
        else:
            where = re.sub(r"\[\d+\]", "[]", field_path)
            if where in unsent:
                unsent[where].steps += 1
            else:
                unsent[where] = _Unsent(1, i, uri)
    return rewrite_uris(step, mapping) if mapping else step


def _lift_clock(step: dict[str, Any], prefer: str | None) -> str | None:
    """Sets the step's `timestamp_ms` from a sensor's capture time; returns the sensor used."""
    if any(c.path in step for c in CLOCKS if "." not in c.path):
        return None  # the step has a clock of its own
    obs = step.get("observation", {})
    found: dict[str, Any] = {}
    for key, value in obs.items():
        if isinstance(value, dict):
            if _CLOCK_KEY in value:
                found[key] = value[_CLOCK_KEY]
            for sub, inner in value.items():
                if isinstance(inner, dict) and _CLOCK_KEY in inner:
                    found[f"{key}.{sub}"] = inner[_CLOCK_KEY]
    meta = step.get("step_metadata")
    if isinstance(meta, dict) and _CLOCK_KEY in meta:
        found["step_metadata"] = meta[_CLOCK_KEY]
    order = ([prefer] if prefer else []) + list(_FIRST_SENSORS) + sorted(found)
    for sensor in order:
        if sensor in found and found[sensor] not in (None, ""):
            step[_CLOCK_KEY] = found[sensor]
            return sensor
    return None


def episode_from_record(record: Any, assets: Any, files: dict[str, Path], stage: Path, *,
                        origin: str) -> SourceReport:
    """The record as a confined Episode whose blob root is `stage` (the caller's empty dir, removed
    by the caller). Raises AppRecordError for a structure that is no episode."""
    record = check_record(record)
    assets = check_assets(assets, record.get("assets"))
    stored = _place_files(assets, files, stage)
    source = "app:" + hashlib.sha256(json_dumps([record, assets], sort_keys=True).encode("utf-8")).hexdigest()[:16]
    report = SourceReport(source=source)
    # Until ingest names it by its content: what a rejected record is listed under.
    ep = Episode(episode_id="app-" + source[len("app:"):], metadata={}, steps=[], source=source, layout=LAYOUT,
                 blob_root=str(stage))
    raw_md = dict(record["metadata"])
    for key in ("task_classification", "source_context"):
        if key in record:
            raw_md.setdefault(key, record[key])
    raw_md["assets"] = [dict({k: v for k, v in a.items() if k not in TRANSFER_KEYS + OURS},
                             **({"uri": stored[a["local_uri"]]} if a["local_uri"] in stored else {}))
                        for a in assets]
    raw_md.pop("episode_id", None)  # the content names it
    meta = normalize_metadata(raw_md, layout=LAYOUT, fallback_id=ep.episode_id,
                              warn=lambda msg, fld: ep.warn(msg, field=fld))
    provenance = meta["provenance"]
    if provenance.get("origin") not in (None, "", f"import:{LAYOUT}", origin):
        provenance["source_origin"] = provenance["origin"]
    provenance["origin"] = origin
    ep.metadata = meta
    prefer = None
    keys = _asset_keys(assets)
    unsent: dict[str, _Unsent] = {}
    for i, raw in enumerate(record["steps"]):
        step = _rewrite_step(dict(raw), i, keys, stored, unsent)
        prefer = _lift_clock(step, prefer) or prefer
        ep.steps.append(step_from_obj(step, i, ep))
    for where, seen in unsent.items():
        ep.warn(f"{seen.steps} step(s) name an asset file the app did not send, first {seen.first_uri!r}; "
                "kept as text", step=seen.first_step, field=where)
    empty = sorted(name for name, path in files.items() if os.path.getsize(path) == 0)
    if empty:
        ep.warn(f"{len(empty)} asset file(s) came empty (0 bytes), e.g. {empty[0]!r}: the app sends an empty "
                "stand-in when its native capture fails", field="metadata.assets")
    assign_timestamps(ep)
    report.episodes.append(confine_blobs(ep))
    return report
