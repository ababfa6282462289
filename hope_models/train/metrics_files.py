"""A run's metrics files, by name: what the writer (metrics.py), the MCAP index (mcap_index.py)
and the column store (metric_series.py) all need, below all three.

    metrics.jsonl                     one JSON object a line (JSONL_NAME)
    metrics.mcap, metrics.1.mcap ...  MCAP segments, one per writer session (mcap_segments)
"""
from __future__ import annotations

import os
import re
from pathlib import Path

JSONL_NAME = "metrics.jsonl"
MCAP_STEM = "metrics"
METRICS_TOPIC = "/metrics"
EVENTS_TOPIC = "/events"
PROFILE = "hope.train.metrics"
RESERVED = ("type", "step", "wall_time")


def mcap_segments(run_dir: str | os.PathLike) -> list[Path]:
    """The run's MCAP segments in writing order: metrics.mcap, metrics.1.mcap, metrics.2.mcap, ..."""
    run = Path(run_dir)
    found: list[tuple[int, Path]] = []
    for p in run.glob(f"{MCAP_STEM}*.mcap"):
        m = re.fullmatch(rf"{MCAP_STEM}(?:\.(\d+))?\.mcap", p.name)
        if m:
            found.append((int(m.group(1) or 0), p))
    return [p for _, p in sorted(found)]


def segment_number(name: str) -> int:
    return 0 if name == f"{MCAP_STEM}.mcap" else int(name.split(".")[1])


__all__ = ["EVENTS_TOPIC", "JSONL_NAME", "MCAP_STEM", "METRICS_TOPIC", "PROFILE", "RESERVED", "mcap_segments",
           "segment_number"]
