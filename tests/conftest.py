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
