"""Train several components one after the other, each in its own process; the parent holds no model.

    run_trainer.py train --sequential vqvae,fast_loop,mid_loop --data DS --run-dir R --steps N

Each component runs as `python -m hope_trainer train --component X ... --run-dir R/X --json` in a child
process, so its memory goes back to the OS when it exits and the parent stays small (it never
imports torch: see tests/test_train_sequential.py). fast_loop and mid_loop get `--vqvae` = the
newest complete checkpoint of R/vqvae (trained earlier in the sequence, or before), unless
--vqvae names another one. The parent polls each child's RSS with psutil; the peak per component
is the larger of that and the child's own report, which is the JSON object the child writes to
the `--result-file` the parent gives it (hope_models/child_result.py; its stdout is not read). The sequence stops at the first component that
does not complete, with its exit code and message. Re-running the same command resumes: finished
components return at once, an interrupted one continues from its last checkpoint.
"""
from __future__ import annotations

import argparse
import json
import signal
import subprocess
import sys
import time
from pathlib import Path
from typing import Any

import psutil

from hope_models import checkpoints as ckpt
from hope_models.checkpoint_format import VQVAE_REF
from hope_models.child_command import trainer_argv
from hope_models.child_result import ChildResultError, read_result, result_argv, result_file, write_result
from hope_models.components import COMPONENTS, NEEDS_VQVAE, TOKENIZER
from hope_models.components.chain import VQVAE_NONE, ChainStep, SequenceError, parse_sequence, plan_chain
from hope_models.train.config import flag_of, values_from_args

POLL_S = 0.2


def child_command(args: argparse.Namespace, component: str, run_dir: Path, vqvae: Path | None) -> list[str]:
    cmd = trainer_argv("train", "--component", component, "--run-dir", str(run_dir), "--json")
    cmd += ["--data", str(args.data), "--steps", str(args.steps)]
    for name, value in values_from_args(args, "train").items():
        if name not in ("run_dir", "vqvae_dir"):  # each child gets its own run dir; the vqvae below
            cmd += [flag_of(name), json.dumps(value) if isinstance(value, dict) else str(value)]
    if vqvae is not None and COMPONENTS[component].reads_codes:
        cmd += ["--vqvae", str(vqvae)]
    return cmd


def _vqvae_for(args: argparse.Namespace, root: Path) -> Path | None:
    """--vqvae, else the newest complete checkpoint of R/<tokenizer> (trained earlier in the chain, or before)."""
    if args.vqvae:
        return Path(args.vqvae)
    try:
        return ckpt.resolve_checkpoint_dir(root / TOKENIZER)
    except ckpt.CheckpointError:
        return None


def _plan(args: argparse.Namespace, names: list[str], root: Path) -> list[ChainStep]:
    """The chain's plan (components/chain.py): --vqvae is given and wins over the chain's tokenizer; a
    tokenizer trained before under R/<tokenizer> counts as given when the chain does not train one."""
    given = bool(args.vqvae) or (TOKENIZER not in names and _vqvae_for(args, root) is not None)
    return plan_chain(names, given=given, given_first=bool(args.vqvae))


def run_child(cmd: list[str]) -> dict[str, Any]:
    """Run one child to the end: its exit code, the result it wrote to its --result-file (or
    `result_error` saying why there is none), polled peak RSS and wall time. Its stderr (progress,
    warnings) goes straight to ours; its stdout (the same result for people) is not read.

    Signals: Ctrl-C in a terminal reaches the child itself (same process group), which checkpoints
    and exits paused, so the parent ignores SIGINT meanwhile (forwarding it would be a second
    Ctrl-C, which aborts); a SIGTERM to the parent (a service stop) is forwarded to the child."""
    with result_file("hope-train-") as path:
        argv = [*cmd, *result_argv(path)]
        started = time.monotonic()
        proc = subprocess.Popen(argv, stdout=subprocess.DEVNULL)

        def forward_term(signum, frame):
            if proc.poll() is None:
                proc.terminate()

        previous = {signal.SIGINT: signal.signal(signal.SIGINT, signal.SIG_IGN),
                    signal.SIGTERM: signal.signal(signal.SIGTERM, forward_term)}
        try:
            child = _watch(proc, started)
        finally:
            for sig, handler in previous.items():
                signal.signal(sig, handler)
        try:
            child["result"], child["result_error"] = read_result(path, argv, proc.returncode), None
        except ChildResultError as exc:
            child["result"], child["result_error"] = {}, str(exc)
        return child


def _watch(proc: subprocess.Popen, started: float) -> dict[str, Any]:
    peak = 0.0
    try:
        ps = psutil.Process(proc.pid)
    except psutil.NoSuchProcess:
        ps = None
    while proc.poll() is None:
        try:
            if ps is not None:
                peak = max(peak, ps.memory_info().rss / (1 << 20))
        except psutil.Error:
            pass
        try:
            proc.wait(timeout=POLL_S)
        except subprocess.TimeoutExpired:
            pass
    return {"exit_code": proc.returncode, "polled_peak_rss_mb": peak, "seconds": time.monotonic() - started}


def run_sequential(args: argparse.Namespace, settings: Any = None) -> int:
    try:
        names = parse_sequence(args.sequential)
    except SequenceError as exc:
        print(f"error: {exc}", file=sys.stderr)
        return 2
    root = Path(args.run_dir)
    if not Path(args.data).exists():
        print(f"error: --data {args.data}: no such file or directory", file=sys.stderr)
        return 2
    rows: list[dict[str, Any]] = []
    code = 0
    for step in _plan(args, names, root):
        name = step.name
        # Resolved at the member's turn: the chain's tokenizer has just written its checkpoint.
        vqvae = _vqvae_for(args, root) if step.vqvae != VQVAE_NONE else None
        if step.missing or (name in NEEDS_VQVAE and vqvae is None):
            msg = (f"{name} needs a trained VQ-VAE: put {TOKENIZER} earlier in --sequential, or pass --vqvae DIR "
                   f"(no complete checkpoint under {root / TOKENIZER})")
            rows.append({"component": name, "outcome": "error", "exit_code": 2, "message": msg})
            code = 2
            break
        cmd = child_command(args, name, root / name, vqvae)
        print(f"== {name}: {' '.join(cmd[1:])}", file=sys.stderr, flush=True)
        child = run_child(cmd)
        res = child["result"]
        reported = res.get("peak_rss_mb") or 0.0
        row = {"component": name, "outcome": res.get("outcome", "failed"), "exit_code": child["exit_code"],
               "steps": res.get("steps"), "first_loss": res.get("first_loss"), "final_loss": res.get("final_loss"),
               "checkpoint": res.get("checkpoint"), "resumed_from": res.get("resumed_from"),
               "peak_rss_mb": round(max(reported, child["polled_peak_rss_mb"]), 1),
               "child_reported_peak_rss_mb": reported, "polled_peak_rss_mb": round(child["polled_peak_rss_mb"], 1),
               "seconds": round(child["seconds"], 2), VQVAE_REF: str(vqvae) if vqvae else None}
        if res.get("message") and row["outcome"] != "completed":
            row["message"] = res["message"]
        if child["result_error"] is not None:
            row["message"] = child["result_error"]
        rows.append(row)
        if child["exit_code"] != 0:
            code = child["exit_code"] or 1
            break
    write_result(getattr(args, "result_file", None), {"exit_code": code, "components": rows})
    if getattr(args, "json", False):
        print(json.dumps(rows))
    else:
        print(format_table(rows))
    if code:
        failed = rows[-1]
        print(f"error: the sequence stopped at {failed['component']} ({failed['outcome']}): "
              f"{failed.get('message', '')}; re-run the same command to resume", file=sys.stderr)
    return code


def format_table(rows: list[dict[str, Any]]) -> str:
    def f(v, spec="{:.4g}"):
        return "-" if v is None else spec.format(v)

    head = f"{'component':<10} {'outcome':<13} {'steps':>6} {'first loss':>10} {'final loss':>10} " \
           f"{'peak RSS MB':>11} {'seconds':>8}  checkpoint"
    lines = [head]
    for r in rows:
        lines.append(f"{r['component']:<10} {r['outcome']:<13} {f(r.get('steps'), '{}'):>6} "
                     f"{f(r.get('first_loss')):>10} {f(r.get('final_loss')):>10} "
                     f"{f(r.get('peak_rss_mb'), '{:.0f}'):>11} {f(r.get('seconds'), '{:.1f}'):>8}  "
                     f"{r.get('checkpoint') or r.get('message', '-')}")
    return "\n".join(lines)
