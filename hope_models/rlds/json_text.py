r"""Reading JSON and JSONL text the way Continuon producers actually write it.

Producers write UTF-8 with or without a BOM, CRLF or LF line ends, blank lines between steps,
bare `NaN`/`Infinity` tokens (Python's json module emits them) and epoch-nanosecond integers
above 2^53. Python's json parser already maps the bare tokens to float nan/inf and keeps
integers exact, so the work here is decoding, line splitting, size guards and turning every
failure into a Problem that names the file and line instead of raising.

Writing goes through `json_dumps` too: Dart strings may hold unpaired UTF-16 surrogates (Dart's
jsonEncode writes them as `\udXXX`, so json.loads hands back a str with a lone surrogate), which
UTF-8 cannot encode. They are kept, escaped as `\udXXX` in the JSON text, so every file we write
stays valid UTF-8 and reads back to the same str; `escape_surrogates` does the same for plain
text fields (a TFRecord string feature, a log line).
"""
from __future__ import annotations

import json
import os
import re
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from hope_models.numbers import huge_integer_error

from .episode import ERROR, WARNING, Problem

DEFAULT_MAX_FILE_BYTES = 512 << 20
DEFAULT_MAX_LINE_BYTES = 64 << 20


@dataclass(frozen=True)
class ReadLimits:
    """Size guards: a file or line above these is refused with a problem naming the limit."""

    max_file_bytes: int = DEFAULT_MAX_FILE_BYTES
    max_line_bytes: int = DEFAULT_MAX_LINE_BYTES
    # an upload's inflate.Budget: what its nested decompressors may produce and its deadline
    budget: Any = field(default=None, compare=False)


_SURROGATE = re.compile("[\ud800-\udfff]")


def _escaped(match: re.Match) -> str:
    return f"\\u{ord(match.group()):04x}"


def escape_surrogates(text: str) -> str:
    r"""`text` with every (necessarily unpaired) surrogate written as the six characters `\udXXX`."""
    return _SURROGATE.sub(_escaped, text) if _SURROGATE.search(text) else text


def json_dumps(obj: Any, **kwargs: Any) -> str:
    r"""json.dumps with ensure_ascii=False (unless given) whose result always encodes as UTF-8.

    json.dumps leaves a lone surrogate in the output as the raw code point; inside JSON text it can
    only sit in a string, where the escape `\udXXX` is exactly what a JSON reader turns back into it."""
    kwargs.setdefault("ensure_ascii", False)
    return escape_surrogates(json.dumps(obj, **kwargs))


def json_bytes(obj: Any, **kwargs: Any) -> bytes:
    return json_dumps(obj, **kwargs).encode("utf-8")


class TextReadError(Exception):
    """A file could not be read as text at all (too big, not UTF-8, I/O error)."""


def _human_bytes(n: int) -> str:
    for unit in ("bytes", "KiB", "MiB", "GiB"):
        if n < 1024 or unit == "GiB":
            return f"{n} {unit}" if unit == "bytes" else f"{n:.1f} {unit}"
        n /= 1024
    return f"{n} bytes"  # pragma: no cover


def read_bytes(path: str | os.PathLike, limits: ReadLimits) -> bytes:
    """Read a whole file, refusing it before reading when it is above max_file_bytes."""
    p = Path(path)
    try:
        size = p.stat().st_size
        if size > limits.max_file_bytes:
            raise TextReadError(
                f"file is {_human_bytes(size)}, above the limit max_file_bytes={limits.max_file_bytes} "
                f"({_human_bytes(limits.max_file_bytes)}); raise the limit to read it")
        return p.read_bytes()
    except OSError as exc:
        raise TextReadError(f"cannot read file: {exc.strerror or exc}") from None


def decode_text(data: bytes) -> str:
    """UTF-8 with or without BOM; invalid UTF-8 names the byte offset. A lone UTF-16 surrogate
    written as its three UTF-8-style bytes (older Dart, Java's modified UTF-8, CESU-8) is taken as
    that surrogate, which the writers keep escaped, rather than costing the episode."""
    try:
        return data.decode("utf-8-sig", "surrogatepass")
    except UnicodeDecodeError as exc:
        raise TextReadError(f"not UTF-8 text: invalid byte at offset {exc.start}") from None


def read_text(path: str | os.PathLike, limits: ReadLimits) -> str:
    return decode_text(read_bytes(path, limits))


def _json_error_text(exc: json.JSONDecodeError) -> str:
    return f"not valid JSON: {exc.msg} (line {exc.lineno} column {exc.colno})"


def parse_json_document(text: str) -> Any:
    """Parse one JSON document; raises TextReadError with the parser's position on failure."""
    try:
        return json.loads(text)
    except json.JSONDecodeError as exc:
        raise TextReadError(_json_error_text(exc)) from None
    except ValueError as exc:  # an integer too long for int(): the field is named
        raise TextReadError(f"not usable JSON: {huge_integer_error(text) or exc}") from None
    except RecursionError:
        raise TextReadError("not usable JSON: nested too deeply") from None


@dataclass
class JsonlLine:
    line_no: int  # 1-based line number in the file, for messages
    obj: dict[str, Any]


@dataclass
class JsonlResult:
    lines: list[JsonlLine] = field(default_factory=list)
    problems: list[Problem] = field(default_factory=list)
    lost: int = 0  # non-blank lines that could not be used (bad JSON, not an object, too long)


def parse_jsonl(text: str, source: str, limits: ReadLimits) -> JsonlResult:
    """One JSON object per line. A bad line in the middle is an error for that line (the
    others still read); a bad LAST line is taken as a write cut short by a crash and dropped
    with a warning, because that is what an interrupted recorder leaves behind."""
    result = JsonlResult()
    # split("\n") rather than splitlines(): JSON strings may legally hold U+2028 and friends,
    # which splitlines() would treat as line breaks.
    raw_lines = text.split("\n")
    last_content = len(raw_lines) - 1
    while last_content >= 0 and not raw_lines[last_content].strip():
        last_content -= 1
    max_chars = limits.max_line_bytes
    loads = json.loads
    for i, line in enumerate(raw_lines):
        if not line or line.isspace():
            continue
        line_no = i + 1
        is_last = i == last_content
        # A str's UTF-8 size is between len and 4*len; only encode when it could be over.
        if len(line) * 4 > max_chars and len(line.encode("utf-8")) > max_chars:
            result.problems.append(Problem(
                ERROR, source, f"line {line_no} is {len(line.encode('utf-8'))} bytes, above the limit "
                f"max_line_bytes={limits.max_line_bytes}; line skipped"))
            result.lost += 1
            continue
        try:
            obj = loads(line)
        except (ValueError, RecursionError) as exc:
            why = (_json_error_text(exc) if isinstance(exc, json.JSONDecodeError) else "nested too deeply"
                   if isinstance(exc, RecursionError) else f"not usable JSON: {huge_integer_error(line) or exc}")
            if is_last:
                result.problems.append(Problem(
                    WARNING, source, f"last line {line_no} is truncated or unparseable ({why}); "
                    f"dropped ({len(line)} characters)"))
            else:
                result.problems.append(Problem(
                    ERROR, source, f"line {line_no}: {why}; line skipped"))
            result.lost += 1
            continue
        if not isinstance(obj, dict):
            result.problems.append(Problem(
                ERROR, source, f"line {line_no}: expected a JSON object per line, found "
                f"{type(obj).__name__}; line skipped"))
            result.lost += 1
            continue
        result.lines.append(JsonlLine(line_no, obj))
    return result
