"""The host over time: the daemon keeps the last hour of samples in memory and 24 h in the registry.

    h = SystemHistory(registry, interval_s=settings.system_sample_s)
    h.refill()                          # at daemon start: the registry's last hour, so a restart keeps the chart
    h.observe(sample, throttle_level)   # every tick; takes one sample every interval_s
    h.samples(seconds)                  # [sample...] of the last `seconds` (at most the window), oldest first
    h.unflushed()                       # the samples not yet in the registry
    h.flush()                           # at stop: write what is pending

A sample is {"time": ISO-8601 UTC, "mem_percent", "mem_used_mb", "mem_available_mb", "mem_total_mb",
"temp_c", "cpu_percent", "throttle_level"} (registry/system_samples.py FIELDS), the same names as
the `system.stats` event, so the System page appends live events to the chart it loaded.

The ring is bounded by count (window_s / interval_s) and read by time. Registry writes are
batched (one transaction about every FLUSH_S: the SD card is written once, not every 5 s) and
rows older than keep_s are pruned every PRUNE_S. A write that fails (the database locked past its
timeout, a full disk) is logged and retried with the next batch; it never stops the daemon's tick,
and what waits for it is bounded by the ring's size. Thread-safe: the webapp reads the ring from
its request threads under `serve`. No torch here.
"""
from __future__ import annotations

import logging
import math
import threading
import time
from collections import deque
from datetime import datetime, timedelta, timezone
from typing import Any, Callable

from registry import system_samples
from registry.system_samples import FIELDS, KEEP_S

log = logging.getLogger(__name__)

WINDOW_S = 3600.0
FLUSH_S = 30.0
PRUNE_S = 600.0


class SystemHistory:
    def __init__(self, registry: Any, interval_s: float = 5.0, *, window_s: float = WINDOW_S,
                 keep_s: float = KEEP_S, flush_s: float = FLUSH_S, prune_s: float = PRUNE_S,
                 clock: Callable[[], float] = time.monotonic):
        if not interval_s > 0:
            raise ValueError(f"system_sample_s must be > 0, got {interval_s!r}")
        self.registry = registry
        self.interval_s = float(interval_s)
        self.window_s = float(window_s)
        self.keep_s = float(keep_s)
        self.capacity = int(math.ceil(self.window_s / self.interval_s)) + 1
        self.flush_every = max(1, int(round(flush_s / self.interval_s)))
        self.prune_s = float(prune_s)
        self._clock = clock
        self._ring: deque[tuple[datetime, dict[str, Any]]] = deque(maxlen=self.capacity)
        self._pending: deque[dict[str, Any]] = deque(maxlen=self.capacity)
        self._lock = threading.Lock()
        self._next_at: float | None = None
        self._pruned_at: float | None = None
        self._failures = 0

    # -- writing -------------------------------------------------------------------------------

    def refill(self) -> int:
        """At start, before the first observe(): the registry's last window into the ring (oldest
        first); how many samples."""
        with self.registry.session(readonly=True) as s:
            rows = system_samples.recent_samples(s, self.window_s)
        with self._lock:
            self._ring.extend((system_samples.as_time(r["time"]), r) for r in rows)
        return len(rows)

    def observe(self, sample: dict[str, Any], throttle_level: int | None) -> bool:
        """Keep `sample` (a daemon.monitor sample) if one is due; True when it was kept."""
        now = self._clock()
        if self._next_at is not None and now < self._next_at:
            return False
        # On the grid while the tick keeps up; from now when it fell behind (a long tick).
        self._next_at = now + self.interval_s if self._next_at is None or now - self._next_at > self.interval_s \
            else self._next_at + self.interval_s
        entry = {"time": sample.get("time") or datetime.now(timezone.utc).isoformat(),
                 **{k: sample.get(k) for k in FIELDS}, "throttle_level": throttle_level}
        at = system_samples.as_time(entry["time"])
        with self._lock:
            self._ring.append((at, entry))
            self._pending.append(entry)
            due = len(self._pending) >= self.flush_every
        if due:
            self.flush()
        return True

    def flush(self) -> bool:
        """Write the pending samples (and prune, when due). False when the write failed (logged; the
        samples stay pending for the next try)."""
        with self._lock:
            batch = list(self._pending)
        if not batch:
            return True
        now = self._clock()
        prune = self._pruned_at is None or now - self._pruned_at >= self.prune_s
        try:
            with self.registry.session() as s:
                system_samples.record_samples(s, batch)
                if prune:
                    system_samples.prune(s, self.keep_s)
        except Exception as exc:  # noqa: BLE001 - the chart's history must never stop the daemon
            self._failures += 1
            if self._failures == 1 or self._failures % 20 == 0:
                log.warning("system history: writing %d sample(s) to the registry failed (%d in a row); kept "
                            "for the next try: %s: %s", len(batch), self._failures, type(exc).__name__, exc)
            return False
        if self._failures:
            log.info("system history: registry writes work again after %d failures", self._failures)
        self._failures = 0
        if prune:
            self._pruned_at = now
        written = {id(sample) for sample in batch}
        with self._lock:
            # observe() only appends (and, when full, drops the oldest): the written ones are a prefix
            while self._pending and id(self._pending[0]) in written:
                self._pending.popleft()
        return True

    # -- reading -------------------------------------------------------------------------------

    def samples(self, seconds: float | None = None, now: datetime | None = None) -> list[dict[str, Any]]:
        seconds = self.window_s if seconds is None else min(float(seconds), self.window_s)
        since = (now or datetime.now(timezone.utc)) - timedelta(seconds=seconds)
        with self._lock:
            return [dict(sample) for at, sample in self._ring if at >= since]

    def unflushed(self) -> list[dict[str, Any]]:
        with self._lock:
            return [dict(sample) for sample in self._pending]

    def __len__(self) -> int:
        return len(self._ring)


__all__ = ["FLUSH_S", "PRUNE_S", "SystemHistory", "WINDOW_S"]
