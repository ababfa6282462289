import os
from pathlib import Path

import pytest

REPO_ROOT = Path(__file__).resolve().parents[1]
SAMPLES = Path(os.environ.get("HOPE_SAMPLES_DIR", REPO_ROOT.parent / "shared" / "rlds_samples" / "continuon"))


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
