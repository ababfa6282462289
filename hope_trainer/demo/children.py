"""The demo's `hope-trainer` children, started together and read together: the recording split
over processes, the reflex's evaluation split over seeds, or one child alone.

    group = ChildGroup([argv, argv], settings).start()   # each in its own session
    while group.running(): ...                           # the demo waits with its own sleep
    group.results()   # [(exit code, the result it wrote to its --result-file, stderr tail)]
    group.close()     # stops what still runs, removes the result files

Each child runs in its own session (Ctrl-C reaches the demo, which stops them), its stdout and
stderr appended to logs/demo-child.log; its result comes back through --result-file
(hope_models/child_result.py), never its stdout.
"""
from __future__ import annotations

import os
import shutil
import subprocess
import tempfile
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from hope_models.child_command import trainer_argv
from hope_models.child_result import read_result, result_argv
from hope_models.log_limits import rotate_if_over

STOP_WAIT_S = 10.0  # SIGTERM, then this long before SIGKILL
TAIL_LINES = 5


@dataclass
class Child:
    argv: list[str]  # the verb and its arguments, as a person types them
    full: list[str]  # what runs: the interpreter, -m hope_trainer, the argv and --result-file
    result_path: Path
    proc: subprocess.Popen | None = None


class ChildGroup:
    def __init__(self, argvs: list[list[str]], settings: Any):
        self.settings = settings
        self.log_path = Path(settings.home) / "logs" / "demo-child.log"
        self._dir = Path(tempfile.mkdtemp(prefix="hope-demo-"))
        self.children = [Child(list(argv), trainer_argv(*argv, *result_argv(self._dir / f"result-{i}.json")),
                               self._dir / f"result-{i}.json") for i, argv in enumerate(argvs)]

    def start(self) -> ChildGroup:
        env = {**os.environ, "HOPE_HOME": str(self.settings.home)}
        self.log_path.parent.mkdir(parents=True, exist_ok=True)
        rotate_if_over(self.log_path, self.settings)
        for child in self.children:
            with open(self.log_path, "ab") as log:  # the child keeps its own descriptor
                child.proc = subprocess.Popen(child.full, stdout=log, stderr=log, stdin=subprocess.DEVNULL, env=env,
                                              start_new_session=True)
        return self

    def running(self) -> bool:
        return any(c.proc is not None and c.proc.poll() is None for c in self.children)

    def what(self) -> str:
        """The verb the group runs, for a message: `eval-reflex` (x2)."""
        verbs = sorted({c.argv[0] for c in self.children})
        return "`" + "`, `".join(verbs) + "`" + (f" (x{len(self.children)})" if len(self.children) > 1 else "")

    def tail(self) -> str:
        try:
            lines = self.log_path.read_text(encoding="utf-8", errors="replace").splitlines()
        except OSError:
            return ""
        return "\n".join(lines[-TAIL_LINES:])

    def results(self) -> list[tuple[int, dict[str, Any], str]]:
        """(exit code, result, the log's tail) of each child, in the order they were given; a child
        that wrote no result is a ChildResultError naming its command and exit code."""
        tail = self.tail()
        out = []
        for c in self.children:
            assert c.proc is not None and c.proc.returncode is not None, "results() after the children exited"
            out.append((c.proc.returncode, read_result(c.result_path, c.full, c.proc.returncode), tail))
        return out

    def stop(self) -> None:
        for c in self.children:
            if c.proc is not None and c.proc.poll() is None:
                c.proc.terminate()
        for c in self.children:
            if c.proc is None:
                continue
            try:
                c.proc.wait(STOP_WAIT_S)
            except subprocess.TimeoutExpired:
                c.proc.kill()
                c.proc.wait()

    def close(self) -> None:
        self.stop()
        shutil.rmtree(self._dir, ignore_errors=True)


__all__ = ["ChildGroup"]
