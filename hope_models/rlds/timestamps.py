"""Pick one clock per episode and turn it into integer nanoseconds on every step.

Producers disagree on which clock they write and in what unit (see FORMAT.md "Time"), and one
sample stores Unix seconds in a field named `wall_time_millis`. So the unit is read from the
data and the field name is only the first guess:

* Candidate clocks, in this order: step `timestamp_ns`, `timestamp_us`, `timestamp_ms`,
  `timestamp_micros`, `observation.robot_state.timestamp_nanos`,
  `observation.robot_state.wall_time_millis`, `step_metadata.timestamp` (seconds, often a
  string), step `timestamp` (no unit in the name). The first one that holds a number on every
  step and is not constant wins (a single-step episode needs no change); when every complete
  clock is constant, the first complete one is used with a warning.
* Epoch magnitude: a first value between 2000-01-01 and 2100-01-01 in some unit (ns ~1e18,
  us ~1e15, ms ~1e12, s ~1e9; the four ranges do not overlap) says the unit. Wall clocks
  (`wall_time_millis`, `step_metadata.timestamp`) are taken at their epoch word; for other
  clocks the name wins when its unit gives a plausible step period and the epoch reading does
  not (a monotonic nanosecond counter can look like epoch milliseconds).
* Relative clocks: the median step period must be plausible (1 ms .. 10 s). The name's unit
  is kept when it is; otherwise the plausible unit nearest to 100 ms is taken.
* Whenever the data says another unit than the name, the episode gets a warning such as
  "field named millis holds seconds". Values are kept epoch or relative as the producer wrote
  them; backwards steps and gaps are validation's to report.
Conversion is exact: integers are scaled as integers, floats and numeric strings through
Decimal of their shortest text, so epoch nanoseconds (> 2^53) survive.
"""
from __future__ import annotations

import math
from dataclasses import dataclass
from decimal import ROUND_HALF_EVEN, Decimal, InvalidOperation
from itertools import pairwise
from typing import Any, Callable

from .episode import Episode, Step

NS_PER = {"ns": 1, "us": 1_000, "ms": 1_000_000, "s": 1_000_000_000}
UNIT_WORD = {"ns": "nanoseconds", "us": "microseconds", "ms": "milliseconds", "s": "seconds"}
NAME_WORD = {"ns": "nanos", "us": "micros", "ms": "millis", "s": "seconds"}  # how field names say it
EPOCH_MIN_S = 946_684_800  # 2000-01-01
EPOCH_MAX_S = 4_102_444_800  # 2100-01-01
PERIOD_MIN_S = 1e-3
PERIOD_MAX_S = 10.0
TYPICAL_PERIOD_S = 0.1


@dataclass(frozen=True)
class Clock:
    path: str  # dotted field path, as reported in problems
    unit: str | None  # the unit the name says; None when the name says nothing
    wall: bool  # a wall clock: expected to hold an epoch time
    get: Callable[[Step], Any]


def _obs_robot(step: Step, key: str) -> Any:
    rs = step.observation.get("robot_state")
    return rs.get(key) if type(rs) is dict else None


def _meta(step: Step, key: str) -> Any:
    return step.step_metadata.get(key)


CLOCKS: tuple[Clock, ...] = (
    Clock("timestamp_ns", "ns", False, lambda s: s.extras.get("timestamp_ns")),
    Clock("timestamp_us", "us", False, lambda s: s.extras.get("timestamp_us")),
    Clock("timestamp_ms", "ms", False, lambda s: s.extras.get("timestamp_ms")),
    Clock("timestamp_micros", "us", False, lambda s: s.extras.get("timestamp_micros")),
    Clock("observation.robot_state.timestamp_nanos", "ns", False, lambda s: _obs_robot(s, "timestamp_nanos")),
    Clock("observation.robot_state.wall_time_millis", "ms", True, lambda s: _obs_robot(s, "wall_time_millis")),
    Clock("step_metadata.timestamp", "s", True, lambda s: _meta(s, "timestamp")),
    Clock("timestamp", None, False, lambda s: s.extras.get("timestamp")),
)


def _number(value: Any) -> int | Decimal | None:
    """An exact number from a JSON value, or None when it is not a finite number."""
    t = type(value)
    if t is int:
        return value
    if t is float:
        return Decimal(repr(value)) if math.isfinite(value) else None
    if t is str:
        try:
            d = Decimal(value.strip())
        except InvalidOperation:
            return None
        return d if d.is_finite() else None
    return None


def _to_ns(value: int | Decimal, unit: str) -> int:
    scaled = value * NS_PER[unit]
    if type(scaled) is int:
        return scaled
    return int(scaled.to_integral_value(rounding=ROUND_HALF_EVEN))


def _epoch_unit(first: float) -> str | None:
    for unit, per in NS_PER.items():
        seconds = first * per / 1e9
        if EPOCH_MIN_S <= seconds <= EPOCH_MAX_S:
            return unit
    return None


def _median_period(values: list[int | Decimal]) -> float | None:
    """Median of the positive differences between consecutive values, in the values' unit."""
    diffs = sorted(float(b - a) for a, b in pairwise(values) if b != a)
    if not diffs:
        return None
    return diffs[len(diffs) // 2]


def _plausible(period: float | None, unit: str) -> bool:
    if period is None:
        return False
    seconds = abs(period) * NS_PER[unit] / 1e9
    return PERIOD_MIN_S <= seconds <= PERIOD_MAX_S


def detect_unit(clock: Clock, values: list[int | Decimal]) -> tuple[str, str | None]:
    """(unit, warning or None) for one clock's values."""
    named = clock.unit
    first = float(values[0])
    epoch = _epoch_unit(first)
    period = _median_period(values)

    def mismatch(unit: str, why: str) -> tuple[str, str]:
        if named is None:
            return unit, None
        return unit, f"field named {NAME_WORD[named]} holds {UNIT_WORD[unit]} ({why}); read as {UNIT_WORD[unit]}"

    if epoch is not None:
        if epoch == named:
            return named, None
        if named is None or clock.wall:
            return mismatch(epoch, f"value {values[0]} is an epoch time in {UNIT_WORD[epoch]}")
        if _plausible(period, named) and not _plausible(period, epoch):
            return named, None  # a counter since boot, not an epoch
        return mismatch(epoch, f"value {values[0]} is an epoch time in {UNIT_WORD[epoch]}")

    if period is None:
        if named is not None:
            return named, None
        return "s", "unit cannot be told from one value; assumed seconds"
    if named is not None and _plausible(period, named):
        return named, None
    candidates = [u for u in NS_PER if _plausible(period, u)]
    if candidates:
        best = min(candidates, key=lambda u: abs(math.log(abs(period) * NS_PER[u] / 1e9 / TYPICAL_PERIOD_S)))
        if named is None:
            return best, None
        return mismatch(best, f"median step period {period:g} is plausible only as {UNIT_WORD[best]}")
    if named is not None:
        return named, (f"median step period {period:g} {named} is implausible "
                       f"(outside {PERIOD_MIN_S * 1000:g} ms .. {PERIOD_MAX_S:g} s) in every unit; kept {named}")
    return "s", (f"median step period {period:g} is implausible in every unit; "
                 f"assumed seconds")


def _collect(clock: Clock, steps: list[Step]) -> tuple[list[int | Decimal], int]:
    """Values of `clock` on the steps that hold a finite number, and how many do."""
    values = []
    get = clock.get
    for s in steps:
        v = _number(get(s))
        if v is not None:
            values.append(v)
    return values, len(values)


def assign_timestamps(ep: Episode, *, canonical: bool = False) -> str | None:
    """Fill Step.timestamp_ns for every step of `ep`; returns the chosen clock's path.

    Every clock present is unit-checked, including the ones not chosen: that is how a seconds
    value in a millis field is found while another clock drives the episode.
    `canonical` is for our own files (canonical dirs, MCAP): their `timestamp_ns` is by
    definition integer nanoseconds and is taken as written, without detection."""
    steps = ep.steps
    if not steps:
        return None
    n = len(steps)

    if canonical:
        missing = 0
        for s in steps:
            v = s.extras.pop("timestamp_ns", None)
            if type(v) is int:
                s.timestamp_ns = v
            else:
                s.timestamp_ns = None
                missing += 1
        if missing == n:
            ep.warn("no step has timestamp_ns; timestamp_ns left empty")
            return None
        if missing:
            ep.warn(f"timestamp_ns is missing or not an integer on {missing} of {n} steps")
        return CLOCKS[0].path

    chosen: tuple[Clock, list] | None = None
    constant_fallback: tuple[Clock, list] | None = None
    partial: list[str] = []
    checked: set[str] = set()

    def check_unit(clock: Clock, values: list) -> None:
        if clock.path in checked:
            return
        checked.add(clock.path)
        _, note = detect_unit(clock, values)
        if note:
            ep.warn(note, field=clock.path)

    for clock in CLOCKS:
        values, count = _collect(clock, steps)
        if count == 0:
            continue
        if count < n:
            partial.append(f"{clock.path} ({count} of {n} steps)")
            if count >= 2:
                check_unit(clock, values)
            continue
        constant = n > 1 and all(v == values[0] for v in values)
        if constant:
            if constant_fallback is None:
                constant_fallback = (clock, values)
        elif chosen is None:
            chosen = (clock, values)
        check_unit(clock, values)

    if chosen is None and constant_fallback is not None:
        chosen = constant_fallback
        ep.warn(f"every clock is constant over the episode; {chosen[0].path} used, all steps get the same "
                f"time", field=chosen[0].path)
    if chosen is None:
        looked = ", ".join(c.path for c in CLOCKS)
        extra = f"; present on some steps only: {', '.join(partial)}" if partial else ""
        ep.warn(f"no clock on every step (looked for {looked}){extra}; timestamp_ns left empty")
        for s in steps:
            s.timestamp_ns = None
            s.extras.pop("timestamp_ns", None)
        return None

    clock, values = chosen
    unit, note = detect_unit(clock, values)
    for s, v in zip(steps, values, strict=True):
        s.timestamp_ns = _to_ns(v, unit)
        s.extras.pop("timestamp_ns", None)
    return clock.path
