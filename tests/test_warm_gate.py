"""The gate in the worker child that trained the run (workers/warm_gate.py): a completed run is
gated and promoted before the child exits, auto-promotion then has nothing left to spawn; a busy
promote lock or auto-promotion off leave the run to the daemon as before.

Each job trains a fast_loop for 30 steps on the tiny synthetic dataset in this process (run_job is
what the Celery task calls in its child); no reflex check applies to synthetic data.
"""
from __future__ import annotations

from pathlib import Path

from daemon.autopromote import AutoPromoter
from daemon_fixtures import Home, tiny_dataset  # noqa: F401 (fixture)
from hope_models.promoted import read_pointer
from registry import runs
from registry.gating import PROMOTE_LOG, promote_lock, promote_lock_busy
from registry.models import Model
from workers import job as job_mod

WORKER = "(in the worker that trained it)"


def _home(tmp_path: Path, auto: str = "1") -> Home:
    return Home(tmp_path / "home", extra_env={"HOPE_AUTO_PROMOTE": auto})


def _train(home: Home, data: Path, task: str = "task-1") -> tuple[str, dict]:
    rid = home.enqueue(data, steps=30)
    with home.registry.session() as s:
        runs.mark_dispatched(s, runs.get_run(s, rid), task)
    out = job_mod.run_job(home.settings, rid, 1, task_id=task, report="db", host="host", pid=4242)
    return rid, out


def _models(home: Home, run_id: str) -> list[Model]:
    with home.registry.session(readonly=True) as s:
        rows = list(s.query(Model).filter(Model.run_id == run_id))
        s.expunge_all()
        return rows


def _messages(home: Home, run_id: str) -> list[str]:
    return [e["payload"]["message"] for e in home.events(run_id, ["log"])]


def test_the_child_that_trained_a_run_gates_and_promotes_it(tmp_path, tiny_dataset):  # noqa: F811
    home = _home(tmp_path)
    try:
        rid, out = _train(home, tiny_dataset)
        assert out["state"] == "completed", out
        (model,) = _models(home, rid)
        assert model.promoted_at is not None and model.gate_result["mode"] == "auto"
        assert read_pointer(home.path, "fast_loop")["version"] == model.version
        assert any(WORKER in m and "promoted fast_loop" in m for m in _messages(home, rid)), _messages(home, rid)
        log = (home.path / "logs" / PROMOTE_LOG).read_text()
        assert f"run {rid}: " in log and WORKER in log
        # auto-promotion finds nothing left to gate; the lock was released when the child was done
        promoter = AutoPromoter(home.settings, home.registry)
        promoter.started_at = model.created_at.replace(year=2000)  # every run counts, not only later ones
        assert promoter.next_run() is None
        assert not promote_lock_busy(home.path)
    finally:
        home.close()


def test_a_gate_running_elsewhere_leaves_the_run_to_auto_promotion(tmp_path, tiny_dataset):  # noqa: F811
    home = _home(tmp_path)
    try:
        with promote_lock(home.path, wait=False) as mine:  # another gate (a `promote` child) holds it
            assert mine and promote_lock_busy(home.path)
            rid, out = _train(home, tiny_dataset)
            assert out["state"] == "completed", out
            assert _models(home, rid) == []  # not gated here, nothing lost
            promoter = AutoPromoter(home.settings, home.registry)
            promoter.started_at = promoter.started_at.replace(year=2000)  # every run counts, not only later ones
            assert promoter.next_run() == rid
            promoter.tick()  # the lock is busy: it waits instead of spawning a child that would block
            assert not promoter.busy
        assert not any(WORKER in m for m in _messages(home, rid))
    finally:
        home.close()


def test_auto_promotion_off_gates_nothing(tmp_path, tiny_dataset):  # noqa: F811
    home = _home(tmp_path, auto="0")
    try:
        rid, out = _train(home, tiny_dataset)
        assert out["state"] == "completed", out
        assert _models(home, rid) == [] and read_pointer(home.path, "fast_loop") is None
        assert not (home.path / "logs" / PROMOTE_LOG).exists()
    finally:
        home.close()
