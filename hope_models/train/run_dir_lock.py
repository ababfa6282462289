"""The run-dir lock: one training job per run dir, an exclusive flock on `<run_dir>/.lock`.

Why: two jobs in one run dir would write the same checkpoints, `last` pointer and metrics
files, and a resume would then load a mix of both. The trainer (`train/loop.py`) holds the lock
for the job's lifetime and refuses to start when another process holds it. A worker child
(`workers/job.py`) first waits until the lock is free: a child the daemon gave up on stops at its
next control poll and leaves the checkpoint the new job resumes from.

An flock, not a pid file: the kernel drops it when the holder dies, even by SIGKILL, so a stale
lock never blocks a resume. The file holds the holder's pid, only to name it in the refusal.
flock belongs to the open file description, so a second `RunDirLock` is refused even in the same
process. Torch-free: the worker's parent imports this.
"""
from __future__ import annotations

import fcntl
import os
import threading
import time
from pathlib import Path

LOCK_NAME = ".lock"


def lock_path(run_dir: Path | str) -> Path:
    return Path(run_dir) / LOCK_NAME


class RunDirBusy(Exception):
    """Another process holds the run dir's lock; `holder` is its pid as written, or ""."""

    def __init__(self, run_dir: Path, holder: str = ""):
        self.run_dir, self.holder = run_dir, holder
        super().__init__(f"{run_dir} is in use by another training job"
                         f"{f' (pid {holder})' if holder else ''}; wait for it or stop it first")


class RunDirLock:
    """`with RunDirLock(run_dir):` holds the lock (the run dir must exist); raises RunDirBusy."""

    def __init__(self, run_dir: Path | str):
        self.path = lock_path(run_dir)
        self.fd: int | None = None

    def acquire(self) -> "RunDirLock":
        fd = os.open(self.path, os.O_RDWR | os.O_CREAT, 0o644)
        try:
            fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
        except BlockingIOError:
            holder = os.pread(fd, 32, 0).decode("ascii", "replace").strip()
            os.close(fd)
            raise RunDirBusy(self.path.parent, holder) from None
        os.ftruncate(fd, 0)
        os.pwrite(fd, f"{os.getpid()}\n".encode("ascii"), 0)
        self.fd = fd
        return self

    def release(self) -> None:
        if self.fd is not None:
            os.close(self.fd)  # closing releases the flock
            self.fd = None

    def __enter__(self) -> "RunDirLock":
        return self if self.fd is not None else self.acquire()

    def __exit__(self, *exc) -> None:
        self.release()


def is_free(run_dir: Path | str) -> bool:
    """Whether no process holds the lock now (no lock file: free). Takes and drops it at once."""
    try:
        fd = os.open(lock_path(run_dir), os.O_RDWR)
    except FileNotFoundError:
        return True
    try:
        fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
        fcntl.flock(fd, fcntl.LOCK_UN)
        return True
    except BlockingIOError:
        return False
    finally:
        os.close(fd)


def wait_until_free(run_dir: Path | str, timeout_s: float, give_up: threading.Event | None = None,
                    poll_s: float = 0.2) -> bool:
    """Wait up to timeout_s for the lock to be free (or until give_up is set); True if it is.
    It does not take the lock: the trainer takes it itself and reports a run dir still busy."""
    deadline = time.monotonic() + timeout_s
    while not (give_up is not None and give_up.is_set()):
        if is_free(run_dir):
            return True
        if time.monotonic() >= deadline:
            return False
        time.sleep(poll_s)
    return False
