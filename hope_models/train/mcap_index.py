"""A finished run's metrics as one indexed MCAP: `index_segments(run_dir)`.

While a run trains, MetricsLog writes metrics.mcap unchunked and flushed message by message (a
kill loses nothing written; train/metrics.py), and a resumed attempt writes the next segment,
metrics.1.mcap, ... When the run ends for good (the trainer's last "state" event says completed,
failed or cancelled and MetricsLog.close() runs on that normal exit), every segment is rewritten
into one indexed file: chunked (zstd when the zstandard module is there), with chunk and message
indexes, statistics and a summary, so Foxglove and `mcap info` open it at once and seek in it.

The segments are copied in writing order (metrics.mcap, metrics.1.mcap, ...: each attempt after
the previous one, so in log-time order unless the clock was set back), message by message with
their log and publish times, sequence numbers, channels and schemas, streamed (memory stays flat
however long the run). A segment cut short by a kill contributes every message before the damage.
The new file carries a metadata record "hope.metrics" {"merged_segments": "metrics.mcap,...",
"sizes": "<bytes>,..."}, and a later attempt's segment is numbered past those names.

Atomic: the new file is written to a temp file in the run dir (.metrics.mcap.tmp-<pid>-<random>,
durable.atomic_open), fsynced and renamed over metrics.mcap, the dir fsynced, and only then are metrics.1.mcap, ... deleted.
A crash before the rename leaves the segments as they were (and a temp file, removed by the next
index_segments); a crash after it leaves the merged metrics.mcap plus segments it already holds:
the next MetricsLog or index_segments (`clean_merged`) deletes the segments the metadata record
names (same name, same size) instead of merging them twice. Any error leaves the segments intact and is logged, not raised:
the index is a convenience, the streaming files are the record.
"""
from __future__ import annotations

import logging
import os
import time
from pathlib import Path

from mcap.records import Channel, Message, Metadata, Schema
from mcap.stream_reader import StreamReader
from mcap.writer import CompressionType, Writer

from hope_models.durable import atomic_open, fsync_path
from hope_models.train.metrics_files import MCAP_STEM, PROFILE, mcap_segments

log = logging.getLogger(__name__)

MERGED_METADATA = "hope.metrics"
TMP_PREFIX = ".metrics.mcap.tmp-"  # hope_models/durable.py's temp name for metrics.mcap


def _compression() -> CompressionType:
    try:
        import zstandard  # noqa: F401  mcap's zstd chunks need it
    except ImportError:
        return CompressionType.NONE
    return CompressionType.ZSTD


def merged_segments(path: Path) -> dict[str, int | None]:
    """{segment name: its size then} a merged metrics.mcap says it holds ({} for a streaming one)."""
    try:
        with open(path, "rb") as f:
            for record in StreamReader(f, skip_magic=False).records:
                if isinstance(record, Metadata) and record.name == MERGED_METADATA:
                    names = [n for n in record.metadata.get("merged_segments", "").split(",") if n]
                    sizes = [int(x) if x.isdigit() else None for x in record.metadata.get("sizes", "").split(",")]
                    return {n: (sizes[i] if i < len(sizes) else None) for i, n in enumerate(names)}
                if isinstance(record, Message):
                    return {}  # the metadata record is written before the first message
    except Exception:  # noqa: BLE001  a damaged file holds no merge record we can trust
        return {}
    return {}


def merged_names(path: Path) -> list[str]:
    """The segment names a merged metrics.mcap says it holds ([] for a streaming segment)."""
    return list(merged_segments(path))


def clean_merged(run_dir: Path) -> list[Path]:
    """Delete the segments the first segment already holds (a crash between the rename and the
    deletes) and temp files a crashed rewrite left; returns the segments still to read."""
    for tmp in run_dir.glob(TMP_PREFIX + "*"):
        tmp.unlink(missing_ok=True)
    segments = mcap_segments(run_dir)
    if not segments:
        return []
    merged = merged_segments(segments[0])
    # a leftover is the very file merged: its name and size match the record (later segments
    # get new names: metrics._next_segment numbers past the merged ones)
    done = {s.name for s in segments[1:] if s.name in merged and merged[s.name] == s.stat().st_size}
    for seg in segments[1:]:
        if seg.name in done:
            log.info("%s: already merged into %s; deleting it", seg, segments[0].name)
            seg.unlink(missing_ok=True)
    if done:
        fsync_path(run_dir)
    return [s for s in segments if s.name not in done]


class _Copier:
    """Copies segments' messages into one Writer, mapping their schemas and channels."""

    def __init__(self, writer: Writer):
        self.writer = writer
        self.schemas: dict[tuple[str, str, bytes], int] = {}
        self.channels: dict[tuple[str, str, int], int] = {}
        self.count = 0

    def copy(self, path: Path) -> None:
        schemas: dict[int, int] = {0: 0}
        channels: dict[int, int] = {}
        with open(path, "rb") as f:
            try:
                for record in StreamReader(f).records:
                    if isinstance(record, Schema):
                        key = (record.name, record.encoding, bytes(record.data))
                        if key not in self.schemas:
                            self.schemas[key] = self.writer.register_schema(record.name, record.encoding, record.data)
                        schemas[record.id] = self.schemas[key]
                    elif isinstance(record, Channel):
                        key = (record.topic, record.message_encoding, schemas.get(record.schema_id, 0))
                        if key not in self.channels:
                            self.channels[key] = self.writer.register_channel(record.topic, record.message_encoding,
                                                                              key[2], dict(record.metadata))
                        channels[record.id] = self.channels[key]
                    elif isinstance(record, Message) and record.channel_id in channels:
                        self.writer.add_message(channels[record.channel_id], record.log_time, record.data,
                                                record.publish_time, record.sequence)
                        self.count += 1
            except Exception as exc:  # noqa: BLE001  a segment cut short by a kill: keep what was read
                log.warning("%s: read up to a damaged record (%s: %s); the messages before it are kept",
                            path, type(exc).__name__, exc)


def index_segments(run_dir: str | os.PathLike) -> Path | None:
    """Rewrite the run's MCAP segments as one indexed metrics.mcap; its path, or None when there
    is none or the rewrite failed (then the segments are untouched)."""
    run = Path(run_dir)
    t0 = time.monotonic()
    try:
        segments = clean_merged(run)
    except OSError as exc:
        log.warning("%s: MCAP segments not indexed: %s", run, exc)
        return None
    if not segments:
        return None
    target = run / f"{MCAP_STEM}.mcap"
    try:
        with atomic_open(target, "wb") as f:  # its temp file is TMP_PREFIX + pid + random
            writer = Writer(f, use_chunking=True, compression=_compression())
            writer.start(profile=PROFILE, library="hope-seed-trainer")
            writer.add_metadata(MERGED_METADATA, {"merged_segments": ",".join(s.name for s in segments),
                                                  "sizes": ",".join(str(s.stat().st_size) for s in segments)})
            copier = _Copier(writer)
            for seg in segments:
                copier.copy(seg)
            writer.finish()
    except Exception as exc:  # noqa: BLE001  never lose the streaming files over the index
        log.warning("%s: MCAP segments not indexed (the streaming files are kept): %s", run, exc)
        return None
    for seg in segments:
        if seg != target:
            seg.unlink(missing_ok=True)
    fsync_path(run)
    log.info("%s: %d MCAP message(s) of %d segment(s) indexed in %.2f s", target, copier.count, len(segments),
             time.monotonic() - t0)
    return target
