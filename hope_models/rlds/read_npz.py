"""Read ContinuonCloud's episode upload format: `<episode_id>.npz` beside its `<episode_id>.npz.json`.

ContinuonCloud's backend (`POST /episodes/{robot_id}`) stores one `.npz` per episode, at most
100 MiB, holding `observations` [T, obs_dim], `actions` [T, act_dim] and optionally `rewards` [T]
and `timestamps` [T]; the episode's `episode_id`, `task_name`, `duration_seconds`, `num_steps` and
`success` travel as query fields. The arrays carry no names, so the exporter
(`hope_models/data/export_npz.py`) writes a sidecar JSON beside each file that says which dotted
field each column block is, and the query fields:

    {"format": "hope.cloud_npz/1", "episode_id": ...,
     "npz": {"file": "<id>.npz", "bytes": N, "sha256": ...},
     "query": {"episode_id", "task_name", "duration_seconds", "num_steps", "success"},
     "arrays": {"observations": {"shape": [T, D], "dtype": "float32",
                                 "fields": [{"path", "size", "offset", "kind"}, ...]},
                "actions": {... the same ...},
                "rewards": {"shape": [T], "dtype": "float32"},
                "timestamps": {"shape": [T], "dtype": "float64", "unit": "s", "origin_ns": int}},
     "terminal_steps": [...], "spec": {the feature spec}, "metadata": {the episode's metadata}}

`kind` is "number", "bool" or "vector" (a list), so a step is rebuilt with the types it had.
Timestamps are seconds since the first step (exact to the nanosecond for any real episode);
`origin_ns` is the first step's clock. The sidecar is read here without the data tier: it holds
the field paths itself.

Nothing is unpickled: every member's .npy header is read first and an object dtype is refused,
the archive is opened with `allow_pickle=False`, only the four array names are allowed, and each
array's shape must be the one its sidecar states. A missing sidecar, a sidecar from another
export (sha256), or a shape that differs is an error naming the file and the array. A member that
declares more than inflate_cap of its compressed size (rlds/inflate.py) is refused before it is
inflated (InflateError): zipfile never inflates past the declared size.
"""
from __future__ import annotations

import math
import os
import zipfile
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from ..durable import file_sha256
from .episode import ERROR, Episode, Problem, SourceReport, Step
from .inflate import InflateError, inflate_cap
from .json_text import ReadLimits, TextReadError, parse_json_document, read_text
from .normalize import normalize_metadata

FORMAT = "hope.cloud_npz/1"
LAYOUT = "cloud_npz"
NPZ_SUFFIX = ".npz"
SIDECAR_SUFFIX = ".npz.json"
# The backend answers 413 when len(content) > 100 * 1024 * 1024.
CLOUD_MAX_BYTES = 100 * 1024 * 1024
VECTORS = {"observations": "observation", "actions": "action"}  # array -> the step key its fields start with
ARRAYS = ("observations", "actions", "rewards", "timestamps")
FIELD_KINDS = ("number", "bool", "vector")


class NpzFormatError(ValueError):
    """The pair cannot be read; the message names the file and the array or sidecar key."""


@dataclass
class FieldLayout:
    path: str  # dotted, starting with "observation." or "action."
    size: int
    offset: int
    kind: str  # one of FIELD_KINDS


@dataclass
class Sidecar:
    path: Path
    fields: dict[str, list[FieldLayout]]  # "observations" / "actions" -> column blocks
    shapes: dict[str, tuple[int, ...]]  # array name -> the shape the sidecar states
    num_steps: int
    episode_id: str | None
    npz_sha256: str | None
    origin_ns: int
    terminal_steps: set[int] = field(default_factory=set)
    metadata: dict[str, Any] = field(default_factory=dict)


def sidecar_path(npz: str | os.PathLike) -> Path:
    """`x.npz` -> `x.npz.json` (a name discover passes over, like a manifest)."""
    npz = Path(npz)
    return npz.with_name(npz.name + ".json")


def read_npz(path: str | os.PathLike, limits: ReadLimits | None = None) -> SourceReport:
    limits = limits or ReadLimits()
    file = Path(path)
    report = SourceReport(source=str(file))
    try:
        sidecar = read_sidecar(file, limits)
        arrays = load_arrays(file, sidecar, limits)
    except NpzFormatError as exc:
        report.problems.append(Problem(ERROR, str(file), str(exc)))
        return report
    report.episodes.append(build_episode(file, sidecar, arrays))
    return report


# -- the sidecar ------------------------------------------------------------------------------

def _int(value: Any, where: str, minimum: int = 0) -> int:
    if type(value) is not int or value < minimum:
        raise NpzFormatError(f"{where}: must be an integer >= {minimum}, got {value!r}")
    return value


def _object(value: Any, where: str) -> dict[str, Any]:
    if not isinstance(value, dict):
        raise NpzFormatError(f"{where}: must be a JSON object, got {type(value).__name__}")
    return value


def _shape(value: Any, where: str, ndim: int) -> tuple[int, ...]:
    if not isinstance(value, list) or len(value) != ndim:
        raise NpzFormatError(f"{where}: must be a list of {ndim} integers, got {value!r}")
    return tuple(_int(v, where) for v in value)


def _fields(spec: dict[str, Any], name: str, where: str) -> list[FieldLayout]:
    raw = spec.get("fields")
    if not isinstance(raw, list) or not raw:
        raise NpzFormatError(f"{where}.fields: must be a non-empty list")
    root = VECTORS[name]
    out: list[FieldLayout] = []
    offset = 0
    for i, f in enumerate(raw):
        at = f"{where}.fields[{i}]"
        f = _object(f, at)
        path = f.get("path")
        if not isinstance(path, str) or not path.startswith(root + ".") or "" in path.split("."):
            raise NpzFormatError(f"{at}.path: must be a dotted path starting with {root!r}., got {path!r}")
        size = _int(f.get("size"), f"{at}.size", 1)
        kind = f.get("kind", "vector" if size > 1 else "number")
        if kind not in FIELD_KINDS or (kind != "vector" and size != 1):
            raise NpzFormatError(f"{at}.kind: {kind!r} with size {size} (kinds: {', '.join(FIELD_KINDS)}; "
                                 "a number or bool has size 1)")
        if f.get("offset", offset) != offset:
            raise NpzFormatError(f"{at}.offset: {f.get('offset')!r}, the sizes before it add up to {offset}")
        out.append(FieldLayout(path, size, offset, kind))
        offset += size
    paths = [f.path for f in out]
    for p in paths:
        parents = {".".join(p.split(".")[:k]) for k in range(2, p.count(".") + 1)}
        if paths.count(p) > 1 or parents & set(paths):
            raise NpzFormatError(f"{where}.fields: {p!r} is named twice or nested inside another field")
    return out


def read_sidecar(npz: Path, limits: ReadLimits) -> Sidecar:
    path = sidecar_path(npz)
    if not path.is_file():
        raise NpzFormatError(f"no sidecar {path.name} beside it: without it the columns of observations "
                             "and actions have no field names (export --cloud --format npz writes both)")
    try:
        doc = _object(parse_json_document(read_text(path, limits)), str(path))
    except TextReadError as exc:
        raise NpzFormatError(f"{path}: {exc}") from None
    if doc.get("format") != FORMAT:
        raise NpzFormatError(f"{path}: format: {doc.get('format')!r} is not {FORMAT!r}")
    arrays = _object(doc.get("arrays"), f"{path}: arrays")
    unknown = set(arrays) - set(ARRAYS)
    if unknown or not set(VECTORS) <= set(arrays):
        raise NpzFormatError(f"{path}: arrays: needs observations and actions, may have rewards and "
                             f"timestamps; got {sorted(arrays)}")
    fields: dict[str, list[FieldLayout]] = {}
    shapes: dict[str, tuple[int, ...]] = {}
    for name, spec in arrays.items():
        where = f"{path}: arrays.{name}"
        spec = _object(spec, where)
        shapes[name] = _shape(spec.get("shape"), f"{where}.shape", 2 if name in VECTORS else 1)
        if name in VECTORS:
            fields[name] = _fields(spec, name, where)
            width = sum(f.size for f in fields[name])
            if shapes[name][1] != width:
                raise NpzFormatError(f"{where}: shape {list(shapes[name])}, but its fields add up to {width} columns")
    query = _object(doc.get("query", {}), f"{path}: query")
    num_steps = _int(query.get("num_steps", shapes["observations"][0]), f"{path}: query.num_steps")
    for name, shape in shapes.items():
        if shape[0] != num_steps:
            raise NpzFormatError(f"{path}: arrays.{name}: {shape[0]} rows, query.num_steps is {num_steps}")
    npz_info = _object(doc.get("npz", {}), f"{path}: npz")
    sha = npz_info.get("sha256")
    origin = arrays.get("timestamps", {}).get("origin_ns", 0)
    terminal = doc.get("terminal_steps", [])
    if not isinstance(terminal, list):
        raise NpzFormatError(f"{path}: terminal_steps: must be a list of step indices")
    episode_id = query.get("episode_id", doc.get("episode_id"))
    return Sidecar(path, fields, shapes, num_steps,
                   episode_id if isinstance(episode_id, str) and episode_id else None,
                   sha if isinstance(sha, str) else None,
                   _int(origin, f"{path}: arrays.timestamps.origin_ns"),
                   {_int(t, f"{path}: terminal_steps") for t in terminal},
                   _object(doc.get("metadata", {}), f"{path}: metadata"))


# -- the arrays -------------------------------------------------------------------------------

def _header(archive: zipfile.ZipFile, member: str) -> tuple[tuple[int, ...], np.dtype]:
    with archive.open(member) as f:
        version = np.lib.format.read_magic(f)
        if version == (1, 0):
            shape, _, dtype = np.lib.format.read_array_header_1_0(f)
        else:
            shape, _, dtype = np.lib.format.read_array_header_2_0(f)
    return shape, dtype


def _check_inflation(file: Path, archive: zipfile.ZipFile, limits: ReadLimits) -> None:
    """A member may inflate to its declared size only (zipfile stops there, and its CRC then
    fails): that size within inflate_cap of its compressed bytes, and within an upload's budget."""
    for info in archive.infolist():
        cap = inflate_cap(info.compress_size, limits)
        if info.file_size > cap:
            raise InflateError(f"{file}: member {info.filename!r}: declares {info.file_size} bytes from "
                               f"{info.compress_size} compressed, more than {cap} (a decompression bomb?)")
        if limits.budget is not None:
            limits.budget.spend(info.file_size, f"{file}: member {info.filename!r}")


def _check_members(file: Path, sidecar: Sidecar, limits: ReadLimits) -> None:
    """Every member's .npy header against the sidecar, before any array data is read."""
    try:
        with zipfile.ZipFile(file) as archive:
            members = archive.namelist()
            expected = {f"{name}.npy" for name in sidecar.shapes}
            if sorted(members) != sorted(expected):
                raise NpzFormatError(f"members {sorted(members)}; its sidecar {sidecar.path.name} lists "
                                     f"{sorted(expected)}")
            _check_inflation(file, archive, limits)
            for member in members:
                name = member[:-len(".npy")]
                shape, dtype = _header(archive, member)
                if dtype.hasobject:
                    raise NpzFormatError(f"{name}: dtype {dtype} holds Python objects, which only pickle can "
                                         "load: refused")
                if dtype.kind not in "fiub":
                    raise NpzFormatError(f"{name}: dtype {dtype} is not numeric")
                if tuple(shape) != sidecar.shapes[name]:
                    raise NpzFormatError(f"{name}: shape {list(shape)}, its sidecar {sidecar.path.name} says "
                                         f"{list(sidecar.shapes[name])}")
                if math.prod(shape) * dtype.itemsize > limits.max_file_bytes:
                    raise NpzFormatError(f"{name}: {math.prod(shape) * dtype.itemsize} bytes unpacked, above "
                                         f"max_file_bytes={limits.max_file_bytes}")
    except (NpzFormatError, InflateError):
        raise
    except (zipfile.BadZipFile, ValueError, OSError, EOFError) as exc:
        raise NpzFormatError(f"not a readable .npz archive: {exc}") from None


def load_arrays(file: Path, sidecar: Sidecar, limits: ReadLimits) -> dict[str, np.ndarray]:
    try:
        size = file.stat().st_size
        if size > limits.max_file_bytes:
            raise NpzFormatError(f"file is {size} bytes, above the limit max_file_bytes={limits.max_file_bytes}")
        if sidecar.npz_sha256 is not None and file_sha256(file) != sidecar.npz_sha256:
            raise NpzFormatError(f"sha256 differs from the one in its sidecar {sidecar.path.name}: the two "
                                 "files are from different exports")
    except OSError as exc:
        raise NpzFormatError(f"cannot read file: {exc.strerror or exc}") from None
    _check_members(file, sidecar, limits)
    out: dict[str, np.ndarray] = {}
    try:
        with np.load(file, allow_pickle=False) as npz:
            for name in sidecar.shapes:
                out[name] = npz[name]
    except (ValueError, OSError, zipfile.BadZipFile) as exc:
        raise NpzFormatError(f"cannot load its arrays: {exc}") from None
    ts = out.get("timestamps")
    if ts is not None and not np.isfinite(ts.astype(np.float64)).all():
        bad = int(np.argwhere(~np.isfinite(ts.astype(np.float64)))[0][0])
        raise NpzFormatError(f"timestamps: step {bad} is NaN or infinite")
    return out


# -- the episode ------------------------------------------------------------------------------

def _place(target: dict[str, Any], layout: FieldLayout, row: list) -> None:
    *parents, leaf = layout.path.split(".")[1:]
    for part in parents:
        target = target.setdefault(part, {})
    value = row[layout.offset:layout.offset + layout.size]
    if layout.kind == "vector":
        target[leaf] = value
    elif layout.kind == "bool":
        target[leaf] = bool(value[0])
    else:
        target[leaf] = value[0]


def build_episode(file: Path, sidecar: Sidecar, arrays: dict[str, np.ndarray]) -> Episode:
    ep = Episode(episode_id="", metadata={}, steps=[], source=str(file), layout=LAYOUT)
    stem = file.name[:-len(NPZ_SUFFIX)] if file.name.endswith(NPZ_SUFFIX) else file.name
    fallback = sidecar.episode_id or stem
    ep.metadata = normalize_metadata(sidecar.metadata, layout=LAYOUT, fallback_id=fallback,
                                     warn=lambda msg, fld: ep.warn(msg, field=fld))
    ep.episode_id = str(ep.metadata["episode_id"])
    rows = {name: arrays[name].astype(np.float64).tolist() for name in VECTORS}
    rewards = arrays["rewards"].astype(np.float64).tolist() if "rewards" in arrays else None
    seconds = arrays.get("timestamps")
    for t in range(sidecar.num_steps):
        observation: dict[str, Any] = {}
        action: dict[str, Any] = {}
        for layout in sidecar.fields["observations"]:
            _place(observation, layout, rows["observations"][t])
        for layout in sidecar.fields["actions"]:
            _place(action, layout, rows["actions"][t])
        step = Step(observation=observation, action=action, reward=rewards[t] if rewards is not None else 0.0,
                    is_terminal=t in sidecar.terminal_steps)
        if seconds is not None:
            # seconds since the first step: exact back to the nanosecond below 2**53 ns (104 days)
            step.timestamp_ns = sidecar.origin_ns + round(float(seconds[t]) * 1e9)
        ep.steps.append(step)
    if not ep.steps:
        ep.warn("episode has no steps", field="steps")
    elif seconds is None:
        ep.warn("no timestamps array; timestamp_ns left empty", field="timestamps")
    return ep
