#!/usr/bin/env python3
"""HOPE Seed Trainer command line, for a checkout: the same as `hope-trainer` / `python -m hope_trainer`.

The dispatcher (COMMANDS, build_parser, main) lives in hope_trainer/cli.py; this script only lets
`python run_trainer.py ...` work from the checkout without an installed console script.
"""
from __future__ import annotations

import sys

from hope_trainer.cli import COMMANDS, build_parser, main

__all__ = ["COMMANDS", "build_parser", "main"]

if __name__ == "__main__":
    sys.exit(main())
