"""`hope-trainer serve`: the all-in-one mode (first run, a laptop, a bench Pi). No Redis needed.

    hope-trainer serve [--host 127.0.0.1] [--port 8765] [--inference-port 8766] [--no-worker] [--queue pi]

One process runs the webapp (REST + Socket.IO) and the daemon (a background thread pushing events
straight into this process's Socket.IO), and supervises the Celery worker as a child process
(restarted with backoff if it dies; its output goes to $HOPE_HOME/logs/worker.log). The broker is
the embedded SQLite one under $HOPE_HOME/broker unless HOPE_REDIS_URL is set. It prints the URL and
the API token ($HOPE_HOME/token, created 0600 on the first start).

Ctrl-C or SIGTERM stops everything in order: the daemon stops dispatching; the running job is asked
to checkpoint and hand its run back to the queue (up to 30 s); the worker is stopped (SIGTERM, then
SIGKILL after 20 s); a job that could not finish in time is recorded as interrupted and requeued.
The next `serve` finds the runs as they were left and resumes the queued one from its checkpoint.
A second Ctrl-C skips the waiting. Exit 0 after a clean stop, 2 when it cannot start (port taken,
unreadable token), 1 when the daemon loop died.
BrainService (the promoted models, hot-reloaded from $HOPE_HOME/promoted/) answers POST
/api/brain/infer on the inference port (the robot's door, webapp/inference_door.py) in a child
process of its own (webapp/door_process.py: no editor request shares its interpreter; its log is
$HOPE_HOME/logs/door.log), and in this process on the editor's port; promoting and the sim reflex
run as `hope-trainer` children.
Nothing in this process imports torch: only the worker's job child and those children do.
"""
from __future__ import annotations

import argparse
import logging
import os
import signal
import subprocess
import sys
import threading
import time
from pathlib import Path
from typing import TYPE_CHECKING, Any

from daemon.events import SocketIOSink
from hope_models.child_command import RestartBackoff, dies_with_parent
from hope_models.log_format import console_formatter
from hope_models.log_limits import PipeToLog, rate_limit, rotating_file_handler
from hope_models.malloc_arenas import limit_malloc_arenas
from hope_models.numbers import NumberError, int_from_text
from hope_models.settings import SettingsError, load_settings
from hope_trainer.console import say
from webapp import create_app
from webapp.door_process import DoorProcess
from webapp.server import ConnectionLimits, HttpServer, ServerError
from workers.cli import worker_command, worker_env

if TYPE_CHECKING:
    from flask import Flask

    from daemon.service import Daemon
    from hope_models.runtime.brain_service import BrainService
    from registry.db import Registry

log = logging.getLogger("hope.serve")

SHUTDOWN_WAIT_S = 30.0  # for the running job to checkpoint and requeue itself
WORKER_STOP_S = 20.0  # for the worker to exit after SIGTERM, before SIGKILL
BACKOFF_S = (1.0, 2.0, 5.0, 10.0, 30.0, 60.0)  # worker restarts; reset after it stayed up STABLE_S
STABLE_S = 60.0

def port_number(text: str) -> int:
    try:  # the one rule for numbers (hope_models/numbers.py)
        return int_from_text("--port", text, minimum=0, maximum=65535)
    except NumberError as exc:
        raise argparse.ArgumentTypeError(f"{exc.reason}: not a port number (0-65535; 0 = any free port)") from None


def add_listen_arguments(parser: argparse.ArgumentParser) -> None:
    """--host/--port of every command that serves the webapp (serve, webapp, demo)."""
    parser.add_argument("--host", default=None, help="address to listen on (default: settings, 127.0.0.1)")
    parser.add_argument("--port", type=port_number, default=None,
                        help="port (default: settings, 8765; 0 = any free one)")
    parser.add_argument("--inference-port", type=port_number, default=None,
                        help="the robot's inference port (default: settings, 8766; 0 = any free one; "
                             "with --port 0 it is any free one too)")


def listen_settings(args: argparse.Namespace):
    """The settings with --host/--port applied; SettingsError when config.toml or the env is bad."""
    settings = load_settings()
    if args.host is not None:
        settings.host = args.host
    if args.port is not None:
        settings.port = args.port
    if getattr(args, "inference_port", None) is not None:
        settings.inference_port = args.inference_port
    elif args.port == 0:
        settings.inference_port = 0  # a second instance (tests) must not collide on the fixed door
    return settings


def add_arguments(parser: argparse.ArgumentParser) -> None:
    add_listen_arguments(parser)
    parser.add_argument("--no-worker", action="store_true",
                        help="do not start a worker child (one runs elsewhere, e.g. `run_trainer.py worker`)")
    parser.add_argument("--queue", default="pi", help="the queue the worker child serves (default pi)")
    parser.add_argument("--tick", type=float, default=0.5, help=argparse.SUPPRESS)  # daemon tick, seconds


class WorkerSupervisor:
    """Keeps one worker process alive (restart with backoff) until stop()."""

    def __init__(self, settings: Any, queue: str, log_path: Path):
        self.cmd = worker_command(settings, queue)
        self.env = worker_env(settings)
        self.settings = settings
        self.log_path = log_path
        self.proc: subprocess.Popen | None = None
        self.restarts = 0
        self._stopping = threading.Event()
        self._thread = threading.Thread(target=self._loop, name="worker-supervisor", daemon=True)
        self._lock = threading.Lock()

    def start(self) -> None:
        self._thread.start()

    def _spawn(self) -> subprocess.Popen:
        self.log_path.parent.mkdir(parents=True, exist_ok=True)
        argv = dies_with_parent(self.cmd)
        # its own session: the terminal's Ctrl-C reaches serve only, which stops the worker in order.
        # Its output (and its job child's, tracebacks and prints included) through a pipe we rotate:
        # an appended file would grow without bound.
        proc = subprocess.Popen(argv, stdin=subprocess.DEVNULL, stdout=subprocess.PIPE, stderr=subprocess.STDOUT,
                                env=self.env, start_new_session=True)
        assert proc.stdout is not None  # stdout=PIPE
        PipeToLog(self.log_path, self.settings).start(proc.stdout)
        return proc

    def _loop(self) -> None:
        backoff = RestartBackoff(BACKOFF_S, STABLE_S)
        while not self._stopping.is_set():
            started = time.monotonic()
            try:
                with self._lock:
                    if self._stopping.is_set():
                        return
                    self.proc = self._spawn()
                log.info("worker started (pid %d), log %s", self.proc.pid, self.log_path)
                code = self.proc.wait()
                why = f"exited with code {code}"
            except OSError as exc:  # cannot start it at all (log dir unwritable, python gone): keep trying
                why = f"could not be started: {exc}"
            if self._stopping.is_set():
                return
            delay = backoff.after_exit(started)
            self.restarts += 1
            log.warning("worker %s; restarting in %.0f s (see %s)%s", why, delay, self.log_path,
                        "\n" + self.log_tail() if backoff.failures >= 2 else "")
            self._stopping.wait(delay)

    def log_tail(self, lines: int = 15) -> str:
        try:
            text = self.log_path.read_text(encoding="utf-8", errors="replace").splitlines()
        except OSError:
            return ""
        return "\n".join("  | " + line for line in text[-lines:])

    def alive(self) -> bool:
        return self.proc is not None and self.proc.poll() is None

    def stop(self, timeout: float = WORKER_STOP_S, force: bool = False) -> int | None:
        """SIGTERM (Celery's warm shutdown), SIGKILL the whole group after `timeout` (or at once with force)."""
        with self._lock:
            self._stopping.set()
            proc = self.proc
        if proc is None:
            return None
        if proc.poll() is None:
            try:
                if force:
                    os.killpg(proc.pid, signal.SIGKILL)
                else:
                    proc.send_signal(signal.SIGTERM)
            except ProcessLookupError:
                pass
            try:
                proc.wait(timeout)
            except subprocess.TimeoutExpired:
                log.warning("worker did not stop within %.0f s; killing it", timeout)
        # whatever is left of its process group (a job child that did not exit)
        try:
            os.killpg(proc.pid, signal.SIGKILL)
        except (ProcessLookupError, PermissionError):
            pass
        code = proc.wait()
        self._thread.join(2.0)
        return code


class Serve:
    """The pieces of one `serve` process, started and stopped in order."""

    def __init__(self, settings: Any, args: argparse.Namespace):
        self.settings = settings
        self.args = args
        self.shutdown = threading.Event()
        self.force = threading.Event()
        self.daemon_stop = threading.Event()
        self.registry: Registry | None = None
        self.server: HttpServer | None = None
        self.door: DoorProcess | None = None  # the inference port, a child process (webapp/door_process.py)
        self.daemon: Daemon | None = None
        self.daemon_thread: threading.Thread | None = None
        self.worker: WorkerSupervisor | None = None
        self.app: Flask | None = None
        self.brain: BrainService | None = None  # the promoted models, answering POST /api/brain/infer
        self.failed = False  # the daemon loop died: exit non-zero after stopping the rest

    def start(self) -> str:
        from daemon.service import Daemon  # lazy: loads mcap, numpy, psutil, sqlalchemy
        from hope_models.runtime.brain_service import BrainService  # NumPy, no torch
        from registry.db import Registry  # lazy: loads sqlalchemy
        from webapp.auth import load_or_create_token  # lazy: loads flask

        self.registry = Registry.open(self.settings, migrate=True)  # the one migration of this process
        token = load_or_create_token(self.settings)
        self.brain = BrainService(self.settings.home)
        app, socketio = create_app(self.settings, token=token, registry=self.registry, brain=self.brain)
        self.app = app
        self.server = HttpServer(app, self.settings.host, self.settings.port,  # bind before anything runs
                                 ConnectionLimits.from_settings(self.settings))
        self.door = DoorProcess(self.settings).start()  # the robot's door, in a process of its own
        # remote_reports=False: serve's own worker child trains every run, on this host.
        self.daemon = Daemon(self.settings, SocketIOSink(socketio), tick_s=self.args.tick, registry=self.registry,
                             local_queues=(self.args.queue,), remote_reports=False)
        app.extensions["hope"].daemon = self.daemon
        self.daemon.start()  # reconcile what the last stop (or crash) left
        self.brain.start()  # loads what is promoted now, then watches the pointers
        self.server.start()
        self.daemon_thread = threading.Thread(target=self._run_daemon, name="daemon", daemon=True)
        self.daemon_thread.start()
        if not self.args.no_worker:
            self.worker = WorkerSupervisor(self.settings, self.args.queue, self.settings.home / "logs" / "worker.log")
            self.worker.start()
        return token

    def _run_daemon(self) -> None:
        assert self.daemon is not None  # start() sets it before it starts this thread
        try:
            self.daemon.run_forever(self.daemon_stop)
        except Exception:  # noqa: BLE001 - a dead daemon thread must stop serve, not leave it half-alive
            log.exception("the daemon loop crashed; stopping")
            self.failed = True
            self.shutdown.set()

    # -- stopping ----------------------------------------------------------------------------

    def _local_running(self) -> list[str]:
        from sqlalchemy import select  # lazy: loads sqlalchemy

        from registry import runs  # lazy: loads sqlalchemy
        from registry.models import Run  # lazy: loads sqlalchemy

        assert self.registry is not None  # called by stop() only with a worker, which start() adds last
        with self.registry.session(readonly=True) as s:
            return list(s.scalars(select(Run.id).where(Run.state.in_(runs.ACTIVE), Run.queue == self.args.queue)))

    def _hand_back_runs(self) -> list[str]:
        """Ask our worker's running job to checkpoint and requeue itself; a run dispatched but not yet
        claimed by a child goes back to the queue at once (its task, if delivered later, is stale)."""
        from registry import runs  # lazy: loads sqlalchemy
        from registry.models import Run  # lazy: loads sqlalchemy

        waiting = []
        for run_id in self._local_running():
            assert self.registry is not None  # _local_running() checked it
            with self.registry.session() as s:
                run = s.get(Run, run_id)
                if run is None or run.state not in runs.ACTIVE:
                    continue
                if run.state == "starting":
                    runs.transition(s, run, "queued", reason="shutdown", message=runs.SHUTDOWN_MESSAGE)
                    log.info("run %s: not started yet; back in the queue", run_id)
                else:
                    runs.request_shutdown(s, run)
                    waiting.append(run_id)
                    log.info("run %s: asking the job to checkpoint and stop", run_id)
        return waiting

    def _wait_runs(self, run_ids: list[str], timeout: float) -> list[str]:
        deadline = time.monotonic() + timeout
        left = list(run_ids)
        while left and time.monotonic() < deadline and not self.force.is_set():
            if self.worker is not None and not self.worker.alive():
                break
            time.sleep(0.2)
            still = set(self._local_running())
            left = [r for r in left if r in still]
        return left

    def stop(self) -> None:
        log.info("stopping%s", " now (forced)" if self.force.is_set() else "")
        self.daemon_stop.set()  # no new dispatches from here on
        if self.daemon is not None:
            self.daemon.wake()  # leave the tick's wait now
        if self.daemon_thread is not None:
            self.daemon_thread.join(10.0)
        if self.worker is not None:
            left = self._wait_runs(self._hand_back_runs(), SHUTDOWN_WAIT_S)
            if left:
                log.warning("run(s) %s did not stop within %.0f s", ", ".join(left), SHUTDOWN_WAIT_S)
            log.info("stopping the worker")
            code = self.worker.stop(timeout=0.5 if self.force.is_set() else WORKER_STOP_S, force=self.force.is_set())
            log.info("worker stopped (exit code %s)", code)
            if self.daemon is not None and self.daemon.reconciler is not None:
                # a job killed before it could hand its run back: interrupted -> queued (attempt + 1)
                for action in self.daemon.reconciler.reconcile():
                    log.info("run %s %s (%s)", action.run_id, action.action, action.why)
        if self.server is not None:
            self.server.stop()
        if self.door is not None:
            self.door.stop()
        if self.app is not None:
            self.app.extensions["hope"].close()  # a promotion gate or sim reflex child still running
        if self.brain is not None:
            self.brain.stop()
        if self.daemon is not None:
            self.daemon.stop()
        if self.registry is not None:
            self.registry.close()


def brain_summary(brain: Any) -> str:
    """One line: what BrainService serves per component (or why not)."""
    parts = []
    for component, st in sorted(brain.status().items()):
        if st.get("version"):
            parts.append(f"{component} {st['version']}")
        elif st.get("last_error"):
            parts.append(f"{component} not served: {st['last_error']}")
        else:
            parts.append(f"{component} nothing promoted yet (run_trainer.py promote RUN)")
    return "brain: " + ("; ".join(parts) or "no components")


def door_line(door: Any) -> str:
    also = f", and the Unix socket {door.socket}" if door.socket else ""
    return f"inference: {door.url}api/brain/infer (the robot's port{also}: infer, GET /api/brain, ping, health)"


def setup_logging(home: Path, console_level: int = logging.INFO, settings: Any = None) -> None:
    """Services log to $HOPE_HOME/logs/daemon.log, rotated at `settings`' log_max_mb; the terminal
    gets `console_level` and up (the demo keeps it to warnings so its own lines stay readable).
    Under a systemd unit the terminal lines carry journald priorities instead of a timestamp
    (hope_models/log_format.py). Both are rate-limited (hope_models/log_limits.py)."""
    root = logging.getLogger()
    root.setLevel(logging.INFO)
    console = logging.StreamHandler(sys.stderr)
    console.setLevel(console_level)
    console.setFormatter(console_formatter("%H:%M:%S"))
    console.addFilter(rate_limit())
    root.addHandler(console)
    root.addHandler(rotating_file_handler(home / "logs" / "daemon.log", settings))
    for noisy in ("werkzeug", "engineio", "socketio", "kombu", "celery", "amqp", "alembic"):
        logging.getLogger(noisy).setLevel(logging.WARNING)


def run(args: argparse.Namespace) -> int:
    from registry.db import RegistryError  # lazy: loads sqlalchemy
    from webapp.auth import TokenError  # lazy: loads flask

    limit_malloc_arenas()  # a thread per connection, for days: hope_models/malloc_arenas.py
    try:
        settings = listen_settings(args)
    except SettingsError as exc:
        print(f"error: {exc}", file=sys.stderr)
        return 2
    setup_logging(settings.home, settings=settings)
    serve = Serve(settings, args)

    def on_signal(signum, _frame):
        if serve.shutdown.is_set():
            serve.force.set()
            print("\nstopping now (not waiting for the job)", file=sys.stderr, flush=True)
        else:
            serve.shutdown.set()
            print("\nstopping: the running job checkpoints and goes back to the queue (again to force)",
                  file=sys.stderr, flush=True)

    previous = {sig: signal.signal(sig, on_signal) for sig in (signal.SIGINT, signal.SIGTERM)}
    try:
        try:
            token = serve.start()
        except (RegistryError, TokenError, ServerError, OSError) as exc:
            print(f"error: {exc}", file=sys.stderr)
            serve.stop()
            return 2
        broker = "redis" if settings.redis_url else f"embedded ({settings.home / 'broker'})"
        worker = "no worker (--no-worker)" if args.no_worker else f"worker queue {args.queue}"
        assert serve.server is not None  # start() returned: it is listening
        say(f"Robot Editor: {serve.server.url}  token: {token}")
        say(door_line(serve.door))
        say(f"state {settings.home}, broker {broker}, {worker}; Ctrl-C to stop")
        say(brain_summary(serve.brain))
        while not serve.shutdown.is_set():
            serve.shutdown.wait(0.5)
        serve.stop()
        if serve.failed:
            print("stopped after an error in the daemon loop (see above and logs/daemon.log)", file=sys.stderr)
            return 1
        print("stopped", file=sys.stderr, flush=True)
        return 0
    finally:
        for sig, handler in previous.items():
            signal.signal(sig, handler)
