"""The daemon's policy against a real registry, with the broker replaced by a list of sent tasks
(the real worker and broker are in test_daemon_processes.py / test_daemon_redis.py): dispatch
order and one-at-a-time, send failures, throttle and thermal/memory requeue, reconcile of dead
and hung children, claim timeouts, chains, event tailing, system.stats."""
from __future__ import annotations

import contextlib
import os
import socket
import subprocess
import sys
import threading
import time
from datetime import timedelta

import pytest

from registry import runs
from daemon.dispatch import Dispatcher
from registry.sequences import create_sequence
from daemon.events import EventTailer, ListSink
from registry.models import utcnow
from daemon.monitor import SystemMonitor, ThrottlePolicy
from daemon.reconcile import Reconciler, child_alive
from daemon.service import Daemon
from daemon_fixtures import Home, home, tiny_dataset, wait_until  # noqa: F401

HOST = socket.gethostname()


class Broker:
    """Stands in for Celery's send_task: records (run_id, attempt, queue, task_id)."""

    def __init__(self):
        self.sent: list[tuple[str, int, str, str]] = []
        self.fail: Exception | None = None

    def __call__(self, run_id, attempt, queue, task_id):
        if self.fail is not None:
            raise self.fail
        self.sent.append((run_id, attempt, queue, task_id))


def claim(home: Home, run_id: str, pid: int, host: str = HOST):
    with home.registry.session() as s:
        run = runs.get_run(s, run_id)
        return runs.claim(s, run_id, run.celery_task_id, run.attempt, host, pid)


def finish(home: Home, run_id: str, pid: int, outcome: str = "completed"):
    with home.registry.session() as s:
        return runs.finish(s, run_id, pid, outcome, "done", step=10, last_checkpoint=None)


@pytest.fixture
def broker():
    return Broker()


@pytest.fixture
def dispatcher(home, broker):
    return Dispatcher(home.registry, home.settings, send=broker, local_queues=("pi",), memory_retry_s=0)


def test_fifo_with_priority_and_one_running_per_queue(home, tiny_dataset, dispatcher, broker):
    a = home.enqueue(tiny_dataset)
    b = home.enqueue(tiny_dataset)
    urgent = home.enqueue(tiny_dataset, priority=5)
    sent = dispatcher.dispatch(0)
    assert [d.run_id for d in sent] == [urgent] and broker.sent[0][:3] == (urgent, 1, "pi")
    assert home.run(urgent)["state"] == "starting" and home.run(urgent)["celery_task_id"] == broker.sent[0][3]
    assert dispatcher.dispatch(0) == []  # one at a time
    claim(home, urgent, 4242)
    assert home.run(urgent)["state"] == "running"
    assert dispatcher.dispatch(0) == []
    finish(home, urgent, 4242)
    assert [d.run_id for d in dispatcher.dispatch(0)] == [a]
    finish(home, a, claim(home, a, 4243).worker_pid)
    assert [d.run_id for d in dispatcher.dispatch(0)] == [b]


def test_queues_dispatch_independently(home, tiny_dataset, dispatcher, broker):
    pi1 = home.enqueue(tiny_dataset)
    pi2 = home.enqueue(tiny_dataset)
    gpu = home.enqueue(tiny_dataset, queue="gpu")
    sent = {d.queue: d.run_id for d in dispatcher.dispatch(0)}
    assert sent == {"pi": pi1, "gpu": gpu}
    assert home.run(pi2)["state"] == "queued"


def test_a_failed_send_leaves_the_run_queued(home, tiny_dataset, dispatcher, broker):
    rid = home.enqueue(tiny_dataset)
    broker.fail = ConnectionError("broker down")
    assert dispatcher.dispatch(0) == []
    run = home.run(rid)
    assert run["state"] == "queued" and run["celery_task_id"] is None and run["attempt"] == 1
    last = home.events(rid, ["state"])[-1]["payload"]
    assert last["reason"] == "send_failed" and "broker down" in last["message"]
    broker.fail = None
    assert [d.run_id for d in dispatcher.dispatch(0)] == [rid]


def test_hot_host_starts_nothing_locally_but_other_queues_go(home, tiny_dataset, dispatcher, broker):
    pi = home.enqueue(tiny_dataset)
    gpu = home.enqueue(tiny_dataset, queue="gpu")
    assert [d.run_id for d in dispatcher.dispatch(2)] == [gpu]
    assert home.run(pi)["state"] == "queued"
    sent = dispatcher.dispatch(1)
    assert [d.run_id for d in sent] == [pi] and home.run(pi)["throttle_level"] == 1  # starts slowed
    assert home.run(gpu)["throttle_level"] == 0  # another host's queue: not our temperature


def test_thermal_and_memory_paused_runs_are_requeued_when_the_host_allows(home, tiny_dataset, dispatcher):
    hot, mem, user = (home.enqueue(tiny_dataset, memory_budget_mb=2000) for _ in range(3))
    for rid, outcome, level in ((hot, "paused_user", 2), (mem, "paused_memory", 0), (user, "paused_user", 0)):
        assert [d.run_id for d in dispatcher.dispatch(0)] == [rid]
        claim(home, rid, 5000)
        with home.registry.session() as s:
            runs.get_run(s, rid).throttle_level = level
        finish(home, rid, 5000, outcome)
    assert [home.run(r)["pause_reason"] for r in (hot, mem, user)] == ["thermal", "memory", "user"]
    assert dispatcher.requeue_paused(1, 1000.0) == []  # still warm; too little memory
    assert dispatcher.requeue_paused(0, 1000.0) == [hot]
    assert dispatcher.requeue_paused(0, 2500.0) == [mem]
    assert home.run(user)["state"] == "paused"  # only the user resumes a user pause
    assert home.states(hot)[-1] == "queued" and home.run(hot)["desired_state"] == "run"


def test_memory_requeue_waits_memory_retry_s(home, tiny_dataset, broker):
    d = Dispatcher(home.registry, home.settings, send=broker, memory_retry_s=3600)
    rid = home.enqueue(tiny_dataset)
    d.dispatch(0)
    claim(home, rid, 5001)
    finish(home, rid, 5001, "paused_memory")
    assert d.requeue_paused(0, 1e9) == []


def dead_pid() -> int:
    p = subprocess.Popen([sys.executable, "-c", "pass"])
    p.wait()
    return p.pid


def test_dead_child_is_interrupted_and_requeued_then_fails_after_max_attempts(home, tiny_dataset, dispatcher):
    rid = home.enqueue(tiny_dataset, max_attempts=2)
    rec = Reconciler(home.registry, host=HOST, heartbeat_timeout_s=30)
    dispatcher.dispatch(0)
    claim(home, rid, dead_pid())
    actions = rec.reconcile()
    assert [(a.run_id, a.action) for a in actions] == [(rid, "interrupted")]
    run = home.run(rid)
    assert run["state"] == "queued" and run["attempt"] == 2 and run["worker_pid"] is None
    assert home.states(rid)[-3:] == ["running", "interrupted", "queued"]
    assert "is gone" in home.events(rid, ["state"])[-2]["payload"]["message"]
    dispatcher.dispatch(0)
    claim(home, rid, dead_pid())
    rec.reconcile()
    run = home.run(rid)
    assert run["state"] == "failed" and run["error"].startswith("gave up after 2 attempts")


def test_live_child_with_fresh_heartbeat_is_left_alone(home, tiny_dataset, dispatcher):
    rid = home.enqueue(tiny_dataset)
    dispatcher.dispatch(0)
    claim(home, rid, os.getpid())
    assert Reconciler(home.registry, host=HOST).reconcile() == []
    assert home.run(rid)["state"] == "running"


def test_stale_heartbeat_on_another_host_interrupts(home, tiny_dataset, dispatcher):
    rid = home.enqueue(tiny_dataset)
    dispatcher.dispatch(0)
    claim(home, rid, 1, host="desktop")  # pid 1 exists here, but the child lives on another host
    rec = Reconciler(home.registry, host=HOST, heartbeat_timeout_s=30)
    assert rec.reconcile() == []
    with home.registry.session() as s:
        runs.get_run(s, rid).heartbeat_at = utcnow() - timedelta(seconds=31)
    assert [a.action for a in rec.reconcile()] == ["interrupted"]
    assert "no heartbeat" in home.events(rid, ["state"])[-2]["payload"]["message"]


def test_hung_local_child_is_killed_before_the_run_is_requeued(home, tiny_dataset, dispatcher):
    rid = home.enqueue(tiny_dataset)
    dispatcher.dispatch(0)
    hung = subprocess.Popen([sys.executable, "-c", "import time; time.sleep(60)"])
    try:
        claim(home, rid, hung.pid)
        with home.registry.session() as s:
            runs.get_run(s, rid).heartbeat_at = utcnow() - timedelta(seconds=60)
        actions = Reconciler(home.registry, host=HOST, heartbeat_timeout_s=30).reconcile()
        assert [a.action for a in actions] == ["interrupted"] and "killed" in actions[0].why
        assert hung.wait(5) == -9
        assert home.run(rid)["state"] == "queued"
    finally:
        hung.kill()
        hung.wait()


def test_heartbeats_are_not_judged_after_the_daemon_itself_stalled(home, tiny_dataset, dispatcher):
    rid = home.enqueue(tiny_dataset)
    dispatcher.dispatch(0)
    claim(home, rid, 1, host="desktop")
    t = [0.0]
    rec = Reconciler(home.registry, host=HOST, heartbeat_timeout_s=30, clock=lambda: t[0])
    rec.reconcile()
    with home.registry.session() as s:
        runs.get_run(s, rid).heartbeat_at = utcnow() - timedelta(seconds=100)
    t[0] = 100.0  # the daemon was suspended with the machine
    assert rec.reconcile() == []
    t[0] = 100.5
    assert [a.action for a in rec.reconcile()] == ["interrupted"]


def test_pid_reused_by_a_newer_process_counts_as_dead():
    alive, _ = child_alive(os.getpid(), utcnow())
    assert alive
    alive, why = child_alive(os.getpid(), utcnow() - timedelta(days=1))  # claimed before this process began
    assert not alive and "newer process" in why


def test_unclaimed_task_is_resent_with_a_new_id_and_the_old_one_is_refused(home, tiny_dataset, dispatcher, broker):
    rid = home.enqueue(tiny_dataset)
    dispatcher.dispatch(0)
    old_task = broker.sent[-1][3]
    rec = Reconciler(home.registry, host=HOST, claim_timeout_s=600, resend=dispatcher.resend)
    assert rec.reconcile() == []
    with home.registry.session() as s:
        runs.get_run(s, rid).heartbeat_at = utcnow() - timedelta(seconds=601)
    assert [a.action for a in rec.reconcile()] == ["resent"]
    new_task = broker.sent[-1][3]
    assert new_task != old_task and broker.sent[-1][:2] == (rid, 1)
    with home.registry.session() as s:
        assert runs.claim(s, rid, old_task, 1, HOST, 7000) is None  # the lost message, if it comes back
        assert runs.claim(s, rid, new_task, 1, HOST, 7001) is not None
    assert any("re-sent" in e["payload"]["message"] for e in home.events(rid, ["log"]))


def test_create_sequence_links_members_and_runs_them_in_order(home, tiny_dataset, dispatcher, broker):
    base = {"data": str(tiny_dataset), "steps": 30, "threads": 1}
    with home.registry.session() as s:
        chain = create_sequence(s, "vqvae,fast_loop,mid_loop", base, total_steps=30, runs_dir=home.settings.runs_dir)
        ids = [r.id for r in chain]
        assert [r.sequence_index for r in chain] == [0, 1, 2] and len({r.sequence_id for r in chain}) == 1
        assert "vqvae_run" not in chain[0].config
        assert chain[1].config["vqvae_run"] == ids[0] and chain[2].config["vqvae_run"] == ids[0]
        assert chain[1].run_dir == str(home.settings.runs_dir / ids[1])
    for expected in ids:
        assert [d.run_id for d in dispatcher.dispatch(0)] == [expected]
        finish(home, expected, claim(home, expected, 6000).worker_pid)
    assert [home.run(i)["state"] for i in ids] == ["completed"] * 3


def test_a_failed_chain_member_cancels_the_rest(home, tiny_dataset, dispatcher):
    base = {"data": str(tiny_dataset), "steps": 30}
    with home.registry.session() as s:
        ids = [r.id for r in create_sequence(s, ["vqvae", "fast_loop"], base, total_steps=30,
                                             runs_dir=home.settings.runs_dir)]
    dispatcher.dispatch(0)
    finish(home, ids[0], claim(home, ids[0], 6001).worker_pid, "failed")
    assert dispatcher.dispatch(0) == []
    run = home.run(ids[1])
    assert run["state"] == "cancelled" and f"previous run {ids[0]}" in run["error"]


@pytest.mark.parametrize("components, base, match", [
    ("mid_loop", {}, "needs a trained VQ-VAE"),
    ("fast_loop,vqvae", {}, "vqvae must come before"),
    ("vqvae,nope", {}, "unknown component"),
])
def test_create_sequence_refuses_bad_chains(home, components, base, match):
    with home.registry.session() as s, pytest.raises(runs.RunError, match=match):
        create_sequence(s, components, {"data": "/x", **base}, total_steps=10, runs_dir="/tmp/r")


def test_tailer_maps_kinds_to_socketio_events_and_starts_at_the_newest(home, tiny_dataset):
    old = home.enqueue(tiny_dataset)
    sink = ListSink()
    tailer = EventTailer(home.registry, sink)
    assert tailer.poll() == 0  # the creation event of `old` is history
    with home.registry.session() as s:
        runs.add_event(s, old, "progress", {"step": 5, "total": 60, "loss": 0.5})
        runs.add_event(s, old, "checkpoint", {"step": 5, "path": "/x"})
        runs.add_event(s, old, "metric", {"step": 5, "loss": 0.5})
        runs.add_event(s, old, "throttle", {"level": 1})
        runs.request_control(s, old, "cancel")
    assert tailer.poll() == 5  # metric stays in the database
    assert sink.names() == ["run.progress", "run.log", "system.throttle", "run.state", "run.log"]
    progress = sink.of("run.progress")[0]
    assert progress["run_id"] == old and progress["step"] == 5 and progress["event_id"] > 0
    assert sink.of("run.log")[0]["kind"] == "checkpoint"
    assert sink.of("run.state")[0]["state"] == "cancelled"
    assert tailer.poll() == 0


def test_tailer_survives_a_failing_sink(home, tiny_dataset, caplog):
    class Broken:
        def emit(self, event, data):
            raise OSError("socket closed")

    rid = home.enqueue(tiny_dataset)
    tailer = EventTailer(home.registry, Broken(), after_id=0)
    assert tailer.poll() == 0 and tailer.last_id > 0
    assert len([r for r in caplog.records if "socket closed" in r.getMessage()]) == 1
    assert rid


def make_daemon(home: Home, broker: Broker, zone, sink, **kw) -> Daemon:
    monitor = SystemMonitor(None, zone_path=str(zone), vcgencmd=None, thermal_interval_s=0.0)
    d = Daemon(home.settings, sink, tick_s=0.05, stats_every_s=kw.pop("stats_every_s", 0.0), monitor=monitor,
               policy=ThrottlePolicy(75, 82, 70), registry=home.registry, host=HOST, send=broker, **kw)
    d.start()
    return d


def test_daemon_tick_throttles_the_active_run_and_pauses_it_when_hot(home, tiny_dataset, broker, tmp_path):
    zone = tmp_path / "temp"
    zone.write_text("50000\n")
    sink = ListSink()
    d = make_daemon(home, broker, zone, sink)
    d.tick()
    assert sink.of("system.stats") and sink.of("system.stats")[0]["temp_c"] == 50.0
    zone.write_text("77000\n")
    d.tick()  # no run: the level change goes straight to browsers
    assert sink.of("system.throttle")[-1]["level"] == 1 and sink.of("system.throttle")[-1]["run_id"] is None
    rid = home.enqueue(tiny_dataset)
    d.tick()
    assert home.run(rid)["state"] == "starting" and home.run(rid)["throttle_level"] == 1
    claim(home, rid, os.getpid())
    assert home.run(rid)["state"] == "running" and home.run(rid)["throttle_level"] == 1
    zone.write_text("83000\n")
    d.tick()
    assert home.run(rid)["throttle_level"] == 2
    ev = home.events(rid, ["throttle"])[-1]["payload"]
    assert ev["level"] == 2 and ev["previous"] == 1 and "hard limit" in ev["reason"]
    assert [e["level"] for e in sink.of("system.throttle")][-1] == 2 and sink.of("system.throttle")[-1]["run_id"] == rid
    # the worker's control hook pauses the job (level 2 -> desired pause); it reports back:
    finish(home, rid, os.getpid(), "paused_user")
    assert home.run(rid)["pause_reason"] == "thermal"
    d.tick()
    zone.write_text("75000\n")
    d.tick()
    assert home.run(rid)["state"] == "paused"  # not below resume yet
    zone.write_text("65000\n")
    d.tick()  # cooled: requeued, and dispatched again in the same tick
    assert home.run(rid)["state"] == "starting" and home.run(rid)["throttle_level"] == 0
    assert home.states(rid)[-3:] == ["paused", "queued", "starting"]
    d.stop()


def test_run_forever_ticks_until_stopped_and_notifies(home, tiny_dataset, broker, tmp_path):
    import socket as so

    from daemon.sdnotify import SdNotifier

    listener = so.socket(so.AF_UNIX, so.SOCK_DGRAM)
    listener.bind(str(tmp_path / "notify"))
    listener.settimeout(5)
    notifier = SdNotifier({"NOTIFY_SOCKET": str(tmp_path / "notify"), "WATCHDOG_USEC": "200000"})
    zone = tmp_path / "temp"
    zone.write_text("40000\n")
    d = make_daemon(home, broker, zone, ListSink(), notifier=notifier)
    rid = home.enqueue(tiny_dataset)
    stop = threading.Event()
    t = threading.Thread(target=d.run_forever, args=(stop,))
    t.start()
    try:
        assert listener.recv(256).startswith(b"READY=1")
        assert listener.recv(256) == b"WATCHDOG=1"
        deadline = time.monotonic() + 5
        while home.run(rid)["state"] != "starting":
            assert time.monotonic() < deadline
            time.sleep(0.02)
    finally:
        stop.set()
        t.join(5)
    assert not t.is_alive() and d.ticks >= 1
    d.stop()
    msgs = []
    listener.settimeout(0.3)
    try:
        while True:
            msgs.append(listener.recv(256))
    except (TimeoutError, so.timeout):
        pass
    finally:
        listener.close()
    assert msgs and msgs[-1].startswith(b"STOPPING=1")


def test_a_failing_tick_is_logged_and_the_loop_goes_on(home, broker, tmp_path, caplog):
    zone = tmp_path / "temp"
    zone.write_text("40000\n")
    d = make_daemon(home, broker, zone, ListSink())
    calls = []

    def broken():
        calls.append(1)
        raise RuntimeError("database is locked")

    real = d.reconciler.reconcile
    d.reconciler.reconcile = broken
    assert d.safe_tick() is False and d.safe_tick() is False
    assert len([r for r in caplog.records if "daemon tick failed" in r.getMessage()]) == 1
    d.reconciler.reconcile = real
    assert d.safe_tick() is True and len(calls) == 2


def test_a_memory_paused_run_that_makes_no_progress_is_not_requeued_forever(home, tiny_dataset, dispatcher):
    rid = home.enqueue(tiny_dataset, memory_budget_mb=100)

    def run_until_memory_pause(step):
        assert [d.run_id for d in dispatcher.dispatch(0)] == [rid]
        claim(home, rid, 5100)
        with home.registry.session() as s:
            runs.finish(s, rid, 5100, "paused_memory", "memory soft limit", step=step, last_checkpoint=None)

    run_until_memory_pause(10)
    assert dispatcher.requeue_paused(0, 500.0) == [rid]
    run_until_memory_pause(30)  # got further: requeued again
    assert dispatcher.requeue_paused(0, 500.0) == [rid]
    run_until_memory_pause(30)  # no progress since the last automatic resume
    assert dispatcher.requeue_paused(0, 500.0) == []
    assert dispatcher.requeue_paused(0, 500.0) == []
    warnings = [e["payload"] for e in home.events(rid, ["log"]) if "memory_requeue_stopped" in e["payload"]]
    assert len(warnings) == 1 and "resume it yourself" in warnings[0]["message"]
    with home.registry.session() as s:
        runs.request_control(s, rid, "resume")  # the user takes over
    assert home.run(rid)["state"] == "queued"


@contextlib.contextmanager
def _looping(d: Daemon):
    """d.run_forever on a thread, from its first tick until the block ends (then stopped and joined)."""
    stop = threading.Event()
    t = threading.Thread(target=d.run_forever, args=(stop,))
    t.start()
    try:
        wait_until(lambda: d.ticks >= 1, 5, "the first tick", interval=0.01)
        yield
    finally:
        stop.set()
        d.wake()
        t.join(5)
    assert not t.is_alive()
    d.stop()


def test_wake_makes_the_loop_tick_now(home, tiny_dataset, broker, tmp_path):
    zone = tmp_path / "temp"
    zone.write_text("40000\n")
    d = make_daemon(home, broker, zone, ListSink())
    d.tick_s = 30.0  # without wake() the second tick would come in 30 s
    with _looping(d):
        rid = home.enqueue(tiny_dataset)
        d.wake()
        wait_until(lambda: home.run(rid)["state"] == "starting", 5,
                   "wake() did not make the daemon dispatch at once", interval=0.01)


def test_a_burst_of_wakes_costs_a_few_ticks_and_retention_looks_at_most_every_ten_seconds(
        home, tiny_dataset, broker, tmp_path, monkeypatch):
    """Every run request wakes the daemon; a client sending hundreds must not make it tick (and
    scan every finished run for retention) hundreds of times in the process that answers the robot."""
    from daemon import service

    zone = tmp_path / "temp"
    zone.write_text("40000\n")
    d = make_daemon(home, broker, zone, ListSink())
    d.tick_s = 30.0
    scans = []
    monkeypatch.setattr(d.dispatcher.disk, "maybe_prune", lambda: scans.append(time.monotonic()) or [])
    with _looping(d):
        first = d.ticks
        began = time.monotonic()
        while time.monotonic() - began < 1.0:  # ~1,000 wakes in one second
            d.wake()
            time.sleep(0.001)
        spent = time.monotonic() - began
        woken = d.ticks - first
    assert 1 <= woken <= spent / service.MIN_TICK_GAP_S + 2, (woken, spent)
    assert len(scans) == 1, "retention scanned again within PRUNE_EVERY_S"


def test_daemon_start_resends_a_dispatch_a_crash_left_unsent(home, tiny_dataset, broker, tmp_path):
    rid = home.enqueue(tiny_dataset)
    with home.registry.session() as s:  # committed as dispatched, then the daemon died before sending
        runs.mark_dispatched(s, runs.get_run(s, rid), "never-sent")
        runs.get_run(s, rid).heartbeat_at = utcnow() - timedelta(seconds=31)
    zone = tmp_path / "temp"
    zone.write_text("40000\n")
    monitor = SystemMonitor(None, zone_path=str(zone), vcgencmd=None)
    d = Daemon(home.settings, ListSink(), monitor=monitor, registry=home.registry, host=HOST,
               heartbeat_timeout_s=30, claim_timeout_s=600, send=broker)
    d.start()
    assert [sent[0] for sent in broker.sent] == [rid]
    run = home.run(rid)
    assert run["state"] == "starting" and run["celery_task_id"] == broker.sent[0][3] != "never-sent"
    d.stop()


def test_a_run_on_a_queue_with_no_worker_waits_visibly_and_cancel_ends_it_at_once(home, tiny_dataset, broker,
                                                                                   tmp_path):
    """enqueue --queue gpu with no gpu worker: the run is sent but nothing claims it. It must read as
    waiting (not running), hold its queue with the reason on the run behind it, end at once on
    cancel (not be re-sent any more), and its message, taken by a worker that comes up later, must
    not train it."""
    from daemon.cli.status import collect, format_table
    from workers.job import run_job

    zone = tmp_path / "temp"
    zone.write_text("40000\n")
    d = make_daemon(home, broker, zone, ListSink(), claim_timeout_s=600)
    rid = home.enqueue(tiny_dataset, queue="gpu")
    behind = home.enqueue(tiny_dataset, queue="gpu")
    for _ in range(3):
        d.tick()
    assert [sent[0] for sent in broker.sent] == [rid]  # sent once, and nothing else started on gpu
    stale_task = broker.sent[0][3]
    run = home.run(rid)
    assert run["state"] == "starting" and run["worker_pid"] is None
    assert run["waiting"].startswith("waiting for a worker on queue 'gpu' since ")
    with home.registry.session(readonly=True) as s:
        shown = {o["id"]: o for o in collect(s, None, False)}
    assert shown[behind]["state"] == "queued" and f"behind run {rid}, waiting for a worker" in shown[behind]["waiting"]
    table = format_table(list(shown.values())).splitlines()
    assert [row.split()[3] for row in table if row.startswith(rid + " ")] == ["starting"]  # STATE
    assert any(row.startswith(f"{rid}: waiting for a worker on queue 'gpu' since") for row in table)
    assert "waiting for a worker on queue gpu" in d.status_text()

    with home.registry.session() as s:
        assert runs.request_control(s, rid, "cancel").state == "cancelled"  # at once, no daemon involved
    with home.registry.session() as s:  # long after: the re-send of unclaimed runs leaves it alone
        runs.get_run(s, rid).heartbeat_at = utcnow() - timedelta(seconds=3600)
    d.tick()
    assert [sent[0] for sent in broker.sent] == [rid, behind]  # the queue moved on to the next run
    assert home.run(rid)["state"] == "cancelled"

    # a gpu worker comes up and its child takes the old message: refused, nothing trained
    out = run_job(home.settings, rid, 1, task_id=stale_task, host=HOST, pid=os.getpid())
    assert out["status"] == "stale"
    run = home.run(rid)
    assert run["state"] == "cancelled" and run["worker_pid"] is None and run["step"] == 0
    assert not (home.settings.runs_dir / rid / "checkpoints").exists()
    assert any("ignored a stale delivery" in e["payload"]["message"] for e in home.events(rid, ["log"]))
    d.stop()
