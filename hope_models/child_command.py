"""The command line of a child process this package starts: `python -m <module> ...`.

Every child (a training job's `train`, the gate's `promote`, the sim reflex's `eval-reflex`, the
demo's steps, the Celery worker) runs with the interpreter of its parent and names its entry point
as a module, never a script path: an installed wheel has no `run_trainer.py`, and a module is found
from any working directory, so no child needs the checkout as its cwd. The module is a string here,
not an import, so this lowest layer can start the top layer's commands.
"""
from __future__ import annotations

import os
import subprocess
import sys
import time

TRAINER_MODULE = "hope_trainer"  # `python -m hope_trainer <verb>` is `hope-trainer <verb>`


def module_argv(module: str, *args: str, python: str | None = None) -> list[str]:
    """`[python, "-m", module, *args]`, with this process's interpreter unless `python` says otherwise."""
    return [python or sys.executable, "-m", module, *args]


def trainer_argv(*args: str, python: str | None = None) -> list[str]:
    """The argv of a `hope-trainer <args>` child, e.g. trainer_argv("promote", run_id, "--json")."""
    return module_argv(TRAINER_MODULE, *args, python=python)


# Runs a long-lived child (the worker, the inference door) under PR_SET_PDEATHSIG, so it gets SIGTERM
# if its parent dies without stopping it (SIGKILL, OOM): an orphaned worker would keep taking jobs
# next to the next serve's worker, an orphaned door would hold the robot's port. Set in a tiny exec
# wrapper instead of preexec_fn, which is unsafe in a threaded parent.
_PDEATHSIG_WRAPPER = (
    "import ctypes, os, signal, sys\n"
    "try:\n"
    "    ctypes.CDLL(None, use_errno=True).prctl(1, int(signal.SIGTERM))  # PR_SET_PDEATHSIG\n"
    "except (OSError, AttributeError):\n"
    "    pass  # not Linux: the supervisor still stops the child on a clean exit\n"
    "if os.getppid() != int(sys.argv[1]):\n"
    "    sys.exit(0)  # the parent died before we got here\n"
    "os.execv(sys.argv[2], sys.argv[2:])\n"
)


def dies_with_parent(argv: list[str]) -> list[str]:
    """`argv` (argv[0] a path to an executable) run so that it gets SIGTERM when this process dies."""
    return [sys.executable, "-c", _PDEATHSIG_WRAPPER, str(os.getpid()), *argv]


def end_child(proc: subprocess.Popen, timeout: float) -> None:
    """SIGTERM, up to `timeout` seconds for it to exit, then SIGKILL; reaped either way."""
    if proc.poll() is None:
        proc.terminate()
        try:
            proc.wait(timeout)
        except subprocess.TimeoutExpired:
            proc.kill()
            proc.wait()


__all__ = ["TRAINER_MODULE", "dies_with_parent", "end_child", "module_argv", "trainer_argv"]


class RestartBackoff:
    """How long a supervisor waits before starting a child again: the next of `delays` after each
    quick death, the first again once the child had stayed up `stable_s` (the worker under serve,
    the inference door)."""

    def __init__(self, delays: tuple[float, ...], stable_s: float = 60.0):
        self.delays, self.stable_s = delays, stable_s
        self.failures = 0

    def after_exit(self, started: float) -> float:
        """The delay after a child that ran since `started` (time.monotonic()) exited."""
        self.failures = 0 if time.monotonic() - started >= self.stable_s else self.failures + 1
        return self.delay()

    def after_failed_start(self) -> float:
        """The delay after a child that could not even be started."""
        self.failures += 1
        return self.delay()

    def delay(self) -> float:
        return self.delays[min(self.failures, len(self.delays) - 1)]
