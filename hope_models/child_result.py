"""A `hope-trainer` child's result: a JSON object the child writes to the file its parent names.

    parent:  with result_file() as path:
                 proc = subprocess.run(trainer_argv("promote", run_id, *result_argv(path)))
                 outcome = read_result(path, proc.args, proc.returncode)   # or ChildResultError
    child:   add_result_argument(parser)          # --result-file PATH
             write_result(args.result_file, out)  # at the end, whatever the outcome

The parent passes `--result-file PATH` (a flag, not an environment variable: it shows in the
child's argv and logs, a grandchild does not inherit it, and a command that cannot report refuses
it as a usage error instead of leaving the parent waiting for a file). The child writes its result
there atomically (durable.atomic_write), so the parent sees the whole object or no file. The
parent reads it with a bound on its size; a missing, oversized or unreadable file is a
ChildResultError naming the child's command and its exit code. Stdout is not part of it: the
children's `--json` line stays for people and scripts, and whatever else they print (frames,
progress, libraries' warnings) cannot be taken for a result. Used by the sequential trainer, the
daemon's auto-promoter, the webapp and the demo; it sits at the bottom of the package beside
child_command.py, which builds those children's argv.
"""
from __future__ import annotations

import argparse
import json
import shutil
import sys
import tempfile
from contextlib import contextmanager
from pathlib import Path
from typing import Any, Iterator, Sequence

from hope_models.child_command import TRAINER_MODULE
from hope_models.durable import atomic_write

RESULT_FLAG = "--result-file"
MAX_RESULT_BYTES = 4 << 20  # a result is a summary (eval-reflex's per-episode rows at most), never frames


class ChildResultError(RuntimeError):
    """A child left no readable result: the message names its command and how it exited."""


# -- the child's side -------------------------------------------------------------------------------

def add_result_argument(parser: argparse.ArgumentParser) -> None:
    parser.add_argument(RESULT_FLAG, dest="result_file", metavar="PATH", default=None,
                        help="also write the result as one JSON object to PATH (atomically, at the end); "
                             "how the processes that start this command read its outcome")


def write_result(path: str | Path | None, result: dict[str, Any]) -> None:
    """Write `result` to `path` atomically (nothing when `path` is None). A failure is said on stderr,
    not raised: the command's exit code stays its own, and the parent reports the missing file."""
    if path is None:
        return
    try:
        atomic_write(path, json.dumps(result))
    except (OSError, TypeError, ValueError) as exc:
        print(f"error: cannot write the result to {RESULT_FLAG} {path}: {exc}", file=sys.stderr)


# -- the parent's side ------------------------------------------------------------------------------

def result_argv(path: str | Path) -> list[str]:
    """The arguments that ask a child to write its result to `path`."""
    return [RESULT_FLAG, str(path)]


@contextmanager
def result_file(prefix: str = "hope-result-") -> Iterator[Path]:
    """A path for one child's result in a fresh private directory, removed with it afterwards."""
    folder = Path(tempfile.mkdtemp(prefix=prefix))
    try:
        yield folder / "result.json"
    finally:
        shutil.rmtree(folder, ignore_errors=True)


def command_text(argv: Sequence[str]) -> str:
    """A child's command as a person would type it: `hope-trainer promote r1 --json` (without the
    interpreter and without the result file's own flag)."""
    args = [str(a) for a in argv]
    if len(args) >= 3 and args[1:3] == ["-m", TRAINER_MODULE]:
        args = ["hope-trainer", *args[3:]]
    if RESULT_FLAG in args:
        i = args.index(RESULT_FLAG)
        del args[i:i + 2]
    return " ".join(args)


def how_it_exited(code: int | None) -> str:
    if code is None:
        return "did not exit (stopped)"
    if code < 0:
        return f"was killed by signal {-code} (exit code {code})"
    return f"exited with code {code}"


def read_result(path: str | Path, argv: Sequence[str], code: int | None) -> dict[str, Any]:
    """The JSON object a child wrote to `path`, or ChildResultError naming `argv` and its exit `code`."""
    path = Path(path)
    child = f"`{command_text(argv)}` {how_it_exited(code)}"
    try:
        with open(path, "rb") as f:
            data = f.read(MAX_RESULT_BYTES + 1)
    except FileNotFoundError:
        raise ChildResultError(f"{child} without a result (it wrote nothing to {path})") from None
    except OSError as exc:
        raise ChildResultError(f"{child}; its result {path} cannot be read: {exc}") from None
    if len(data) > MAX_RESULT_BYTES:
        raise ChildResultError(f"{child}; its result {path} is larger than {MAX_RESULT_BYTES} bytes")
    try:
        obj = json.loads(data.decode("utf-8"))
    except (UnicodeDecodeError, json.JSONDecodeError) as exc:
        raise ChildResultError(f"{child}; its result {path} is not JSON: {exc}") from None
    if not isinstance(obj, dict):
        raise ChildResultError(f"{child}; its result {path} is a JSON {type(obj).__name__}, not an object")
    return obj


__all__ = ["ChildResultError", "MAX_RESULT_BYTES", "RESULT_FLAG", "add_result_argument", "command_text",
           "read_result", "result_argv", "result_file", "write_result"]
