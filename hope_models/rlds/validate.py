"""Content rules for canonical episodes, in two profiles.

`train` stops what would corrupt training (NaN/Inf, ragged or non-numeric vectors, time running
backwards, nothing to learn from) and warns about what a person should look at but training can
live with. `cloud` adds what the Pi runtime's upload package needs (FORMAT.md, "The Pi runtime's
upload package") and the public-sharing rules the Flutter app relies on.

Readers record their own structural findings on `Episode.problems`; `validate_episode` returns only
the content findings, and `episode_report` (validation_report.py) merges both into the per-episode
verdict the CLI prints.
"""
from __future__ import annotations

import math
import statistics
from collections import Counter
from dataclasses import dataclass, field
from itertools import pairwise
from typing import Any

from .episode import ERROR, WARNING, Episode, Problem
from .write_episode_dir import blob_refs

PROFILES = ("train", "cloud")

DOCUMENTED_ENUMS: dict[str, tuple[str, ...]] = {
    "xr_mode": ("trainer", "workstation", "observer"),
    "control_role": ("human_teleop", "human_supervisor", "human_dev_xr"),
}
# The documented flat keys; the v1.1 optional blocks are too often absent to be worth a warning.
OPTIONAL_METADATA = ("xr_mode", "control_role", "environment_id", "tags", "software")
GAP_FACTOR = 3.0
SAFETY_FIELDS: dict[str, type] = {"content_rating": dict, "pii_attestation": dict,
                                  "pii_cleared": bool, "pending_review": bool}
SHARE_TEXT_FIELDS = ("slug", "title", "license")


def is_number(value: Any) -> bool:
    return isinstance(value, (int, float)) and not isinstance(value, bool)


# -- collecting findings ------------------------------------------------------------------------

@dataclass
class _Findings:
    """Keeps the first finding of each kind and counts the repeats, so one NaN-filled image
    gives one line that says how many more there were instead of twelve thousand."""

    source: str
    _first: dict[tuple, list] = field(default_factory=dict)

    def add(self, severity: str, kind: str, message: str, step: int | None = None,
            field_path: str | None = None, group: str | None = None) -> None:
        key = (severity, kind, group if group is not None else field_path)
        if key in self._first:
            self._first[key][4] += 1
        else:
            self._first[key] = [severity, message, step, field_path, 0]

    def problems(self) -> list[Problem]:
        out = []
        for severity, message, step, field_path, repeats in self._first.values():
            if repeats:
                message += f" ({repeats} more like this in the episode)"
            out.append(Problem(severity, self.source, message, step, field_path))
        return out


def _strip_indices(path: str) -> str:
    """`observation.objects[3].position[1]` -> `observation.objects[].position[]`: the repeat key."""
    out, depth = [], 0
    for ch in path:
        if ch == "[":
            depth += 1
            out.append("[]")
        elif ch == "]":
            depth -= 1
        elif depth == 0:
            out.append(ch)
    return "".join(out)


# -- train profile: numbers and vectors ---------------------------------------------------------

@dataclass
class _ListSeen:
    step: int
    length: int
    has_number: bool
    bad: tuple[int, Any] | None  # first element that is not a number


@dataclass
class _Walk:
    """Everything one pass over the steps learns about the lists at each field path."""

    lists: dict[str, list[_ListSeen]] = field(default_factory=dict)
    non_lists: dict[str, list[tuple[int, Any]]] = field(default_factory=dict)


def _walk(value: Any, path: str, step: int, walk: _Walk, found: _Findings) -> None:
    if isinstance(value, dict):
        for key, sub in value.items():
            _walk(sub, f"{path}.{key}", step, walk, found)
    elif isinstance(value, list):
        # Fast path for the common case, a flat list of finite numbers (12,288 floats per image
        # step in one producer): C-level type set and sum instead of a Python loop per element.
        if value and set(map(type, value)) <= {float, int}:
            try:
                finite = math.isfinite(sum(value))
            except OverflowError:
                finite = False
            if finite:
                walk.lists.setdefault(path, []).append(_ListSeen(step, len(value), True, None))
                return
        bad = None
        has_number = False
        for i, element in enumerate(value):
            if is_number(element):
                has_number = True
                if isinstance(element, float) and not math.isfinite(element):
                    found.add(ERROR, "non_finite", f"{element} is not a finite number", step,
                              f"{path}[{i}]", group=_strip_indices(path))
            else:
                if bad is None:
                    bad = (i, element)
                if isinstance(element, (dict, list)):
                    _walk(element, f"{path}[{i}]", step, walk, found)
        walk.lists.setdefault(path, []).append(_ListSeen(step, len(value), has_number, bad))
    else:
        if isinstance(value, float) and not math.isfinite(value):
            found.add(ERROR, "non_finite", f"{value} is not a finite number", step, path,
                      group=_strip_indices(path))
        if value is not None:
            walk.non_lists.setdefault(path, []).append((step, value))


def _check_vectors(walk: _Walk, found: _Findings) -> None:
    """A field path is a numeric vector when any step holds numbers there; from then on every
    step must hold only numbers there, and as many as the first step that had it."""
    for path, seen in walk.lists.items():
        if not any(s.has_number for s in seen):
            continue  # lists of strings, of objects, or always empty: not a vector
        for s in seen:
            if s.bad is not None:
                index, element = s.bad
                found.add(ERROR, "non_numeric", f"element is {_describe(element)} in a numeric "
                          "vector", s.step, f"{path}[{index}]", group=_strip_indices(path))
        reference = seen[0]
        for s in seen[1:]:
            if s.length != reference.length:
                found.add(ERROR, "vector_length", "vector length changed within the episode: "
                          f"{s.length} here, {reference.length} at step {reference.step}",
                          s.step, path)
                reference = s  # a second change is reported against the new length
        for step, value in walk.non_lists.get(path, []):
            found.add(ERROR, "vector_type", f"expected a numeric vector (length {seen[0].length} "
                      f"at step {seen[0].step}), found {_describe(value)}", step, path)


def _describe(value: Any) -> str:
    if value is None:
        return "null"
    return f"{type(value).__name__} {repr(value)[:40]}"


def _check_numbers(ep: Episode, found: _Findings) -> None:
    walk = _Walk()
    for i, step in enumerate(ep.steps):
        _walk(step.observation, "observation", i, walk, found)
        _walk(step.action, "action", i, walk, found)
        if not is_number(step.reward):
            found.add(ERROR, "reward_type", f"reward is {_describe(step.reward)}, not a number",
                      i, "reward")
        elif isinstance(step.reward, float) and not math.isfinite(step.reward):
            found.add(ERROR, "non_finite", f"{step.reward} is not a finite number", i, "reward")
    _check_vectors(walk, found)


# -- train profile: steps, time, terminal flag, metadata, blobs ---------------------------------

def _check_usable(ep: Episode, found: _Findings) -> bool:
    if not ep.steps:
        found.add(ERROR, "no_steps", "episode has no usable steps (0 steps)", None, "steps")
        return False
    if not any(step.observation or step.action for step in ep.steps):
        found.add(ERROR, "no_steps", f"episode has no usable steps: all {len(ep.steps)} steps have "
                  "an empty observation and action", None, "steps")
        return False
    return True


def _check_timestamps(ep: Episode, found: _Findings) -> None:
    stamps: list[tuple[int, int]] = []  # (step index, timestamp_ns)
    for i, step in enumerate(ep.steps):
        ts = step.timestamp_ns
        if ts is None:
            continue
        if not isinstance(ts, int) or isinstance(ts, bool):
            found.add(ERROR, "timestamp_type", f"timestamp_ns is {_describe(ts)}, not an integer",
                      i, "timestamp_ns")
            continue
        stamps.append((i, ts))
    if not stamps:
        return  # readers already warn when an episode has no clock at all
    if len(stamps) < len(ep.steps):
        missing = [i for i, s in enumerate(ep.steps) if s.timestamp_ns is None]
        found.add(WARNING, "timestamp_missing", f"{len(missing)} of {len(ep.steps)} steps have no "
                  "timestamp", missing[0], "timestamp_ns")
    periods: list[tuple[int, int]] = []  # (step index, ns since the previous stamped step)
    for (prev_i, prev), (i, ts) in pairwise(stamps):
        if ts < prev:
            found.add(ERROR, "timestamp_backwards", f"timestamp goes backwards: {ts} ns is "
                      f"{(prev - ts) / 1e6:.3f} ms before step {prev_i} ({prev} ns)", i, "timestamp_ns")
        elif ts == prev:
            found.add(WARNING, "timestamp_repeat", f"timestamp {ts} ns repeats step {prev_i}", i,
                      "timestamp_ns")
        else:
            periods.append((i, ts - prev))
    if len(periods) < 2:
        return
    median = statistics.median(p for _, p in periods)
    for i, period in periods:
        if period > GAP_FACTOR * median:
            found.add(WARNING, "gap", f"gap of {period / 1e9:.3f} s before this step is over "
                      f"{GAP_FACTOR:g}x the median period {median / 1e9:.3f} s", i, "timestamp_ns")


def _check_terminal(ep: Episode, found: _Findings) -> None:
    last = len(ep.steps) - 1
    for i, step in enumerate(ep.steps[:-1]):
        if step.is_terminal is True:
            found.add(WARNING, "terminal_early", f"terminal flag on a step that is not the last "
                      f"(last is step {last})", i, "is_terminal")
    if ep.steps[-1].is_terminal is not True:
        found.add(WARNING, "terminal_missing", "last step is not marked terminal", last,
                  "is_terminal")


def _check_metadata(ep: Episode, found: _Findings) -> None:
    meta = ep.metadata
    for key, documented in DOCUMENTED_ENUMS.items():
        value = meta.get(key)
        if value is None:
            continue
        if not isinstance(value, str):
            found.add(WARNING, "enum", f"{_describe(value)} is not a string", None, f"metadata.{key}")
        elif value not in documented:
            found.add(WARNING, "enum", f"undocumented value {value!r} kept as a string "
                      f"(documented: {', '.join(documented)})", None, f"metadata.{key}")
    provenance = meta.get("provenance")
    lost = provenance.get("steps_lost") if isinstance(provenance, dict) else None
    if is_number(lost) and lost > 0:
        # ingest records what its reader could not recover; the canonical copy reads cleanly
        found.add(WARNING, "steps_lost", f"{lost} step(s) of the original were lost when it was "
                  "recovered", None, "metadata.provenance.steps_lost")
    missing = [key for key in OPTIONAL_METADATA if meta.get(key) in (None, "", [], {})]
    if missing:
        found.add(WARNING, "metadata_missing", f"missing optional metadata: {', '.join(missing)}",
                  None, "metadata")


def _check_blobs(ep: Episode, found: _Findings) -> None:
    for ref in blob_refs(ep):
        if ref.status == "missing":
            found.add(WARNING, "blob", f"blob {ref.uri!r} not found at {ref.path}", ref.step,
                      ref.field, group=_strip_indices(ref.field))
        elif ref.status == "escapes":
            found.add(WARNING, "blob", f"blob {ref.uri!r} points outside the episode dir; not "
                      "resolved", ref.step, ref.field, group=_strip_indices(ref.field))
        elif ref.status == "unresolvable":
            found.add(WARNING, "blob", f"relative blob {ref.uri!r} cannot be resolved: the "
                      "episode has no blob root", ref.step, ref.field, group="unresolvable")


# -- cloud profile ------------------------------------------------------------------------------

def derive_action_source(ep: Episode) -> tuple[str | None, list[str]]:
    """`metadata.action_source`, else the steps' `action.source` (the most common one when they
    disagree). Returns the value and every distinct step source, so callers can warn on a mix."""
    step_sources = (s.action.get("source") for s in ep.steps if isinstance(s.action, dict))
    sources = Counter(src for src in step_sources if isinstance(src, str) and src)
    declared = ep.metadata.get("action_source")
    if isinstance(declared, str) and declared:
        return declared, sorted(sources)
    if not sources:
        return None, []
    return sources.most_common(1)[0][0], sorted(sources)


def robot_type(metadata: dict[str, Any]) -> str | None:
    for key in ("robot_type", "robot_model"):
        value = metadata.get(key)
        if isinstance(value, str) and value:
            return value
    return None


def _check_cloud(ep: Episode, found: _Findings) -> None:
    meta = ep.metadata

    def need(condition: bool, field_path: str, message: str) -> None:
        if not condition:
            found.add(ERROR, "cloud", message, None, field_path)

    episode_id = meta.get("episode_id")
    need(isinstance(episode_id, str) and bool(episode_id), "metadata.episode_id",
         "missing episode_id (required by the upload package)")
    need(robot_type(meta) is not None, "metadata.robot_type",
         "missing robot_type (or robot_model), required by the upload package")
    xr_mode = meta.get("xr_mode")
    need(isinstance(xr_mode, str) and bool(xr_mode), "metadata.xr_mode",
         "missing xr_mode (required by the upload package)")
    action_source, step_sources = derive_action_source(ep)
    need(action_source is not None, "metadata.action_source",
         "missing action_source, and no step has action.source to derive it from")
    if "action_source" not in meta and len(step_sources) > 1:
        found.add(WARNING, "cloud", f"steps have several action.source values ({', '.join(step_sources)}); "
                  f"the upload package will say {action_source!r}", None, "metadata.action_source")
    if "total_steps" in meta:
        total = meta["total_steps"]
        need(is_number(total) and total == len(ep.steps), "metadata.total_steps",
             f"total_steps is {total!r} but the episode has {len(ep.steps)} steps")

    safety = meta.get("safety")
    if not isinstance(safety, dict):
        need(False, "metadata.safety", "missing safety block (content_rating, pii_attestation, "
             "pii_cleared, pending_review)")
        safety = {}
    else:
        for key, kind in SAFETY_FIELDS.items():
            need(isinstance(safety.get(key), kind), f"metadata.safety.{key}",
                 f"safety.{key} must be {'an object' if kind is dict else 'true or false'}, "
                 f"found {_describe(safety.get(key))}")

    share = meta.get("share")
    if share is None:
        return
    if not isinstance(share, dict):
        need(False, "metadata.share", f"share must be an object, found {_describe(share)}")
        return
    public = share.get("public", False)
    if not isinstance(public, bool):
        need(False, "metadata.share.public", f"share.public must be true or false, found {_describe(public)}")
        return
    if not public:
        return
    need(safety.get("pii_cleared") is True, "metadata.safety.pii_cleared",
         "public sharing requires safety.pii_cleared true")
    need(safety.get("pending_review") is False, "metadata.safety.pending_review",
         "public sharing requires safety.pending_review false")
    for key in SHARE_TEXT_FIELDS:
        value = share.get(key)
        need(isinstance(value, str) and bool(value.strip()), f"metadata.share.{key}",
             f"public sharing requires share.{key}")
    tags = share.get("tags")
    need(isinstance(tags, list) and any(isinstance(t, str) and t for t in tags), "metadata.share.tags",
         "public sharing requires at least one tag in share.tags")


# -- the entry point -------------------------------------------------------------------------------

def validate_episode(ep: Episode, profile: str = "train") -> list[Problem]:
    """Content findings for one episode (not including `ep.problems`, which the caller merges)."""
    if profile not in PROFILES:
        raise ValueError(f"unknown validation profile {profile!r} (known: {', '.join(PROFILES)})")
    found = _Findings(ep.source)
    if _check_usable(ep, found):
        _check_numbers(ep, found)
        _check_timestamps(ep, found)
        _check_terminal(ep, found)
        _check_blobs(ep, found)
    _check_metadata(ep, found)
    if profile == "cloud":
        _check_cloud(ep, found)
    # Episode-wide findings first, then in step order: how a person reads down an episode.
    return sorted(found.problems(), key=lambda p: (p.step is not None, p.step or 0))
