"""`hope-trainer doctor`: one screen that says what is wrong on this machine, and what to do.

    hope-trainer doctor            # ok / warn / fail, one line per check, the fix under each
    hope-trainer doctor --json     # [{"check", "status", "detail", "fix"}, ...]
    hope-trainer doctor --skip torch --skip render

Exits 1 when any check fails, else 0 (warnings and skips do not fail). Reads, never writes:
see hope_trainer/doctor/.
"""
from __future__ import annotations

import argparse
import json
import logging
import os
import sys
from pathlib import Path

import hope_models.settings as settings_module
from hope_trainer.doctor import FAIL, OK, SKIP, WARN, Check, check_names, run_checks

_MARK = {OK: "ok  ", WARN: "WARN", FAIL: "FAIL", SKIP: "skip"}


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--json", action="store_true", help="print the checks as one JSON list")
    parser.add_argument("--skip", action="append", default=[], metavar="CHECK", choices=check_names(),
                        help=f"leave a check out (repeatable): {', '.join(check_names())}")


def load_settings_readonly():
    """(settings, a fail line or None), read without securing $HOPE_HOME (no mkdir, no chmod):
    the doctor reports the home as it is."""
    try:
        return settings_module.load_settings(secure=False), None
    except settings_module.SettingsError as exc:
        home = Path(os.environ.get("HOPE_HOME") or settings_module.DEFAULT_HOME).expanduser()
        return settings_module.Settings(home=home), Check(
            "settings", FAIL, f"{exc}; the checks below use the defaults",
            "fix config.toml or the HOPE_* variable it names")


def render(checks: list[Check], home: Path) -> str:
    width = max(len(c.check) for c in checks)
    lines = [f"hope-trainer doctor  (HOPE_HOME={home})", ""]
    for c in checks:
        lines.append(f"  {_MARK[c.status]}  {c.check:<{width}}  {c.detail}")
        if c.fix and c.status in (WARN, FAIL):
            lines.append(f"        {'':<{width}}  fix: {c.fix}")
    counts = {s: sum(c.status == s for c in checks) for s in (OK, WARN, FAIL, SKIP)}
    lines += ["", f"{counts[OK]} ok, {counts[WARN]} warn, {counts[FAIL]} fail, {counts[SKIP]} skipped"]
    return "\n".join(lines)


def run(args: argparse.Namespace) -> int:
    # The thermal readers log an unreadable source once per process; here it is a line of the report.
    logging.getLogger("hope_models.train.thermal").setLevel(logging.ERROR)
    settings, settings_fail = load_settings_readonly()
    checks = ([settings_fail] if settings_fail else []) + run_checks(settings, skip=args.skip)
    if args.json:
        print(json.dumps([c.to_json_obj() for c in checks], indent=1))
    else:
        print(render(checks, Path(settings.home)))
    sys.stdout.flush()
    return 1 if any(c.status == FAIL for c in checks) else 0
