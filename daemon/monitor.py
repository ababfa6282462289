"""What the daemon watches on its host: memory (psutil), CPU, temperature, firmware throttling.

`SystemMonitor.sample()` is one snapshot, the payload of the `system.stats` event:

    {"time": ISO UTC, "mem_total_mb", "mem_used_mb", "mem_available_mb", "mem_percent", "cpu_percent",
     "temp_c": float | None, "throttled": {...vcgencmd flags...} | None,
     "sources": {"thermal_zone": {"path", "ok", "error"}, "vcgencmd": {"command", "ok", "error"}}}

The thermal sources are read through hope_models.train.thermal (the same readers and parsers the
trainer's governor uses), so a sysfs zone or a `vcgencmd` behave the same in both places. Neither
source is required: a missing one is logged once and shows in "sources", never an error.

`ThrottlePolicy` turns a reading into the throttle level the daemon writes on the active run
(the worker's control hook maps 1 to a half-speed throttle and 2 to a thermal pause):

    level 2  temp >= hard_c
    level 1  temp >= soft_c, or the firmware reports it is slowing the CPU now
    level 0  only once temp is below resume_c (and the firmware is not slowing): a level, once
             raised, holds between resume_c and soft/hard (hysteresis), so a job at the edge does
             not bounce between pause and run every few seconds.
No torch here.
"""
from __future__ import annotations

import logging
import time
from dataclasses import dataclass
from datetime import datetime, timezone
from typing import Any, Callable

import psutil

from hope_models.train.thermal import ThermalGovernor, ThrottledFlags

log = logging.getLogger(__name__)

MB = 1024 * 1024
LEVELS = (0, 1, 2)


class SystemMonitor:
    """Samples memory and CPU every call, the thermal sources at most every `thermal_interval_s`
    (vcgencmd is a subprocess; the daemon ticks twice a second). mem_used_mb is total - available,
the memory mem_percent counts (psutil's own "used" leaves out what the kernel cannot reclaim)."""

    def __init__(self, settings: Any = None, *, zone_path: str | None | bool = False,
                 vcgencmd: str | None | bool = False, thermal_interval_s: float = 1.0,
                 read_fn: Callable[[str], str] | None = None, clock: Callable[[], float] = time.monotonic):
        # False = take it from settings; None or "" = that source is switched off.
        if zone_path is False:
            zone_path = getattr(settings, "thermal_zone_path", None)
        if vcgencmd is False:
            vcgencmd = getattr(settings, "vcgencmd_path", None)
        self.zone_path = str(zone_path) if zone_path else None
        self.vcgencmd = str(vcgencmd) if vcgencmd else None
        self.thermal_interval_s = float(thermal_interval_s)
        self._clock = clock
        # The governor is used only as the reader of both sources (its levels are the trainer's,
        # not ours); it logs an unreadable zone or a failing vcgencmd once.
        self._reader = ThermalGovernor(self.zone_path, self.vcgencmd, read_fn=read_fn, clock=clock)
        self._thermal_at: float | None = None
        self._temp_c: float | None = None
        self._flags: ThrottledFlags | None = None
        self._reported: set[str] = set()
        psutil.cpu_percent(interval=None)  # primes the counter: the first real call then has a baseline

    def _read_thermal(self) -> None:
        now = self._clock()
        if self._thermal_at is not None and now - self._thermal_at < self.thermal_interval_s:
            return
        reading = self._reader.sample()
        self._temp_c, self._flags, self._thermal_at = reading.temp_c, reading.throttled_flags, now
        for name, configured, got in (("thermal_zone", self.zone_path, self._temp_c is not None),
                                      ("vcgencmd", self.vcgencmd, self._flags is not None)):
            if configured and not got and name not in self._reported:
                self._reported.add(name)
                log.info("monitor: %s %s gives no reading; the throttle level ignores it", name, configured)
            elif got:
                self._reported.discard(name)

    def sources(self) -> dict[str, Any]:
        zone_ok = self._temp_c is not None
        vc_ok = self._flags is not None
        return {
            "thermal_zone": {"path": self.zone_path, "ok": zone_ok,
                             "error": None if zone_ok else ("not configured" if not self.zone_path
                                                            else "not readable")},
            "vcgencmd": {"command": self.vcgencmd, "ok": vc_ok,
                         "error": None if vc_ok else ("not configured" if not self.vcgencmd
                                                      else "not available")},
        }

    def sample(self) -> dict[str, Any]:
        mem = psutil.virtual_memory()
        self._read_thermal()
        return {
            "time": datetime.now(timezone.utc).isoformat(),
            "mem_total_mb": round(mem.total / MB, 1),
            "mem_used_mb": round((mem.total - mem.available) / MB, 1),
            "mem_available_mb": round(mem.available / MB, 1),
            "mem_percent": float(mem.percent),
            "cpu_percent": float(psutil.cpu_percent(interval=None)),
            "temp_c": self._temp_c,
            "throttled": self._flags.to_json_obj() if self._flags is not None else None,
            "sources": self.sources(),
        }


@dataclass(frozen=True)
class ThrottleChange:
    level: int
    previous: int
    reason: str
    temp_c: float | None

    def to_json_obj(self) -> dict[str, Any]:
        return {"level": self.level, "previous": self.previous, "reason": self.reason, "temp_c": self.temp_c}


class ThrottlePolicy:
    """update(temp_c, slowing_now) -> ThrottleChange when the level changes, else None."""

    def __init__(self, soft_c: float = 75.0, hard_c: float = 82.0, resume_c: float = 70.0):
        soft_c, hard_c, resume_c = float(soft_c), float(hard_c), float(resume_c)
        if not soft_c < hard_c:
            raise ValueError(f"thermal limits: thermal_soft_c ({soft_c:g}) must be below thermal_hard_c ({hard_c:g})")
        if not resume_c <= soft_c:
            raise ValueError(f"thermal limits: thermal_resume_c ({resume_c:g}) must not be above "
                             f"thermal_soft_c ({soft_c:g})")
        self.soft_c, self.hard_c, self.resume_c = soft_c, hard_c, resume_c
        self.level = 0

    @classmethod
    def from_settings(cls, settings: Any) -> "ThrottlePolicy":
        return cls(settings.thermal_soft_c, settings.thermal_hard_c, settings.thermal_resume_c)

    def _next(self, temp_c: float | None, slowing_now: bool) -> tuple[int, str]:
        if temp_c is not None and temp_c >= self.hard_c:
            return 2, f"{temp_c:.1f} C is at or above the hard limit {self.hard_c:g} C"
        if temp_c is not None and temp_c >= self.resume_c and self.level > 0:
            return self.level, f"{temp_c:.1f} C is not yet below the resume limit {self.resume_c:g} C"
        if temp_c is not None and temp_c >= self.soft_c:
            return 1, f"{temp_c:.1f} C is at or above the soft limit {self.soft_c:g} C"
        if slowing_now:
            return 1, "the firmware reports it is throttling the CPU"
        if temp_c is None:
            return 0, "no temperature reading"
        if self.level > 0:
            return 0, f"{temp_c:.1f} C is below the resume limit {self.resume_c:g} C"
        return 0, f"{temp_c:.1f} C is below the soft limit {self.soft_c:g} C"

    def update(self, temp_c: float | None, slowing_now: bool = False) -> ThrottleChange | None:
        level, reason = self._next(temp_c, bool(slowing_now))
        if level == self.level:
            return None
        change = ThrottleChange(level, self.level, reason, temp_c)
        self.level = level
        return change

    def update_from_sample(self, sample: dict[str, Any]) -> ThrottleChange | None:
        flags = sample.get("throttled") or {}
        return self.update(sample.get("temp_c"), bool(flags.get("throttled") or flags.get("soft_temp_limit")))


__all__ = ["LEVELS", "SystemMonitor", "ThrottleChange", "ThrottlePolicy"]
