"""Inferring a feature spec from the data: which numeric fields (nearly) every episode has.

Inference flattens the numeric leaves of `observation` and `action` (numbers, bools as 0/1, flat
lists of numbers) into dotted paths and keeps a field only when (nearly) every episode has it with
the same length; clocks, ids and media are never fields. Every camera (cameras.py) whose frames
decode in (nearly) every episode is stored; the one the tokenizer reads is an inline `image_rgb`
when there is one, else the colour camera most episodes have. What it leaves out, and why, goes
into the spec's notes.
"""
from __future__ import annotations

import math
import re
from collections import Counter
from dataclasses import dataclass, field
from typing import Any

from hope_models.data.cameras import CameraCheck, camera_refs, check_camera
from hope_models.data.features import (
    DEFAULT_COVERAGE,
    DEFAULT_FRAME_SIZE,
    FRAME_FIELD,
    FRAME_SHAPE,
    MAX_VECTOR,
    FeatureField,
    FeatureGroup,
    FeatureSpec,
    FeatureSpecError,
    FrameFeature,
    frame_shape,
    is_number,
)
from hope_models.data.spec_request import PartialGroup, SpecRequest

_CAMEL = re.compile(r"([a-z0-9])([A-Z])")


def _is_clock_or_id(key: str) -> bool:
    """Clocks and ids are numbers but carry no signal a policy should see (and grow without bound)."""
    k = _CAMEL.sub(r"\1_\2", key).lower()
    return (k.startswith("timestamp") or k.endswith("_timestamp") or k.startswith("wall_time")
            or k.endswith(("_nanos", "_micros", "_millis", "_id", "_ids")) or k in {"step_index", "id", "seq"})


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
        elif is_number(value):
            out[path] = 1
        elif isinstance(value, list) and all(is_number(v) for v in value):
            out[path] = len(value)
    return out


def step_signature(observation: dict, action: dict) -> dict[str, int]:
    sig = numeric_leaves(observation, "observation")
    numeric_leaves(action, "action", sig)
    return sig


@dataclass
class EpisodeSignature:
    """Numeric leaves an episode has with the same length at its first and last step."""

    episode_id: str
    leaves: dict[str, int]
    # cameras referenced at the first or the last step, checked there (or at every step)
    cameras: dict[str, CameraCheck] = field(default_factory=dict)


def episode_signature(episode_id: str, steps: list, blob_root: str | None = None,
                      check_cameras: bool = True, every_step: bool = False,
                      frame_size: int = DEFAULT_FRAME_SIZE) -> EpisodeSignature:
    # First and last step only: the cache build then checks every step of the selected fields
    # and excludes (with the step named) an episode where one goes missing or changes length.
    first = step_signature(steps[0].observation, steps[0].action)
    last = step_signature(steps[-1].observation, steps[-1].action)
    sig = EpisodeSignature(episode_id, {p: n for p, n in first.items() if last.get(p) == n})
    if check_cameras:
        paths = set(camera_refs(steps[0].observation)) | set(camera_refs(steps[-1].observation))
        for path in sorted(paths):
            sig.cameras[path] = check_camera(steps, path, blob_root, frame_size, every_step)
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
    no_action: FeatureSpecError | None = None
    if request.action is None:
        # The documented action is the command vector; named scalars and Kotlin's tagged objects
        # (linear_mps.x, ...) are the fallback when a dataset has no usable command.
        command = [p for p in counts if p == "action.command"]
        chosen = _select(counts, n, command, coverage, notes) if command else []
        if chosen:
            action = FeatureGroup(chosen)
        else:
            others = sorted(p for p in counts if p.startswith("action.") and p != "action.command")
            try:
                action = resolve(None, "action", others)
            except FeatureSpecError as exc:  # fine for a camera dataset: the tokenizer needs no action
                action, no_action = FeatureGroup([]), exc
    else:
        action = resolve(request.action, "action", [])

    if request.frame_given:
        frame, cameras = request.frame, list(request.cameras)
    else:
        frame = None
        need = max(1, math.ceil(coverage * n))
        size = request.frame_size
        for p in frame_paths:
            length, c = counts[p].most_common(1)[0]
            if length == math.prod(FRAME_SHAPE) and c >= need:
                frame = FrameFeature(p, frame_shape(size))
            else:
                notes.append(f"{p}: no frame feature ({length} values in {c} of {n} episodes; needs "
                             f"{math.prod(FRAME_SHAPE)} in {need})")
        frame, cameras = _infer_cameras(signatures, need, notes, frame, size)
    if no_action is not None:
        if frame is None:  # nothing to train at all: say why the cameras could not stand in
            unusable = [note for note in notes if ": not stored (frames decode" in note]
            raise FeatureSpecError(str(no_action) + ("; and no camera for the tokenizer: " + "; ".join(unusable)
                                                     if unusable else "")) from None
        notes.append(f"action: none ({no_action}); only the tokenizer trains on this dataset, from "
                     f"{frame.path}")
    return FeatureSpec(observation, action, frame, request.std_floor, notes, cameras)


def _infer_cameras(signatures: list[EpisodeSignature], need: int, notes: list[str], inline: FrameFeature | None,
                   size: int) -> tuple[FrameFeature | None, list[FrameFeature]]:
    """(the frame the tokenizer reads, the other cameras): every camera whose frames decode in at
    least `need` episodes; the tokenizer's is the inline frame, else the colour camera most have."""
    n = len(signatures)
    seen: Counter = Counter()
    ok: Counter = Counter()
    why: dict[str, str] = {}
    kinds: dict[str, str] = {}
    for sig in signatures:
        for path, check in sig.cameras.items():
            seen[path] += 1
            kinds[path] = check.kind
            if check.ok:
                ok[path] += 1
            else:
                why.setdefault(path, f"{sig.episode_id}: {check.problem or 'no frame at some step'}")
    usable = sorted((p for p in seen if ok[p] >= need), key=lambda p: (-ok[p], _camera_rank(p), p))
    colour = [p for p in usable if kinds[p] == "rgb"]
    frame = inline
    if frame is None and colour:
        frame = FrameFeature(colour[0], frame_shape(size), "blob")
    cameras = [FrameFeature(p, frame_shape(size, kinds[p]), "blob", kinds[p])
               for p in usable if frame is None or p != frame.path]
    for path in sorted(seen):
        if path in usable:
            continue
        example = f"; e.g. {why[path]}" if path in why else ""
        notes.append(f"{path}: not stored (frames decode in {ok[path]} of {n} episodes; needs {need}{example})")
    return frame, cameras


# Which camera the tokenizer reads when several decode everywhere: the robot's own view first
# (the app's egocentric camera, a head or front camera), then one that says it is colour.
_MAIN_CAMERA_WORDS = (("ego", "head", "front", "main"), ("rgb", "color", "colour", "camera"))


def _camera_rank(path: str) -> int:
    name = path.rsplit(".", 1)[-1].lower()
    return next((rank for rank, words in enumerate(_MAIN_CAMERA_WORDS) if any(w in name for w in words)),
                len(_MAIN_CAMERA_WORDS))


def _sizes(counter: Counter) -> str:
    return ", ".join(f"{size} values in {c} episodes" for size, c in counter.most_common())
