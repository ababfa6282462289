"""Workers (registry/workers.py, workers/heartbeat.py, the "worker" report of daemon/remote.py,
GET /api/workers): a real local worker beats into the registry with its queue and its current run
and is stopped after its shutdown; a remote worker's beats arrive through Redis (fakeredis) with
report "redis"; a malformed worker report is dropped with a log line; a worker that stops beating
turns offline; the order and the queue counts of the endpoint."""
from __future__ import annotations

import json
import logging
import uuid
from datetime import datetime, timedelta, timezone
from pathlib import Path

import fakeredis
import pytest

from daemon.remote import RemoteReports
from daemon_fixtures import Home, home, procs, redis_server, start_worker, tiny_dataset, wait_until  # noqa: F401
from registry import runs, workers
from registry.models import new_run_id
from registry.report_protocol import REPORTS_KEY, worker_report
from registry.workers import WorkerBeat
from workers.heartbeat import WorkerHeartbeat, report_mode

NOW = datetime.now(timezone.utc)


@pytest.fixture(autouse=True)
def _now():
    """Each test's own NOW: set at import, it would be minutes old by the time a test runs under
    xdist, and beats 'a second ago' would read as long silent."""
    global NOW
    NOW = datetime.now(timezone.utc)


def api_get(home, path: str):
    from webapp import create_app
    from webapp.auth import load_or_create_token

    token = load_or_create_token(home.settings)
    app, _ = create_app(home.settings, token=token, registry=home.registry)
    try:
        r = app.test_client().get(path, headers={"Authorization": f"Bearer {token}"})
        return r.status_code, r.get_json()
    finally:
        app.extensions["hope"].close()


def beat(name, *, ago_s=0.0, queues=("pi",), current=None, report="db", heartbeat_s=5.0, pid=100) -> WorkerBeat:
    return WorkerBeat(name=name, host="box", pid=pid, queues=list(queues), report=report, heartbeat_s=heartbeat_s,
                      started_at=NOW - timedelta(hours=1), current_run_id=current, at=NOW - timedelta(seconds=ago_s))


def add_run(home, data, queue="pi", steps=50) -> str:
    return home.enqueue(data, steps=steps, queue=queue)


def test_states_order_and_queue_counts(home, tiny_dataset):
    queued = add_run(home, tiny_dataset, queue="gpu")
    active = add_run(home, tiny_dataset)
    with home.registry.session() as s:
        runs.mark_dispatched(s, runs.get_run(s, active), "t-1")
        workers.record_beat(s, beat("old@box", ago_s=40))                       # 8 intervals silent
        workers.record_beat(s, beat("pi@box", ago_s=1, current=active))
        workers.record_beat(s, beat("gpu@desk", ago_s=30, queues=["gpu"], report="redis", heartbeat_s=20))
        workers.record_beat(s, beat("gone@box", ago_s=2, queues=["cpu"]))
        assert workers.mark_stopped(s, "gone@box", 100, at=NOW - timedelta(seconds=2))
        assert not workers.mark_stopped(s, "pi@box", 999)  # another process's row is left alone
    code, body = api_get(home, "/api/workers")
    assert code == 200 and body["heartbeat_s"] == 5.0
    got = [(w["name"], w["state"]) for w in body["workers"]]
    # online first (each judged by its own interval: 30 s < 3 x 20 s), then last_seen, newest first
    assert got == [("pi@box", "online"), ("gpu@desk", "online"), ("gone@box", "stopped"), ("old@box", "offline")]
    pi = body["workers"][0]
    assert pi["current"] == {"run_id": active, "component": "fast_loop", "state": "starting", "step": 0,
                             "total_steps": 50}
    assert pi["queues"] == ["pi"] and pi["report"] == "db" and pi["host"] == "box" and pi["pid"] == 100
    assert datetime.fromisoformat(pi["last_seen"]) == NOW - timedelta(seconds=1)
    assert body["workers"][1]["report"] == "redis" and body["workers"][2]["current"] is None
    assert body["queues"] == [
        {"name": "cpu", "queued": 0, "starting": 0, "running": 0, "paused": 0, "workers_online": 0},
        {"name": "gpu", "queued": 1, "starting": 0, "running": 0, "paused": 0, "workers_online": 1},
        {"name": "pi", "queued": 0, "starting": 1, "running": 0, "paused": 0, "workers_online": 1}]
    assert queued
    assert api_get(home, "/api/workers?all=1")[0] == 400


def test_a_worker_that_stops_beating_turns_offline(home):
    hb = WorkerHeartbeat(home.settings, "pi@here", ["pi"], interval_s=0.2, current=lambda: None)
    assert report_mode(home.settings) is None  # no registry yet, no Redis: nowhere to beat
    assert hb.beat() is None
    home.registry  # the daemon's first start migrates it
    assert report_mode(home.settings) == "db"
    hb.beat()
    with home.registry.session(readonly=True) as s:
        assert [w["state"] for w in workers.list_workers(s)] == ["online"]
        # no beat for 3 intervals (0.6 s): offline, though never stopped
        assert [w["state"] for w in workers.list_workers(s, now=NOW + timedelta(seconds=60))] == ["offline"]
        row = workers.list_workers(s)[0]
    assert row["stopped_at"] is None and row["heartbeat_s"] == 0.2 and row["report"] == "db"
    hb.beat()  # it comes back: online again
    hb.stop()
    with home.registry.session(readonly=True) as s:
        assert [w["state"] for w in workers.list_workers(s)] == ["stopped"]


def remote_worker(tmp_path, client, current):
    """A worker on another machine: its own HOPE_HOME (no registry), a Redis URL."""
    elsewhere = Home(tmp_path / "desk", redis_url="redis://desk.invalid:6379/0")
    assert report_mode(elsewhere.settings) == "redis"
    return WorkerHeartbeat(elsewhere.settings, "gpu@desk", ["gpu"], interval_s=1.0, host="desk", pid=4242,
                           current=lambda: current, redis_client=client)


def test_a_remote_workers_beats_arrive_through_redis(home, tiny_dataset, tmp_path, caplog):
    client = fakeredis.FakeRedis()
    rid = add_run(home, tiny_dataset, queue="gpu")
    hb = remote_worker(tmp_path, client, rid)
    remote = RemoteReports(home.registry, client, local_queues=("pi",))
    hb.beat()
    with caplog.at_level(logging.INFO, logger="daemon.remote"):
        assert remote.poll() == 1 and remote.dropped == 0
    assert any("gpu@desk" in r.getMessage() and "through Redis" in r.getMessage() for r in caplog.records)
    code, body = api_get(home, "/api/workers")
    (w,) = body["workers"]
    assert (w["name"], w["host"], w["pid"], w["queues"], w["report"], w["state"]) == \
        ("gpu@desk", "desk", 4242, ["gpu"], "redis", "online")
    assert w["current"]["run_id"] == rid and w["current"]["state"] == "queued"
    assert body["queues"] == [{"name": "gpu", "queued": 1, "starting": 0, "running": 0, "paused": 0,
                               "workers_online": 1}]
    # applied reports are trimmed; last_seen is the daemon's clock, not the remote one's (which may
    # be far off: a beat stamped 10 minutes ago still shows the worker online)
    assert client.llen(REPORTS_KEY) == 0
    client.rpush(REPORTS_KEY, worker_report(beat("gpu@desk", ago_s=600, queues=["gpu"], current=rid, pid=4242)))
    assert remote.poll() == 1 and remote.dropped == 0
    (w,) = api_get(home, "/api/workers")[1]["workers"]
    assert w["state"] == "online" and w["pid"] == 4242
    assert datetime.fromisoformat(w["last_seen"]) > NOW
    first_seen = w["last_seen"]
    hb.stop()
    remote.poll()
    (w,) = api_get(home, "/api/workers")[1]["workers"]
    assert w["state"] == "stopped" and w["current"] is None and w["last_seen"] >= first_seen


@pytest.mark.parametrize("bad, why", [
    ({"name": "gpu@desk"}, "'host' must be str"),
    ({"queues": []}, "queues must be"),
    ({"queues": ["GPU; rm -rf"]}, "queues must be"),
    ({"pid": True}, "'pid' must be int"),
    ({"heartbeat_s": 0}, "heartbeat_s must be"),
    ({"event": "exploded"}, "event 'exploded'"),
    ({"current_run_id": 7}, "'current_run_id' must be str"),
])
def test_a_malformed_worker_report_is_dropped_with_a_log_line(home, tmp_path, caplog, bad, why):
    client = fakeredis.FakeRedis()
    good = json.loads(worker_report(beat("gpu@desk")))
    msg = {**good, **bad}
    if bad == {"name": "gpu@desk"}:
        msg.pop("host")
    client.rpush(REPORTS_KEY, json.dumps(msg))
    client.rpush(REPORTS_KEY, json.dumps(good))  # the next one still applies
    remote = RemoteReports(home.registry, client)
    with caplog.at_level(logging.WARNING, logger="daemon.remote"):
        assert remote.poll() == 2
    assert remote.dropped == 1 and remote.applied == 1 and client.llen(REPORTS_KEY) == 0
    lines = [r.getMessage() for r in caplog.records if "malformed remote report dropped" in r.getMessage()]
    assert len(lines) == 1 and why in lines[0], lines
    with home.registry.session(readonly=True) as s:
        assert [w["name"] for w in workers.list_workers(s)] == ["gpu@desk"]


def test_a_real_local_worker_beats_with_its_queue_and_current_run(tmp_path, tiny_dataset, procs):
    from test_worker import maps_has_libtorch
    from workers.celery import create_celery

    home = Home(tmp_path / "home", extra_env={"HOPE_WORKER_HEARTBEAT_S": "0.3"})
    try:
        home.registry  # migrated before the worker starts
        worker = start_worker(home, "pi")
        procs.append(worker)

        def listed():
            with home.registry.session(readonly=True) as s:
                return workers.list_workers(s)

        w = wait_until(lambda: [w for w in listed() if w["state"] == "online"], 60, "the worker to beat", home)[0]
        assert (w["name"], w["pid"], w["queues"], w["report"], w["current"]) == \
            (f"worker-pi@{w['host']}", worker.pid, ["pi"], "db", None)
        rid = home.enqueue(tiny_dataset, steps=5000)
        with home.registry.session() as s:
            runs.mark_dispatched(s, runs.get_run(s, rid), task := str(uuid.uuid4()))
        create_celery(home.settings).send_task("hope.train_run", args=[rid, 1], queue="pi", task_id=task)
        w = wait_until(lambda: (x := listed()[0])["current"] and x["current"]["state"] == "running" and x, 60,
                       "the worker to report its current run", home)
        assert w["current"]["run_id"] == rid and w["current"]["component"] == "fast_loop"
        assert w["current"]["total_steps"] == 5000
        with home.registry.session() as s:
            runs.request_control(s, rid, "cancel")
        wait_until(lambda: home.run(rid)["state"] == "cancelled", 30, "the run to be cancelled", home)
        wait_until(lambda: listed()[0]["current"] is None, 10, "the current run to clear", home)
        assert not maps_has_libtorch(worker.pid), "the worker parent loaded libtorch"
        assert worker.stop() == 0
        (w,) = listed()
        assert w["state"] == "stopped" and w["current"] is None
        assert "heartbeat every 0.3 s into the registry" in Path(worker.log).read_text()
    finally:
        home.close()


def test_a_real_remote_worker_beats_through_a_real_redis(tmp_path, redis_server, procs):
    """The worker parent on "another machine" (its own HOPE_HOME, no registry) beats through a real
    redis-server; the daemon's side (RemoteReports) writes its row with report "redis"."""
    import redis

    pi = Home(tmp_path / "pi", redis_url=redis_server.url)
    desk = Home(tmp_path / "desk", redis_url=redis_server.url, extra_env={"HOPE_WORKER_HEARTBEAT_S": "0.3"})
    client = redis.Redis.from_url(redis_server.url)
    try:
        remote = RemoteReports(pi.registry, client, local_queues=("pi",))
        worker = start_worker(desk, "gpu")
        procs.append(worker)

        def listed():
            remote.poll()
            with pi.registry.session(readonly=True) as s:
                return workers.list_workers(s)

        (w,) = wait_until(lambda: [w for w in listed() if w["state"] == "online"], 60, "the remote worker's beat", desk)
        assert (w["name"], w["pid"], w["queues"], w["report"]) == (f"worker-gpu@{w['host']}", worker.pid, ["gpu"],
                                                                  "redis")
        assert not (desk.path / "hope.db").exists(), "the remote worker opened a registry of its own"
        assert worker.stop() == 0
        (w,) = listed()
        assert w["state"] == "stopped" and remote.dropped == 0
    finally:
        client.close()
        pi.close()
