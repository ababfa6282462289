import fcntl
import os
import shutil
from pathlib import Path
from typing import Callable

import pytest

REPO_ROOT = Path(__file__).resolve().parents[1]
SAMPLES = Path(os.environ.get("HOPE_SAMPLES_DIR", REPO_ROOT.parent / "shared" / "rlds_samples" / "continuon"))

if os.environ.get("PYTEST_XDIST_WORKER"):
    # `make test` runs a worker per core: torch's default of a thread per core in each worker makes
    # every small op of one wait on the other's busy core (a 300-step test: 38 s instead of 3.3).
    # Set before any test module imports torch; the commands a test starts inherit it, and the
    # training jobs among them still set their own thread count.
    os.environ.setdefault("OMP_NUM_THREADS", "1")


def pytest_configure(config):
    # here, not in pyproject.toml's markers: a change there makes `make` reinstall the venv
    config.addinivalue_line("markers", "heavy: minutes of training on full-length episodes; not in `make test` "
                                       "(`make test-heavy` runs them)")


@pytest.fixture(scope="session")
def repo_root() -> Path:
    return REPO_ROOT


@pytest.fixture(scope="session")
def samples_dir() -> Path:
    # The real Continuon samples ship beside the repo (../shared); CI always has them, so a
    # missing dir is a setup error, not a reason to skip.
    if not SAMPLES.is_dir():
        pytest.fail(f"sample episodes not found at {SAMPLES}; set HOPE_SAMPLES_DIR or put ../shared beside the repo")
    return SAMPLES


@pytest.fixture
def torch_one_thread():
    """One thread and deterministic kernels for the test, restored afterwards (torch imported lazily,
    so tests that never touch torch do not pay for it)."""
    import torch

    threads, det = torch.get_num_threads(), torch.are_deterministic_algorithms_enabled()
    torch.set_num_threads(1)
    torch.use_deterministic_algorithms(True)
    yield
    torch.set_num_threads(threads)
    torch.use_deterministic_algorithms(det)


def shared_build(tmp_path_factory, name: str, build: Callable[[Path], None]) -> Path:
    """A directory built once per test run by `build(dir)`, even when pytest-xdist runs the tests in
    several workers (`make test` does): the first worker to ask builds it under a file lock in the
    run's shared temp root, the others wait for it and reuse it. What is built there is read-only
    for the tests, as a session-wide fixture is."""
    root = tmp_path_factory.getbasetemp()
    if os.environ.get("PYTEST_XDIST_WORKER"):
        root = root.parent  # .../pytest-N/popen-gw0 -> .../pytest-N, shared by the workers
    target = root / f"shared-{name}"
    with open(root / f"shared-{name}.lock", "w") as lock:
        fcntl.flock(lock, fcntl.LOCK_EX)
        try:
            if not (target / ".built").exists():
                shutil.rmtree(target, ignore_errors=True)  # a build that failed half-way
                target.mkdir()
                build(target)
                (target / ".built").touch()
        finally:
            fcntl.flock(lock, fcntl.LOCK_UN)
    return target
