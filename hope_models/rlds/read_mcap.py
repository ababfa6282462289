"""Read an episode MCAP written by `write_mcap.write_episode_mcap` (JSON messages).

The file is read sequentially, so an MCAP cut short by a crash (no footer) still yields the
steps before the damage, with a warning. An MCAP without our two topics is not an episode and
is reported as such rather than guessed at.

Chunks are inflated here, not by the mcap library: it trusts a chunk's declared uncompressed size
(zstd) or none at all (lz4), inflates the chunk whole, and walks it (a few KB became 256 MB of
empty records walked one by one). Here a chunk is read record by record as it inflates, never
past the size it states, and all the file's chunks together may state at most
inflate_cap(file size) (and an upload's budget): past that the file is refused (InflateError,
naming it). A record inside a chunk that is not a schema, channel or message is damage.
"""
from __future__ import annotations

import io
import json
import os
import struct
from dataclasses import dataclass, field
from pathlib import Path
from typing import Iterator

from mcap.data_stream import ReadDataStream
from mcap.opcode import Opcode
from mcap.records import Channel, Chunk, Message
from mcap.stream_reader import StreamReader

from hope_models.numbers import huge_integer_error

from .episode import ERROR, WARNING, Episode, Problem, SourceReport
from .inflate import MAX_RATIO, Counted, InflateError, inflate_cap, open_inflated
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
    found = _read_messages(data, source, limits)
    if found.unreadable is not None:
        report.problems.append(found.unreadable)
        return report
    if STEPS_TOPIC not in found.topics.values():
        report.problems.extend(found.notes)
        report.problems.append(Problem(ERROR, source, f"not an episode MCAP: no {STEPS_TOPIC} channel"))
        return report
    report.episodes.append(_episode(file, found))
    return report


@dataclass
class _Messages:
    """What one sequential pass over the file found on our two topics, and what went wrong."""

    source: str
    topics: dict[int, str] = field(default_factory=dict)  # channel id -> topic
    encodings: dict[int, str] = field(default_factory=dict)  # channel id -> message encoding
    header: dict | None = None  # the METADATA_TOPIC message
    steps: list[tuple[int, dict]] = field(default_factory=list)  # (sequence in file, step object)
    notes: list[Problem] = field(default_factory=list)
    bad_messages: int = 0
    unreadable: Problem | None = None  # set when not even one channel could be read

    def take(self, record: Message) -> None:
        topic = self.topics.get(record.channel_id)
        if topic not in (METADATA_TOPIC, STEPS_TOPIC):
            return
        if self.encodings.get(record.channel_id) != "json":
            self.notes.append(Problem(ERROR, self.source, f"{topic} uses message encoding "
                                      f"{self.encodings.get(record.channel_id)!r}, expected json"))
            return
        try:
            obj = json.loads(record.data)
        except (json.JSONDecodeError, UnicodeDecodeError) as exc:
            self.bad(f"{topic} message {record.sequence} is not valid JSON ({exc})")
            return
        except ValueError as exc:  # an integer too long for int()
            self.bad(f"{topic} message {record.sequence} is not usable JSON "
                     f"({huge_integer_error(bytes(record.data)) or exc})")
            return
        if not isinstance(obj, dict):
            self.bad(f"{topic} message {record.sequence} is not a JSON object")
            return
        if topic == METADATA_TOPIC:
            self.header = obj
        else:
            self.steps.append((len(self.steps), obj))

    def bad(self, message: str) -> None:
        self.bad_messages += 1
        self.notes.append(Problem(ERROR, self.source, message))


class _Chunks:
    """The file's chunks, each inflated as it is read, record by record (see the module doc)."""

    def __init__(self, source: str, compressed: int, limits: ReadLimits):
        self.source, self.budget = source, limits.budget
        self.left = inflate_cap(compressed, limits)

    def records(self, chunk: Chunk) -> Iterator[Channel | Message]:
        """The chunk's Channel and Message records (schemas are not read); ValueError for damage,
        InflateError when its stated size is past what the file's chunks may still inflate to."""
        if chunk.uncompressed_size > self.left:
            raise InflateError(f"{self.source}: an MCAP chunk states {chunk.uncompressed_size} bytes "
                               f"uncompressed, more than the {self.left} its file's chunks may still inflate to "
                               f"({MAX_RATIO} times the file's size, or max_file_bytes): refused")
        with open_inflated(chunk.compression, chunk.data) as raw:
            stream = Counted(raw, chunk.uncompressed_size, self.source, self.budget)
            while stream.size < chunk.uncompressed_size:
                opcode, length = struct.unpack("<BQ", stream.read(9))
                if opcode not in (Opcode.CHANNEL, Opcode.MESSAGE, Opcode.SCHEMA):
                    raise ValueError(f"a record of opcode {opcode} inside a chunk")
                body = stream.read(length)
                if opcode == Opcode.CHANNEL:
                    yield Channel.read(ReadDataStream(io.BytesIO(body)))
                elif opcode == Opcode.MESSAGE:
                    yield Message.read(ReadDataStream(io.BytesIO(body)), length)
            if raw.read(1):
                raise ValueError(f"a chunk inflates to more than the {chunk.uncompressed_size} bytes it states")
        if chunk.uncompressed_crc and stream.crc != chunk.uncompressed_crc:
            raise ValueError(f"a chunk's CRC is {stream.crc:#010x}, it states {chunk.uncompressed_crc:#010x}")
        self.left -= stream.size


def _records(reader: StreamReader, chunks: _Chunks):
    for record in reader.records:
        if isinstance(record, Chunk):
            yield from chunks.records(record)
        else:
            yield record


def _read_messages(data: bytes, source: str, limits: ReadLimits) -> _Messages:
    found = _Messages(source)
    reader = StreamReader(io.BytesIO(data), emit_chunks=True, validate_crcs=True,
                          record_size_limit=limits.max_file_bytes)
    try:
        for record in _records(reader, _Chunks(source, len(data), limits)):
            if isinstance(record, Channel):
                found.topics[record.id] = record.topic
                found.encodings[record.id] = record.message_encoding
            elif isinstance(record, Message):
                found.take(record)
    except InflateError:
        raise
    except Exception as exc:  # the mcap library raises several types for damaged input
        if not found.topics:
            found.unreadable = Problem(ERROR, source, f"not a readable MCAP file ({type(exc).__name__}: {exc})")
        else:
            found.notes.append(Problem(WARNING, source, f"MCAP file ends early or is damaged after "
                                       f"{len(found.steps)} steps ({type(exc).__name__}: {exc}); "
                                       "the steps before are read"))
    return found


def _episode(file: Path, found: _Messages) -> Episode:
    source = found.source
    header = found.header or {}
    metadata = header.get("metadata") if found.header else None
    if not isinstance(metadata, dict):
        found.notes.append(Problem(WARNING, source, f"no usable {METADATA_TOPIC} message; metadata is empty"))
        metadata = {}
    episode_id = str(header.get("episode_id") or metadata.get("episode_id") or id_from_name(file.name))
    metadata = dict(metadata)
    metadata.setdefault("episode_id", episode_id)
    blob_root = header.get("blob_root")
    ep = Episode(episode_id=episode_id, metadata=metadata, steps=[], source=source, layout=LAYOUT,
                 blob_root=blob_root if isinstance(blob_root, str) else None)
    lost = header.get("steps_lost", 0)
    ep.steps_lost = (lost if isinstance(lost, int) else 0) + found.bad_messages
    ep.problems.extend(found.notes)

    # The step's own step_index orders it; file order breaks ties and covers its absence.
    steps = sorted(found.steps, key=lambda item: (item[1].get("step_index") if type(item[1].get("step_index")) is int
                                                  else item[0], item[0]))
    for _, obj in steps:
        ep.steps.append(step_from_obj(obj, len(ep.steps), ep, trusted=True))
    if not ep.steps:
        ep.warn("episode MCAP holds no steps")
    assign_timestamps(ep, canonical=True)
    return ep
