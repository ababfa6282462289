"""The service processes keep glibc to two malloc arenas (hope_models/malloc_arenas.py): a thread per
connection would otherwise spread the heap over up to eight arenas per core, whose freed memory
is rarely returned (serve's RSS climbed under the soak's attack with no Python object kept)."""
from __future__ import annotations

import subprocess
import sys

import pytest

from daemon_fixtures import REPO

_THREADS = """
import ctypes, sys, threading
sys.path.insert(0, {repo!r})
from hope_models.malloc_arenas import limit_malloc_arenas
if {limit}:
    assert limit_malloc_arenas()
start = threading.Barrier(16)
def work():
    start.wait()  # all at once, as connections arrive
    keep = [bytearray(4096) for _ in range(2000)]
    del keep
threads = [threading.Thread(target=work) for _ in range(16)]
for t in threads: t.start()
for t in threads: t.join()
ctypes.CDLL(None).malloc_stats()  # one "Arena N:" block per arena, on stderr
"""


def _arenas(limit: bool) -> int:
    out = subprocess.run([sys.executable, "-c", _THREADS.format(repo=str(REPO), limit=limit)],
                         capture_output=True, text=True, timeout=60)
    assert out.returncode == 0, out.stderr
    return sum(1 for line in out.stderr.splitlines() if line.startswith("Arena "))


@pytest.mark.skipif(not sys.platform.startswith("linux"), reason="glibc's mallopt")
def test_sixteen_threads_share_two_arenas_in_a_service_process():
    assert _arenas(limit=False) > 2, "the default spreads threads over more arenas (else this test shows nothing)"
    assert _arenas(limit=True) <= 2
