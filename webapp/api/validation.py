"""Reading and checking request input, so every view refuses bad input the same way.

A JSON body must say `Content-Type: application/json` (else 415), fit MAX_CONTENT_LENGTH (else
413, enforced before anything reads it: webapp/errors.py), be UTF-8 JSON (else 400) and, for
these endpoints, an object nested at most MAX_DEPTH levels (no endpoint needs more; deeper input
would reach code that recurses). The JSON constants NaN / Infinity are refused while parsing; a
number that overflows (1e999 parses to inf) is refused by the field checks, which want finite
numbers; an integer of more digits than Python converts (4300) is refused naming its field. An
endpoint that takes no input accepts an empty body or {} and refuses anything else
(no_body), and a GET refuses query parameters it does not know (query_args). Every error is an
ApiError whose message names the field.
"""
from __future__ import annotations

import json
import math
import re
from typing import Any, Iterable, overload

from flask import current_app, request

from hope_models.numbers import NumberError, huge_integer_error, int_from_text
from registry.run_request import RunRequestError, check_int, listed
from webapp.errors import ApiError

MAX_STR = 4096  # no text field of the API needs more
MAX_DEPTH = 20  # the deepest body the API reads is 4 levels (sequential -> model_config -> window -> horizons_s)


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
    deep = _nesting_beyond_limit(raw)
    if deep is not None:
        raise ApiError(f"the request body is not valid JSON for this API: {deep} is nested more than {MAX_DEPTH} "
                       "levels deep", 400)
    try:
        body = json.loads(raw.decode("utf-8"), parse_constant=_no_constants)
    except UnicodeDecodeError as exc:
        raise ApiError(f"the request body is not UTF-8 text: {exc.reason} at byte {exc.start}", 400) from None
    except json.JSONDecodeError as exc:
        raise ApiError(f"the request body is not valid JSON: {exc.msg} (line {exc.lineno}, column {exc.colno})",
                       400) from None
    except ValueError as exc:  # NaN / Infinity, or an integer too long for int()
        huge = huge_integer_error(raw)
        raise ApiError(f"the request body is not usable JSON: {huge}" if huge else
                       f"the request body is not valid JSON: {exc}", 400) from None
    except RecursionError:  # cannot happen below MAX_DEPTH; kept as the parser's own guard
        raise ApiError("the request body is not valid JSON: nested too deeply", 400) from None
    if not isinstance(body, dict):
        raise ApiError(f"the request body must be a JSON object, got {_kind(body)}", 400)
    if allowed is not None:
        known = set(allowed)
        unknown = sorted(str(k) for k in body if k not in known)
        if unknown:
            raise ApiError(f"unknown field(s) {listed(unknown)} (known: {', '.join(sorted(known)) or 'none'})", 400)
    for name in required:
        if name not in body or body[name] is None:
            raise ApiError(f"{name}: required", 400)
    return body


_TOKENS = re.compile(rb'"(?:[^"\\]|\\.)*"\s*(:?)|[\[\]{}]')


def _nesting_beyond_limit(raw: bytes) -> str | None:
    """Where the body nests deeper than MAX_DEPTH: the top-level field it happens in (or "it"),
    else None. Read off the bytes before parsing, without recursion: a parser or a check that
    recursed would fail at a depth that depends on the stack it runs on (a RecursionError in one
    place, a parsed body that recursion fails on later in another)."""
    depth = 0
    field = None
    for m in _TOKENS.finditer(raw):
        token = m.group(0)
        if token[:1] == b'"':
            if depth == 1 and m.group(1):
                field = token[:token.rindex(b":")].rstrip()
        elif token in b"[{":
            depth += 1
            if depth > MAX_DEPTH:
                try:
                    return "it" if field is None else str(json.loads(field))
                except ValueError:
                    return "it"
        else:
            depth -= 1
    return None


def no_body() -> None:
    """For an endpoint that takes no input: an empty body (any content type) or {}. Fields are
    refused, not ignored: a client that sends them expects them to mean something."""
    if request.get_data(cache=True).strip():
        json_body(allowed=())


def query_args(*allowed: str) -> None:
    """Refuse query parameters the endpoint does not read (a typo would otherwise be ignored)."""
    unknown = sorted(k for k in request.args if k not in allowed)
    if unknown:
        raise ApiError(f"unknown query parameter(s) {listed(unknown)} (known: {', '.join(allowed) or 'none'})", 400)


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
    """An integer field, by the rule run requests follow (registry.run_request.check_int: a JSON
    number without a fraction; booleans and strings are refused)."""
    value = body.get(name)
    if value is None:
        return default
    try:
        return check_int(name, value, minimum=minimum, maximum=maximum)
    except RunRequestError as exc:
        raise ApiError(str(exc), 400) from None


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
    try:
        value.encode("utf-8")
    except UnicodeEncodeError:  # JSON's "\ud800" escape: no file name, database or log can take it
        raise ApiError(f"{name}: not valid Unicode text (a lone surrogate)", 400) from None
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




@overload
def query_int(name: str, *, default: int, minimum: int, maximum: int | None = None) -> int: ...
@overload
def query_int(name: str, *, default: None, minimum: int, maximum: int | None = None) -> int | None: ...


def query_int(name: str, *, default: int | None, minimum: int, maximum: int | None = None) -> int | None:
    """An integer query-string parameter (?name=...)."""
    text = request.args.get(name)
    if text is None or text == "":
        return default
    try:  # query text is read as a JSON number, the one rule for text (hope_models/numbers.py)
        return int_from_text(name, text, minimum=minimum, maximum=maximum)
    except NumberError as exc:
        raise ApiError(str(exc), 400) from None


__all__ = ["MAX_DEPTH", "get_bool", "get_int", "get_numbers", "get_str", "json_body", "no_body", "query_args",
           "query_int"]
