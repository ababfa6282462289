"""Read an episode MCAP written by `write_mcap.write_episode_mcap` (JSON messages).

The file is read sequentially, so an MCAP cut short by a crash (no footer) still yields the
steps before the damage, with a warning. An MCAP without our two topics is not an episode and
is reported as such rather than guessed at.
"""
from __future__ import annotations

import io
import json
import os
from pathlib import Path

from mcap.records import Channel, Message, Schema
from mcap.stream_reader import StreamReader

from .episode import ERROR, WARNING, Episode, Problem, SourceReport
from .json_text import ReadLimits, TextReadError, read_bytes
from .normalize import id_from_name, step_from_obj
from .timestamps import assign_timestamps
from .write_mcap import METADATA_TOPIC, STEPS_TOPIC

LAYOUT = "mcap"


def read_mcap(path: str | os.PathLike, limits: ReadLimits | None = None) -> SourceReport:
    limits = limits or ReadLimits()
    file = Path(path)
    source = str(file)
    report = SourceReport(source=source)
    try:
        data = read_bytes(file, limits)
    except TextReadError as exc:
        report.problems.append(Problem(ERROR, source, str(exc)))
        return report

    topics: dict[int, str] = {}
    encodings: dict[int, str] = {}
    header: dict | None = None
    steps: list[tuple[int, dict]] = []  # (sequence in file, step object)
    notes: list[Problem] = []
    bad_messages = 0
    reader = StreamReader(io.BytesIO(data), validate_crcs=True, record_size_limit=limits.max_file_bytes)
    try:
        for record in reader.records:
            if isinstance(record, Schema):
                continue
            if isinstance(record, Channel):
                topics[record.id] = record.topic
                encodings[record.id] = record.message_encoding
            elif isinstance(record, Message):
                topic = topics.get(record.channel_id)
                if topic not in (METADATA_TOPIC, STEPS_TOPIC):
                    continue
                if encodings.get(record.channel_id) != "json":
                    notes.append(Problem(ERROR, source, f"{topic} uses message encoding "
                                         f"{encodings.get(record.channel_id)!r}, expected json"))
                    continue
                try:
                    obj = json.loads(record.data)
                except (json.JSONDecodeError, UnicodeDecodeError) as exc:
                    bad_messages += 1
                    notes.append(Problem(ERROR, source, f"{topic} message {record.sequence} is not valid JSON ({exc})"))
                    continue
                if not isinstance(obj, dict):
                    bad_messages += 1
                    notes.append(Problem(ERROR, source, f"{topic} message {record.sequence} is not a JSON object"))
                    continue
                if topic == METADATA_TOPIC:
                    header = obj
                else:
                    steps.append((len(steps), obj))
    except Exception as exc:  # the mcap library raises several types for damaged input
        if not topics:
            report.problems.append(Problem(ERROR, source, f"not a readable MCAP file ({type(exc).__name__}: {exc})"))
            return report
        notes.append(Problem(WARNING, source, f"MCAP file ends early or is damaged after {len(steps)} steps "
                             f"({type(exc).__name__}: {exc}); the steps before are read"))

    if STEPS_TOPIC not in topics.values():
        report.problems.extend(notes)
        report.problems.append(Problem(ERROR, source, f"not an episode MCAP: no {STEPS_TOPIC} channel"))
        return report

    fallback_id = id_from_name(file.name)
    metadata = header.get("metadata") if header else None
    if not isinstance(metadata, dict):
        notes.append(Problem(WARNING, source, f"no usable {METADATA_TOPIC} message; metadata is empty"))
        metadata = {}
    episode_id = str((header or {}).get("episode_id") or metadata.get("episode_id") or fallback_id)
    metadata = dict(metadata)
    metadata.setdefault("episode_id", episode_id)
    blob_root = (header or {}).get("blob_root")
    ep = Episode(episode_id=episode_id, metadata=metadata, steps=[], source=source, layout=LAYOUT,
                 blob_root=blob_root if isinstance(blob_root, str) else None)
    lost = (header or {}).get("steps_lost", 0)
    ep.steps_lost = (lost if isinstance(lost, int) else 0) + bad_messages
    ep.problems.extend(notes)

    # The step's own step_index orders it; file order breaks ties and covers its absence.
    steps.sort(key=lambda item: (item[1].get("step_index") if type(item[1].get("step_index")) is int
                                 else item[0], item[0]))
    for _, obj in steps:
        ep.steps.append(step_from_obj(obj, len(ep.steps), ep, trusted=True))
    if not ep.steps:
        ep.warn("episode MCAP holds no steps")
    assign_timestamps(ep, canonical=True)
    report.episodes.append(ep)
    return report
