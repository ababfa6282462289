"""The robot's door in a process of its own: an interpreter nothing on the Robot Editor's side shares.

    door = DoorProcess(settings)   # in serve / webapp, after the registry is migrated
    door.start()                   # ServerError when the port or socket cannot be had
    door.port, door.url, door.socket, door.pid
    door.stop()

    python -m webapp.door_process --ready-fd N     # the child (started by DoorProcess only)

The inference port (webapp/inference_door.py) has listeners and threads of its own, but threads
share one interpreter lock: every request the editor's side answers (an upload checked, a run
created, a neighbour's refused long-polls) holds it for a while, and the robot's answer waits. In
the soak, with every attacker running, the door in serve's process answered at p99 2.5x its quiet
figure; in a process of its own, 1.1x (docs/benchmarks.md). So the child hosts the same Flask app
filtered to the robot's routes (create_door_app: no Socket.IO, no editor blueprints), with a BrainService of its own (it watches the same promotion
pointers, so both processes serve the same versions), and records first inferences (the loop
closure) in the registry like serve's does. Its log goes to $HOPE_HOME/logs/door.log (rotated).

It is restarted with backoff when it dies, on the port it had (so a robot's URL stays right even
with inference_port 0), and it gets SIGTERM when its parent dies.
"""
from __future__ import annotations

import argparse
import json
import logging
import os
import select
import signal
import subprocess
import sys
import threading
import time
from pathlib import Path
from typing import Any

from hope_models.child_command import RestartBackoff, dies_with_parent, end_child, module_argv
from hope_models.log_format import configure_logging
from hope_models.log_limits import PipeToLog
from hope_models.malloc_arenas import limit_malloc_arenas
from hope_models.settings import SettingsError, load_settings
from webapp.inference_door import create_door_app, open_inference_door
from webapp.server import ServerError, http_url

log = logging.getLogger(__name__)

MODULE = "webapp.door_process"
READY_TIMEOUT_S = 120.0  # imports and the first model load; minutes under arm64 emulation, seconds on a Pi
STOP_S = 5.0
BACKOFF_S = (0.5, 1.0, 2.0, 5.0, 10.0, 30.0)  # restarts; reset after it stayed up STABLE_S
STABLE_S = 60.0


def door_env(settings: Any, port: int | None = None) -> dict[str, str]:
    """The child's environment: this process's, with what the door must share with the caller's
    settings even when they came from code or the command line rather than the environment."""
    env = dict(os.environ)
    env.update({
        "HOPE_HOME": str(settings.home),
        "HOPE_HOST": str(settings.host),
        "HOPE_INFERENCE_PORT": str(settings.inference_port if port is None else port),
        "HOPE_INFERENCE_SOCKET": str(getattr(settings, "inference_socket", "") or ""),
        "HOPE_MAX_CONNECTIONS": str(settings.max_connections),
        "HOPE_MAX_CONNECTIONS_PER_CLIENT": str(settings.max_connections_per_client),
        "HOPE_ALLOWED_HOSTS": ",".join(getattr(settings, "allowed_hosts", []) or []),
        "PYTHONUNBUFFERED": "1",
    })
    return env


class DoorProcess:
    """The parent's side: start the child, learn its port, keep it alive, stop it."""

    def __init__(self, settings: Any):
        self.settings = settings
        self.port: int | None = None
        self.socket: str | None = None
        self.proc: subprocess.Popen | None = None
        self.restarts = 0
        self._stopping = threading.Event()
        self._lock = threading.Lock()
        self._watcher: threading.Thread | None = None
        self.log_path = Path(settings.home) / "logs" / "door.log"

    @property
    def pid(self) -> int | None:
        return None if self.proc is None else self.proc.pid

    @property
    def url(self) -> str:
        return http_url(str(self.settings.host), self.port)

    def start(self) -> "DoorProcess":
        self.proc, ready = self._spawn(self.settings.inference_port)
        self.port, self.socket = ready["port"], ready.get("socket")
        self._watcher = threading.Thread(target=self._watch, name="door-supervisor", daemon=True)
        self._watcher.start()
        return self

    def _spawn(self, port: int) -> tuple[subprocess.Popen, dict]:
        self.log_path.parent.mkdir(parents=True, exist_ok=True)
        read_fd, write_fd = os.pipe()
        try:
            # its own session: the terminal's Ctrl-C reaches the parent, which stops the door last
            proc = subprocess.Popen(dies_with_parent(module_argv(MODULE, "--ready-fd", str(write_fd))),
                                    stdin=subprocess.DEVNULL, stdout=subprocess.PIPE, stderr=subprocess.STDOUT,
                                    env=door_env(self.settings, port), pass_fds=(write_fd,),
                                    start_new_session=True)
        finally:
            os.close(write_fd)
        assert proc.stdout is not None  # stdout=PIPE
        PipeToLog(self.log_path, self.settings).start(proc.stdout)
        try:
            ready = _read_ready(read_fd, proc, READY_TIMEOUT_S)
        finally:
            os.close(read_fd)
        if "error" in ready:
            end_child(proc, STOP_S)
            raise ServerError(ready["error"])
        log.info("inference door: pid %d on port %d%s, log %s", proc.pid, ready["port"],
                 f" and {ready['socket']}" if ready.get("socket") else "", self.log_path)
        return proc, ready

    def _watch(self) -> None:
        backoff = RestartBackoff(BACKOFF_S, STABLE_S)
        while not self._stopping.is_set():
            proc = self.proc
            started = time.monotonic()
            code = proc.wait() if proc is not None else None
            if self._stopping.is_set():
                return
            delay = backoff.after_exit(started)
            log.warning("the inference door exited with code %s; restarting in %.1f s (see %s)", code, delay,
                        self.log_path)
            if self._stopping.wait(delay):
                return
            try:
                with self._lock:
                    if self._stopping.is_set():
                        return
                    self.proc, _ = self._spawn(self.port or 0)  # the port the robot was told
                self.restarts += 1
            except (ServerError, OSError) as exc:
                log.warning("the inference door could not be restarted: %s", exc)
                self.proc = None
                self._stopping.wait(backoff.after_failed_start())

    def stop(self, timeout: float = STOP_S) -> None:
        self._stopping.set()
        with self._lock:
            proc = self.proc
        if proc is not None:
            end_child(proc, timeout)
        if self._watcher is not None:
            self._watcher.join(timeout)


def _read_ready(fd: int, proc: subprocess.Popen, timeout: float) -> dict:
    """The child's one JSON line on the ready pipe: {"port", "socket"} or {"error"}."""
    deadline = time.monotonic() + timeout
    data = b""
    while b"\n" not in data:
        left = deadline - time.monotonic()
        if left <= 0:
            end_child(proc, STOP_S)
            raise ServerError(f"the inference door did not start within {timeout:.0f} s (see logs/door.log)")
        readable, _, _ = select.select([fd], [], [], min(left, 0.5))
        if readable:
            chunk = os.read(fd, 4096)
            if not chunk:
                code = proc.wait(STOP_S)
                raise ServerError(f"the inference door exited with code {code} before it was ready "
                                  "(see logs/door.log)")
            data += chunk
    try:
        ready = json.loads(data.split(b"\n", 1)[0])
    except ValueError:
        end_child(proc, STOP_S)
        raise ServerError(f"the inference door said {data[:200]!r}, not its port") from None
    return ready


# -- the child --------------------------------------------------------------------------------


def child(ready_fd: int) -> int:
    from hope_models.runtime.brain_service import BrainService  # NumPy, no torch
    from registry.db import Registry, RegistryError  # lazy: loads sqlalchemy
    from webapp.auth import TokenError, load_or_create_token  # lazy: loads flask

    limit_malloc_arenas()  # a thread per connection, for days: hope_models/malloc_arenas.py
    configure_logging(logging.INFO)
    for noisy in ("werkzeug", "engineio", "socketio"):
        logging.getLogger(noisy).setLevel(logging.WARNING)
    # The handler only appends to a list: one that took a lock (Event.set) could run while the main
    # thread held that very lock in Event.wait, and a second SIGTERM (its parent's death and a stop)
    # then deadlocked the door for good.
    stopping: list[int] = []
    signal.signal(signal.SIGTERM, lambda signum, _frame: stopping.append(signum))
    signal.signal(signal.SIGINT, lambda signum, _frame: stopping.append(signum))

    def say(obj: dict) -> None:
        os.write(ready_fd, (json.dumps(obj) + "\n").encode())

    try:
        settings = load_settings()
        registry = Registry.open(settings, migrate=False)  # the parent migrated it
        token = load_or_create_token(settings)
    except (SettingsError, RegistryError, TokenError, OSError) as exc:
        say({"error": f"the inference door: {exc}"})
        return 2
    brain = BrainService(settings.home)
    app = create_door_app(settings, token=token, registry=registry, brain=brain)
    try:
        door = open_inference_door(app, settings)
    except ServerError as exc:
        say({"error": str(exc)})
        registry.close()
        return 2
    brain.start()
    door.start()
    say({"port": door.port, "socket": None if door.socket is None else str(door.socket)})
    os.close(ready_fd)
    log.info("inference door serving on %s (pid %d)", door.url, os.getpid())
    while not stopping:
        time.sleep(0.5)
    door.stop()
    app.extensions["hope"].close()
    brain.stop()
    registry.close()
    log.info("inference door stopped")
    return 0


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog=f"python -m {MODULE}", description="the robot's inference door "
                                     "(started by `serve` and `webapp`, not by hand)")
    parser.add_argument("--ready-fd", type=int, required=True, help="where to write the port once listening")
    args = parser.parse_args(argv)
    return child(args.ready_fd)


if __name__ == "__main__":
    sys.exit(main())


__all__ = ["DoorProcess", "door_env", "main"]
