"""Shared pieces for the daemon tests: a tiny dataset, a tmp $HOPE_HOME, real processes (a Celery
worker, the daemon, a redis-server on a free loopback port) and wait_until, which on a timeout
fails with the registry's state and the processes' log tails, so a failure says what happened.

Test modules import what they use:  from daemon_fixtures import ...  (tests/ is on sys.path).
Fixtures are plain functions here; the dataset is built once per test run (conftest.shared_build),
however many modules and xdist workers use it.
"""
from __future__ import annotations

import json
import os
import shutil
import signal
import socket
import subprocess
import sys
import time
from datetime import datetime
from pathlib import Path
from typing import Any, Callable

import pytest

REPO = Path(__file__).resolve().parents[1]

_DATASET: dict[str, Path] = {}


def tiny_dataset_path(tmp_path_factory) -> Path:
    """~600 steps of a learnable synthetic dataset (obs 4, act 2): a fast_loop step takes ~15 ms.
    Built once per test run (conftest.shared_build), whatever the number of xdist workers."""
    if "path" not in _DATASET:
        from conftest import shared_build

        def build(root: Path) -> None:
            from hope_models.data.synthetic import generate_dataset

            generate_dataset(root / "ds", 600, obs_dim=4, act_dim=2, episode_seconds=(3, 9), seed=3)

        _DATASET["path"] = shared_build(tmp_path_factory, "daemon-ds", build) / "ds"
    return _DATASET["path"]


@pytest.fixture
def tiny_dataset(tmp_path_factory) -> Path:
    return tiny_dataset_path(tmp_path_factory)


class Home:
    """A tmp $HOPE_HOME: its Settings, the environment for child processes, and its registry."""

    def __init__(self, path: Path, redis_url: str | None = None, extra_env: dict[str, str] | None = None):
        from hope_models.settings import load_settings

        self.path = path
        path.mkdir(parents=True, exist_ok=True)
        self.env = {k: v for k, v in os.environ.items() if not k.startswith("HOPE_")}
        self.env.update({"HOPE_HOME": str(path), "PYTHONUNBUFFERED": "1",
                         # No thermal sources unless a test sets them: this machine's zone must not
                         # throttle the jobs.
                         "HOPE_THERMAL_ZONE": str(path / "no-thermal-zone"), "HOPE_VCGENCMD": "",
                         "OMP_NUM_THREADS": "1", "MKL_NUM_THREADS": "1",
                         # Gating imports torch in a child per completed run; tests of promotion
                         # turn it back on.
                         "HOPE_AUTO_PROMOTE": "0",
                         # the robot's door on any free port: tests run side by side
                         "HOPE_INFERENCE_PORT": "0"})
        self.env.pop("NOTIFY_SOCKET", None)
        self.env.pop("WATCHDOG_USEC", None)
        if redis_url:
            self.env["HOPE_REDIS_URL"] = redis_url
        self.env.update(extra_env or {})
        self.settings = load_settings(env=self.env)
        self._registry = None
        self.logs: list[Path] = []

    @property
    def registry(self):
        if self._registry is None:
            from registry.db import Registry

            self._registry = Registry.open(self.settings, migrate=True)
        return self._registry

    def close(self) -> None:
        if self._registry is not None:
            self._registry.close()
            self._registry = None

    # -- runs ------------------------------------------------------------------------------

    def enqueue(self, data: Path, *, component: str = "fast_loop", steps: int = 60, queue: str = "pi",
                priority: int = 0, max_attempts: int = 3, **overrides: Any) -> str:
        """A queued run through the same door as `enqueue` (registry.run_request)."""
        from registry.run_request import build_request, submit

        cfg = {"seed": 0, "batch_size": 8, "threads": 1, "warmup": 5, "log_every": 5,
               "checkpoint_every_steps": 20}
        cfg.update(overrides)
        req = build_request(component=component, data=str(data), steps=steps, queue=queue, priority=priority,
                            max_attempts=max_attempts, overrides=cfg)
        with self.registry.session() as s:
            return submit(s, self.settings, req).id

    def run(self, run_id: str) -> dict[str, Any]:
        from registry import runs

        with self.registry.session(readonly=True) as s:
            return _as_dict(runs.get_run(s, run_id))

    def runs(self) -> list[dict[str, Any]]:
        from registry import runs

        with self.registry.session(readonly=True) as s:
            return [_as_dict(r) for r in runs.list_runs(s)]

    def events(self, run_id: str, kinds: list[str] | None = None) -> list[dict[str, Any]]:
        from registry import runs

        with self.registry.session(readonly=True) as s:
            return [e.to_json_obj() for e in runs.run_events(s, run_id, kinds=kinds)]

    def states(self, run_id: str) -> list[str]:
        return [e["payload"]["state"] for e in self.events(run_id, ["state"])]

    def describe(self) -> str:
        """The registry's runs and the tails of the logs, for a failure message."""
        lines = ["runs:"]
        try:
            for r in self.runs():
                lines.append(f"  {r['id']} {r['component']} {r['queue']} {r['state']}({r['pause_reason']}) "
                             f"step {r['step']}/{r['total_steps']} attempt {r['attempt']} pid {r['worker_pid']} "
                             f"task {r['celery_task_id']} error {r['error']!r}")
                for e in self.events(r["id"], ["state", "log"])[-12:]:
                    lines.append(f"      {e['time']} {e['kind']} {json.dumps(e['payload'])[:300]}")
                # what the job itself last wrote (a child stuck between steps shows where)
                metrics = Path(r.get("run_dir") or "/nonexistent") / "metrics.jsonl"
                if metrics.exists():
                    lines.append(f"    {metrics} (tail):")
                    lines.extend(f"      {line[:300]}" for line in metrics.read_text(errors="replace").splitlines()[-8:])
        except Exception as exc:  # noqa: BLE001 - describing must not hide the real failure
            lines.append(f"  (registry unreadable: {exc})")
        for log in self.logs:
            text = log.read_text(errors="replace") if log.exists() else "(no log)"
            lines.append(f"--- {log.name} (tail) ---")
            lines.extend(text.splitlines()[-40:])
        return "\n".join(lines)


def _as_dict(run) -> dict[str, Any]:
    return {**run.to_json_obj(), "celery_task_id": run.celery_task_id}


@pytest.fixture
def home(tmp_path):
    h = Home(tmp_path / "home")
    yield h
    h.close()


def wait_until(predicate: Callable[[], Any], timeout: float, what: str, home: Home | None = None,
               interval: float = 0.1) -> Any:
    """Poll `predicate` until it returns something truthy (returned); on timeout fail with the
    state of the registry and the logs."""
    deadline = time.monotonic() + timeout
    while True:
        value = predicate()
        if value:
            return value
        if time.monotonic() > deadline:
            pytest.fail(f"timed out after {timeout:g} s waiting for {what}\n" + (home.describe() if home else ""))
        time.sleep(interval)


# -- the recorded timeline ----------------------------------------------------------------------

JOB_TIMEOUT = 90  # one tiny job on 2 busy cores, torch import in the child included


def _t(iso: str) -> datetime:
    return datetime.fromisoformat(iso)


def assert_never_overlapping(home, run_ids):
    """From the recorded timeline (run_events): each run's [claimed, left running] interval, one
    per attempt, is disjoint from every other run's. Returns the intervals sorted by start."""
    intervals = []
    for rid in run_ids:
        claimed = None
        for e in home.events(rid, ["state", "log"]):
            if e["kind"] == "log" and e["payload"]["message"].startswith("claimed by pid"):
                claimed = _t(e["time"])
            if e["kind"] == "state" and e["payload"]["from"] == "running" and claimed is not None:
                intervals.append((claimed, _t(e["time"]), rid))
                claimed = None
        assert claimed is None, f"{rid}: a claim without an end\n{home.describe()}"
    intervals.sort()
    for (s1, e1, r1), (s2, e2, r2) in zip(intervals, intervals[1:]):
        assert e1 <= s2, f"{r1} [{s1}, {e1}] overlaps {r2} [{s2}, {e2}]"
    return intervals


def all_states(home, ids, state="completed"):
    return all(home.run(r)["state"] == state for r in ids)


# -- processes --------------------------------------------------------------------------------

class Proc:
    """A child process with its output in a log file; stop() is SIGTERM, then SIGKILL."""

    def __init__(self, name: str, cmd: list[str], env: dict[str, str], log: Path, *, teardown_kill: bool = False,
                 cwd: Path = REPO):
        self.name, self.cmd, self.log = name, cmd, log
        # A Celery worker's warm shutdown takes ~4 s even when idle; once a test is over nothing
        # checks it, so the fixture kills its process group instead (tests that check a clean
        # stop call stop() themselves).
        self.teardown_kill = teardown_kill
        self._fh = open(log, "ab")
        self.popen = subprocess.Popen(cmd, env=env, cwd=cwd, stdout=self._fh, stderr=subprocess.STDOUT,
                                      start_new_session=True)

    @property
    def pid(self) -> int:
        return self.popen.pid

    def alive(self) -> bool:
        return self.popen.poll() is None

    def signal(self, sig: int) -> None:
        if self.alive():
            os.kill(self.pid, sig)

    def stop(self, timeout: float = 20.0) -> int | None:
        if self.alive():
            self.popen.send_signal(signal.SIGTERM)
            try:
                self.popen.wait(timeout)
            except subprocess.TimeoutExpired:
                pass
        if self.alive():
            try:  # the whole session: a prefork child left behind would keep training
                os.killpg(self.pid, signal.SIGKILL)
            except ProcessLookupError:
                pass
            self.popen.wait(10)
        self._kill_leftover_group()
        self._fh.close()
        return self.popen.returncode

    def kill(self) -> None:
        """SIGKILL to the whole process group (the worker parent and its child)."""
        if self.alive():
            try:
                os.killpg(self.pid, signal.SIGKILL)
            except ProcessLookupError:
                pass
            self.popen.wait(10)
        self.stop()

    def _kill_leftover_group(self) -> None:
        try:
            os.killpg(self.pid, signal.SIGKILL)  # children of ours that outlived the parent
        except (ProcessLookupError, PermissionError):
            pass

    def children(self) -> list[int]:
        import psutil

        try:
            return [c.pid for c in psutil.Process(self.pid).children() if c.status() != psutil.STATUS_ZOMBIE]
        except psutil.NoSuchProcess:
            return []

    def rss_kb(self) -> int:
        for line in Path(f"/proc/{self.pid}/status").read_text().splitlines():
            if line.startswith("VmRSS:"):
                return int(line.split()[1])
        raise AssertionError(f"no VmRSS for {self.name} pid {self.pid}")


def start_worker(home: Home, queue: str = "pi", name: str | None = None) -> Proc:
    from workers.cli import worker_command

    name = name or f"worker-{queue}"
    cmd = worker_command(home.settings, queue, hostname=f"{name}@%h", loglevel="info")
    log = home.path / f"{name}.log"
    home.logs.append(log)
    return Proc(name, cmd, home.env, log, teardown_kill=True)


def start_daemon(home: Home, *args: str, name: str = "daemon") -> Proc:
    cmd = [sys.executable, str(REPO / "run_trainer.py"), "daemon", "--tick-s", "0.2", "--log-level", "info", *args]
    log = home.path / f"{name}.log"
    if log not in home.logs:
        home.logs.append(log)
    return Proc(name, cmd, home.env, log)


@pytest.fixture
def procs():
    """Every Proc a test starts goes in this list and is stopped at the end, whatever happens."""
    started: list[Proc] = []
    yield started
    for p in reversed(started):
        if p.teardown_kill:
            p.kill()
        else:
            p.stop()


# -- redis --------------------------------------------------------------------------------------

def free_port() -> int:
    with socket.socket(socket.AF_INET, socket.SOCK_STREAM) as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


class RedisServer:
    """An apt-installed redis-server on a free loopback port, no persistence (like a restart that
    loses what was in memory: the worst case for the broker)."""

    def __init__(self, workdir: Path, port: int | None = None):
        exe = shutil.which("redis-server")
        if exe is None:
            pytest.fail("redis-server is not installed; the Redis tests need it (apt-get install redis-server, "
                        "or `make system-deps`)")
        self.exe = exe
        self.port = port or free_port()
        self.workdir = workdir
        workdir.mkdir(parents=True, exist_ok=True)
        self.proc: subprocess.Popen | None = None
        self.start()

    @property
    def url(self) -> str:
        return f"redis://127.0.0.1:{self.port}/0"

    def start(self) -> None:
        self.proc = subprocess.Popen(
            [self.exe, "--port", str(self.port), "--bind", "127.0.0.1", "--save", "", "--appendonly", "no",
             "--dir", str(self.workdir), "--protected-mode", "yes"],
            stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL, start_new_session=True)
        deadline = time.monotonic() + 10
        while time.monotonic() < deadline:
            try:
                with socket.create_connection(("127.0.0.1", self.port), timeout=0.5) as c:
                    c.sendall(b"PING\r\n")
                    if c.recv(16).startswith(b"+PONG"):
                        return
            except OSError:
                pass
            if self.proc.poll() is not None:
                pytest.fail(f"redis-server on port {self.port} exited with {self.proc.returncode}")
            time.sleep(0.05)
        pytest.fail(f"redis-server on port {self.port} did not answer PING within 10 s")

    def stop(self) -> None:
        if self.proc is not None and self.proc.poll() is None:
            self.proc.terminate()
            try:
                self.proc.wait(10)
            except subprocess.TimeoutExpired:
                self.proc.kill()
                self.proc.wait(5)
        self.proc = None

    def restart(self, down_s: float = 1.0) -> None:
        self.stop()
        time.sleep(down_s)
        self.start()


@pytest.fixture
def redis_server(tmp_path):
    server = RedisServer(tmp_path / "redis")
    yield server
    server.stop()


__all__ = ["Home", "JOB_TIMEOUT", "Proc", "REPO", "RedisServer", "all_states", "assert_never_overlapping", "free_port",
           "home", "procs", "redis_server", "start_daemon", "start_worker", "tiny_dataset", "tiny_dataset_path",
           "wait_until"]
