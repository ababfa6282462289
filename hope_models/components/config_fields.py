"""A component's config dataclass filled from a request: its defaults, the dims the data fixes and
the request's overrides, each override checked against its field's type and range, the result
validated by the dataclass itself. Every error is a ValueError naming model_config.<key>."""
from __future__ import annotations

import dataclasses
import math
from typing import TYPE_CHECKING, Any

from hope_models.numbers import short

if TYPE_CHECKING:
    from hope_models.data.windows import WindowSpec

# Far beyond any model that fits a Pi; it keeps the estimate's arithmetic in floats.
MAX_INT = 2**31 - 1
MAX_TUPLE = 64


def refuse_unknown(component: str, keys: set, names: set[str]) -> None:
    unknown = sorted(str(k) for k in keys - names)
    if unknown:
        raise ValueError(f"model_config for {component}: unknown key(s) {short(unknown)}; valid keys: "
                         f"{sorted(names) + ['window']}")


def make_config(cls, derived: dict[str, Any], overrides: dict[str, Any], component: str):
    """cls(**defaults | derived | overrides), validated; overriding a derived dim with another value is refused."""
    names = {f.name: f for f in dataclasses.fields(cls)}
    refuse_unknown(component, set(overrides), set(names))
    values = dict(derived)
    for key, value in overrides.items():
        default = names[key].default
        if isinstance(default, tuple):
            if not isinstance(value, (list, tuple)) or len(value) > MAX_TUPLE:
                raise ValueError(f"model_config.{key}={short(value)} must be a list of at most {MAX_TUPLE} values")
            if any(isinstance(v, bool) or not isinstance(v, int) or abs(v) > MAX_INT for v in value):
                raise ValueError(f"model_config.{key}={short(value)} must be a list of integers")
            value = tuple(value)
        elif isinstance(default, bool) or isinstance(value, bool):
            raise ValueError(f"model_config.{key}={short(value)} has the wrong type")
        elif isinstance(default, int) and not isinstance(value, int):
            raise ValueError(f"model_config.{key}={short(value)} must be an integer")
        elif isinstance(default, int) and abs(value) > MAX_INT:
            raise ValueError(f"model_config.{key}={short(value)} is out of range (at most {MAX_INT})")
        elif isinstance(default, float) and not (isinstance(value, (int, float)) and math.isfinite(value)):
            raise ValueError(f"model_config.{key}={short(value)} must be a finite number")
        elif isinstance(default, str) and not isinstance(value, str):
            raise ValueError(f"model_config.{key}={short(value)} must be a string")
        if key in derived and value != derived[key]:
            raise ValueError(f"model_config.{key}={short(value)} does not fit: the {component} for this data needs "
                             f"{key}={derived[key]!r}")
        values[key] = float(value) if isinstance(default, float) else value
    cfg = cls(**values)
    cfg.validate()
    return cfg


def horizon_steps(spec: WindowSpec) -> tuple[int, ...]:
    steps = []
    for h in spec.horizons_s:
        s = h / spec.grid_step_s
        if abs(s - round(s)) > 1e-6 or round(s) < 1:
            raise ValueError(f"horizons_s: {h} s is not a whole number of the mid window's {spec.grid_step_s:g} s "
                             "grid steps (choose duration_s/k so that it is)")
        steps.append(int(round(s)))
    return tuple(steps)
