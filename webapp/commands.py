"""`hope-trainer` commands the webapp runs as child processes, because they need torch.

The webapp never imports torch (it shares a process with the daemon under `serve`, and the idle
budget is 400 MB; torch alone is ~250 MB). The promotion gate (`promote`, validation loss) and the
sim reflex (`eval-reflex`) therefore run as `python -m hope_trainer ... --json` children: the
same code path as the shell, their memory goes back to the OS when they exit, and their answer is
the JSON object they write to the `--result-file` this module gives them (hope_models/child_result.py);
their stdout is only passed to a caller's line consumer (eval-reflex's frames), never parsed for it.

Children get HOPE_HOME from the app's settings (tests build settings without touching os.environ),
one torch thread, and their own session, so the terminal's Ctrl-C reaches `serve` only, which then
stops them in order (ChildProcesses.close).
"""
from __future__ import annotations

import logging
import os
import signal
import subprocess
import threading
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Callable

from hope_models.child_command import trainer_argv
from hope_models.child_result import ChildResultError, read_result, result_argv, result_file

log = logging.getLogger(__name__)

STDERR_TAIL = 2000  # characters of a failed child's stderr kept for the error message


def child_env(settings: Any) -> dict[str, str]:
    env = dict(os.environ)
    env.update({"HOPE_HOME": str(settings.home), "PYTHONUNBUFFERED": "1", "OMP_NUM_THREADS": "1",
                "MKL_NUM_THREADS": "1"})
    return env


def error_line(stderr: str) -> str:
    """The child's own `error: ...` line if it printed one, else the tail of its stderr."""
    lines = [ln.strip() for ln in stderr.splitlines() if ln.strip()]
    for line in reversed(lines):
        if line.startswith("error:"):
            return line[len("error:"):].strip()
    return "\n".join(lines)[-STDERR_TAIL:]


@dataclass
class ChildResult:
    argv: list[str]
    code: int | None  # None: killed (timeout, shutdown)
    output: dict[str, Any] | None  # the JSON object the child wrote to its --result-file; None: see result_error
    stderr: str
    elapsed_s: float
    timed_out: bool = False
    result_error: str | None = None  # why there is no output: the command and how it exited

    def error(self) -> str:
        if isinstance(self.output, dict) and isinstance(self.output.get("error"), str):
            return self.output["error"]
        line = error_line(self.stderr)
        if self.output is None and self.result_error:
            return f"{self.result_error}: {line}" if line else self.result_error
        return line or f"exit code {self.code}"


class ChildProcesses:
    """Starts children and remembers the live ones, so the app's shutdown can stop them."""

    def __init__(self, settings: Any):
        self.settings = settings
        self._live: set[subprocess.Popen] = set()
        self._lock = threading.Lock()
        self._closed = False

    def run(self, args: list[str], *, timeout_s: float,
            on_line: Callable[[str], bool] | None = None) -> ChildResult:
        """Run `hope-trainer <args>` to the end (blocking the calling thread). With `on_line`,
        stdout is read line by line while the child runs and each line is passed to it (e.g.
        eval-reflex's frame lines; its True/False return is no longer needed). `output` is what the child
        wrote to its --result-file, never a stdout line."""
        return self._run_streaming(args, timeout_s, on_line or (lambda _line: False))

    def _run_streaming(self, args: list[str], timeout_s: float, on_line: Callable[[str], bool]) -> ChildResult:
        with result_file("hope-child-") as path:
            return self._run_with_result(args, timeout_s, on_line, path)

    def _run_with_result(self, args: list[str], timeout_s: float, on_line: Callable[[str], bool],
                         result_path: Path) -> ChildResult:
        argv = trainer_argv(*args, *result_argv(result_path))
        started = time.monotonic()
        with self._lock:
            if self._closed:
                return ChildResult(argv, None, None, "the webapp is shutting down", 0.0)
            proc = subprocess.Popen(argv, stdin=subprocess.DEVNULL, stdout=subprocess.PIPE, stderr=subprocess.PIPE,
                                    text=True, bufsize=1, env=child_env(self.settings), start_new_session=True)
            self._live.add(proc)
        log.info("started %s (pid %d)", " ".join(args), proc.pid)
        stdout, stderr = proc.stdout, proc.stderr
        assert stdout is not None and stderr is not None  # both PIPE
        err: list[str] = []

        def read_stdout() -> None:  # drained to the end: a child must never block on a full pipe
            for line in stdout:
                try:
                    on_line(line)
                except Exception:  # noqa: BLE001 - a bad consumer must not stall the child on a full pipe
                    log.exception("%s: the stdout consumer failed on a line", " ".join(args))

        def read_stderr() -> None:
            err.extend(stderr)

        readers = [threading.Thread(target=read_stdout, name=f"child-{proc.pid}-out", daemon=True),
                   threading.Thread(target=read_stderr, name=f"child-{proc.pid}-err", daemon=True)]
        for t in readers:
            t.start()
        timed_out = False
        try:
            try:
                proc.wait(timeout=timeout_s)
            except subprocess.TimeoutExpired:
                timed_out = True
                self._kill(proc)
                proc.wait()
            for t in readers:
                t.join(timeout=10)
        finally:
            with self._lock:
                self._live.discard(proc)
            for stream in (stdout, stderr):
                try:
                    stream.close()
                except OSError:
                    pass
        code = None if timed_out or proc.returncode < 0 else proc.returncode
        try:
            output, problem = read_result(result_path, argv, proc.returncode), None
        except ChildResultError as exc:
            output, problem = None, str(exc)
        result = ChildResult(argv, code, output, "".join(err), round(time.monotonic() - started, 3), timed_out,
                             problem)
        log.info("%s finished: exit %s in %.1f s", " ".join(args), proc.returncode, result.elapsed_s)
        return result

    @staticmethod
    def _kill(proc: subprocess.Popen) -> None:
        try:
            os.killpg(proc.pid, signal.SIGKILL)
        except (ProcessLookupError, PermissionError):
            pass

    def close(self, timeout_s: float = 5.0) -> None:
        """SIGTERM every live child, SIGKILL what is left after `timeout_s`."""
        with self._lock:
            self._closed = True
            live = list(self._live)
        for proc in live:
            try:
                os.killpg(proc.pid, signal.SIGTERM)
            except (ProcessLookupError, PermissionError):
                pass
        deadline = time.monotonic() + timeout_s
        for proc in live:
            try:
                proc.wait(max(0.0, deadline - time.monotonic()))
            except subprocess.TimeoutExpired:
                self._kill(proc)


__all__ = ["ChildProcesses", "ChildResult", "child_env", "trainer_argv"]
