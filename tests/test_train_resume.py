"""SIGKILL a real `run_trainer.py train` subprocess, re-run the same command: the final weights are
bitwise identical to an uninterrupted run's (compared tensor by tensor with torch.equal)."""
from __future__ import annotations

import json
import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest
import torch

from hope_models.data.synthetic import generate_dataset
from hope_models import checkpoints as ckpt

REPO = Path(__file__).resolve().parents[1]


@pytest.fixture(scope="module")
def data(tmp_path_factory) -> tuple[Path, Path]:
    root = tmp_path_factory.mktemp("resume")
    generate_dataset(root / "ds", 3000, obs_dim=6, act_dim=2, episode_seconds=(3, 9), seed=4)
    return root / "ds", root / "cache"


def _cmd(data, run_dir: Path, component: str, steps: int, every: int, *extra: str) -> list[str]:
    ds, cache = data
    return [sys.executable, str(REPO / "run_trainer.py"), "train", "--component", component, "--data", str(ds),
            "--run-dir", str(run_dir), "--steps", str(steps), "--seed", "7", "--batch-size", "16", "--threads", "1",
            "--checkpoint-every", str(every), "--log-every", "2", "--cache-dir", str(cache),
            "--thermal-zone", str(run_dir.parent / "no-thermal-zone"), "--json", *extra]


def _run(cmd: list[str]) -> dict:
    proc = subprocess.run(cmd, capture_output=True, text=True, timeout=120, cwd=REPO)
    assert proc.returncode == 0, proc.stderr
    return json.loads(proc.stdout.strip().splitlines()[-1])


def _last_logged_step(run_dir: Path) -> int:
    try:
        lines = (run_dir / "metrics.jsonl").read_text().splitlines()
    except FileNotFoundError:
        return 0
    steps = [json.loads(ln)["step"] for ln in lines if ln.endswith("}") and '"type":"metric"' in ln]
    return max(steps, default=0)


def _writing(run_dir: Path) -> bool:
    try:
        return any(n.startswith(".tmp-") for n in os.listdir(run_dir / "checkpoints"))
    except FileNotFoundError:
        return False


def _kill_when(cmd: list[str], run_dir: Path, past_step: int, during_write: bool = False) -> int:
    """Start the command, SIGKILL it once metrics show a step past `past_step` (and, with
    during_write, as soon as a checkpoint temp dir appears after that); returns that step."""
    proc = subprocess.Popen(cmd, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL, cwd=REPO)
    try:
        deadline = time.monotonic() + 90
        while (seen := _last_logged_step(run_dir)) <= past_step:
            assert proc.poll() is None, "the run ended before it could be killed"
            assert time.monotonic() < deadline, "no progress past the first checkpoint"
            time.sleep(0.01)
        while during_write and not _writing(run_dir):
            assert proc.poll() is None and time.monotonic() < deadline, "no checkpoint write seen"
        os.kill(proc.pid, signal.SIGKILL)
    finally:
        proc.wait(timeout=30)
    assert proc.returncode == -signal.SIGKILL
    assert not (run_dir / "result.json").exists(), "the run finished before the kill"
    return seen


def _assert_same_weights(a: Path, b: Path) -> None:
    wa, wb = ckpt.load_latest(a).model, ckpt.load_latest(b).model
    assert wa.keys() == wb.keys()
    for k in wa:
        assert torch.equal(wa[k], wb[k]), f"{k} differs after resume"


STEPS = 120


@pytest.fixture(scope="module")
def fast_ref(data, tmp_path_factory) -> Path:
    """An uninterrupted fast_loop run; checkpoint intervals do not change the math, so every
    fast_loop test below compares against it whatever its own --checkpoint-every."""
    run = tmp_path_factory.mktemp("ref") / "run"
    ref = _run(_cmd(data, run, "fast_loop", STEPS, 40))
    assert ref["outcome"] == "completed" and ref["resumed_from"] is None and ref["steps"] == STEPS
    return run


def _killed_then_rerun(data, run: Path, component: str, steps: int, every: int, past_step: int) -> dict:
    cmd = _cmd(data, run, component, steps, every)
    seen = _kill_when(cmd, run, past_step=past_step)
    out = _run(cmd)
    assert out["outcome"] == "completed" and out["steps"] == steps
    assert out["resumed_from"] is not None and every <= out["resumed_from"] <= seen < steps
    return out


def test_sigkill_mid_run_then_rerun_gives_bitwise_identical_weights(data, tmp_path, fast_ref):
    run = tmp_path / "killed"
    out = _killed_then_rerun(data, run, "fast_loop", STEPS, 40, past_step=50)
    _assert_same_weights(fast_ref, run)
    ra = json.loads((fast_ref / "result.json").read_text())
    rb = json.loads((run / "result.json").read_text())
    assert out["first_loss"] == ra["first_loss"] and out["final_loss"] == ra["final_loss"]
    assert ra["summary"] == rb["summary"]  # the loss history rode along in the checkpoint


def test_sigkill_vqvae_whose_dead_code_restarts_draw_from_the_rng(data, tmp_path):
    steps, every = 240, 40
    ref = _run(_cmd(data, tmp_path / "ref", "vqvae", steps, every))
    assert ref["outcome"] == "completed"
    _killed_then_rerun(data, tmp_path / "killed", "vqvae", steps, every, past_step=every + 10)
    _assert_same_weights(tmp_path / "ref", tmp_path / "killed")


def test_sigkill_during_checkpoint_writes_then_rerun(data, tmp_path, fast_ref):
    """Kill the moment a checkpoint temp dir shows up (a checkpoint every step), so the kill lands
    inside a write; the re-run resumes from the newest complete checkpoint and ends identical."""
    torn = 0
    for attempt in range(3):  # the write may finish between seeing its temp dir and the kill
        run = tmp_path / f"killed{attempt}"
        cmd = _cmd(data, run, "fast_loop", STEPS, 1, "--keep", "2")
        _kill_when(cmd, run, past_step=30, during_write=True)
        torn += any(p.name.startswith(".tmp-") for p in (run / "checkpoints").iterdir())
        out = _run(cmd)
        assert out["outcome"] == "completed" and out["resumed_from"] is not None and out["resumed_from"] >= 30
        _assert_same_weights(fast_ref, run)
        assert not [p for p in (run / "checkpoints").iterdir() if p.name.startswith((".tmp-", ".del-"))]
        if torn:
            break
    assert torn, "no kill landed inside a checkpoint write"


def test_truncated_newest_checkpoint_is_skipped_on_resume(data, tmp_path, fast_ref):
    run = tmp_path / "r"
    cmd = _cmd(data, run, "fast_loop", STEPS, 40)
    _run(cmd)
    newest = run / "checkpoints" / f"{STEPS:08d}"
    f = newest / "training_state.safetensors"
    f.write_bytes(f.read_bytes()[: f.stat().st_size // 2])  # a torn write of the newest
    proc = subprocess.run(cmd, capture_output=True, text=True, timeout=120, cwd=REPO)
    assert proc.returncode == 0, proc.stderr
    out = json.loads(proc.stdout.strip().splitlines()[-1])
    assert out["outcome"] == "completed" and out["resumed_from"] == 80
    assert f"skipping checkpoint {newest}" in proc.stderr and "training_state.safetensors" in proc.stderr
    assert ckpt.load_latest(run).step == STEPS and ckpt.verify(newest) is None  # rewritten whole
    _assert_same_weights(fast_ref, run)


def test_mid_loop_with_a_frozen_vqvae_pauses_and_resumes_exactly(data, tmp_path):
    """In-process (the real components, no stand-in): pause mid_loop by Control, resume, compare."""
    from hope_models.train.contract import ControlCommand
    from hope_models.train.loop import TrainConfig, train

    ds, cache = data

    def cfg(component, run, steps, vqvae=None):
        return TrainConfig(component=component, data=str(ds), run_dir=str(run), steps=steps, seed=5, batch_size=8,
                           threads=1, checkpoint_every_steps=100, cache_dir=str(cache), thermal_zone=None,
                           vcgencmd=None, vqvae_dir=vqvae, control_interval_s=0.0, log_every=5)

    class PauseAt:
        def poll(self, step):
            return ControlCommand(desired="pause" if step >= 13 else "run")

    assert train(cfg("vqvae", tmp_path / "vq", 20)).outcome == "completed"
    vq = str(tmp_path / "vq")
    assert train(cfg("mid_loop", tmp_path / "ref", 30, vq)).outcome == "completed"
    paused = train(cfg("mid_loop", tmp_path / "mid", 30, vq), PauseAt())
    assert paused.outcome == "paused_user" and paused.steps == 13
    done = train(cfg("mid_loop", tmp_path / "mid", 30, vq))
    assert done.outcome == "completed" and done.resumed_from == 13
    _assert_same_weights(tmp_path / "ref", tmp_path / "mid")
