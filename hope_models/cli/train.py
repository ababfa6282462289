"""`run_trainer.py train`: train one component in the foreground, or a sequence of them.

    run_trainer.py train --component fast_loop --data DS --run-dir R --steps 2000 --seed 0 [--json]
    run_trainer.py train --sequential vqvae,fast_loop,mid_loop --data DS --run-dir R --steps 2000

Re-running the same command after a kill, a pause or Ctrl-C continues from the last good
checkpoint (see docs/training.md). Exit codes: contract.OUTCOME_EXIT_CODES (0 completed, 1 failed,
3 paused for memory, 4 paused, 5 cancelled), 2 for usage errors (bad arguments, a missing or
unusable dataset, a run dir holding another job, a model that cannot fit the memory budget).
The sequential parent never imports torch: each component trains in a child process.
"""
from __future__ import annotations

import argparse
import json
import math
import signal
import sys
import time
from typing import Any

from hope_models.child_result import add_result_argument, write_result
from hope_models.components import COMPONENTS
from hope_models.settings import Settings, SettingsError, load_settings
from hope_models.train.config import (
    OPTIONS,
    TrainConfig,
    add_flag,
    add_flags,
    deployment_values,
    over_deployment_budget,
    values_from_args,
)
from hope_models.train.contract import ControlCommand
from hope_models.train.loop import TrainSetupError, train


def add_arguments(parser: argparse.ArgumentParser) -> None:
    # every option's flag, default and help come from TrainConfig (train/config.py)
    what = parser.add_mutually_exclusive_group(required=True)
    what.add_argument("--component", choices=COMPONENTS, help=OPTIONS["component"].help)
    what.add_argument("--sequential", metavar="LIST",
                      help="comma-separated components trained one after the other, each in its own process "
                           "(e.g. vqvae,fast_loop,mid_loop); each gets RUN_DIR/<component>")
    add_flag(parser, "data", required=True)
    add_flag(parser, "run_dir", required=True)
    add_flag(parser, "steps", required=True)
    add_flags(parser, "train", skip=("run_dir",))
    parser.add_argument("--json", action="store_true", help="print the result as JSON on stdout")
    add_result_argument(parser)


def run(args: argparse.Namespace) -> int:
    try:
        settings = load_settings()
    except SettingsError as exc:
        print(f"error: {exc}", file=sys.stderr)
        return 2
    if args.sequential:
        from hope_models.train.sequential import run_sequential  # torch-free: children train
        return run_sequential(args, settings)
    return _run_one(args, settings)


# -- one component, in this process ---------------------------------------------------------------

class SignalControl:
    """Ctrl-C / SIGTERM ask the loop to checkpoint and stop as paused (re-run to resume); a second
    one aborts at once (the last checkpoint still stands)."""

    def __init__(self):
        self.desired = "run"
        self._previous = {}
        for sig in (signal.SIGINT, signal.SIGTERM):
            self._previous[sig] = signal.signal(sig, self._handle)

    def _handle(self, signum, frame):
        if self.desired != "run":
            raise KeyboardInterrupt
        self.desired = "pause"
        print("\nstopping: checkpointing after this step (again to abort now)", file=sys.stderr, flush=True)

    def poll(self, step: int) -> ControlCommand:
        return ControlCommand(desired=self.desired)

    def restore(self) -> None:
        for sig, handler in self._previous.items():
            signal.signal(sig, handler)


class ConsoleEvents:
    """Progress on stderr (one line rewritten on a terminal, a line every few seconds otherwise),
    warnings and thermal changes as lines of their own."""

    def __init__(self, component: str):
        self.component = component
        self.tty = sys.stderr.isatty()
        self.min_gap_s = 0.2 if self.tty else 5.0
        self._last = 0.0
        self._open_line = False

    def _line(self, text: str) -> None:
        if self._open_line:
            sys.stderr.write("\n")
            self._open_line = False
        print(text, file=sys.stderr, flush=True)

    def __call__(self, kind: str, payload: dict) -> None:
        if kind == "progress":
            now = time.monotonic()
            last = payload["step"] >= payload["total"]
            if now - self._last < self.min_gap_s and not last:
                return
            self._last = now
            eta = payload.get("eta_s")
            text = (f"{self.component} step {payload['step']}/{payload['total']}  loss {payload['loss']:.4g}  "
                    f"{payload['steps_per_s']:.1f} steps/s  ETA {_duration(eta)}  RSS {payload['rss_mb']:.0f} MB")
            if self.tty:
                sys.stderr.write("\r" + text.ljust(100))
                sys.stderr.flush()
                self._open_line = True
            else:
                print(text, file=sys.stderr, flush=True)
        elif kind == "log":
            level = payload.get("level", "info")
            self._line(payload["message"] if level == "info" else f"{level}: {payload['message']}")
        elif kind == "throttle":
            temp = payload.get("temp_c")
            where = f" at {temp:.1f} C" if isinstance(temp, (int, float)) else ""
            self._line(f"thermal: {payload.get('event', 'level')} {payload.get('level')}{where}: "
                       f"{payload.get('reason', '')}")
        elif kind == "resume":
            self._line(f"resuming from step {payload['step']} ({payload['path']})")

    def finish(self) -> None:
        if self._open_line:
            sys.stderr.write("\n")
            self._open_line = False


def _duration(seconds: Any) -> str:
    if not isinstance(seconds, (int, float)) or not math.isfinite(seconds):
        return "?"
    s = int(seconds)
    return f"{s // 3600}h{s % 3600 // 60:02d}m" if s >= 3600 else f"{s // 60}m{s % 60:02d}s"


def config_from_args(args: argparse.Namespace, settings: Settings, component: str, run_dir: str):
    """The TrainConfig of the flags given, the deployment's values from `settings` for the rest
    of what the deployment decides, TrainConfig's defaults for everything else."""
    given = values_from_args(args, "train")
    given.pop("run_dir", None)  # a sequence gives each component its own
    too_much = over_deployment_budget(given.get("memory_budget_mb", 0.0), settings)
    if too_much:
        raise TrainSetupError(too_much)
    return TrainConfig(component=component, data=args.data, run_dir=run_dir, steps=args.steps,
                       **{**deployment_values(settings), **given})


def _run_one(args: argparse.Namespace, settings: Settings) -> int:
    events = ConsoleEvents(args.component)
    control = SignalControl()
    try:
        cfg = config_from_args(args, settings, args.component, args.run_dir)
        result = train(cfg, control, events)
    except TrainSetupError as exc:
        events.finish()
        failed = {"component": args.component, "outcome": "error", "message": str(exc)}
        write_result(args.result_file, failed)
        if args.json:
            print(json.dumps(failed))
        print(f"error: {exc}", file=sys.stderr)
        return 2
    finally:
        control.restore()
    events.finish()
    write_result(args.result_file, result.cli_json())
    if args.json:
        print(json.dumps(result.cli_json()))
        if result.outcome != "completed":
            print(f"{result.outcome}: {result.message}", file=sys.stderr)
    else:
        print(format_result(result, cfg.memory_budget_mb))
    return result.exit_code


def format_result(result, budget_mb: float) -> str:
    def f(v):
        return "-" if v is None else f"{v:.4g}"

    resumed = f", resumed from step {result.resumed_from}" if result.resumed_from is not None else ""
    lines = [f"{result.outcome}: {result.component} at step {result.steps}/{result.total_steps}{resumed}",
             f"  loss {f(result.first_loss)} -> {f(result.final_loss)}"]
    s = result.summary or {}
    if s.get("ratio") is not None:
        lines[-1] += (f"  (mean of the first 10 steps {f(s['first10_mean'])}, last 10 {f(s['last10_mean'])}, "
                      f"ratio {s['ratio']:.3f}, slope {f(s.get('slope'))}/step)")
    if s.get("val"):
        lines.append("  validation: " + ", ".join(f"{k} {f(v)}" for k, v in sorted(s["val"].items())))
    lines.append(f"  checkpoint {result.checkpoint or '-'}")
    lines.append(f"  peak RSS {result.peak_rss_mb:.0f} MB of the {budget_mb:.0f} MB budget")
    if result.outcome != "completed":
        lines.append(f"  {result.message}")
    return "\n".join(lines)
