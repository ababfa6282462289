"""What the components' held-out figures share: the gate's statuses and reading a finite number
out of a metrics dict (absent, NaN or not a number: None)."""
from __future__ import annotations

import math
from typing import Any

PASSED, FAILED = "passed", "failed"


def num(metrics: dict[str, Any], key: str) -> float | None:
    v = metrics.get(key)
    return float(v) if isinstance(v, (int, float)) and not isinstance(v, bool) and math.isfinite(v) else None


def fmt(value: Any, spec: str, missing: str = "-") -> str:
    """A figure for a report line: formatted, or `missing` when it was not measured."""
    if isinstance(value, bool) or not isinstance(value, (int, float)) or not math.isfinite(value):
        return missing
    return format(value, spec)
