"""A banner line reaches the console in one write, so a log line written to the same file by
another thread or a child can never land inside it (hope_trainer/console.py)."""
from __future__ import annotations

import sys

from hope_trainer.console import say


class Writes:
    def __init__(self):
        self.calls: list[str] = []

    def write(self, text: str) -> int:
        self.calls.append(text)
        return len(text)

    def flush(self) -> None:
        self.calls.append("<flush>")


def test_a_line_is_one_write_where_print_makes_two(monkeypatch):
    out = Writes()
    monkeypatch.setattr(sys, "stdout", out)
    say("Robot Editor: http://127.0.0.1:5000/  token: abc")
    assert out.calls == ["Robot Editor: http://127.0.0.1:5000/  token: abc\n", "<flush>"]
    out.calls.clear()
    print("Robot Editor: x  token: abc", flush=True)  # what the banner used: text and newline apart
    assert out.calls[:2] == ["Robot Editor: x  token: abc", "\n"]


def test_the_services_banners_are_said_not_printed():
    from pathlib import Path

    root = Path(__file__).resolve().parents[1] / "hope_trainer"
    for path in (root / "commands" / "serve.py", root / "commands" / "webapp.py"):
        banner = [line for line in path.read_text().splitlines() if "Robot Editor: " in line]
        assert banner and all("say(" in line for line in banner), (path, banner)
