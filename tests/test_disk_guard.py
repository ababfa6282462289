"""The daemon and a full disk (daemon/disk_guard.py): no dispatch below the free-space floor (the
run stays queued and says why in `waiting`), a disk-paused run requeued once space is back,
retention of old run dirs, and a tick whose registry write hits "database or disk is full"
leaving the daemon serving."""
from __future__ import annotations

import sqlite3
from pathlib import Path

import pytest

from hope_models import checkpoints as ckpt
from daemon.disk_guard import PIN_FILE, DiskGuard
from daemon.service import Daemon
from daemon_fixtures import Home, home, tiny_dataset  # noqa: F401
from registry import runs
from registry.models import Model, utcnow
from test_daemon_service import broker, claim, dispatcher, finish  # noqa: F401 (fixtures)


def fake_checkpoint(run_dir: Path, step: int, mb: int) -> None:
    """A checkpoint step dir of `mb` MB (sparse: only its size is read)."""
    d = ckpt.checkpoints_dir(run_dir) / ckpt.step_dir_name(step)
    d.mkdir(parents=True)
    with open(d / "model.safetensors", "wb") as f:
        f.truncate(mb * 1024 * 1024)


def free_is(monkeypatch, mb: float) -> None:
    monkeypatch.setattr("hope_models.disk.free_mb", lambda path: mb)


def test_no_dispatch_below_the_setting_floor_the_run_says_why_and_starts_later(home, tiny_dataset, dispatcher,
                                                                              broker, monkeypatch):
    rid = home.enqueue(tiny_dataset)
    home.settings.disk_floor_mb = 500
    free_is(monkeypatch, 120.0)
    assert dispatcher.dispatch(0) == [] and dispatcher.dispatch(0) == []
    run = home.run(rid)
    assert run["state"] == "queued" and broker.sent == []
    with home.registry.session(readonly=True) as s:
        waiting = runs.to_json(s, [runs.get_run(s, rid)])[0]["waiting"]
        error = runs.get_run(s, rid).to_json_obj()["error"]
    assert "120 MB free" in waiting and "500 MB" in waiting and str(home.settings.home) in waiting
    assert error is None  # a hold is no error
    logged = [e["payload"]["message"] for e in home.events(rid, ["log"]) if "disk space" in e["payload"]["message"]]
    assert len(logged) == 1  # said once, not every tick
    free_is(monkeypatch, 800.0)  # space is back
    assert [d.run_id for d in dispatcher.dispatch(0)] == [rid]
    with home.registry.session(readonly=True) as s:
        assert runs.get_run(s, rid).to_json_obj()["waiting"].startswith("waiting for a worker")


def test_default_floor_is_the_checkpoint_size_times_keep_plus_two_plus_200(home, tiny_dataset, dispatcher,
                                                                          monkeypatch):
    rid = home.enqueue(tiny_dataset, keep_last=3)
    fake_checkpoint(home.run(rid)["run_dir"], 20, 30)  # a resumed job: 30 MB x (3 + 2) + 200 = 350 MB
    with home.registry.session(readonly=True) as s:
        assert DiskGuard(home.registry, home.settings).floor_mb(s, runs.get_run(s, rid)) == pytest.approx(350.0)
    free_is(monkeypatch, 340.0)
    assert dispatcher.dispatch(0) == []
    free_is(monkeypatch, 360.0)
    assert [d.run_id for d in dispatcher.dispatch(0)] == [rid]


def test_a_first_run_floor_comes_from_its_configuration_and_matches_a_real_checkpoint(home, tiny_dataset,
                                                                                     tmp_path):
    """No checkpoint anywhere yet: the size is estimated from the model the run describes, and it
    is the size its real checkpoint then has on disk (within 20 %)."""
    from daemon.disk_guard import newest_checkpoint_mb
    from hope_models.train.loop import TrainConfig, train

    model_config = {"d_model": 192, "d_state": 32}
    rid = home.enqueue(tiny_dataset, keep_last=3, model_config=model_config)
    guard = DiskGuard(home.registry, home.settings)
    with home.registry.session(readonly=True) as s:
        run = runs.get_run(s, rid)
        estimate = guard.checkpoint_mb(s, run)
        assert guard.floor_mb(s, run) == pytest.approx(estimate * 5 + 200.0)
    res = train(TrainConfig(component="fast_loop", data=str(tiny_dataset), run_dir=str(tmp_path / "r"), steps=2,
                            batch_size=4, model_config=model_config, cache_dir=str(home.settings.cache_dir),
                            thermal_zone=None, vcgencmd=None))
    assert res.outcome == "completed"
    real = newest_checkpoint_mb(tmp_path / "r")
    assert estimate > 0.5 and real == pytest.approx(estimate, rel=0.2), (estimate, real)


def test_a_disk_paused_run_is_requeued_when_space_is_back(home, tiny_dataset, dispatcher, monkeypatch):
    rid = home.enqueue(tiny_dataset)
    assert [d.run_id for d in dispatcher.dispatch(0)] == [rid]
    claim(home, rid, 6000)
    finish(home, rid, 6000, "paused_disk")
    assert home.run(rid)["state"] == "paused" and home.run(rid)["pause_reason"] == "disk"
    home.settings.disk_floor_mb = 500
    free_is(monkeypatch, 100.0)
    assert dispatcher.requeue_paused(0, 1e9) == []
    free_is(monkeypatch, 600.0)
    assert dispatcher.requeue_paused(0, 1e9) == [rid] and home.run(rid)["state"] == "queued"


def _finished(home, tiny_dataset, dispatcher, n: int) -> list[str]:
    ids = []
    for i in range(n):
        rid = home.enqueue(tiny_dataset)
        assert [d.run_id for d in dispatcher.dispatch(0)] == [rid]
        claim(home, rid, 7000 + i)
        finish(home, rid, 7000 + i)
        fake_checkpoint(home.run(rid)["run_dir"], 10, 1)
        ids.append(rid)
    return ids


def test_retention_keeps_the_last_n_promoted_pinned_and_their_vqvae(home, tiny_dataset, dispatcher):
    old_vq, promoted, pinned, plain, new1, new2 = _finished(home, tiny_dataset, dispatcher, 6)
    reader = home.enqueue(tiny_dataset)  # queued: it will read old_vq's codes (a chain's mid_loop would)
    with home.registry.session() as s:
        row = runs.get_run(s, reader)
        row.config = {**row.config, "vqvae_run": old_vq}
    (Path(home.run(pinned)["run_dir"]) / PIN_FILE).touch()
    with home.registry.session() as s:
        s.add(Model(component="fast_loop", checkpoint_path="x", run_id=promoted, promoted_at=utcnow()))
    outside = home.path.parent / "elsewhere-run"  # a run dir outside $HOPE_HOME/runs is never deleted
    with home.registry.session() as s:
        runs.get_run(s, plain).run_dir = str(outside)
    fake_checkpoint(outside, 10, 1)
    home.settings.keep_runs = 3
    guard = DiskGuard(home.registry, home.settings)
    assert guard.maybe_prune() == []  # plain, new1, new2 are the last 3; the others promoted, read, pinned
    for rid in (old_vq, promoted, pinned, new1, new2):
        assert Path(home.run(rid)["run_dir"]).is_dir(), rid
    assert outside.is_dir() and home.run(reader)["state"] == "queued"

    with home.registry.session() as s:
        runs.request_control(s, reader, "cancel")
    # it never started: it neither counts toward keep_runs nor keeps old_vq, which nothing reads now
    assert home.run(reader)["state"] == "cancelled"
    assert guard.maybe_prune() == [old_vq]
    _finished(home, tiny_dataset, dispatcher, 3)
    # plain's dir is outside runs/, pinned is pinned, promoted is promoted
    assert sorted(guard.maybe_prune()) == sorted([new1, new2])
    assert Path(home.run(pinned)["run_dir"]).is_dir() and Path(home.run(promoted)["run_dir"]).is_dir()
    assert not Path(home.run(old_vq)["run_dir"]).exists() and home.run(old_vq)["state"] == "completed"
    assert any("pruned by retention" in e["payload"]["message"] for e in home.events(old_vq, ["log"]))
    assert [p for p in Path(home.settings.runs_dir).iterdir() if p.name.startswith(".pruned")] == []
    assert guard.maybe_prune() == []  # no run finished since: no new scan


def test_keep_runs_zero_keeps_everything(home, tiny_dataset, dispatcher):
    ids = _finished(home, tiny_dataset, dispatcher, 2)
    home.settings.keep_runs = 0
    assert DiskGuard(home.registry, home.settings).prune() == []
    assert all(Path(home.run(r)["run_dir"]).is_dir() for r in ids)


def test_a_full_database_fails_the_tick_not_the_daemon(home, broker, monkeypatch):
    d = Daemon(home.settings, registry=home.registry, send=broker, tick_s=0.01)
    d.start()
    try:
        def full(*a, **kw):
            raise sqlite3.OperationalError("database or disk is full")

        monkeypatch.setattr(d.dispatcher, "dispatch", full)
        assert d.safe_tick() is False and d.safe_tick() is False  # logged, retried next tick
        monkeypatch.undo()
        assert d.safe_tick() is True
    finally:
        d.stop()


def test_a_job_whose_write_hits_enospc_pauses_its_run_for_disk(home, tiny_dataset, monkeypatch):
    """The worker's side: an ENOSPC out of the trainer (here before its loop could catch it) is a
    paused run with reason disk and the path in its message, not a failed run with a traceback."""
    import errno

    from workers import job as job_mod

    rid = home.enqueue(tiny_dataset)
    with home.registry.session() as s:
        runs.mark_dispatched(s, runs.get_run(s, rid), "task-1")

    def full(*a, **kw):
        raise OSError(errno.ENOSPC, "No space left on device", str(home.path / "runs" / "x" / "metrics.jsonl"))

    monkeypatch.setattr(job_mod, "train", full)
    out = job_mod.run_job(home.settings, rid, 1, task_id="task-1", report="db", host="host", pid=4343)
    assert out["outcome"] == "paused_disk" and out["state"] == "paused"
    run = home.run(rid)
    assert (run["state"], run["pause_reason"]) == ("paused", "disk")
    logs = [e["payload"]["message"] for e in home.events(rid, ["log"])]
    assert any("metrics.jsonl" in m and "MB free" in m for m in logs)
    assert not any("Traceback" in m for m in logs)
