"""TFRecord files of one `tf.train.Example` per step, gzip or not, intact or damaged.

Framing per record: u64 length, masked CRC32C of the length, payload, masked CRC32C of the
payload. Both CRCs are checked. Compression is detected from the gzip magic `1f 8b`, never
from the name; concatenated gzip members are read in turn, bounded by what they produce
(rlds/tfrecord_framing.py, which finds the records at native speed).

Damage seen in the wild (the Continuon `.tfrecord.gz` samples): an empty gzip member followed
by uncompressed TFRecord bytes that overwrote the start of record 0. Bytes after the gzip data
that are not gzip are read as uncompressed TFRecord, and after any bad record the reader
scans forward to the next offset where both the length CRC and the payload CRC are valid.
What was skipped is reported, and `step_index` gaps say which steps were lost.

Episodes are rebuilt by grouping records on `episode_id` and ordering by `step_index`.
"""
from __future__ import annotations

import json
import os
import struct
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from hope_models.numbers import huge_integer_error

from .episode import ERROR, WARNING, Episode, Problem, SourceReport
from .json_text import ReadLimits, TextReadError, read_bytes
from .normalize import id_from_name, normalize_metadata, step_from_obj
from .tf_example import BYTES, FLOAT, ExampleDecodeError, Feature, decode_example, float32_value
from .tfrecord_framing import GZIP_MAGIC, masked_crc, scan_records, unwrap_gzip, valid_record_at
from .timestamps import assign_timestamps

__all__ = ["GZIP_MAGIC", "LAYOUT", "masked_crc", "read_tfrecord", "scan_records", "unwrap_gzip", "valid_record_at"]

LAYOUT = "tfrecord"
# Features with a fixed meaning; anything else is kept in the step's extras.
_KNOWN = {"episode_id", "step_index", "reward", "is_terminal", "observation", "action", "step_metadata",
          "observation_command", "action_command"}


def _text(value: bytes) -> str | None:
    try:
        return value.decode("utf-8", "surrogatepass")  # a lone surrogate's bytes: kept (json_text.decode_text)
    except UnicodeDecodeError:
        return None


def _plain(feature: Feature) -> Any:
    """A feature's value as JSON-able data: single values unwrapped, bytes as text or hex."""
    if feature.kind == BYTES:
        vals: list[Any] = [_text(v) if _text(v) is not None else v.hex() for v in feature.values]
    elif feature.kind == FLOAT:
        vals = [float32_value(v) for v in feature.values]
    else:
        vals = list(feature.values)
    return vals[0] if len(vals) == 1 else vals


def _json_feature(features: dict[str, Feature], name: str, problems: list[tuple[str, str]]) -> Any:
    f = features.get(name)
    if f is None or not f.values:
        return None
    raw = f.values[0]
    text = _text(raw) if isinstance(raw, bytes) else None
    if text is None:
        problems.append((name, f"feature {name} is not UTF-8 text"))
        return None
    try:
        return json.loads(text)
    except json.JSONDecodeError as exc:
        problems.append((name, f"feature {name} is not valid JSON: {exc.msg} (column {exc.colno})"))
        return None
    except ValueError as exc:  # an integer too long for int()
        problems.append((name, f"feature {name} is not usable JSON: {huge_integer_error(text) or exc}"))
        return None


def _step_metadata(features: dict[str, Feature]) -> Any:
    f = features.get("step_metadata")
    if f is None or not f.values:
        return None
    raw = f.values[0]
    text = _text(raw) if isinstance(raw, bytes) else None
    if text is None:
        return {"bytes_hex": raw.hex()} if isinstance(raw, bytes) else raw
    if not text.strip():
        return None
    if text.lstrip().startswith("{"):
        try:
            return json.loads(text)
        except ValueError:  # not JSON (or an integer too long for int()): kept as the text it is
            pass
    return text  # plain text (the wiki TFRecord): normalize turns it into {"text": ...}


def _same_float32(a: list, b: list) -> bool:
    if len(a) != len(b):
        return False
    try:
        return all(struct.pack("<f", float(x)) == struct.pack("<f", float(y)) for x, y in zip(a, b, strict=True))
    except (TypeError, ValueError, OverflowError):
        return False


@dataclass
class _Record:
    offset: str  # "byte N" or "decompressed byte N"
    episode_id: str | None
    step_index: int | None
    raw_step: dict[str, Any]
    notes: list[tuple[str, str]]  # (field, message) about this record
    command_notes: list[tuple[str, str]]


def _record_to_step(offset: str, features: dict[str, Feature]) -> _Record:
    notes: list[tuple[str, str]] = []
    eid_f = features.get("episode_id")
    episode_id = None
    if eid_f is not None and eid_f.values:
        v = eid_f.values[0]
        episode_id = (_text(v) if isinstance(v, bytes) else str(v)) or None
    idx_f = features.get("step_index")
    step_index = int(idx_f.values[0]) if idx_f is not None and idx_f.values and isinstance(idx_f.values[0], int) else None

    observation = _json_feature(features, "observation", notes)
    action = _json_feature(features, "action", notes)
    raw: dict[str, Any] = {
        "observation": observation if observation is not None else {},
        "action": action if action is not None else {},
    }
    rew = features.get("reward")
    if rew is not None and rew.values:
        raw["reward"] = float32_value(rew.values[0]) if rew.kind == FLOAT else rew.values[0]
    term = features.get("is_terminal")
    if term is not None and term.values:
        raw["is_terminal"] = term.values[0]
    meta = _step_metadata(features)
    if meta is not None:
        raw["step_metadata"] = meta
    if step_index is not None:
        raw["step_index"] = step_index

    # The float-list command copies are informational: the JSON is the source of truth. They fill
    # a missing JSON command, and a copy that disagrees with the JSON is reported, never merged.
    command_notes: list[tuple[str, str]] = []
    for feat_name, target, block in (("action_command", "action", raw["action"]),
                                     ("observation_command", "observation", raw["observation"])):
        f = features.get(feat_name)
        if f is None or not f.values or f.kind != FLOAT or not isinstance(block, dict):
            continue
        copy = [float32_value(v) for v in f.values]
        if "command" not in block:
            block["command"] = copy
        elif not (isinstance(block["command"], list) and _same_float32(block["command"], copy)):
            command_notes.append((f"{target}.command",
                                  f"feature {feat_name} {copy} disagrees with {target}.command "
                                  f"{block['command']!r}; the JSON value is kept"))
    for name, feature in features.items():
        if name not in _KNOWN:
            raw[name] = _plain(feature)
    return _Record(offset, episode_id, step_index, raw, notes, command_notes)


def _gaps(indices: list[int]) -> tuple[int, str]:
    """How many step indices below the highest one are absent, and which (as ranges). Works
    on the gaps between present values, so a wild index cannot make it enumerate billions."""
    present = sorted({i for i in indices if i >= 0})
    if not present:
        return 0, ""
    ranges = []
    prev = -1
    for v in present:
        if v > prev + 1:
            ranges.append(str(prev + 1) if v == prev + 2 else f"{prev + 1}-{v - 1}")
        prev = v
    text = ", ".join(ranges[:10]) + (", ..." if len(ranges) > 10 else "")
    return present[-1] + 1 - len(present), text


def read_tfrecord(path: str | os.PathLike, limits: ReadLimits | None = None) -> SourceReport:
    limits = limits or ReadLimits()
    file = Path(path)
    source = str(file)
    report = SourceReport(source=source)
    try:
        data = read_bytes(file, limits)
    except TextReadError as exc:
        report.problems.append(Problem(ERROR, source, str(exc)))
        return report

    file_notes: list[Problem] = []  # findings about the file, repeated on each of its episodes
    records, corrupt = _framed_records(data, source, limits, file_notes)
    decoded, bad_payloads = _decode_records(records, source, file_notes)
    corrupt_text = _describe_corrupt(corrupt)
    if not decoded:
        report.problems.extend(file_notes)
        if corrupt or bad_payloads or file_notes:
            what = f"{corrupt_text}; " if corrupt else ""
            report.problems.append(Problem(ERROR, source, f"{what}no valid record found"))
        else:
            report.skipped = True
            report.skip_reason = "no records"
            report.problems.append(Problem(WARNING, source, "TFRecord file holds no records; skipped"))
        return report

    file_id = id_from_name(file.name)
    groups: dict[str, list[_Record]] = {}
    for rec in decoded:
        groups.setdefault(rec.episode_id or file_id, []).append(rec)
    several = len(groups) > 1
    attributed = False  # whether a step_index gap accounts for the corrupt regions
    for eid, recs in groups.items():
        ep = Episode(episode_id=eid, metadata={}, steps=[], source=f"{source}#{eid}" if several else source,
                     layout=LAYOUT, blob_root=str(file.parent))
        ep.metadata = normalize_metadata(None, layout=LAYOUT, fallback_id=eid,
                                         warn=lambda msg, fld, ep=ep: ep.warn(msg, field=fld))
        ep.problems.extend(file_notes)
        attributed |= _fill_episode(ep, recs, corrupt_text if corrupt else "")
        assign_timestamps(ep)
        report.episodes.append(ep)

    if corrupt and not attributed:
        msg = (f"{corrupt_text}; no step_index gap in any episode, so the lost records were whole "
               f"episodes or trailing steps")
        if len(report.episodes) == 1:
            report.episodes[0].warn(msg)
        else:
            report.problems.append(Problem(WARNING, source, msg))
    return report


def _framed_records(data: bytes, source: str, limits: ReadLimits,
                    file_notes: list[Problem]) -> tuple[list[tuple[str, bytes]], list[tuple[str, int]]]:
    """([(where, payload)], [(where, length)] of the corrupt regions) from every gzip member and
    uncompressed stretch of the file."""
    container = unwrap_gzip(data, source, limits)
    file_notes.extend(container.notes)
    records: list[tuple[str, bytes]] = []
    corrupt: list[tuple[str, int]] = []
    for offset, part in container.parts:
        scan = scan_records(part, max(offset, 0), limits.budget, source)
        where = "decompressed data" if offset < 0 else "file"
        at = "decompressed byte" if offset < 0 else "byte"
        records.extend((f"{at} {o}", payload) for o, payload in scan.records)
        corrupt.extend((f"{at} {o}", n) for o, n in scan.corrupt)
        if scan.truncated_tail:
            file_notes.append(Problem(WARNING, source, f"last record of the {where} is truncated "
                                      f"({scan.truncated_tail} bytes); dropped"))
    return records, corrupt


def _decode_records(records: list[tuple[str, bytes]], source: str,
                    file_notes: list[Problem]) -> tuple[list[_Record], int]:
    """The records that decode as tf.train.Example, and how many did not."""
    decoded: list[_Record] = []
    bad_payloads = 0
    for offset, payload in records:
        try:
            features = decode_example(payload)
        except ExampleDecodeError as exc:
            bad_payloads += 1
            file_notes.append(Problem(WARNING, source, f"record at {offset} has valid CRCs but is not a "
                                      f"tf.train.Example ({exc}); skipped"))
            continue
        decoded.append(_record_to_step(offset, features))
    return decoded, bad_payloads


def _describe_corrupt(corrupt: list[tuple[str, int]]) -> str:
    if not corrupt:
        return ""
    total = sum(n for _, n in corrupt)
    spots = ", ".join(f"{n} bytes at {o}" for o, n in corrupt[:5]) + (", ..." if len(corrupt) > 5 else "")
    return f"{len(corrupt)} corrupt region(s) ({total} bytes) skipped [{spots}]"


def _fill_episode(ep: Episode, recs: list[_Record], corrupt_text: str) -> bool:
    """Append the records as steps in step_index order (file order without one) and report the
    step_index gaps; True when a gap is put down to the file's corrupt regions (`corrupt_text`)."""
    indexed = all(r.step_index is not None for r in recs)
    if indexed:
        recs = sorted(recs, key=lambda r: r.step_index)  # stable: duplicates stay in file order
        seen: set[int] = set()
        for r in recs:
            if r.step_index in seen:
                ep.warn(f"step_index {r.step_index} appears more than once (record at {r.offset})")
            seen.add(r.step_index)
    elif any(r.step_index is not None for r in recs):
        ep.warn("step_index missing on some records; records kept in file order")
    for r in recs:
        index = len(ep.steps)
        for fld, msg in r.notes:
            ep.error(f"{msg} (record at {r.offset})", step=index, field=fld)
        for fld, msg in r.command_notes:
            ep.warn(msg, step=index, field=fld)
        ep.steps.append(step_from_obj(r.raw_step, index, ep))
    if not indexed:
        return False
    missing, which = _gaps([r.step_index for r in recs])
    if not missing:
        return False
    have = len({r.step_index for r in recs})
    detail = f"steps {which} missing (recovered {have} of {have + missing} by step_index)"
    if corrupt_text:
        ep.warn(f"{corrupt_text}; {detail}")
        ep.steps_lost += missing
        return True
    ep.warn(f"step_index gap: {detail}")
    return False
