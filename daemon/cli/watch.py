"""`run_trainer.py watch RUN`: follow a run until it ends.

On a terminal: one progress line rewritten in place (bar, step/total, loss, steps/s, ETA, state).
Otherwise (a pipe, a log file): one line per change. A paused or interrupted run is shown with its
reason and watched on (it may be resumed or requeued). Exit code: 0 completed, 1 failed,
5 cancelled (as `train`), 2 unknown run; Ctrl-C stops watching (130) and leaves the run alone.
It only reads the database (the run row, every --interval seconds).
"""
from __future__ import annotations

import argparse
import math
import sys
import time
from typing import TYPE_CHECKING, Any

from daemon.cli.registry import open_registry, print_json, run_command
from daemon.cli.status import state_text
from hope_models.numbers import NumberError, float_from_text
from hope_models.train.contract import OUTCOME_EXIT_CODES

if TYPE_CHECKING:
    from registry.db import Registry

END_EXIT_CODES = {"completed": OUTCOME_EXIT_CODES["completed"], "failed": OUTCOME_EXIT_CODES["failed"],
                  "cancelled": OUTCOME_EXIT_CODES["cancelled"]}
BAR_WIDTH = 24


def _interval(text: str) -> float:
    try:  # the one rule for numbers (hope_models/numbers.py)
        return float_from_text("--interval", text, minimum=0.05, maximum=60.0)
    except NumberError as exc:
        raise argparse.ArgumentTypeError(exc.reason + " (seconds)") from None


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("run", metavar="RUN", help="the run id (see `run_trainer.py status`)")
    parser.add_argument("--interval", type=_interval, default=0.5, help="seconds between looks (default 0.5)")
    parser.add_argument("--json", action="store_true",
                        help="no progress lines; print the run as JSON when it ends")


def _duration(seconds: float | None) -> str:
    if seconds is None or not math.isfinite(seconds):
        return "?"
    s = int(seconds)
    return f"{s // 3600}h{s % 3600 // 60:02d}m" if s >= 3600 else f"{s // 60}m{s % 60:02d}s"


def progress_line(run: dict[str, Any]) -> str:
    step, total = int(run["step"]), max(1, int(run["total_steps"]))
    filled = min(BAR_WIDTH, BAR_WIDTH * step // total)
    bar = "#" * filled + "-" * (BAR_WIDTH - filled)
    loss = run.get("loss")
    sps = run.get("steps_per_s")
    eta = (total - step) / sps if isinstance(sps, (int, float)) and sps > 0 and run["state"] == "running" else None
    parts = [f"{run['id']} {run['component']}", f"[{bar}] {step}/{total}",
             f"loss {loss:.4g}" if isinstance(loss, (int, float)) else "loss -",
             f"{sps:.1f} steps/s" if isinstance(sps, (int, float)) else "- steps/s",
             f"ETA {_duration(eta)}", state_text(run)]
    if run["state"] == "running" and run.get("throttle_level"):
        parts.append(f"throttle {run['throttle_level']}")
    if run["state"] in ("queued", "interrupted") and run.get("attempt", 1) > 1:
        parts.append(f"attempt {run['attempt']}/{run['max_attempts']}")
    if run.get("waiting"):
        parts.append(run["waiting"])
    return "  ".join(parts)


def end_line(run: dict[str, Any]) -> str:
    text = f"{run['state']}: {run['id']} {run['component']} at step {run['step']}/{run['total_steps']}"
    if isinstance(run.get("loss"), (int, float)):
        text += f", loss {run['loss']:.4g}"
    if run.get("error"):
        text += f"\n  {run['error']}"
    if run["state"] == "completed" and run.get("last_checkpoint"):
        text += f"\n  checkpoint {run['last_checkpoint']}"
    return text


class Display:
    """Where the lines go: rewritten in place on a terminal, one per change otherwise."""

    def __init__(self, stream=None, quiet: bool = False):
        self.stream = stream or sys.stdout
        self.tty = self.stream.isatty()
        self.quiet = quiet
        self._last: str | None = None
        self._open = False

    def show(self, run: dict[str, Any]) -> None:
        if self.quiet:
            return
        line = progress_line(run)
        if line == self._last:
            return
        self._last = line
        if self.tty:
            self.stream.write("\r" + line.ljust(110))
            self._open = True
        else:
            self.stream.write(line + "\n")
        self.stream.flush()

    def close(self) -> None:
        if self._open:
            self.stream.write("\n")
            self.stream.flush()
            self._open = False


def watch(registry: Registry, run_id: str, interval: float, display: Display) -> dict[str, Any]:
    """Poll until the run is in a terminal state; returns its final JSON object."""
    from registry import runs  # lazy: loads sqlalchemy

    while True:
        with registry.session(readonly=True) as s:
            obj = runs.to_json(s, [runs.get_run(s, run_id)])[0]
        display.show(obj)
        if obj["state"] in END_EXIT_CODES:
            return obj
        time.sleep(interval)


def run(args: argparse.Namespace) -> int:
    def body() -> int:
        display = Display(quiet=args.json)
        with open_registry() as (_settings, registry):
            try:
                final = watch(registry, args.run, args.interval, display)
            except KeyboardInterrupt:
                display.close()
                print(f"stopped watching; run {args.run} is not affected", file=sys.stderr)
                return 130
            finally:
                display.close()
        if args.json:
            print_json(final)
        else:
            print(end_line(final), flush=True)
        return END_EXIT_CODES[final["state"]]

    return run_command(body)
