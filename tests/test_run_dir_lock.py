"""The run-dir lock (hope_models/train/run_dir_lock.py): one holder at a time, across processes."""
from __future__ import annotations

import os
import subprocess
import sys
import threading
import time
from pathlib import Path

import pytest

from hope_models.train.run_dir_lock import LOCK_NAME, RunDirBusy, RunDirLock, is_free, wait_until_free

ROOT = Path(__file__).resolve().parents[1]

# The other process: takes the lock, says so, holds it until its stdin closes.
HOLDER = """
import sys
from hope_models.train.run_dir_lock import RunDirLock
with RunDirLock(sys.argv[1]):
    print("held", flush=True)
    sys.stdin.read()
"""


@pytest.fixture
def holder(tmp_path):
    procs = []

    def start():
        p = subprocess.Popen([sys.executable, "-c", HOLDER, str(tmp_path)], cwd=ROOT, text=True,
                             stdin=subprocess.PIPE, stdout=subprocess.PIPE)
        procs.append(p)
        assert p.stdout.readline().strip() == "held"
        return p

    yield start
    for p in procs:
        if p.poll() is None:
            p.kill()
        p.wait(timeout=10)


def release(p: subprocess.Popen) -> None:
    p.stdin.close()
    assert p.wait(timeout=10) == 0


def test_a_second_holder_is_refused_while_another_process_holds_it(tmp_path, holder):
    p = holder()
    assert (tmp_path / LOCK_NAME).read_text().strip() == str(p.pid)
    assert not is_free(tmp_path)
    with pytest.raises(RunDirBusy) as exc:
        RunDirLock(tmp_path).acquire()
    assert exc.value.holder == str(p.pid)
    assert "in use by another training job" in str(exc.value) and f"pid {p.pid}" in str(exc.value)
    release(p)
    assert is_free(tmp_path)
    with RunDirLock(tmp_path) as lock:  # free once the holder has gone
        assert lock.fd is not None and (tmp_path / LOCK_NAME).read_text().strip() == str(os.getpid())


def test_killed_holder_leaves_no_stale_lock(tmp_path, holder):
    p = holder()
    p.kill()
    p.wait(timeout=10)
    assert is_free(tmp_path)


def test_released_on_close(tmp_path, holder):
    lock = RunDirLock(tmp_path).acquire()
    with pytest.raises(RunDirBusy):  # flock is per open file description: refused in-process too
        RunDirLock(tmp_path).acquire()
    lock.release()
    assert lock.fd is None and is_free(tmp_path)
    with RunDirLock(tmp_path):
        pass
    assert is_free(tmp_path)
    p = holder()  # and another process can take it now
    release(p)


def test_no_lock_file_is_free(tmp_path):
    assert is_free(tmp_path) and wait_until_free(tmp_path, 0.0)
    assert not (tmp_path / LOCK_NAME).exists()  # the check does not create it


def test_wait_returns_once_free_and_times_out_when_not(tmp_path, holder):
    p = holder()
    t0 = time.monotonic()
    assert wait_until_free(tmp_path, 0.3, poll_s=0.05) is False
    assert time.monotonic() - t0 >= 0.3

    threading.Timer(0.3, p.stdin.close).start()
    t0 = time.monotonic()
    assert wait_until_free(tmp_path, 30.0, poll_s=0.05) is True
    assert time.monotonic() - t0 < 10
    assert p.wait(timeout=10) == 0


def test_wait_stops_when_asked_to_give_up(tmp_path, holder):
    holder()
    give_up = threading.Event()
    threading.Timer(0.2, give_up.set).start()
    t0 = time.monotonic()
    assert wait_until_free(tmp_path, 30.0, give_up, poll_s=0.05) is False
    assert time.monotonic() - t0 < 10


def test_importing_it_stays_torch_free():
    code = ("import sys, hope_models.train.run_dir_lock, workers.job; "
            "sys.exit('torch' in sys.modules)")
    assert subprocess.run([sys.executable, "-c", code], cwd=ROOT).returncode == 0
