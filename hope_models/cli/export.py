"""`run_trainer.py export --cloud EPISODE... --out DIR [--format package|npz] [--spec FILE] [--allow-invalid] [--json]`.

`--format package` (the default) writes the Pi runtime's upload package <episode_id>.tar.gz per
episode. Each episode is checked with the cloud profile first; one that fails is refused (exit 1)
unless --allow-invalid, which packages it anyway (content JSON cannot hold, such as NaN, is still
refused).

`--format npz` writes ContinuonCloud's own upload format: <episode_id>.npz (`observations`,
`actions`, `rewards`, `timestamps`) and its sidecar <episode_id>.npz.json (the field layout, the
feature spec and the backend's query fields; hope_models/rlds/read_npz.py). The fields are the
feature spec's: inferred from each episode, or the `--spec FILE` override as other commands take
it. Episodes are checked with the train profile (refused unless --allow-invalid); one that does
not fit its spec (the step and field named) or whose npz would be over 100 MiB is refused always.

Exit 0 when nothing was refused, 1 when something was, 2 for a usage error such as a missing
path, no --cloud, or a spec file that cannot be read.
"""
from __future__ import annotations

import argparse
import json
import os
import sys
from typing import Any

from hope_models.cli.validate import missing_paths, print_entry, reader_options
from hope_models.data.export_npz import export_npz_paths
from hope_models.data.features import FeatureSpecError
from hope_models.data.spec_request import SpecRequest
from hope_models.rlds.export_cloud import export_paths

FORMATS = ("package", "npz")


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("episodes", nargs="+", metavar="EPISODE", help="episode files or dirs")
    parser.add_argument("--cloud", action="store_true", help="write episodes for the cloud (see --format)")
    parser.add_argument("--format", choices=FORMATS, default="package",
                        help="package: the Pi runtime's <id>.tar.gz upload package (default); npz: "
                             "ContinuonCloud's <id>.npz with its <id>.npz.json sidecar")
    parser.add_argument("--spec", metavar="FILE",
                        help="with --format npz: feature spec JSON choosing the fields (default: inferred "
                             "from each episode)")
    parser.add_argument("--out", required=True, metavar="DIR", help="where the files go")
    parser.add_argument("--allow-invalid", action="store_true",
                        help="export episodes that fail the validation profile instead of refusing them")
    parser.add_argument("--json", action="store_true", help="print one JSON document")


def _usage_error(args: argparse.Namespace) -> str | None:
    if not args.cloud:
        return "say which export to write: --cloud (with --format package or npz)"
    if args.spec is not None and args.format != "npz":
        return "--spec chooses the fields of --format npz; the package holds every field"
    if os.path.exists(args.out) and not os.path.isdir(args.out):
        return f"--out {args.out}: exists and is not a directory"
    return None


def _export(args: argparse.Namespace, options: dict[str, int]) -> dict[str, Any] | None:
    if args.format == "package":
        return export_paths(args.episodes, args.out, allow_invalid=args.allow_invalid, **options)
    request = None
    if args.spec is not None:
        try:
            request = SpecRequest.load(args.spec)
        except (FeatureSpecError, OSError) as exc:
            print(f"export: --spec {args.spec}: {getattr(exc, 'strerror', None) or exc}", file=sys.stderr)
            return None
    return export_npz_paths(args.episodes, args.out, request, allow_invalid=args.allow_invalid, **options)


def run(args: argparse.Namespace) -> int:
    problem = _usage_error(args)
    if problem is not None:
        print(f"export: {problem}", file=sys.stderr)
        return 2
    if missing_paths("export", args.episodes):
        return 2
    options = reader_options("export")
    if options is None:
        return 2
    result = _export(args, options)
    if result is None:
        return 2
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
            profile = "cloud" if args.format == "package" else "train"
            print(f"refused episodes fail the {profile} profile or do not fit; fix them, or pass --allow-invalid",
                  file=sys.stderr)
    return 0 if summary["ok"] else 1
