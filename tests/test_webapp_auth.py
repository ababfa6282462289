"""The webapp's token auth and the minimal runs API, in process (Flask and Socket.IO test clients).

The same checks against a real `serve` process are in test_cli_daemon.py.
"""
from __future__ import annotations

import os
import stat
import subprocess
import sys
from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parents[1]


@pytest.fixture
def settings(tmp_path):
    from hope_models.settings import load_settings

    return load_settings(env={"HOPE_HOME": str(tmp_path / "home")})


@pytest.fixture
def webapp(settings):
    from registry.db import Registry
    from webapp import create_app
    from webapp.auth import load_or_create_token

    token = load_or_create_token(settings)
    registry = Registry.open(settings)
    app, socketio = create_app(settings, token=token, registry=registry)
    yield app, socketio, token
    registry.close()


def bearer(token: str) -> dict[str, str]:
    return {"Authorization": f"Bearer {token}"}


def test_token_file_is_created_private_and_reused(settings):
    from webapp.auth import load_or_create_token, token_path

    token = load_or_create_token(settings)
    path = token_path(settings)
    assert stat.S_IMODE(path.stat().st_mode) == 0o600
    assert len(token) >= 40
    assert load_or_create_token(settings) == token  # a restart keeps the token the user copied


def test_token_file_readable_by_others_is_refused(settings):
    from webapp.auth import TokenError, load_or_create_token, token_path

    load_or_create_token(settings)
    os.chmod(token_path(settings), 0o644)
    with pytest.raises(TokenError, match="chmod 600"):
        load_or_create_token(settings)


def test_health_is_open_everything_else_needs_the_token(webapp):
    app, _socketio, token = webapp
    client = app.test_client()
    health = client.get("/api/health")
    assert health.status_code == 200 and health.get_json()["status"] == "ok"

    for headers in ({}, bearer("wrong-token-of-some-length"), {"Authorization": f"Basic {token}"},
                    {"Authorization": "Bearer "}):
        for method, path in (("GET", "/api/runs"), ("POST", "/api/runs"), ("GET", "/api/runs/r-x"),
                             ("POST", "/api/runs/r-x/cancel"), ("GET", "/api/not-a-route")):
            response = client.open(path, method=method, headers=headers)
            assert response.status_code == 401, (method, path, headers, response.get_data(as_text=True))
            assert "error" in response.get_json()
            assert response.headers["WWW-Authenticate"].startswith("Bearer")

    ok = client.get("/api/runs", headers=bearer(token))
    assert ok.status_code == 200 and ok.get_json() == {"runs": []}


def _api_routes(app) -> list[tuple[str, str]]:
    """(method, path) of every API route of the app, path parameters filled in."""
    import re

    out = []
    for rule in app.url_map.iter_rules():
        if not rule.rule.startswith("/api/"):
            continue
        path = re.sub(r"<[^>]+>", "x-1", rule.rule)
        for method in sorted(rule.methods - {"HEAD", "OPTIONS"}):
            out.append((method, path))
    return out


def test_every_api_route_but_health_needs_the_token(webapp):
    """Default deny: each route the app has (issue 6's included, and any added later) answers 401
    without the token or with a wrong one, before it looks at the request."""
    app, _socketio, token = webapp
    client = app.test_client()
    routes = _api_routes(app)
    expected = {("POST", "/api/brain/infer"), ("POST", "/api/brain/promote"), ("POST", "/api/brain/rollback"),
                ("GET", "/api/brain"), ("GET", "/api/system"), ("POST", "/api/training/sequential"),
                ("GET", "/api/runs/x-1/metrics"), ("POST", "/api/sim/reflex"), ("GET", "/api/sim/reflex/x-1"),
                ("GET", "/api/runs"), ("POST", "/api/runs"), ("GET", "/api/health")}
    assert expected <= set(routes), sorted(expected - set(routes))
    for method, path in routes:
        for headers in ({}, bearer("wrong-token-of-some-length"), {"Authorization": f"Basic {token}"}):
            response = client.open(path, method=method, headers=headers, json={"component": "fast_loop"})
            if path in ("/api/health", "/api/ping", "/api/ownership/status"):  # the @public views
                assert response.status_code == 200
                continue
            assert response.status_code == 401, (method, path, headers, response.get_data(as_text=True))
            assert "token" in response.get_json()["error"]


def test_runs_api_create_control_and_4xx(webapp, settings):
    app, _socketio, token = webapp
    client = app.test_client()
    h = bearer(token)
    from hope_models.data.synthetic import generate_dataset

    dataset = settings.datasets_dir / "ds"
    generate_dataset(dataset, 200, obs_dim=6, act_dim=2, seed=0, episode_seconds=(4.0, 6.0))  # checked at the door

    created = client.post("/api/runs", headers=h, json={"component": "fast_loop", "data": "ds", "steps": 40,
                                                        "threads": 1, "seed": 3})
    assert created.status_code == 201, created.get_data(as_text=True)
    run = created.get_json()["run"]
    assert run["state"] == "queued" and run["total_steps"] == 40
    assert run["config"] == {"data": str(dataset.resolve()), "steps": 40, "threads": 1, "seed": 3}
    assert created.headers["Location"] == f"/api/runs/{run['id']}"
    assert client.get(f"/api/runs/{run['id']}", headers=h).get_json()["run"]["id"] == run["id"]
    assert [r["id"] for r in client.get("/api/runs?state=queued", headers=h).get_json()["runs"]] == [run["id"]]

    assert client.post(f"/api/runs/{run['id']}/pause", headers=h).get_json()["run"]["state"] == "paused"
    assert client.post(f"/api/runs/{run['id']}/resume", headers=h).get_json()["run"]["state"] == "queued"
    assert client.post(f"/api/runs/{run['id']}/cancel", headers=h).get_json()["run"]["state"] == "cancelled"
    again = client.post(f"/api/runs/{run['id']}/cancel", headers=h)
    assert again.status_code == 409 and "nothing to cancel" in again.get_json()["error"]

    bad = [
        ({"component": "fast_loop"}, "data"),
        ({"component": "nope", "data": "ds"}, "component"),
        ({"component": "fast_loop", "data": "missing-ds"}, "does not exist"),
        ({"component": "fast_loop", "data": "/etc"}, "outside the allowed data roots"),
        ({"component": "fast_loop", "data": "ds", "steps": 0}, "steps"),
        ({"component": "fast_loop", "data": "ds", "steps": "many"}, "steps"),
        ({"component": "fast_loop", "data": "ds", "lr": -1}, "lr"),
        ({"component": "fast_loop", "data": "ds", "queue": "GPU!"}, "queue"),
        ({"component": "fast_loop", "data": "ds", "model_config": [1]}, "model_config"),
        ({"component": "fast_loop", "data": "ds", "run_dir": "/tmp/x"}, "unknown field"),
        ({"component": "mid_loop", "data": "ds", "vqvae_run": "r-none"}, "vqvae_run"),
        ([1, 2], "JSON object"),
    ]
    for body, needle in bad:
        response = client.post("/api/runs", headers=h, json=body)
        assert response.status_code == 400, (body, response.get_data(as_text=True))
        assert needle in response.get_json()["error"], (body, response.get_json())
    not_json = client.post("/api/runs", headers=h, data="component=fast_loop")
    assert not_json.status_code == 415 and "application/json" in not_json.get_json()["error"]
    assert client.get("/api/runs?state=sleeping", headers=h).status_code == 400
    assert client.get("/api/runs?limit=abc", headers=h).status_code == 400
    missing = client.get("/api/runs/r-missing", headers=h)
    assert missing.status_code == 404 and "r-missing" in missing.get_json()["error"]
    assert client.post("/api/runs/r-missing/pause", headers=h).status_code == 404
    wrong_method = client.delete("/api/runs", headers=h)
    assert wrong_method.status_code == 405 and "error" in wrong_method.get_json()


def test_socketio_connect_needs_the_token(webapp):
    app, socketio, token = webapp

    assert not socketio.test_client(app).is_connected()
    assert not socketio.test_client(app, auth={"token": "wrong-token-of-some-length"}).is_connected()
    assert not socketio.test_client(app, query_string="token=wrong").is_connected()

    by_auth = socketio.test_client(app, auth={"token": token})
    by_query = socketio.test_client(app, query_string=f"token={token}")
    assert by_auth.is_connected() and by_query.is_connected()

    # a namespace added later (issue 6) is covered by the same connect check
    @socketio.on("ping", namespace="/editor")
    def _ping(_data=None):
        return "pong"

    assert not socketio.test_client(app, namespace="/editor", auth={"token": "x" * 20}).is_connected("/editor")
    assert socketio.test_client(app, namespace="/editor", auth={"token": token}).is_connected("/editor")

    socketio.emit("run.progress", {"run_id": "r-1", "step": 3})
    received = by_auth.get_received()
    assert {"name": "run.progress", "args": [{"run_id": "r-1", "step": 3}], "namespace": "/"} in received


def test_create_app_refuses_a_weak_token(settings):
    from registry.db import Registry
    from webapp import create_app

    with Registry.open(settings) as registry, pytest.raises(ValueError, match="token"):
        create_app(settings, token="short", registry=registry)


def test_webapp_does_not_import_torch(tmp_path):
    code = ("import sys; from hope_models.settings import load_settings; from webapp import create_app; "
            "from webapp.auth import load_or_create_token; s = load_settings(); "
            "app, sio = create_app(s, token=load_or_create_token(s)); "
            "c = app.test_client(); assert c.get('/api/health').status_code == 200; "
            "print('torch' in sys.modules)")
    env = {**os.environ, "HOPE_HOME": str(tmp_path / "home")}
    proc = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, cwd=REPO, env=env, timeout=60)
    assert proc.returncode == 0, proc.stderr
    assert proc.stdout.strip() == "False"


# -- the real `run_trainer.py webapp` process (production mode: Redis message queue, systemd notify) --

class EngineIOPolling:
    """A minimal Socket.IO client over Engine.IO long-polling with urllib (no extra dependency)."""

    def __init__(self, base: str):
        import json
        import urllib.request

        self._json, self._request = json, urllib.request
        self.base = base.rstrip("/") + "/socket.io/?EIO=4&transport=polling"
        opened = self._get(self.base)
        assert opened.startswith("0"), opened
        self.url = self.base + "&sid=" + json.loads(opened[1:])["sid"]

    def _get(self, url: str) -> str:
        with self._request.urlopen(url, timeout=15) as response:
            return response.read().decode()

    def send(self, packet: str) -> None:
        request = self._request.Request(self.url, data=packet.encode(), method="POST",
                                        headers={"Content-Type": "text/plain;charset=UTF-8"})
        with self._request.urlopen(request, timeout=15) as response:
            assert response.read().lower() == b"ok"

    def receive(self) -> list[str]:
        return self._get(self.url).split("\x1e")  # packets are separated by the record separator

    def connect(self, token: str) -> str:
        self.send("40" + self._json.dumps({"token": token}))
        return self.receive()[0]


def test_webapp_command_relays_redis_events_and_notifies_systemd(tmp_path):
    import json
    import socket as pysocket
    import urllib.request

    from daemon.events import RedisEmitterSink
    from daemon_fixtures import RedisServer

    redis = RedisServer(tmp_path / "redis")
    notify_path = tmp_path / "notify"
    sd = pysocket.socket(pysocket.AF_UNIX, pysocket.SOCK_DGRAM)
    sd.bind(str(notify_path))
    sd.settimeout(20)
    env = {k: v for k, v in os.environ.items() if not k.startswith("HOPE_")}
    env.update({"HOPE_HOME": str(tmp_path / "home"), "HOPE_REDIS_URL": redis.url,
                "NOTIFY_SOCKET": str(notify_path), "WATCHDOG_USEC": "1000000"})
    proc = subprocess.Popen([sys.executable, str(REPO / "run_trainer.py"), "webapp", "--port", "0"], env=env,
                            cwd=REPO, stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True)
    try:
        ready = sd.recv(4096).decode()
        assert ready.startswith("READY=1"), ready
        assert sd.recv(4096).decode() == "WATCHDOG=1"  # pinged because /api/health answers
        line = next(line for line in proc.stdout if "Robot Editor:" in line)
        base = line.split()[2]
        token = (tmp_path / "home" / "token").read_text().strip()
        with urllib.request.urlopen(base + "api/health", timeout=10) as response:
            assert json.loads(response.read())["status"] == "ok"

        refused = EngineIOPolling(base).connect("not-the-token-at-all")
        assert refused.startswith("44") and "unauthorized" in refused, refused
        client = EngineIOPolling(base)
        assert client.connect(token).startswith("40{"), "the token was refused"

        # what the daemon process does in production: a write-only emitter on the Redis queue
        RedisEmitterSink(redis.url).emit("run.progress", {"run_id": "r-x", "step": 7})
        packets = client.receive()
        assert '42["run.progress",{"run_id":"r-x","step":7}]' in packets, packets
    finally:
        proc.terminate()
        code = proc.wait(20)
        sd.close()
        redis.stop()
    assert code == 0
