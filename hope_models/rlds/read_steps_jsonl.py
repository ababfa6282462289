"""Steps-only JSONL: one step per line, no metadata file.

Lines that carry `episode_id` are grouped into one episode per id (first-seen order, lines kept
in file order); lines without it belong to an episode named after the file. A line holding only
`metadata`/`episode_metadata` (and optionally `episode_id`) is taken as that episode's metadata.
"""
from __future__ import annotations

import os
from pathlib import Path

from .episode import ERROR, WARNING, Episode, Problem, SourceReport
from .json_text import ReadLimits, TextReadError, parse_jsonl, read_text
from .normalize import id_from_name, normalize_metadata, step_from_obj
from .timestamps import assign_timestamps

LAYOUT = "steps_jsonl"
_METADATA_KEYS = {"metadata", "episode_metadata"}


def read_steps_jsonl(path: str | os.PathLike, limits: ReadLimits | None = None) -> SourceReport:
    limits = limits or ReadLimits()
    file = Path(path)
    report = SourceReport(source=str(file))
    try:
        text = read_text(file, limits)
    except TextReadError as exc:
        report.problems.append(Problem(ERROR, str(file), str(exc)))
        return report
    result = parse_jsonl(text, str(file), limits)
    file_id = id_from_name(file.name)

    groups: dict[str, list[dict]] = {}
    metadata: dict[str, object] = {}
    for line in result.lines:
        obj = line.obj
        raw_id = obj.get("episode_id", obj.get("episodeId"))
        eid = file_id if raw_id is None or raw_id == "" else str(raw_id)
        keys = set(obj) - {"episode_id", "episodeId"}
        if keys and keys <= _METADATA_KEYS:
            metadata[eid] = obj.get("metadata", obj.get("episode_metadata"))
            groups.setdefault(eid, [])
            continue
        groups.setdefault(eid, []).append(obj)

    if not groups:
        report.problems.extend(result.problems)
        if result.lost:
            report.problems.append(Problem(ERROR, str(file), f"none of the {result.lost} non-blank lines could "
                                           f"be read as a step"))
        else:
            report.skipped = True
            report.skip_reason = "no steps"
            report.problems.append(Problem(WARNING, str(file), "JSONL file holds no steps; skipped"))
        return report

    several = len(groups) > 1
    for eid, objs in groups.items():
        source = f"{file}#{eid}" if several else str(file)
        ep = Episode(episode_id=eid, metadata={}, steps=[], source=source, layout=LAYOUT, blob_root=str(file.parent))
        ep.metadata = normalize_metadata(metadata.get(eid), layout=LAYOUT, fallback_id=eid,
                                         warn=lambda msg, fld, ep=ep: ep.warn(msg, field=fld))
        ep.episode_id = str(ep.metadata["episode_id"])
        for obj in objs:
            ep.steps.append(step_from_obj(obj, len(ep.steps), ep, source=str(file)))
        if not ep.steps:
            ep.warn("episode has no steps")
        assign_timestamps(ep)
        report.episodes.append(ep)

    # Line-level problems cannot be tied to an episode once a line failed to parse (its
    # episode_id is unknown): with one episode they belong to it, otherwise to the file.
    if len(report.episodes) == 1:
        report.episodes[0].problems[:0] = result.problems
        report.episodes[0].steps_lost += result.lost
    else:
        report.problems.extend(result.problems)
    return report
