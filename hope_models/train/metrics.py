"""Training metrics and events: metrics.jsonl, a crash-safe metrics.mcap, and an event callback.

Every record goes to three places:
  run_dir/metrics.jsonl   one JSON object per line, written and flushed line by line
  run_dir/metrics.mcap    JSON messages with jsonschema schemas on two channels, so Foxglove
                          plots /metrics.loss, /metrics.rss_mb, ... against time:
                            /metrics  {"type": "metric", "step", "wall_time", <name>: <value>, ...}
                            /events   {"type": "event", "kind", "wall_time", "payload": {...}}
  emit(kind, payload)     the worker's / CLI's callback ("metric" with the record, or the event)

Crash safety: the MCAP is written unchunked and the file is flushed after every message, so a
process killed with SIGKILL leaves a file whose messages up to the last flush read back with a
streaming reader (read_mcap_records here, or mcap's NonSeekingReader); only the summary and
footer are missing. An MCAP cannot be appended to after it is finished, so a resumed run
(MetricsLog on a run dir that already has one) writes the next segment, metrics.1.mcap,
metrics.2.mcap, ..., and appends to metrics.jsonl.

The end of a run: when the trainer's last "state" event says the run ended for good
(FINAL_STATES: completed, failed, cancelled) and close() runs, every segment is rewritten into one
indexed metrics.mcap (chunked, with indexes, statistics and a summary; atomic, the streaming files
kept until the indexed one is in place: train/mcap_index.py). A paused run (memory, disk, user,
shutdown) keeps its streaming segments: it resumes, and a pause must not wait for a rewrite.

A resumed run repeats the steps after its last checkpoint; the loop records an event of kind
"resume" with {"step": N}, and read_metrics / load_losses drop the earlier records of the steps
after N, so a summary sees each step once.

Values that are not finite (a NaN loss) are written as null: JSON has no NaN, and the event that
stops the run says what happened. No torch here.
"""
from __future__ import annotations

import json
import logging
import math
import os
import re
import time
from pathlib import Path
from typing import Any, Callable, Iterable

from mcap.records import Channel, Message
from mcap.stream_reader import StreamReader
from mcap.writer import CompressionType, Writer

from hope_models.durable import fsync_path
from hope_models.train.mcap_index import clean_merged, index_segments, merged_names
from hope_models.train.metric_series import write_columns
from hope_models.train.metrics_files import (  # noqa: F401 - the names every reader of a run's metrics uses
    EVENTS_TOPIC,
    JSONL_NAME,
    MCAP_STEM,
    METRICS_TOPIC,
    PROFILE,
    RESERVED,
    mcap_segments,
    segment_number,
)

log = logging.getLogger(__name__)

FINAL_STATES = ("completed", "failed", "cancelled")  # a "state" event naming one ends the run for good

METRIC_SCHEMA = {
    "title": "hope.train.Metric",
    "type": "object",
    "properties": {
        "type": {"const": "metric"},
        "step": {"type": "integer"},
        "wall_time": {"type": "number", "description": "unix time, s"},
        "loss": {"type": ["number", "null"]},
        "lr": {"type": ["number", "null"]},
        "grad_norm": {"type": ["number", "null"]},
        "steps_per_s": {"type": ["number", "null"]},
        "rss_mb": {"type": ["number", "null"]},
        "temp_c": {"type": ["number", "null"]},
        "throttle_level": {"type": ["string", "null"]},
    },
    "required": ["type", "step", "wall_time"],
    "additionalProperties": {"type": ["number", "string", "boolean", "null"]},
}

EVENT_SCHEMA = {
    "title": "hope.train.Event",
    "type": "object",
    "properties": {
        "type": {"const": "event"},
        "kind": {"type": "string"},
        "wall_time": {"type": "number", "description": "unix time, s"},
        "payload": {"type": "object"},
    },
    "required": ["type", "kind", "wall_time", "payload"],
}


def _clean(value: Any) -> Any:
    """JSON-safe: non-finite floats to None, numpy/torch scalars to Python numbers."""
    if isinstance(value, bool) or value is None or isinstance(value, str):
        return value
    if isinstance(value, int):
        return value
    if isinstance(value, float):
        return value if math.isfinite(value) else None
    if isinstance(value, dict):
        return {str(k): _clean(v) for k, v in value.items()}
    if isinstance(value, (list, tuple)):
        return [_clean(v) for v in value]
    item = getattr(value, "item", None)  # numpy and 0-d torch scalars
    if callable(item):
        try:
            return _clean(item())
        except (TypeError, ValueError):
            pass
    return str(value)


def _dumps(obj: dict) -> str:
    return json.dumps(obj, separators=(",", ":"), allow_nan=False, ensure_ascii=False)


def _next_segment(run: Path) -> Path:
    """The next unused segment name; past the names a merged metrics.mcap already holds, so a
    segment written after a merge is never mistaken for one it merged (train/mcap_index.py)."""
    existing = mcap_segments(run)
    if not existing:
        return run / f"{MCAP_STEM}.mcap"
    merged = [n for n in merged_names(existing[0]) if re.fullmatch(rf"{MCAP_STEM}(?:\.\d+)?\.mcap", n)]
    n = max(segment_number(p.name) for p in existing + [run / m for m in merged])
    return run / f"{MCAP_STEM}.{n + 1}.mcap"


def _truncate_partial_line(path: Path) -> None:
    """Cut a last line without its newline (a write cut short): appending to it would glue
    the next record onto it and spoil both."""
    size = path.stat().st_size
    if size == 0:
        return
    with open(path, "rb+") as f:
        f.seek(size - 1)
        if f.read(1) == b"\n":
            return
        pos = size
        while pos > 0:  # scan back for the last newline, a block at a time
            step = min(4096, pos)
            f.seek(pos - step)
            block = f.read(step)
            idx = block.rfind(b"\n")
            if idx >= 0:
                pos = pos - step + idx + 1
                break
            pos -= step
        log.warning("%s: cutting an incomplete last line (%d bytes) before appending", path, size - pos)
        f.truncate(pos)


class MetricsLog:
    def __init__(self, run_dir: str | os.PathLike, emit: Callable[[str, dict], None] | None = None):
        self.run_dir = Path(run_dir)
        self.run_dir.mkdir(parents=True, exist_ok=True)
        self._emit = emit
        jsonl = self.run_dir / JSONL_NAME
        if jsonl.exists():
            _truncate_partial_line(jsonl)
        clean_merged(self.run_dir)  # segments a merge crashed before deleting: never counted twice
        self.jsonl_path = jsonl
        # Line buffering would split nothing we care about; we flush explicitly after each line.
        self._jsonl = open(jsonl, "a", encoding="utf-8")
        self.mcap_path = _next_segment(self.run_dir)
        self._mcap_file = open(self.mcap_path, "wb")
        # Unchunked: each message is a complete record in the file as soon as it is flushed.
        self._writer = Writer(self._mcap_file, use_chunking=False, compression=CompressionType.NONE)
        self._writer.start(profile=PROFILE, library="hope-seed-trainer")
        metric_schema = self._writer.register_schema(name="hope.train.Metric", encoding="jsonschema",
                                                     data=json.dumps(METRIC_SCHEMA).encode())
        event_schema = self._writer.register_schema(name="hope.train.Event", encoding="jsonschema",
                                                    data=json.dumps(EVENT_SCHEMA).encode())
        self._channels = {
            METRICS_TOPIC: self._writer.register_channel(METRICS_TOPIC, "json", metric_schema),
            EVENTS_TOPIC: self._writer.register_channel(EVENTS_TOPIC, "json", event_schema),
        }
        self._mcap_file.flush()
        self._sequence = 0
        self._closed = False
        self._final = False  # the run ended for good: close() indexes the segments

    def _write(self, topic: str, record: dict) -> None:
        if self._closed:
            raise RuntimeError(f"{self.run_dir}: the metrics log is closed")
        text = _dumps(record)
        self._jsonl.write(text + "\n")
        self._jsonl.flush()
        now_ns = time.time_ns()
        self._writer.add_message(self._channels[topic], log_time=now_ns, publish_time=now_ns,
                                 data=text.encode("utf-8"), sequence=self._sequence)
        self._mcap_file.flush()
        self._sequence += 1

    def log(self, step: int, values: dict[str, Any]) -> dict:
        """One metric record for a training step; returns it (as written)."""
        clash = [k for k in values if k in RESERVED]
        if clash:
            raise ValueError(f"metric names {clash} are reserved for the record itself ({', '.join(RESERVED)})")
        record = {"type": "metric", "step": int(step), "wall_time": round(time.time(), 6)}
        record.update(_clean(dict(values)))
        self._write(METRICS_TOPIC, record)
        if self._emit is not None:
            self._emit("metric", record)
        return record

    def event(self, kind: str, payload: dict[str, Any] | None = None) -> dict:
        """An event record (throttle, checkpoint, resume, paused, nan, ...); returns it."""
        if not isinstance(kind, str) or not kind:
            raise ValueError(f"event kind must be a non-empty string, got {kind!r}")
        clean = _clean(dict(payload or {}))
        record = {"type": "event", "kind": kind, "wall_time": round(time.time(), 6), "payload": clean}
        self._write(EVENTS_TOPIC, record)
        if kind == "state":
            self._final = clean.get("state") in FINAL_STATES
        if self._emit is not None:
            self._emit(kind, clean)
        return record

    def sync(self) -> None:
        """fsync both files (the loop calls this at checkpoints: survives power loss, not only kill)."""
        if self._closed:
            return
        self._jsonl.flush()
        os.fsync(self._jsonl.fileno())
        self._mcap_file.flush()
        os.fsync(self._mcap_file.fileno())

    def close(self, index: bool | None = None) -> None:
        """Finish the MCAP (summary and footer) and close both files. Idempotent. Then, when the
        last "state" event ended the run for good (or index=True), rewrite the segments as one
        indexed metrics.mcap (train/mcap_index.py: seconds for 100k records; never raises) and
        save the metric columns (train/metric_series.py)."""
        if self._closed:
            return
        try:
            self._writer.finish()
            self.sync()
        finally:
            self._closed = True
            self._mcap_file.close()
            self._jsonl.close()
        fsync_path(self.run_dir)
        if self._final if index is None else index:
            index_segments(self.run_dir)
            write_columns(self.run_dir)  # the run page's first look at it loads, not parses

    def __enter__(self) -> "MetricsLog":
        return self

    def __exit__(self, *exc) -> None:
        self.close()


# -- reading back ---------------------------------------------------------------------------------

def read_mcap_records(path: str | os.PathLike) -> tuple[list[tuple[str, dict]], bool]:
    """(topic, record) pairs of one segment in file order, and whether the file is complete.

    Reads sequentially, so a segment cut short by a kill (no footer; maybe half a record at the
    end) yields every message before the damage and complete=False."""
    topics: dict[int, str] = {}
    out: list[tuple[str, dict]] = []
    complete = False
    with open(path, "rb") as f:
        try:
            for record in StreamReader(f).records:
                if isinstance(record, Channel):
                    topics[record.id] = record.topic
                elif isinstance(record, Message):
                    out.append((topics[record.channel_id], json.loads(record.data)))
            complete = True
        except Exception as exc:  # noqa: BLE001  the mcap library raises several types for a damaged tail
            log.debug("%s: stopped reading at %s: %s", path, type(exc).__name__, exc)
    return out, complete


def read_jsonl(path: str | os.PathLike) -> list[dict]:
    """Every complete, decodable line of a metrics.jsonl (a damaged line is skipped)."""
    records = []
    with open(path, encoding="utf-8", errors="replace") as f:
        for line in f:
            if not line.endswith("\n"):
                break  # cut short by a kill
            try:
                obj = json.loads(line)
            except json.JSONDecodeError:
                continue
            if isinstance(obj, dict):
                records.append(obj)
    return records


def latest_timeline(records: Iterable[dict]) -> list[dict]:
    """Drop metric records superseded by a resume: after an event {"kind": "resume",
    "payload": {"step": N}}, earlier metric records with step > N were trained again."""
    out: list[dict] = []
    for rec in records:
        if rec.get("type") == "event" and rec.get("kind") == "resume":
            step = (rec.get("payload") or {}).get("step")
            if isinstance(step, int):
                out = [r for r in out if r.get("type") != "metric" or r.get("step", 0) <= step]
        out.append(rec)
    return out


def read_metrics(run_dir: str | os.PathLike) -> list[dict]:
    """The run's records from metrics.jsonl, with repeated steps after a resume dropped."""
    path = Path(run_dir) / JSONL_NAME
    if not path.exists():
        return []
    return latest_timeline(read_jsonl(path))


def load_losses(run_dir: str | os.PathLike, key: str = "loss") -> list[tuple[int, float]]:
    """(step, loss) of every logged step, for convergence_summary of a run that may have resumed."""
    return [(r["step"], r[key]) for r in read_metrics(run_dir)
            if r.get("type") == "metric" and isinstance(r.get(key), (int, float))]


def convergence_summary(losses: Iterable[tuple[int, float]]) -> dict[str, float | int | None]:
    """Mean loss of the first and last 10 logged steps, their ratio, and the least-squares slope
    of loss over the step number (loss per step; negative while it learns). Non-finite losses are
    left out. With fewer than 20 points the two means share points; with none, all are None."""
    pts = sorted((int(s), float(v)) for s, v in losses if v is not None and math.isfinite(float(v)))
    n = len(pts)
    if n == 0:
        return {"first10_mean": None, "last10_mean": None, "ratio": None, "slope": None, "n": 0}
    first = sum(v for _, v in pts[:10]) / len(pts[:10])
    last = sum(v for _, v in pts[-10:]) / len(pts[-10:])
    ratio = last / first if first != 0 else None
    slope = None
    if n >= 2:
        mx = sum(s for s, _ in pts) / n
        my = sum(v for _, v in pts) / n
        sxx = sum((s - mx) ** 2 for s, _ in pts)
        if sxx > 0:
            slope = sum((s - mx) * (v - my) for s, v in pts) / sxx
    return {"first10_mean": first, "last10_mean": last, "ratio": ratio, "slope": slope, "n": n}
