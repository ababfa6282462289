"""`hope-trainer doctor`: what is wrong on this machine, one line per check, each with its fix.

    checks = run_checks(settings, skip={"torch"})   # [Check(check, status, detail, fix), ...]

A check reads state and never changes it: no migration, no token made, no chmod, no directory
created (the command loads the settings without securing $HOPE_HOME, see commands/doctor.py).
The checks live by what they look at: `host.py` the machine (architecture, Python, memory cgroup,
page size, thermal sources, memory, disk), `children.py` what has to be proven in a child process
(torch's build, an EGL frame: a broken torch or GL driver is a fail line, not a crash of the doctor),
`state.py` this deployment's state ($HOPE_HOME, token, database, broker, services).
"""
from __future__ import annotations

from collections.abc import Iterable
from typing import Any

from hope_trainer.doctor import children, host, state
from hope_trainer.doctor.check import FAIL, OK, SKIP, STATUSES, WARN, Check, CheckFn


def all_checks() -> list[tuple[str, CheckFn]]:
    """(name, function) in the order they are printed; a function returns one Check or several."""
    return [("architecture", host.check_architecture), ("python", host.check_python),
            ("torch", children.check_torch), ("render", children.check_render),
            ("memory-cgroup", host.check_memory_cgroup), ("page-size", host.check_page_size),
            ("thermal", host.check_thermal), ("memory", host.check_memory), ("disk", host.check_disk),
            ("home", state.check_home), ("token", state.check_token), ("database", state.check_database),
            ("broker", state.check_broker), ("services", state.check_services)]


def run_checks(settings: Any, skip: Iterable[str] = ()) -> list[Check]:
    """Every check not in `skip`, in order. A check that raises is reported as its own fail line
    (a bug in the doctor must not hide what the other checks find)."""
    skip = set(skip)
    out: list[Check] = []
    for name, fn in all_checks():
        if name in skip:
            out.append(Check(name, SKIP, "skipped (--skip)"))
            continue
        try:
            got = fn(settings)
        except Exception as exc:  # noqa: BLE001 - reported, never swallowed
            out.append(Check(name, FAIL, f"the check itself failed: {type(exc).__name__}: {exc}",
                             "report this as a bug of hope-trainer doctor"))
            continue
        out.extend([got] if isinstance(got, Check) else got)
    return out


def check_names() -> list[str]:
    return [name for name, _ in all_checks()]


__all__ = ["FAIL", "OK", "SKIP", "STATUSES", "WARN", "Check", "CheckFn", "all_checks", "check_names", "run_checks"]
