"""OpenMP's idle threads wait passively in the processes that start torch jobs (hope_models/omp_wait.py):
the command line and the worker parent set OMP_WAIT_POLICY before any torch loads, unless the user did."""
from __future__ import annotations

import json
import os
import subprocess
import sys
from pathlib import Path

from hope_models.omp_wait import passive_waits

REPO = Path(__file__).resolve().parents[1]


def test_passive_unless_the_user_chose():
    env: dict[str, str] = {}
    assert passive_waits(env) == "PASSIVE" and env == {"OMP_WAIT_POLICY": "PASSIVE"}
    mine = {"OMP_WAIT_POLICY": "ACTIVE"}
    assert passive_waits(mine) == "ACTIVE" and mine == {"OMP_WAIT_POLICY": "ACTIVE"}


CHILD = r"""
import json, os, sys
from hope_trainer.cli import main
try:
    main(["sim-demos", "--help"])
except SystemExit:
    pass
cli = os.environ.get("OMP_WAIT_POLICY")
del os.environ["OMP_WAIT_POLICY"]
import workers.celery as w
w._private_files()
print(json.dumps({"cli": cli, "worker": os.environ.get("OMP_WAIT_POLICY"), "torch": "torch" in sys.modules}))
"""


def test_the_command_line_and_the_worker_parent_set_it_before_torch():
    env = {k: v for k, v in os.environ.items() if k != "OMP_WAIT_POLICY"}
    proc = subprocess.run([sys.executable, "-c", CHILD], cwd=REPO, capture_output=True, text=True, env=env,
                          timeout=120)
    assert proc.returncode == 0, proc.stderr[-2000:]
    out = json.loads(proc.stdout.strip().splitlines()[-1])
    assert out == {"cli": "PASSIVE", "worker": "PASSIVE", "torch": False}
