"""`run_trainer.py dataset DATASET_DIR`: build the feature spec and cache of a dataset and summarise it."""
from __future__ import annotations

import argparse
import json
import sys

from hope_models.settings import SettingsError, load_settings


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("dataset_dir", help="a dataset dir of canonical episodes (as written by ingest)")
    parser.add_argument("--spec", metavar="FILE", help="feature spec JSON overriding the inferred one")
    parser.add_argument("--cache-dir", metavar="DIR", help="cache root (default: $HOPE_HOME/cache)")
    parser.add_argument("--json", action="store_true", help="print the summary as JSON")


def run(args: argparse.Namespace) -> int:
    from hope_models.data.cache import CacheError  # lazy: loads mcap, numpy
    from hope_models.data.features import FeatureSpecError  # lazy: loads numpy
    from hope_models.data.summary import format_summary, summarise_dataset  # lazy: loads mcap, numpy

    try:
        cache_dir = args.cache_dir or load_settings().cache_dir
        summary = summarise_dataset(args.dataset_dir, cache_dir, args.spec)
    except (CacheError, FeatureSpecError, SettingsError) as exc:
        # Bad data or a bad spec file is the user's to fix: say what and where, no traceback.
        if args.json:
            print(json.dumps({"ok": False, "error": str(exc)}))
        print(f"error: {exc}", file=sys.stderr)
        return 2
    except OSError as exc:
        print(f"error: {exc.filename or args.dataset_dir}: {exc.strerror or exc}", file=sys.stderr)
        return 2
    if args.json:
        print(json.dumps({"ok": True, **summary}, indent=1))
    else:
        print(format_summary(summary))
    return 0
