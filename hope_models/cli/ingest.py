"""`run_trainer.py ingest SRC... --into DATASET_DIR [--json]`: copy episodes into a canonical dataset.

Episodes are validated with the train profile first; rejected ones are listed in
<DATASET_DIR>/manifest.json and not written. Re-running with the same input changes nothing.
Exit 0 when nothing was rejected, 1 when something was (the rest is still ingested) or the dataset
dir cannot be used, 2 for a usage error such as a missing source, 6 when the disk filled up (what
was written is kept; free space and re-run: it goes on where it stopped).
"""
from __future__ import annotations

import argparse
import json
import sys

from hope_models.cli.validate import missing_paths, print_entry, reader_options
from hope_models.rlds.ingest import IngestDiskFull, IngestError, ingest_paths


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("sources", nargs="+", metavar="SRC", help="episode files or dirs")
    parser.add_argument("--into", required=True, metavar="DATASET_DIR",
                        help="the canonical dataset dir (created if missing)")
    parser.add_argument("--json", action="store_true", help="print one JSON document")


def run(args: argparse.Namespace) -> int:
    if missing_paths("ingest", args.sources):
        return 2
    options = reader_options("ingest")
    if options is None:
        return 2
    try:
        result = ingest_paths(args.sources, args.into, **options)
    except IngestDiskFull as exc:  # the exit code of a training job paused for disk (contract.py)
        print(f"ingest: {exc}", file=sys.stderr)
        return 6
    except IngestError as exc:
        print(f"ingest: {exc}", file=sys.stderr)
        return 1
    summary = result["summary"]
    if args.json:
        json.dump(result, sys.stdout, indent=2)
        sys.stdout.write("\n")
    else:
        for entry in result["episodes"]:
            entry = dict(entry, warnings=[] if entry["action"] != "skipped" else entry["warnings"])
            print_entry(f"{entry['action']:<10} {entry['steps']:>6} steps  "
                        f"{entry['episode_id'] or '-'}  {entry['source']}", entry)
        print(f"{result['dataset']}: {summary['written']} written, {summary['unchanged']} unchanged, "
              f"{summary['duplicate']} duplicate, "
              f"{summary['rejected']} rejected, {summary['skipped']} skipped "
              "(warnings: run validate on the sources)")
    return 0 if summary["ok"] else 1
