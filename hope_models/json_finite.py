"""JSON has no NaN or Infinity (browsers and strict parsers refuse them): a diverged loss or a
refused candidate's metrics travel and are stored with non-finite floats as null. One rule for the
registry, the remote-worker reports and the promotion records (train/metrics.py has the wider
version that also turns numpy/torch scalars into numbers)."""
from __future__ import annotations

import math
from typing import Any


def finite(value: Any) -> Any:
    """`value` with every non-finite float inside dicts, lists and tuples replaced by None."""
    if isinstance(value, float):
        return value if math.isfinite(value) else None
    if isinstance(value, dict):
        return {str(k): finite(v) for k, v in value.items()}
    if isinstance(value, (list, tuple)):
        return [finite(v) for v in value]
    return value
