"""Validation verdicts: per episode, per source, and for every path a command names.

`episode_report` merges a reader's structural findings with the content rules of validate.py into
one verdict (accepted, with warnings, partly recovered, rejected, skipped); `validate_paths` is what
`validate` prints, and ingest and the cloud export build their reports from the same entries.
"""
from __future__ import annotations

import os
from collections import Counter
from pathlib import Path
from typing import Any, Iterable, Iterator, Sequence

from .discover import iter_reports
from .episode import ERROR, Episode, Problem, SourceReport
from .validate import PROFILES, validate_episode

STATUSES = ("accepted", "accepted_with_warnings", "partly_recovered", "rejected", "skipped")


def status_of(errors: Sequence[Any], warnings: Sequence[Any], steps_lost: int) -> str:
    if errors:
        return "rejected"
    if steps_lost:
        return "partly_recovered"
    return "accepted_with_warnings" if warnings else "accepted"


def episode_report(ep: Episode, profile: str = "train",
                   extra_problems: Iterable[Problem] = ()) -> dict[str, Any]:
    """The verdict on one episode; `extra_problems` are findings of its file (the SourceReport's)."""
    problems = list(extra_problems) + list(ep.problems) + validate_episode(ep, profile)
    errors = [str(p) for p in problems if p.severity == ERROR]
    warnings = [str(p) for p in problems if p.severity != ERROR]
    status = status_of(errors, warnings, ep.steps_lost)
    return {"source": ep.source, "episode_id": ep.episode_id, "ok": status != "rejected",
            "status": status, "steps": len(ep.steps), "steps_lost": ep.steps_lost,
            "errors": errors, "warnings": warnings}


def _source_entry(source: str, status: str, problems: Iterable[Problem],
                  note: str | None = None) -> dict[str, Any]:
    problems = list(problems)
    errors = [str(p) for p in problems if p.severity == ERROR]
    warnings = [str(p) for p in problems if p.severity != ERROR]
    if note and not errors and not warnings:
        warnings.append(f"{source}: {note}")
    return {"source": source, "episode_id": None, "ok": status != "rejected", "status": status,
            "steps": 0, "steps_lost": 0, "errors": errors, "warnings": warnings}


def report_entries(report: SourceReport, profile: str = "train") -> list[dict[str, Any]]:
    """One entry per episode of a SourceReport; a skipped source or a source that gave no
    episode (unreadable file) becomes a single entry so that every file shows up."""
    if report.skipped and not report.episodes:
        has_errors = any(p.severity == ERROR for p in report.problems)
        return [_source_entry(report.source, "rejected" if has_errors else "skipped",
                              report.problems, report.skip_reason or "skipped")]
    if not report.episodes:
        problems = list(report.problems)
        if not any(p.severity == ERROR for p in problems):
            problems.append(Problem(ERROR, report.source, "no episode could be read from this source"))
        return [_source_entry(report.source, "rejected", problems)]
    entries = []
    for ep in report.episodes:
        try:
            entries.append(episode_report(ep, profile, report.problems))
        except Exception as exc:  # bad data must not stop the other episodes; the entry says why
            entries.append(exception_entry(ep.source, exc, ep.episode_id))
    return entries


def exception_entry(source: str, exc: BaseException, episode_id: str | None = None) -> dict[str, Any]:
    return {"source": source, "episode_id": episode_id, "ok": False, "status": "rejected",
            "steps": 0, "steps_lost": 0, "errors": [f"{source}: {type(exc).__name__}: {exc}"],
            "warnings": []}


def summarize(entries: Sequence[dict[str, Any]]) -> dict[str, Any]:
    counts = Counter(e["status"] for e in entries)
    summary: dict[str, Any] = {status: counts.get(status, 0) for status in STATUSES}
    summary["episodes"] = sum(1 for e in entries if e["status"] != "skipped")
    summary["steps"] = sum(e["steps"] for e in entries)
    summary["ok"] = all(e["ok"] for e in entries)
    return summary


def read_reports(path: str | Path, **reader_options: Any) -> Iterator[SourceReport]:
    """The reports under one path, one at a time (discover already turns a reader crash on one
    file into an error report for that file, so one bad file never hides the others)."""
    return iter_reports([path], **reader_options)


def unique_paths(paths: Iterable[str | Path]) -> list[Path]:
    """The paths in order, without repeats of the same file (so nothing is counted twice)."""
    seen: set[str] = set()
    out = []
    for path in paths:
        key = os.path.realpath(path)
        if key not in seen:
            seen.add(key)
            out.append(Path(path))
    return out


def validate_paths(paths: Iterable[str | Path], profile: str = "train",
                   **reader_options: Any) -> dict[str, Any]:
    """Reads every path (files or dirs, recursively) and validates every episode found.

    Raises FileNotFoundError for a path that does not exist (a usage error, not bad data)."""
    if profile not in PROFILES:
        raise ValueError(f"unknown validation profile {profile!r} (known: {', '.join(PROFILES)})")
    paths = unique_paths(paths)
    for path in paths:
        if not path.exists():
            raise FileNotFoundError(f"{path}: no such file or directory")
    entries: list[dict[str, Any]] = []
    for path in paths:
        for report in read_reports(path, **reader_options):
            entries.extend(report_entries(report, profile))
    skipped = [{"source": e["source"], "reason": (e["warnings"] or ["skipped"])[0]}
               for e in entries if e["status"] == "skipped"]
    return {"episodes": entries, "skipped": skipped, "summary": summarize(entries)}
