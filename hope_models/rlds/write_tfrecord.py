"""Write TFRecord files (for tests and converters), framed exactly as TensorFlow does.

`episode_to_examples` produces the feature set of the Continuon JSON->TFRecord converter
(JSON text in bytes features plus a float32 copy of the command), with `timestamp_ns` added
as an int64 feature so the clock survives the trip. The JSON is ASCII (lone surrogates escaped);
a plain-text feature keeps a lone surrogate as the text `\\udXXX` (json_text.escape_surrogates).
"""
from __future__ import annotations

import gzip as gzip_module
import json
import os
import struct
from pathlib import Path
from typing import Any, Iterable, Mapping

from .episode import Episode
from .json_text import escape_surrogates
from .read_tfrecord import masked_crc
from .tf_example import FLOAT, Feature, encode_example


def frame_record(payload: bytes) -> bytes:
    length = struct.pack("<Q", len(payload))
    return length + struct.pack("<I", masked_crc(length)) + payload + struct.pack("<I", masked_crc(payload))


def write_tfrecord(path: str | os.PathLike, examples: Iterable[bytes | Mapping[str, Any]],
                   gzip: bool = False) -> Path:
    """Each item is either a feature mapping (encoded with tf_example.encode_example) or raw
    payload bytes (written as given, which lets tests frame payloads that are not Examples)."""
    target = Path(path)
    body = b"".join(frame_record(ex if isinstance(ex, (bytes, bytearray)) else encode_example(ex))
                    for ex in examples)
    if gzip:
        body = gzip_module.compress(body, mtime=0)
    target.write_bytes(body)
    return target


def _command(block: dict) -> list[float]:
    cmd = block.get("command")
    if isinstance(cmd, list) and all(isinstance(v, (int, float)) and not isinstance(v, bool) for v in cmd):
        return [float(v) for v in cmd]
    return []


def episode_to_examples(ep: Episode) -> list[dict[str, Any]]:
    examples = []
    for i, step in enumerate(ep.steps):
        features: dict[str, Any] = {
            "episode_id": escape_surrogates(ep.episode_id),  # a bytes feature holds UTF-8
            "step_index": i,
            "reward": float(step.reward),
            "is_terminal": int(step.is_terminal),
            "observation": json.dumps(step.observation),
            "action": json.dumps(step.action),
            "observation_command": Feature(FLOAT, _command(step.observation)),
            "action_command": Feature(FLOAT, _command(step.action)),
        }
        if step.step_metadata:
            features["step_metadata"] = json.dumps(step.step_metadata)
        if step.timestamp_ns is not None:
            features["timestamp_ns"] = step.timestamp_ns
        examples.append(features)
    return examples
