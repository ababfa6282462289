"""Map what producers wrote onto the canonical v1.1 names, keeping everything else.

Readers parse a container into plain dicts; this module turns those dicts into canonical
metadata and `Step`s: camelCase keys become snake_case, aliases (`obs`, `done`, `gloveFrame`,
`episode_metadata`, `continuon.*`, Kotlin software keys) become the documented names, and
structural surprises are recorded as problems on the episode. Values are never changed here
(units and clocks are `timestamps.py`'s job, content rules are validation's).
"""
from __future__ import annotations

import re
from functools import lru_cache
from typing import Any, Callable

from .episode import SCHEMA_VERSION, Episode, Step

# Only keys that start lower-case and contain an upper-case letter are camelCase; PascalCase,
# CONSTANT_CASE and dotted keys are left as written because guessing at them loses information.
_CAMEL_HEAD = re.compile(r"(.)([A-Z][a-z]+)")
_CAMEL_TAIL = re.compile(r"([a-z0-9])([A-Z])")

STEP_ALIASES = {"obs": "observation", "done": "is_terminal"}
OBSERVATION_ALIASES = {"glove_frame": "glove"}
# Kotlin's SoftwareInfo field names (after snake-casing) -> documented software keys
SOFTWARE_ALIASES = {
    "xr_app_version": "xr_app",
    "brain_version": "continuonbrain_os",
    "glove_firmware_version": "glove_firmware",
}
# keys Kotlin writes as literal dotted names and legacy files nest under "continuon"
CONTINUON_LIFTED = ("xr_mode", "control_role")

Warn = Callable[[str, str | None], None]  # (message, field path)


@lru_cache(maxsize=8192)
def snake(key: str) -> str:
    if not key or not key[0].islower() or key.islower() or "." in key:
        return key
    if not any(c.isupper() for c in key):
        return key
    return _CAMEL_TAIL.sub(r"\1_\2", _CAMEL_HEAD.sub(r"\1_\2", key)).lower()


def snake_keys(obj: Any) -> Any:
    """Recursively snake_case dict keys. Returns the same object when nothing changes, so
    already-canonical data costs a walk and no copies. When both `fooBar` and `foo_bar` exist
    in one dict, the snake_case one wins and the camelCase one is kept under its own name."""
    t = type(obj)
    if t is dict:
        changed = False
        pairs = []
        for k, v in obj.items():
            nk = snake(k) if type(k) is str else k
            nv = snake_keys(v) if type(v) in (dict, list) else v
            if nk != k or nv is not v:
                changed = True
            pairs.append((k, nk, nv))
        if not changed:
            return obj
        out: dict[Any, Any] = {}
        for k, nk, nv in pairs:
            if nk != k and nk in obj:
                out[k] = nv  # the snake_case original takes the name
            else:
                out[nk] = nv
        return out
    if t is list:
        if not any(type(x) in (dict, list) for x in obj):
            return obj
        new = [snake_keys(x) for x in obj]
        return new if any(a is not b for a, b in zip(new, obj)) else obj
    return obj


def _drop_nulls(obj: Any) -> Any:
    # Kotlin's serializer writes every absent optional as an explicit null; in metadata a null
    # carries no information and would only trip "wrong type" checks downstream.
    if type(obj) is dict:
        return {k: _drop_nulls(v) for k, v in obj.items() if v is not None}
    return obj


# -- metadata -------------------------------------------------------------------------------

def normalize_metadata(raw: Any, *, layout: str, fallback_id: str, warn: Warn) -> dict[str, Any]:
    """Canonical v1.1 metadata from any producer's metadata object (or None)."""
    if raw is None:
        md: dict[str, Any] = {}
    elif isinstance(raw, dict):
        md = dict(raw)
    else:
        warn(f"metadata is a JSON {type(raw).__name__}, not an object; ignored", "metadata")
        md = {}

    wrapped = md.pop("episode_metadata", None)
    if isinstance(wrapped, dict):
        outer = md
        md = dict(wrapped)
        for k, v in outer.items():
            md.setdefault(k, v)
    elif wrapped is not None:
        md["episode_metadata"] = wrapped

    md = snake_keys(_drop_nulls(md))
    if not isinstance(md, dict):  # pragma: no cover - _drop_nulls keeps dicts dicts
        md = {}

    # literal dotted keys written by the Kotlin app
    for key in [k for k in md if isinstance(k, str) and k.startswith("continuon.")]:
        name = key[len("continuon."):]
        if name not in md:
            md[name] = md.pop(key)
        elif md[name] == md[key]:
            del md[key]
        else:
            warn(f"{key}={md[key]!r} disagrees with {name}={md[name]!r}; kept both, {name} is used", key)

    nested = md.get("continuon")
    if isinstance(nested, dict):
        nested = dict(nested)
        for name in CONTINUON_LIFTED:
            if name not in nested:
                continue
            if name not in md:
                md[name] = nested.pop(name)
            elif md[name] == nested[name]:
                nested.pop(name)
            else:
                warn(f"continuon.{name}={nested[name]!r} disagrees with {name}={md[name]!r}; "
                     f"kept both, {name} is used", f"continuon.{name}")
        if isinstance(nested.get("tags"), list):
            tags = md.get("tags")
            if tags is None:
                md["tags"] = nested.pop("tags")
            elif isinstance(tags, list):
                md["tags"] = tags + [t for t in nested.pop("tags") if t not in tags]
        if nested:
            md["continuon"] = nested
        else:
            del md["continuon"]

    software = md.get("software")
    if isinstance(software, dict):
        software = dict(software)
        for old, new in SOFTWARE_ALIASES.items():
            if old in software and new not in software:
                software[new] = software.pop(old)
        md["software"] = software

    original_version = md.get("schema_version")
    if original_version != SCHEMA_VERSION:
        md.setdefault("source_schema_version", "1.0" if original_version is None else str(original_version))

    episode_id = md.get("episode_id")
    if episode_id is None or episode_id == "":
        episode_id = fallback_id
    elif not isinstance(episode_id, str):
        episode_id = str(episode_id)

    provenance = md.get("provenance")
    if isinstance(provenance, dict):
        if not provenance.get("origin"):
            provenance = {**provenance, "origin": f"import:{layout}"}
    else:
        if provenance is not None:
            warn(f"provenance is a {type(provenance).__name__}, not an object; kept as provenance.notes",
                 "provenance")
            provenance = {"origin": f"import:{layout}", "notes": provenance}
        else:
            provenance = {"origin": f"import:{layout}"}

    md.pop("schema_version", None)
    md.pop("episode_id", None)
    md.pop("provenance", None)
    return {"schema_version": SCHEMA_VERSION, "episode_id": episode_id, **md, "provenance": provenance}


# -- steps ----------------------------------------------------------------------------------

_TRUE = {"true", "1", "yes"}
_FALSE = {"false", "0", "no", ""}


def _as_bool(value: Any) -> bool | None:
    if isinstance(value, bool):
        return value
    if isinstance(value, int) and value in (0, 1):
        return bool(value)
    if isinstance(value, float) and value in (0.0, 1.0):
        return bool(value)
    if isinstance(value, str):
        v = value.strip().lower()
        if v in _TRUE:
            return True
        if v in _FALSE:
            return False
    return None


def step_from_obj(raw: dict[str, Any], index: int, ep: Episode, *, source: str | None = None,
                  trusted: bool = False) -> Step:
    """Build a Step from one parsed step object, recording structural problems on `ep`.

    `trusted` is for our own canonical files: keys are known to be snake_case already, so the
    recursive key walk is skipped (it is the one cost that scales with the payload size).
    Clock fields (`timestamp_ns`, `timestamp_micros`, ...) stay in `extras` until
    `timestamps.assign_timestamps` picks one."""
    obj = dict(raw) if trusted else snake_keys(raw)
    if obj is raw:
        obj = dict(raw)
    for alias, name in STEP_ALIASES.items():
        if alias in obj and name not in obj:
            obj[name] = obj.pop(alias)

    observation = obj.pop("observation", None)
    if observation is None:
        ep.warn("step has no observation", step=index, field="observation", source=source)
        observation = {}
    elif not isinstance(observation, dict):
        ep.error(f"observation is a JSON {type(observation).__name__}, not an object", step=index,
                 field="observation", source=source)
        observation = {}
    elif not trusted:
        for alias, name in OBSERVATION_ALIASES.items():
            if alias in observation and name not in observation:
                observation = {(name if k == alias else k): v for k, v in observation.items()}

    action = obj.pop("action", None)
    if action is None:
        ep.warn("step has no action", step=index, field="action", source=source)
        action = {}
    elif isinstance(action, list):
        ep.warn("action is a bare list; read as action.command", step=index, field="action", source=source)
        action = {"command": action}
    elif not isinstance(action, dict):
        ep.error(f"action is a JSON {type(action).__name__}, not an object", step=index, field="action",
                 source=source)
        action = {}

    reward_raw = obj.pop("reward", None)
    if reward_raw is None:
        reward = 0.0
    elif isinstance(reward_raw, (int, float)) and not isinstance(reward_raw, bool):
        reward = float(reward_raw)
    else:
        try:
            reward = float(reward_raw)  # numeric strings
        except (TypeError, ValueError):
            ep.error(f"reward {reward_raw!r} is not a number", step=index, field="reward", source=source)
            reward = 0.0

    terminal_raw = obj.pop("is_terminal", None)
    if terminal_raw is None:
        is_terminal = False
    else:
        parsed = _as_bool(terminal_raw)
        if parsed is None:
            ep.error(f"is_terminal {terminal_raw!r} is not a boolean", step=index, field="is_terminal",
                     source=source)
            parsed = False
        is_terminal = parsed

    meta = obj.pop("step_metadata", None)
    if meta is None:
        step_metadata: dict[str, Any] = {}
    elif isinstance(meta, dict):
        step_metadata = meta
    elif isinstance(meta, str):
        step_metadata = {"text": meta} if meta else {}
    else:
        ep.warn(f"step_metadata is a JSON {type(meta).__name__}; kept as step_metadata.value", step=index,
                field="step_metadata", source=source)
        step_metadata = {"value": meta}

    obj.pop("episode_id", None)  # grouping key of steps-only files; the episode carries it
    source_index = obj.pop("step_index", None)
    if source_index is not None and source_index != index:
        obj["source_step_index"] = source_index

    return Step(observation=observation, action=action, reward=reward, is_terminal=is_terminal,
                step_metadata=step_metadata, extras=obj)


def _has_upper(d: dict) -> bool:
    return any(type(k) is str and k != k.lower() for k in d)


def canonical_step(obj: dict[str, Any], index: int) -> Step | None:
    """The lean path for our own canonical lines: a Step when every core field already has its
    canonical type and the top-level keys (of the step, observation and action) are lower-case,
    else None so the caller takes `step_from_obj`. No copies, no recursive key walk.
    Consumes `obj` (it becomes the step's extras)."""
    observation = obj.get("observation")
    action = obj.get("action")
    reward = obj.get("reward", 0.0)
    is_terminal = obj.get("is_terminal", False)
    meta = obj.get("step_metadata")
    if (type(observation) is not dict or type(action) is not dict or type(is_terminal) is not bool
            or type(reward) not in (float, int) or (meta is not None and type(meta) is not dict)
            or obj.get("step_index") != index or "episode_id" in obj
            or _has_upper(obj) or _has_upper(observation) or _has_upper(action)):
        return None
    for key in ("observation", "action", "reward", "is_terminal", "step_metadata", "step_index"):
        obj.pop(key, None)
    return Step(observation=observation, action=action, reward=float(reward), is_terminal=is_terminal,
                step_metadata=meta if meta is not None else {}, extras=obj)


def id_from_name(name: str) -> str:
    """Episode id from a file or directory name: strip the container extensions."""
    for suffix in (".gz", ".tfrecord", ".tfrecords", ".jsonl", ".json", ".mcap"):
        if name.endswith(suffix) and len(name) > len(suffix):
            name = name[: -len(suffix)]
    return name
