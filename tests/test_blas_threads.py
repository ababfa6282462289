"""BrainService puts NumPy's OpenBLAS on one thread for its own process only (hope_models/runtime/blas_threads.py).

Measured in a fresh interpreter without OPENBLAS_NUM_THREADS, GOTO_NUM_THREADS or OMP_NUM_THREADS
(conftest sets the last), where OpenBLAS starts with a thread per core; a child it starts with its
own environment keeps that default.
"""
from __future__ import annotations

import json
import logging
import os
import subprocess
import sys
import textwrap
from pathlib import Path

import pytest

from hope_models.runtime import blas_threads

ROOT = Path(__file__).resolve().parents[1]
THREAD_VARS = ("OPENBLAS_NUM_THREADS", "GOTO_NUM_THREADS", "OMP_NUM_THREADS")

# The getter is the one blas_threads found (numpy_openblas()), so the figures are the library's own.
SCRIPT = textwrap.dedent("""
    import json, os, subprocess, sys
    from hope_models.runtime import blas_threads
    from hope_models.runtime.brain_service import BrainService

    lib = blas_threads.numpy_openblas()
    before = lib.threads()
    brain = BrainService(sys.argv[1])
    child = subprocess.run([sys.executable, "-c", sys.argv[2]], env=os.environ, capture_output=True,
                           text=True, timeout=30, check=True)
    print(json.dumps({"before": before, "after": lib.threads(), "reported": brain.blas_threads.after,
                      "library": brain.blas_threads.library, "env": os.environ.get("OPENBLAS_NUM_THREADS"),
                      "child": json.loads(child.stdout)}))
""")
CHILD = ("import json, os; from hope_models.runtime import blas_threads; "
         "print(json.dumps({'env': os.environ.get('OPENBLAS_NUM_THREADS'), "
         "'threads': blas_threads.numpy_openblas().threads()}))")


def _cores() -> int:
    return len(os.sched_getaffinity(0)) if hasattr(os, "sched_getaffinity") else (os.cpu_count() or 1)


@pytest.mark.skipif(not sys.platform.startswith("linux"), reason="finds the library through /proc/self/maps")
def test_brain_service_limits_its_own_blas_not_its_childrens(tmp_path):
    if _cores() < 2:
        pytest.skip("one core: OpenBLAS's default is already 1 thread, the limit could not be told apart")
    if not isinstance(blas_threads.numpy_openblas(), blas_threads.OpenBlas):
        pytest.skip(f"NumPy here uses no OpenBLAS: {blas_threads.numpy_openblas()}")
    env = {k: v for k, v in os.environ.items() if k not in THREAD_VARS}
    env["PYTHONPATH"] = os.pathsep.join([str(ROOT), env.get("PYTHONPATH", "")]).rstrip(os.pathsep)
    out = subprocess.run([sys.executable, "-c", SCRIPT, str(tmp_path), CHILD], env=env, cwd=ROOT,
                         capture_output=True, text=True, timeout=60)
    assert out.returncode == 0, out.stderr
    got = json.loads(out.stdout.strip().splitlines()[-1])
    assert got["before"] >= 2, got  # OpenBLAS's default, a thread per core: the limit is told apart from it
    assert got["after"] == got["reported"] == 1, got
    assert "openblas" in Path(got["library"]).name.lower(), got
    assert got["env"] is None, got  # nothing exported ...
    assert got["child"] == {"env": None, "threads": got["before"]}, got  # ... so a child keeps the default


def test_no_openblas_is_logged_and_claims_nothing(monkeypatch, caplog, tmp_path):
    maps = tmp_path / "maps"
    maps.write_text("7f00-7f01 r--p 00000000 fe:00 1  /usr/lib/libmkl_rt.so.2\n"
                    "7f02-7f03 r--p 00000000 fe:00 2  /site/torch/lib/libopenblasp-r0.3.so\n")
    read = blas_threads.mapped_openblas
    monkeypatch.setattr(blas_threads, "mapped_openblas", lambda: read(maps))
    monkeypatch.setattr(blas_threads, "_logged", set())
    with caplog.at_level(logging.INFO, logger=blas_threads.__name__):
        result = blas_threads.limit_numpy_blas_threads()
    assert (result.library, result.before, result.after) == (None, None, None)
    assert "no OpenBLAS of NumPy's" in result.note and "torch" in result.note  # torch's is named, not touched
    assert [r.getMessage() for r in caplog.records] == [result.note]


def test_mapped_openblas_reads_paths_with_spaces_and_skips_deleted(tmp_path):
    maps = tmp_path / "maps"
    maps.write_text("7f00-7f01 r-xp 00000000 fe:00 1   /opt/my env/numpy.libs/libscipy_openblas64_-ab.so\n"
                    "7f01-7f02 r--p 00001000 fe:00 1   /opt/my env/numpy.libs/libscipy_openblas64_-ab.so\n"
                    "7f03-7f04 r--p 00000000 fe:00 3   /tmp/libopenblas.so (deleted)\n"
                    "7f05-7f06 rw-p 00000000 00:00 0 \n")
    assert blas_threads.mapped_openblas(maps) == ["/opt/my env/numpy.libs/libscipy_openblas64_-ab.so"]
    assert blas_threads.mapped_openblas(tmp_path / "absent") is None
