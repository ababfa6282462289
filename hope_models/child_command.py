"""The command line of a child process this package starts: `python -m <module> ...`.

Every child (a training job's `train`, the gate's `promote`, the sim reflex's `eval-reflex`, the
demo's steps, the Celery worker) runs with the interpreter of its parent and names its entry point
as a module, never a script path: an installed wheel has no `run_trainer.py`, and a module is found
from any working directory, so no child needs the checkout as its cwd. The module is a string here,
not an import, so this lowest layer can start the top layer's commands.
"""
from __future__ import annotations

import sys

TRAINER_MODULE = "hope_trainer"  # `python -m hope_trainer <verb>` is `hope-trainer <verb>`


def module_argv(module: str, *args: str, python: str | None = None) -> list[str]:
    """`[python, "-m", module, *args]`, with this process's interpreter unless `python` says otherwise."""
    return [python or sys.executable, "-m", module, *args]


def trainer_argv(*args: str, python: str | None = None) -> list[str]:
    """The argv of a `hope-trainer <args>` child, e.g. trainer_argv("promote", run_id, "--json")."""
    return module_argv(TRAINER_MODULE, *args, python=python)


__all__ = ["TRAINER_MODULE", "module_argv", "trainer_argv"]
