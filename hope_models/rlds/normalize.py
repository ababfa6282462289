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
        return new if any(a is not b for a, b in zip(new, obj, strict=True)) else obj
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
    md = _unwrapped(raw, warn)
    _lift_dotted_continuon(md, warn)
    _lift_nested_continuon(md, warn)
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
    provenance = _provenance(md.get("provenance"), layout, warn)

    md.pop("schema_version", None)
    md.pop("episode_id", None)
    md.pop("provenance", None)
    return {"schema_version": SCHEMA_VERSION, "episode_id": episode_id, **md, "provenance": provenance}


def _unwrapped(raw: Any, warn: Warn) -> dict[str, Any]:
    """The metadata as a snake_case dict without nulls, out of a legacy `episode_metadata` wrapper."""
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
    return md


def _lift_dotted_continuon(md: dict[str, Any], warn: Warn) -> None:
    """Literal dotted keys written by the Kotlin app (`continuon.xr_mode`) to their plain names."""
    for key in [k for k in md if isinstance(k, str) and k.startswith("continuon.")]:
        name = key[len("continuon."):]
        if name not in md:
            md[name] = md.pop(key)
        elif md[name] == md[key]:
            del md[key]
        else:
            warn(f"{key}={md[key]!r} disagrees with {name}={md[name]!r}; kept both, {name} is used", key)


def _lift_nested_continuon(md: dict[str, Any], warn: Warn) -> None:
    """Legacy files nest xr_mode, control_role and tags under `continuon`: lift them to the top."""
    nested = md.get("continuon")
    if not isinstance(nested, dict):
        return
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


def _provenance(provenance: Any, layout: str, warn: Warn) -> dict[str, Any]:
    """The provenance object with an origin (`import:<layout>` when the producer gave none)."""
    if isinstance(provenance, dict):
        if not provenance.get("origin"):
            provenance = {**provenance, "origin": f"import:{layout}"}
        return provenance
    if provenance is not None:
        warn(f"provenance is a {type(provenance).__name__}, not an object; kept as provenance.notes",
             "provenance")
        return {"origin": f"import:{layout}", "notes": provenance}
    return {"origin": f"import:{layout}"}


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
    where = {"step": index, "source": source}  # what every problem of this step names
    observation = _observation(obj.pop("observation", None), ep, where, trusted)
    action = _action(obj.pop("action", None), ep, where)
    reward = _reward(obj.pop("reward", None), ep, where)
    is_terminal = _is_terminal(obj.pop("is_terminal", None), ep, where)
    step_metadata = _step_metadata(obj.pop("step_metadata", None), ep, where)

    obj.pop("episode_id", None)  # grouping key of steps-only files; the episode carries it
    source_index = obj.pop("step_index", None)
    if source_index is not None and source_index != index:
        obj["source_step_index"] = source_index

    return Step(observation=observation, action=action, reward=reward, is_terminal=is_terminal,
                step_metadata=step_metadata, extras=obj)


def _observation(observation: Any, ep: Episode, where: dict[str, Any], trusted: bool) -> dict[str, Any]:
    if observation is None:
        ep.warn("step has no observation", field="observation", **where)
        return {}
    if not isinstance(observation, dict):
        ep.error(f"observation is a JSON {type(observation).__name__}, not an object", field="observation",
                 **where)
        return {}
    if not trusted:
        for alias, name in OBSERVATION_ALIASES.items():
            if alias in observation and name not in observation:
                observation = {(name if k == alias else k): v for k, v in observation.items()}
    return observation


def _action(action: Any, ep: Episode, where: dict[str, Any]) -> dict[str, Any]:
    if action is None:
        ep.warn("step has no action", field="action", **where)
        return {}
    if isinstance(action, list):
        ep.warn("action is a bare list; read as action.command", field="action", **where)
        return {"command": action}
    if not isinstance(action, dict):
        ep.error(f"action is a JSON {type(action).__name__}, not an object", field="action", **where)
        return {}
    return action


def _reward(reward: Any, ep: Episode, where: dict[str, Any]) -> float:
    if reward is None:
        return 0.0
    if isinstance(reward, (int, float)) and not isinstance(reward, bool):
        return float(reward)
    try:
        return float(reward)  # numeric strings
    except (TypeError, ValueError):
        ep.error(f"reward {reward!r} is not a number", field="reward", **where)
        return 0.0


def _is_terminal(terminal: Any, ep: Episode, where: dict[str, Any]) -> bool:
    if terminal is None:
        return False
    parsed = _as_bool(terminal)
    if parsed is None:
        ep.error(f"is_terminal {terminal!r} is not a boolean", field="is_terminal", **where)
        return False
    return parsed


def _step_metadata(meta: Any, ep: Episode, where: dict[str, Any]) -> dict[str, Any]:
    if meta is None:
        return {}
    if isinstance(meta, dict):
        return meta
    if isinstance(meta, str):
        return {"text": meta} if meta else {}
    ep.warn(f"step_metadata is a JSON {type(meta).__name__}; kept as step_metadata.value",
            field="step_metadata", **where)
    return {"value": meta}


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
