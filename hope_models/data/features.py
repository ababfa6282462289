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
     "cameras": [{"path": "observation.depth", "shape": [64, 64, 1], "source": "blob", "kind": "depth"}],
     "std_floor": 0.001}

The frame (the camera the tokenizer reads) is either inline (`source` "inline", the default when
absent: a flat list of floats in [0, 1] such as the vlm sample's `image_rgb`) or a blob (`source`
"blob": `path` names an observation object whose `uri` is a frame file: a .npy array, a JPEG or
PNG still, or a video; see cameras.py). `cameras` lists every other camera the cache stores (absent
when there is none), a depth camera (`kind` "depth") as float32 metres [H, W, 1]. Inference prefers
an inline `image_rgb`; without one the colour camera that (nearly) every episode has; every camera
usable in (nearly) every episode is stored. `frame_size` (64, 96 or 128; an override key) is the
square size frames are resized to.

In an override, a field may be a bare path string (size taken from the data), any group or the
frame may be left out (inferred), and mean/std may be left out (computed when the cache is built).

This module holds the spec's types and its JSON form. Reading a spec or an override file is
spec_request.py, choosing fields from the data spec_inference.py, reading them out of an episode's
steps extract.py, and the normalisation statistics running_stats.py.
"""
from __future__ import annotations

import json
import math
from dataclasses import dataclass, field
from typing import Any

import numpy as np

SPEC_FORMAT = "hope.feature_spec/1"
FRAME_FIELD = "image_rgb"
FRAME_SHAPE = (64, 64, 3)
FRAME_SIZES = (64, 96, 128)  # square frame sizes the cache stores (the VQ-VAE needs multiples of 16)
DEFAULT_FRAME_SIZE = 64
FRAME_SOURCES = ("inline", "blob")  # image floats in the step / a frame file the step references
FRAME_KINDS = ("rgb", "depth")  # uint8 colour [H, W, 3] / float32 metres [H, W, 1]
DEFAULT_STD_FLOOR = 1e-3
DEFAULT_COVERAGE = 0.9  # "nearly every episode": a field missing from >10% of episodes is dropped
MAX_VECTOR = 4096  # longer flat lists are media (a frame, a waveform), not state


class FeatureSpecError(ValueError):
    """The spec cannot be built or loaded; the message names the field or file."""


def is_number(v: Any) -> bool:
    """What counts as a numeric value of a field: ints and floats, bools included (they become 0/1)."""
    return isinstance(v, (int, float))


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


def camera_kind(path: str) -> str:
    """A camera whose name says depth holds depth; every other one colour."""
    return "depth" if "depth" in path.rsplit(".", 1)[-1].lower() else "rgb"


def frame_shape(size: int, kind: str = "rgb") -> tuple[int, int, int]:
    return (size, size, 1 if kind == "depth" else 3)


@dataclass
class FrameFeature:
    path: str  # inline: the float list; blob: the reference object (its `uri` names the file)
    shape: tuple[int, int, int] = FRAME_SHAPE
    source: str = "inline"  # one of FRAME_SOURCES
    kind: str = "rgb"  # one of FRAME_KINDS

    @property
    def size(self) -> int:
        return math.prod(self.shape)

    @property
    def name(self) -> str:
        return self.path.removeprefix("observation.")

    @property
    def dtype(self) -> str:
        """The cache array's dtype: colour stays uint8, depth is metres."""
        return "<f4" if self.kind == "depth" else "|u1"

    def to_json_obj(self) -> dict[str, Any]:
        obj: dict[str, Any] = {"path": self.path, "shape": list(self.shape), "source": self.source}
        if self.kind != "rgb":  # colour specs read the same as before cameras had kinds
            obj["kind"] = self.kind
        return obj


@dataclass
class FeatureSpec:
    observation: FeatureGroup
    action: FeatureGroup
    frame: FrameFeature | None = None  # the camera the tokenizer reads (colour)
    std_floor: float = DEFAULT_STD_FLOOR
    notes: list[str] = field(default_factory=list)  # why fields were left out; not part of identity
    cameras: list[FrameFeature] = field(default_factory=list)  # every other camera the cache stores

    def all_cameras(self) -> list[FrameFeature]:
        return ([self.frame] if self.frame is not None else []) + list(self.cameras)

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
        if self.cameras:  # absent, not [], so a spec without extra cameras reads as it always did
            obj["cameras"] = [c.to_json_obj() for c in self.cameras]
        if with_notes:
            obj["notes"] = list(self.notes)
        return obj

    def to_json(self) -> str:
        return json.dumps(self.to_json_obj(), indent=1)

    def normalizer(self) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
        """(obs_mean, obs_std, act_mean, act_std) as float32 arrays."""
        if not (self.observation.has_stats and self.action.has_stats):
            raise FeatureSpecError("feature spec has no normalisation statistics yet (build the cache first)")
        f32 = lambda v: np.asarray(v, dtype=np.float32)  # noqa: E731
        return f32(self.observation.mean), f32(self.observation.std), f32(self.action.mean), f32(self.action.std)
