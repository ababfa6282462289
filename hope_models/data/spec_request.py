"""Reading a feature spec's JSON: a complete spec, or an override file that may leave parts to infer.

An override (`--spec FILE`) is parsed into a SpecRequest: a field may be a bare path string (its
size then comes from the data), a group or the frame may be absent (inferred), mean/std may be
absent (computed when the cache is built). A complete spec is a request with nothing left open.
The JSON shape is in features.py.
"""
from __future__ import annotations

import json
import math
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from hope_models.data.features import (
    DEFAULT_COVERAGE,
    DEFAULT_FRAME_SIZE,
    DEFAULT_STD_FLOOR,
    FRAME_KINDS,
    FRAME_SIZES,
    FRAME_SOURCES,
    SPEC_FORMAT,
    FeatureField,
    FeatureGroup,
    FeatureSpec,
    FeatureSpecError,
    FrameFeature,
    frame_shape,
    is_number,
)


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
    cameras: list[FrameFeature] = field(default_factory=list)  # with a given frame: the others stored
    frame_size: int = DEFAULT_FRAME_SIZE

    @classmethod
    def from_json_obj(cls, obj: Any, where: str) -> "SpecRequest":
        if not isinstance(obj, dict):
            raise FeatureSpecError(f"{where}: a feature spec must be a JSON object")
        fmt = obj.get("format", SPEC_FORMAT)
        if fmt != SPEC_FORMAT:
            raise FeatureSpecError(f"{where}: format {fmt!r} is not {SPEC_FORMAT!r}")
        unknown = set(obj) - {"format", "observation", "action", "frame", "cameras", "frame_size", "std_floor",
                              "notes"}
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
        size = obj.get("frame_size", DEFAULT_FRAME_SIZE)
        if size not in FRAME_SIZES or isinstance(size, bool):
            raise FeatureSpecError(f"{where}: frame_size must be one of {', '.join(map(str, FRAME_SIZES))}, "
                                   f"got {size!r}")
        req.frame_size = size
        if "frame" in obj:
            req.frame_given = True
            req.frame = _parse_frame(obj["frame"], f"{where}: frame")
            if req.frame is not None and req.frame.kind != "rgb":
                raise FeatureSpecError(f"{where}: frame: the tokenizer reads a colour camera, not {req.frame.kind}")
        cameras = obj.get("cameras", [])
        if not isinstance(cameras, list):
            raise FeatureSpecError(f"{where}: cameras must be a list of {{'path', 'shape', 'source', 'kind'}}")
        if cameras and not req.frame_given:
            raise FeatureSpecError(f"{where}: cameras given without a frame: give both, or neither to infer them")
        for i, cam in enumerate(cameras):
            parsed = _parse_frame(cam, f"{where}: cameras[{i}]")
            if parsed is None:
                raise FeatureSpecError(f"{where}: cameras[{i}]: must be an object, not null")
            req.cameras.append(parsed)
        return req

    @classmethod
    def load(cls, path: str | Path) -> "SpecRequest":
        return cls.from_json_obj(read_spec_json(Path(path)), str(path))

    def identity(self) -> str:
        """Canonical text of the request, hashed into the cache key."""
        def group(g: PartialGroup | None):
            return None if g is None else {"fields": [[f.path, f.size] for f in g.fields], "mean": g.mean, "std": g.std}
        return json.dumps({"observation": group(self.observation), "action": group(self.action),
                           "frame": None if self.frame is None else [self.frame.path, list(self.frame.shape),
                                                                     self.frame.source],
                           "frame_given": self.frame_given, "std_floor": self.std_floor,
                           "coverage": DEFAULT_COVERAGE,
                           **({"cameras": [c.to_json_obj() for c in self.cameras]} if self.cameras else {}),
                           **({"frame_size": self.frame_size} if self.frame_size != DEFAULT_FRAME_SIZE else {})},
                          sort_keys=True)

    @property
    def needs_inference(self) -> bool:
        groups = (self.observation, self.action)
        return any(g is None or any(f.size is None for f in g.fields) for g in groups) or not self.frame_given


_F32_MAX = float(np.finfo(np.float32).max)


def read_spec_json(path: Path) -> Any:
    try:
        return json.loads(path.read_text(encoding="utf-8"))
    except OSError as exc:
        raise FeatureSpecError(f"{path}: cannot read feature spec: {exc.strerror or exc}") from None
    except (json.JSONDecodeError, UnicodeDecodeError) as exc:
        raise FeatureSpecError(f"{path}: feature spec is not valid JSON: {exc}") from None


def _parse_group(obj: Any, root: str, where: str, std_floor: float) -> PartialGroup:
    # An empty action group is a camera dataset without actions (only the tokenizer trains on it).
    if (not isinstance(obj, dict) or not isinstance(obj.get("fields"), list)
            or not (obj["fields"] or root == "action")):
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
            if not isinstance(vec, list) or not all(is_number(v) and abs(v) <= _F32_MAX for v in vec):
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
    unknown = set(obj) - {"path", "shape", "source", "kind"}
    if unknown:
        raise FeatureSpecError(f"{where}: unknown keys {sorted(unknown)}")
    if not obj["path"].startswith("observation."):
        raise FeatureSpecError(f"{where}: path {obj['path']!r} must start with 'observation.'")
    kind = obj.get("kind", "rgb")  # absent in specs written before depth cameras existed
    if kind not in FRAME_KINDS:
        raise FeatureSpecError(f"{where}: kind must be one of {', '.join(FRAME_KINDS)}, got {kind!r}")
    channels = frame_shape(DEFAULT_FRAME_SIZE, kind)[2]
    shape = obj.get("shape", list(frame_shape(DEFAULT_FRAME_SIZE, kind)))
    if (not isinstance(shape, list) or len(shape) != 3
            or not all(isinstance(s, int) and not isinstance(s, bool) and s > 0 for s in shape)
            or shape[2] != channels):
        raise FeatureSpecError(f"{where}: shape must be [height, width, {channels}] for a {kind} camera, "
                               f"got {shape!r}")
    source = obj.get("source", "inline")  # absent in specs written before frame blobs existed
    if source not in FRAME_SOURCES:
        raise FeatureSpecError(f"{where}: source must be one of {', '.join(FRAME_SOURCES)}, got {source!r}")
    if source == "inline" and kind != "rgb":
        raise FeatureSpecError(f"{where}: an inline frame is colour floats; a {kind} camera is a file (source blob)")
    return FrameFeature(obj["path"], (shape[0], shape[1], shape[2]), source, kind)


def spec_from_json_obj(obj: Any, where: str = "feature spec") -> FeatureSpec:
    """A complete spec (every field sized, mean and std given), as saved in a cache or a checkpoint."""
    partial = SpecRequest.from_json_obj(obj, where)
    missing = [name for name, g in (("observation", partial.observation), ("action", partial.action))
               if g is None or any(f.size is None for f in g.fields) or g.mean is None or g.std is None]
    if missing:
        raise FeatureSpecError(f"{where}: not a complete spec: {', '.join(missing)} needs fields with sizes, "
                               "mean and std")
    notes = obj.get("notes", [])
    if not isinstance(notes, list) or not all(isinstance(n, str) for n in notes):
        raise FeatureSpecError(f"{where}: notes must be a list of strings")
    return FeatureSpec(observation=partial.observation.resolved(), action=partial.action.resolved(),
                       frame=partial.frame, std_floor=partial.std_floor, notes=list(notes),
                       cameras=list(partial.cameras))


def load_spec(path: str | Path) -> FeatureSpec:
    """A spec.json file (a cache's, or one a user wrote) as a FeatureSpec; FeatureSpecError names it."""
    return spec_from_json_obj(read_spec_json(Path(path)), str(path))


def spec_from_request(request: SpecRequest) -> FeatureSpec:
    """The spec an override file fully determines (every field sized, frame stated)."""
    if request.needs_inference:
        raise FeatureSpecError("the spec request leaves fields to infer from the data")
    return FeatureSpec(request.observation.resolved(), request.action.resolved(), request.frame, request.std_floor,
                       cameras=list(request.cameras))
