"""Promotion pointer files: which checkpoint each component serves, one small JSON file each.

    $HOPE_HOME/promoted/<component>.json
    {"component": "fast_loop", "checkpoint": "/abs/.../checkpoints/00002000",
     "version": "<run>@<step>:<sha12>", "sha256": "<hex of model.safetensors>",
     "model_id": 7, "run_id": "r-..." | null, "promoted_at": "<ISO 8601 UTC>"}

The pointer is what the serving side reads (BrainService watches it; `eval-reflex --checkpoint
promoted` resolves it); the models table in the registry is the history. A pointer is replaced
atomically (a temp file in the same dir, fsynced, renamed over the old one, the dir fsynced), so
a reader sees the old pointer or the new one, never half of one, even across a power cut.

The version a pointer records is checkpoint_format.version_name, the one rule that names a set of
weights (BrainService and ReflexPolicy name what they serve with it too). This module sits at the
bottom of the package, beside checkpoint_format.py: the promotion writes pointers (the daemon, the
gate's `promote` command) and the torch-free runtime reads them (BrainService), and neither of
those imports the other.
"""
from __future__ import annotations

import json
import os
import re
from pathlib import Path
from typing import Any

from hope_models import checkpoint_format
from hope_models.durable import atomic_write, fsync_path

POINTER_DIR = "promoted"
# The fields a pointer must hold, and their JSON types (None allowed where the tuple says so).
POINTER_FIELDS: dict[str, tuple[type, ...]] = {
    "component": (str,),
    "checkpoint": (str,),
    "version": (str,),
    "sha256": (str,),
    "model_id": (int,),
    "run_id": (str, type(None)),
    "promoted_at": (str,),
}
# A component name becomes a file name: keep it to a safe alphabet (no separators, no dots).
_COMPONENT_RE = re.compile(r"^[a-z][a-z0-9_]{0,31}$")
_SHA_RE = re.compile(r"^[0-9a-f]{64}$")


class PointerError(ValueError):
    """A pointer file cannot be read or written as asked; the message names the file and why."""


def _check_component(component: Any) -> str:
    if not isinstance(component, str) or not _COMPONENT_RE.match(component):
        raise PointerError(f"component {component!r} is not a valid component name ([a-z][a-z0-9_]*)")
    return component


def pointer_path(home: str | os.PathLike, component: str) -> Path:
    """$HOPE_HOME/promoted/<component>.json (the file need not exist)."""
    return Path(home) / POINTER_DIR / f"{_check_component(component)}.json"


def _validate(obj: Any, where: str, component: str | None = None) -> dict[str, Any]:
    if not isinstance(obj, dict):
        raise PointerError(f"{where}: must be a JSON object, got {type(obj).__name__}")
    for key, types in POINTER_FIELDS.items():
        if key not in obj:
            raise PointerError(f"{where}: field {key!r} is missing")
        value = obj[key]
        if isinstance(value, bool) or not isinstance(value, types):
            want = " or ".join("null" if t is type(None) else t.__name__ for t in types)
            raise PointerError(f"{where}: field {key!r} must be {want}, got {value!r}")
    if component is not None and obj["component"] != component:
        raise PointerError(f"{where}: names component {obj['component']!r}, expected {component!r}")
    if not Path(obj["checkpoint"]).is_absolute():
        raise PointerError(f"{where}: field 'checkpoint' must be an absolute path, got {obj['checkpoint']!r}")
    if not _SHA_RE.match(obj["sha256"]):
        raise PointerError(f"{where}: field 'sha256' must be 64 lowercase hex digits, got {obj['sha256']!r}")
    return obj


def read_pointer(home: str | os.PathLike, component: str) -> dict[str, Any] | None:
    """The pointer of `component`, or None when nothing has been promoted yet.

    PointerError (naming the file) when the file exists but is not a valid pointer: a corrupt
    pointer must be noticed, not read as "no model"."""
    path = pointer_path(home, component)
    try:
        raw = path.read_bytes()
    except FileNotFoundError:
        return None
    except OSError as exc:
        raise PointerError(f"{path}: cannot read: {exc.strerror or exc}") from None
    try:
        obj = json.loads(raw.decode("utf-8"))
    except (UnicodeDecodeError, json.JSONDecodeError) as exc:
        raise PointerError(f"{path}: not valid JSON: {exc}") from None
    return _validate(obj, str(path), component)


def write_pointer(home: str | os.PathLike, component: str, obj: dict[str, Any]) -> Path:
    """Replace the pointer of `component` atomically with `obj` (validated first). Returns the path."""
    path = pointer_path(home, component)
    obj = _validate(dict(obj), f"pointer for {component}", component)
    data = (json.dumps(obj, indent=1, sort_keys=True, allow_nan=False) + "\n").encode("utf-8")
    path.parent.mkdir(parents=True, exist_ok=True)
    try:
        atomic_write(path, data)
    except OSError as exc:
        raise PointerError(f"{path}: cannot write: {exc.strerror or exc}") from None
    return path


def remove_pointer(home: str | os.PathLike, component: str) -> bool:
    """Delete the pointer (nothing promoted any more). True if there was one."""
    path = pointer_path(home, component)
    try:
        path.unlink()
    except FileNotFoundError:
        return False
    fsync_path(path.parent)
    return True


def checkpoint_version(ckpt_dir: str | os.PathLike) -> tuple[str, str]:
    """(version, sha256 of model.safetensors) a pointer records for a checkpoint dir
    (checkpoint_format.checkpoint_version); PointerError when the weights cannot be read."""
    try:
        return checkpoint_format.checkpoint_version(ckpt_dir)
    except checkpoint_format.CheckpointError as exc:
        raise PointerError(str(exc)) from None


__all__ = ["PointerError", "pointer_path", "read_pointer", "write_pointer", "remove_pointer", "checkpoint_version",
           "POINTER_DIR", "POINTER_FIELDS"]
