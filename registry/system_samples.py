"""The host's sampled history in the registry (table system_samples): what the System page plots.

    record_sample(session, sample)              # one sample: a dict with "time" (ISO text or an
                                                # aware datetime) and any of FIELDS (missing: null)
    record_samples(session, samples)            # several, in one transaction
    recent_samples(session, seconds, now=None)  # [sample_json...] of the last `seconds`, oldest first
    prune(session, keep_s=KEEP_S, now=None)     # delete what is older than keep_s; how many rows

The daemon (daemon/system_history.py) writes them in batches and keeps 24 h; the standalone
webapp, which has no daemon in its process, reads them for GET /api/system/history. A sample
in JSON is {"time": ISO-8601 UTC, **FIELDS}, the field names of the `system.stats` event.
"""
from __future__ import annotations

import math
from datetime import datetime, timedelta, timezone
from typing import Any, Iterable

from sqlalchemy import delete, select

from registry.models import SystemSample, utcnow

FIELDS = ("mem_percent", "mem_used_mb", "mem_available_mb", "mem_total_mb", "temp_c", "cpu_percent",
          "throttle_level")
KEEP_S = 24 * 3600


def as_time(value: Any) -> datetime:
    """An aware UTC datetime from an ISO string or a datetime; ValueError names what is wrong."""
    if isinstance(value, str):
        value = datetime.fromisoformat(value)
    if not isinstance(value, datetime):
        raise ValueError(f"sample time {value!r} is neither ISO-8601 text nor a datetime")
    if value.tzinfo is None or value.utcoffset() is None:
        raise ValueError(f"sample time {value!r} has no timezone (UTC expected)")
    return value.astimezone(timezone.utc)


def _number(name: str, value: Any) -> float | int | None:
    if value is None:
        return None
    if isinstance(value, bool) or not isinstance(value, (int, float)):
        raise ValueError(f"sample field {name!r} = {value!r} is not a number")
    if not math.isfinite(value):
        return None  # a sensor's NaN is "no reading", not a point on the chart
    return int(value) if name == "throttle_level" else float(value)


def row_of(sample: dict[str, Any]) -> SystemSample:
    return SystemSample(time=as_time(sample["time"]), **{k: _number(k, sample.get(k)) for k in FIELDS})


def record_sample(session, sample: dict[str, Any]) -> None:
    """Add one sample (committed with the session). Fields beyond FIELDS are ignored."""
    session.add(row_of(sample))


def record_samples(session, samples: Iterable[dict[str, Any]]) -> int:
    rows = [row_of(s) for s in samples]
    session.add_all(rows)
    return len(rows)


def sample_json(row: SystemSample) -> dict[str, Any]:
    return {"time": row.time.isoformat(), **{k: getattr(row, k) for k in FIELDS}}


def recent_samples(session, seconds: float, now: datetime | None = None) -> list[dict[str, Any]]:
    since = (now or utcnow()) - timedelta(seconds=float(seconds))
    rows = session.scalars(select(SystemSample).where(SystemSample.time >= since)
                           .order_by(SystemSample.time, SystemSample.id))
    return [sample_json(r) for r in rows]


def prune(session, keep_s: float = KEEP_S, now: datetime | None = None) -> int:
    before = (now or utcnow()) - timedelta(seconds=float(keep_s))
    return session.execute(delete(SystemSample).where(SystemSample.time < before)).rowcount or 0


__all__ = ["FIELDS", "KEEP_S", "as_time", "prune", "recent_samples", "record_sample", "record_samples",
           "sample_json"]
