"""Auto-promotion: gate every run that completes, one `run_trainer.py promote` child at a time, and
finish the reflex checks after serving that a dead process left owed.

    promoter = AutoPromoter(settings, registry)
    promoter.tick()      # from the daemon's loop; returns at once
    promoter.close()     # at shutdown: stops a gate still running

Each tick: if a promote child is running, nothing else happens (one gate at a time; the tick never
waits for it). When it has exited, its outcome (the JSON object it wrote to its --result-file,
hope_models/child_result.py) becomes a `log` event on the
run ("auto-promote: promoted ...", "auto-promote: the gate refused ...: <reasons>") and a line in
$HOPE_HOME/logs/promote.log, which also collects the child's stdout and stderr. Then:

1. an owed check first (registry/gating.py owed_checks): a model served with its reflex check after
   serving deferred and never recorded, because the process running it (a worker child's gate, a
   `promote` child) died during it: a SIGKILL, a power cut. Such a model answers the robot now,
   unchecked, so when the promote lock is free (nobody is running that check) the tick starts
   `run_trainer.py promote --finish-checks --json` before gating anything else; the child runs the
   check and rolls the model back when it fails. This runs whether or not settings.auto_promote is
   on: it finishes a check a promotion already started. A model whose finishing child failed
   without recording a verdict is not tried again by this process (the next start tries it);
2. then, when settings.auto_promote is on, the next run to gate is chosen and
   `run_trainer.py promote RUN --auto --json` is started for it.

Which runs: completed runs with no row in the models table yet that finished after the newest run
that has one (the watermark lives in the registry, so it survives restarts: a run that completed
while the daemon was down is gated at the next start). With no row at all yet, only runs finishing
after this AutoPromoter was created count, so upgrading a registry full of old runs does not gate
them all. Oldest first. A run whose child failed without recording anything (exit 2, a crash) is
not retried by this process; its log event says why, and `run_trainer.py promote RUN` retries by
hand. The daemon never imports torch: the gate runs in the child.
"""
from __future__ import annotations

import logging
import os
import subprocess
import sys
from dataclasses import dataclass
from datetime import datetime
from pathlib import Path
from typing import Any, Callable

from sqlalchemy import exists, func, select

from hope_models.child_command import end_child, trainer_argv
from hope_models.child_result import ChildResultError, read_result, result_argv
from hope_models.log_limits import rotate_if_over
from hope_models.settings import GATE_ENV
from registry import runs
from registry.gating import PROMOTE_LOG as LOG_FILE
from registry.gating import describe_finished, owed_checks, promote_lock_busy
from registry.gating import describe_outcome as describe
from registry.models import Model, Run, utcnow

log = logging.getLogger(__name__)

STOP_TIMEOUT_S = 10.0


@dataclass(frozen=True)
class OwedCheck:
    """A served model whose reflex check after serving is owed (registry/gating.py owes_check)."""
    model_id: int
    run_id: str | None
    what: str  # "fast_loop <version> (model <id>)"


class AutoPromoter:
    def __init__(self, settings: Any, registry: Any, *, python: str = sys.executable,
                 clock: Callable[[], datetime] = utcnow, extra_args: tuple[str, ...] = ()):
        self.settings = settings
        self.registry = registry
        self.python = python
        self.clock = clock
        self.extra_args = tuple(extra_args)  # e.g. ("--threads", "2")
        self.started_at = clock()
        self.logs_dir = Path(settings.home) / "logs"
        self._proc: subprocess.Popen | None = None
        self._run_id: str | None = None  # the run the child gates, or None
        self._checks: list[OwedCheck] = []  # the owed checks the child finishes, or []
        self._out_path: Path | None = None  # the child's --result-file
        self._argv: list[str] = []
        self._attempted: set[str] = set()
        self._checked: set[int] = set()  # models whose owed check a child was started for
        self._failures = 0
        self.last_outcome: dict[str, Any] | None = None  # what the last child said (tests, status)

    @property
    def busy(self) -> bool:
        return self._proc is not None

    @property
    def current_run(self) -> str | None:
        """The run the child judges: the one it gates, or the run of the model whose check it finishes."""
        if self._run_id is not None:
            return self._run_id
        return next((c.run_id for c in self._checks if c.run_id is not None), None)

    # -- the tick -----------------------------------------------------------------------------

    def tick(self) -> None:
        """Never raises: a failing auto-promotion must not stop the daemon's loop (logged once per streak)."""
        try:
            self._tick()
        except Exception:  # noqa: BLE001
            self._failures += 1
            if self._failures == 1 or self._failures % 100 == 0:
                log.exception("auto-promote tick failed (%d in a row)", self._failures)
            return
        self._failures = 0

    def _tick(self) -> None:
        if self._proc is not None:
            if self._proc.poll() is None:
                return
            self._collect()
        owed = self.next_checks()
        if owed:
            # The lock held: the check is running now in the process that holds it, or another gate
            # runs, after which this one comes before the next run's gate.
            if not promote_lock_busy(Path(self.settings.home)):
                self._spawn_checks(owed)
            return
        if not self.settings.auto_promote:
            return
        run_id = self.next_run()
        # The lock held: a gate runs elsewhere, often in the worker child that trained this very
        # run (workers/warm_gate.py); a child spawned now would only wait for it, then skip.
        if run_id is not None and not promote_lock_busy(Path(self.settings.home)):
            self._spawn(run_id)

    def next_checks(self) -> list[OwedCheck]:
        """The owed checks (module doc) no child of this process was started for yet."""
        with self.registry.session(readonly=True) as s:
            return [OwedCheck(m.id, m.run_id, f"{m.component} {m.version} (model {m.id})")
                    for m in owed_checks(s) if m.id not in self._checked]

    def next_run(self) -> str | None:
        """The oldest completed run not gated yet that finished after the watermark (module doc)."""
        with self.registry.session(readonly=True) as s:
            gated = select(func.max(Run.finished_at)).where(exists().where(Model.run_id == Run.id))
            watermark = s.scalar(gated)
            if watermark is None:
                watermark = self.started_at
            candidates = s.scalars(
                select(Run.id)
                .where(Run.state == "completed", Run.finished_at > watermark,
                       ~exists().where(Model.run_id == Run.id))
                .order_by(Run.finished_at, Run.id)
            ).all()
        for run_id in candidates:
            if run_id not in self._attempted:
                return run_id
        return None

    # -- the child ------------------------------------------------------------------------------

    def _log_line(self, text: str) -> None:
        self.logs_dir.mkdir(parents=True, exist_ok=True)
        with open(self.logs_dir / LOG_FILE, "a", encoding="utf-8") as f:
            f.write(f"{self.clock().isoformat(timespec='seconds')} {text}\n")

    def _start(self, tag: str, args: tuple[str, ...], label: str) -> int:
        """Start `promote *args --json` writing its result to .promote-<tag>.json; its pid."""
        self.logs_dir.mkdir(parents=True, exist_ok=True)
        out_path = self.logs_dir / f".promote-{tag}.json"
        out_path.unlink(missing_ok=True)  # a stale one from a daemon that died meanwhile is not this child's result
        cmd = trainer_argv("promote", *args, "--json", *self.extra_args, python=self.python)
        # The child loads its settings from HOPE_HOME like any command; the gate's own settings are
        # passed explicitly so it gates with exactly what this daemon was configured with.
        env = {**os.environ, "HOPE_HOME": str(self.settings.home),
               **{var: str(getattr(self.settings, name)) for var, name in GATE_ENV.items()}}
        rotate_if_over(self.logs_dir / LOG_FILE, self.settings)  # a gate per completed run: it would only grow
        self._log_line(f"{label} ({' '.join(cmd[1:])})")
        argv = [*cmd, *result_argv(out_path)]
        with open(self.logs_dir / LOG_FILE, "ab") as log_file:
            # A session of its own: Ctrl-C on `serve` reaches the daemon, which stops the child in close().
            self._proc = subprocess.Popen(argv, stdout=log_file, stderr=log_file, stdin=subprocess.DEVNULL,
                                          env=env, start_new_session=True)
        self._out_path, self._argv = out_path, argv
        return self._proc.pid

    def _spawn(self, run_id: str) -> None:
        self._attempted.add(run_id)
        pid = self._start(run_id, (run_id, "--auto"), f"run {run_id}: gating")
        self._run_id = run_id
        self._event(run_id, "info", "auto-promote: gating this run's checkpoint against the promoted model "
                                    f"(pid {pid}; log: {self.logs_dir / LOG_FILE})")
        log.info("auto-promote: gating run %s (pid %d)", run_id, pid)

    def _spawn_checks(self, owed: list[OwedCheck]) -> None:
        self._checked.update(c.model_id for c in owed)
        what = ", ".join(c.what for c in owed)
        pid = self._start("checks", ("--finish-checks",), f"{what}: finishing the reflex check interrupted "
                                                            "after serving")
        self._checks = list(owed)
        for check in owed:
            self._event(check.run_id, "warning", f"auto-promote: {check.what} is served but its reflex check after "
                                                 "serving was interrupted (its process died); running it now "
                                                 f"(pid {pid}; log: {self.logs_dir / LOG_FILE})")
        log.warning("auto-promote: finishing the interrupted reflex check of %s (pid %d)", what, pid)

    def _collect(self) -> None:
        proc, out_path = self._proc, self._out_path
        self._proc = self._out_path = None
        assert proc is not None and out_path is not None
        code = proc.returncode
        try:
            outcome, problem = read_result(out_path, self._argv, code), None
        except ChildResultError as exc:
            outcome, problem = None, str(exc)
        out_path.unlink(missing_ok=True)
        if self._checks:
            checks, self._checks = self._checks, []
            self._collect_checks(checks, code, outcome, problem)
            return
        run_id, self._run_id = self._run_id, None
        assert run_id is not None
        level, message = describe(code, outcome, problem)
        self.last_outcome = {"run_id": run_id, "exit_code": code, **(outcome or {})}
        self._log_line(f"run {run_id}: {message}")
        self._event(run_id, level, message)
        log.info("auto-promote: run %s: %s", run_id, message)

    def _collect_checks(self, checks: list[OwedCheck], code: int | None, outcome: dict[str, Any] | None,
                        problem: str | None) -> None:
        self.last_outcome = {"model_ids": [c.model_id for c in checks], "exit_code": code, **(outcome or {})}
        finished = (outcome or {}).get("finished")
        if not isinstance(finished, list):
            why = problem or f"it said: {(outcome or {}).get('error')}"
            for check in checks:
                message = (f"auto-promote: the reflex check of {check.what} was not finished: {why}; it is tried "
                           f"again when the service restarts, or `run_trainer.py promote --finish-checks`; see "
                           f"$HOPE_HOME/logs/{LOG_FILE}")
                self._log_line(message)
                self._event(check.run_id, "error", message)
                log.error("%s", message)
            return
        for entry in finished:
            level, message = describe_finished(entry)
            self._log_line(message)
            self._event(entry.get("run_id"), level, message)
            log.info("%s", message)
        done = {entry.get("model_id") for entry in finished}
        for check in checks:
            if check.model_id not in done:  # demoted, or checked by another process, before the child held the lock
                self._log_line(f"auto-promote: {check.what}: nothing to check any more")

    def _event(self, run_id: str | None, level: str, message: str) -> None:
        if run_id is None:  # a checkpoint promoted by path, outside any run: the log file has it
            return
        try:
            with self.registry.session() as s:
                runs.add_event(s, run_id, "log", {"level": level, "message": message, "source": "auto-promote"})
        except runs.RunError as exc:  # the run was deleted meanwhile: the log file still has it
            log.warning("auto-promote: cannot record an event on run %s: %s", run_id, exc)

    def close(self, timeout: float = STOP_TIMEOUT_S) -> None:
        """Stop a child still running (it has recorded nothing yet: the run is gated, the check
        finished, at the next start)."""
        proc = self._proc
        if proc is None:
            return
        end_child(proc, timeout)
        if self._out_path is not None:
            self._out_path.unlink(missing_ok=True)
        if self._checks:
            self._log_line(f"{', '.join(c.what for c in self._checks)}: check stopped (the service is stopping)")
        else:
            self._log_line(f"run {self._run_id}: gate stopped (the service is stopping)")
        self._proc = self._run_id = self._out_path = None
        self._checks = []


__all__ = ["AutoPromoter", "OwedCheck", "describe", "LOG_FILE"]
