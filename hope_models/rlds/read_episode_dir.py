"""Episode directories: `<id>/metadata.json` + `<id>/steps/*.jsonl` (+ `blobs/`).

Every producer writes only `steps/000000.jsonl`, but all `steps/*.jsonl` are read in lexical
order; a legacy top-level `steps.jsonl` is read when there is no `steps/` dir. A dir with
metadata and no steps is a skip, not an error: the Pi's autonomous loop leaves many of them.

Our own canonical dirs (schema_version "1.1" with provenance.origin) are read on a lean path,
because training reads hundreds of thousands of steps from them: their keys are already
canonical and their metadata is taken as written, so reading them back is lossless. A producer's
dir (the XR app's) has its frame ids matched to frame files (rlds/frame_files.py).
"""
from __future__ import annotations

import os
from pathlib import Path

from .episode import ERROR, WARNING, Episode, Problem, SourceReport
from .frame_files import attach_frame_ids
from .json_text import ReadLimits, TextReadError, parse_json_document, parse_jsonl, read_text
from .normalize import canonical_step, normalize_metadata, step_from_obj
from .timestamps import assign_timestamps

METADATA_FILE = "metadata.json"
LEGACY_STEPS_FILE = "steps.jsonl"


def is_episode_dir(path: Path) -> bool:
    return (path / METADATA_FILE).is_file()


def step_files(path: Path) -> list[Path]:
    steps_dir = path / "steps"
    files = sorted(steps_dir.glob("*.jsonl")) if steps_dir.is_dir() else []
    return [f for f in files if f.is_file()]


def _is_canonical(metadata: object) -> bool:
    if not isinstance(metadata, dict) or metadata.get("schema_version") != "1.1":
        return False
    provenance = metadata.get("provenance")
    return isinstance(provenance, dict) and bool(provenance.get("origin"))


def read_episode_dir(path: str | os.PathLike, limits: ReadLimits | None = None) -> SourceReport:
    limits = limits or ReadLimits()
    root = Path(path)
    report = SourceReport(source=str(root))
    meta_file = root / METADATA_FILE
    have_metadata = meta_file.is_file()
    raw_md: object = None
    if have_metadata:
        try:
            raw_md = parse_json_document(read_text(meta_file, limits))
        except TextReadError as exc:
            report.problems.append(Problem(ERROR, str(meta_file), str(exc)))
            return report

    files = step_files(root)
    legacy = root / LEGACY_STEPS_FILE
    ignored_legacy = False
    if not files and legacy.is_file():
        files = [legacy]
    elif files and legacy.is_file():
        ignored_legacy = True

    if not files:
        report.skipped = True
        report.skip_reason = "metadata only: no steps/*.jsonl"
        report.problems.append(Problem(WARNING, str(root), "metadata.json without steps (no steps/*.jsonl); skipped"))
        return report

    canonical = _is_canonical(raw_md)
    layout = "canonical_dir" if canonical else "episode_dir"
    ep = Episode(episode_id=root.name, metadata={}, steps=[], source=str(root), layout=layout,
                 blob_root=str(root))
    if canonical:
        metadata = dict(raw_md)
        if not metadata.get("episode_id"):
            metadata["episode_id"] = root.name
    else:
        metadata = normalize_metadata(raw_md, layout=layout, fallback_id=root.name,
                                      warn=lambda msg, fld: ep.warn(msg, field=fld, source=str(meta_file)))
    ep.metadata = metadata
    ep.episode_id = str(metadata["episode_id"])
    if not have_metadata:
        ep.warn(f"no {METADATA_FILE}; metadata derived from the directory name", source=str(meta_file))
    if ignored_legacy:
        ep.warn(f"both steps/ and {LEGACY_STEPS_FILE} exist; {LEGACY_STEPS_FILE} ignored", source=str(legacy))

    steps = ep.steps
    for file in files:
        try:
            text = read_text(file, limits)
        except TextReadError as exc:
            ep.error(str(exc), source=str(file))
            continue
        result = parse_jsonl(text, str(file), limits)
        ep.problems.extend(result.problems)
        ep.steps_lost += result.lost
        source = str(file)
        for line in result.lines:
            step = canonical_step(line.obj, len(steps)) if canonical else None
            if step is None:  # a hand-edited or foreign line still gets the full mapping
                step = step_from_obj(line.obj, len(steps), ep, source=source)
            steps.append(step)

    if not steps:
        ep.warn("steps files hold no steps")
    if not canonical:  # a producer's dir (the XR app's): frame ids name files; ours are attached already
        attach_frame_ids(ep, root)
    assign_timestamps(ep, canonical=canonical)
    report.episodes.append(ep)
    return report
