"""A token holder against the run queue and retention, over the real HTTP server in this process.

- a burst of runs created on a queue no worker serves and cancelled at once (hostile_clients.run_flood)
  does not make retention delete a trained run: runs that never produced anything do not count
  toward keep_runs;
- the newest completed run of each component is kept whatever keep_runs says;
- runs waiting to start (queued or starting) are capped per queue: 429 from POST /api/runs and
  POST /api/training/sequential, exit 75 from `enqueue` / `sequential`, exact under concurrent requests.
"""
from __future__ import annotations

import json
import threading
from pathlib import Path

import pytest

from daemon.disk_guard import DiskGuard
from daemon_fixtures import home, tiny_dataset  # noqa: F401
from hostile_clients import http_request, run_flood
from test_daemon_service import broker, claim, dispatcher, finish  # noqa: F401 (fixtures)
from test_disk_guard import fake_checkpoint


class Server:
    """create_app on the real (guarded) HTTP server, over `home`'s registry."""

    def __init__(self, home):
        from webapp import create_app
        from webapp.auth import load_or_create_token
        from webapp.server import HttpServer

        self.token = load_or_create_token(home.settings)
        self.app, _ = create_app(home.settings, token=self.token, registry=home.registry)
        self.server = HttpServer(self.app, "127.0.0.1", 0, None)
        self.server.start()
        self.port = self.server.port

    def post(self, path: str, body: dict) -> tuple[int, dict]:
        status, raw = http_request(self.port, "POST", path, body=json.dumps(body).encode(), timeout=60.0,
                                   headers={"Authorization": f"Bearer {self.token}",
                                            "Content-Type": "application/json"})
        return status, json.loads(raw or b"{}")

    def close(self) -> None:
        self.server.stop()
        self.app.extensions["hope"].close()


@pytest.fixture
def server(home, tiny_dataset):
    home.settings.data_roots = [str(tiny_dataset.parent)]
    s = Server(home)
    yield s
    s.close()


def trained(home, tiny_dataset, dispatcher, component: str = "fast_loop", outcome: str = "completed") -> str:
    """A run that ran: dispatched, claimed, finished, with a checkpoint and metrics in its dir."""
    rid = home.enqueue(tiny_dataset, component=component)
    assert [d.run_id for d in dispatcher.dispatch(0)] == [rid]
    claim(home, rid, 7100)
    finish(home, rid, 7100, outcome)
    run_dir = Path(home.run(rid)["run_dir"])
    fake_checkpoint(run_dir, 10, 1)
    (run_dir / "metrics.jsonl").write_text('{"type": "metric", "step": 10, "wall_time": 1.0, "loss": 0.5}\n')
    return rid


def kept(home, rid: str) -> bool:
    run_dir = Path(home.run(rid)["run_dir"])
    return (run_dir / "metrics.jsonl").is_file() and (run_dir / "checkpoints").is_dir()


def test_a_create_and_cancel_flood_does_not_make_retention_delete_trained_runs(home, tiny_dataset, dispatcher,
                                                                               server, caplog):
    oldest, older, newest = (trained(home, tiny_dataset, dispatcher) for _ in range(3))
    home.settings.keep_runs = 2
    flood = run_flood(server.port, server.token, str(tiny_dataset), runs=21)
    assert flood["created"] == {201: 21} and flood["cancelled"] == {200: 21}, flood
    assert all(home.run(r)["state"] == "cancelled" for r in flood["ids"])
    caplog.set_level("INFO", logger="daemon.disk_guard")
    # the two newest runs that produced something are kept; the 21 that never started do not count
    assert DiskGuard(home.registry, home.settings).prune() == [oldest]
    assert kept(home, older) and kept(home, newest) and not Path(home.run(oldest)["run_dir"]).exists()
    events = [e["payload"] for e in home.events(oldest, ["log"]) if "retention" in e["payload"]]
    assert len(events) == 1 and events[0]["retention"]["keep_runs"] == 2
    assert oldest in events[0]["message"] and "pruned by retention" in events[0]["message"]
    assert any(oldest in r.getMessage() and "retention" in r.getMessage() for r in caplog.records)


def test_the_newest_completed_run_of_each_component_is_kept(home, tiny_dataset, dispatcher):
    vq = trained(home, tiny_dataset, dispatcher, component="vqvae")
    first = trained(home, tiny_dataset, dispatcher)
    last_completed = trained(home, tiny_dataset, dispatcher)
    failed = trained(home, tiny_dataset, dispatcher, outcome="failed")  # produced metrics: it counts
    assert home.run(failed)["state"] == "failed"
    home.settings.keep_runs = 1
    assert DiskGuard(home.registry, home.settings).prune() == [first]
    assert kept(home, vq) and kept(home, last_completed) and kept(home, failed)


def test_runs_waiting_to_start_are_capped_per_queue_with_a_429(home, tiny_dataset, server):
    home.settings.max_queued_runs = 3
    run = {"component": "fast_loop", "data": str(tiny_dataset), "steps": 10, "queue": "q1"}
    chain = {"data": str(tiny_dataset), "steps": 10, "queue": "q1"}
    assert [server.post("/api/runs", run)[0] for _ in range(3)] == [201, 201, 201]
    status, body = server.post("/api/runs", run)
    assert status == 429 and "max_queued_runs=3" in body["error"] and "'q1'" in body["error"], body
    answer = server.app.test_client().post("/api/runs", json=run, headers={"Authorization": f"Bearer {server.token}"})
    assert answer.status_code == 429 and answer.headers.get("Retry-After") == "30", answer.headers
    status, body = server.post("/api/training/sequential", {**chain, "components": "vqvae,fast_loop"})
    assert status == 429 and "max_queued_runs" in body["error"], body
    # another queue has its own room; a chain needs room for all its members
    assert server.post("/api/runs", {**run, "queue": "q2"})[0] == 201
    status, body = server.post("/api/training/sequential", {**chain, "queue": "q2", "components": "vqvae,fast_loop"})
    assert status == 201, body
    status, body = server.post("/api/training/sequential", {**chain, "queue": "q2", "components": "vqvae"})
    assert status == 429 and "max_queued_runs" in body["error"], body
    # a cancelled run frees its place
    queued = [r for r in home.runs() if r["queue"] == "q1"]
    assert server.post(f"/api/runs/{queued[0]['id']}/cancel", {})[0] == 200
    assert server.post("/api/runs", run)[0] == 201


def test_a_queue_filling_flood_stops_at_the_cap(home, tiny_dataset, server):
    home.settings.max_queued_runs = 4
    flood = run_flood(server.port, server.token, str(tiny_dataset), runs=7, queue="full", cancel=False)
    assert flood["created"] == {201: 4, 429: 3} and flood["cancelled"] == {}, flood
    assert sorted(r["id"] for r in home.runs() if r["queue"] == "full") == sorted(flood["ids"])


def test_the_cap_holds_under_concurrent_requests(home, tiny_dataset, server):
    home.settings.max_queued_runs = 2
    run = {"component": "fast_loop", "data": str(tiny_dataset), "steps": 10, "queue": "burst"}
    statuses: list[int] = []
    threads = [threading.Thread(target=lambda: statuses.append(server.post("/api/runs", run)[0])) for _ in range(6)]
    for t in threads:
        t.start()
    for t in threads:
        t.join(120)
    assert sorted(statuses) == [201, 201, 429, 429, 429, 429]
    assert len([r for r in home.runs() if r["queue"] == "burst"]) == 2


def test_the_cli_refuses_a_full_queue_with_exit_75(home, tiny_dataset, monkeypatch, capsys):
    import run_trainer

    monkeypatch.setenv("HOPE_HOME", str(home.path))
    monkeypatch.setenv("HOPE_MAX_QUEUED_RUNS", "1")
    args = ["--data", str(tiny_dataset), "--steps", "10", "--queue", "cli"]
    assert run_trainer.main(["enqueue", "--component", "fast_loop", *args]) == 0
    capsys.readouterr()
    assert run_trainer.main(["enqueue", "--component", "fast_loop", *args]) == 75
    err = capsys.readouterr().err
    assert "queue 'cli' is full" in err and "max_queued_runs=1" in err
    assert run_trainer.main(["sequential", "--components", "vqvae,fast_loop", *args]) == 75
    assert "max_queued_runs=1" in capsys.readouterr().err
    assert len([r for r in home.runs() if r["queue"] == "cli"]) == 1
