"""The production broker: a real redis-server (apt-installed) on a free loopback port, with the
daemon and Celery worker processes pointed at it through HOPE_REDIS_URL.
- redis-server restarted mid-run (losing everything it held): the worker reconnects, the run
  completes, and the next run is dispatched and completes too;
- two workers on two queues (pi, gpu) against one Redis each serve their own runs, one at a time
  each; the daemon's events reach the Socket.IO message queue on Redis as JSON.
The Redis tests fail (not skip) when redis-server is missing: production depends on it.
"""
from __future__ import annotations

import json
import threading
import time

import pytest

from daemon import runs
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
    assert rhome.run(first)["attempt"] == 1 and rhome.states(first) == ["queued", "running", "completed"]
    assert rhome.run(second)["attempt"] == 1
    assert_never_overlapping(rhome, [first, second])


def test_two_workers_on_two_queues_serve_their_own_runs_one_at_a_time(rhome, redis_server, tiny_dataset, procs):
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
    pi = [rhome.enqueue(tiny_dataset, steps=20, queue="pi") for _ in range(2)]
    gpu = [rhome.enqueue(tiny_dataset, steps=20, queue="gpu") for _ in range(2)]
    w_pi = start_worker(rhome, "pi")
    w_gpu = start_worker(rhome, "gpu")
    procs.extend([w_pi, w_gpu])
    procs.append(start_daemon(rhome, "--local-queues", "pi", "--stats-every-s", "1"))
    ids = pi + gpu
    try:
        wait_until(lambda: all_states(rhome, ids) or any(rhome.run(r)["state"] in ("failed", "cancelled")
                                                          for r in ids),
                   3 * JOB_TIMEOUT, "the runs of both queues to complete", rhome)
    finally:
        time.sleep(1.2)  # one more system.stats
        stop.set()
        listener.join(5)
        pubsub.close()
        client.close()
    assert all_states(rhome, ids), rhome.describe()
    assert_never_overlapping(rhome, pi)
    assert_never_overlapping(rhome, gpu)
    # each worker received exactly its queue's tasks (its log names each task id it got)
    pi_log, gpu_log = w_pi.log.read_text(), w_gpu.log.read_text()
    for rid in pi:
        task = rhome.run(rid)["celery_task_id"]
        assert task in pi_log and task not in gpu_log, rhome.describe()
    for rid in gpu:
        task = rhome.run(rid)["celery_task_id"]
        assert task in gpu_log and task not in pi_log, rhome.describe()
    # the daemon's events went out on the Socket.IO message queue
    events = {m["event"] for m in heard if m.get("method") == "emit"}
    assert {"run.state", "run.progress", "system.stats"} <= events, events
    done = [m["data"][0] for m in heard if m.get("event") == "run.state" and m["data"][0]["state"] == "completed"]
    assert {d["run_id"] for d in done} == set(ids)
    assert all(rhome.run(r)["state"] in runs.TERMINAL for r in ids)
