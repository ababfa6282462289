"""Write one canonical episode as an MCAP file that Foxglove opens.

Two channels, JSON message encoding with jsonschema schemas:
  /episode/metadata  one message: {"episode_id", "metadata", "steps_lost", "blob_root"}
  /episode/steps     one message per step: Step.to_json_obj(index)
log_time of a step is its timestamp_ns (or index * 100 ms when the episode has no clock); the
step's own `timestamp_ns` field stays the source of truth when reading back.

The file is written in small uncompressed chunks to a hidden temp file (hope_models.durable.atomic_open:
fsynced, renamed, the dir fsynced), so a crash never leaves a half-written `.mcap` that a reader
would take for an episode.
"""
from __future__ import annotations

import json
import os
from pathlib import Path

from mcap.writer import CompressionType, Writer

from ..durable import atomic_open
from .episode import Episode
from .json_text import json_bytes

METADATA_TOPIC = "/episode/metadata"
STEPS_TOPIC = "/episode/steps"
PROFILE = "hope.rlds.episode"
INDEX_PERIOD_NS = 100_000_000  # log_time spacing when an episode has no clock
CHUNK_BYTES = 256 * 1024

METADATA_SCHEMA = {
    "title": "hope.rlds.EpisodeMetadata",
    "type": "object",
    "properties": {
        "episode_id": {"type": "string"},
        "metadata": {"type": "object"},
        "steps_lost": {"type": "integer"},
        "blob_root": {"type": ["string", "null"]},
    },
    "required": ["episode_id", "metadata"],
}

STEP_SCHEMA = {
    "title": "hope.rlds.Step",
    "type": "object",
    "properties": {
        "step_index": {"type": "integer"},
        "timestamp_ns": {"type": ["integer", "null"]},
        "observation": {"type": "object"},
        "action": {"type": "object"},
        "reward": {"type": "number"},
        "is_terminal": {"type": "boolean"},
        "step_metadata": {"type": "object"},
    },
    "required": ["step_index", "observation", "action"],
}


def _dumps(obj: object) -> bytes:
    # allow_nan: a NaN that reached an export must survive the round trip so validation can
    # name it; Foxglove shows such a message as unparseable, which is the honest outcome.
    # json_bytes: a lone surrogate (a Dart string's) is kept as its \udXXX escape.
    return json_bytes(obj, separators=(",", ":"))


def write_episode_mcap(episode: Episode, path: str | os.PathLike) -> Path:
    target = Path(path)
    target.parent.mkdir(parents=True, exist_ok=True)
    with atomic_open(target, "wb") as stream:
        writer = Writer(stream, chunk_size=CHUNK_BYTES, compression=CompressionType.NONE)
        writer.start(profile=PROFILE, library="hope-seed-trainer")
        meta_schema = writer.register_schema(name="hope.rlds.EpisodeMetadata", encoding="jsonschema",
                                             data=json.dumps(METADATA_SCHEMA).encode())
        step_schema = writer.register_schema(name="hope.rlds.Step", encoding="jsonschema",
                                             data=json.dumps(STEP_SCHEMA).encode())
        meta_channel = writer.register_channel(topic=METADATA_TOPIC, message_encoding="json", schema_id=meta_schema)
        step_channel = writer.register_channel(topic=STEPS_TOPIC, message_encoding="json", schema_id=step_schema)

        times = [s.timestamp_ns for s in episode.steps]
        first = next((t for t in times if t is not None), 0)
        header = {"episode_id": episode.episode_id, "metadata": episode.metadata,
                  "steps_lost": episode.steps_lost, "blob_root": episode.blob_root}
        writer.add_message(meta_channel, log_time=max(0, first), publish_time=max(0, first), data=_dumps(header))
        for i, step in enumerate(episode.steps):
            t = step.timestamp_ns if step.timestamp_ns is not None else i * INDEX_PERIOD_NS
            t = max(0, t)  # MCAP times are unsigned
            writer.add_message(step_channel, log_time=t, publish_time=t, sequence=i,
                               data=_dumps(step.to_json_obj(i)))
        writer.finish()
    return target
