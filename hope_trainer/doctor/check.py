"""One doctor check's answer (`Check`) and its statuses: what the checks of host.py, children.py and
state.py return and `run_checks` (this package's __init__) collects, below all of them."""
from __future__ import annotations

from collections.abc import Callable, Iterable
from dataclasses import asdict, dataclass
from typing import Any

OK, WARN, FAIL, SKIP = "ok", "warn", "fail", "skip"
STATUSES = (OK, WARN, FAIL, SKIP)


@dataclass(frozen=True)
class Check:
    check: str  # the check's name, e.g. "token"
    status: str  # ok | warn | fail | skip (skip: not applicable here, e.g. no systemd)
    detail: str  # what was found
    fix: str = ""  # what to do about it ("" when nothing needs doing)

    def __post_init__(self):
        if self.status not in STATUSES:
            raise ValueError(f"check {self.check!r}: status {self.status!r} is not one of {STATUSES}")

    def to_json_obj(self) -> dict[str, Any]:
        return asdict(self)


CheckFn = Callable[[Any], "Check | Iterable[Check]"]


__all__ = ["FAIL", "OK", "SKIP", "STATUSES", "WARN", "Check", "CheckFn"]
