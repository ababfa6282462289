"""Writing one episode as a canonical dir: <dataset>/<episode_id>/metadata.json, steps/000000.jsonl, blobs/.

The dir is built under a temporary name in the dataset dir and renamed into place, so a reader
(or a crash) never sees half an episode. Relative blob files the steps reference (in observation,
action, step_metadata or a step-level key such as the Pi arm recorder's `audio.uri`) are copied
into `blobs/` and their URIs rewritten to `blobs/<path>`; URIs with a scheme stay opaque.

The content hash covers what is written (metadata but its id, steps, blob bytes) with every
object's keys sorted, so the same input always hashes the same whatever order a producer wrote
its keys in, and ingest can tell "already here" from "a different episode with the same id".
`legacy_content_sha256` is the hash as it was computed before keys were sorted: manifests written
then still hold it.

Blobs of an episode that came over the network are confined (`confine_blobs`): only relative URIs
inside the episode's own blob root are followed; absolute paths and `file://` URIs are opaque text,
never opened, so a client cannot make the trainer read (or copy) a file of its choosing.
"""
from __future__ import annotations

import copy
import hashlib
import json
import os
import posixpath
import re
import shutil
import uuid
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Iterator

from ..durable import file_sha256, fsync_files, fsync_path
from .episode import SCHEMA_VERSION, Episode, Step
from .json_text import json_dumps

STEPS_FILE = "steps/000000.jsonl"
BLOBS_DIR = "blobs"
TMP_PREFIX = ".tmp-"
_SCHEME = re.compile(r"^[A-Za-z][A-Za-z0-9+.\-]+:")  # two letters at least: not a drive letter
_SAFE_ID = re.compile(r"^[A-Za-z0-9][A-Za-z0-9._-]{0,127}$")
# the keys Step.to_json_obj writes itself: an extra of the same name is not written, so not walked
_STEP_FIELDS = ("step_index", "timestamp_ns", "observation", "action", "reward", "is_terminal", "step_metadata")
_CONFINED = "_hope_blobs_confined"  # an attribute set on an Episode (its own dataclass has no such field)


# -- blob references ----------------------------------------------------------------------------

@dataclass(frozen=True)
class BlobRef:
    step: int
    field: str  # dotted path of the URI, e.g. "observation.media.rgb.uri"
    uri: str
    status: str  # "ok", "missing", "escapes", "unresolvable" (relative, no blob root), "opaque"
    path: Path | None = None  # the local file it names, when it names one
    rel: str | None = None  # normalised path relative to the blob root (relative URIs only)


def _is_uri_key(key: str) -> bool:
    return key == "uri" or key.endswith("_uri")


def _uri_fields(value: Any, path: str) -> Iterator[tuple[str, str]]:
    if isinstance(value, dict):
        for key, sub in value.items():
            sub_path = f"{path}.{key}"
            if isinstance(sub, str) and _is_uri_key(str(key)) and sub:
                yield sub_path, sub
            else:
                yield from _uri_fields(sub, sub_path)
    elif isinstance(value, list) and not set(map(type, value)).isdisjoint((dict, list)):
        for i, sub in enumerate(value):  # only lists that hold objects can hold URIs
            if isinstance(sub, (dict, list)):
                yield from _uri_fields(sub, f"{path}[{i}]")


def step_uri_fields(step: dict[str, Any]) -> Iterator[tuple[str, str]]:
    """(dotted path, uri) of every URI field of a step as JSON: its observation, action and
    step_metadata and its step-level keys alike (the Pi's arm recorder puts `audio: {uri}` there)."""
    for key, value in step.items():
        if isinstance(value, str) and _is_uri_key(str(key)) and value:
            yield str(key), value
        else:
            yield from _uri_fields(value, str(key))


def _step_parts(step: Step) -> Iterator[tuple[str, Any]]:
    yield "observation", step.observation
    yield "action", step.action
    yield "step_metadata", step.step_metadata
    for key, value in step.extras.items():
        if key not in _STEP_FIELDS:
            yield key, value


def confine_blobs(ep: Episode) -> Episode:
    """Marks `ep` as untrusted: validation, preparation and writing follow only relative blob URIs
    inside its blob root from now on."""
    setattr(ep, _CONFINED, True)
    return ep


def blobs_confined(ep: Episode) -> bool:
    return bool(getattr(ep, _CONFINED, False))


def _resolve(uri: str, blob_root: str | None, confined: bool = False,
             real_root: str | None = None) -> tuple[str, Path | None, str | None]:
    """`real_root`: the blob root's real path when the caller has it (one per episode, not per blob:
    a 2,000-tap handoff names 8,000 files)."""
    if confined and (uri.startswith("file:") or os.path.isabs(uri) or uri.startswith("\\")):
        return "opaque", None, None  # not even stat()ed: whether it exists is no one's business
    if uri.startswith("file://"):
        local = Path(uri[len("file://"):])
        return ("ok" if local.is_file() else "missing"), local, None
    if _SCHEME.match(uri):
        return "opaque", None, None
    if os.path.isabs(uri):
        local = Path(uri)
        return ("ok" if local.is_file() else "missing"), local, None
    rel = posixpath.normpath(uri.replace("\\", "/"))
    if rel == ".." or rel.startswith("../"):
        return "escapes", None, rel
    if blob_root is None:
        return "unresolvable", None, rel
    root = Path(blob_root)
    local = root / rel
    # A symlink inside the episode dir can still point anywhere; only the real path counts.
    if not os.path.realpath(local).startswith((real_root or os.path.realpath(root)) + os.sep):
        return "escapes", local, rel
    return ("ok" if local.is_file() else "missing"), local, rel


def blob_refs(ep: Episode) -> list[BlobRef]:
    """Every blob URI in the steps (observation, action, step_metadata and step-level keys),
    checked once per distinct URI (at its first step)."""
    refs: list[BlobRef] = []
    seen: set[str] = set()
    confined = blobs_confined(ep)
    real_root = None if ep.blob_root is None else os.path.realpath(ep.blob_root)
    for i, step in enumerate(ep.steps):
        for part, value in _step_parts(step):
            for field_path, uri in step_uri_fields({part: value}):
                if uri in seen:
                    continue
                seen.add(uri)
                status, path, rel = _resolve(uri, ep.blob_root, confined, real_root)
                refs.append(BlobRef(i, field_path, uri, status, path, rel))
    # Files handed in beside the steps (the app's assets) are part of the episode even when no
    # step names them; they are listed in metadata.assets with the `uri` they are stored under.
    assets = ep.metadata.get("assets")
    for i, asset in enumerate(assets if isinstance(assets, list) else []):
        asset_uri = asset.get("uri") if isinstance(asset, dict) else None
        if isinstance(asset_uri, str) and asset_uri and asset_uri not in seen:
            seen.add(asset_uri)
            status, path, rel = _resolve(asset_uri, ep.blob_root, confined, real_root)
            refs.append(BlobRef(0, f"metadata.assets[{i}].uri", asset_uri, status, path, rel))
    return refs


def rewrite_uris(value: Any, mapping: dict[str, str]) -> Any:
    """`value` with every URI field (`uri`, `*_uri`) found in `mapping` replaced."""
    if isinstance(value, dict):
        return {k: (mapping.get(v, v) if isinstance(v, str) and _is_uri_key(str(k))
                    else rewrite_uris(v, mapping)) for k, v in value.items()}
    if isinstance(value, list):
        return [rewrite_uris(v, mapping) for v in value]
    return value


# -- the content as written ---------------------------------------------------------------------

def canonical_metadata(ep: Episode, episode_id: str | None = None) -> dict[str, Any]:
    meta = copy.deepcopy(ep.metadata)
    meta["schema_version"] = SCHEMA_VERSION
    meta["episode_id"] = episode_id or ep.episode_id
    provenance = meta.get("provenance")
    if not isinstance(provenance, dict):
        provenance = {} if provenance is None else {"notes": str(provenance)}
        meta["provenance"] = provenance
    provenance.setdefault("origin", f"import:{ep.layout}")
    if ep.steps_lost:
        provenance["steps_lost"] = ep.steps_lost  # a gap the timestamps alone do not explain
    return meta


@dataclass
class PreparedEpisode:
    """An episode turned into the exact JSON and files that will be written."""

    episode_id: str
    metadata: dict[str, Any]
    steps: list[dict[str, Any]]
    blobs: dict[str, Path] = field(default_factory=dict)  # "blobs/x.npy" -> source file
    blob_sha256: dict[str, str] = field(default_factory=dict)
    content_sha256: str = ""
    _steps_text: str | None = field(default=None, repr=False)

    def metadata_text(self, episode_id: str | None = None) -> str:
        meta = dict(self.metadata, episode_id=episode_id or self.episode_id)
        return json_dumps(meta, indent=2, allow_nan=False) + "\n"

    def steps_text(self) -> str:
        # Serialised once, keys sorted: it is both hashed and written, and large episodes take a while.
        if self._steps_text is None:
            self._steps_text = "".join(
                json_dumps(s, allow_nan=False, separators=(",", ":"), sort_keys=True) + "\n"
                for s in self.steps)
        return self._steps_text

    def legacy_content_sha256(self) -> str | None:
        """The hash before keys were sorted (None for content that hash could not cover: a lone
        surrogate did not encode then, so no manifest can hold such an episode under it)."""
        try:
            digest = hashlib.sha256()
            digest.update(json.dumps(self._anonymous(), indent=2, ensure_ascii=False,
                                     allow_nan=False).encode("utf-8"))
            for s in self.steps:
                digest.update((json.dumps(s, ensure_ascii=False, allow_nan=False, separators=(",", ":"))
                               + "\n").encode("utf-8"))
            digest.update(json.dumps(self.blob_sha256, sort_keys=True).encode("utf-8"))
        except UnicodeEncodeError:
            return None
        return digest.hexdigest()

    def _anonymous(self) -> dict[str, Any]:
        # The id is left out of the hash: it names the content, and an episode written under a
        # suffixed id (or re-ingested from a dataset dir) must still be recognised as the same.
        return {k: v for k, v in self.metadata.items() if k != "episode_id"}


def prepare_episode(ep: Episode, as_id: str | None = None) -> PreparedEpisode:
    """`as_id` is the id the written metadata will carry (default: the episode's own). The blobs
    of a confined episode (`confine_blobs`) are only looked for inside its blob root."""
    episode_id = as_id or ep.episode_id
    blobs: dict[str, Path] = {}
    mapping: dict[str, str] = {}
    for ref in blob_refs(ep):
        if ref.status != "ok" or ref.rel is None or ref.path is None:
            continue  # absolute, opaque, missing or escaping blobs are left as they are
        dest = ref.rel if ref.rel.startswith(BLOBS_DIR + "/") else f"{BLOBS_DIR}/{ref.rel}"
        blobs[dest] = ref.path
        if dest != ref.uri:
            mapping[ref.uri] = dest
    steps = []
    for i, step in enumerate(ep.steps):
        obj = step.to_json_obj(i)
        if mapping:
            for part, _ in _step_parts(step):
                obj[part] = rewrite_uris({part: obj[part]}, mapping)[part]
        steps.append(obj)
    prepared = PreparedEpisode(episode_id, canonical_metadata(ep, episode_id), steps, blobs)
    prepared.blob_sha256 = {name: file_sha256(path) for name, path in sorted(blobs.items())}
    digest = hashlib.sha256()
    digest.update(json_dumps(prepared._anonymous(), indent=2, allow_nan=False, sort_keys=True).encode("utf-8"))
    digest.update(prepared.steps_text().encode("utf-8"))
    digest.update(json.dumps(prepared.blob_sha256, sort_keys=True).encode("utf-8"))
    prepared.content_sha256 = digest.hexdigest()
    return prepared


# -- ids and atomic writing ---------------------------------------------------------------------

def safe_episode_id(episode_id: str) -> str:
    """A dir name that cannot escape the dataset dir; ids that need changing get a hash of the
    original so two different ids never collapse into the same name."""
    if _SAFE_ID.match(episode_id) and episode_id not in (".", ".."):
        return episode_id
    cleaned = re.sub(r"[^A-Za-z0-9._-]", "_", episode_id).lstrip("._-")[:100] or "episode"
    raw = episode_id.encode("utf-8", "surrogatepass")  # a lone surrogate still names one id
    return f"{cleaned}-{hashlib.sha256(raw).hexdigest()[:8]}"




def _write_text(path: Path, text: str) -> None:
    with open(path, "w", encoding="utf-8", newline="\n") as f:
        f.write(text)
        f.flush()
        os.fsync(f.fileno())


def write_prepared(prepared: PreparedEpisode, dataset_dir: str | os.PathLike,
                   episode_id: str | None = None) -> Path:
    dataset = Path(dataset_dir)
    final_id = safe_episode_id(episode_id or prepared.episode_id)
    final = dataset / final_id
    if final.exists():
        raise FileExistsError(f"{final}: episode dir already exists")
    dataset.mkdir(parents=True, exist_ok=True)
    tmp = dataset / f"{TMP_PREFIX}{final_id}-{uuid.uuid4().hex[:8]}"
    try:
        (tmp / "steps").mkdir(parents=True)
        _write_text(tmp / "metadata.json", prepared.metadata_text(final_id))
        _write_text(tmp / STEPS_FILE, prepared.steps_text())
        copied = []
        for name, source in prepared.blobs.items():
            dest = tmp / name
            dest.parent.mkdir(parents=True, exist_ok=True)
            shutil.copyfile(source, dest)
            copied.append(dest)
            if file_sha256(dest) != prepared.blob_sha256[name]:
                raise OSError(f"{source}: blob changed while it was being copied")
        fsync_files(copied, tmp)
        for sub in sorted({p for p in tmp.rglob("*") if p.is_dir()} | {tmp}, reverse=True):
            fsync_path(sub)
        os.rename(tmp, final)
        fsync_path(dataset)
    except BaseException:
        shutil.rmtree(tmp, ignore_errors=True)
        raise
    return final


def write_episode_dir(episode: Episode, dataset_dir: str | os.PathLike,
                      episode_id: str | None = None) -> Path:
    """Writes `episode` as <dataset_dir>/<episode_id>/ and returns that dir.

    Raises FileExistsError when the dir exists (ingest decides what a clash means), and
    ValueError for content JSON cannot hold (NaN/Inf: validate first)."""
    return write_prepared(prepare_episode(episode), dataset_dir, episode_id)


def remove_stale_tmp_dirs(dataset_dir: Path) -> list[Path]:
    """Leftovers of a write that crashed before its rename; they never hold a complete episode."""
    removed = []
    if dataset_dir.is_dir():
        for entry in dataset_dir.iterdir():
            if entry.name.startswith(TMP_PREFIX) and entry.is_dir():
                shutil.rmtree(entry, ignore_errors=True)
                removed.append(entry)
    return removed
