"""The indexed MCAP a finished run leaves (hope_models/train/mcap_index.py via MetricsLog.close):
chunked with indexes and statistics after a final state, every segment of a resumed run merged,
the streaming file kept for a pause or a kill, and a crash between the merge's rename and its
deletes never counting a segment twice."""
from __future__ import annotations

import json
import os
import signal
import subprocess
import sys
import time
from pathlib import Path

from mcap.reader import make_reader

from hope_models.train.mcap_index import index_segments, merged_names
from hope_models.train.metrics import MetricsLog, mcap_segments, read_jsonl, read_mcap_records

MAGIC = b"\x89MCAP0\r\n"


def _jsonl_records(run: Path) -> list[dict]:
    return read_jsonl(run / "metrics.jsonl")


def _summary(path: Path):
    with open(path, "rb") as f:
        return make_reader(f).get_summary()


def _messages(path: Path) -> list[dict]:
    with open(path, "rb") as f:
        return [json.loads(m.data) for _, _, m in make_reader(f).iter_messages(log_time_order=False)]


def _attempt(run: Path, steps: range, state: str, resume_at: int | None = None) -> None:
    log = MetricsLog(run)
    if resume_at is not None:
        log.event("resume", {"step": resume_at})
    for s in steps:
        log.log(s, {"loss": 1.0 / s, "lr": 1e-3})
    log.event("state", {"state": state, "step": steps[-1], "message": ""})
    log.close()


def test_completed_run_is_one_indexed_mcap(tmp_path):
    run = tmp_path / "run"
    _attempt(run, range(1, 301), "completed")
    path = run / "metrics.mcap"
    assert path.read_bytes()[:8] == MAGIC
    summary = _summary(path)
    records = _jsonl_records(run)
    assert summary.chunk_indexes, "no chunk indexes: not an indexed MCAP"
    assert summary.statistics.message_count == len(records) == 301
    assert _messages(path) == records
    assert merged_names(path) == ["metrics.mcap"]
    assert not list(run.glob(".metrics.mcap.tmp-*"))


def test_paused_then_resumed_then_completed_merges_the_segments(tmp_path):
    run = tmp_path / "run"
    _attempt(run, range(1, 101), "paused_user")
    # a pause keeps the streaming file: unchunked, no chunk indexes
    assert not _summary(run / "metrics.mcap").chunk_indexes
    _attempt(run, range(81, 201), "paused_memory", resume_at=80)
    assert [p.name for p in mcap_segments(run)] == ["metrics.mcap", "metrics.1.mcap"]
    _attempt(run, range(181, 251), "completed", resume_at=180)
    assert [p.name for p in mcap_segments(run)] == ["metrics.mcap"]
    summary = _summary(run / "metrics.mcap")
    records = _jsonl_records(run)
    assert summary.chunk_indexes
    assert summary.statistics.message_count == len(records) == 100 + 1 + 2 + 120 + 1 + 2 + 70 + 1 - 2
    assert _messages(run / "metrics.mcap") == records
    assert merged_names(run / "metrics.mcap") == ["metrics.mcap", "metrics.1.mcap", "metrics.2.mcap"]


def test_failed_and_cancelled_runs_are_indexed_too(tmp_path):
    for state in ("failed", "cancelled"):
        run = tmp_path / state
        _attempt(run, range(1, 11), state)
        assert _summary(run / "metrics.mcap").chunk_indexes, state


def test_a_crash_after_the_rename_does_not_count_a_segment_twice(tmp_path):
    run = tmp_path / "run"
    _attempt(run, range(1, 51), "paused_user")
    _attempt(run, range(41, 61), "paused_user", resume_at=40)
    kept = (run / "metrics.1.mcap").read_bytes()
    index_segments(run)
    # as if the process died after os.replace and before deleting metrics.1.mcap
    (run / "metrics.1.mcap").write_bytes(kept)
    (run / ".metrics.mcap.tmp-99999").write_bytes(b"half a file")
    _attempt(run, range(51, 71), "completed", resume_at=50)
    assert [p.name for p in mcap_segments(run)] == ["metrics.mcap"]
    assert not list(run.glob(".metrics.mcap.tmp-*"))
    assert _messages(run / "metrics.mcap") == _jsonl_records(run)


_KILLED = """
import sys, time
from hope_models.train.metrics import MetricsLog
log = MetricsLog(sys.argv[1])
for s in range(1, 51):
    log.log(s, {"loss": 1.0 / s})
log.event("state", {"state": "completed", "step": 50})
print("ready", flush=True)
time.sleep(60)
"""


def test_a_killed_log_still_reads_with_the_streaming_reader(tmp_path):
    run = tmp_path / "run"
    proc = subprocess.Popen([sys.executable, "-c", _KILLED, str(run)], stdout=subprocess.PIPE, text=True)
    try:
        assert proc.stdout.readline().strip() == "ready"
    finally:
        os.kill(proc.pid, signal.SIGKILL)
        proc.wait()
    records, complete = read_mcap_records(run / "metrics.mcap")
    assert not complete
    assert [r for _, r in records] == _jsonl_records(run)
    assert len(records) == 51
    # the next attempt still starts a new segment; indexing then merges both
    _attempt(run, range(51, 61), "completed", resume_at=50)
    assert [r for r in _messages(run / "metrics.mcap")] == _jsonl_records(run)


def test_indexing_30k_messages(tmp_path):
    """The rewrite at a run's end, timed (100k messages took 2.0-3.6 s on the 2-core dev box)."""
    run = tmp_path / "run"
    log = MetricsLog(run)
    for s in range(1, 30_001):
        log.log(s, {"loss": 1.0 / s, "lr": 1e-3, "grad_norm": 0.5, "steps_per_s": 20.0, "rss_mb": 300.0})
    log.event("state", {"state": "completed", "step": 30_000})
    t0 = time.perf_counter()
    log.close()
    elapsed = time.perf_counter() - t0
    summary = _summary(run / "metrics.mcap")
    assert summary.statistics.message_count == 30_001
    print(f"indexing 30k messages: {elapsed:.2f} s")
    assert elapsed < 10.0
