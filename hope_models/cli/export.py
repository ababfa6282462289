"""`run_trainer.py export --cloud EPISODE... --out DIR [--allow-invalid] [--json]`.

Writes the Pi runtime's upload package <episode_id>.tar.gz per episode. Each episode is checked
with the cloud profile first; one that fails is refused (exit 1) unless --allow-invalid, which
packages it anyway (content JSON cannot hold, such as NaN, is still refused). Exit 2 for a usage
error such as a missing path or no --cloud.
"""
from __future__ import annotations

import argparse
import json
import os
import sys

from hope_models.cli.validate import missing_paths, print_entry, reader_options
from hope_models.rlds.export_cloud import export_paths


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("episodes", nargs="+", metavar="EPISODE", help="episode files or dirs")
    parser.add_argument("--cloud", action="store_true",
                        help="write the Pi runtime's cloud upload package (the only format so far)")
    parser.add_argument("--out", required=True, metavar="DIR", help="where the packages go")
    parser.add_argument("--allow-invalid", action="store_true",
                        help="package episodes that fail the cloud profile instead of refusing them")
    parser.add_argument("--json", action="store_true", help="print one JSON document")


def run(args: argparse.Namespace) -> int:
    if not args.cloud:
        print("export: say which package to write: --cloud (the only format so far)", file=sys.stderr)
        return 2
    if missing_paths("export", args.episodes):
        return 2
    if os.path.exists(args.out) and not os.path.isdir(args.out):
        print(f"export: --out {args.out}: exists and is not a directory", file=sys.stderr)
        return 2
    options = reader_options("export")
    if options is None:
        return 2
    result = export_paths(args.episodes, args.out, allow_invalid=args.allow_invalid, **options)
    summary = result["summary"]
    if args.json:
        json.dump(result, sys.stdout, indent=2)
        sys.stdout.write("\n")
    else:
        for entry in result["episodes"]:
            print_entry(f"{entry['action']:<9} {entry['package'] or entry['source']}", entry)
        print(f"{summary['exported']} exported, {summary['refused']} refused, "
              f"{summary['skipped']} skipped")
        if summary["refused"] and not args.allow_invalid:
            print("refused episodes fail the cloud profile; fix them, or pass --allow-invalid",
                  file=sys.stderr)
    return 0 if summary["ok"] else 1
