"""One rule for numbers at every door, and the one place that applies it.

The doors: a command-line flag, an environment variable, a query parameter, `config.toml`, the
JSON of the HTTP API, and a run's stored config that a worker reads back. The rule:

- a number field takes any finite number; never `true`/`false`, NaN or an infinity (`1e999`
  overflows to one);
- an integer field takes an integer; a float with no fraction (`2000.0`) is that integer, while
  `2000.5` is refused;
- where the medium has a number type (JSON, TOML) a number must be one: the string `"2000"` is
  refused, as for any other field that wants a number;
- where everything is text (a flag, an environment variable, a query parameter) a number is
  written as JSON writes it, without blanks (`-5`, `0.001`, `1e-3`; not `+5`, `0x10`, `1_000`,
  `nan`, ` 5`), and an integer as decimal digits only (`2000`; not `2e3` or `2000.0`).

So `--steps 2000`, `HOPE_PORT=8765` and `{"steps": 2000.0}` are accepted, and `--steps 2000.5`,
`HOPE_PORT=true`, `?limit=1e3` and `{"steps": "2000"}` are refused with a message naming the field.
"""
from __future__ import annotations

import json
import math
import re
import reprlib
import sys
from typing import Any

_repr = reprlib.Repr()
_repr.maxstring = _repr.maxother = 60  # a message shows a value, never a 4 kB string or a deep tree

# JSON's number grammar (RFC 8259), the only text accepted as a number
_JSON_NUMBER = re.compile(r"-?(?:0|[1-9][0-9]*)(?:\.[0-9]+)?(?:[eE][+-]?[0-9]+)?")
_DIGITS = re.compile(r"-?[0-9]+")


def short(value: Any) -> str:
    """repr() for a message: bounded in length and depth, whatever the value."""
    return _repr.repr(value)


class NumberError(ValueError):
    """A value a numeric field cannot take. str() is "<name>: <reason>"; `reason` alone lets a
    caller phrase the field its own way (e.g. a command-line flag), and `rule` is the bound a
    number broke ("must be >= 1"), None for a value that is no number."""

    def __init__(self, name: str, reason: str, rule: str | None = None):
        super().__init__(f"{name}: {reason}")
        self.name, self.reason, self.rule = name, reason, rule


def _bound(name: str, value: Any, rule: str) -> NumberError:
    return NumberError(name, f"{short(value)} {rule}", rule)


def from_text(name: str, text: str) -> int | float:
    """The number a flag, an environment variable or a query parameter spells (an int when
    written as one)."""
    if not isinstance(text, str) or not _JSON_NUMBER.fullmatch(text):
        raise NumberError(name, f"expected a number, got {short(text)}")
    if _DIGITS.fullmatch(text):
        if len(text) > 400:  # int() of a huge digit string is slow and no field takes it
            raise NumberError(name, f"{short(text)} is out of range")
        return int(text)
    return float(text)


def int_from_text(name: str, text: str, *, minimum: int | None = None, maximum: int | None = None) -> int:
    """An integer field written as text: decimal digits (an optional minus), then as_int's bounds."""
    if not isinstance(text, str) or not _DIGITS.fullmatch(text):
        raise NumberError(name, f"expected an integer, got {short(text)}")
    return as_int(name, from_text(name, text), minimum=minimum, maximum=maximum)


def float_from_text(name: str, text: str, **bounds: float | None) -> float:
    """A number field written as text, then as_float's bounds."""
    return as_float(name, from_text(name, text), **bounds)


def _finite(name: str, value: Any, what: str) -> float:
    if isinstance(value, bool) or not isinstance(value, (int, float)):
        raise NumberError(name, f"expected {what}, got {short(value)}")
    try:
        v = float(value)
    except OverflowError:  # an integer with hundreds of digits
        v = math.inf
    if not math.isfinite(v):
        raise NumberError(name, f"{short(value)} is not a finite number")
    return v


def as_int(name: str, value: Any, *, minimum: int | None = None, maximum: int | None = None) -> int:
    """`value` as an integer field, within [minimum, maximum]."""
    if isinstance(value, float) and math.isfinite(value) and value.is_integer():
        value = int(value)
    if isinstance(value, bool) or not isinstance(value, int):
        raise NumberError(name, f"expected an integer, got {short(value)}")
    if minimum is not None and value < minimum:
        raise _bound(name, value, f"must be >= {minimum}")
    if maximum is not None and value > maximum:
        raise _bound(name, value, f"must be <= {maximum}")
    return value


def as_float(name: str, value: Any, *, minimum: float | None = None, maximum: float | None = None,
             above: float | None = None, below: float | None = None) -> float:
    """`value` as a number field: finite, >= minimum, <= maximum, > above, < below (each optional)."""
    v = _finite(name, value, "a number")
    if minimum is not None and v < minimum:
        raise _bound(name, v, f"must be >= {minimum:g}")
    if above is not None and v <= above:
        raise _bound(name, v, f"must be > {above:g}")
    if maximum is not None and v > maximum:
        raise _bound(name, v, f"must be <= {maximum:g}")
    if below is not None and v >= below:
        raise _bound(name, v, f"must be < {below:g}")
    return v


class _Huge:
    """Where an integer too long to convert stood, in a second parse of the text."""


def _path_of(obj: Any, marker: Any) -> str | None:
    stack: list[tuple[Any, str]] = [(obj, "")]
    while stack:  # no recursion: the text may nest as deep as the parser allows
        value, path = stack.pop()
        if value is marker:
            return path or "the value"
        if isinstance(value, dict):
            stack.extend((v, f"{path}.{k}" if path else str(k)) for k, v in reversed(list(value.items())))
        elif isinstance(value, list):
            stack.extend((v, f"{path}[{i}]") for i, v in reversed(list(enumerate(value))))
    return None


def huge_integer_error(text: str | bytes) -> str | None:
    """Why a JSON text json.loads refused with a plain ValueError (not a JSONDecodeError): an
    integer of more digits than Python converts (sys.get_int_max_str_digits(), 4300 by default;
    no field takes one), as "<field path>: an integer of N digits ...", or None when that is not
    it. Parses the text a second time, so call it only after json.loads failed."""
    limit = sys.get_int_max_str_digits()
    found: list[int] = []
    marker = _Huge()

    def parse_int(digits: str) -> Any:
        if limit and len(digits.lstrip("-")) > limit:
            found.append(len(digits.lstrip("-")))
            return marker
        return 0

    try:
        obj = json.loads(text, parse_int=parse_int, parse_float=lambda _: 0.0, parse_constant=lambda _: 0.0)
    except (ValueError, RecursionError):
        return None
    if not found:
        return None
    where = _path_of(obj, marker) or "a value"
    where = short(where)[1:-1] if len(where) > 60 else where
    return f"{where}: an integer of {found[0]} digits; no number here may have more than {limit}"


__all__ = ["NumberError", "as_float", "as_int", "float_from_text", "from_text", "huge_integer_error",
           "int_from_text", "short"]
