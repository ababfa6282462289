"""`run_trainer.py validate PATH... [--profile train|cloud] [--json]`: a verdict on every episode.

Exit 0 when every episode found is ok (accepted, with warnings, partly recovered, or skipped),
1 when any is rejected, 2 for a usage error such as a missing path.
"""
from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path
from typing import Any

from hope_models.rlds.validate import PROFILES
from hope_models.rlds.validation_report import STATUSES, validate_paths
from hope_models.settings import SettingsError, load_settings


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("paths", nargs="+", metavar="PATH",
                        help="episode files or dirs (dirs are searched recursively)")
    parser.add_argument("--profile", choices=PROFILES, default="train",
                        help="train: what would corrupt training; cloud: adds the upload package's "
                             "required metadata, safety block and public-sharing rules")
    parser.add_argument("--json", action="store_true", help="print one JSON document")


def reader_options(command: str) -> dict[str, int] | None:
    """The reader's size guards from the deployment settings; None (after a message) if broken."""
    try:
        settings = load_settings()
    except SettingsError as exc:
        print(f"{command}: {exc}", file=sys.stderr)
        return None
    return {"max_file_bytes": settings.max_file_mb << 20, "max_line_bytes": settings.max_line_kb << 10}


def missing_paths(command: str, paths: list[str]) -> bool:
    missing = [p for p in paths if not Path(p).exists()]
    for path in missing:
        print(f"{command}: {path}: no such file or directory", file=sys.stderr)
    return bool(missing)


def print_entry(head: str, entry: dict[str, Any]) -> None:
    print(head)
    for message in entry["errors"]:
        print(f"    error: {message}")
    for message in entry["warnings"]:
        print(f"    warning: {message}")


def run(args: argparse.Namespace) -> int:
    if missing_paths("validate", args.paths):
        return 2
    options = reader_options("validate")
    if options is None:
        return 2
    result = validate_paths(args.paths, args.profile, **options)
    summary = result["summary"]
    if args.json:
        json.dump({"episodes": result["episodes"], "summary": summary}, sys.stdout, indent=2)
        sys.stdout.write("\n")
    else:
        for entry in result["episodes"]:
            lost = f" ({entry['steps_lost']} lost)" if entry["steps_lost"] else ""
            print_entry(f"{entry['status']:<22} {entry['steps']:>6} steps{lost}  {entry['source']}", entry)
        counts = ", ".join(f"{summary[s]} {s}" for s in STATUSES if summary[s])
        print(f"{summary['episodes']} episodes, {summary['steps']} steps ({counts or 'nothing found'}); "
              f"profile {args.profile}: {'ok' if summary['ok'] else 'NOT ok'}")
    return 0 if summary["ok"] else 1
