"""Single-file episodes: `{"metadata": {...}, "steps": [...]}`.

Older files say `episode_metadata` instead of `metadata`; the arm recorder and the Pi's upload
package write the same shape as `<id>/episode.json`, so that file takes its id from its
directory, and its per-step camera files beside it (`step_0003_rgb.npy`) are attached to the
steps by position (rlds/frame_files.py). Other top-level keys are kept as metadata (unknown keys
are never dropped).
"""
from __future__ import annotations

import os
from pathlib import Path

from .episode import ERROR, WARNING, Episode, Problem, SourceReport
from .frame_files import attach_pi_files
from .json_text import ReadLimits, TextReadError, parse_json_document, read_text
from .normalize import id_from_name, normalize_metadata, step_from_obj
from .timestamps import assign_timestamps

LAYOUT = "single_json"
ARM_RECORDER_FILE = "episode.json"


def fallback_episode_id(path: Path) -> str:
    if path.name == ARM_RECORDER_FILE and path.parent.name:
        return path.parent.name
    return id_from_name(path.name)


def read_single_json(path: str | os.PathLike, limits: ReadLimits | None = None) -> SourceReport:
    limits = limits or ReadLimits()
    file = Path(path)
    report = SourceReport(source=str(file))
    try:
        doc = parse_json_document(read_text(file, limits))
    except TextReadError as exc:
        report.problems.append(Problem(ERROR, str(file), str(exc)))
        return report
    return episode_from_document(doc, file, report)


def episode_from_document(doc: object, file: Path, report: SourceReport) -> SourceReport:
    if isinstance(doc, list):
        raw_md: object = None
        raw_steps: object = doc  # a bare list of steps
    elif isinstance(doc, dict) and "steps" in doc:
        rest = {k: v for k, v in doc.items() if k not in ("steps", "metadata", "episode_metadata")}
        raw_md = doc.get("metadata") if "metadata" in doc else doc.get("episode_metadata")
        if isinstance(raw_md, dict):
            raw_md = {**rest, **raw_md}
        elif raw_md is None:
            raw_md = rest or None
        raw_steps = doc["steps"]
    else:
        report.skipped = True
        report.skip_reason = "not an episode: no 'steps' list"
        report.problems.append(Problem(WARNING, str(file), "JSON file has no 'steps' list; not an episode, skipped"))
        return report

    if not isinstance(raw_steps, list):
        report.problems.append(Problem(ERROR, str(file), f"'steps' is a JSON {type(raw_steps).__name__}, not a list",
                                       field="steps"))
        return report

    ep = Episode(episode_id="", metadata={}, steps=[], source=str(file), layout=LAYOUT,
                 blob_root=str(file.parent))
    ep.metadata = normalize_metadata(raw_md, layout=LAYOUT, fallback_id=fallback_episode_id(file),
                                     warn=lambda msg, fld: ep.warn(msg, field=fld))
    ep.episode_id = str(ep.metadata["episode_id"])
    for i, raw in enumerate(raw_steps):
        if not isinstance(raw, dict):
            ep.error(f"steps[{i}] is a JSON {type(raw).__name__}, not an object; step skipped", field=f"steps[{i}]")
            ep.steps_lost += 1
            continue
        ep.steps.append(step_from_obj(raw, len(ep.steps), ep))
    if not ep.steps:
        ep.warn("episode has no steps", field="steps")
    if file.name == ARM_RECORDER_FILE:  # the Pi's layout: its camera frames are files beside it
        attach_pi_files(ep, file.parent)
    assign_timestamps(ep)
    report.episodes.append(ep)
    return report
