"""The production broker: a real redis-server (apt-installed) on a free loopback port, with the
daemon and Celery worker processes pointed at it through HOPE_REDIS_URL.
- redis-server restarted mid-run (losing everything it held): the worker reconnects, the run
  completes, and the next run is dispatched and completes too;
- two workers on two queues (pi, gpu) against one Redis each serve their own runs, one at a time
  each and in parallel; the gpu worker has its own HOPE_HOME (another machine) and reports through
  Redis; pause/resume/cancel reach it; the daemon's events reach the Socket.IO message queue as JSON.
The Redis tests fail (not skip) when redis-server is missing: production depends on it.
"""
from __future__ import annotations

import json
import os
import threading
import time
from datetime import datetime
from pathlib import Path

import pytest

from registry import runs
from daemon_fixtures import (JOB_TIMEOUT, Home, all_states, assert_never_overlapping, procs,  # noqa: F401
                             redis_server, start_daemon, start_worker, tiny_dataset, wait_until)

pytestmark = pytest.mark.slow


@pytest.fixture
def rhome(tmp_path, redis_server):
    h = Home(tmp_path / "home", redis_url=redis_server.url)
    yield h
    h.close()


def test_redis_sink_publishes_json_on_the_socketio_channel(redis_server):
    import redis

    from daemon.events import RedisEmitterSink

    client = redis.Redis.from_url(redis_server.url)
    pubsub = client.pubsub(ignore_subscribe_messages=True)
    pubsub.subscribe("flask-socketio")
    time.sleep(0.1)
    RedisEmitterSink(redis_server.url).emit("run.progress", {"run_id": "r-1", "step": 3})
    message = None
    deadline = time.monotonic() + 5
    while message is None and time.monotonic() < deadline:
        message = pubsub.get_message(timeout=0.5)
    assert message is not None, "nothing published on the flask-socketio channel"
    body = json.loads(message["data"])  # JSON, never pickle
    assert body["method"] == "emit" and body["event"] == "run.progress"
    assert body["data"] == [{"run_id": "r-1", "step": 3}] and body["namespace"] == "/"
    pubsub.close()
    client.close()
    with pytest.raises(ValueError, match="redis://"):
        RedisEmitterSink("sqla+sqlite:///x")


def test_redis_restarted_mid_run_the_run_completes_and_the_next_one_runs(rhome, redis_server, tiny_dataset, procs):
    first = rhome.enqueue(tiny_dataset, steps=1000, checkpoint_every_steps=200)
    second = rhome.enqueue(tiny_dataset, steps=20)
    procs.append(start_worker(rhome))
    procs.append(start_daemon(rhome))
    wait_until(lambda: rhome.run(first)["step"] >= 1, JOB_TIMEOUT, f"{first} to be training", rhome,
               interval=0.02)
    redis_server.restart(down_s=1.0)
    assert rhome.run(first)["state"] == "running" and rhome.run(first)["step"] < 1000, \
        "the run ended before Redis was back: make it longer\n" + rhome.describe()
    wait_until(lambda: all_states(rhome, [first, second]) or
               any(rhome.run(r)["state"] in ("failed", "cancelled") for r in (first, second)),
               2 * JOB_TIMEOUT, "both runs to complete after the Redis restart", rhome)
    assert all_states(rhome, [first, second]), rhome.describe()
    # the run in flight was not lost or restarted: one attempt, trained through the restart
    assert rhome.run(first)["attempt"] == 1 and rhome.states(first) == ["queued", "starting", "running",
                                                                          "completed"]
    assert rhome.run(second)["attempt"] == 1
    assert_never_overlapping(rhome, [first, second])


def _open_files(pid: int) -> set[str]:
    found = set()
    for fd in Path(f"/proc/{pid}/fd").iterdir():
        try:
            found.add(os.readlink(fd))
        except OSError:  # closed meanwhile
            pass
    return found


def _first_interval(home, rid):
    """[claimed, left running] of a run's first attempt, from its recorded timeline."""
    claims = [e["time"] for e in home.events(rid, ["log"]) if e["payload"]["message"].startswith("claimed by pid")]
    ends = [e["time"] for e in home.events(rid, ["state"]) if e["payload"]["from"] == "running"]
    assert claims and ends, f"{rid} never ran\n{home.describe()}"
    return datetime.fromisoformat(claims[0]), datetime.fromisoformat(ends[0])


def test_a_remote_worker_reports_through_redis_and_runs_beside_the_local_one(rhome, redis_server, tiny_dataset,
                                                                            procs, tmp_path):
    """Two workers on two queues against one Redis. The `gpu` worker stands for another machine:
    its own HOPE_HOME, no access to the Pi's hope.db (the dataset and the run dirs are absolute
    paths both see: the shared state dir). The daemon (local queues: pi) sends gpu runs with
    report="redis": the gpu job reports through Redis and the daemon writes the registry. Each
    worker serves its own runs one at a time, the two queues in parallel, and a pause, resume and
    cancel made in the Pi's registry reach the remote child through its control key."""
    import redis

    client = redis.Redis.from_url(redis_server.url)
    pubsub = client.pubsub(ignore_subscribe_messages=True)
    pubsub.subscribe("flask-socketio")
    heard: list[dict] = []
    stop = threading.Event()

    def listen():
        while not stop.is_set():
            m = pubsub.get_message(timeout=0.2)
            if m is not None:
                heard.append(json.loads(m["data"]))

    listener = threading.Thread(target=listen, daemon=True)
    listener.start()
    gpu_home = Home(tmp_path / "gpu-home", redis_url=redis_server.url)  # never opens a registry
    pi = [rhome.enqueue(tiny_dataset, steps=150, queue="pi") for _ in range(2)]
    # checkpoints only when asked to stop; long enough to be paused, resumed and cancelled
    long = rhome.enqueue(tiny_dataset, steps=200_000, checkpoint_every_steps=1_000_000, queue="gpu")
    short = rhome.enqueue(tiny_dataset, steps=40, queue="gpu")
    w_pi = start_worker(rhome, "pi")
    w_gpu = start_worker(gpu_home, "gpu")
    rhome.logs.append(w_gpu.log)
    procs.extend([w_pi, w_gpu])
    procs.append(start_daemon(rhome, "--local-queues", "pi", "--stats-every-s", "1"))
    try:
        run = wait_until(lambda: (r := rhome.run(long))["step"] >= 20 and r, JOB_TIMEOUT,
                         f"the remote run {long} to train 20 steps", rhome, interval=0.05)
        assert run["worker_pid"] in w_gpu.children(), rhome.describe()
        opened = _open_files(run["worker_pid"])
        assert opened and not [f for f in opened if "hope.db" in f], f"the remote child opened the registry: {opened}"
        # pause in the Pi's registry -> control key -> the remote child checkpoints and stops
        with rhome.registry.session() as s:
            runs.request_control(s, long, "pause")
        t0 = time.monotonic()
        paused = wait_until(lambda: (r := rhome.run(long))["state"] != "running" and r, 15,
                            "the remote run to pause", rhome, interval=0.05)
        assert time.monotonic() - t0 < 5
        assert (paused["state"], paused["pause_reason"]) == ("paused", "user"), rhome.describe()
        assert Path(paused["last_checkpoint"]).name == f"{paused['step']:08d}" and paused["step"] >= 20
        assert Path(paused["last_checkpoint"], "model.safetensors").is_file()
        with rhome.registry.session() as s:
            runs.request_control(s, long, "resume")
        wait_until(lambda: rhome.run(long)["step"] > paused["step"] + 10, JOB_TIMEOUT,
                   "the resumed remote run to train on", rhome, interval=0.05)
        assert any(e["payload"]["message"].startswith(f"resuming from step {paused['step']}")
                   for e in rhome.events(long, ["log"])), rhome.describe()
        with rhome.registry.session() as s:
            runs.request_control(s, long, "cancel")
        done = wait_until(lambda: (r := rhome.run(long))["state"] != "running" and r, 15,
                          "the remote run to be cancelled", rhome, interval=0.05)
        assert done["state"] == "cancelled", rhome.describe()
        assert Path(done["last_checkpoint"]).name == f"{done['step']:08d}" and done["step"] > paused["step"] + 10
        assert rhome.states(long) == ["queued", "starting", "running", "paused", "queued", "starting", "running",
                                      "cancelled"]

        ids = pi + [short]
        wait_until(lambda: all_states(rhome, ids) or any(rhome.run(r)["state"] in ("failed", "cancelled")
                                                          for r in ids),
                   3 * JOB_TIMEOUT, "the other runs of both queues to complete", rhome)
    finally:
        time.sleep(1.2)  # one more system.stats
        stop.set()
        listener.join(5)
        pubsub.close()
        client.close()
    assert all_states(rhome, ids), rhome.describe()
    # the remote run is in the Pi's registry: progress and checkpoint events, weights in its run dir
    run = rhome.run(short)
    assert run["step"] == 40 and run["loss"] is not None and run["worker_pid"] is None
    assert [e["payload"]["step"] for e in rhome.events(short, ["checkpoint"])] == [20, 40]
    assert rhome.events(short, ["progress"])[-1]["payload"]["step"] == 40
    assert Path(run["last_checkpoint"], "model.safetensors").is_file()
    assert Path(run["last_checkpoint"]).parent.parent == Path(run["run_dir"])
    # ...and the remote box never had one
    assert not (gpu_home.path / "hope.db").exists() and not list(gpu_home.path.glob("hope.db*")), \
        sorted(p.name for p in gpu_home.path.iterdir())
    # one at a time on each queue; the two queues in parallel
    assert_never_overlapping(rhome, pi)
    assert_never_overlapping(rhome, [long, short])
    (p0, p1), (g0, g1) = _first_interval(rhome, pi[0]), _first_interval(rhome, long)
    assert max(p0, g0) < min(p1, g1), f"the queues did not run in parallel: pi {p0}-{p1}, gpu {g0}-{g1}"
    # each worker received exactly its queue's tasks, and reported the way the daemon asked
    pi_log, gpu_log = w_pi.log.read_text(), w_gpu.log.read_text()
    for rid in pi:
        task = rhome.run(rid)["celery_task_id"]
        assert task in pi_log and task not in gpu_log, rhome.describe()
    for rid in (long, short):
        task = rhome.run(rid)["celery_task_id"]
        assert task in gpu_log and task not in pi_log, rhome.describe()
    assert pi_log.count("'report': 'db'") == 2 and "'report': 'redis'" not in pi_log
    assert gpu_log.count("'status': 'reported'") == 3 and "'report': 'db'" not in gpu_log
    assert client_is_clean(redis_server.url, [*pi, long, short])
    # the daemon's events went out on the Socket.IO message queue, the remote run's included
    events = {m["event"] for m in heard if m.get("method") == "emit"}
    assert {"run.state", "run.progress", "system.stats"} <= events, events
    done = [m["data"][0] for m in heard if m.get("event") == "run.state" and m["data"][0]["state"] == "completed"]
    assert {d["run_id"] for d in done} == set(ids)
    assert any(m["data"][0].get("run_id") == short for m in heard if m.get("event") == "run.progress")


def client_is_clean(url: str, run_ids) -> bool:
    """Every report was applied, no claim answer was left behind; control keys expire (TTL)."""
    import redis

    client = redis.Redis.from_url(url)
    try:
        assert client.llen("hope:reports") == 0
        assert not list(client.scan_iter("hope:claim:*"))
        for rid in run_ids:
            ttl = client.ttl(f"hope:control:{rid}")
            assert ttl == -2 or 0 < ttl <= 300, (rid, ttl)
    finally:
        client.close()
    return True
