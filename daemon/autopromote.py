"""Auto-promotion: gate every run that completes, one `run_trainer.py promote` child at a time.

    promoter = AutoPromoter(settings, registry)
    promoter.tick()      # from the daemon's loop; returns at once
    promoter.close()     # at shutdown: stops a gate still running

Each tick: if a promote child is running, nothing else happens (one gate at a time; the tick never
waits for it). When it has exited, its outcome (the JSON object it wrote to its --result-file,
hope_models/child_result.py) becomes a `log` event on the
run ("auto-promote: promoted ...", "auto-promote: the gate refused ...: <reasons>") and a line in
$HOPE_HOME/logs/promote.log, which also collects the child's stdout and stderr. Then, when
settings.auto_promote is on, the next run to gate is chosen and
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
from registry.gating import describe_outcome as describe
from registry.gating import promote_lock_busy
from registry.models import Model, Run, utcnow

log = logging.getLogger(__name__)

STOP_TIMEOUT_S = 10.0


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
        self._run_id: str | None = None
        self._out_path: Path | None = None  # the child's --result-file
        self._argv: list[str] = []
        self._attempted: set[str] = set()
        self._failures = 0
        self.last_outcome: dict[str, Any] | None = None  # what the last child said (tests, status)

    @property
    def busy(self) -> bool:
        return self._proc is not None

    @property
    def current_run(self) -> str | None:
        return self._run_id

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
        if not self.settings.auto_promote:
            return
        run_id = self.next_run()
        # The lock held: a gate runs elsewhere, often in the worker child that trained this very
        # run (workers/warm_gate.py); a child spawned now would only wait for it, then skip.
        if run_id is not None and not promote_lock_busy(Path(self.settings.home)):
            self._spawn(run_id)

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

    def _spawn(self, run_id: str) -> None:
        self._attempted.add(run_id)
        self.logs_dir.mkdir(parents=True, exist_ok=True)
        out_path = self.logs_dir / f".promote-{run_id}.json"
        out_path.unlink(missing_ok=True)  # a stale one from a daemon that died meanwhile is not this gate's result
        cmd = trainer_argv("promote", run_id, "--auto", "--json", *self.extra_args, python=self.python)
        # The child loads its settings from HOPE_HOME like any command; the gate's own settings are
        # passed explicitly so it gates with exactly what this daemon was configured with.
        env = {**os.environ, "HOPE_HOME": str(self.settings.home),
               **{var: str(getattr(self.settings, name)) for var, name in GATE_ENV.items()}}
        rotate_if_over(self.logs_dir / LOG_FILE, self.settings)  # a gate per completed run: it would only grow
        self._log_line(f"run {run_id}: gating ({' '.join(cmd[1:])})")
        argv = [*cmd, *result_argv(out_path)]
        with open(self.logs_dir / LOG_FILE, "ab") as log_file:
            # A session of its own: Ctrl-C on `serve` reaches the daemon, which stops the child in close().
            self._proc = subprocess.Popen(argv, stdout=log_file, stderr=log_file, stdin=subprocess.DEVNULL,
                                          env=env, start_new_session=True)
        self._run_id, self._out_path, self._argv = run_id, out_path, argv
        self._event(run_id, "info", "auto-promote: gating this run's checkpoint against the promoted model "
                                    f"(pid {self._proc.pid}; log: {self.logs_dir / LOG_FILE})")
        log.info("auto-promote: gating run %s (pid %d)", run_id, self._proc.pid)

    def _collect(self) -> None:
        proc, run_id, out_path = self._proc, self._run_id, self._out_path
        self._proc = self._run_id = self._out_path = None
        assert proc is not None and run_id is not None and out_path is not None
        code = proc.returncode
        try:
            outcome, problem = read_result(out_path, self._argv, code), None
        except ChildResultError as exc:
            outcome, problem = None, str(exc)
        out_path.unlink(missing_ok=True)
        level, message = describe(code, outcome, problem)
        self.last_outcome = {"run_id": run_id, "exit_code": code, **(outcome or {})}
        self._log_line(f"run {run_id}: {message}")
        self._event(run_id, level, message)
        log.info("auto-promote: run %s: %s", run_id, message)

    def _event(self, run_id: str, level: str, message: str) -> None:
        try:
            with self.registry.session() as s:
                runs.add_event(s, run_id, "log", {"level": level, "message": message, "source": "auto-promote"})
        except runs.RunError as exc:  # the run was deleted meanwhile: the log file still has it
            log.warning("auto-promote: cannot record an event on run %s: %s", run_id, exc)

    def close(self, timeout: float = STOP_TIMEOUT_S) -> None:
        """Stop a gate still running (it has recorded nothing yet; the run is gated at the next start)."""
        proc = self._proc
        if proc is None:
            return
        end_child(proc, timeout)
        if self._out_path is not None:
            self._out_path.unlink(missing_ok=True)
        self._log_line(f"run {self._run_id}: gate stopped (the service is stopping)")
        self._proc = self._run_id = self._out_path = None


__all__ = ["AutoPromoter", "describe", "LOG_FILE"]
