"""JSON/JSONL text handling: encodings, line ends, bare NaN tokens, bad and truncated lines."""
from __future__ import annotations

import json
import math
from pathlib import Path

import pytest

from hope_models.rlds.discover import read_path
from hope_models.rlds.episode import ERROR, WARNING
from hope_models.rlds.json_text import ReadLimits, TextReadError, parse_jsonl, read_text

LIMITS = ReadLimits()


def step_line(i: int) -> str:
    return json.dumps({"timestamp_ms": i * 100, "observation": {"i": i}, "action": {}})


def test_truncated_last_line_is_dropped_with_a_warning(tmp_path: Path):
    f = tmp_path / "cut.jsonl"
    f.write_text("\n".join(step_line(i) for i in range(3)) + "\n" + step_line(3)[:25])
    [report] = read_path(f)
    [ep] = report.episodes
    assert [s.observation["i"] for s in ep.steps] == [0, 1, 2]
    assert ep.steps_lost == 1 and ep.errors == []
    [w] = [p for p in ep.warnings if "truncated" in p.message]
    assert "last line 4" in w.message and w.source == str(f)


def test_bad_middle_line_is_an_error_and_the_rest_is_read(tmp_path: Path):
    f = tmp_path / "mid.jsonl"
    f.write_text("\n".join([step_line(0), '{"observation": {"i": 1}, "action": ', step_line(2), step_line(3)]))
    [report] = read_path(f)
    [ep] = report.episodes
    assert [s.observation["i"] for s in ep.steps] == [0, 2, 3]
    [e] = ep.errors
    assert e.severity == ERROR and "line 2" in e.message and "not valid JSON" in e.message
    assert ep.steps_lost == 1


def test_nan_and_infinity_tokens_and_big_ints():
    text = '{"a": NaN, "b": Infinity, "c": -Infinity, "t": 1764952865006200431}\n'
    [line] = parse_jsonl(text, "mem", LIMITS).lines
    assert math.isnan(line.obj["a"]) and line.obj["b"] == math.inf and line.obj["c"] == -math.inf
    assert line.obj["t"] == 1764952865006200431 and type(line.obj["t"]) is int


def test_bom_crlf_and_blank_lines(tmp_path: Path):
    f = tmp_path / "win.jsonl"
    body = "\r\n".join([step_line(0), "", "   ", step_line(1), step_line(2)]) + "\r\n\r\n"
    f.write_bytes(b"\xef\xbb\xbf" + body.encode("utf-8"))
    [report] = read_path(f)
    [ep] = report.episodes
    assert len(ep.steps) == 3 and ep.problems == []
    assert [s.timestamp_ns for s in ep.steps] == [0, 100_000_000, 200_000_000]

    single = tmp_path / "win.json"
    single.write_bytes(b"\xef\xbb\xbf" + json.dumps({"steps": [{"observation": {}, "action": {}}]},
                                                    indent=2).replace("\n", "\r\n").encode())
    [report] = read_path(single)
    assert len(report.episodes) == 1


def test_line_separators_inside_strings_do_not_split_lines():
    text = json.dumps({"observation": {"say": "a\u2028b\u0085c"}}, ensure_ascii=False) + "\n"
    result = parse_jsonl(text, "mem", LIMITS)
    assert [line.obj["observation"]["say"] for line in result.lines] == ["a\u2028b\u0085c"]


def test_non_object_lines_and_line_numbers():
    text = "\n".join(['{"a": 1}', "[1, 2]", "", '{"a": 2}'])
    result = parse_jsonl(text, "src.jsonl", LIMITS)
    assert [line.line_no for line in result.lines] == [1, 4]
    [p] = result.problems
    assert p.severity == ERROR and p.source == "src.jsonl" and "line 2" in p.message and "list" in p.message


def test_invalid_utf8_and_size_guard(tmp_path: Path):
    f = tmp_path / "latin.jsonl"
    f.write_bytes(b'{"a": "caf\xe9"}\n')
    with pytest.raises(TextReadError, match="not UTF-8 text: invalid byte at offset 10"):
        read_text(f, LIMITS)
    [report] = read_path(f)
    assert report.episodes == [] and report.problems[0].severity == ERROR

    with pytest.raises(TextReadError, match="max_file_bytes=4"):
        read_text(f, ReadLimits(max_file_bytes=4))

    long_line = '{"observation": {"s": "' + "é" * 60 + '"}}'  # 60 chars, 120+ bytes
    result = parse_jsonl(long_line + "\n" + step_line(1), "x", ReadLimits(max_line_bytes=100))
    assert len(result.lines) == 1 and result.lost == 1
    assert result.problems[0].severity == ERROR and "max_line_bytes=100" in result.problems[0].message


def test_only_blank_lines_is_no_steps(tmp_path: Path):
    f = tmp_path / "blank.jsonl"
    f.write_text("\n \n\t\n")
    [report] = read_path(f)
    assert report.skipped and report.episodes == []
    assert all(p.severity == WARNING for p in report.problems)
