"""Reading and checking request input, so every view refuses bad input the same way.

A JSON body must say `Content-Type: application/json` (else 415), fit MAX_CONTENT_LENGTH (else
413, enforced before anything reads it: webapp/errors.py), be UTF-8 JSON (else 400) and, for
these endpoints, an object. The JSON constants NaN / Infinity are refused while parsing; a number
that overflows (1e999 parses to inf) is refused by the field checks, which want finite numbers.
Every error is an ApiError whose message names the field.
"""
from __future__ import annotations

import json
import math
from typing import Any, Iterable

from flask import current_app, request

from webapp.errors import ApiError

MAX_STR = 4096  # no text field of the API needs more


def _no_constants(name: str):
    raise ValueError(f"{name} is not valid JSON (JSON has no NaN or Infinity)")


def json_body(*, allowed: Iterable[str] | None = None, required: Iterable[str] = ()) -> dict[str, Any]:
    """The request's JSON object; unknown keys (when `allowed` is given) and missing required ones
    are refused with the field named."""
    mimetype = request.mimetype or ""
    if mimetype != "application/json" and not mimetype.endswith("+json"):
        shown = request.content_type or "none"
        raise ApiError(f"the request body must be JSON: send Content-Type: application/json (got {shown})", 415)
    raw = request.get_data(cache=True)  # 413 past MAX_CONTENT_LENGTH when there is a Content-Length
    limit = current_app.config.get("MAX_CONTENT_LENGTH")
    if limit is not None and request.content_length is None and len(raw) >= limit:
        # a chunked body is read up to the limit only (werkzeug's LimitedStream): it did not fit
        raise ApiError(f"request body too large: at least {len(raw)} bytes; the limit is {limit} bytes", 413)
    if not raw.strip():
        raise ApiError("the request body is empty: send a JSON object", 400)
    try:
        body = json.loads(raw.decode("utf-8"), parse_constant=_no_constants)
    except UnicodeDecodeError as exc:
        raise ApiError(f"the request body is not UTF-8 text: {exc.reason} at byte {exc.start}", 400) from None
    except json.JSONDecodeError as exc:
        raise ApiError(f"the request body is not valid JSON: {exc.msg} (line {exc.lineno}, column {exc.colno})",
                       400) from None
    except ValueError as exc:  # NaN / Infinity
        raise ApiError(f"the request body is not valid JSON: {exc}", 400) from None
    except RecursionError:
        raise ApiError("the request body is not valid JSON: nested too deeply", 400) from None
    if not isinstance(body, dict):
        raise ApiError(f"the request body must be a JSON object, got {_kind(body)}", 400)
    if allowed is not None:
        known = set(allowed)
        unknown = sorted(str(k) for k in body if k not in known)
        if unknown:
            raise ApiError(f"unknown field(s) {', '.join(unknown)} (known: {', '.join(sorted(known))})", 400)
    for name in required:
        if name not in body or body[name] is None:
            raise ApiError(f"{name}: required", 400)
    return body


def _kind(value: Any) -> str:
    if value is None:
        return "null"
    if isinstance(value, bool):
        return "a boolean"
    if isinstance(value, (int, float)):
        return "a number"
    if isinstance(value, str):
        return "a string"
    if isinstance(value, list):
        return "a list"
    if isinstance(value, dict):
        return "an object"
    return type(value).__name__


def _short(value: Any) -> str:
    text = json.dumps(value) if not isinstance(value, float) or math.isfinite(value) else repr(value)
    return text if len(text) <= 60 else text[:57] + "..."


def get_int(body: dict, name: str, *, default: int | None = None, minimum: int | None = None,
            maximum: int | None = None) -> int | None:
    """An integer field (JSON number without a fraction; booleans and strings are refused)."""
    value = body.get(name)
    if value is None:
        return default
    if isinstance(value, float) and math.isfinite(value) and value.is_integer():
        value = int(value)
    if isinstance(value, bool) or not isinstance(value, int):
        raise ApiError(f"{name}: expected an integer, got {_kind(value)} {_short(value)}", 400)
    if minimum is not None and value < minimum:
        raise ApiError(f"{name}: {value} must be >= {minimum}", 400)
    if maximum is not None and value > maximum:
        raise ApiError(f"{name}: {value} must be <= {maximum}", 400)
    return value


def get_bool(body: dict, name: str, *, default: bool = False) -> bool:
    value = body.get(name)
    if value is None:
        return default
    if not isinstance(value, bool):
        raise ApiError(f"{name}: expected true or false, got {_kind(value)} {_short(value)}", 400)
    return value


def get_str(body: dict, name: str, *, default: str | None = None, max_len: int = MAX_STR,
            choices: Iterable[str] | None = None) -> str | None:
    value = body.get(name)
    if value is None:
        return default
    if not isinstance(value, str):
        raise ApiError(f"{name}: expected a string, got {_kind(value)} {_short(value)}", 400)
    if not value.strip():
        raise ApiError(f"{name}: must not be empty", 400)
    if len(value) > max_len:
        raise ApiError(f"{name}: longer than {max_len} characters", 400)
    if choices is not None:
        options = list(choices)
        if value not in options:
            raise ApiError(f"{name}: {_short(value)} is not one of {', '.join(options)}", 400)
    return value


def get_numbers(body: dict, name: str, *, max_len: int, min_len: int = 1) -> list[float]:
    """A list of finite numbers (NaN, inf, 1e999, booleans, strings and nested lists are refused)."""
    value = body.get(name)
    if not isinstance(value, list):
        raise ApiError(f"{name}: expected a list of numbers, got {_kind(value)}", 400)
    if not min_len <= len(value) <= max_len:
        raise ApiError(f"{name}: has {len(value)} values; expected {min_len} to {max_len}", 400)
    out = []
    for i, v in enumerate(value):
        if isinstance(v, bool) or not isinstance(v, (int, float)):
            raise ApiError(f"{name}[{i}]: expected a number, got {_kind(v)} {_short(v)}", 400)
        f = float(v)
        if not math.isfinite(f):
            raise ApiError(f"{name}[{i}]: {v!r} is not a finite number (NaN and overflowing values such as "
                           "1e999 are refused)", 400)
        out.append(f)
    return out


def query_int(name: str, *, default: int | None, minimum: int, maximum: int | None = None) -> int | None:
    """An integer query-string parameter (?name=...)."""
    text = request.args.get(name)
    if text is None or text == "":
        return default
    try:
        value = int(text)
    except ValueError:
        raise ApiError(f"{name}: {text[:40]!r} is not an integer", 400) from None
    if value < minimum or (maximum is not None and value > maximum):
        bound = f"between {minimum} and {maximum}" if maximum is not None else f">= {minimum}"
        raise ApiError(f"{name}: {value} must be {bound}", 400)
    return value


__all__ = ["get_bool", "get_int", "get_numbers", "get_str", "json_body", "query_int"]
