"""`run_trainer.py train` as a user runs it: JSON shape, human output, exit codes, Ctrl-C, usage errors."""
from __future__ import annotations

import json
import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest

from hope_models.data.synthetic import generate_dataset

REPO = Path(__file__).resolve().parents[1]


@pytest.fixture(scope="module")
def ds(tmp_path_factory) -> Path:
    root = tmp_path_factory.mktemp("cli")
    generate_dataset(root / "ds", 2000, obs_dim=6, act_dim=2, episode_seconds=(3, 9), seed=3)
    return root


def _args(ds: Path, run_dir: Path, *extra: str, component: str = "fast_loop", steps: int = 20) -> list[str]:
    return [sys.executable, str(REPO / "run_trainer.py"), "train", "--component", component, "--data",
            str(ds / "ds"), "--run-dir", str(run_dir), "--steps", str(steps), "--seed", "0", "--batch-size", "8",
            "--threads", "1", "--cache-dir", str(ds / "cache"), *extra]


def _run(cmd: list[str], **kw) -> subprocess.CompletedProcess:
    return subprocess.run(cmd, capture_output=True, text=True, timeout=120, cwd=REPO, **kw)


def test_json_output_shape(ds, tmp_path):
    proc = _run(_args(ds, tmp_path / "r", "--json"))
    assert proc.returncode == 0, proc.stderr
    out = json.loads(proc.stdout)  # stdout is exactly one JSON object
    assert set(out) >= {"component", "steps", "first_loss", "final_loss", "checkpoint", "peak_rss_mb",
                        "resumed_from", "outcome"}
    assert out["component"] == "fast_loop" and out["steps"] == 20 and out["outcome"] == "completed"
    assert out["resumed_from"] is None and isinstance(out["first_loss"], float) and out["peak_rss_mb"] > 50
    assert Path(out["checkpoint"]) == tmp_path / "r" / "checkpoints" / "00000020"
    assert "step 20/20" in proc.stderr  # progress stays on stderr


def test_human_output(ds, tmp_path):
    proc = _run(_args(ds, tmp_path / "r", "--log-every", "5"))
    assert proc.returncode == 0, proc.stderr
    assert proc.stdout.startswith("completed: fast_loop at step 20/20")
    assert "loss " in proc.stdout and "peak RSS" in proc.stdout and "checkpoints/00000020" in proc.stdout
    progress = [ln for ln in proc.stderr.splitlines() if "steps/s" in ln]
    assert progress and "ETA" in progress[-1] and "loss" in progress[-1]


def test_ctrl_c_checkpoints_pauses_with_exit_4_and_rerun_resumes(ds, tmp_path):
    cmd = _args(ds, tmp_path / "r", "--json", "--log-every", "1", steps=100_000)
    proc = subprocess.Popen(cmd, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, cwd=REPO)
    metrics = tmp_path / "r" / "metrics.jsonl"
    deadline = time.monotonic() + 60
    while not (metrics.exists() and metrics.read_text().count('"type":"metric"') >= 5):
        assert proc.poll() is None and time.monotonic() < deadline, proc.stderr.read() if proc.poll() else ""
        time.sleep(0.02)
    os.kill(proc.pid, signal.SIGINT)
    stdout, stderr = proc.communicate(timeout=60)
    assert proc.returncode == 4, stderr
    out = json.loads(stdout)
    assert out["outcome"] == "paused_user" and out["steps"] >= 5
    assert Path(out["checkpoint"]).name == f"{out['steps']:08d}" and "Traceback" not in stderr
    again = _run(cmd[:cmd.index("--steps") + 1] + [str(out["steps"] + 3)] + cmd[cmd.index("--steps") + 2:])
    assert again.returncode == 0, again.stderr
    assert json.loads(again.stdout)["resumed_from"] == out["steps"]


@pytest.mark.parametrize("case", ["missing_data", "no_episodes", "unknown_component", "budget", "bad_vqvae"])
def test_usage_errors_exit_2_with_a_message_and_no_traceback(ds, tmp_path, case):
    run = tmp_path / "r"
    if case == "missing_data":
        cmd = _args(ds, run)
        cmd[cmd.index("--data") + 1] = str(tmp_path / "nowhere")
        expect = f"--data {tmp_path / 'nowhere'}: no such file or directory"
    elif case == "no_episodes":
        empty = tmp_path / "empty"
        (empty / "ep").mkdir(parents=True)
        (empty / "ep" / "readme.txt").write_text("nothing")
        cmd = _args(ds, run)
        cmd[cmd.index("--data") + 1] = str(empty)
        expect = f"--data {empty}"
    elif case == "unknown_component":
        cmd = _args(ds, run, component="slow_loop")
        expect = "invalid choice: 'slow_loop'"
    elif case == "budget":
        cmd = _args(ds, run, "--memory-budget-mb", "50")
        expect = "exceeds the budget of 50 MB"
    else:
        cmd = _args(ds, run, "--vqvae", str(tmp_path))
        expect = "no complete checkpoint"
    proc = _run(cmd)
    assert proc.returncode == 2, (proc.stdout, proc.stderr)
    assert expect in proc.stderr and "Traceback" not in proc.stderr
    if case != "unknown_component":
        proc = _run(cmd + ["--json"])
        err = json.loads(proc.stdout)
        assert proc.returncode == 2 and err["outcome"] == "error" and expect in err["message"]
