"""The daemon with real processes on the embedded sqla+sqlite broker: a Celery worker process
(prefork, one child per job) and the daemon process (`run_trainer.py daemon`), each with its
own tmp $HOPE_HOME. Checked from the registry's recorded timeline:
- five enqueued runs train one at a time, in order, and the worker parent's RSS stays flat;
- SIGKILL of the worker child mid-run: interrupted, requeued, resumed from its checkpoint,
  completed with the same final weights as an uninterrupted run of the same config;
- SIGKILL of the daemon, then a restart: consistent state, nothing lost, everything completes
  (a vqvae -> fast_loop chain included, linked by vqvae_run).
"""
from __future__ import annotations

import os
import signal
import time
from pathlib import Path

import numpy as np
import pytest

from registry import runs
from registry.sequences import create_sequence
from daemon_fixtures import (JOB_TIMEOUT, all_states, assert_never_overlapping, home, procs,  # noqa: F401
                             start_daemon, start_worker, tiny_dataset, wait_until)

pytestmark = pytest.mark.slow


def final_weights(run_dir: str) -> dict[str, np.ndarray]:
    from safetensors.numpy import load_file

    ckpts = sorted((Path(run_dir) / "checkpoints").glob("0*"))
    assert ckpts, f"no checkpoints in {run_dir}"
    return load_file(str(ckpts[-1] / "model.safetensors"))


def worker_child(home, rid) -> int | None:
    run = home.run(rid)
    return run["worker_pid"] if run["state"] == "running" else None


def test_five_runs_one_at_a_time_in_order_and_the_worker_parent_does_not_grow(home, tiny_dataset, procs):
    ids = [home.enqueue(tiny_dataset, steps=20, seed=i) for i in range(5)]  # enqueued with the daemon down
    worker = start_worker(home)
    procs.append(worker)
    daemon = start_daemon(home)
    procs.append(daemon)
    rss_kb = []
    for rid in ids:
        wait_until(lambda: home.run(rid)["state"] in runs.TERMINAL, JOB_TIMEOUT, f"{rid} to finish", home)
        time.sleep(0.3)  # the parent has reaped the child and logged the task's end
        rss_kb.append(worker.rss_kb())
    assert [home.run(r)["state"] for r in ids] == ["completed"] * 5, home.describe()
    intervals = assert_never_overlapping(home, ids)
    assert [r for _, _, r in intervals] == ids  # FIFO
    for rid in ids:
        run = home.run(rid)
        assert run["step"] == 20 and run["attempt"] == 1 and run["last_checkpoint"].endswith("00000020")
        progress = home.events(rid, ["progress"])
        assert progress and progress[-1]["payload"]["step"] == 20
    # each job ran in its own child (max-tasks-per-child=1): five distinct pids
    pids = {e["payload"]["message"].split()[3] for rid in ids for e in home.events(rid, ["log"])
            if e["payload"]["message"].startswith("claimed by pid")}
    assert len(pids) == 5
    # the parent never imports torch, and keeps its size across jobs (noise allowed)
    assert "libtorch" not in Path(f"/proc/{worker.pid}/maps").read_text(), "the worker parent has torch loaded"
    assert "libtorch" not in Path(f"/proc/{daemon.pid}/maps").read_text(), "the daemon has torch loaded"
    growth_mb = (max(rss_kb[1:]) - rss_kb[1]) / 1024
    assert growth_mb < 10, f"worker parent VmRSS after each job (kB): {rss_kb}"


def test_sigkill_of_the_child_resumes_from_its_checkpoint_with_the_same_final_weights(home, tiny_dataset, procs):
    cfg = dict(steps=600, checkpoint_every_steps=50, seed=7)
    victim = home.enqueue(tiny_dataset, **cfg)
    reference = home.enqueue(tiny_dataset, **cfg)  # the same job, never interrupted (runs second)
    procs.append(start_worker(home))
    procs.append(start_daemon(home, "--heartbeat-timeout-s", "30"))
    seen = wait_until(lambda: home.run(victim)["last_checkpoint"], JOB_TIMEOUT,
                      f"{victim} to write its first checkpoint", home, interval=0.01)
    pid = worker_child(home, victim)
    assert pid and home.run(victim)["step"] < 400, "the job got too far before the kill\n" + home.describe()
    os.kill(pid, signal.SIGKILL)
    wait_until(lambda: all_states(home, [victim, reference]) or
               any(home.run(r)["state"] in ("failed", "cancelled") for r in (victim, reference)),
               2 * JOB_TIMEOUT, "both runs to complete", home)
    assert all_states(home, [victim, reference]), home.describe()
    run = home.run(victim)
    assert run["attempt"] == 2 and run["step"] == 600
    states = home.states(victim)
    assert states == ["queued", "starting", "running", "interrupted", "queued", "starting", "running",
                      "completed"], states
    lost = home.events(victim, ["state"])[3]["payload"]
    assert f"pid {pid}" in lost["message"] and "gone" in lost["message"]
    # the second attempt resumed from a checkpoint the first one wrote (the newest before the kill)
    resumed = [e["payload"] for e in home.events(victim, ["log"]) if e["payload"].get("event") == "resume"]
    seen_step = int(Path(seen).name)
    assert len(resumed) == 1, resumed
    assert resumed[0]["data"]["step"] >= seen_step and resumed[0]["data"]["step"] % 50 == 0, (seen, resumed)
    assert resumed[0]["data"]["step"] < 600
    assert home.run(reference)["attempt"] == 1
    assert_never_overlapping(home, [victim, reference])
    a, b = final_weights(run["run_dir"]), final_weights(home.run(reference)["run_dir"])
    assert a.keys() == b.keys() and a
    for name in a:
        assert np.array_equal(a[name], b[name]), f"tensor {name} differs after the resume"


def test_sigkill_of_the_daemon_then_restart_loses_nothing(home, tiny_dataset, procs):
    with home.registry.session() as s:
        chain = [r.id for r in create_sequence(
            s, ["vqvae", "fast_loop"], {"data": str(tiny_dataset), "steps": 30, "seed": 0, "batch_size": 8,
                                        "threads": 1, "warmup": 3, "checkpoint_every_steps": 10},
            total_steps=30, runs_dir=home.settings.runs_dir)]
    single = home.enqueue(tiny_dataset, steps=30)
    ids = chain + [single]
    procs.append(start_worker(home))
    daemon = start_daemon(home)
    procs.append(daemon)
    # Killed while the vqvae job is in flight (claimed by a child, which takes seconds to start):
    wait_until(lambda: worker_child(home, chain[0]), JOB_TIMEOUT, "the vqvae run to be claimed", home, interval=0.02)
    daemon.signal(signal.SIGKILL)
    daemon.popen.wait(10)
    # The job in flight finishes on its own (the worker does not need the daemon); nothing else starts.
    wait_until(lambda: home.run(chain[0])["state"] == "completed", JOB_TIMEOUT, "the vqvae run to complete", home)
    time.sleep(1.0)
    assert [home.run(r)["state"] for r in chain[1:] + [single]] == ["queued", "queued"], home.describe()
    restarted = start_daemon(home, name="daemon2")
    procs.append(restarted)
    wait_until(lambda: all_states(home, ids) or any(home.run(r)["state"] in ("failed", "cancelled") for r in ids),
               2 * JOB_TIMEOUT, "every run to complete after the restart", home)
    assert all_states(home, ids), home.describe()
    intervals = assert_never_overlapping(home, ids)
    assert [r for _, _, r in intervals] == ids
    for rid in ids:
        assert home.states(rid) == ["queued", "starting", "running", "completed"] and home.run(rid)["attempt"] == 1
    fast = home.run(chain[1])
    assert fast["config"]["vqvae_run"] == chain[0]
    # fast_loop read the codes of the chain's VQ-VAE
    import json
    cfg = json.loads((Path(fast["last_checkpoint"]) / "config.json").read_text())
    assert chain[0] in json.dumps(cfg)
    assert restarted.alive()
    assert restarted.stop() == 0  # SIGTERM: a clean exit


def test_daemon_process_notifies_systemd_and_stops_cleanly_on_sigterm(home, tmp_path, procs):
    import socket

    sock_path = str(tmp_path / "notify.sock")
    listener = socket.socket(socket.AF_UNIX, socket.SOCK_DGRAM)
    listener.bind(sock_path)
    listener.settimeout(30)
    home.env.update({"NOTIFY_SOCKET": sock_path, "WATCHDOG_USEC": "1000000"})
    try:
        daemon = start_daemon(home)
        procs.append(daemon)
        first = listener.recv(512)
        assert first.startswith(b"READY=1\nSTATUS="), first
        assert listener.recv(512) == b"WATCHDOG=1"  # every half WatchdogSec
        assert listener.recv(512) == b"WATCHDOG=1"
        assert "libtorch" not in Path(f"/proc/{daemon.pid}/maps").read_text()
        from registry.db import Registry
        Registry.open(home.settings, migrate=False).close()  # the daemon migrated the registry it found missing
        daemon.signal(signal.SIGTERM)
        assert daemon.popen.wait(10) == 0
        rest = []
        listener.settimeout(0.5)
        try:
            while True:
                rest.append(listener.recv(512))
        except (TimeoutError, socket.timeout):
            pass
        assert rest and rest[-1].startswith(b"STOPPING=1"), rest
    finally:
        listener.close()


def test_a_hot_host_pauses_the_run_and_it_resumes_once_cool(home, tiny_dataset, procs):
    zone = Path(home.env["HOPE_THERMAL_ZONE"])
    zone.write_text("50000\n")
    rid = home.enqueue(tiny_dataset, steps=1000, checkpoint_every_steps=100)
    procs.append(start_worker(home))
    procs.append(start_daemon(home))
    wait_until(lambda: home.run(rid)["step"] >= 20, JOB_TIMEOUT, f"{rid} to be training", home, interval=0.05)
    zone.write_text("90000\n")  # over the hard limit (82 C)
    wait_until(lambda: home.run(rid)["state"] == "paused", 30, f"{rid} to pause for heat", home)
    run = home.run(rid)
    assert run["pause_reason"] == "thermal" and run["step"] < 1000 and run["last_checkpoint"], home.describe()
    paused_at = run["step"]
    assert run["last_checkpoint"].endswith(f"{paused_at:08d}")  # it checkpointed where it stopped
    throttle = [e["payload"] for e in home.events(rid, ["throttle"])]
    assert throttle and throttle[-1]["level"] == 2 and throttle[-1]["source"] == "daemon"
    time.sleep(1.0)
    assert home.run(rid)["state"] == "paused"  # stays paused while hot
    zone.write_text("75000\n")  # below hard, not below resume (70 C): still paused
    time.sleep(1.0)
    assert home.run(rid)["state"] == "paused"
    zone.write_text("60000\n")
    wait_until(lambda: home.run(rid)["state"] == "completed", JOB_TIMEOUT, f"{rid} to resume and complete", home)
    assert home.states(rid) == ["queued", "starting", "running", "paused", "queued", "starting", "running",
                                "completed"]
    assert home.run(rid)["attempt"] == 1
    resumed = [e["payload"] for e in home.events(rid, ["log"]) if e["payload"].get("event") == "resume"]
    assert [r["data"]["step"] for r in resumed] == [paused_at]
