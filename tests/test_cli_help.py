"""Every registered command must import and declare its arguments (a missing module breaks --help)."""
import subprocess
import sys
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))

from run_trainer import COMMANDS  # noqa: E402


def test_help_lists_every_command():
    proc = subprocess.run([sys.executable, str(REPO / "run_trainer.py"), "--help"], capture_output=True, text=True,
                          timeout=120)
    assert proc.returncode == 0, proc.stderr
    for name in COMMANDS:
        assert name in proc.stdout


def test_light_commands_do_not_import_torch():
    # validate/ingest/dataset run on the daemon side of the house: they must not pay for torch
    code = ("import sys, run_trainer; run_trainer.build_parser(); "
            "print('torch' in sys.modules)")
    proc = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, cwd=REPO, timeout=120)
    assert proc.returncode == 0, proc.stderr
    assert proc.stdout.strip() == "False"
