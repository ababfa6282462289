"""A lazily started daemon thread that runs posted calls in order, and a way to wait for them.

BrainService posts its on_first_inference hook here: the webapp's hook writes to SQLite, which may
wait for the daemon's write lock, and a robot's request must never wait for that. A call that
raises is logged and the thread goes on. Torch-free.
"""
from __future__ import annotations

import logging
import queue
import threading
from typing import Any, Callable

log = logging.getLogger(__name__)


class HookThread:
    def __init__(self, name: str):
        self.name = name
        self._queue: queue.SimpleQueue = queue.SimpleQueue()
        self._pending = 0
        self._cond = threading.Condition()
        self._thread: threading.Thread | None = None

    def post(self, fn: Callable[..., Any], *args: Any) -> None:
        """Run fn(*args) on the thread (started on the first post, and again after stop)."""
        with self._cond:
            self._pending += 1
            if self._thread is None:
                self._thread = threading.Thread(target=self._run, name=self.name, daemon=True)
                self._thread.start()
        self._queue.put((fn, args))

    def _run(self) -> None:
        while True:
            item = self._queue.get()
            if item is None:
                return
            fn, args = item
            try:
                fn(*args)
            except Exception:  # a hook must never kill the thread that runs the next one
                log.exception("%s: %r failed", self.name, fn)
            finally:
                with self._cond:
                    self._pending -= 1
                    self._cond.notify_all()

    def wait(self, timeout: float = 5.0) -> bool:
        """Wait until every posted call has run. True if so within timeout."""
        with self._cond:
            return self._cond.wait_for(lambda: self._pending == 0, timeout)

    def stop(self, timeout: float = 5.0) -> None:
        """Run what is posted (within timeout), then end the thread."""
        self.wait(timeout)
        with self._cond:
            thread, self._thread = self._thread, None
        if thread is not None:
            self._queue.put(None)
            thread.join(timeout)


__all__ = ["HookThread"]
