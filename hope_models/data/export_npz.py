"""Export episodes as ContinuonCloud's upload format: `<episode_id>.npz` and its sidecar JSON.

Per episode, the feature spec (inferred from the episode, or the `--spec` file's request) picks
the numeric fields; `observations` [T, obs_dim] and `actions` [T, act_dim] are those fields in
the spec's order as float32, `rewards` [T] float32, and `timestamps` [T] float64 seconds since
the first step when every step has a clock. The sidecar `<episode_id>.npz.json` holds the field
layout (dotted path, size, offset, kind), the spec, the metadata, the terminal steps and the
backend's query fields (`episode_id`, `task_name`, `duration_seconds`, `num_steps`, `success`).
The format and its reader are hope_models/rlds/read_npz.py.

An episode that does not fit the spec is refused with the step and field named, one whose npz
would be over the backend's 100 MiB with its size; a frame feature is never exported (the format
holds vectors only). The npz is written member by member with `allow_pickle=False` and fixed zip
dates (byte-reproducible), atomically, then its sidecar, atomically.
"""
from __future__ import annotations

import hashlib
import json
import os
import zipfile
from pathlib import Path
from typing import Any, Iterable

import numpy as np

from hope_models.data.extract import EpisodeMismatch, group_matrix
from hope_models.data.features import FeatureGroup, FeatureSpec, FeatureSpecError, is_number
from hope_models.data.spec_inference import episode_signature, infer_spec
from hope_models.data.spec_request import SpecRequest
from hope_models.durable import atomic_open, atomic_write, file_sha256
from hope_models.rlds.episode import Episode
from hope_models.rlds.export_cloud import export_each
from hope_models.rlds.read_npz import CLOUD_MAX_BYTES, FORMAT, NPZ_SUFFIX, sidecar_path
from hope_models.rlds.validation_report import exception_entry
from hope_models.rlds.write_episode_dir import safe_episode_id

ZIP_DATE = (1980, 1, 1, 0, 0, 0)  # the earliest a zip can say: no clock in the bytes


class NpzTooLarge(ValueError):
    """The episode's npz would be over the backend's limit; the message gives both sizes."""


def episode_spec(ep: Episode, request: SpecRequest | None = None) -> FeatureSpec:
    """The spec this episode is exported with: the request's fields, the rest inferred from the
    episode itself; never a frame."""
    request = request or SpecRequest()
    frame = request.frame
    request = SpecRequest(request.observation, request.action, None, True, request.std_floor)
    if not ep.steps:
        raise FeatureSpecError("episode has no steps")
    spec = infer_spec([episode_signature(ep.episode_id, ep.steps, ep.blob_root, check_cameras=False)], request)
    if frame is not None:
        spec.notes.append(f"{frame.path}: frame not exported, the cloud npz holds vectors only")
    return spec


def _float32(matrix: np.ndarray, group: FeatureGroup) -> np.ndarray:
    out = matrix.astype(np.float32)
    bad = np.argwhere(~np.isfinite(out))
    if len(bad):
        step, col = int(bad[0][0]), int(bad[0][1])
        names = group.dim_names()
        raise EpisodeMismatch(f"value {matrix[step, col]!r} does not fit in float32", step,
                              names[col].split("[")[0])
    return out


def cloud_arrays(ep: Episode, spec: FeatureSpec) -> tuple[dict[str, np.ndarray], int | None]:
    """The npz arrays of an episode, and the clock origin (ns) of `timestamps`; EpisodeMismatch
    names the step and field that do not fit."""
    arrays = {"observations": _float32(group_matrix(ep.steps, spec.observation), spec.observation),
              "actions": _float32(group_matrix(ep.steps, spec.action), spec.action)}
    rewards = np.asarray([s.reward for s in ep.steps], dtype=np.float64)
    if not np.isfinite(rewards.astype(np.float32)).all():
        raise EpisodeMismatch("is NaN, infinite or beyond float32", int(np.argwhere(
            ~np.isfinite(rewards.astype(np.float32)))[0][0]), "reward")
    arrays["rewards"] = rewards.astype(np.float32)
    clock = [s.timestamp_ns for s in ep.steps]
    if not all(type(t) is int for t in clock):
        return arrays, None
    origin = clock[0]
    arrays["timestamps"] = np.asarray([t - origin for t in clock], dtype=np.float64) / 1e9
    return arrays, origin


def field_layout(ep: Episode, group: FeatureGroup) -> list[dict[str, Any]]:
    """Each field's place in the matrix and the type its first step holds (a list, a bool, a
    number), so the reader rebuilds the step as it was."""
    out, offset = [], 0
    first = ep.steps[0]
    for f in group.fields:
        value: Any = {"observation": first.observation, "action": first.action}
        for part in f.path.split("."):
            value = value.get(part) if isinstance(value, dict) else None
        kind = "bool" if isinstance(value, bool) else "number" if is_number(value) and f.size == 1 else "vector"
        out.append({"path": f.path, "size": f.size, "offset": offset, "kind": kind})
        offset += f.size
    return out


def task_name(metadata: dict[str, Any]) -> str | None:
    """The task as the Continuon producers name it: `task_name` (the brain's task library), `task`,
    the app's `task_classification.tasks`, or a simulated episode's task."""
    for value in (metadata.get("task_name"), metadata.get("task")):
        if isinstance(value, str) and value:
            return value
    classification = metadata.get("task_classification")
    tasks = classification.get("tasks") if isinstance(classification, dict) else None
    if isinstance(tasks, list) and tasks and isinstance(tasks[0], str):
        return tasks[0]
    provenance = metadata.get("provenance")
    sim = provenance.get("sim") if isinstance(provenance, dict) else None
    task = sim.get("task") if isinstance(sim, dict) else None
    return task if isinstance(task, str) and task else None


def query_fields(ep: Episode, episode_id: str) -> dict[str, Any]:
    """What `POST /episodes/{robot_id}` takes as query fields."""
    success = ep.metadata.get("success")
    return {"episode_id": episode_id, "task_name": task_name(ep.metadata),
            "duration_seconds": max(0.0, ep.duration_s), "num_steps": len(ep.steps),
            "success": success if isinstance(success, bool) else None}


def _write_npz(final: Path, arrays: dict[str, np.ndarray], max_bytes: int) -> int:
    """Writes the npz atomically; NpzTooLarge (and nothing written) past max_bytes."""
    floor = sum(a.nbytes for a in arrays.values())
    if floor > max_bytes:
        raise NpzTooLarge(f"its npz would be over {floor} bytes, above the cloud's limit of {max_bytes} bytes")
    with atomic_open(final, "wb") as f:
        with zipfile.ZipFile(f, "w", zipfile.ZIP_STORED, allowZip64=True) as archive:
            for name, array in arrays.items():
                info = zipfile.ZipInfo(f"{name}.npy", date_time=ZIP_DATE)
                info.external_attr = 0o644 << 16
                with archive.open(info, "w", force_zip64=True) as member:
                    np.lib.format.write_array(member, np.ascontiguousarray(array), allow_pickle=False)
        size = f.tell()
        if size > max_bytes:
            raise NpzTooLarge(f"its npz is {size} bytes, above the cloud's limit of {max_bytes} bytes")
    return size


def write_cloud_npz(ep: Episode, spec: FeatureSpec, out_dir: str | os.PathLike, episode_id: str | None = None,
                    max_bytes: int = CLOUD_MAX_BYTES) -> tuple[Path, Path]:
    """Writes <out_dir>/<episode_id>.npz and its sidecar; returns both paths. Does not validate
    (export_npz_paths does). Raises EpisodeMismatch, NpzTooLarge, or ValueError/TypeError for
    metadata JSON cannot hold."""
    episode_id = safe_episode_id(episode_id or ep.episode_id)
    arrays, origin = cloud_arrays(ep, spec)
    described: dict[str, Any] = {
        name: {"shape": list(a.shape), "dtype": str(a.dtype)} for name, a in arrays.items()}
    described["observations"]["fields"] = field_layout(ep, spec.observation)
    described["actions"]["fields"] = field_layout(ep, spec.action)
    if origin is not None:
        described["timestamps"].update(unit="s", origin_ns=origin)
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    final = out / f"{episode_id}{NPZ_SUFFIX}"
    sidecar = {"format": FORMAT, "episode_id": episode_id, "npz": {"file": final.name},
               "query": query_fields(ep, episode_id), "arrays": described,
               "terminal_steps": [i for i, s in enumerate(ep.steps) if s.is_terminal],
               "spec": spec.to_json_obj(), "metadata": ep.metadata}
    json.dumps(sidecar, allow_nan=False)  # metadata JSON cannot hold is refused before any file is written
    size = _write_npz(final, arrays, max_bytes)
    sidecar["npz"].update(bytes=size, sha256=file_sha256(final))
    atomic_write(sidecar_path(final), json.dumps(sidecar, indent=1, allow_nan=False) + "\n")
    return final, sidecar_path(final)


def _export_one(ep: Episode, entry: dict[str, Any], out_dir: str | os.PathLike, request: SpecRequest | None,
                used_ids: set[str], max_bytes: int) -> dict[str, Any]:
    try:
        spec = episode_spec(ep, request)
        episode_id = safe_episode_id(ep.episode_id)
        if episode_id in used_ids:
            # Two sources with one id would overwrite each other's files.
            episode_id = f"{episode_id}-{hashlib.sha256(ep.source.encode('utf-8', 'surrogatepass')).hexdigest()[:8]}"
            entry = dict(entry, warnings=entry["warnings"] + [
                f"{ep.source}: metadata.episode_id: {ep.episode_id!r} was already exported in this run; "
                f"written as {episode_id!r}"])
        npz, sidecar = write_cloud_npz(ep, spec, out_dir, episode_id, max_bytes)
        used_ids.add(episode_id)
        return dict(entry, action="exported", package=str(npz), sidecar=str(sidecar))
    except (EpisodeMismatch, FeatureSpecError) as exc:
        failed = dict(exception_entry(ep.source, exc, ep.episode_id),
                      errors=[f"{ep.source}: does not fit the feature spec: {exc}"])
    except (OSError, ValueError, TypeError) as exc:  # NpzTooLarge is a ValueError
        failed = exception_entry(ep.source, exc, ep.episode_id)
        if isinstance(exc, NpzTooLarge):
            failed["errors"] = [f"{ep.source}: episode {ep.episode_id!r}: {exc}"]
    return dict(failed, action="refused", package=None, sidecar=None, warnings=entry["warnings"])


def export_npz_paths(paths: Iterable[str | os.PathLike], out_dir: str | os.PathLike,
                     request: SpecRequest | None = None, allow_invalid: bool = False,
                     max_bytes: int = CLOUD_MAX_BYTES, **reader_options: Any) -> dict[str, Any]:
    """Checks every episode under `paths` with the train profile (the backend asks nothing of the
    metadata, but the arrays must be trainable) and writes those that pass (all with
    `allow_invalid`, which still refuses an episode that does not fit its spec or the size)."""
    return export_each(paths, "train", allow_invalid,
                       lambda ep, entry, used_ids: _export_one(ep, entry, out_dir, request, used_ids, max_bytes),
                       {"package": None, "sidecar": None}, **reader_options)
