"""Remote workers' reports through Redis (registry/report_protocol.py, workers/report.py,
daemon/remote.py), in process: a real registry, Redis replaced by fakeredis. The real processes (a
worker with its own HOPE_HOME, a real redis-server) are in test_daemon_redis.py.
- RemoteReports applies each report type to the registry, in order, and answers claims;
- malformed reports are dropped with a log, and never stop the ones after them;
- a busy registry leaves the reports in Redis for the next tick;
- RedisChannel (the remote child's side) against RemoteReports: claim, control, finish; a claim
  nobody answers is withdrawn and then never applied;
- which report mode the dispatcher puts in the task, and the daemon's tick doing both halves.
"""
from __future__ import annotations

import json
import logging
import threading
import time
from datetime import datetime, timedelta, timezone

import fakeredis
import pytest

from registry import runs
from daemon.remote import RemoteReports
from daemon_fixtures import Home, tiny_dataset  # noqa: F401
from registry.report_channel import RegistryChannel
from registry.report_protocol import (REPORTS_KEY, BadReport, ChannelError, ControlRow, StaleDelivery, claim_key,
                                      control_key, parse_report)
from workers.report import RedisChannel

HOST = "gpu-box"
PID = 777


@pytest.fixture
def rhome(tmp_path):
    # A Redis URL in the settings makes queues outside local_queues remote; fakeredis stands in.
    h = Home(tmp_path / "home", redis_url="redis://127.0.0.1:1/0")
    yield h
    h.close()


@pytest.fixture
def redis_client():
    return fakeredis.FakeRedis()


@pytest.fixture
def remote(rhome, redis_client):
    return RemoteReports(rhome.registry, redis_client, local_queues=("pi",))


def dispatched(home: Home, data, *, queue: str = "gpu", task_id: str = "task-1", vqvae_run: str | None = None,
               **kw) -> str:
    """A run marked dispatched under task_id, as the daemon leaves it before the child claims."""
    rid = home.enqueue(data, queue=queue, **kw)
    with home.registry.session() as s:
        run = runs.get_run(s, rid)
        if vqvae_run is not None:  # a chain member's link (enqueue checks it exists; here it may not)
            run.config = {**run.config, "vqvae_run": vqvae_run}
        runs.mark_dispatched(s, run, task_id)
    return rid


def report(type_: str, run_id: str, *, task_id: str = "task-1", attempt: int = 1, pid: int = PID, host: str = HOST,
           t: float | None = None, **fields) -> str:
    return json.dumps({"type": type_, "run_id": run_id, "task_id": task_id, "attempt": attempt, "pid": pid,
                       "host": host, "time": time.time() if t is None else t, **fields})


def push(client, *messages) -> None:
    client.rpush(REPORTS_KEY, *messages)


def answer(client, run_id: str, task_id: str = "task-1") -> dict:
    raw = client.get(claim_key(run_id, task_id))
    assert raw is not None, f"no claim answer for {run_id}/{task_id}"
    return json.loads(raw)


def control(client, run_id: str) -> dict:
    raw = client.get(control_key(run_id))
    assert raw is not None, f"no control state published for {run_id}"
    return json.loads(raw)


# -- applying reports ---------------------------------------------------------------------------

def test_claim_is_answered_with_the_run_and_its_control_state(rhome, tiny_dataset, remote, redis_client):
    vq = rhome.enqueue(tiny_dataset, component="vqvae", steps=10)
    with rhome.registry.session() as s:
        run = runs.get_run(s, vq)
        runs.transition(s, run, "starting")
        runs.transition(s, run, "running")
        runs.transition(s, run, "completed")
    rid = dispatched(rhome, tiny_dataset, steps=30, vqvae_run=vq)
    push(redis_client, report("claim", rid))
    assert remote.poll() == 1 and redis_client.llen(REPORTS_KEY) == 0

    got = answer(redis_client, rid)
    assert got["ok"] is True
    snap = got["run"]
    row = rhome.run(rid)
    assert (snap["id"], snap["component"], snap["total_steps"], snap["run_dir"], snap["attempt"]) == \
        (rid, "fast_loop", 30, row["run_dir"], 1)
    assert snap["config"] == row["config"] and snap["vqvae_dir"] == rhome.run(vq)["run_dir"]
    assert snap["vqvae_error"] is None
    assert (row["worker_pid"], row["worker_host"]) == (PID, HOST)
    # the control state is there before the child reads it, and names the child as the holder
    assert control(redis_client, rid) == {"state": "running", "worker_pid": PID, "worker_host": HOST,
                                          "desired_state": "run", "throttle_level": 0, "requested_reason": None}
    assert redis_client.ttl(claim_key(rid, "task-1")) > 0 and redis_client.ttl(control_key(rid)) > 0


def test_stale_claims_are_refused_with_why(rhome, tiny_dataset, remote, redis_client):
    rid = dispatched(rhome, tiny_dataset)
    other = dispatched(rhome, tiny_dataset, queue="gpu2", vqvae_run="r-nope")
    push(redis_client, report("claim", rid, task_id="old-task"),  # not the run's task id
         report("claim", rid, attempt=2),  # not its attempt
         report("claim", "r-missing"),
         report("claim", other))  # claimed fine; its vqvae_run cannot be resolved: the job fails with this
    assert remote.poll() == 4
    refused = answer(redis_client, rid, "old-task")
    assert refused["ok"] is False and refused["status"] == "stale"
    assert "ignored a stale delivery (task old-task, attempt 1)" in refused["why"]
    wrong_attempt = answer(redis_client, rid)
    assert wrong_attempt["ok"] is False and "attempt 2" in wrong_attempt["why"]
    missing = answer(redis_client, "r-missing")
    assert missing == {"ok": False, "status": "missing", "why": missing["why"]} and "no run r-missing" in missing["why"]
    assert rhome.run(rid)["worker_pid"] is None  # nobody claimed it
    logs = [e["payload"]["message"] for e in rhome.events(rid, ["log"])]
    assert sum("ignored a stale delivery" in m for m in logs) == 2
    assert answer(redis_client, other)["run"]["vqvae_error"] == f"run {other}: vqvae_run r-nope does not exist"


def test_heartbeats_events_requests_and_finish_are_applied_in_order(rhome, tiny_dataset, remote, redis_client):
    rid = dispatched(rhome, tiny_dataset, steps=100)
    past = time.time() - 30
    push(redis_client,
         report("claim", rid),
         report("heartbeat", rid),
         report("event", rid, kind="progress", t=past,
                payload={"step": 5, "total": 100, "loss": 0.5, "steps_per_s": 9.0},
                row={"step": 5, "loss": 0.5, "steps_per_s": 9.0}),
         report("event", rid, kind="checkpoint", payload={"step": 10, "path": "/ck/10"},
                row={"step": 10, "last_checkpoint": "/ck/10"}),
         report("event", rid, kind="log", payload={"level": "info", "message": "from far away"}),
         report("event", rid, kind="progress", t=time.time() + 3600,  # a clock ahead: not in the future
                payload={"step": 11, "total": 100, "loss": float("nan")}, row={"step": 11}),
         report("control_request", rid, request="shutdown"))
    assert remote.poll() == 7 and remote.dropped == 0
    run = rhome.run(rid)
    assert (run["step"], run["loss"], run["steps_per_s"], run["last_checkpoint"]) == (11, 0.5, 9.0, "/ck/10")
    assert (run["desired_state"], run["requested_reason"]) == ("pause", "shutdown")
    progress = rhome.events(rid, ["progress"])
    assert [e["payload"]["step"] for e in progress] == [5, 11]
    first = datetime.fromisoformat(progress[0]["time"])
    assert abs(first.timestamp() - past) < 0.01  # when it happened on the remote box
    assert datetime.fromisoformat(progress[1]["time"]) <= datetime.now(timezone.utc)
    assert progress[1]["payload"]["loss"] is None
    assert [e["payload"]["step"] for e in rhome.events(rid, ["checkpoint"])] == [10]
    assert any(e["payload"]["message"] == "from far away" for e in rhome.events(rid, ["log"]))

    push(redis_client, report("finish", rid, outcome="paused_user", message="paused at step 12", step=12,
                              last_checkpoint="/ck/12"))
    assert remote.poll() == 1
    run = rhome.run(rid)
    assert (run["state"], run["attempt"], run["step"], run["last_checkpoint"]) == ("queued", 1, 12, "/ck/12")
    assert rhome.events(rid, ["state"])[-1]["payload"]["reason"] == "shutdown"
    assert control(redis_client, rid)["state"] == "queued"  # published at once: the run left running


def test_reports_of_a_superseded_child_change_nothing_and_tell_it(rhome, tiny_dataset, remote, redis_client):
    rid = dispatched(rhome, tiny_dataset, steps=100)
    push(redis_client, report("claim", rid))
    remote.poll()
    # the same pid on another host, and another pid on this host: neither holds the run
    for pid, host in ((PID, "other-box"), (PID + 1, HOST)):
        push(redis_client,
             report("heartbeat", rid, pid=pid, host=host, row={"step": 50}),
             report("event", rid, pid=pid, host=host, kind="progress", payload={"step": 60}, row={"step": 60}),
             report("control_request", rid, pid=pid, host=host, request="shutdown"),
             report("finish", rid, pid=pid, host=host, outcome="completed", message="done", step=100,
                    last_checkpoint=None))
        assert remote.poll() == 4
    run = rhome.run(rid)
    assert (run["state"], run["step"], run["desired_state"], run["worker_pid"]) == ("running", 0, "run", PID)
    # its events are kept as its log, like a local superseded child's
    assert [e["payload"]["step"] for e in rhome.events(rid, ["progress"])] == [60, 60]
    # the control state names the real holder, so the stale child stops
    assert not ControlRow.from_json_obj(control(redis_client, rid)).owned_by(PID + 1, HOST)
    assert ControlRow.from_json_obj(control(redis_client, rid)).owned_by(PID, HOST)


def test_a_second_finish_or_claim_is_harmless(rhome, tiny_dataset, remote, redis_client):
    """A daemon killed between applying reports and trimming them applies them again."""
    rid = dispatched(rhome, tiny_dataset, steps=100)
    claim = report("claim", rid)
    push(redis_client, claim, claim)
    assert remote.poll() == 2
    assert answer(redis_client, rid)["ok"] is True  # the first answer stands
    redis_client.delete(claim_key(rid, "task-1"))  # the child read it
    push(redis_client, claim)
    remote.poll()
    assert answer(redis_client, rid)["ok"] is True  # the same child is answered the same
    done = report("finish", rid, outcome="completed", message="done", step=100, last_checkpoint="/ck/100")
    push(redis_client, done, done)
    assert remote.poll() == 2
    assert rhome.states(rid) == ["queued", "starting", "running", "completed"]
    claims = [e for e in rhome.events(rid, ["log"]) if e["payload"]["message"].startswith("claimed by pid")]
    assert len(claims) == 1


BAD = [
    (b"\xff\xfe not json", "not JSON"),
    ("[1, 2]", "not a JSON object"),
    ('{"type": "explode", "run_id": "r"}', "type 'explode' is not one of"),
    (json.dumps({"type": "heartbeat", "run_id": "r", "task_id": "t", "attempt": "1", "pid": 1, "host": "h",
                 "time": 1.0}), "'attempt' must be int"),
    (json.dumps({"type": "heartbeat", "run_id": "r", "task_id": "t", "attempt": 1, "pid": True, "host": "h",
                 "time": 1.0}), "'pid' must be int"),
    (json.dumps({"type": "heartbeat", "run_id": "", "task_id": "t", "attempt": 1, "pid": 1, "host": "h",
                 "time": 1.0}), "must be non-empty"),
    (json.dumps({"type": "heartbeat", "run_id": "r", "task_id": "t", "attempt": 1, "pid": 1, "host": "h",
                 "time": 1.0, "row": {"state": "completed"}}), "row fields \\['state'\\]"),
    (json.dumps({"type": "event", "run_id": "r", "task_id": "t", "attempt": 1, "pid": 1, "host": "h",
                 "time": 1.0, "kind": "progress", "payload": [1]}), "'payload' must be dict"),
    (json.dumps({"type": "control_request", "run_id": "r", "task_id": "t", "attempt": 1, "pid": 1, "host": "h",
                 "time": 1.0, "request": "reboot"}), "request 'reboot' is not one of"),
    (json.dumps({"type": "finish", "run_id": "r", "task_id": "t", "attempt": 1, "pid": 1, "host": "h",
                 "time": 1.0, "outcome": "completed", "message": "m", "step": "12"}), "'step' must be int"),
]


@pytest.mark.parametrize("raw,why", BAD)
def test_parse_report_says_what_is_wrong(raw, why):
    with pytest.raises(BadReport, match=why):
        parse_report(raw)


def test_malformed_and_impossible_reports_are_dropped_and_the_rest_applied(rhome, tiny_dataset, remote,
                                                                            redis_client, caplog):
    rid = dispatched(rhome, tiny_dataset)
    push(redis_client, report("claim", rid), *[raw for raw, _ in BAD],
         report("event", rid, kind="bogus-kind", payload={}),  # well-formed, refused by the registry
         report("finish", rid, outcome="exploded", message="?", step=None, last_checkpoint=None),
         report("heartbeat", rid, row={"step": 7}))
    with caplog.at_level(logging.WARNING, logger="daemon.remote"):
        assert remote.poll() == len(BAD) + 4
    assert remote.dropped == len(BAD) + 2 and remote.applied == 2
    assert redis_client.llen(REPORTS_KEY) == 0
    assert rhome.run(rid)["step"] == 7 and rhome.run(rid)["state"] == "running"
    messages = [r.getMessage() for r in caplog.records]
    assert sum("malformed remote report dropped" in m for m in messages) == len(BAD)
    assert any("event kind 'bogus-kind'" in m for m in messages)
    assert any("outcome 'exploded'" in m for m in messages)


def test_a_busy_registry_leaves_the_reports_for_the_next_tick(rhome, tiny_dataset, remote, redis_client,
                                                               monkeypatch):
    rid = dispatched(rhome, tiny_dataset)
    push(redis_client, report("claim", rid), report("heartbeat", rid, row={"step": 3}),
         report("heartbeat", rid, row={"step": 4}))
    real = RegistryChannel.heartbeat
    busy = [True]

    def heartbeat(self, **row):
        if busy[0]:
            raise ChannelError("database is locked", transient=True)
        return real(self, **row)

    monkeypatch.setattr(RegistryChannel, "heartbeat", heartbeat)
    assert remote.poll() == 1  # the claim; both heartbeats wait, in order
    assert redis_client.llen(REPORTS_KEY) == 2 and rhome.run(rid)["step"] == 0
    busy[0] = False
    assert remote.poll() == 2 and rhome.run(rid)["step"] == 4 and redis_client.llen(REPORTS_KEY) == 0


def test_publish_running_covers_remote_queues_only(rhome, tiny_dataset, remote, redis_client):
    local = dispatched(rhome, tiny_dataset, queue="pi")
    far = dispatched(rhome, tiny_dataset, queue="gpu")
    queued = rhome.enqueue(tiny_dataset, queue="gpu2")
    with rhome.registry.session() as s:
        runs.claim(s, far, "task-1", 1, HOST, PID)  # a remote child trains it (a starting run would end at once)
        runs.request_control(s, far, "cancel")
    assert remote.publish_running() == 1
    assert redis_client.get(control_key(local)) is None and redis_client.get(control_key(queued)) is None
    assert control(redis_client, far)["desired_state"] == "cancel"


# -- the remote child's side against the daemon's -----------------------------------------------

class FakeDaemon:
    """RemoteReports polled in a thread, as the daemon's tick would."""

    def __init__(self, remote: RemoteReports):
        self.remote, self.stop = remote, threading.Event()
        self.thread = threading.Thread(target=self._loop, daemon=True)

    def _loop(self):
        while not self.stop.wait(0.02):
            self.remote.poll()
            self.remote.publish_running()

    def __enter__(self):
        self.thread.start()
        return self

    def __exit__(self, *exc):
        self.stop.set()
        self.thread.join(5)


def test_redis_channel_claims_reads_control_and_finishes(rhome, tiny_dataset, remote, redis_client):
    rid = dispatched(rhome, tiny_dataset, steps=50)
    channel = RedisChannel(redis_client, rid, "task-1", 1, PID, HOST, claim_wait_s=5)
    with FakeDaemon(remote):
        snap = channel.claim()
        assert snap.id == rid and snap.total_steps == 50 and snap.config["data"] == str(tiny_dataset)
        assert redis_client.get(claim_key(rid, "task-1")) is None  # read and removed
        row = channel.control()
        assert row.owned_by(PID, HOST) and row.desired_state == "run"
        assert channel.event("progress", {"step": 3, "loss": 0.25}, {"step": 3, "loss": 0.25}) is True
        with rhome.registry.session() as s:
            runs.request_control(s, rid, "pause")
        deadline = time.monotonic() + 5
        while channel.control().desired_state != "pause":
            assert time.monotonic() < deadline, "the pause never reached the control state"
            time.sleep(0.02)
        assert channel.finish("paused_user", "paused at step 3", step=3, last_checkpoint="/ck/3") == "reported"
        deadline = time.monotonic() + 5
        while rhome.run(rid)["state"] == "running":
            assert time.monotonic() < deadline, "the finish was never applied"
            time.sleep(0.02)
    run = rhome.run(rid)
    assert (run["state"], run["pause_reason"], run["step"], run["loss"]) == ("paused", "user", 3, 0.25)
    assert control(redis_client, rid)["state"] == "paused"


def test_a_claim_nobody_answers_is_withdrawn_and_never_applied(rhome, tiny_dataset, remote, redis_client):
    rid = dispatched(rhome, tiny_dataset)
    channel = RedisChannel(redis_client, rid, "task-1", 1, PID, HOST, claim_wait_s=0.3)
    t0 = time.monotonic()
    with pytest.raises(StaleDelivery, match="did not answer the claim of task task-1 within 0.3 s") as info:
        channel.claim()
    assert info.value.status == "no_answer" and time.monotonic() - t0 < 3
    with pytest.raises(ChannelError, match="no control state in Redis"):
        channel.control()
    assert remote.poll() == 1  # the daemon comes back: the withdrawn claim is skipped
    assert rhome.run(rid)["worker_pid"] is None and rhome.run(rid)["state"] == "starting"


def test_a_claim_answered_as_the_child_gives_up_is_undone(rhome, tiny_dataset, remote, redis_client, monkeypatch):
    """The child withdraws (SET NX) just after the daemon checked and before it answered: the
    daemon finds its answer refused and does not leave the run to a child that is gone."""
    rid = dispatched(rhome, tiny_dataset)
    push(redis_client, report("claim", rid))
    real_claim = RegistryChannel.claim

    def claim_while_the_child_withdraws(self):
        snap = real_claim(self)
        redis_client.set(claim_key(rid, "task-1"), json.dumps({"ok": False, "status": "no_answer"}))
        return snap

    monkeypatch.setattr(RegistryChannel, "claim", claim_while_the_child_withdraws)
    remote.poll()
    run = rhome.run(rid)
    assert (run["state"], run["attempt"], run["worker_pid"]) == ("queued", 2, None)
    assert "withdrew its claim" in rhome.events(rid, ["state"])[-2]["payload"]["message"]


# -- dispatch and the daemon's tick ------------------------------------------------------------

class FakeCelery:
    def __init__(self):
        self.sent = []

    def send_task(self, name, args=None, kwargs=None, queue=None, task_id=None, **_):
        self.sent.append({"name": name, "args": args, "kwargs": kwargs, "queue": queue, "task_id": task_id})


@pytest.mark.parametrize("redis_url,remote_reports,gpu_mode", [
    ("redis://127.0.0.1:1/0", True, "redis"),
    ("redis://127.0.0.1:1/0", False, "db"),  # serve: every queue is local
    (None, True, "db"),  # embedded broker: a worker can only be on this host
])
def test_the_task_says_how_to_report(tmp_path, tiny_dataset, redis_url, remote_reports, gpu_mode):
    from daemon.dispatch import Dispatcher

    home = Home(tmp_path / "home", redis_url=redis_url)
    try:
        pi, gpu = home.enqueue(tiny_dataset, queue="pi"), home.enqueue(tiny_dataset, queue="gpu")
        app = FakeCelery()
        Dispatcher(home.registry, home.settings, celery_app=app, local_queues=("pi",),
                   remote_reports=remote_reports).dispatch(0)
        sent = {m["args"][0]: m for m in app.sent}
        assert sent[pi]["kwargs"] == {"report": "db"} and sent[pi]["queue"] == "pi"
        assert sent[gpu]["kwargs"] == {"report": gpu_mode} and sent[gpu]["queue"] == "gpu"
        assert sent[gpu]["args"] == [gpu, 1] and sent[gpu]["name"] == "hope.train_run"
        json.dumps(app.sent)  # JSON all the way
    finally:
        home.close()


def test_daemon_tick_applies_reports_and_publishes_control(rhome, tiny_dataset, redis_client, tmp_path):
    from daemon.events import ListSink
    from daemon.monitor import SystemMonitor, ThrottlePolicy
    from daemon.service import Daemon

    monitor = SystemMonitor(None, zone_path=str(tmp_path / "no-zone"), vcgencmd=None, thermal_interval_s=0.0)
    app = FakeCelery()
    d = Daemon(rhome.settings, ListSink(), monitor=monitor, policy=ThrottlePolicy(75, 82, 70),
               registry=rhome.registry, celery_app=app, local_queues=("pi",), remote_reports=True,
               redis_client=redis_client)
    d.start()
    rid = rhome.enqueue(tiny_dataset, queue="gpu")
    d.tick()
    (msg,) = app.sent
    assert msg["kwargs"] == {"report": "redis"} and rhome.run(rid)["state"] == "starting"
    push(redis_client, report("claim", rid, task_id=msg["task_id"]),
         report("event", rid, task_id=msg["task_id"], kind="progress", payload={"step": 2}, row={"step": 2}))
    d.tick()
    assert answer(redis_client, rid, msg["task_id"])["ok"] is True and rhome.run(rid)["step"] == 2
    assert control(redis_client, rid)["worker_pid"] == PID
    with rhome.registry.session() as s:
        runs.request_control(s, rid, "cancel")
    d.tick()
    assert control(redis_client, rid)["desired_state"] == "cancel"
    # Redis away: the rest of the tick goes on (the reports wait in Redis)
    down = fakeredis.FakeServer()
    down.connected = False  # fakeredis: every command raises ConnectionError
    d.remote.client = fakeredis.FakeRedis(server=down)
    queued = rhome.enqueue(tiny_dataset, queue="pi")
    assert d.safe_tick() is True and d._remote_failures == 2  # poll and publish both failed...
    assert rhome.run(queued)["state"] == "starting"  # ...and the local queue was still dispatched
    d.stop()


def test_heartbeat_staleness_still_judges_remote_runs(rhome, tiny_dataset, remote, redis_client):
    """Reconcile is unchanged for remote runs: another host's child is judged by its heartbeats,
    which now arrive through reports."""
    from daemon.reconcile import Reconciler

    rid = dispatched(rhome, tiny_dataset)
    push(redis_client, report("claim", rid))
    remote.poll()
    rec = Reconciler(rhome.registry, host="the-pi", heartbeat_timeout_s=30)
    assert rec.reconcile() == []
    with rhome.registry.session() as s:
        runs.get_run(s, rid).heartbeat_at = datetime.now(timezone.utc) - timedelta(seconds=31)
    push(redis_client, report("heartbeat", rid))
    remote.poll()  # a fresh heartbeat arrived in time
    assert rec.reconcile() == []
    with rhome.registry.session() as s:
        runs.get_run(s, rid).heartbeat_at = datetime.now(timezone.utc) - timedelta(seconds=31)
    (action,) = rec.reconcile()
    assert action.action == "interrupted" and f"no heartbeat from worker child pid {PID} on {HOST}" in action.why
    assert rhome.run(rid)["state"] == "queued" and rhome.run(rid)["attempt"] == 2


def test_a_backlog_is_applied_in_batches_in_order(rhome, tiny_dataset, redis_client):
    remote = RemoteReports(rhome.registry, redis_client, local_queues=("pi",), batch=4)
    rid = dispatched(rhome, tiny_dataset, steps=100)
    push(redis_client, report("claim", rid),
         *[report("heartbeat", rid, row={"step": step}) for step in range(1, 10)])
    assert remote.poll() == 4 and rhome.run(rid)["step"] == 3  # one batch per tick
    assert remote.poll(batches=10) == 6 and rhome.run(rid)["step"] == 9  # the rest, at daemon start
    assert redis_client.llen(REPORTS_KEY) == 0 and remote.poll(batches=10) == 0
