"""The feature spec: which numeric fields of a step form the observation and action vectors.

No vector size is fixed across the Continuon ecosystem, so each dataset gets its own spec,
inferred from the data and overridable by a JSON file. Inference flattens the numeric leaves of
`observation` and `action` (numbers, bools as 0/1, flat lists of numbers) into dotted paths and
keeps a field only when (nearly) every episode has it with the same length; an episode that then
does not fit the spec is excluded from the cache with the reason, never padded.

Spec JSON (the same shape is the override file, saved in the cache and in checkpoint config.json):

    {"format": "hope.feature_spec/1",
     "observation": {"fields": [{"path": "observation.robot_state.joint_positions", "size": 6}, ...],
                     "mean": [...], "std": [...]},
     "action": {"fields": [{"path": "action.command", "size": 6}], "mean": [...], "std": [...]},
     "frame": {"path": "observation.image_rgb", "shape": [64, 64, 3], "source": "inline"} or null,
     "std_floor": 0.001}

The frame is either inline (`source` "inline", the default when absent: a flat list of floats in
[0, 1] such as the vlm sample's `image_rgb`) or a blob (`source` "blob": `path` names an
observation object whose `uri` is a .npy file holding the frame, e.g. `observation.media.rgb`;
see frames.py). Inference prefers an inline `image_rgb`; without one it picks a .npy frame
reference that (nearly) every episode has and whose first file loads as a [64, 64, 3] frame.

In an override, a field may be a bare path string (size taken from the data), any group or the
frame may be left out (inferred), and mean/std may be left out (computed when the cache is built).
"""
from __future__ import annotations

import json
import math
import re
from collections import Counter
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from hope_models.data.frames import (
    BlobFrameError, frame_blob_refs, frame_blob_uri, load_frame_blob, resolve_blob_uri,
)

SPEC_FORMAT = "hope.feature_spec/1"
FRAME_FIELD = "image_rgb"
FRAME_SHAPE = (64, 64, 3)
FRAME_SOURCES = ("inline", "blob")  # image floats in the step / a .npy file the step references
DEFAULT_STD_FLOOR = 1e-3
DEFAULT_COVERAGE = 0.9  # "nearly every episode": a field missing from >10% of episodes is dropped
MAX_VECTOR = 4096  # longer flat lists are media (a frame, a waveform), not state


class FeatureSpecError(ValueError):
    """The spec cannot be built or loaded; the message names the field or file."""


# -- which leaves count --------------------------------------------------------------------------

_CAMEL = re.compile(r"([a-z0-9])([A-Z])")


def _is_clock_or_id(key: str) -> bool:
    """Clocks and ids are numbers but carry no signal a policy should see (and grow without bound)."""
    k = _CAMEL.sub(r"\1_\2", key).lower()
    return (k.startswith("timestamp") or k.endswith("_timestamp") or k.startswith("wall_time")
            or k.endswith(("_nanos", "_micros", "_millis", "_id", "_ids")) or k in {"step_index", "id", "seq"})


def _is_number(v: Any) -> bool:
    return isinstance(v, (int, float))  # bools included: they become 0/1


def numeric_leaves(obj: Any, prefix: str, out: dict[str, int] | None = None) -> dict[str, int]:
    """Dotted path -> length of every numeric leaf (scalars have length 1, empty lists length 0).

    Skips clocks and ids, blob references (objects with a `uri`) and the media block; the frame
    field is reported like any list so the caller can pick it out as a frame feature.
    """
    out = {} if out is None else out
    if not isinstance(obj, dict):
        return out
    if "uri" in obj:  # a blob reference: width/height/sample rate describe a file, not the robot
        return out
    for key, value in obj.items():
        if not isinstance(key, str) or _is_clock_or_id(key) or key == "media":
            continue
        path = f"{prefix}.{key}"
        if isinstance(value, dict):
            numeric_leaves(value, path, out)
        elif _is_number(value):
            out[path] = 1
        elif isinstance(value, list) and all(_is_number(v) for v in value):
            out[path] = len(value)
    return out


def step_signature(observation: dict, action: dict) -> dict[str, int]:
    sig = numeric_leaves(observation, "observation")
    numeric_leaves(action, "action", sig)
    return sig


# -- the spec ------------------------------------------------------------------------------------

@dataclass
class FeatureField:
    path: str  # dotted, starting with "observation." or "action."
    size: int


@dataclass
class FeatureGroup:
    fields: list[FeatureField]
    mean: list[float] | None = None
    std: list[float] | None = None  # already floored

    @property
    def dim(self) -> int:
        return sum(f.size for f in self.fields)

    @property
    def has_stats(self) -> bool:
        return self.mean is not None and self.std is not None

    def dim_names(self) -> list[str]:
        return [f.path if f.size == 1 else f"{f.path}[{i}]" for f in self.fields for i in range(f.size)]


@dataclass
class FrameFeature:
    path: str  # inline: the float list; blob: the reference object (its `uri` names the file)
    shape: tuple[int, int, int] = FRAME_SHAPE
    source: str = "inline"  # one of FRAME_SOURCES

    @property
    def size(self) -> int:
        return math.prod(self.shape)

    def to_json_obj(self) -> dict[str, Any]:
        return {"path": self.path, "shape": list(self.shape), "source": self.source}


@dataclass
class FeatureSpec:
    observation: FeatureGroup
    action: FeatureGroup
    frame: FrameFeature | None = None
    std_floor: float = DEFAULT_STD_FLOOR
    notes: list[str] = field(default_factory=list)  # why fields were left out; not part of identity

    @property
    def obs_dim(self) -> int:
        return self.observation.dim

    @property
    def act_dim(self) -> int:
        return self.action.dim

    def all_fields(self) -> list[FeatureField]:
        return self.observation.fields + self.action.fields

    def to_json_obj(self, with_notes: bool = True) -> dict[str, Any]:
        def group(g: FeatureGroup) -> dict[str, Any]:
            return {"fields": [{"path": f.path, "size": f.size} for f in g.fields],
                    "mean": g.mean, "std": g.std}

        obj: dict[str, Any] = {
            "format": SPEC_FORMAT,
            "observation": group(self.observation),
            "action": group(self.action),
            "frame": None if self.frame is None else self.frame.to_json_obj(),
            "std_floor": self.std_floor,
        }
        if with_notes:
            obj["notes"] = list(self.notes)
        return obj

    def to_json(self) -> str:
        return json.dumps(self.to_json_obj(), indent=1)

    @classmethod
    def from_json_obj(cls, obj: Any, where: str = "feature spec") -> "FeatureSpec":
        partial = SpecRequest.from_json_obj(obj, where)
        missing = [name for name, g in (("observation", partial.observation), ("action", partial.action))
                   if g is None or any(f.size is None for f in g.fields) or g.mean is None or g.std is None]
        if missing:
            raise FeatureSpecError(f"{where}: not a complete spec: {', '.join(missing)} needs fields with sizes, "
                                   "mean and std")
        notes = obj.get("notes", [])
        if not isinstance(notes, list) or not all(isinstance(n, str) for n in notes):
            raise FeatureSpecError(f"{where}: notes must be a list of strings")
        spec = cls(observation=partial.observation.resolved(), action=partial.action.resolved(),
                   frame=partial.frame, std_floor=partial.std_floor, notes=list(notes))
        return spec

    @classmethod
    def load(cls, path: str | Path) -> "FeatureSpec":
        return cls.from_json_obj(_read_json(Path(path)), str(path))

    def normalizer(self) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
        """(obs_mean, obs_std, act_mean, act_std) as float32 arrays."""
        if not (self.observation.has_stats and self.action.has_stats):
            raise FeatureSpecError("feature spec has no normalisation statistics yet (build the cache first)")
        f32 = lambda v: np.asarray(v, dtype=np.float32)  # noqa: E731
        return f32(self.observation.mean), f32(self.observation.std), f32(self.action.mean), f32(self.action.std)


# -- override files / partial specs --------------------------------------------------------------

@dataclass
class PartialField:
    path: str
    size: int | None


@dataclass
class PartialGroup:
    fields: list[PartialField]
    mean: list[float] | None = None
    std: list[float] | None = None

    def resolved(self) -> FeatureGroup:
        return FeatureGroup([FeatureField(f.path, int(f.size)) for f in self.fields], self.mean, self.std)


@dataclass
class SpecRequest:
    """What the user asked for (an override file, possibly partial); None parts are inferred."""

    observation: PartialGroup | None = None
    action: PartialGroup | None = None
    frame: FrameFeature | None = None
    frame_given: bool = False  # "frame": null in a file means "no frame feature", not "infer"
    std_floor: float = DEFAULT_STD_FLOOR

    @classmethod
    def from_json_obj(cls, obj: Any, where: str) -> "SpecRequest":
        if not isinstance(obj, dict):
            raise FeatureSpecError(f"{where}: a feature spec must be a JSON object")
        fmt = obj.get("format", SPEC_FORMAT)
        if fmt != SPEC_FORMAT:
            raise FeatureSpecError(f"{where}: format {fmt!r} is not {SPEC_FORMAT!r}")
        unknown = set(obj) - {"format", "observation", "action", "frame", "std_floor", "notes"}
        if unknown:
            raise FeatureSpecError(f"{where}: unknown keys {sorted(unknown)}")
        req = cls()
        floor = obj.get("std_floor", DEFAULT_STD_FLOOR)
        if not isinstance(floor, (int, float)) or isinstance(floor, bool) or not floor > 0 or not math.isfinite(floor):
            raise FeatureSpecError(f"{where}: std_floor must be a positive number, got {floor!r}")
        req.std_floor = float(floor)
        for name in ("observation", "action"):
            if obj.get(name) is not None:
                setattr(req, name, _parse_group(obj[name], name, f"{where}: {name}", req.std_floor))
        if "frame" in obj:
            req.frame_given = True
            req.frame = _parse_frame(obj["frame"], f"{where}: frame")
        return req

    @classmethod
    def load(cls, path: str | Path) -> "SpecRequest":
        return cls.from_json_obj(_read_json(Path(path)), str(path))

    def identity(self) -> str:
        """Canonical text of the request, hashed into the cache key."""
        def group(g: PartialGroup | None):
            return None if g is None else {"fields": [[f.path, f.size] for f in g.fields], "mean": g.mean, "std": g.std}
        return json.dumps({"observation": group(self.observation), "action": group(self.action),
                           "frame": None if self.frame is None else [self.frame.path, list(self.frame.shape),
                                                                     self.frame.source],
                           "frame_given": self.frame_given, "std_floor": self.std_floor,
                           "coverage": DEFAULT_COVERAGE}, sort_keys=True)

    @property
    def needs_inference(self) -> bool:
        groups = (self.observation, self.action)
        return any(g is None or any(f.size is None for f in g.fields) for g in groups) or not self.frame_given


_F32_MAX = float(np.finfo(np.float32).max)


def _read_json(path: Path) -> Any:
    try:
        return json.loads(path.read_text(encoding="utf-8"))
    except OSError as exc:
        raise FeatureSpecError(f"{path}: cannot read feature spec: {exc.strerror or exc}") from None
    except (json.JSONDecodeError, UnicodeDecodeError) as exc:
        raise FeatureSpecError(f"{path}: feature spec is not valid JSON: {exc}") from None


def _parse_group(obj: Any, root: str, where: str, std_floor: float) -> PartialGroup:
    if not isinstance(obj, dict) or not isinstance(obj.get("fields"), list) or not obj["fields"]:
        raise FeatureSpecError(f"{where}: needs a non-empty 'fields' list")
    fields: list[PartialField] = []
    for i, f in enumerate(obj["fields"]):
        if isinstance(f, str):
            f = {"path": f}
        if not isinstance(f, dict) or not isinstance(f.get("path"), str):
            raise FeatureSpecError(f"{where}: fields[{i}] must be a path string or {{'path', 'size'}}")
        if not f["path"].startswith(root + "."):
            raise FeatureSpecError(f"{where}: fields[{i}] path {f['path']!r} must start with '{root}.'")
        size = f.get("size")
        if size is not None and (not isinstance(size, int) or isinstance(size, bool) or size < 1):
            raise FeatureSpecError(f"{where}: fields[{i}] ({f['path']}) size must be a positive integer, got {size!r}")
        fields.append(PartialField(f["path"], size))
    if len({f.path for f in fields}) != len(fields):
        raise FeatureSpecError(f"{where}: a field is listed twice")
    mean, std = obj.get("mean"), obj.get("std")
    if (mean is None) != (std is None):
        raise FeatureSpecError(f"{where}: give both mean and std, or neither (they are then computed)")
    if mean is not None:
        dim = sum(f.size for f in fields) if all(f.size is not None for f in fields) else None
        for name, vec in (("mean", mean), ("std", std)):
            # within float32's range: the models and the runtime normalise in float32, where a
            # larger statistic (from a hand-edited or hostile spec) would become Inf
            if not isinstance(vec, list) or not all(_is_number(v) and abs(v) <= _F32_MAX for v in vec):
                raise FeatureSpecError(f"{where}: {name} must be a list of finite numbers within float32's range")
            if dim is not None and len(vec) != dim:
                raise FeatureSpecError(f"{where}: {name} has {len(vec)} values, the fields make {dim}")
        if dim is None:
            raise FeatureSpecError(f"{where}: mean/std given, so every field needs an explicit size")
        if any(s <= 0 for s in std):
            raise FeatureSpecError(f"{where}: std values must be positive")
        mean = [float(v) for v in mean]
        std = [max(float(v), std_floor) for v in std]
    return PartialGroup(fields, mean, std)


def _parse_frame(obj: Any, where: str) -> FrameFeature | None:
    if obj is None:
        return None
    if isinstance(obj, str):
        obj = {"path": obj}
    if not isinstance(obj, dict) or not isinstance(obj.get("path"), str):
        raise FeatureSpecError(f"{where}: must be null, a path string or {{'path', 'shape', 'source'}}")
    unknown = set(obj) - {"path", "shape", "source"}
    if unknown:
        raise FeatureSpecError(f"{where}: unknown keys {sorted(unknown)}")
    if not obj["path"].startswith("observation."):
        raise FeatureSpecError(f"{where}: path {obj['path']!r} must start with 'observation.'")
    shape = obj.get("shape", list(FRAME_SHAPE))
    if (not isinstance(shape, list) or len(shape) != 3
            or not all(isinstance(s, int) and not isinstance(s, bool) and s > 0 for s in shape) or shape[2] != 3):
        raise FeatureSpecError(f"{where}: shape must be [height, width, 3], got {shape!r}")
    source = obj.get("source", "inline")  # absent in specs written before frame blobs existed
    if source not in FRAME_SOURCES:
        raise FeatureSpecError(f"{where}: source must be one of {', '.join(FRAME_SOURCES)}, got {source!r}")
    return FrameFeature(obj["path"], (shape[0], shape[1], shape[2]), source)


# -- inference -----------------------------------------------------------------------------------

@dataclass
class EpisodeSignature:
    """Numeric leaves an episode has with the same length at its first and last step."""

    episode_id: str
    leaves: dict[str, int]
    # .npy frame references present at the first and last step -> "ok" when the first step's file
    # loads as a FRAME_SHAPE frame, else why not
    frame_blobs: dict[str, str] = field(default_factory=dict)


def episode_signature(episode_id: str, steps: list, blob_root: str | None = None,
                      check_frame_blobs: bool = True) -> EpisodeSignature:
    # First and last step only: the cache build then checks every step of the selected fields
    # and excludes (with the step named) an episode where one goes missing or changes length.
    first = step_signature(steps[0].observation, steps[0].action)
    last = step_signature(steps[-1].observation, steps[-1].action)
    sig = EpisodeSignature(episode_id, {p: n for p, n in first.items() if last.get(p) == n})
    if check_frame_blobs:
        refs = frame_blob_refs(steps[0].observation, shape=FRAME_SHAPE)
        later = frame_blob_refs(steps[-1].observation, shape=FRAME_SHAPE)
        for path, uri in refs.items():
            if path not in later:
                continue
            try:
                load_frame_blob(resolve_blob_uri(uri, blob_root), FRAME_SHAPE, uri)
                sig.frame_blobs[path] = "ok"
            except BlobFrameError as exc:
                sig.frame_blobs[path] = str(exc)
    return sig


def _select(counts: dict[str, Counter], n_episodes: int, paths: list[str], coverage: float,
            notes: list[str]) -> list[FeatureField]:
    need = max(1, math.ceil(coverage * n_episodes))
    chosen = []
    for path in paths:
        size, n = counts[path].most_common(1)[0]
        if n < need:
            notes.append(f"{path}: left out, present with one length in {n} of {n_episodes} episodes "
                         f"({_sizes(counts[path])})")
        elif size == 0:
            notes.append(f"{path}: left out, always empty")
        elif size > MAX_VECTOR:
            notes.append(f"{path}: left out, {size} values is media, not state")
        else:
            chosen.append(FeatureField(path, size))
    return chosen


def infer_spec(signatures: list[EpisodeSignature], request: SpecRequest | None = None,
               coverage: float = DEFAULT_COVERAGE) -> FeatureSpec:
    """Choose fields and sizes from episode signatures; keep what the request fixes."""
    request = request or SpecRequest()
    n = len(signatures)
    if n == 0:
        raise FeatureSpecError("no usable episodes to infer a feature spec from")
    counts: dict[str, Counter] = {}
    for sig in signatures:
        for path, size in sig.leaves.items():
            counts.setdefault(path, Counter())[size] += 1
    notes: list[str] = []
    frame_paths = [p for p in counts if p.split(".")[-1] == FRAME_FIELD and p.startswith("observation.")]
    obs_paths = sorted(p for p in counts if p.startswith("observation.") and p not in frame_paths)

    def resolve(partial: PartialGroup | None, root: str, candidates: list[str]) -> FeatureGroup:
        if partial is None:
            fields = _select(counts, n, candidates, coverage, notes)
            if not fields:
                best = sorted(candidates, key=lambda p: -counts[p].most_common(1)[0][1])[:5]
                shown = "; ".join(f"{p} ({_sizes(counts[p])})" for p in best) or "none"
                raise FeatureSpecError(
                    f"no numeric {root} field is present with one length in at least {coverage:.0%} of the "
                    f"{n} episodes (give the fields in a spec file with --spec); best candidates: {shown}")
            return FeatureGroup(fields)
        fields = []
        for f in partial.fields:
            size = f.size
            if size is None:
                if f.path not in counts:
                    raise FeatureSpecError(
                        f"{f.path}: named in the spec override but no episode has it as a numeric field")
                size = counts[f.path].most_common(1)[0][0]
            fields.append(FeatureField(f.path, size))
        return FeatureGroup(fields, partial.mean, partial.std)

    observation = resolve(request.observation, "observation", obs_paths)
    if request.action is None:
        # The documented action is the command vector; named scalars and Kotlin's tagged objects
        # (linear_mps.x, ...) are the fallback when a dataset has no usable command.
        command = [p for p in counts if p == "action.command"]
        chosen = _select(counts, n, command, coverage, notes) if command else []
        if chosen:
            action = FeatureGroup(chosen)
        else:
            others = sorted(p for p in counts if p.startswith("action.") and p != "action.command")
            action = resolve(None, "action", others)
    else:
        action = resolve(request.action, "action", [])

    if request.frame_given:
        frame = request.frame
    else:
        frame = None
        need = max(1, math.ceil(coverage * n))
        for p in frame_paths:
            size, c = counts[p].most_common(1)[0]
            if size == math.prod(FRAME_SHAPE) and c >= need:
                frame = FrameFeature(p, FRAME_SHAPE)
            else:
                notes.append(f"{p}: no frame feature ({size} values in {c} of {n} episodes; needs "
                             f"{math.prod(FRAME_SHAPE)} in {need})")
        blob = _infer_blob_frame(signatures, need, notes, inline=frame)
        frame = frame or blob
    return FeatureSpec(observation, action, frame, request.std_floor, notes)


def _infer_blob_frame(signatures: list[EpisodeSignature], need: int, notes: list[str],
                      inline: FrameFeature | None) -> FrameFeature | None:
    """The .npy frame reference usable in at least `need` episodes (an rgb-named one first)."""
    n = len(signatures)
    seen: Counter = Counter()
    ok: Counter = Counter()
    why: dict[str, str] = {}
    for sig in signatures:
        for path, status in sig.frame_blobs.items():
            seen[path] += 1
            if status == "ok":
                ok[path] += 1
            else:
                why.setdefault(path, f"{sig.episode_id}: {status}")
    usable = sorted((p for p in seen if ok[p] >= need),
                    key=lambda p: ("rgb" not in p.rsplit(".", 1)[-1].lower(), -ok[p], p))
    chosen = None if inline is not None or not usable else usable[0]
    for path in sorted(seen):
        if path == chosen:
            continue
        if path in usable:
            other = inline.path if inline is not None else chosen
            notes.append(f"{path}: frame blobs not used, {other} is the frame feature")
        else:
            example = f"; e.g. {why[path]}" if path in why else ""
            notes.append(f"{path}: no frame feature (a loadable {list(FRAME_SHAPE)} .npy frame in {ok[path]} of "
                         f"{n} episodes; needs {need}{example})")
    return None if chosen is None else FrameFeature(chosen, FRAME_SHAPE, "blob")


def spec_from_request(request: SpecRequest) -> FeatureSpec:
    """The spec an override file fully determines (every field sized, frame stated)."""
    if request.needs_inference:
        raise FeatureSpecError("the spec request leaves fields to infer from the data")
    return FeatureSpec(request.observation.resolved(), request.action.resolved(), request.frame, request.std_floor)


def _sizes(counter: Counter) -> str:
    return ", ".join(f"{size} values in {c} episodes" for size, c in counter.most_common())


# -- extraction ----------------------------------------------------------------------------------

class EpisodeMismatch(ValueError):
    """An episode does not fit the spec; str() is the reason shown in the excluded list."""

    def __init__(self, reason: str, step: int | None = None, field: str | None = None):
        where = "".join([f"step {step}: " if step is not None else "", f"{field}: " if field else ""])
        super().__init__(where + reason)
        self.step, self.field = step, field


def _get(step_obj: dict, parts: tuple[str, ...]) -> Any:
    v: Any = step_obj
    for part in parts:
        if not isinstance(v, dict) or part not in v:
            return _MISSING
        v = v[part]
    return v


_MISSING = object()


def field_matrix(steps: list, f: FeatureField | FrameFeature, dtype=np.float64) -> np.ndarray:
    """The field's values over the episode as an [n, size] array, or EpisodeMismatch naming the step."""
    root, *rest = f.path.split(".")
    parts = tuple(rest)
    attr = "observation" if root == "observation" else "action"
    values = [_get(getattr(s, attr), parts) for s in steps]
    size = f.size
    arr = None
    try:
        arr = np.asarray(values)  # no dtype: numpy would quietly turn "0.5" strings into floats
    except (ValueError, TypeError):
        pass  # ragged or mixed: diagnosed below
    if arr is not None and arr.dtype.kind in "fiub":
        if arr.ndim == 1 and size == 1:
            arr = arr[:, None]
        if arr.ndim == 2 and arr.shape[1] == size:
            arr = arr.astype(dtype, copy=False)
            if not np.isfinite(arr).all():
                bad = int(np.argwhere(~np.isfinite(arr))[0][0])
                raise EpisodeMismatch("value is NaN or infinite", bad, f.path)
            return arr
    for i, v in enumerate(values):  # slow path: name the first step that does not fit
        if v is _MISSING or v is None:
            raise EpisodeMismatch("missing", i, f.path)
        if isinstance(v, dict) and "uri" in v:
            raise EpisodeMismatch("is a blob reference, not numbers (a frame file needs \"source\": \"blob\" "
                                  "in the spec's frame)", i, f.path)
        if _is_number(v):
            n = 1
        elif isinstance(v, list) and all(_is_number(x) for x in v):
            n = len(v)
        else:
            raise EpisodeMismatch(f"not numeric ({type(v).__name__})", i, f.path)
        if n != size:
            raise EpisodeMismatch(f"has {n} values, the spec needs {size}", i, f.path)
    raise EpisodeMismatch("values do not form a numeric matrix", None, f.path)


def blob_frames(steps: list, frame: FrameFeature, blob_root: str | None) -> np.ndarray:
    """Every step's frame file loaded into uint8 [n, H, W, 3], or EpisodeMismatch naming the step,
    the field and the file. Never a placeholder image: one bad or missing file fails the episode."""
    root, *rest = frame.path.split(".")
    parts = tuple(rest)
    attr = "observation" if root == "observation" else "action"
    out = np.empty((len(steps), *frame.shape), dtype=np.uint8)
    prev_uri = None
    for i, s in enumerate(steps):
        v = _get(getattr(s, attr), parts)
        if v is _MISSING or v is None:
            raise EpisodeMismatch("missing", i, frame.path)
        uri = frame_blob_uri(v)
        where = f"{frame.path}.uri" if isinstance(v, dict) else frame.path
        if uri is None:
            raise EpisodeMismatch(f"not a blob reference (needs a 'uri' string, got {type(v).__name__})", i, where)
        if uri == prev_uri:  # a slower camera: consecutive steps share a frame
            out[i] = out[i - 1]
            continue
        try:
            out[i] = load_frame_blob(resolve_blob_uri(uri, blob_root), frame.shape, uri)
        except BlobFrameError as exc:
            raise EpisodeMismatch(str(exc), i, where) from None
        prev_uri = uri
    return out


def group_matrix(steps: list, group: FeatureGroup) -> np.ndarray:
    parts = [field_matrix(steps, f) for f in group.fields]
    return np.concatenate(parts, axis=1) if len(parts) > 1 else parts[0]


# -- statistics ----------------------------------------------------------------------------------

@dataclass
class RunningStats:
    """Per-dimension mean/variance merged episode by episode (Chan et al.), in float64."""

    dim: int
    count: int = 0
    mean: np.ndarray | None = None
    m2: np.ndarray | None = None

    def add(self, x: np.ndarray) -> None:
        n = x.shape[0]
        if n == 0:
            return
        mu = x.mean(axis=0, dtype=np.float64)
        m2 = ((x - mu) ** 2).sum(axis=0, dtype=np.float64)
        if self.count == 0:
            self.count, self.mean, self.m2 = n, mu, m2
            return
        total = self.count + n
        delta = mu - self.mean
        self.mean = self.mean + delta * (n / total)
        self.m2 = self.m2 + m2 + delta ** 2 * (self.count * n / total)
        self.count = total

    def result(self, std_floor: float) -> tuple[list[float], list[float]]:
        if self.count == 0:
            raise FeatureSpecError("no steps to compute normalisation statistics from")
        std = np.sqrt(self.m2 / self.count)
        return [float(v) for v in self.mean], [float(v) for v in np.maximum(std, std_floor)]
