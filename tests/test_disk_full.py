"""A full disk loses nothing: training on a real, small tmpfs runs out of space mid-run, pauses as
"paused_disk" (exit 6) with the path and the free space in its message, keeps its last checkpoint,
and once space is freed the same run dir resumes and ends bitwise equal to an uninterrupted run."""
from __future__ import annotations

import argparse
import errno
import hashlib
import json
import os
import shutil
import sqlite3
import subprocess
from pathlib import Path

import pytest

from hope_models import disk
from hope_models.data.synthetic import generate_dataset
from hope_models import checkpoints as ckpt
from hope_models.train.contract import OUTCOME_EXIT_CODES, ControlCommand
from hope_models.train.loop import TrainConfig, train
from test_train_loop_standin import factory

STEPS, EVERY, HIDDEN = 60, 20, 16
PAGE = 4096


@pytest.fixture(scope="module")
def ds(tmp_path_factory) -> Path:
    root = tmp_path_factory.mktemp("diskds")
    generate_dataset(root / "ds", 1500, obs_dim=6, act_dim=2, episode_seconds=(3, 9), seed=1)
    return root


@pytest.fixture
def small_fs(tmp_path) -> Path:
    """A real 8 MB tmpfs, unmounted afterwards."""
    mnt = tmp_path / "sd"
    mnt.mkdir()
    done = subprocess.run(["mount", "-t", "tmpfs", "-o", "size=8m", "tmpfs", str(mnt)], capture_output=True, text=True)
    if done.returncode != 0:
        pytest.skip(f"cannot mount a tmpfs here (needs root / CAP_SYS_ADMIN): {done.stderr.strip()}")
    try:
        yield mnt
    finally:
        subprocess.run(["umount", "-l", str(mnt)], check=False)


def cfg_for(ds: Path, run_dir: Path) -> TrainConfig:
    return TrainConfig(component="fast_loop", data=str(ds / "ds"), run_dir=str(run_dir), steps=STEPS, seed=3,
                       batch_size=16, lr=3e-3, threads=1, checkpoint_every_steps=EVERY, log_every=5, keep_last=2,
                       cache_dir=str(ds / "cache"), thermal_zone=None, vcgencmd=None, control_interval_s=0.0)


class FillDisk:
    """At step `at`, fill the filesystem with a ballast file that leaves 3 pages: a few metrics lines
    still fit, the next checkpoint (5 files, tmpfs gives each at least a page) does not."""

    def __init__(self, run_dir: Path, ballast: Path, at: int):
        self.run_dir, self.ballast, self.at, self.done = run_dir, ballast, at, False

    def poll(self, step: int) -> ControlCommand:
        if step >= self.at and not self.done:
            self.done = True
            assert len(list(ckpt.list_step_dirs(self.run_dir)[0][1].iterdir())) >= 5
            fill(self.ballast.parent, leave_bytes=3 * PAGE)
        return ControlCommand()


def final_weights_sha(run_dir: Path) -> str:
    """sha256 over the final weights' names, dtypes, shapes and bytes, and the file's own sha256
    (equal weights make equal files: test_train_checkpoint.test_equal_weights_make_equal_files)."""
    digest = hashlib.sha256()
    last = ckpt.load_latest(run_dir)
    digest.update(hashlib.sha256((last.path / ckpt.MODEL_FILE).read_bytes()).digest())
    for name, t in sorted(last.model.items()):
        digest.update(f"{name}:{t.dtype}:{tuple(t.shape)}".encode())
        digest.update(t.contiguous().numpy().tobytes())
    return digest.hexdigest()


def test_full_disk_pauses_keeps_the_checkpoint_and_resumes_bitwise(ds, tmp_path, small_fs):
    ref = train(cfg_for(ds, tmp_path / "ref"), component_factory=factory(hidden=HIDDEN))
    assert ref.outcome == "completed"

    run_dir, ballast = small_fs / "run", small_fs / "ballast"
    events: list[tuple[str, dict]] = []
    r = train(cfg_for(ds, run_dir), FillDisk(run_dir, ballast, at=EVERY + 5), lambda k, p: events.append((k, p)),
              component_factory=factory(hidden=HIDDEN))
    assert r.outcome == "paused_disk" and r.exit_code == OUTCOME_EXIT_CODES["paused_disk"] == 6
    assert r.steps == EVERY and r.checkpoint.endswith(f"{EVERY:08d}")  # resumes from the last one written
    assert str(run_dir) in r.message and "MB free" in r.message and "no space left" in r.message
    logs = [p["message"] for k, p in events if k == "log"]
    assert not any("Traceback" in m for m in logs), logs
    # the previous checkpoint is intact (its manifest's hashes check) and no temp dir is left behind
    loaded = ckpt.load_latest(run_dir)
    assert loaded is not None and loaded.step == EVERY
    assert not [p for p in ckpt.checkpoints_dir(run_dir).iterdir() if p.name.startswith(".")]

    ballast.unlink()  # space is freed
    r2 = train(cfg_for(ds, run_dir), component_factory=factory(hidden=HIDDEN))
    assert r2.outcome == "completed" and r2.resumed_from == EVERY and r2.steps == STEPS
    assert final_weights_sha(run_dir) == final_weights_sha(tmp_path / "ref")


def test_still_full_at_start_pauses_again_without_a_traceback(ds, small_fs):
    """A job started on a card with no room at all (its run dir cannot even take the metrics)."""
    fill(small_fs)
    r = train(cfg_for(ds, small_fs / "run"), component_factory=factory(hidden=HIDDEN))
    assert r.outcome == "paused_disk" and r.steps == 0 and r.checkpoint is None
    assert str(small_fs / "run") in r.message and "MB free" in r.message


def test_is_disk_full_knows_enospc_edquot_and_sqlite_full():
    assert disk.is_disk_full(OSError(errno.ENOSPC, "No space left on device"))
    assert disk.is_disk_full(OSError(errno.EDQUOT, "Disk quota exceeded"))
    assert disk.is_disk_full(sqlite3.OperationalError("database or disk is full"))
    try:
        try:
            raise OSError(errno.ENOSPC, "No space left on device")
        except OSError as inner:
            raise RuntimeError("wrapped") from inner
    except RuntimeError as outer:
        assert disk.is_disk_full(outer)
    assert not disk.is_disk_full(OSError(errno.EACCES, "Permission denied"))
    assert not disk.is_disk_full(ValueError("bad"))


def test_floor_default_is_checkpoint_times_keep_plus_two_plus_margin():
    assert disk.dispatch_floor_mb(10.0, 3) == 10.0 * 5 + 200.0
    assert disk.dispatch_floor_mb(10.0, 3, setting_mb=1234) == 1234.0


def fill(fs: Path, leave_bytes: int = 0) -> Path:
    """A ballast file taking all but `leave_bytes` of the filesystem's free space."""
    ballast = fs / "ballast"
    fd = os.open(ballast, os.O_WRONLY | os.O_CREAT, 0o600)
    try:
        os.posix_fallocate(fd, 0, shutil.disk_usage(fs).free - leave_bytes)
    finally:
        os.close(fd)
    return ballast


def test_an_ingest_that_fills_the_disk_rejects_nothing_and_goes_on_after(tmp_path, small_fs, capsys):
    from hope_models.cli import ingest as ingest_cli
    from hope_models.rlds.ingest import MANIFEST, IngestDiskFull, ingest_paths
    from test_rlds_ingest import single_json, steps_10hz

    src, ds = tmp_path / "src", small_fs / "ds"
    single_json(src / "a" / "first.json", "first", steps_10hz(50))
    assert ingest_paths([src / "a"], ds)["summary"]["written"] == 1
    for i, name in enumerate(("second", "third")):  # other content: not duplicates of the first
        single_json(src / "b" / f"{name}.json", name, steps_10hz(50, command=[0.3 + i, 0.4]))
    ballast = fill(small_fs)
    with pytest.raises(IngestDiskFull) as info:
        ingest_paths([src / "b"], ds)
    assert str(ds) in str(info.value) and "MB free" in str(info.value)
    manifest = json.loads((ds / MANIFEST).read_text())  # the committed manifest is intact
    assert [e["episode_id"] for e in manifest["episodes"]] == ["first"] and manifest["rejected"] == []
    assert ingest_cli.run(argparse.Namespace(sources=[str(src / "b")], into=str(ds), json=False)) == 6
    assert "no space left" in capsys.readouterr().err

    ballast.unlink()
    again = ingest_paths([src / "b"], ds)
    assert again["summary"]["written"] == 2 and again["summary"]["ok"]
    manifest = json.loads((ds / MANIFEST).read_text())
    assert sorted(e["episode_id"] for e in manifest["episodes"]) == ["first", "second", "third"]
