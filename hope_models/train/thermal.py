"""The thermal governor: slow down when the SoC runs warm, stop and wait when it runs hot.

Sources: a thermal-zone file (the kernel writes millidegrees C, e.g. "48312\\n"; a number below
1000 is taken as degrees already) and, when the command exists, `vcgencmd get_throttled`
("throttled=0x50005": the Pi firmware's under-voltage and throttling flags). Neither source is
required: a machine without them trains at the normal level, and the missing source is logged once.

Levels, checked by the loop before every step (before_step):
  normal  temperature below soft_c (75 C).
  slow    above soft_c: sleep fraction x the measured last step time, the fraction growing linearly
          from 0 at soft_c to max_slow_fraction (0.5) at hard_c. The firmware reporting active
          throttling or its soft temperature limit also means at least `slow`.
  hot     at or above hard_c (82 C): the loop calls wait_until_cool, which checkpoints (through the
          loop's callback), then polls every poll_s until the temperature is below resume_c (70 C)
          or the control hook asks for cancel/pause. Between resume_c and hard_c a hot governor
          stays hot: that gap (hysteresis) stops it bouncing in and out of the pause.
Every level change and the start and end of a wait go to emit("throttle", payload).

The zone file is read at most every sample_interval_s (reading it costs microseconds, but
vcgencmd is a subprocess), so the per-step cost is a clock read. No torch here.
"""
from __future__ import annotations

import logging
import os
import shutil
import subprocess
import time
from dataclasses import asdict, dataclass
from typing import Any, Callable

log = logging.getLogger(__name__)

LEVELS = ("normal", "slow", "hot")


@dataclass(frozen=True)
class ThrottledFlags:
    """The bits of `vcgencmd get_throttled` (Raspberry Pi firmware)."""
    raw: int
    under_voltage: bool  # bit 0, now
    arm_freq_capped: bool  # bit 1, now
    throttled: bool  # bit 2, now
    soft_temp_limit: bool  # bit 3, now
    under_voltage_occurred: bool  # bit 16, since boot
    arm_freq_capped_occurred: bool  # bit 17
    throttled_occurred: bool  # bit 18
    soft_temp_limit_occurred: bool  # bit 19

    @property
    def slowing_now(self) -> bool:
        """The firmware is slowing the CPU right now (throttled or at its soft temperature limit)."""
        return self.throttled or self.soft_temp_limit

    def to_json_obj(self) -> dict[str, Any]:
        out = asdict(self)
        out["raw"] = hex(self.raw)
        return out


def parse_throttled(text: str) -> ThrottledFlags:
    """Parse `vcgencmd get_throttled` output ("throttled=0x50005"); ValueError if it is not that."""
    line = text.strip()
    key, sep, value = line.partition("=")
    if sep != "=" or key.strip() != "throttled":
        raise ValueError(f"vcgencmd get_throttled printed {line!r}, expected 'throttled=0x...'")
    try:
        raw = int(value.strip(), 0)
    except ValueError:
        raise ValueError(f"vcgencmd get_throttled printed {line!r}: {value.strip()!r} is not a number") from None
    bit = lambda n: bool(raw >> n & 1)  # noqa: E731
    return ThrottledFlags(raw, bit(0), bit(1), bit(2), bit(3), bit(16), bit(17), bit(18), bit(19))


def parse_temperature(text: str) -> float:
    """Degrees C from a thermal-zone file: millidegrees as the kernel writes them, or degrees
    if the number is below 1000 (some boards and the test fixtures write degrees)."""
    value = float(text.strip())
    if value != value or value in (float("inf"), float("-inf")):
        raise ValueError(f"{text.strip()!r} is not a finite temperature")
    return value / 1000.0 if abs(value) >= 1000 else value


@dataclass(frozen=True)
class ThermalReading:
    temp_c: float | None  # None: no readable thermal zone
    throttled_flags: ThrottledFlags | None  # None: no vcgencmd (or it failed)
    source: str  # "thermal_zone", "vcgencmd", "thermal_zone+vcgencmd" or "none"


@dataclass(frozen=True)
class ThermalAction:
    level: str  # "normal" | "slow" | "hot"
    sleep_s: float  # to sleep before the next step (slow only)
    fraction: float = 0.0  # sleep_s / last step time
    temp_c: float | None = None


def _read_text(path: str) -> str:
    with open(path, encoding="ascii", errors="replace") as f:
        return f.read(64)


class ThermalGovernor:
    def __init__(self, zone_path: str | os.PathLike | None, vcgencmd: str | None = "vcgencmd",
                 soft_c: float = 75.0, hard_c: float = 82.0, resume_c: float = 70.0, *,
                 read_fn: Callable[[str], str] | None = None,
                 sleep_fn: Callable[[float], None] = time.sleep,
                 clock: Callable[[], float] = time.monotonic,
                 emit: Callable[[str, dict], None] | None = None,
                 max_slow_fraction: float = 0.5, firmware_slow_fraction: float = 0.25,
                 slow_hysteresis_c: float = 1.0, poll_s: float = 5.0,
                 sample_interval_s: float = 1.0, vcgencmd_timeout_s: float = 2.0):
        soft_c, hard_c, resume_c = float(soft_c), float(hard_c), float(resume_c)
        if not soft_c < hard_c:
            raise ValueError(f"thermal limits: soft_c ({soft_c:g}) must be below hard_c ({hard_c:g})")
        if not resume_c <= soft_c:
            raise ValueError(f"thermal limits: resume_c ({resume_c:g}) must not be above soft_c ({soft_c:g}), "
                             "or a cooled-down job would resume straight into the slow level")
        if not 0 <= max_slow_fraction <= 10:
            raise ValueError(f"max_slow_fraction = {max_slow_fraction!r} must be within 0-10")
        if not poll_s > 0:
            raise ValueError(f"poll_s = {poll_s!r} must be a positive number of seconds")
        self.zone_path = str(zone_path) if zone_path else None
        self.vcgencmd = vcgencmd or None
        self.soft_c, self.hard_c, self.resume_c = soft_c, hard_c, resume_c
        self.max_slow_fraction = float(max_slow_fraction)
        self.firmware_slow_fraction = float(firmware_slow_fraction)
        self.slow_hysteresis_c = float(slow_hysteresis_c)
        self.poll_s = float(poll_s)
        self.sample_interval_s = float(sample_interval_s)
        self.vcgencmd_timeout_s = float(vcgencmd_timeout_s)
        self._read = read_fn or _read_text
        self._sleep = sleep_fn
        self._clock = clock
        self._emit = emit
        self.level = "normal"
        self.last_reading: ThermalReading | None = None
        self._last_sample_at: float | None = None
        self._vcgencmd_exe: str | None | bool = False  # False: not looked up yet; None: unavailable
        self._judged: tuple[ThermalReading, str] | None = None  # (reading, level) before_step last decided on
        self._fraction = 0.0
        self._warned: set[str] = set()

    # -- sources -----------------------------------------------------------------------------

    def _warn_once(self, key: str, message: str) -> None:
        if key not in self._warned:
            self._warned.add(key)
            log.warning(message)

    def _read_zone(self) -> float | None:
        if not self.zone_path:
            return None
        try:
            temp = parse_temperature(self._read(self.zone_path))
        except (OSError, ValueError) as exc:
            # Logged once: a machine without this zone trains unguarded by temperature, and a
            # zone that comes back later is picked up again on the next read.
            self._warn_once("zone", f"thermal zone {self.zone_path} is not readable ({exc}); "
                            "training without a temperature reading from it")
            return None
        self._warned.discard("zone")
        return temp

    def _read_vcgencmd(self) -> ThrottledFlags | None:
        if self._vcgencmd_exe is False:  # looked up once: which() walks PATH
            self._vcgencmd_exe = shutil.which(self.vcgencmd) if self.vcgencmd else None
        if not self._vcgencmd_exe:
            return None
        try:
            out = subprocess.run([self._vcgencmd_exe, "get_throttled"], capture_output=True, text=True,
                                 timeout=self.vcgencmd_timeout_s, check=True).stdout
            return parse_throttled(out)
        except (OSError, subprocess.SubprocessError, ValueError) as exc:
            # A vcgencmd that fails once (no VideoCore on this machine, a hang) will keep failing:
            # stop spawning it for the rest of the job.
            self._vcgencmd_exe = None
            self._warn_once("vcgencmd", f"{self.vcgencmd} get_throttled failed ({exc}); not asking it again")
            return None

    def sample(self) -> ThermalReading:
        """Read both sources now (the loop goes through before_step, which rate-limits this)."""
        temp = self._read_zone()
        flags = self._read_vcgencmd()
        parts = [name for name, got in (("thermal_zone", temp is not None), ("vcgencmd", flags is not None)) if got]
        reading = ThermalReading(temp, flags, "+".join(parts) or "none")
        self.last_reading = reading
        self._last_sample_at = self._clock()
        return reading

    def _current(self) -> ThermalReading:
        now = self._clock()
        if self.last_reading is None or self._last_sample_at is None \
                or now - self._last_sample_at >= self.sample_interval_s:
            return self.sample()
        return self.last_reading

    # -- levels ------------------------------------------------------------------------------

    def _slow_fraction(self, temp: float | None, flags: ThrottledFlags | None) -> float:
        fraction = 0.0
        if temp is not None and temp > self.soft_c:
            span = self.hard_c - self.soft_c
            fraction = self.max_slow_fraction * min(1.0, (temp - self.soft_c) / span)
        if flags is not None and flags.slowing_now:
            fraction = max(fraction, self.firmware_slow_fraction)
        return fraction

    def _next_level(self, r: ThermalReading) -> tuple[str, str]:
        """(level, reason) for a reading, given the current level (the hysteresis lives here)."""
        t, flags = r.temp_c, r.throttled_flags
        firmware = flags is not None and flags.slowing_now
        if t is None:
            if self.level == "hot":  # no reading to wait on: nothing more to learn by waiting
                return ("slow" if firmware else "normal"), "no temperature reading"
            return ("slow", "firmware reports throttling") if firmware else ("normal", "no temperature reading")
        if t >= self.hard_c:
            return "hot", f"{t:.1f} C is at or above the hard limit {self.hard_c:g} C"
        if self.level == "hot" and t >= self.resume_c:
            return "hot", f"{t:.1f} C is not yet below the resume limit {self.resume_c:g} C"
        if t > self.soft_c or (self.level == "slow" and t > self.soft_c - self.slow_hysteresis_c):
            return "slow", f"{t:.1f} C is above the soft limit {self.soft_c:g} C"
        if firmware:
            return "slow", "firmware reports throttling"
        return "normal", f"{t:.1f} C is below the soft limit {self.soft_c:g} C"

    def _payload(self, r: ThermalReading, **extra) -> dict[str, Any]:
        payload = {"level": self.level, "temp_c": r.temp_c, "source": r.source,
                   "soft_c": self.soft_c, "hard_c": self.hard_c, "resume_c": self.resume_c}
        if r.throttled_flags is not None:
            payload["throttled"] = r.throttled_flags.to_json_obj()
        payload.update(extra)
        return payload

    def _send(self, payload: dict[str, Any]) -> None:
        log.info("thermal: %s", payload)
        if self._emit is not None:
            self._emit("throttle", payload)

    def _set_level(self, level: str, reason: str, r: ThermalReading) -> None:
        if level != self.level:
            previous, self.level = self.level, level
            self._send(self._payload(r, event="level", previous=previous, reason=reason,
                                     sleep_fraction=self._slow_fraction(r.temp_c, r.throttled_flags)
                                     if level == "slow" else 0.0))

    def before_step(self, last_step_seconds: float) -> ThermalAction:
        """What to do before the next step. The loop sleeps sleep_s itself (so that pause and
        cancel stay responsive); on "hot" it calls wait_until_cool."""
        r = self._current()
        if self._judged != (r, self.level):  # a new reading (about once a second): decide again
            level, reason = self._next_level(r)
            self._set_level(level, reason, r)
            fraction = self._slow_fraction(r.temp_c, r.throttled_flags) if level == "slow" else 0.0
            self._judged, self._fraction = (r, self.level), fraction
        if self.level != "slow":
            return ThermalAction(self.level, 0.0, 0.0, r.temp_c)
        return ThermalAction("slow", self._fraction * max(0.0, float(last_step_seconds)), self._fraction, r.temp_c)

    def wait_until_cool(self, checkpoint_fn: Callable[[], Any] | None = None,
                        poll_control_fn: Callable[[], Any] | None = None) -> str:
        """Checkpoint (checkpoint_fn, if given), then block until the temperature is below
        resume_c. Returns why it ended: "cool", "cancel" or "pause" (poll_control_fn returned a
        ControlCommand, or a string, asking for it), or "no_reading" (the sensor went away).
        Called when before_step returned "hot"."""
        if checkpoint_fn is not None:
            checkpoint_fn()
        r = self.sample()
        start = self._clock()
        self.level = "hot"
        self._send(self._payload(r, event="wait_start",
                                 reason=f"waiting for the temperature to fall below {self.resume_c:g} C"))
        while True:
            desired = _desired(poll_control_fn() if poll_control_fn is not None else None)
            if desired in ("cancel", "pause"):
                why = desired
                break
            if r.temp_c is None:
                why = "no_reading"
                break
            if r.temp_c < self.resume_c:
                why = "cool"
                break
            self._sleep(self.poll_s)
            r = self.sample()
        # Cooled down (below resume_c <= soft_c): normal, or slow if the firmware still throttles.
        # Cancel or pause end the job while it is hot; a re-run starts a new governor anyway.
        # The wait's end is also the level change out of hot (to normal, or slow if the firmware
        # still throttles); cancel and pause end the job while it is hot.
        level, reason = self._next_level(r) if why in ("cool", "no_reading") else ("hot", f"control asked to {why}")
        self.level = level
        self._send(self._payload(r, event="wait_end", previous="hot", ended_by=why, reason=reason,
                                 waited_s=round(self._clock() - start, 3)))
        return why


def _desired(command: Any) -> str:
    if command is None:
        return "run"
    if isinstance(command, str):
        return command
    return str(getattr(command, "desired", "run"))


def governor_from_settings(settings: Any, **kwargs) -> ThermalGovernor:
    """A governor with the deployment's thermal settings (hope_models.settings.Settings)."""
    return ThermalGovernor(settings.thermal_zone_path, settings.vcgencmd_path, settings.thermal_soft_c,
                           settings.thermal_hard_c, settings.thermal_resume_c, **kwargs)


__all__ = ["LEVELS", "ThermalAction", "ThermalGovernor", "ThermalReading", "ThrottledFlags",
           "governor_from_settings", "parse_temperature", "parse_throttled"]
