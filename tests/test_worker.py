"""The Celery worker (workers/): its configuration, the job's control and events, and a REAL worker
process on the embedded sqla broker training runs from the registry.

One worker serves the whole module (it trains one run at a time, so the tests' runs queue behind
each other); every job is tiny (fast_loop on ~600 synthetic steps, batch 8, threads=1).
"""
from __future__ import annotations

import os
import signal
import sqlite3
import subprocess
import sys
import time
import uuid
from pathlib import Path

import pytest

from daemon_fixtures import REPO, Home, start_worker, tiny_dataset_path, wait_until

BASE_CONFIG = {"seed": 0, "batch_size": 8, "threads": 1, "warmup": 5, "log_every": 1}


# -- helpers ----------------------------------------------------------------------------------------

def create(home: Home, data: Path, *, steps: int, component: str = "fast_loop", **overrides) -> str:
    from registry import runs
    from registry.models import new_run_id

    rid = new_run_id()
    config = {"data": str(data), **BASE_CONFIG, **overrides}
    with home.registry.session() as s:
        runs.create_run(s, component=component, config=config, total_steps=steps,
                        run_dir=str(home.settings.runs_dir / rid), run_id=rid)
    return rid


def dispatch(home: Home, app, run_id: str, *, task_id: str | None = None, attempt: int | None = None,
             send_id: str | None = None, **send_kw) -> str:
    """What the daemon does: mark the run dispatched under a task id, then send the task.
    send_id/attempt override what is sent (to make a stale delivery)."""
    from registry import runs

    task_id = task_id or str(uuid.uuid4())
    with home.registry.session() as s:
        run = runs.get_run(s, run_id)
        if run.state == "queued":
            runs.mark_dispatched(s, run, task_id)
        real_attempt = run.attempt
    app.send_task("hope.train_run", args=[run_id, attempt or real_attempt], queue="pi",
                  task_id=send_id or task_id, **send_kw)
    return task_id


def wait_state(home: Home, run_id: str, states: set[str], timeout: float) -> dict:
    return wait_until(lambda: (r := home.run(run_id))["state"] in states and r, timeout,
                      f"run {run_id} to reach {sorted(states)}", home, interval=0.05)


def maps_has_libtorch(pid: int) -> bool:
    return "libtorch" in Path(f"/proc/{pid}/maps").read_text()


def checkpoint_step(path: str) -> int:
    return int(Path(path).name)


# -- configuration (no worker) --------------------------------------------------------------------

def test_celery_config_json_only_one_job_at_a_time(tmp_path):
    from hope_models.settings import Settings
    from registry.broker import VISIBILITY_TIMEOUT_S
    from workers.celery import create_celery

    app = create_celery(Settings(home=tmp_path / "h"))
    c = app.conf
    assert list(c.accept_content) == ["json"]
    assert c.task_serializer == c.result_serializer == c.event_serializer == "json"
    assert list(c.result_accept_content) == ["json"]
    assert c.task_acks_late is True and c.task_reject_on_worker_lost is False
    assert c.worker_prefetch_multiplier == 1 and c.worker_concurrency == 1 and c.worker_max_tasks_per_child == 1
    assert c.task_ignore_result is True and not c.result_backend
    assert c.task_default_queue == "pi" and c.worker_hijack_root_logger is False
    assert c.broker_connection_retry_on_startup is True and c.broker_connection_max_retries is None
    # embedded broker: our SQLite transport, absolute file under $HOPE_HOME, fast polling
    assert c.broker_url == f"sqlite:///{(tmp_path / 'h' / 'broker' / 'broker.sqlite').resolve()}"
    assert c.broker_transport == "registry.broker_transport:Transport"
    assert c.broker_transport_options["polling_interval"] <= 0.1
    assert not (tmp_path / "h").exists(), "building the app must not touch the state dir"

    redis = create_celery(Settings(home=tmp_path / "h", redis_url="redis://127.0.0.1:6390/0")).conf
    assert redis.broker_url == "redis://127.0.0.1:6390/0" and not redis.broker_transport
    assert redis.broker_transport_options["visibility_timeout"] == VISIBILITY_TIMEOUT_S >= 7 * 24 * 3600
    assert list(redis.accept_content) == ["json"]


def test_embedded_transport_polls_fast_on_a_wal_file(tmp_path):
    """kombu 5.7's own sqla transport passes transport options to create_engine (polling_interval
    there raises TypeError); ours honours it, creates the broker dir, and uses WAL."""
    from kombu import Connection

    db = tmp_path / "b" / "broker" / "broker.sqlite"
    with Connection(f"sqlite:///{db}", transport="registry.broker_transport:Transport",
                    transport_options={"polling_interval": 0.05}) as conn:
        q = conn.SimpleQueue("pi")
        q.put({"hello": 1}, serializer="json")
        msg = q.get(timeout=2)
        assert msg.payload == {"hello": 1}
        msg.ack()
        assert conn.transport.polling_interval == 0.05
        q.close()
    assert sqlite3.connect(db).execute("PRAGMA journal_mode").fetchone()[0] == "wal"


def test_embedded_transport_drain_keeps_its_timeout_but_not_past_a_worker_stop(tmp_path, monkeypatch):
    """Celery's loop for polling transports asks for 2 s waits and looks at its stop flag only
    between them: once the worker is asked to stop, a wait ends within a slice; otherwise a
    caller still waits as long as it asked."""
    import socket

    from celery.worker import state
    from kombu import Connection, Consumer, Queue

    from registry.broker_transport import DRAIN_SLICE_S

    db = tmp_path / "broker" / "broker.sqlite"
    with Connection(f"sqlite:///{db}", transport="registry.broker_transport:Transport") as conn:
        with Consumer(conn, queues=[Queue("pi")], accept=["json"]):
            started = time.monotonic()
            with pytest.raises(socket.timeout):
                conn.drain_events(timeout=1.0)
            assert 1.0 <= time.monotonic() - started < 3.0
            monkeypatch.setattr(state, "should_stop", 0)  # what Celery's SIGTERM handler sets
            started = time.monotonic()
            with pytest.raises(socket.timeout):
                conn.drain_events(timeout=10.0)
            assert time.monotonic() - started < DRAIN_SLICE_S + 0.5


RACE_SCRIPT = r"""
import multiprocessing as mp, os, sys
from kombu import Connection
import registry.broker_transport

def opener(url, barrier, q):
    barrier.wait()
    try:
        with Connection(url, transport="registry.broker_transport:Transport") as c:
            sq = c.SimpleQueue("pi"); sq.put({"a": 1}, serializer="json"); sq.close()
        q.put("ok")
    except Exception as e:
        q.put(f"{type(e).__name__}: {e}")

mp.set_start_method("fork")
root, bad = sys.argv[1], []
for i in range(10):
    url = f"sqlite:///{root}/{i}/broker/broker.sqlite"
    barrier, q = mp.Barrier(6), mp.Queue()
    ps = [mp.Process(target=opener, args=(url, barrier, q)) for _ in range(6)]
    [p.start() for p in ps]; [p.join() for p in ps]
    bad += [r for r in (q.get() for _ in ps) if r != "ok"]
print(bad[:3])
sys.exit(1 if bad else 0)
"""


def test_embedded_broker_survives_processes_opening_it_at_once(tmp_path):
    """serve starts the daemon and the worker together on a new broker file. With kombu's own
    sqla transport most rounds of this fail (CREATE TABLE 'already exists', or IntegrityError on
    the queue row); ours creates the tables under a lock and retries the queue row."""
    proc = subprocess.run([sys.executable, "-c", RACE_SCRIPT, str(tmp_path)], cwd=REPO, capture_output=True,
                          text=True, timeout=120)
    assert proc.returncode == 0, proc.stdout + proc.stderr


def test_worker_command_and_cli(monkeypatch, tmp_path):
    import argparse

    from hope_models.settings import Settings
    from workers import cli

    cmd = cli.worker_command(None, "gpu")
    assert cmd[:6] == [sys.executable, "-m", "celery", "-A", "workers.celery:app", "worker"]
    for flag in ("--pool=prefork", "--concurrency=1", "--max-tasks-per-child=1", "--prefetch-multiplier=1",
                 "--without-gossip", "--without-mingle", "--without-heartbeat"):
        assert flag in cmd
    assert cmd[cmd.index("-Q") + 1] == "gpu" and cmd[cmd.index("-n") + 1] == "gpu@%h"
    with pytest.raises(ValueError, match="queue 'GPU!'"):
        cli.worker_command(None, "GPU!")
    env = cli.worker_env(Settings(home=tmp_path, redis_url="redis://x:1/0"), {"HOPE_REDIS_URL": "old", "A": "1"})
    assert env == {"HOPE_HOME": str(tmp_path), "HOPE_REDIS_URL": "redis://x:1/0", "A": "1"}
    assert "HOPE_REDIS_URL" not in cli.worker_env(Settings(home=tmp_path), {"HOPE_REDIS_URL": "old"})

    parser = argparse.ArgumentParser()
    cli.add_arguments(parser)
    seen = {}
    monkeypatch.setenv("HOPE_HOME", str(tmp_path))
    monkeypatch.delenv("HOPE_REDIS_URL", raising=False)
    monkeypatch.setattr(os, "execve", lambda exe, argv, env: seen.update(exe=exe, argv=argv, env=env))
    assert cli.run(parser.parse_args(["-Q", "pi", "--loglevel", "warning"])) == 0
    assert seen["argv"] == cli.worker_command(None, "pi", loglevel="warning") and seen["exe"] == sys.executable
    assert seen["env"]["HOPE_HOME"] == str(tmp_path)
    assert cli.run(parser.parse_args(["-Q", "Bad Queue"])) == 2


def test_worker_modules_import_without_torch():
    code = ("import sys, workers.celery, workers.tasks, workers.job, workers.cli, registry.broker_transport; "
            "bad = [m for m in ('torch', 'numpy') if m in sys.modules]; assert not bad, bad")
    subprocess.run([sys.executable, "-c", code], cwd=REPO, check=True, timeout=60)


# -- the job's pieces against a real registry (in this process) --------------------------------------

@pytest.fixture
def reg_home(tmp_path):
    h = Home(tmp_path / "home")
    yield h
    h.close()


def _claimed_run(home: Home, data: Path, pid: int = 4242) -> str:
    from registry import runs

    rid = create(home, data, steps=100)
    with home.registry.session() as s:
        runs.mark_dispatched(s, runs.get_run(s, rid), "task-1")
    with home.registry.session() as s:
        assert runs.claim(s, rid, "task-1", 1, "host", pid) is not None
    return rid


def _set(home: Home, rid: str, **values) -> None:
    from registry.models import Run

    with home.registry.session() as s:
        run = s.get(Run, rid)
        for k, v in values.items():
            setattr(run, k, v)


def _channel(home: Home, rid: str, pid: int = 4242):
    from registry.report_channel import RegistryChannel

    return RegistryChannel(home.registry, rid, "task-1", 1, pid, "host")


def test_run_control_maps_the_row_to_commands(reg_home, tmp_path):
    import threading

    from workers.job import THROTTLE_SLOW, RunControl

    rid = _claimed_run(reg_home, tmp_path / "no-data")
    said = []
    shutdown = threading.Event()
    ctl = RunControl(_channel(reg_home, rid), shutdown=shutdown, emit=lambda k, p: said.append((k, p)))
    assert ctl.poll(0).desired == "run" and ctl.poll(0).throttle == 0
    _set(reg_home, rid, throttle_level=1)
    assert ctl.poll(1).desired == "run" and ctl.poll(1).throttle == THROTTLE_SLOW
    _set(reg_home, rid, throttle_level=2)
    assert ctl.poll(2).desired == "pause"  # thermal: finish() records it as paused(thermal)
    _set(reg_home, rid, throttle_level=0, desired_state="pause")
    assert ctl.poll(3).desired == "pause"
    _set(reg_home, rid, desired_state="cancel")
    assert ctl.poll(4).desired == "cancel"
    _set(reg_home, rid, desired_state="run")
    assert ctl.poll(5).desired == "run"

    # SIGTERM: the row gets desired pause + requested_reason shutdown, the loop pauses
    shutdown.set()
    assert ctl.poll(6).desired == "pause"
    run = reg_home.run(rid)
    assert (run["desired_state"], run["requested_reason"]) == ("pause", "shutdown")

    # the row taken over by another child: this one cancels itself (and says why, once)
    _set(reg_home, rid, worker_pid=999, desired_state="run", requested_reason=None)
    other = RunControl(_channel(reg_home, rid), emit=lambda k, p: said.append((k, p)))
    assert other.poll(7).desired == "cancel" and other.poll(8).desired == "cancel" and other.lost.is_set()
    assert sum("no longer this child's" in p["message"] for _, p in said) == 1
    # the same pid on another host is not this child either
    _set(reg_home, rid, worker_pid=4242, worker_host="elsewhere")
    assert RunControl(_channel(reg_home, rid)).poll(9).desired == "cancel"


def test_thermal_pause_is_recorded_as_thermal_even_if_the_host_cooled_before_finish(reg_home, tmp_path):
    from registry import runs
    from workers.job import RunControl

    rid = _claimed_run(reg_home, tmp_path / "no-data")
    ctl = RunControl(_channel(reg_home, rid))
    _set(reg_home, rid, throttle_level=2)
    assert ctl.poll(1).desired == "pause"
    _set(reg_home, rid, throttle_level=0)  # the daemon saw it cool down before the child reported
    with reg_home.registry.session() as s:
        runs.finish(s, rid, 4242, "paused_user", "paused at step 1", step=1, last_checkpoint=None)
    run = reg_home.run(rid)
    assert (run["state"], run["pause_reason"]) == ("paused", "thermal")


def test_emitter_rate_limits_progress_and_keeps_the_last(reg_home, tmp_path):
    from registry.models import Run
    from workers.job import LOG_MAX_CHARS, Emitter

    rid = _claimed_run(reg_home, tmp_path / "no-data")
    clock = [100.0]
    slept = []

    def sleep(s):
        slept.append(s)
        clock[0] += s

    # a clock in 1/16 s ticks (exact floats) and a 0.25 s gap: one event in four gets through
    em = Emitter(_channel(reg_home, rid), min_gap_s=0.25, clock=lambda: clock[0], sleep=sleep)
    for step in range(1, 21):
        clock[0] += 1 / 16
        em("progress", {"step": step, "total": 20, "loss": 1.0 / step, "steps_per_s": 100.0, "eta_s": 0,
                        "rss_mb": 1.0})
        em("metric", {"type": "metric", "step": step, "loss": 1.0 / step})
    em("checkpoint", {"step": 20, "path": "/x/checkpoints/00000020", "seconds": 0.01})
    em("log", {"level": "error", "message": "x" * (LOG_MAX_CHARS * 3)})
    em("resume", {"step": 10, "path": "/x/10"})
    em.flush()
    steps = [e["payload"]["step"] for e in reg_home.events(rid, ["progress"])]
    assert steps == [1, 5, 9, 13, 17, 20], steps  # the last one always lands...
    assert [e["payload"]["step"] for e in reg_home.events(rid, ["metric"])] == [1, 5, 9, 13, 17, 20]
    assert slept == [1 / 16]  # ...after waiting out the gap, not breaking it
    logs = [e["payload"] for e in reg_home.events(rid, ["log"])]
    assert any(len(p["message"]) <= LOG_MAX_CHARS and "characters cut" in p["message"] for p in logs)
    assert any(p["message"].startswith("resuming from step 10") for p in logs)
    with reg_home.registry.session(readonly=True) as s:
        run = s.get(Run, rid)
        assert (run.step, run.last_checkpoint) == (20, "/x/checkpoints/00000020")
        assert run.loss == pytest.approx(1 / 20) and run.steps_per_s == 100.0


def test_build_train_config(reg_home, tmp_path):
    from registry.models import Run
    from workers.job import JobConfigError, build_train_config

    settings = reg_home.settings
    rid = create(reg_home, tmp_path / "d", steps=77, memory_budget_mb=999)
    with reg_home.registry.session(readonly=True) as s:
        run = s.get(Run, rid)
    cfg = build_train_config(settings, run, lambda r: pytest.fail("no vqvae_run here"))
    assert (cfg.component, cfg.steps, cfg.run_dir, cfg.data) == ("fast_loop", 77, run.run_dir, str(tmp_path / "d"))
    assert cfg.thermal_zone is None and cfg.vcgencmd is None  # the daemon owns thermal
    assert cfg.memory_budget_mb == 999 and cfg.cache_dir == str(settings.cache_dir) and cfg.threads == 1

    def with_config(**config):
        run.config = {"data": "/d", **config}
        return build_train_config(settings, run, lambda r: f"/runs/{r}")

    assert with_config(vqvae_run="r-v").vqvae_dir == "/runs/r-v"
    assert with_config().memory_budget_mb == float(settings.memory_budget_mb)
    for bad, match in [({"bogus_key": 1}, "unknown config key.*'bogus_key'"),
                       ({"thermal_zone": "/sys/x"}, "'thermal_zone' are set by the daemon"),
                       ({"steps": 5}, "steps 5 differs"), ({"component": "vqvae"}, "component 'vqvae' differs"),
                       ({"vqvae_run": "r-v", "vqvae_dir": "/v"}, "both vqvae_run and vqvae_dir"),
                       ({"model_config": [1]}, "model_config must be a JSON object")]:
        with pytest.raises(JobConfigError, match=match):
            with_config(**bad)
    run.config = {}
    with pytest.raises(JobConfigError, match=f"run {rid}: config has no 'data'"):
        build_train_config(settings, run, lambda r: r)


def test_vqvae_run_resolves_to_a_completed_vqvae_runs_dir(reg_home, tmp_path):
    from registry import runs
    from workers.job import JobConfigError, vqvae_dir_of
    from registry.report_channel import snapshot_of

    vq = create(reg_home, tmp_path / "d", steps=10, component="vqvae")
    fast = create(reg_home, tmp_path / "d", steps=10, vqvae_run=vq)
    nope = create(reg_home, tmp_path / "d", steps=10, vqvae_run="r-nope")

    def resolve(rid):  # what the claim hands the job, then what the job makes of it
        with reg_home.registry.session(readonly=True) as s:
            snap = snapshot_of(s, runs.get_run(s, rid))
        return vqvae_dir_of(snap)(snap.config["vqvae_run"])

    with pytest.raises(JobConfigError, match=f"run {fast}: vqvae_run {vq} is a queued vqvae run, not a completed"):
        resolve(fast)
    with pytest.raises(JobConfigError, match=f"run {nope}: vqvae_run r-nope does not exist"):
        resolve(nope)
    with reg_home.registry.session() as s:
        run = runs.get_run(s, vq)
        runs.transition(s, run, "starting")
        runs.transition(s, run, "running")
        runs.transition(s, run, "completed")
    assert resolve(fast) == reg_home.run(vq)["run_dir"]


# -- a real worker process -----------------------------------------------------------------------------

@pytest.fixture(scope="module")
def world(tmp_path_factory):
    """A tmp $HOPE_HOME, the Celery app the daemon would use, and one real worker on queue pi."""
    from workers.celery import create_celery

    data = tiny_dataset_path(tmp_path_factory)
    home = Home(tmp_path_factory.mktemp("worker") / "home")
    home.registry  # migrate before the worker's children open it with migrate=False
    worker = start_worker(home, "pi")
    wait_until(lambda: "ready" in home.logs[-1].read_text(errors="replace"), 60, "the worker to be ready", home)
    yield home, create_celery(home.settings), worker, data
    code = worker.stop()
    home.close()
    assert code == 0, f"the worker exited with {code} on SIGTERM\n{home.describe()}"


@pytest.fixture
def cleanup(world):
    """Runs a test leaves starting or running are cancelled, so the next test's jobs are not stuck
    behind them."""
    from registry import runs

    home = world[0]
    yield
    with home.registry.session() as s:
        live = []
        for run in runs.list_runs(s, states=runs.ACTIVE):
            runs.request_control(s, run.id, "cancel")  # a starting one (never claimed) ends at once
            if run.state == "running":
                live.append(run.id)
    for rid in live:
        wait_state(home, rid, {"cancelled", "completed", "failed", "paused", "queued"}, 30)


def test_real_worker_trains_a_run_to_completion(world, cleanup):
    home, app, worker, data = world
    rid = create(home, data, steps=300, checkpoint_every_steps=100)
    dispatch(home, app, rid)
    run = wait_state(home, rid, {"completed", "failed", "cancelled"}, 60)
    assert run["state"] == "completed", home.describe()
    assert run["step"] == 300 and run["loss"] is not None and run["started_at"] and run["finished_at"]
    assert run["worker_pid"] is None and run["error"] is None
    assert checkpoint_step(run["last_checkpoint"]) == 300 and Path(run["last_checkpoint"]).is_dir()

    events = home.events(rid)
    progress = [e for e in events if e["kind"] == "progress"]
    assert progress[-1]["payload"]["step"] == 300 and progress[-1]["payload"]["total"] == 300
    assert len(progress) >= 2
    from datetime import datetime

    times = [datetime.fromisoformat(e["time"]) for e in progress]
    gaps = [(b - a).total_seconds() for a, b in zip(times, times[1:])]
    assert min(gaps) >= 0.19, f"progress events closer than 0.2 s (more than 5/s): {gaps}"
    # log_every=1: the trainer emitted 300 progress events; the registry got a handful
    assert len(progress) < 300 / 5
    assert [e["payload"]["step"] for e in events if e["kind"] == "checkpoint"] == [100, 200, 300]
    assert home.states(rid) == ["queued", "starting", "running", "completed"]
    claimed = [e for e in events if e["kind"] == "log" and e["payload"]["message"].startswith("claimed by pid")]
    assert len(claimed) == 1 and f"pid {worker.pid} " not in claimed[0]["payload"]["message"]
    assert not maps_has_libtorch(worker.pid), "the worker parent loaded libtorch"
    broker = sqlite3.connect(home.path / "broker" / "broker.sqlite")
    assert broker.execute("SELECT count(*) FROM kombu_message").fetchone()[0] == 0, "delivered messages pile up"


def test_stale_delivery_does_not_train(world, cleanup):
    home, app, worker, data = world
    rid = create(home, data, steps=40)
    task_id = dispatch(home, app, rid, send_id=str(uuid.uuid4()))  # a task id the run does not know
    dispatch(home, app, rid, task_id=task_id, attempt=2)  # the right id, a wrong attempt

    def stale_notes():
        return [e for e in home.events(rid, ["log"]) if "ignored a stale delivery" in e["payload"]["message"]]

    wait_until(lambda: len(stale_notes()) == 2, 30, "two stale deliveries to be refused", home)
    run = home.run(rid)
    assert run["state"] == "starting" and run["worker_pid"] is None and run["step"] == 0
    assert home.events(rid, ["progress", "checkpoint"]) == [] and not Path(run["run_dir"]).exists()

    dispatch(home, app, rid, task_id=task_id)  # the real delivery trains
    assert wait_state(home, rid, {"completed", "failed"}, 60)["state"] == "completed", home.describe()


def test_pickle_message_is_refused(world, cleanup):
    from registry import runs

    home, app, worker, data = world
    rid = create(home, data, steps=40)
    dispatch(home, app, rid, serializer="pickle")
    wait_until(lambda: "Refusing to deserialize" in worker.log.read_text(errors="replace"), 30,
               "the worker to refuse a pickled message", home)
    run = home.run(rid)
    assert run["state"] == "starting" and run["worker_pid"] is None and run["step"] == 0
    with home.registry.session() as s:  # nobody will claim it: retire it
        runs.transition(s, runs.get_run(s, rid), "cancelled", reason="test")


def test_pause_resume_cancel_through_the_registry(world, cleanup):
    from registry import runs

    home, app, worker, data = world
    # checkpoints only when asked to stop (every 10^6 steps otherwise)
    rid = create(home, data, steps=200_000, checkpoint_every_steps=1_000_000, log_every=5)
    dispatch(home, app, rid)
    run = wait_until(lambda: (r := home.run(rid))["step"] >= 20 and r, 60, "the run to train 20 steps", home)
    child = run["worker_pid"]
    assert child and child != worker.pid
    assert maps_has_libtorch(child), "the check would not see torch in a process that has it"
    assert not maps_has_libtorch(worker.pid), "the worker parent loaded libtorch"

    with home.registry.session() as s:
        runs.request_control(s, rid, "pause")
    t0 = time.monotonic()
    paused = wait_state(home, rid, {"paused", "failed", "cancelled", "completed"}, 10)
    assert paused["state"] == "paused" and paused["pause_reason"] == "user", home.describe()
    assert time.monotonic() - t0 < 3.0
    assert checkpoint_step(paused["last_checkpoint"]) == paused["step"] >= 20
    assert Path(paused["last_checkpoint"], "model.safetensors").is_file()

    with home.registry.session() as s:
        runs.request_control(s, rid, "resume")
    assert home.run(rid)["state"] == "queued"
    dispatch(home, app, rid)
    resumed_at = paused["step"]
    wait_until(lambda: home.run(rid)["step"] > resumed_at + 10, 60, "the resumed run to train on", home)
    assert any(e["payload"]["message"].startswith(f"resuming from step {resumed_at}")
               for e in home.events(rid, ["log"])), home.describe()

    with home.registry.session() as s:
        runs.request_control(s, rid, "cancel")
    t0 = time.monotonic()
    done = wait_state(home, rid, {"cancelled", "failed", "completed", "paused"}, 10)
    assert done["state"] == "cancelled", home.describe()
    assert time.monotonic() - t0 < 3.0
    assert checkpoint_step(done["last_checkpoint"]) == done["step"] > resumed_at + 10
    assert home.states(rid) == ["queued", "starting", "running", "paused", "queued", "starting", "running",
                                "cancelled"]


def test_bad_config_and_bad_data_fail_with_a_message(world, cleanup):
    home, app, worker, data = world
    bad_key = create(home, data, steps=40, bogus_key=1)
    no_data = create(home, data, steps=40)
    from registry.models import Run

    with home.registry.session() as s:
        s.get(Run, no_data).config = {**BASE_CONFIG, "data": str(data.parent / "missing-ds")}
    for rid in (bad_key, no_data):
        dispatch(home, app, rid)
    failed = wait_state(home, bad_key, {"failed", "completed", "cancelled"}, 30)
    assert failed["state"] == "failed" and "bogus_key" in failed["error"] and bad_key in failed["error"]
    failed = wait_state(home, no_data, {"failed", "completed", "cancelled"}, 30)
    assert failed["state"] == "failed" and "missing-ds: no such file or directory" in failed["error"]
    assert any(e["payload"]["level"] == "error" for e in home.events(no_data, ["log"]))


@pytest.mark.parametrize("target", ["group", "parent"])
def test_service_stop_checkpoints_requeues_and_exits(target, tmp_path, tmp_path_factory):
    """Stopping the worker mid-job: the child checkpoints and puts the run back in the queue (same
    attempt), the parent waits for that (warm shutdown) and exits 0. "group": systemd's stop with
    KillMode=control-group signals parent and child at once; "parent": only the parent is
    signalled (serve, KillMode=mixed, a terminal) and passes SIGTERM on to the job's child."""
    from workers.celery import create_celery

    data = tiny_dataset_path(tmp_path_factory)
    home = Home(tmp_path / "home")
    home.registry
    worker = start_worker(home, "pi")
    try:
        wait_until(lambda: "ready" in worker.log.read_text(errors="replace"), 60, "the worker to be ready", home)
        rid = create(home, data, steps=200_000, checkpoint_every_steps=1_000_000, log_every=5)
        dispatch(home, create_celery(home.settings), rid)
        run = wait_until(lambda: (r := home.run(rid))["step"] >= 10 and r, 60, "the run to train 10 steps", home)
        assert run["worker_pid"] in worker.children()
        if target == "group":
            os.killpg(worker.pid, signal.SIGTERM)
        else:
            os.kill(worker.pid, signal.SIGTERM)
        # Within systemd's TimeoutStopSec (60 s in hope-worker.service) all told: a checkpoint's
        # fsync waits for whatever else the disk is writing, seconds on a busy machine.
        back = wait_state(home, rid, {"queued", "paused", "failed", "cancelled"}, 30)
        assert back["state"] == "queued" and back["attempt"] == 1, home.describe()
        assert checkpoint_step(back["last_checkpoint"]) == back["step"] >= 10
        last_state = home.events(rid, ["state"])[-1]["payload"]
        assert last_state["reason"] == "shutdown" and "resumes on next start" in last_state["message"]
        assert worker.popen.wait(30) == 0, home.describe()
    finally:
        worker.stop()
        home.close()


def test_a_run_may_not_take_more_memory_than_the_worker_was_given(reg_home, tmp_path):
    """memory_budget_mb in a run's config may lower the worker's budget, never raise it: a row
    that asks for more (written past the door's check, run_request.preflight) is refused before
    the job builds anything."""
    from registry.models import Run
    from workers.job import JobConfigError, build_train_config

    settings = reg_home.settings
    rid = create(reg_home, tmp_path / "d", steps=5)
    with reg_home.registry.session(readonly=True) as s:
        run = s.get(Run, rid)
    for budget in (settings.memory_budget_mb + 1, 1e12):
        run.config = {"data": "/d", "memory_budget_mb": budget}
        with pytest.raises(JobConfigError, match=f"more than this worker's budget of {settings.memory_budget_mb} MB"):
            build_train_config(settings, run, lambda r: pytest.fail("no vqvae_run here"))
    run.config = {"data": "/d", "memory_budget_mb": 100}
    assert build_train_config(settings, run, lambda r: pytest.fail("no vqvae_run here")).memory_budget_mb == 100
