"""The robot's door runs in a process of its own (webapp/door_process.py): nothing the editor's side
does holds its interpreter; it comes back on the same port when it dies, and goes when serve goes."""
from __future__ import annotations

import json
import os
import signal

import psutil
import pytest

from brain_fixtures import serve_a_copy
from hostile_clients import http_request, wait_until
from test_inference_door import _infer_body, _serve_with_door


def _listener(port: int) -> int | None:
    """The pid listening on this TCP port of this machine, or None."""
    for conn in psutil.net_connections(kind="tcp"):
        if conn.status == psutil.CONN_LISTEN and conn.laddr and conn.laddr.port == port:
            return conn.pid
    return None


def _gone(pid: int) -> bool:
    try:
        return psutil.Process(pid).status() == psutil.STATUS_ZOMBIE
    except psutil.NoSuchProcess:
        return True


@pytest.mark.slow
def test_the_door_is_a_child_of_serve_restarted_on_its_port_and_gone_with_serve(tmp_path, tmp_path_factory):
    from daemon_fixtures import Home

    home = Home(tmp_path / "home")
    serve_a_copy(home.path, tmp_path_factory)
    proc, (port, token, door) = _serve_with_door(home)
    auth = {"Authorization": f"Bearer {token}", "Content-Type": "application/json"}

    def answers() -> bool:
        status, body = http_request(door, "POST", "/api/brain/infer", body=_infer_body(), headers=auth)
        return status == 200 and len(json.loads(body)["action"]) == 2

    serve_pid = proc.popen.pid
    child = None
    try:
        assert wait_until(answers, 30)
        child = _listener(door)
        assert child is not None and child != serve_pid, "the door must not share serve's interpreter"
        assert psutil.Process(child).ppid() == serve_pid
        assert _listener(port) == serve_pid  # the Robot Editor stays in serve
        assert (home.path / "logs" / "door.log").stat().st_size > 0
        # the child's app keeps the door's rules: the token, the Host rule, only the robot's routes
        assert http_request(door, "GET", "/api/brain")[0] == 401
        status, body = http_request(door, "GET", "/api/brain", headers=auth)
        assert status == 200 and json.loads(body)["components"]["fast_loop"]["serving"]["version"], body
        assert http_request(door, "GET", "/api/ping")[0] == 200
        assert http_request(door, "GET", "/api/runs", headers=auth)[0] == 404
        assert http_request(door, "POST", "/api/brain/promote", body=b"{}", headers=auth)[0] == 404
        assert http_request(door, "GET", "/api/ping", headers={"Host": "evil.example:80"})[0] in (400, 403, 421)

        os.kill(child, signal.SIGKILL)  # an OOM kill, a crash
        assert wait_until(lambda: _listener(door) not in (None, child), 30), "the door was not restarted"
        child = _listener(door)
        assert wait_until(answers, 30), "the restarted door does not answer on the robot's port"
    finally:
        proc.popen.kill()  # serve dies without stopping anything: the door must not outlive it
        proc.popen.wait(10)
        home.close()
    assert child is not None and wait_until(lambda: _gone(child), 15), "the door outlived serve"


def test_the_door_stops_on_a_burst_of_signals(tmp_path):
    """Its parent's death and a service stop can both send SIGTERM at once: the door must still exit
    (a handler that took a lock once deadlocked it, with the robot's port held for good)."""
    from hope_models.settings import load_settings
    from registry.db import Registry
    from webapp.door_process import DoorProcess

    settings = load_settings(tmp_path / "home", env={})
    settings.inference_port = 0
    Registry.open(settings, migrate=True).close()
    door = DoorProcess(settings).start()
    try:
        pid = door.pid
        assert wait_until(lambda: http_request(door.port, "GET", "/api/ping")[0] == 200, 20)
        for _ in range(200):  # as fast as they come: a handler runs while the last one still does
            try:
                os.kill(pid, signal.SIGTERM)
            except ProcessLookupError:
                break
        assert wait_until(lambda: _gone(pid), 15), "the door did not exit after SIGTERM"
    finally:
        door.stop()
